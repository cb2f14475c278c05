"""The command line (python -m SDFCARLib): bad input, an end-to-end run, evaluate, demo, templates."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import TINY_DETECTOR, TINY_DETECTOR_SPACING_MM, TINY_SHAPE, TINY_SPACING_MM, tiny_geometry_dict, write_json
from SDFCARLib.cli import main
from SDFCARLib.geometry import VIEW_PAIRS, Geometry, standard_geometry

REPO = Path(__file__).resolve().parents[1]


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _png(path: Path, array: np.ndarray) -> Path:
    import imageio.v3 as iio

    iio.imwrite(path, np.asarray(array, np.uint8), extension=".png")
    return path


def _assert_bad_input(code: int, err: str, message: str) -> None:
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    assert message.lower() in lines[0].lower(), lines[0]


# --- bad input ----------------------------------------------------------------------------------
def _bad_mask(kind: str, tmp_path: Path) -> Path:
    rows, cols = TINY_DETECTOR
    if kind == "empty":
        return _png(tmp_path / "bad.png", np.zeros((rows, cols)))
    if kind == "all-ones":
        return _png(tmp_path / "bad.png", np.full((rows, cols), 255))
    if kind == "shape":
        return _png(tmp_path / "bad.png", np.pad(np.full((10, 10), 255), ((0, rows - 30), (0, cols - 10))))
    if kind == "non-binary":
        return _png(tmp_path / "bad.png", np.indices((rows, cols))[1] % 3)  # values 0, 1, 2
    if kind == "nan":
        import nrrd

        data = np.zeros((rows, cols), np.float32)
        data[5:9, 5:9] = 1.0
        data[0, 0] = np.nan
        nrrd.write(str(tmp_path / "bad.nrrd"), data, index_order="C")
        return tmp_path / "bad.nrrd"
    if kind == "unreadable":
        (tmp_path / "bad.png").write_bytes(b"\x89PNG but not really")
        return tmp_path / "bad.png"
    if kind == "missing":
        return tmp_path / "does-not-exist.png"
    raise AssertionError(kind)


BAD_MASKS = {
    "empty": "mask is empty",
    "all-ones": "marks every pixel as vessel",
    "shape": "differs from the detector shape (96, 96)",
    "non-binary": "not binary (values 0, 1, 2)",
    "nan": "NaN",
    "unreadable": "cannot read",
    "missing": "not found",
}


@pytest.mark.parametrize("kind", sorted(BAD_MASKS))
def test_bad_masks_are_refused_and_nothing_is_written(kind, tmp_path, capsys, geometry_file, mask_files):
    bad = _bad_mask(kind, tmp_path)
    out = tmp_path / "out"
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask1", mask_files[0], "--mask2", bad,
                       "--out", out, "--steps", 1, "--no-progress")
    _assert_bad_input(code, err, BAD_MASKS[kind])
    assert bad.name in err
    assert not out.exists()


def _set(data, path, value):
    target = data
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value


BAD_GEOMETRIES = {
    "primary angle": (("views", 0, "primary_deg"), 200.0, "views[0].primary_deg = 200.0 is out of range"),
    "secondary angle": (("views", 1, "secondary_deg"), -95.0, "views[1].secondary_deg = -95.0 is out of range"),
    "sod >= sid": (("views", 0, "sod_mm"), 1000.0, "views[0].sod_mm = 1000.0 must be smaller than"),
    "negative sid": (("views", 0, "sid_mm"), -1000.0, "views[0].sid_mm (source to detector) must be positive, got -1000.0"),
    "off the detectors": (("volume", "center_mm"), [300.0, 0.0, 0.0], "does not project onto the detector"),
    "missing field": (("views", 1, "sid_mm"), KeyError, "views[1] is missing required field(s): sid_mm"),
    "wrong type": (("views", 0, "detector_shape"), "512", "views[0].detector_shape must be a list"),
    "unknown field": (("volume", "spacing"), 1.0, "volume has unknown field(s): spacing"),
}


@pytest.mark.parametrize("case", sorted(BAD_GEOMETRIES))
def test_bad_geometry_is_refused_naming_the_field(case, tmp_path, capsys, mask_files):
    path, value, message = BAD_GEOMETRIES[case]
    data = tiny_geometry_dict()
    _set(data, path, value)
    geometry = write_json(tmp_path / "bad-geometry.json", data)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("earlier work")
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry, "--mask1", mask_files[0], "--mask2", mask_files[1],
                       "--out", out, "--no-progress")
    _assert_bad_input(code, err, message)
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and (out / "keep.txt").read_text() == "earlier work"


def test_invalid_json_and_wrong_view_count_are_refused(tmp_path, capsys, mask_files):
    (tmp_path / "g.json").write_text('{"volume": {"shape": [32, 32, 32],}')
    code, _, err = run(capsys, "reconstruct", "--geometry", tmp_path / "g.json", "--mask1", mask_files[0],
                       "--mask2", mask_files[1], "--out", tmp_path / "out")
    _assert_bad_input(code, err, "is not valid JSON")
    data = tiny_geometry_dict()
    data["views"].append(dict(data["views"][0]))
    code, _, err = run(capsys, "reconstruct", "--geometry", write_json(tmp_path / "three.json", data),
                       "--mask1", mask_files[0], "--mask2", mask_files[1], "--out", tmp_path / "out")
    _assert_bad_input(code, err, "describes 3 view(s) but 2 image(s) were given")
    assert not (tmp_path / "out").exists()


def test_existing_results_are_not_overwritten_without_the_flag(tmp_path, capsys, geometry_file, mask_files):
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.json").write_text("{}")
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask1", mask_files[0], "--mask2", mask_files[1],
                       "--out", out, "--no-progress")
    _assert_bad_input(code, err, "already holds report.json")
    assert (out / "report.json").read_text() == "{}"


def test_grid_options_of_xa_runs_are_refused_with_a_geometry_file_and_an_unwritable_out_before_work(
        tmp_path, capsys, geometry_file, mask_files):
    base = ["reconstruct", "--geometry", geometry_file, "--mask1", mask_files[0], "--mask2", mask_files[1], "--no-progress"]
    code, _, err = run(capsys, *base, "--out", tmp_path / "out", "--volume-shape", 64, 64, 64, "--volume-spacing", 1.6)
    _assert_bad_input(code, err, "--volume-shape, --volume-spacing set the grid of a reconstruction from XA runs (--dicom); "
                                 "with --geometry the grid is the GEOM.json's volume")
    code, _, err = run(capsys, *base, "--out", tmp_path / "out", "--volume-spacing", 0)
    assert code == 2 and "--volume-spacing: must be a positive number, got 0" in err
    (tmp_path / "notes.txt").write_text("mine")
    code, _, err = run(capsys, *base, "--out", tmp_path / "notes.txt" / "out")
    _assert_bad_input(code, err, "which is a file, not a folder")
    assert not (tmp_path / "out").exists()


def test_unknown_mode_and_preset_are_refused(tmp_path, capsys, geometry_file, mask_files):
    base = ["reconstruct", "--geometry", geometry_file, "--mask1", mask_files[0], "--mask2", mask_files[1], "--out", tmp_path / "out"]
    code, _, err = run(capsys, *base, "--mode", "sdf")
    _assert_bad_input(code, err, "unknown mode 'sdf'")
    code, _, err = run(capsys, *base, "--preset", "slow")
    _assert_bad_input(code, err, "unknown preset 'slow'")
    for setting, message in [("steps=3", "use --steps"), ("bogus=1", "unknown setting 'bogus'"),
                             ("memory_check=maybe", "takes true or false")]:
        code, _, err = run(capsys, *base, "--set", setting)
        _assert_bad_input(code, err, message)
    assert not (tmp_path / "out").exists()


def test_verbose_shows_the_traceback(tmp_path, capsys, geometry_file, mask_files):
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask1", tmp_path / "nope.png",
                       "--mask2", mask_files[1], "--out", tmp_path / "out", "--verbose")
    assert code == 2 and "Traceback" in err and err.strip().splitlines()[-1].startswith("error: ")


def test_entry_point_version_and_error_status():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    done = subprocess.run([sys.executable, "-m", "SDFCARLib", "--version"], capture_output=True, text=True, env=env, cwd=REPO)
    from SDFCARLib import __version__

    assert done.returncode == 0 and done.stdout.strip() == f"SDFCARLib {__version__}"
    done = subprocess.run([sys.executable, "-m", "SDFCARLib", "evaluate", "--prediction", "missing.nrrd", "--label", "x.nrrd"],
                          capture_output=True, text=True, env=env, cwd=REPO)
    assert done.returncode == 2 and done.stderr.startswith("error: ") and "Traceback" not in done.stderr


# --- end to end ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def simulated(tmp_path_factory, tiny_case):
    """The tiny case's label as NRRD and its views simulated by the CLI."""
    from SDFCARLib.io import write_volume_nrrd

    folder = tmp_path_factory.mktemp("simulated")
    geometry = write_json(folder / "geometry.json", tiny_geometry_dict())
    label = write_volume_nrrd(folder / "label.nrrd", tiny_case.label, tiny_case.geometry.volume)
    assert main(["simulate", "--label", str(label), "--geometry", str(geometry), "--out", str(folder / "views")]) == 0
    return folder


