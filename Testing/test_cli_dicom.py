"""The command line on XA DICOM input: `geometry` and `reconstruct --dicom1/--dicom2` (issue 3)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import dicom_fixtures as fx
from xa_writer import write_xa
from SDFCARLib import dicom
from SDFCARLib.cli import main
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.io import write_mask_png
from SDFCARLib.phantoms import Branch, CentrelineTree, beer_lambert_counts, make_case

JPEG_LOSSLESS_SV1 = "1.2.840.10008.1.2.4.70"


LAO30 = CArmView(30.0, 0.0, 1000.0, 757.0, (1.0, 1.0), (64, 64))
RAO30_CRA10 = CArmView(-30.0, 10.0, 1040.0, 760.0, (1.0, 1.0), (64, 64))


def tube_runs(views):
    """A small tube on a 24³ grid seen in ``views``: the geometry, and per view (n, view, three frames
    of 12-bit counts at rising contrast, the clean mask)."""
    geometry = Geometry(VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0)), views)
    tube = CentrelineTree([Branch(np.array([[-12.0, 0, -10], [10.0, 4, 12]]), np.array([3.0, 2.5]))])
    case = make_case(tube, geometry)
    runs = []
    for n, (view, line_integral, mask) in enumerate(zip(views, case.line_integrals, case.masks), start=1):
        frames = np.stack([beer_lambert_counts(c * line_integral, 0.25, 3000.0, 12) for c in (0.2, 1.0, 0.5)])
        runs.append((n, view, frames, mask))
    return geometry, runs


@pytest.fixture(scope="module")
def dicom_pair(tmp_path_factory):
    """Two multi-frame JPEG-Lossless XA runs of a small tube; view 1 lacks ImagerPixelSpacing."""
    folder = tmp_path_factory.mktemp("xa")
    geometry, runs = tube_runs((LAO30, RAO30_CRA10))
    paths, masks = [], []
    for n, view, frames, mask in runs:
        native = write_xa(folder / f"native{n}.dcm", frames, view, bits_stored=12,
                          omit=("ImagerPixelSpacing",) if n == 1 else ())
        paths.append(fx.recompress(native, folder / f"view{n}.dcm", JPEG_LOSSLESS_SV1))
        masks.append(write_mask_png(folder / f"mask{n}.png", mask))
    return geometry, paths, masks


def test_geometry_command_needs_the_missing_pixel_spacing_then_matches(dicom_pair, tmp_path, capsys):
    geometry, paths, _ = dicom_pair
    out = tmp_path / "GEOM.json"
    volume = ["--volume-shape", "24", "24", "24", "--volume-spacing", "2"]
    code = main(["geometry", "--dicom1", str(paths[0]), "--dicom2", str(paths[1]), "--out", str(out)] + volume)
    err = capsys.readouterr().err
    assert code == 2 and "pixel spacing" in err and "--pixel-spacing1" in err
    assert not out.exists()
    code = main(["geometry", "--dicom1", str(paths[0]), "--dicom2", str(paths[1]), "--pixel-spacing1", "1", "1",
                 "--out", str(out)] + volume)
    err = capsys.readouterr().err
    assert code == 0, err
    # Every value is listed with its source, the user's value included.
    assert "[user]" in err and "(0018,1110)" in err and "frame 1" in err
    assert Geometry.load(out) == geometry
    saved = json.loads(out.read_text())
    assert saved["provenance"]["views"][0]["fields"]["pixel_spacing_mm"]["source"] == "user"


def test_reconstruct_from_dicom_files(dicom_pair, tmp_path, capsys):
    geometry, paths, masks = dicom_pair
    out = tmp_path / "result"
    args = ["reconstruct", "--dicom1", str(paths[0]), "--dicom2", str(paths[1]), "--pixel-spacing1", "1", "1",
            "--volume-shape", "24", "24", "24", "--volume-spacing", "2", "--mask1", str(masks[0]),
            "--mask2", str(masks[1]), "--out", str(out), "--steps", "3", "--no-progress"]
    assert main(args) == 0, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    # fast reads view 2's motion off the frames; the DICOM geometry is used as read otherwise
    assert "consistency" in report["calibration"]["method"] and report["calibration"]["views"][0]["view"] == 2
    assert main(args[:-5] + ["--out", str(tmp_path / "as-read"), "--steps", "3", "--no-progress",
                             "--set", "calibrate_from_frames=false"]) == 0, capsys.readouterr().err
    as_read = json.loads((tmp_path / "as-read" / "report.json").read_text())
    assert as_read["geometry_digest"] == geometry.digest() and "calibration" not in as_read
    # the grid read with the tags is printed where it is the grid used; one to be placed on the masks is printed where
    # it is placed (`_place_grid`), not first as the default it replaces
    from SDFCARLib.cli.parser import build_parser
    from SDFCARLib.cli.reconstruct import _geometry_for_reconstruct

    capsys.readouterr()
    _, _, request = _geometry_for_reconstruct(build_parser().parse_args(args))
    assert request is None and "volume: {'shape': [24, 24, 24]" in capsys.readouterr().err
    _, _, request = _geometry_for_reconstruct(build_parser().parse_args(
        [a for a in args if a not in ("--volume-shape", "24")]))
    err = capsys.readouterr().err
    assert request is not None and "primary_deg" in err and "volume: " not in err
    assert report["inputs"]["dicom"][0].endswith("view1.dcm")
    assert report["inputs"]["geometry_provenance"]["views"][0]["fields"]["pixel_spacing_mm"]["source"] == "user"
    # The chosen frames are the path-length evidence (fast): the runs' iodine is 0.25 per mm.
    assert report["frame_evidence"]["used"] is True
    assert [v["attenuation_per_mm"] for v in report["frame_evidence"]["views"]] == pytest.approx([0.25, 0.25], rel=0.25)
    # Both --geometry and DICOM, or neither: a clear error and nothing written.
    code = main(args[:1] + ["--geometry", "x.json"] + args[1:-5] + ["--out", str(tmp_path / "b")])
    assert code == 2 and "not both" in capsys.readouterr().err and not (tmp_path / "b").exists()
    code = main(["reconstruct", "--mask1", str(masks[0]), "--mask2", str(masks[1]), "--out", str(tmp_path / "c")])
    assert code == 2 and "--dicom1" in capsys.readouterr().err


def _three_steps_on(run1, run2, masks, out, capsys):
    """(report, stderr) of a three-step `reconstruct` of the pair's masks on the runs ``run1``, ``run2``."""
    args = ["reconstruct", "--dicom1", str(run1), "--dicom2", str(run2), "--pixel-spacing1", "1", "1",
            "--volume-shape", "24", "24", "24", "--volume-spacing", "2", "--mask1", str(masks[0]),
            "--mask2", str(masks[1]), "--out", str(out), "--steps", "3", "--no-progress"]
    assert main(args) == 0
    return json.loads((out / "report.json").read_text()), capsys.readouterr().err


