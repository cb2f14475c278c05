"""The command line on XA DICOM input: `geometry` and `reconstruct --dicom1/--dicom2` (issue 3)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import dicom_fixtures as fx
from xa_writer import write_xa
from SDFCARLib.cli import main
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.io import write_mask_png
from SDFCARLib.phantoms import Branch, CentrelineTree, beer_lambert_counts, make_case

JPEG_LOSSLESS_SV1 = "1.2.840.10008.1.2.4.70"


@pytest.fixture(scope="module")
def dicom_pair(tmp_path_factory):
    """Two multi-frame JPEG-Lossless XA runs of a small tube; view 1 lacks ImagerPixelSpacing."""
    folder = tmp_path_factory.mktemp("xa")
    views = (CArmView(30.0, 0.0, 1000.0, 757.0, (1.0, 1.0), (64, 64)),
             CArmView(-30.0, 10.0, 1040.0, 760.0, (1.0, 1.0), (64, 64)))
    geometry = Geometry(VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0)), views)
    tube = CentrelineTree([Branch(np.array([[-12.0, 0, -10], [10.0, 4, 12]]), np.array([3.0, 2.5]))])
    case = make_case(tube, geometry)
    paths, masks = [], []
    for n, (view, line_integral, mask) in enumerate(zip(views, case.line_integrals, case.masks), start=1):
        frames = np.stack([beer_lambert_counts(c * line_integral, 0.25, 3000.0, 12) for c in (0.2, 1.0, 0.5)])
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
    assert report["geometry_digest"] == geometry.digest()
    assert report["inputs"]["dicom"][0].endswith("view1.dcm")
    assert report["inputs"]["geometry_provenance"]["views"][0]["fields"]["pixel_spacing_mm"]["source"] == "user"
    # Both --geometry and DICOM, or neither: a clear error and nothing written.
    code = main(args[:1] + ["--geometry", "x.json"] + args[1:-5] + ["--out", str(tmp_path / "b")])
    assert code == 2 and "not both" in capsys.readouterr().err and not (tmp_path / "b").exists()
    code = main(["reconstruct", "--mask1", str(masks[0]), "--mask2", str(masks[1]), "--out", str(tmp_path / "c")])
    assert code == 2 and "--dicom1" in capsys.readouterr().err


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
    assert saved["volume"]["spacing_mm"] == [2.0, 2.0, 2.0] and saved["volume"]["shape"] != [128, 128, 128]
    assert len(volume["mask_coverage"]) == 2 and min(volume["mask_coverage"]) > 0.95
    out = tmp_path / "default.json"
    assert main(base + ["--out", str(out)]) == 0
    assert "could not be placed" in capsys.readouterr().err
    saved = json.loads(out.read_text())
    assert "give --mask1/--mask2" in saved["provenance"]["volume"]["source"] and saved["volume"]["shape"] == [128] * 3
    assert main(base + ["--mask1", str(masks[0]), "--out", str(tmp_path / "x.json")]) == 2
    assert "both --mask1 and --mask2" in capsys.readouterr().err