def test_simulate_writes_masks_and_line_integrals_of_every_view(simulated, tiny_case):
    import imageio.v3 as iio

    from SDFCARLib.io import read_line_integral

    views = simulated / "views"
    assert sorted(p.name for p in views.iterdir()) == ["view1_lineint.nrrd", "view1_mask.png", "view2_lineint.nrrd", "view2_mask.png"]
    for n in (1, 2):
        png = iio.imread(views / f"view{n}_mask.png")
        assert png.dtype == np.uint8 and set(np.unique(png)) == {0, 255}
        np.testing.assert_array_equal(png > 0, tiny_case.masks[n - 1])
        np.testing.assert_allclose(read_line_integral(views / f"view{n}_lineint.nrrd"), tiny_case.line_integrals[n - 1], atol=1e-6)


def test_simulate_refuses_a_label_outside_the_views(tmp_path, capsys, geometry_file):
    from SDFCARLib.geometry import VolumeGrid
    from SDFCARLib.io import write_volume_nrrd

    far = VolumeGrid((4, 4, 4), (2.0, 2.0, 2.0), (0.0, 0.0, 400.0))  # 400 mm above the isocenter
    label = write_volume_nrrd(tmp_path / "far.nrrd", np.ones(far.shape, bool), far)
    code, _, err = run(capsys, "simulate", "--label", label, "--geometry", geometry_file, "--out", tmp_path / "out")
    assert code == 2 and "leaves no shadow" in err and not (tmp_path / "out").exists()