def test_display_processed_runs_give_no_path_lengths(dicom_pair, tmp_path, capsys):
    """A run whose frames were processed for display (0028,1040 DISP, as real GE runs are) is not read as
    absorbance: the masks alone are fitted, and the report and the terminal say which view and why."""
    import pydicom

    _, paths, masks = dicom_pair
    processed = tmp_path / "view2-disp.dcm"
    ds = pydicom.dcmread(str(paths[1]))
    ds.PixelIntensityRelationship = "DISP"
    ds.save_as(str(processed))
    assert dicom.load_xa(processed).pixel_intensity_relationship == "DISP"
    assert dicom.intensity_tags_of_file(paths[0]).relationship == "LIN"
    assert dicom.intensity_tags_of_file(masks[0]) is None  # not DICOM: nothing known
    report, err = _three_steps_on(paths[0], processed, masks, tmp_path / "result", capsys)
    evidence = report["frame_evidence"]
    assert evidence["used"] is False and evidence["pixel_intensity_relationship"] == ["LIN", "DISP"]
    assert "view 2" in evidence["why"] and "is DISP" in evidence["why"] and "LIN" in evidence["why"]
    assert evidence["why"] in report["warnings"] and "is DISP" in err
    assert report["frame_intensity"] == ["LIN", "DISP"]  # for `analyse`: no densitometry on these frames
    assert "consistency" in report["calibration"]["method"]  # the frames still place the views


