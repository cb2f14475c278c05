"""`python -m SDFCARLib segment`: a vessel mask from one XA DICOM frame or a plain image."""

from __future__ import annotations

import json

import numpy as np
import pytest
from skimage.draw import line

from xa_writer import write_xa
from SDFCARLib.angiogram import AngiogramSettings, simulate_angiogram
from SDFCARLib.cli import main
from SDFCARLib.geometry import CArmView
from SDFCARLib.io import read_image


def _vessel_line_integral(shape=(128, 128), spacing_mm=0.3, radius_mm=1.2):
    from scipy import ndimage

    centre = np.ones(shape, bool)
    for (r0, c0), (r1, c1) in [((15, 20), (110, 100)), ((60, 60), (25, 110))]:
        rr, cc = line(r0, c0, r1, c1)
        centre[rr, cc] = False
    d = ndimage.distance_transform_edt(centre) * spacing_mm
    return 2.0 * np.sqrt(np.maximum(radius_mm**2 - d**2, 0.0))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 3-frame XA run: no contrast, full contrast, half contrast; 0.39 mm pixels, SID/SOD 1.3."""
    line_integral = _vessel_line_integral()
    settings = AngiogramSettings(collimator_fraction=0.06, ribs=1)
    frames = np.stack([simulate_angiogram(c * line_integral, 0.3, 7, settings)[0] for c in (0.0, 1.0, 0.5)])
    view = CArmView(30.0, 0.0, 975.0, 750.0, (0.39, 0.39), (128, 128))
    folder = tmp_path_factory.mktemp("xa")
    path = write_xa(folder / "run.dcm", frames, view, bits_stored=12)
    other = CArmView(-30.0, 20.0, 975.0, 750.0, (0.39, 0.39), (128, 128))  # same frames: plumbing only
    write_xa(folder / "run2.dcm", frames, other, bits_stored=12)
    write_xa(folder / "run3.dcm", frames, CArmView(0.0, 30.0, 975.0, 750.0, (0.39, 0.39), (128, 128)), bits_stored=12)
    return path, line_integral > 0


def test_segment_a_dicom_run(run, tmp_path, capsys):
    path, truth = run
    out = tmp_path / "masks" / "view1.png"
    assert main(["segment", "--dicom", str(path), "--out", str(out)]) == 0
    err = capsys.readouterr()
    assert "frame 1 (0-based)" in err.err and "1 component(s)" in err.out
    mask = read_image(out) > 0
    inner = np.zeros_like(truth)
    inner[20:108, 20:108] = True
    assert (mask & truth).sum() > 0.7 * (truth & inner).sum() and (mask & ~truth).sum() < 0.3 * mask.sum()
    for suffix in ("_frame.png", "_overlay.png"):
        assert (tmp_path / "masks" / f"view1{suffix}").exists()
    assert read_image(tmp_path / "masks" / "view1_frame.png").shape == (128, 128)
    report = json.loads((tmp_path / "masks" / "view1.json").read_text())
    assert report["source"]["frame"]["index"] == 1
    assert report["parameters"]["magnification"] == pytest.approx(1.3)
    assert report["parameters"]["pixel_spacing_source"] == "the DICOM tags"
    assert report["parameters"]["magnification_source"] == "the DICOM tags' SID/SOD"
    assert "pixel spacing the DICOM tags, magnification the DICOM tags' SID/SOD" in err.out
    # The frame written back segments the same way as a plain image with the same geometry.
    again = tmp_path / "again.png"
    assert main(["segment", "--image", str(tmp_path / "masks" / "view1_frame.png"), "--pixel-spacing", "0.39", "0.39",
                 "--magnification", "1.3", "--out", str(again)]) == 0
    assert np.array_equal(read_image(again) > 0, mask)
    assert main(["segment", "--dicom", str(path), "--out", str(out)]) == 2  # exists, no --overwrite
    assert "--overwrite" in capsys.readouterr().err


@pytest.mark.parametrize("argv_tail, message", [
    (["--frame", "5"], "frame 5 is out of range: this run has 3 frames"),
    (["--frame", "0"], "no vessel found"),
])
def test_segment_bad_frames(run, tmp_path, capsys, argv_tail, message):
    path, _ = run
    out = tmp_path / "m.png"
    assert main(["segment", "--dicom", str(path), "--out", str(out)] + argv_tail) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_segment_bad_images(tmp_path, capsys):
    import imageio.v3 as iio

    flat, colour = tmp_path / "flat.png", tmp_path / "colour.png"
    iio.imwrite(flat, np.full((64, 64), 90, np.uint8))
    iio.imwrite(colour, np.dstack([np.arange(64 * 64, dtype=np.uint8).reshape(64, 64), np.zeros((64, 64), np.uint8),
                                   np.zeros((64, 64), np.uint8)]))
    for image, message in [(flat, "the frame is flat"), (colour, "colour image")]:
        assert main(["segment", "--image", str(image), "--out", str(tmp_path / "m.png")]) == 2
        assert message in capsys.readouterr().err
    assert main(["segment", "--image", str(flat), "--frame", "2", "--out", str(tmp_path / "m.png")]) == 2
    assert "--frame picks a frame of a --dicom run" in capsys.readouterr().err
    assert main(["segment", "--image", str(flat), "--out", str(tmp_path / "m.nrrd")]) == 2
    assert "ending in .png" in capsys.readouterr().err


def test_reconstruct_with_auto_masks(run, tmp_path, capsys):
    path, _ = run
    out = tmp_path / "result"
    args = ["reconstruct", "--dicom1", str(path), "--dicom2", str(path.parent / "run2.dcm"), "--auto-masks",
            "--volume-shape", "8", "8", "8", "--volume-spacing", "8", "--steps", "1", "--no-progress", "--out", str(out)]
    assert main(args) == 0, capsys.readouterr().err
    captured = capsys.readouterr()
    assert "auto mask of frame 1" in captured.err and "--auto-masks" in captured.out
    report = json.loads((out / "report.json").read_text())
    auto = report["inputs"]["auto_masks"]
    assert len(auto) == 2 and auto[0]["pipeline"] == "angiogram_mask" and auto[0]["frame"]["index"] == 1
    assert report["inputs"]["targets"] == ["auto_mask1.png", "auto_mask2.png"]
    assert main(["segment", "--dicom", str(path), "--out", str(tmp_path / "seg.png")]) == 0
    assert np.array_equal(read_image(out / "auto_mask1.png"), read_image(tmp_path / "seg.png"))
    assert (out / "auto_mask2_overlay.png").exists()
    assert main(args[:-1] + [str(tmp_path / "r2"), "--mask1", "m.png"]) == 2
    assert "makes the masks itself; remove --mask1" in capsys.readouterr().err


def test_reconstruct_with_auto_masks_of_three_runs_and_a_frame_per_run(run, tmp_path, capsys):
    path, _ = run
    out = tmp_path / "result"
    runs = [str(path), str(path.parent / "run2.dcm"), str(path.parent / "run3.dcm")]
    # The three runs hold the same frames (plumbing only): the frames' pose search, which test_cli_dicom's three runs
    # check, would search a motion these views cannot show, for a minute.
    args = ["reconstruct", "--dicom", *runs, "--frame", "auto", "2", "auto", "--auto-masks", "--volume-shape", "8", "8",
            "8", "--volume-spacing", "8", "--steps", "1", "--set", "calibrate_from_frames=false", "--no-progress",
            "--out", str(out)]
    assert main(args) == 0, capsys.readouterr().err
    captured = capsys.readouterr()
    assert "view 2: auto mask of frame 2" in captured.err and "auto_mask3.png" in captured.out
    report = json.loads((out / "report.json").read_text())
    assert [a["frame"]["index"] for a in report["inputs"]["auto_masks"]] == [1, 2, 1]
    assert report["inputs"]["targets"] == ["auto_mask1.png", "auto_mask2.png", "auto_mask3.png"]
    assert json.loads((out / "auto_mask2.json").read_text())["source"]["frame"]["index"] == 2
    # The frame each mask was made from is the frame the geometry was read from.
    views = report["inputs"]["geometry_provenance"]["views"]
    assert [v["frame"]["index"] for v in views] == [1, 2, 1]
    assert all((out / f"qa_view{n}.png").is_file() for n in (1, 2, 3))


def test_a_run_processed_for_display_is_segmented_without_the_edge_trim(tmp_path, capsys):
    """A run whose Pixel Intensity Relationship says it was processed for display (DISP, GE's DRM): `segment` and
    `reconstruct --auto-masks` lower the mask's edge rule to the display share and say so; a LIN run keeps it."""
    from SDFCARLib.display_processing import display_processed
    from SDFCARLib.masks import DISPLAY_EDGE_FRACTION, AngioMaskSettings

    line_integral = _vessel_line_integral()
    frame = simulate_angiogram(line_integral, 0.3, 7, AngiogramSettings(ribs=1))[0]
    shown = display_processed(frame, 0.39)[None]
    views = [CArmView(a, 0.0, 975.0, 750.0, (0.39, 0.39), (128, 128)) for a in (30.0, -30.0)]
    runs = {}
    for relationship in ("DRM", "LIN"):
        runs[relationship] = [write_xa(tmp_path / f"{relationship}{n}.dcm", shown, view, bits_stored=8,
                                       extra={"PixelIntensityRelationship": relationship}) for n, view in enumerate(views)]
    for relationship, share in (("DRM", DISPLAY_EDGE_FRACTION), ("LIN", AngioMaskSettings().edge_fraction)):
        out = tmp_path / relationship / "view1.png"
        assert main(["segment", "--dicom", str(runs[relationship][0]), "--out", str(out)]) == 0
        err = capsys.readouterr().err
        assert ("processed for display (Pixel Intensity Relationship DRM)" in err) == (relationship == "DRM")
        report = json.loads(out.with_suffix(".json").read_text())
        assert report["parameters"]["edge_fraction"] == share
        assert report["source"]["pixel_intensity_relationship"] == relationship
    result = tmp_path / "result"
    assert main(["reconstruct", "--dicom", *map(str, runs["DRM"]), "--auto-masks", "--volume-shape", "8", "8", "8",
                 "--volume-spacing", "8", "--steps", "1", "--no-progress", "--out", str(result)]) == 0
    err = capsys.readouterr().err
    assert err.count("processed for display, DRM") == 2
    assert [a["edge_fraction"] for a in json.loads((result / "report.json").read_text())["inputs"]["auto_masks"]] == \
        [DISPLAY_EDGE_FRACTION] * 2


def test_an_image_said_to_be_processed_for_display_is_segmented_without_the_edge_trim(tmp_path, capsys):
    """`segment --image … --image-intensity DISP` (a viewer's export): the display rule, recorded; a --dicom run's
    relationship comes from its tags, so the option is refused there."""
    from SDFCARLib.display_processing import display_processed
    from SDFCARLib.io import write_image_nrrd
    from SDFCARLib.masks import DISPLAY_EDGE_FRACTION, AngioMaskSettings

    frame = simulate_angiogram(_vessel_line_integral(), 0.3, 7, AngiogramSettings(ribs=1))[0]
    image = write_image_nrrd(tmp_path / "export.nrrd", display_processed(frame, 0.39))
    geometry = ["--pixel-spacing", "0.39", "0.39", "--magnification", "1.3"]
    # an 8-bit image said nothing of is taken as processed for display (raw detector frames are 10–16 bit), and says so
    counts = write_image_nrrd(tmp_path / "counts.nrrd", frame.astype(np.uint16))
    for n, (path, given, share, recorded) in enumerate((
            (image, ["--image-intensity", "DISP"], DISPLAY_EDGE_FRACTION, "DISP (--image-intensity)"),
            (image, [], DISPLAY_EDGE_FRACTION, "DISP (assumed: an 8-bit image)"),
            (image, ["--image-intensity", "LIN"], AngioMaskSettings().edge_fraction, "LIN (--image-intensity)"),
            (counts, [], AngioMaskSettings().edge_fraction, None))):
        out = tmp_path / f"mask{n}.png"
        assert main(["segment", "--image", str(path), *geometry, *given, "--out", str(out)]) == 0
        report = json.loads(out.with_suffix(".json").read_text())
        assert report["parameters"]["edge_fraction"] == share
        assert report["source"].get("pixel_intensity_relationship") == recorded
        err = capsys.readouterr().err
        assert ("processed for display" in err) == (share == DISPLAY_EDGE_FRACTION)
        assert ("8-bit grey levels" in err) == (recorded is not None and "assumed" in recorded)
    xa = write_xa(tmp_path / "run.dcm", display_processed(frame, 0.39)[None], bits_stored=8)
    assert main(["segment", "--dicom", str(xa), "--image-intensity", "DISP", "--out", str(tmp_path / "x.png")]) == 2
    assert "remove --image-intensity" in capsys.readouterr().err


def test_segment_keeps_the_pixel_spacing_the_tags_give_when_the_distances_are_missing(run, tmp_path, capsys):
    path, _ = run
    import pydicom

    ds = pydicom.dcmread(str(path))
    for keyword in ("DistanceSourceToPatient", "EstimatedRadiographicMagnificationFactor"):
        delattr(ds, keyword)
    no_sod = tmp_path / "no_sod.dcm"
    ds.save_as(str(no_sod))
    out = tmp_path / "m.png"
    assert main(["segment", "--dicom", str(no_sod), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    parameters = json.loads((tmp_path / "m.json").read_text())["parameters"]
    assert parameters["pixel_spacing_source"] == "the DICOM tags"  # 0.39 mm from ImagerPixelSpacing, kept
    assert parameters["magnification_source"] == "default (not given)"
    assert "note: the magnification could not be read from the tags" in err and "--magnification" in err
    assert "DistanceSourceToPatient" in err


def test_a_run_that_declares_burned_in_annotation_is_segmented_with_a_warning_and_its_geometry_noted(run, tmp_path,
                                                                                                      capsys):
    import pydicom

    from SDFCARLib.dicom import view_from_dicom

    path, truth = run
    ds = pydicom.dcmread(str(path))
    frames = ds.pixel_array.copy()
    frames[:, 24:27, 30:60] = 0  # a dark burned-in mark away from the vessels: the mask takes it for one
    ds.PixelData = frames.tobytes()
    ds.BurnedInAnnotation = "YES"
    marked = tmp_path / "marked.dcm"
    ds.save_as(str(marked))
    out = tmp_path / "m.png"
    assert main(["segment", "--dicom", str(marked), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    said = "tag (0028,0301) BurnedInAnnotation = YES: text or marks are drawn into this run's pixels"
    assert f"warning: {said}" in err and "check the masks there" in err
    assert any(said in w for w in json.loads((tmp_path / "m.json").read_text())["parameters"]["warnings"])
    assert (read_image(out) > 0)[24:27, 35:55].any()  # what the warning is about
    assert any(said in note for note in view_from_dicom(str(marked), 1)[1]["notes"])  # the geometry's notes say it too
    ds.BurnedInAnnotation = "NO"
    ds.save_as(str(marked))
    assert not any("BurnedInAnnotation" in note for note in view_from_dicom(str(marked), 1)[1]["notes"])


def test_reconstruct_with_auto_masks_keeps_auto_mask_files_the_folder_holds(run, tmp_path, capsys):
    path, _ = run
    out = tmp_path / "result"
    out.mkdir()
    (out / "auto_mask1.png").write_bytes(b"the user's file")
    args = ["reconstruct", "--dicom1", str(path), "--dicom2", str(path.parent / "run2.dcm"), "--auto-masks",
            "--volume-shape", "8", "8", "8", "--volume-spacing", "8", "--steps", "1", "--no-progress", "--out", str(out)]
    assert main(args) == 2
    assert "auto_mask1.png" in capsys.readouterr().err
    assert (out / "auto_mask1.png").read_bytes() == b"the user's file" and not (out / "report.json").exists()


def test_segment_an_inverted_image_only_when_told_and_never_over_its_input(tmp_path, capsys):
    import imageio.v3 as iio

    frame, _ = simulate_angiogram(_vessel_line_integral(), 0.3, 3, AngiogramSettings(ribs=1))
    inverted = tmp_path / "inverted.png"
    iio.imwrite(inverted, (4095 - frame).astype(np.uint16))
    mask = tmp_path / "mask.png"
    assert main(["segment", "--image", str(inverted), "--out", str(mask)]) == 2
    assert "look bright, not dark" in capsys.readouterr().err and not mask.exists()
    assert main(["segment", "--image", str(inverted), "--bright-vessels", "--out", str(mask)]) == 0, capsys.readouterr().err
    capsys.readouterr()
    truth = _vessel_line_integral() > 0
    got = read_image(mask) > 0
    assert 2 * (got & truth).sum() / (got.sum() + truth.sum()) > 0.75
    # an --out whose files would include the input frame is refused before anything is written
    before = inverted.read_bytes()
    assert main(["segment", "--image", str(inverted), "--bright-vessels", "--overwrite",
                 "--out", str(tmp_path / "inverted.png")]) == 2
    assert "the input frame itself" in capsys.readouterr().err and inverted.read_bytes() == before


def test_segment_says_what_a_reconstruction_would_warn_of(tmp_path, capsys, monkeypatch):
    import imageio.v3 as iio

    import SDFCARLib.masks as masks

    frame, _ = simulate_angiogram(_vessel_line_integral(), 0.3, 3, AngiogramSettings(ribs=1))
    image = tmp_path / "frame.png"
    iio.imwrite(image, frame.astype(np.uint16))
    real = masks.segment_angiogram

    def with_specks(*args, **kwargs):  # the pipeline's result with some 60 one-pixel specks
        result = real(*args, **kwargs)
        result.mask[100:, :] = False
        result.mask[104:124:4, 4:124:20] = True
        result.mask[110:126:5, 2:120:14] = True
        return result

    monkeypatch.setattr(masks, "segment_angiogram", with_specks)
    assert main(["segment", "--image", str(image), "--out", str(tmp_path / "m.png")]) == 0
    err = capsys.readouterr().err
    assert "warning: mask: the mask has" in err and "specks" in err
    assert "specks" in json.loads((tmp_path / "m.json").read_text())["parameters"]["warnings"][0]


def test_auto_masks_of_an_inverted_run_name_the_view_and_the_segment_command(tmp_path, capsys):
    frames = np.stack([simulate_angiogram(c * _vessel_line_integral(), 0.3, 7, AngiogramSettings(ribs=1))[0]
                       for c in (1.0, 1.0)])
    view = CArmView(30.0, 0.0, 975.0, 750.0, (0.39, 0.39), (128, 128))
    (tmp_path / "my runs").mkdir()  # a path with a space: the command the message gives must still work pasted
    inverted = write_xa(tmp_path / "my runs" / "inverted.dcm", (4095 - frames).astype(np.uint16), view, bits_stored=12)
    other = write_xa(tmp_path / "other.dcm", frames.astype(np.uint16),
                     CArmView(-30.0, 20.0, 975.0, 750.0, (0.39, 0.39), (128, 128)), bits_stored=12)
    out = tmp_path / "result"
    assert main(["reconstruct", "--dicom", str(other), str(inverted), "--auto-masks", "--volume-shape", "8", "8", "8",
                 "--volume-spacing", "8", "--steps", "1", "--no-progress", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"view 2 ({inverted})" in err and "look bright" in err and not out.exists()
    import shlex

    command = err.split("`")[1]
    assert command.startswith(f"segment --dicom {shlex.quote(str(inverted))} --frame ") and "--bright-vessels" in command
    mask = tmp_path / "mask2.png"
    assert main(shlex.split(command.replace("MASK.png", shlex.quote(str(mask))))) == 0, capsys.readouterr().err
    assert mask.is_file()