def test_reconstruct_correct_motion_reports_the_shift_found(simulated, tmp_path, capsys):
    out = tmp_path / "result"
    code, _, err = run(capsys, "reconstruct", "--geometry", simulated / "geometry.json",
                       "--mask1", simulated / "views" / "view1_mask.png", "--mask2", simulated / "views" / "view2_mask.png",
                       "--out", out, "--steps", 3, "--no-progress", "--correct-motion",
                       "--set", "calibration_steps=20", "--set", "calibration_candidates=3", "--set", "calibration_range_mm=2")
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert report["settings"]["calibrate"] is True
    (view2,) = report["calibration"]["views"]
    assert view2["view"] == 2 and abs(view2["shift_mm"]) <= 2.0
    assert len(view2["shift"]["candidates"]) == len(view2["shift"]["losses"]) >= 3
    assert "rotation_in_plane" not in view2 and "rotation_tilt" not in view2  # rotations are searched on request only
    # the result's geometry carries the motion found as view 2's object motion; view 1 is untouched
    geometry = Geometry.from_dict(report["geometry"])
    np.testing.assert_allclose(geometry.views[1].object_translation_mm, view2["object_translation_mm"], atol=1e-3)
    np.testing.assert_allclose(geometry.views[1].object_rotation_deg, view2["object_rotation_deg"], atol=1e-3)
    assert not geometry.views[0].has_object_motion
    code, _, err = run(capsys, "reconstruct", "--geometry", simulated / "geometry.json",
                       "--mask1", simulated / "views" / "view1_mask.png", "--mask2", simulated / "views" / "view2_mask.png",
                       "--out", tmp_path / "again", "--set", "calibrate=true")
    assert code == 2 and "--correct-motion" in err


def test_reconstruct_end_to_end_writes_every_output(simulated, tmp_path, capsys, tiny_geometry):
    import nrrd

    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")

    from SDFCARLib.io import read_surface_vtk

    out = tmp_path / "result"
    code, stdout, err = run(capsys, "reconstruct", "--geometry", simulated / "geometry.json",
                            "--mask1", simulated / "views" / "view1_mask.png", "--mask2", simulated / "views" / "view2_mask.png",
                            "--label", simulated / "label.nrrd", "--out", out, "--steps", 3, "--seed", 3, "--no-progress",
                            "--set", "prune_tolerance=0.05", "--set", "support_margin_mm=1")
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    names = {"occupancy.nrrd", "field.nrrd", "segmentation.seg.nrrd", "surface.vtk", "report.json"}
    assert names <= {p.name for p in out.iterdir()}
    assert (out / "scene.mrml").exists() == report["scene"]["written"]
    assert set(report["files"].values()) == {p.name for p in out.iterdir()}

    assert report["settings"]["steps"] == 3 and report["seed"] == 3 and report["target_kind"] == "mask"
    assert report["settings"]["preset"] == "fast" and report["settings"]["mode"] == "sdfcar"
    assert report["settings"]["prune_tolerance"] == 0.05 and report["settings"]["support_margin_mm"] == 1.0
    for key in ("device", "versions", "timings_s", "final_losses", "geometry"):
        assert key in report
    assert len(report["reprojection_dice"]) == 2
    assert Geometry.from_dict(report["geometry"]) == tiny_geometry
    assert report["inputs"]["targets"][0].endswith("view1_mask.png")
    for method in ("prediction", "visual_hull"):
        assert set(report["metrics"][method]) >= {"cldice", "dice", "iou", "chamfer_l2_mm", "re_error", "reprojection_dice"}
    assert report["metrics"]["visual_hull"]["tsens"] == 1.0  # the hull of the label's own masks contains its skeleton
    assert "visual hull" in stdout

    grid = tiny_geometry.volume
    header = nrrd.read_header(str(out / "segmentation.seg.nrrd"))
    assert header["space"] == "left-posterior-superior" and list(header["sizes"]) == list(grid.shape)
    np.testing.assert_allclose(header["space origin"], grid.origin)
    np.testing.assert_allclose(header["space directions"], np.diag(grid.spacing_mm))
    assert header["Segment0_LabelValue"] == "1"
    segmentation = nrrd.read(str(out / "segmentation.seg.nrrd"))[0]
    occupancy = nrrd.read(str(out / "occupancy.nrrd"))[0]
    np.testing.assert_array_equal(segmentation.astype(bool), occupancy >= 0.5)
    assert int(segmentation.sum()) == report["segmented_voxels"]

    vertices, faces = read_surface_vtk(out / "surface.vtk")
    assert len(vertices) == report["surface"]["vertices"] and len(faces) == report["surface"]["triangles"]
    lo, hi = grid.bounds()
    assert np.all(vertices >= lo - 1e-4) and np.all(vertices <= hi + 1e-4)
    assert (len(faces) == 0) == (report["segmented_voxels"] == 0)


def test_reconstruct_from_line_integrals(simulated, tmp_path, capsys):
    out = tmp_path / "result"
    views = simulated / "views"
    code, _, err = run(capsys, "reconstruct", "--geometry", simulated / "geometry.json", "--lineint1", views / "view1_lineint.nrrd",
                       "--lineint2", views / "view2_lineint.nrrd", "--out", out, "--steps", 2, "--no-progress")
    assert code == 0, err
    assert json.loads((out / "report.json").read_text())["target_kind"] == "line_integral"
    code, _, err = run(capsys, "reconstruct", "--geometry", simulated / "geometry.json", "--lineint1", views / "view1_lineint.nrrd",
                       "--mask2", views / "view2_mask.png", "--out", tmp_path / "mixed")
    _assert_bad_input(code, err, "give either masks or line integrals")


def test_ctrl_c_cancels_with_status_130_and_writes_nothing(tmp_path, capsys, geometry_file, mask_files, monkeypatch):
    handler_before = signal.getsignal(signal.SIGINT)  # SIG_IGN when started from a background shell
    import SDFCARLib.optimiser as optimiser

    real_reconstruct = optimiser.reconstruct

    def reconstruct_interrupted_at_step_2(*args, progress=None, **kwargs):
        def report(info):
            progress(info)
            if info.get("phase") == "optimise" and info["step"] >= 2:
                os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C in the terminal sends

        return real_reconstruct(*args, progress=report, progress_interval_s=0.0, **kwargs)

    monkeypatch.setattr(optimiser, "reconstruct", reconstruct_interrupted_at_step_2)
    out = tmp_path / "out"
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask1", mask_files[0], "--mask2", mask_files[1],
                       "--out", out, "--steps", 1000)
    assert code == 130 and "cancelled" in err and "nothing was written" in err
    assert "optimising" in err  # the progress bar was shown
    assert not out.exists()
    assert signal.getsignal(signal.SIGINT) is handler_before  # Ctrl-C behaves as before again