def test_a_log_run_is_read_on_a_linear_scale_and_its_path_lengths_fitted(dicom_pair, tmp_path, capsys):
    """A run stored as a logarithm of the intensity (0028,1040 LOG, sign −1) is linearised where it is read: its
    path lengths are fitted like the LIN run's, and the geometry's notes say how it was read."""
    _, paths, masks = dicom_pair
    counts = np.maximum(dicom.load_xa(paths[1]).frames, 1.0)
    log = np.log(counts)
    stored = np.round(4000.0 - 900.0 * (log - log.min())).astype(np.uint16)  # higher values, less intensity
    log_run = write_xa(tmp_path / "view2-log.dcm", stored, dicom.view_from_dicom(dicom.load_xa(paths[1]), 1)[0],
                       bits_stored=12, extra={"PixelIntensityRelationship": "LOG", "PixelIntensityRelationshipSign": -1})
    report, err = _three_steps_on(paths[0], log_run, masks, tmp_path / "result", capsys)
    assert report["frame_evidence"]["used"] is True and report["frame_intensity"] == ["LIN", "LIN"]
    # the same iodine per mm of path as the LIN run's, up to the slope the LOG run does not record
    mu = [v["attenuation_per_mm"] for v in report["frame_evidence"]["views"]]
    assert mu[0] == pytest.approx(0.25, rel=0.25) and mu[1] == pytest.approx(0.25 * 900 * 8 / 4096, rel=0.25)
    notes = " ".join(report["inputs"]["geometry_provenance"]["views"][1]["notes"])
    assert "LOG" in notes and "linear scale" in notes and "(0028,1041) -1" in notes and "linear scale" in err


def test_geometry_places_the_grid_on_the_masks_or_says_it_could_not(dicom_pair, tmp_path, capsys):
    geometry, paths, masks = dicom_pair
    base = ["geometry", "--dicom1", str(paths[0]), "--dicom2", str(paths[1]), "--pixel-spacing1", "1", "1",
            "--volume-spacing", "2"]
    out = tmp_path / "placed.json"
    assert main(base + ["--mask1", str(masks[0]), "--mask2", str(masks[1]), "--out", str(out)]) == 0, \
        capsys.readouterr().err
    saved = json.loads(out.read_text())
    volume = saved["provenance"]["volume"]
    assert volume["source"].startswith("placed on the masks' region")
    # the terminal names the grid used once, not first the default it replaces
    err = capsys.readouterr().err
    assert err.count("volume: ") == 1 and "placed on the masks' region" in err and "default: 128³" not in err
    assert saved["volume"]["spacing_mm"] == [2.0, 2.0, 2.0] and saved["volume"]["shape"] != [128, 128, 128]
    assert len(volume["mask_coverage"]) == 2 and min(volume["mask_coverage"]) > 0.95
    out = tmp_path / "default.json"
    assert main(base + ["--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "could not be placed" in err and "volume: {'shape': [128, 128, 128]" in err
    saved = json.loads(out.read_text())
    source = saved["provenance"]["volume"]["source"]
    assert "--mask A B" in source and "--mask1/--mask2" in source and saved["volume"]["shape"] == [128] * 3
    assert main(base + ["--mask1", str(masks[0]), "--out", str(tmp_path / "x.json")]) == 2
    assert "both --mask1 and --mask2" in capsys.readouterr().err


# --- any number of runs: --dicom A B C … ----------------------------------------------------------
@pytest.fixture(scope="module")
def dicom_three(tmp_path_factory):
    """Three 3-frame XA runs (LAO 30, RAO 30 cranial 10, AP cranial 30) of a small tube, their masks; run 3
    lacks ImagerPixelSpacing."""
    folder = tmp_path_factory.mktemp("xa3")
    geometry, runs = tube_runs((LAO30, RAO30_CRA10, CArmView(0.0, 30.0, 1000.0, 750.0, (1.0, 1.0), (64, 64))))
    paths, masks = [], []
    for n, view, frames, mask in runs:
        paths.append(str(write_xa(folder / f"run{n}.dcm", frames, view, bits_stored=12,
                                  omit=("ImagerPixelSpacing",) if n == 3 else ())))
        masks.append(str(write_mask_png(folder / f"mask{n}.png", mask)))
    return geometry, paths, masks


def test_reconstruct_from_three_dicom_runs(dicom_three, tmp_path, capsys):
    geometry, paths, masks = dicom_three
    out = tmp_path / "result"
    args = ["reconstruct", "--dicom", *paths, "--frame", "auto", "2", "0", "--pixel-spacing", "auto", "auto", "1",
            "--volume-shape", "24", "24", "24", "--volume-spacing", "2", "--mask", *masks, "--out", str(out),
            "--steps", "3", "--no-progress"]
    assert main(args) == 0, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    # the geometry used is the DICOM's, with the views after the first corrected for the motion read off the frames
    used = Geometry.from_dict(report["geometry"])
    assert len(used.views) == 3 and used.views[0] == geometry.views[0]
    assert [v.with_object_motion((0, 0, 0), (0, 0, 0)) for v in used.views] == list(geometry.views)
    assert [Path(p).name for p in report["inputs"]["dicom"]] == ["run1.dcm", "run2.dcm", "run3.dcm"]
    views = report["inputs"]["geometry_provenance"]["views"]
    # Frame choice per run: run 1 automatic (the frame with the most contrast), runs 2 and 3 as given.
    assert [(v["frame"]["index"], v["frame"]["method"]) for v in views] == [(1, "contrast"), (2, "user"), (0, "user")]
    assert views[2]["fields"]["pixel_spacing_mm"]["source"] == "user"
    assert views[0]["fields"]["pixel_spacing_mm"]["source"].startswith("tag (0018,1164)")
    # The epipolar check ran on the three views, each against both others: the tags' geometry agrees.
    assert len(report["view_consistency"]) == 3 and min(report["view_consistency"]) > 0.9
    assert all((out / f"qa_view{n}.png").is_file() for n in (1, 2, 3))


def test_three_runs_refuse_mixed_forms_and_wrong_counts(dicom_three, tmp_path, capsys):
    _, paths, masks = dicom_three
    base = ["reconstruct", "--volume-shape", "24", "24", "24", "--volume-spacing", "2", "--pixel-spacing", "auto",
            "auto", "1", "--steps", "1", "--no-progress", "--out", str(tmp_path / "r")]
    cases = [
        (["--dicom", *paths, "--mask", *masks[:2]], "--dicom names 3 XA runs (one per view) but 2 image(s)"),
        (["--dicom", *paths, "--dicom1", paths[0], "--mask", *masks], "either as --dicom A B C"),
        (["--dicom", *paths, "--frame2", "1", "--mask", *masks],
         "--frame2 is for --dicom1/--dicom2; with --dicom A B … give one value per run instead, e.g. --frame auto 1 auto"),
        (["--dicom1", paths[0], "--dicom2", paths[1], "--frame", "1", "2", "--mask", *masks[:2]],
         "--frame, --pixel-spacing are for --dicom A B …; with --dicom1/--dicom2 use the numbered options "
         "(--frame1/--frame2, --pixel-spacing1/--pixel-spacing2)"),
        (["--dicom", *paths, "--frame", "1", "2", "--mask", *masks], "--frame has 2 value(s) but --dicom names 3 runs"),
        (["--dicom", *paths, "--sod", "750", "x", "auto", "--mask", *masks], "--sod value 2 of 3 ('x') is not a number"),
        (["--dicom", *paths, "--frame", "auto", "auto", "7", "--mask", *masks], "frame 7 is out of range"),
        (["--dicom", paths[0], "--mask", masks[0]], "at least two XA runs"),
        (["--dicom", *paths], "no view images: give one mask per view with --mask V1 V2 V3 (3 views), or --auto-masks"),
    ]
    for extra, message in cases:
        assert main(base + extra) == 2, extra
        err = capsys.readouterr().err
        assert message in err, (extra, err)
        assert not (tmp_path / "r").exists()
    # Run 3 has no pixel spacing tag: the error names the list form, and that it is run 3's value.
    assert main(["geometry", "--dicom", *paths, "--out", str(tmp_path / "g.json")]) == 2
    err = capsys.readouterr().err
    assert "view 3" in err and "value 3 of --pixel-spacing with one value per --dicom run" in err


def test_geometry_command_writes_three_views_and_places_the_grid(dicom_three, tmp_path, capsys):
    geometry, paths, masks = dicom_three
    out = tmp_path / "GEOM.json"
    assert main(["geometry", "--dicom", *paths, "--pixel-spacing", "auto", "auto", "1", "--volume-spacing", "2",
                 "--mask", *masks, "--out", str(out)]) == 0, capsys.readouterr().err
    saved = json.loads(out.read_text())
    assert Geometry.from_dict(saved).views == geometry.views
    assert len(saved["provenance"]["views"]) == 3 and len(saved["provenance"]["volume"]["mask_coverage"]) == 3
    assert saved["provenance"]["volume"]["source"].startswith("placed on the masks' region")
    assert main(["geometry", "--dicom", *paths, "--pixel-spacing", "auto", "auto", "1", "--mask", *masks[:2],
                 "--out", str(tmp_path / "g2.json")]) == 2
    assert "--dicom names 3 XA runs (one per view) but 2 mask(s)" in capsys.readouterr().err