# --- evaluate, demo, geometry-template ----------------------------------------------------------
def test_reconstruct_help_lists_for_set_only_the_keys_set_accepts(capsys):
    from SDFCARLib.cli.common import SETTINGS_SET_BY_FLAGS
    from SDFCARLib.settings import SETTING_KEYS

    code, stdout, _ = run(capsys, "reconstruct", "--help")
    assert code == 0
    listed = " ".join(stdout.split())  # argparse wraps the help
    assert all(f" {key}=" not in listed and f":{key}=" not in listed for key in SETTINGS_SET_BY_FLAGS)
    assert all(f"{key}=" in listed for key in set(SETTING_KEYS) - set(SETTINGS_SET_BY_FLAGS))


def test_evaluate_a_perfect_prediction(simulated, tmp_path, capsys):
    label = simulated / "label.nrrd"
    code, stdout, err = run(capsys, "evaluate", "--prediction", label, "--label", label, "--geometry", simulated / "geometry.json",
                            "--json", tmp_path / "metrics.json")
    assert code == 0, err
    metrics = json.loads((tmp_path / "metrics.json").read_text())["metrics"]
    assert metrics["prediction"]["dice"] == 1.0 and metrics["prediction"]["chamfer_l2_mm"] == 0.0
    assert metrics["prediction"]["re_error"] == 0.0 and metrics["prediction"]["reprojection_dice"] == [1.0, 1.0]
    assert metrics["visual_hull"]["dice"] < 1.0  # ghosts: the hull is larger than the tree
    assert "clDice" in stdout
    code, _, err = run(capsys, "evaluate", "--prediction", label, "--label", label, "--json", tmp_path / "metrics.json")
    _assert_bad_input(code, err, "already holds metrics.json")


def test_evaluate_refuses_other_grids_and_unthresholded_volumes(simulated, tmp_path, capsys, tiny_case):
    from SDFCARLib.geometry import VolumeGrid
    from SDFCARLib.io import write_volume_nrrd

    grid = tiny_case.geometry.volume
    other = VolumeGrid(grid.shape, (1.0, 1.0, 1.0), grid.center_mm)
    write_volume_nrrd(tmp_path / "other.nrrd", tiny_case.label, other)
    code, _, err = run(capsys, "evaluate", "--prediction", tmp_path / "other.nrrd", "--label", simulated / "label.nrrd")
    _assert_bad_input(code, err, "different grids")
    write_volume_nrrd(tmp_path / "occupancy.nrrd", tiny_case.label * np.float32(0.7) + np.float32(0.1), grid)
    code, _, err = run(capsys, "evaluate", "--prediction", tmp_path / "occupancy.nrrd", "--label", simulated / "label.nrrd")
    _assert_bad_input(code, err, "--threshold")
    code, _, err = run(capsys, "evaluate", "--prediction", tmp_path / "occupancy.nrrd", "--label", simulated / "label.nrrd",
                       "--threshold", 0.5)
    assert code == 0, err
    assert "warning" not in err
    # a threshold no voxel reaches (occupancy lies in [0, 1]) still evaluates, but says why everything is 0
    code, stdout, err = run(capsys, "evaluate", "--prediction", tmp_path / "occupancy.nrrd", "--label", simulated / "label.nrrd",
                            "--threshold", 2)
    assert code == 0, err
    assert "warning: no voxel of" in err and "reaches --threshold 2: the prediction is empty" in err


def test_demo_reconstructs_the_sample_case_and_compares_with_the_hull(tmp_path, capsys, monkeypatch, tiny_case):
    import SDFCARLib.sample_data as sample_data

    # The bundled case takes minutes; the demo's wiring is the same on the tiny case.
    tiny = sample_data.SampleCase(tiny_case.geometry, tiny_case.masks, tiny_case.label, tmp_path)
    monkeypatch.setattr(sample_data, "load_sample_case", lambda directory=None: tiny)
    code, stdout, err = run(capsys, "demo", "--out", tmp_path / "demo", "--steps", 2, "--no-progress")
    assert code == 0, err
    assert "reconstruction" in stdout and "visual hull (baseline)" in stdout and "clDice" in stdout
    report = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert report["settings"]["preset"] == "fast" and "visual_hull" in report["metrics"]
    # the case's masks are named as reconstruct names its inputs, so that `analyse demo-output` finds them
    from SDFCARLib.analysis.outputs import _masks_for
    from SDFCARLib.io import write_mask_png
    from SDFCARLib.sample_data import FILES

    assert report["inputs"]["targets"] == [str(tmp_path / FILES["mask1"]), str(tmp_path / FILES["mask2"])]
    for n, mask in enumerate(tiny_case.masks):
        write_mask_png(tmp_path / FILES[f"mask{n + 1}"], mask)
    masks, note = _masks_for(report, Geometry.from_dict(report["geometry"]), None)
    assert note is None and all(np.array_equal(a, b) for a, b in zip(masks, tiny_case.masks))


def test_demo_with_the_ensemble_preset_keeping_the_best_reprojecting_fit_says_which(tmp_path, capsys, monkeypatch, tiny_case):
    import SDFCARLib.sample_data as sample_data

    tiny = sample_data.SampleCase(tiny_case.geometry, tiny_case.masks, tiny_case.label, tmp_path)
    monkeypatch.setattr(sample_data, "load_sample_case", lambda directory=None: tiny)
    code, out, err = run(capsys, "demo", "--out", tmp_path / "demo", "--preset", "ensemble", "--steps", 2, "--seed", 7,
                         "--set", "ensemble_combine=best_reprojection", "--no-progress")
    assert code == 0, err
    assert "ensemble preset, mode sdfcar, 3 fits of 2 steps" in err
    report = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert report["settings"]["ensemble_fits"] == 3 and report["ensemble_seeds"] == [7, 8, 9]
    choice = report["ensemble_choice"]
    assert choice["seeds"] == [7, 8, 9] and len(choice["reprojection_dice"]) == 3
    assert all(len(dice) == 2 for dice in choice["reprojection_dice"])  # per fit, per view
    assert report["reprojection_dice"] == choice["reprojection_dice"][choice["chosen_fit"]]
    assert f"Kept the fit of seed {choice['chosen_seed']} of 3 (seeds 7, 8, 9): the highest mean reprojection Dice" in out


def test_bundled_sample_case_equals_a_fresh_regeneration(tmp_path):
    import nrrd

    from SDFCARLib.io import read_mask
    from SDFCARLib.sample_data import FILES, SAMPLE_DIR, load_sample_case, write_sample_case

    write_sample_case(tmp_path / "fresh")
    for key, name in FILES.items():
        bundled, fresh = SAMPLE_DIR / name, tmp_path / "fresh" / name
        if name.endswith(".png"):
            np.testing.assert_array_equal(read_mask(bundled), read_mask(fresh), err_msg=name)
        elif name.endswith(".nrrd"):
            (a, header_a), (b, header_b) = nrrd.read(str(bundled)), nrrd.read(str(fresh))
            np.testing.assert_array_equal(a, b)
            assert {k: str(v) for k, v in header_a.items()} == {k: str(v) for k, v in header_b.items()}
        elif name.endswith(".json"):
            assert json.loads(bundled.read_text()) == json.loads(fresh.read_text())
        else:
            assert bundled.read_text() == fresh.read_text(), name
    case = load_sample_case()
    assert case.label.shape == (128, 128, 128) and case.label.any()
    assert [m.shape for m in case.masks] == [(512, 512), (512, 512)]
    assert sum(p.stat().st_size for p in SAMPLE_DIR.iterdir()) < 100_000  # small enough to ship in the package


def test_geometry_template_writes_a_valid_geometry(tmp_path, capsys):
    path = tmp_path / "geom.json"
    code, _, err = run(capsys, "geometry-template", "--view-pair", "paper", "--out", path, "--shape", 64, 64, 64)
    assert code == 0, err
    geometry = Geometry.load(path)
    assert geometry.volume.shape == (64, 64, 64)
    assert [(v.primary_deg, v.secondary_deg, v.sid_mm, v.sod_mm) for v in geometry.views] == [tuple(p) for p in VIEW_PAIRS["paper"]]
    code, _, err = run(capsys, "geometry-template", "--out", path)
    _assert_bad_input(code, err, "already exists")
    code, stdout, _ = run(capsys, "geometry-template", "--view-pair", "lao30-rao30")
    assert code == 0 and Geometry.from_dict(json.loads(stdout)).views[1].primary_deg == -30.0
    # a protocol's distances are replaced where the user gives one, kept where not
    code, stdout, err = run(capsys, "geometry-template", "--view-pair", "paper", "--sid-mm", 1200)
    assert code == 0, err
    assert [(v.sid_mm, v.sod_mm) for v in Geometry.from_dict(json.loads(stdout)).views] == [
        (1200.0, sod) for _, _, _, sod in VIEW_PAIRS["paper"]]
    code, _, err = run(capsys, "geometry-template", "--view-pair", "paper", "--sod-mm", 0)
    assert code == 2 and "--sod-mm: must be a positive number, got 0" in err


def test_geometry_template_takes_any_number_of_views(tmp_path, capsys):
    code, stdout, err = run(capsys, "geometry-template", "--view", 30, 0, "--view", -30, 0, "--view", 0, 30,
                            "--view", 45, -20, "--sod-mm", 780)
    assert code == 0, err
    views = Geometry.from_dict(json.loads(stdout)).views
    assert [(v.primary_deg, v.secondary_deg, v.sod_mm, v.sid_mm) for v in views] == [
        (30.0, 0.0, 780.0, 1000.0), (-30.0, 0.0, 780.0, 1000.0), (0.0, 30.0, 780.0, 1000.0), (45.0, -20.0, 780.0, 1000.0)]
    code, stdout, _ = run(capsys, "geometry-template", "--view-pair", "lao30-rao30-cra30")
    assert code == 0 and len(Geometry.from_dict(json.loads(stdout)).views) == 3
    code, _, err = run(capsys, "geometry-template", "--view", 30, 0)
    _assert_bad_input(code, err, "--view was given 1 time; a reconstruction needs at least two views")
    code, _, err = run(capsys, "geometry-template", "--view", 30, 0, "--view", -30, 0, "--view-pair", "paper")
    _assert_bad_input(code, err, "either --view-pair or the views' angles")


# --- the grid placed on the masks (region.py) -------------------------------------------------------------
def test_reconstruct_places_the_grid_on_the_masks(tmp_path, mask_files, capsys):
    data = tiny_geometry_dict()
    data["volume"] = {"auto": True, "spacing_mm": 2.0}
    geometry = write_json(tmp_path / "auto.json", data)
    out = tmp_path / "auto"
    args = ["reconstruct", "--mask1", str(mask_files[0]), "--mask2", str(mask_files[1]), "--steps", "2",
            "--no-progress", "--threads", "1"]
    assert main(args + ["--geometry", str(geometry), "--out", str(out)]) == 0, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert report["grid"]["source"].startswith("placed on the masks' region")
    assert report["grid"]["placement"]["grid"] == report["geometry"]["volume"]
    assert report["geometry"]["volume"]["spacing_mm"] == [2.0, 2.0, 2.0]
    assert all(c > 0.95 for c in report["grid"]["mask_coverage"])
    # --auto-volume on a geometry with a grid: the grid moves, its voxel size stays
    plain = tmp_path / "geometry.json"
    write_json(plain, tiny_geometry_dict())
    assert main(args + ["--geometry", str(plain), "--auto-volume", "--out", str(tmp_path / "forced")]) == 0
    forced = json.loads((tmp_path / "forced" / "report.json").read_text())
    assert forced["grid"]["placement"] is not None and forced["geometry"]["volume"]["spacing_mm"] == [2.0, 2.0, 2.0]
    # without it the user's grid is kept and its coverage recorded
    assert main(args + ["--geometry", str(plain), "--out", str(tmp_path / "kept")]) == 0
    kept = json.loads((tmp_path / "kept" / "report.json").read_text())
    assert kept["grid"]["placement"] is None and kept["grid"]["source"].startswith("user")
    assert kept["geometry"]["volume"] == tiny_geometry_dict()["volume"]


def test_reconstruct_takes_any_number_of_views(tiny_case, tmp_path, capsys):
    from SDFCARLib.io import write_volume_nrrd

    geometry = standard_geometry("lao30-rao30-cra30", volume_shape=TINY_SHAPE, spacing_mm=TINY_SPACING_MM,
                                 detector_shape=TINY_DETECTOR, detector_spacing_mm=TINY_DETECTOR_SPACING_MM)
    geometry_json = write_json(tmp_path / "geometry3.json", geometry.to_dict())
    label = write_volume_nrrd(tmp_path / "label.nrrd", tiny_case.label, tiny_case.geometry.volume)
    assert main(["simulate", "--label", str(label), "--geometry", str(geometry_json), "--out", str(tmp_path / "views")]) == 0
    masks = [tmp_path / "views" / f"view{n}_mask.png" for n in (1, 2, 3)]
    out = tmp_path / "result3"
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_json, "--mask", *masks, "--out", out,
                       "--steps", 3, "--no-progress", "--label", label)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert len(report["reprojection_dice"]) == 3 and len(report["inputs"]["targets"]) == 3
    assert (out / "qa_view3.png").exists()
    # one image per view, and one way of giving them
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_json, "--mask", *masks[:2], "--out", tmp_path / "r2")
    _assert_bad_input(code, err, "describes 3 view(s) but 2 image(s) were given")
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_json, "--mask", *masks, "--mask1", masks[0],
                       "--out", tmp_path / "r3")
    _assert_bad_input(code, err, "either as --mask A B … or as --mask1/--mask2")


def test_geometry_template_warns_of_views_along_one_line(tmp_path, capsys):
    from SDFCARLib.cli import main

    assert main(["geometry-template", "--view", "30", "0", "--view", "30", "0", "--out", str(tmp_path / "g.json")]) == 0
    assert "warning: views 1 and 2 look along the same line" in capsys.readouterr().err
    assert main(["geometry-template", "--view", "0", "0", "--view", "180", "0", "--out", str(tmp_path / "h.json")]) == 0
    assert "look along the same line" in capsys.readouterr().err
    assert main(["geometry-template", "--view", "30", "0", "--view", "-30", "0", "--out", str(tmp_path / "i.json")]) == 0
    assert "warning" not in capsys.readouterr().err


def test_simulate_projects_the_whole_centreline_and_warns_of_the_part_outside_the_volume(tmp_path, capsys, geometry_file):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    from SDFCARLib.geometry import Geometry

    geometry = Geometry.load(geometry_file)
    lo, hi = geometry.volume.bounds()
    # a tube along x from the middle of the volume to 10 mm beyond its +x face
    start, end = (lo + hi) / 2, np.array([hi[0] + 10.0, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2])
    path = tmp_path / "tube.vtk"
    path.write_text("# vtk DataFile Version 3.0\ntube\nASCII\nDATASET POLYDATA\nPOINTS 2 float\n"
                    f"{start[0]} {start[1]} {start[2]} {end[0]} {end[1]} {end[2]}\nLINES 1 3\n2 0 1\n"
                    "POINT_DATA 2\nSCALARS radii float 1\nLOOKUP_TABLE default\n1.5 1.5\n")
    code, _, err = run(capsys, "simulate", "--label", path, "--geometry", geometry_file, "--out", tmp_path / "out")
    assert code == 0 and "part of the label lies outside the geometry's volume" in err
    from SDFCARLib.io import read_image
    from SDFCARLib.phantoms import load_centreline_vtk, simulate_views, voxelize

    tree = load_centreline_vtk(path)
    clipped = simulate_views(voxelize(tree, geometry.volume), geometry.volume, geometry.views, 0.2)[1][0]
    assert (read_image(tmp_path / "out" / "view1_mask.png") > 0).sum() > clipped.sum()  # the views see all of it


def test_simulate_does_not_grow_the_grid_to_a_tree_far_from_the_volume(tmp_path, capsys, geometry_file):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    path = tmp_path / "far.vtk"  # 1 m from the isocenter, as in another frame's coordinates
    path.write_text("# vtk DataFile Version 3.0\nfar\nASCII\nDATASET POLYDATA\nPOINTS 2 float\n1000 0 0 1040 0 0\n"
                    "LINES 1 3\n2 0 1\nPOINT_DATA 2\nSCALARS radii float 1\nLOOKUP_TABLE default\n1.5 1.5\n")
    code, _, err = run(capsys, "simulate", "--label", path, "--geometry", geometry_file, "--out", tmp_path / "out")
    assert code == 2 and "do not reach the volume grid" in err and not (tmp_path / "out").exists()


def test_evaluate_and_reconstruct_say_when_a_centreline_label_reaches_beyond_the_volume(tmp_path, capsys, geometry_file):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    from SDFCARLib.geometry import Geometry
    from SDFCARLib.io import write_volume_nrrd
    from SDFCARLib.phantoms import load_centreline_vtk, voxelize

    volume = Geometry.load(geometry_file).volume
    lo, hi = volume.bounds()
    middle = (lo + hi) / 2

    def tube(name, end_x):  # along x from the middle of the volume, radius 1.5 mm
        path = tmp_path / name
        path.write_text("# vtk DataFile Version 3.0\ntube\nASCII\nDATASET POLYDATA\nPOINTS 2 float\n"
                        f"{middle[0]} {middle[1]} {middle[2]} {end_x} {middle[1]} {middle[2]}\nLINES 1 3\n2 0 1\n"
                        "POINT_DATA 2\nSCALARS radii float 1\nLOOKUP_TABLE default\n1.5 1.5\n")
        return path

    inside, beyond = tube("inside.vtk", middle[0] + 0.4 * (hi[0] - middle[0])), tube("beyond.vtk", hi[0] + 10.0)
    length = hi[0] + 10.0 - middle[0]
    for path in (inside, beyond):
        prediction = write_volume_nrrd(tmp_path / f"{path.stem}.nrrd", voxelize(load_centreline_vtk(path), volume), volume)
        code, _, err = run(capsys, "evaluate", "--prediction", prediction, "--label", path, "--geometry", geometry_file,
                           "--json", tmp_path / f"{path.stem}.json")
        warnings = json.loads((tmp_path / f"{path.stem}.json").read_text())["warnings"]
        assert code == 0, err
        if path == inside:
            assert "warning" not in err and warnings == []
        else:  # 10 mm of the tube's length lie beyond the +x face
            assert f"10.0 mm of the label centreline's {length:.1f} mm" in err and "score the part inside only" in err
            assert len(warnings) == 1 and warnings[0] in err
    code, _, err = run(capsys, "simulate", "--label", beyond, "--geometry", geometry_file, "--out", tmp_path / "views")
    assert code == 0, err
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask1", tmp_path / "views" / "view1_mask.png",
                       "--mask2", tmp_path / "views" / "view2_mask.png", "--label", beyond, "--out", tmp_path / "result",
                       "--steps", 2, "--no-progress")
    assert code == 0, err
    assert "10.0 mm of the ground-truth label centreline's" in err
    report = json.loads((tmp_path / "result" / "report.json").read_text())
    assert any("10.0 mm of the ground-truth label centreline's" in w for w in report["warnings"])


# --- cancel and terminate near the end of a run ------------------------------------------------------
def _interrupt_when(monkeypatch, phase: str):
    """reconstruct, sending this process SIGINT (Ctrl-C) at the first progress report of ``phase``."""
    import SDFCARLib.optimiser as optimiser

    real_reconstruct = optimiser.reconstruct

    def interrupted(*args, progress=None, **kwargs):
        sent = []

        def report(info):
            progress(info)
            if info.get("phase") == phase and not sent:
                sent.append(True)
                os.kill(os.getpid(), signal.SIGINT)

        return real_reconstruct(*args, progress=report, **kwargs)

    monkeypatch.setattr(optimiser, "reconstruct", interrupted)


def _leftovers(out: Path):
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.sdfcar-"))


def test_ctrl_c_while_the_field_is_evaluated_is_honoured(tmp_path, capsys, geometry_file, mask_files, monkeypatch):
    _interrupt_when(monkeypatch, "output")  # "evaluating the field on the grid…"
    out = tmp_path / "out"
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask", *mask_files, "--out", out,
                       "--steps", 2)
    assert code == 130 and "cancelled: nothing was written" in err, err
    assert not out.exists() and not _leftovers(out)


def _signal_after_the_qa_pictures(monkeypatch, signum) -> None:
    """The process sends itself ``signum`` once the QA pictures are written: in the middle of writing the results."""
    import SDFCARLib.outputs as outputs

    real_qa = outputs.write_qa_png

    def qa_then_signal(*args, **kwargs):
        real_qa(*args, **kwargs)
        os.kill(os.getpid(), signum)

    monkeypatch.setattr(outputs, "write_qa_png", qa_then_signal)


def test_ctrl_c_while_the_results_are_written_stops_and_keeps_nothing(tmp_path, capsys, geometry_file, mask_files,
                                                                      monkeypatch):
    _signal_after_the_qa_pictures(monkeypatch, signal.SIGINT)
    out = tmp_path / "out"
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask", *mask_files, "--out", out,
                       "--steps", 2, "--no-progress")
    assert code == 130 and "cancelled: nothing was written" in err, err
    assert not out.exists() and not _leftovers(out)


def test_sigterm_while_the_results_are_written_cleans_up_with_status_143(tmp_path, capsys, geometry_file, mask_files,
                                                                         monkeypatch):
    def reached_the_test(signum, frame):  # without the command's own handler the signal lands here
        raise RuntimeError("SIGTERM was not handled by the command")

    previous = signal.signal(signal.SIGTERM, reached_the_test)
    _signal_after_the_qa_pictures(monkeypatch, signal.SIGTERM)
    out = tmp_path / "out"
    try:
        code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask", *mask_files, "--out", out,
                           "--steps", 2, "--no-progress")
        assert signal.getsignal(signal.SIGTERM) is reached_the_test  # the command's handler is gone again
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert code == 143 and "terminated (SIGTERM): nothing was written" in err, err
    assert not out.exists() and not _leftovers(out)


def test_ctrl_c_during_the_analysis_says_the_reconstruction_was_kept(tmp_path, capsys, geometry_file, mask_files,
                                                                     monkeypatch):
    import SDFCARLib.analysis.outputs as analysis_outputs

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(analysis_outputs, "analyse_result_dir", interrupted)
    out = tmp_path / "out"
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask", *mask_files, "--out", out,
                       "--steps", 2, "--no-progress", "--analyse")
    assert code == 130, err
    assert f"cancelled: the reconstruction was written to {out}; the analysis (--analyse) was not written" in err
    assert "nothing was written" not in err
    assert (out / "report.json").is_file() and not (out / "analysis").exists()


def test_a_seed_out_of_range_is_refused_by_its_range(tmp_path, capsys, geometry_file, mask_files):
    code, _, err = run(capsys, "reconstruct", "--geometry", geometry_file, "--mask", *mask_files, "--out", tmp_path / "o",
                       "--seed", "99999999999999999999")
    _assert_bad_input(code, err, "seed must be a whole number from 0 to 4294967295")


def test_overwrite_replaces_the_previous_results_analysis_and_keeps_the_users_files(tmp_path, capsys, geometry_file,
                                                                                      mask_files):
    out = tmp_path / "out"
    args = ["reconstruct", "--geometry", geometry_file, "--mask", *mask_files, "--out", out, "--steps", 2, "--no-progress"]
    code, _, err = run(capsys, *args)
    assert code == 0, err
    for name in ("analysis", "analysis-2", "analysis-3"):  # as `analyse` writes them, of the result about to go
        (out / name).mkdir()
        (out / name / "analysis.json").write_text("{}")
        (out / name / "profile_branch01.csv").write_text("s,d\n")
    (out / "analysis-3" / "my notes.txt").write_text("mine")  # the user's: the folder is kept
    (out / "mine.txt").write_text("mine")
    code, _, err = run(capsys, *args, "--overwrite")
    assert code == 0, err
    assert not (out / "analysis").exists() and not (out / "analysis-2").exists()
    assert (out / "analysis-3" / "my notes.txt").read_text() == "mine" and (out / "mine.txt").read_text() == "mine"
    assert (out / "report.json").is_file()


def test_the_summary_says_what_the_pose_search_did(tmp_path, capsys):
    from SDFCARLib.cli.common import print_summary

    report = tmp_path / "report.json"
    report.write_text(json.dumps({"method": "sdfcar", "reprojection_dice": [0.9, 0.9], "calibration": {
        "method": "epipolar consistency of the frames' vessel line integrals", "views": [
            {"view": 2, "left_as_given": True, "consistency_gain": 2.47, "untruncated_consistency_gain": 0.91,
             "why_left_as_given": "the motion found made the views 2.47× more consistent, but on the epipolar planes no "
                                  "vessel running into a collimator or the image's edge lies on only 0.91×"}]}}))
    print_summary({"report": report})
    out = capsys.readouterr().out
    assert "View 2: pose left as given from the frames: the motion found made the views 2.47× more consistent" in out
    assert "piece" not in out  # the report does not say
    data = json.loads(report.read_text())
    data["components"] = {"components": 16, "largest_component_fraction": 0.473}
    report.write_text(json.dumps(data))
    print_summary({"report": report})
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[1] == "reprojection Dice per view: 0.900 / 0.900"  # the pieces right below it
    assert lines[2].startswith("The result is in 16 pieces (26-connected voxels); the largest holds 47 % of them.")
    assert captured.err == ""  # a run without warnings prints no header
    data["warnings"] = ["first thing", "second thing"]
    report.write_text(json.dumps(data))
    print_summary({"report": report})
    assert capsys.readouterr().err.splitlines() == ["2 warning(s) of this run (report.json → warnings):",
                                                    "warning: first thing", "warning: second thing"]


def test_grid_coverage_warning_names_the_cause_that_fits_how_the_grid_was_made(tmp_path, tiny_case, capsys):
    from SDFCARLib.cli.reconstruct import grid_coverage_warnings
    from SDFCARLib.io import write_mask_png

    assert grid_coverage_warnings([0.95, 0.91], placed=True) == [] == grid_coverage_warnings([0.9, 1.0], placed=False)
    # a grid placed on the masks cannot cut the tree: the views disagree, and --auto-volume would change nothing
    (placed,) = grid_coverage_warnings([0.95, 0.79], placed=True)
    assert placed.startswith("the grid's visual hull explains only 79 % of view 2's mask pixels")
    assert "the views disagree" in placed and "--auto-volume" not in placed
    (given,) = grid_coverage_warnings([0.5, 0.95], placed=False)
    assert "view 1's" in given and "the grid cuts the tree" in given and "--auto-volume" in given
    # end to end: view 2's mask moved across the epipolar lines (rows), the grid placed on the masks
    masks = [write_mask_png(tmp_path / "m1.png", tiny_case.masks[0]),
             write_mask_png(tmp_path / "m2.png", np.roll(tiny_case.masks[1], 12, axis=0))]
    data = tiny_geometry_dict()
    data["volume"] = {"auto": True, "spacing_mm": 2.0}
    args = ["reconstruct", "--geometry", str(write_json(tmp_path / "auto.json", data)), "--mask1", str(masks[0]),
            "--mask2", str(masks[1]), "--steps", "2", "--no-progress", "--threads", "1", "--out", str(tmp_path / "out")]
    assert main(args) == 0
    err = capsys.readouterr().err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert min(report["grid"]["mask_coverage"]) < 0.9
    assert "the views disagree" in err and "place it on the masks with --auto-volume" not in err
