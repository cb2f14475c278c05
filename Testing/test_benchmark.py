"""The evaluation harness (SDFCARLib/benchmark/): a tiny end-to-end run on a Dask LocalCluster,
resume, recorded failures, the folder suite's preprocessing, the summary tables and bad input.

Runs use a 32³ grid at 2 mm and a 96² detector at 1 mm with a few optimisation steps, so that the
whole file stays well under a minute and a half on two shared cores.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from SDFCARLib import benchmark as bm
from SDFCARLib.benchmark import run as bm_run
from SDFCARLib.geometry import VIEW_PAIRS, VolumeGrid

TINY = ["--volume-shape", 32, 32, 32, "--spacing-mm", 2, "--detector-shape", 96, 96, "--detector-spacing-mm", 1]
TINY_GRID = bm.GridOptions((32, 32, 32), 2.0, (96, 96), 1.0)
TABLE_HEADER = ("| Method | clDice (%) | Dice (%) | IoU (%) | reError | Chamfer-ℓ2 (mm) | reMSE (×1e-4) | "
                "skeleton-Dice (%) | connected components | wall time (s) | cases (ok/failed) |")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sdfcar")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS)
    commands = parser.add_subparsers(dest="command")
    bm.add_benchmark_command(commands, common)
    return parser


def run_cli(capsys, *argv):
    args = _parser().parse_args(["benchmark", *(str(a) for a in argv)])
    code = args.func(args)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def read_csv(path: Path):
    with path.open(newline="", encoding="utf-8") as stream:
        reader = csv.DictReader(stream)
        return reader.fieldnames, list(reader)


def table_lines(summary: str):
    return [line for line in summary.splitlines() if line.startswith("|")]


# --- end to end -----------------------------------------------------------------------------------
def test_tiny_suite_end_to_end_then_resume(tmp_path, capsys):
    pytest.importorskip("distributed", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")
    pytest.importorskip("matplotlib", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")
    out = tmp_path / "bench"
    argv = ["--suite", "rca", "--cases", 2, "--modes", "sdfcar,neca", "--steps", 5, "--out", out, "--workers", 2,
            "--no-progress", *TINY]
    code, stdout, err = run_cli(capsys, *argv)
    assert code == 0, err

    header, rows = read_csv(out / "results.csv")
    assert header == bm.COLUMNS
    assert sorted((r["case"], r["mode"]) for r in rows) == sorted(
        (case, mode) for case in ("RCA-0", "RCA-1") for mode in ("hull", "sdfcar", "neca"))
    assert all(r["status"] == "ok" and r["error"] == "" for r in rows), [r["error"] for r in rows]
    assert {r["seed"] for r in rows if r["case"] == "RCA-1"} == {"1"}
    assert all(r["steps"] == "5" and r["protocol"] == "paper" and r["target_kind"] == "line_integral" for r in rows)
    for r in rows:
        assert 0.0 <= float(r["dice"]) <= 1.0 and float(r["wall_s"]) >= 0.0 and r["device"]
    # Every row of a case scores against the same label.
    for case in ("RCA-0", "RCA-1"):
        assert len({r["voxels_label"] for r in rows if r["case"] == case}) == 1

    # The hull row is the visual hull of the case's masks scored with metrics.py.
    from SDFCARLib.hull import visual_hull
    from SDFCARLib.metrics import dice, iou

    spec = bm.build_cases(bm.BenchmarkConfig("rca", out, cases=1))[0]
    case = bm.prepare_case(spec, "paper", TINY_GRID)
    hull = visual_hull(case.masks, case.geometry.views, case.geometry.volume)
    hull_row = next(r for r in rows if r["case"] == "RCA-0" and r["mode"] == "hull")
    assert float(hull_row["dice"]) == pytest.approx(dice(hull, case.label))
    assert float(hull_row["iou"]) == pytest.approx(iou(hull, case.label))
    assert int(hull_row["voxels_label"]) == int(case.label.sum()) > 0

    summary = (out / "summary.md").read_text(encoding="utf-8")
    assert summary in stdout
    lines = table_lines(summary)
    assert lines[0] == TABLE_HEADER
    body = lines[2:]
    assert [line.split("|")[1].strip() for line in body] == [
        "Visual hull (masks only) (`hull`)", "SDF-CAR (`sdfcar`)", "NeCA (`neca`)"]
    assert all(line.rstrip(" |").endswith("2/0") for line in body)
    assert all(len(line.split("|")) == len(lines[0].split("|")) for line in body)
    assert "Ordering sdfcar vs neca" in summary
    assert "--suite rca --modes sdfcar,neca --preset fast --protocol paper --seed 0" in summary
    import torch

    assert f"torch {torch.__version__}" in summary and "cores" in summary

    record = json.loads((out / "run.json").read_text(encoding="utf-8"))["runs"][-1]
    assert record["seeds"] == [0, 1] and record["cases"] == ["RCA-0", "RCA-1"]
    assert record["versions"]["torch"] == torch.__version__ and record["machine"]["cores"] >= 1
    assert "LocalCluster: 2 process worker(s)" in record["cluster"]["description"]

    figures = out / "figures"
    for metric in ("cldice", "dice", "iou", "re_error", "chamfer_l2_mm", "re_mse", "skeleton_dice", "wall_s"):
        assert (figures / f"box_rca_{metric}.png").stat().st_size > 0
    import imageio.v3 as iio

    for case_name in ("RCA-0", "RCA-1"):
        for mode in ("hull", "sdfcar", "neca"):
            image = iio.imread(figures / f"overlay_{case_name}_{mode}.png")
            assert image.ndim == 3 and image.shape[0] >= 256
    # The hull contains the label's voxels projecting inside both masks: some green (overlap) pixels.
    hull_image = iio.imread(figures / "overlay_RCA-0_hull.png")
    assert np.any(np.all(hull_image[..., :3] == (40, 200, 60), axis=-1))

    # Resume: the same command finds every row done, adds none and starts no cluster.
    started = time.perf_counter()
    code, _, err = run_cli(capsys, *argv)
    elapsed = time.perf_counter() - started
    assert code == 0, err
    assert "nothing to run" in err
    assert len(read_csv(out / "results.csv")[1]) == len(rows)
    assert elapsed < 20
    assert table_lines((out / "summary.md").read_text(encoding="utf-8"))[2:] != []
    assert len(json.loads((out / "run.json").read_text(encoding="utf-8"))["runs"]) == 2


def test_motion_protocol_rows_carry_the_depth_aligned_metrics(tmp_path, capsys):
    """With heart motion the rows add the tree's offset along view 1's axis and the scores there; static rows do not."""
    pytest.importorskip("distributed", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")
    from SDFCARLib.hull import visual_hull
    from SDFCARLib.metrics import depth_aligned_metrics

    rows_of = {}
    for protocol in ("realistic-lao30-rao30", "realistic-static-lao30-rao30"):
        out = tmp_path / protocol
        code, _, err = run_cli(capsys, "--suite", "rca", "--cases", 1, "--modes", "hull", "--protocol", protocol,
                               "--out", out, "--workers", 1, "--no-progress", *TINY)
        assert code == 0, err
        rows_of[protocol] = read_csv(out / "results.csv")[1]
    moved = rows_of["realistic-lao30-rao30"][0]
    assert float(moved["motion_mm"]) > 0
    spec = bm.build_cases(bm.BenchmarkConfig("rca", tmp_path, cases=1))[0]
    case = bm.prepare_case(spec, "realistic-lao30-rao30", TINY_GRID)
    hull = visual_hull(case.masks, case.geometry.views, case.geometry.volume)
    expected = depth_aligned_metrics(hull, case.label, case.geometry.volume, case.geometry.views[0].detector_direction)
    for key, value in expected.items():
        assert float(moved[key]) == pytest.approx(value)
    assert float(moved["dice_depth_aligned"]) >= float(moved["dice"])  # no shift is one of the shifts searched
    static = rows_of["realistic-static-lao30-rao30"][0]
    assert static["depth_offset_mm"] == static["cldice_depth_aligned"] == ""


def test_failed_run_is_recorded_and_retried_on_request(tmp_path, capsys, monkeypatch):
    LocalCluster = pytest.importorskip("distributed", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)").LocalCluster
    pytest.importorskip("matplotlib", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")

    real = bm_run._reconstruct

    def neca_fails(geometry, targets, settings, target_kind, frames=None, frame_intensity=None):
        if settings.run.mode == "neca":
            raise RuntimeError("injected failure")
        return real(geometry, targets, settings, target_kind, frames, frame_intensity)

    monkeypatch.setattr(bm_run, "_reconstruct", neca_fails)
    out = tmp_path / "bench"
    argv = ["--suite", "lad", "--cases", 1, "--modes", "sdfcar,neca", "--steps", 2, "--out", out, "--no-progress",
            "--protocol", "clinical-lao30-rao30", *TINY]
    # Workers in this process (threads) see the monkeypatch; --scheduler exercises the existing-cluster path.
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        code, stdout, err = run_cli(capsys, *argv, "--scheduler", cluster.scheduler_address)
        assert code == 0, err
        _, rows = read_csv(out / "results.csv")
        by_mode = {r["mode"]: r for r in rows}
        assert set(by_mode) == {"hull", "sdfcar", "neca"}
        assert by_mode["sdfcar"]["status"] == "ok" and by_mode["hull"]["status"] == "ok"
        failed = by_mode["neca"]
        assert failed["status"] == "failed" and "injected failure" in failed["error"] and failed["dice"] == ""
        assert failed["case"] == "LAD-0" and failed["target_kind"] == "mask"
        trace = (out / failed["traceback_file"]).read_text(encoding="utf-8")
        assert "Traceback" in trace and "injected failure" in trace
        assert "1 run(s) failed" in err and "failed: LAD-0 × neca" in err and "injected" not in stdout.split("## Failed runs")[0]
        summary = (out / "summary.md").read_text(encoding="utf-8")
        assert "## Failed runs" in summary and "injected failure" in summary
        neca_line = next(line for line in table_lines(summary) if "(`neca`)" in line)
        assert neca_line.rstrip(" |").endswith("0/1") and "n/a" in neca_line

        # A plain re-run keeps the failure (no new row); --retry-failed runs it again.
        code, _, err = run_cli(capsys, *argv, "--scheduler", cluster.scheduler_address)
        assert code == 0 and len(read_csv(out / "results.csv")[1]) == 3
        monkeypatch.setattr(bm_run, "_reconstruct", real)
        code, _, err = run_cli(capsys, *argv, "--scheduler", cluster.scheduler_address, "--retry-failed")
        assert code == 0, err
    _, rows = read_csv(out / "results.csv")
    assert [r["mode"] for r in rows].count("neca") == 2 and rows[-1]["mode"] == "neca" and rows[-1]["status"] == "ok"
    neca_line = next(line for line in table_lines((out / "summary.md").read_text(encoding="utf-8")) if "(`neca`)" in line)
    assert neca_line.rstrip(" |").endswith("1/0")


def test_local_cluster_workers_do_not_inherit_dasks_malloc_trim_setting(tmp_path, monkeypatch):
    """Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_ (glibc then maps every large tensor afresh: a fit at
    half speed); the benchmark's own cluster leaves it unset, and Dask's configuration as it was."""
    pytest.importorskip("distributed", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")
    import dask

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    key = bm_run.WORKER_ENVIRON_KEY
    # Dask's own default (65536 in 2026.8), set here so that the test does not depend on the installed version
    with dask.config.set({f"{key}.MALLOC_TRIM_THRESHOLD_": 65536, f"{key}.OMP_NUM_THREADS": 1}):
        client, cluster, _ = bm_run._start_client(bm.BenchmarkConfig("rca", tmp_path, workers=1), processes=True)
        try:
            seen = client.run(lambda: {name: os.environ.get(name) for name in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS")})
        finally:
            client.close()
            cluster.close()
        assert dask.config.get(key)["MALLOC_TRIM_THRESHOLD_"] == 65536  # Dask's configuration as it was
    (worker,) = seen.values()
    assert worker["MALLOC_TRIM_THRESHOLD_"] is None
    assert worker["OMP_NUM_THREADS"] == "1"  # Dask's other settings stay: torch's threads are set per task


@pytest.mark.parametrize("trim", [None, "65536"])
def test_own_scheduler_whose_workers_trim_malloc_gets_a_warning(tmp_path, capsys, monkeypatch, trim):
    LocalCluster = pytest.importorskip("distributed", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)").LocalCluster
    pytest.importorskip("matplotlib", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")
    if trim is None:
        monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    else:
        monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", trim)  # the workers below are threads of this process
    argv = ["--suite", "lad", "--cases", 1, "--modes", "sdfcar", "--steps", 2, "--out", tmp_path / "bench", "--no-progress",
            "--protocol", "clinical-lao30-rao30", *TINY]
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        code, _, err = run_cli(capsys, *argv, "--scheduler", cluster.scheduler_address)
    assert code == 0, err
    warned = [line for line in err.splitlines() if "MALLOC_TRIM_THRESHOLD_" in line]
    if trim is None:
        assert warned == []
    else:
        assert len(warned) == 1 and "1 worker(s)" in warned[0] and "--no-nanny" in warned[0]


def test_case_preparation_failure_becomes_a_row_per_mode(tmp_path):
    """A label file the folder suite cannot split fails its cases, with the reason, not the run."""
    from SDFCARLib.io import write_volume_nrrd

    folder = tmp_path / "labels"
    folder.mkdir()
    label = np.zeros((20, 20, 20), bool)
    label[5:15, 8:12, 8:12] = True  # one component only
    write_volume_nrrd(folder / "single.nrrd", label, VolumeGrid((20, 20, 20), (1.0, 1.0, 1.0)))
    config = bm.BenchmarkConfig(f"folder:{folder}", tmp_path / "out", modes=("neca",), grid=TINY_GRID)
    spec = bm.build_cases(config)[0]
    prepared = bm.prepare_task(spec, "paper", TINY_GRID)
    assert "connected component" in prepared["error"]
    outcome = bm.run_task(prepared, spec, "neca", bm.task_options(config))
    row = outcome["row"]
    assert row["status"] == "failed" and row["case"] == "single-lad" and row["mode"] == "neca"
    assert row["error"].startswith("case preparation failed") and "Traceback" in outcome["traceback"]


# --- folder suite preprocessing --------------------------------------------------------------------
def _two_trees(spacing: float = 0.5):
    """A 0.5 mm label: a sphere (r 4 mm) at x = +12 mm (patient's left), a larger box at x = −12 mm
    (right) and a one-voxel fragment."""
    grid = VolumeGrid((100, 60, 60), (spacing,) * 3)
    x, y, z = np.moveaxis(grid.index_to_world(np.indices(grid.shape).reshape(3, -1).T).reshape(grid.shape + (3,)), -1, 0)
    sphere = (x - 12.0) ** 2 + y ** 2 + z ** 2 <= 4.0 ** 2
    box = (np.abs(x + 12.0) < 6.0) & (np.abs(y) < 4.0) & (np.abs(z - 2.0) < 4.0)
    label = sphere | box
    label[0, 0, 0] = True
    return label, grid, sphere, box


@pytest.mark.parametrize("fmt", ["nrrd", "nifti-ras"])
def test_folder_preprocessing_resamples_centres_and_names_the_trees(tmp_path, fmt):
    label, grid, sphere, box = _two_trees()
    if fmt == "nrrd":
        from SDFCARLib.io import write_volume_nrrd

        path = write_volume_nrrd(tmp_path / "case7.nrrd", label, grid)
        expected = {"lad": sphere, "rca": box}
    else:
        # NIfTI's world is RAS: with a +x (towards the patient's right) column the same array puts
        # the sphere on the patient's right, so the trees swap names.
        import nibabel

        path = tmp_path / "case7.nii.gz"
        nibabel.save(nibabel.Nifti1Image(label.astype(np.uint8), np.diag([0.5, 0.5, 0.5, 1.0])), str(path))
        expected = {"lad": box, "rca": sphere}
    trees = bm.preprocess_label_file(path, spacing_mm=1.0, shape=(32, 32, 32))
    assert set(trees) == {"lad", "rca"}
    for name, (mask, out_grid, info) in trees.items():
        assert mask.shape == (32, 32, 32) and out_grid.spacing_mm == (1.0, 1.0, 1.0)
        assert np.allclose(out_grid.center_mm, 0.0)
        # 1 mm voxels hold 8 of the 0.5 mm ones.
        assert mask.sum() == pytest.approx(expected[name].sum() / 8, rel=0.15)
        assert info["fragment_voxels_dropped"] == 1 and info["voxels_cut_off"] == 0
        nz = np.argwhere(mask)
        assert np.all(np.abs((nz.min(axis=0) + nz.max(axis=0)) / 2 - 15.5) <= 0.5)  # centred
    sphere_tree = "lad" if fmt == "nrrd" else "rca"
    extent = np.ptp(np.argwhere(trees[sphere_tree][0]), axis=0) + 1
    assert np.all(np.abs(extent - 8) <= 1)  # 8 mm diameter at 1 mm

    # In the folder suite each file gives a left and a right case, seeds in file order.
    config = bm.BenchmarkConfig(f"folder:{tmp_path}", tmp_path / "out", seed=5)
    cases = bm.build_cases(config)
    assert [(c.name, c.tree, c.seed) for c in cases] == [("case7-lad", "lad", 5), ("case7-rca", "rca", 6)]
    prepared = bm.prepare_case(cases[0], "clinical-lao30-rao30", bm.GridOptions((32, 32, 32), None, (96, 96), 1.0))
    assert prepared.geometry.volume.spacing_mm == (1.0, 1.0, 1.0)  # folder suites at 1 mm
    assert np.array_equal(prepared.label, trees["lad"][0]) and all(m.any() for m in prepared.masks)


def test_folder_preprocessing_refuses_a_single_tree():
    label = np.zeros((10, 10, 10), bool)
    label[2:8, 4:6, 4:6] = True
    with pytest.raises(bm.BenchmarkError, match="connected component"):
        bm.preprocess_label_volume(label, VolumeGrid((10, 10, 10), (1.0, 1.0, 1.0)))


# --- suites, protocols, options -----------------------------------------------------------------
def test_suites_cases_and_seeds(tmp_path):
    cases = bm.build_cases(bm.BenchmarkConfig("lad", tmp_path, cases=3, seed=10))
    assert [(c.name, c.tree, c.seed) for c in cases] == [("LAD-10", "lad", 10), ("LAD-11", "lad", 11), ("LAD-12", "lad", 12)]
    assert len(bm.build_cases(bm.BenchmarkConfig("rca", tmp_path))) == 10
    with pytest.raises(bm.BenchmarkError, match="--centreline"):
        bm.build_cases(bm.BenchmarkConfig("721a", tmp_path, centreline=tmp_path / "missing.vtk"))
    # The same case spec rebuilds the same label and views (seeds fixed per case).
    spec = cases[0]
    a, b = bm.prepare_case(spec, "paper", TINY_GRID), bm.prepare_case(spec, "paper", TINY_GRID)
    assert np.array_equal(a.label, b.label) and all(np.array_equal(x, y) for x, y in zip(a.targets, b.targets))


@pytest.mark.skipif(not bm.default_centreline().is_file(), reason="the shared 721A centreline is not in this checkout")
def test_721a_suite_prepares_the_centreline(tmp_path):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    cases = bm.build_cases(bm.BenchmarkConfig("721a", tmp_path, cases=2))
    assert [(c.name, c.seed) for c in cases] == [("721A-s0", 0), ("721A-s1", 1)]
    prepared = bm.prepare_case(cases[0], "clinical-lao30-rao30", TINY_GRID)
    assert prepared.label.any() and prepared.target_kind == "mask" and all(m.any() for m in prepared.masks)


def test_protocol_geometries():
    paper = bm.protocol_geometry("paper", "rca")
    assert paper.volume.shape == (128, 128, 128) and paper.volume.spacing_mm == (0.8, 0.8, 0.8)
    assert [(v.primary_deg, v.secondary_deg, v.sid_mm, v.sod_mm) for v in paper.views] == VIEW_PAIRS["paper"]
    assert all(v.detector_shape == (512, 512) and v.pixel_spacing_mm == (0.278, 0.278) for v in paper.views)
    assert bm.protocol_geometry("paper", "folder").volume.spacing_mm == (1.0, 1.0, 1.0)
    clinical = bm.protocol_geometry("clinical-lao50cra25-rao50cra25", "lad")
    assert [(v.primary_deg, v.secondary_deg) for v in clinical.views] == [(50.0, 25.0), (-50.0, 25.0)]
    assert bm.PROTOCOLS["paper"][1] == "line_integral" and bm.PROTOCOLS["clinical-lao30-rao30"][1] == "mask"


def test_overrides_are_typed_from_the_settings():
    assert bm.parse_overrides(["learning_rate=1e-3", "levels=8", "table_learning_rate=none", "device=cuda"]) == {
        "learning_rate": 1e-3, "levels": 8, "table_learning_rate": None, "device": "cuda"}
    # Typing by the field's annotation (the optimiser's list of flags changes as presets are tuned).
    from SDFCARLib.settings import ReconstructionError, typed_setting_value

    assert typed_setting_value("flag", "true", bool) is True and typed_setting_value("flag", "off", bool) is False
    with pytest.raises(ReconstructionError, match="true or false"):
        typed_setting_value("flag", "maybe", bool)
    for item, message in [("levels=8.5", "whole number"), ("learning_rate=fast", "takes a number"),
                          ("noequals", "KEY=VALUE"), ("seed=3", "--seed"), ("bogus=1", "unknown setting")]:
        with pytest.raises(bm.BenchmarkError, match=message):
            bm.parse_overrides([item])
    a = bm.BenchmarkConfig("rca", Path("x"), overrides={"learning_rate": 1e-3})
    b = bm.BenchmarkConfig("rca", Path("x"), overrides={"learning_rate": 2e-3})
    assert a.config_id() != b.config_id()  # variants never share rows
    assert a.config_id() == bm.BenchmarkConfig("rca", Path("elsewhere"), overrides={"learning_rate": 1e-3}).config_id()


def test_retuned_preset_changes_the_configuration(monkeypatch):
    """Rows made with a preset's old values are not resumed once the preset changes."""
    from SDFCARLib import settings

    before = bm.BenchmarkConfig("rca", Path("x")).config_id()
    monkeypatch.setitem(settings.PRESETS, "fast", dict(settings.PRESETS["fast"], learning_rate=0.123))
    assert bm.BenchmarkConfig("rca", Path("x")).config_id() != before


@pytest.mark.parametrize("argv, message", [
    (["--suite", "nope"], "unknown suite"),
    (["--suite", "rca", "--modes", "sdfcar,bogus"], "unknown mode"),
    (["--suite", "rca", "--modes", "neca,neca"], "twice"),
    (["--suite", "rca", "--set", "learning_rate=abc"], "takes a number"),
    (["--suite", "rca", "--set", "learning_rate=-1"], "learning_rate must be positive"),
    (["--suite", "rca", "--set", "mode=neca"], "--modes"),
    (["--suite", "rca", "--preset", "nosuch"], "unknown preset"),
    (["--suite", "721a", "--centreline", "{tmp}/missing.vtk"], "--centreline"),
    (["--suite", "folder:{tmp}/nowhere"], "no such folder"),
    (["--suite", "folder:{tmp}"], "no label volume"),
    (["--suite", "rca", "--set", "width=0"], "width is a size of the field's network"),
    (["--suite", "rca", "--set", "levels=-1"], "levels is a size of the field's network"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code, _, err = run_cli(capsys, *argv, "--out", out)
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], err
    assert not out.exists()


# --- results file and summary --------------------------------------------------------------------
def test_results_file_survives_a_row_cut_short(tmp_path):
    results = bm.ResultsFile(tmp_path / "results.csv")
    results.append({"suite": "rca", "case": "RCA-0", "mode": "hull", "status": "ok", "dice": 0.5})
    with (tmp_path / "results.csv").open("a", encoding="utf-8") as stream:
        stream.write("rca,rca,RCA-1,1,paper")  # a crash mid-write
    assert [r["case"] for r in bm.ResultsFile(tmp_path / "results.csv").rows()] == ["RCA-0"]
    results.append({"suite": "rca", "case": "RCA-2", "mode": "hull", "status": "ok", "dice": 0.25})
    rows = bm.ResultsFile(tmp_path / "results.csv").rows()
    assert [(r["case"], float(r["dice"])) for r in rows] == [("RCA-0", 0.5), ("RCA-2", 0.25)]
    (tmp_path / "other.csv").write_text("a,b\n1,2\n", encoding="utf-8")
    with pytest.raises(bm.BenchmarkError, match="not a benchmark results file"):
        bm.ResultsFile(tmp_path / "other.csv")


def _row(case, mode, dice, chamfer, status="ok"):
    values = {"cldice": dice, "dice": dice, "iou": dice / 2, "skeleton_dice": dice, "re_error": 1 - dice,
              "chamfer_l2_mm": chamfer, "re_mse": (1 - dice) * 1e-4, "wall_s": 10.0}
    return {"suite": "rca", "tree": "rca", "case": case, "mode": mode, "status": status,
            **{k: repr(v) for k, v in values.items()}}


def test_summary_table_means_bold_and_ordering():
    rows = []
    for n, (s, c, h) in enumerate([(0.9, 0.5, 0.3), (0.8, 0.6, 0.3), (1.0, 0.7, 0.3)]):
        rows += [_row(f"RCA-{n}", "hull", h, 3.0), _row(f"RCA-{n}", "sdfcar", s, 1.0 if n else math.nan),
                 _row(f"RCA-{n}", "neca", c, 2.0)]
    rows.append(_row("RCA-3", "neca", 0.0, 0.0, status="failed"))
    table = bm.summary_tables(rows, ["sdfcar", "neca"])[0]
    lines = bm._table_markdown(table).splitlines()
    assert lines[0] == TABLE_HEADER
    hull, sdfcar, neca = (line.split(" | ") for line in lines[2:])
    assert sdfcar[2] == "**90.00 ± 10.00**" and neca[2] == "60.00 ± 10.00" and hull[2] == "30.00 ± 0.00"  # Dice (%)
    assert sdfcar[5] == "**1.00 ± 0.00 (n=2)**"  # Chamfer: one case undefined
    assert sdfcar[4] == "**0.100 ± 0.100**" and neca[4] == "0.400 ± 0.100"  # reError, lower is better
    assert neca[-1].rstrip(" |") == "3/1"
    ordering = "\n".join(bm.ordering_lines(table))
    assert "Dice (%): sdfcar better (90.00 vs 60.00; sdfcar better in 3/3 cases)" in ordering
    assert "Chamfer-ℓ2 (mm): sdfcar better (1.00 vs 2.00; sdfcar better in 2/2 cases)" in ordering
    assert "reproduces on 6 of 6 metrics — it reproduces." in ordering
    side = "\n".join(bm.side_by_side_lines(table))
    assert "`sdfcar` against the visual hull on 3 cases: clDice 0.900 vs 0.300 (×3.00, +0.600; higher in 3/3)" in side
    assert "`neca` against the visual hull on 3 cases: clDice 0.600 vs 0.300 (×2.00, +0.300" in side
    assert "wall time 10.0 s per case" in side and "Empty reconstructions" not in side
    one = bm.summary_tables([_row("RCA-0", "hull", 0.3, 3.0), dict(_row("RCA-0", "sdfcar", 0.0, math.nan),
                                                                  voxels_predicted="0")], ["sdfcar"])[0]
    assert "30.00 ± n/a" in bm._table_markdown(one)  # one case has no spread, not a spread of 0
    assert "Empty reconstructions (no voxel predicted" in "\n".join(bm.side_by_side_lines(one))
    swapped = [dict(r, mode={"sdfcar": "neca", "neca": "sdfcar"}.get(r["mode"], r["mode"])) for r in rows if r["status"] == "ok"]
    assert "it does not fully reproduce" in "\n".join(bm.ordering_lines(bm.summary_tables(swapped, ["sdfcar", "neca"])[0]))


def test_a_negative_seed_and_cuda_without_a_gpu_are_refused_before_any_work(tmp_path, capsys, monkeypatch):
    import torch

    with pytest.raises(SystemExit):  # argparse: numpy's generators take no negative seed
        _parser().parse_args(["benchmark", "--suite", "rca", "--seed", "-1", "--out", str(tmp_path / "out")])
    assert "must be a whole number, 0 or more" in capsys.readouterr().err
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # as on the CI machine, whatever this one has
    code, _, err = run_cli(capsys, "--suite", "rca", "--cases", "1", "--set", "device=cuda", "--out", tmp_path / "gpu")
    assert code == 2 and "--set device=cuda: this machine has no CUDA GPU" in err and "--set device=cpu" in err
    assert not (tmp_path / "gpu").exists()


def test_an_interrupted_run_is_recorded_as_such_and_each_row_names_its_run(tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")
    pytest.importorskip("matplotlib", reason="the benchmark harness needs the 'bench' extra (dask[distributed], matplotlib)")
    real_append = bm_run.ResultsFile.append
    appended = []

    def ctrl_c_after_the_first_row(self, row):
        if appended:
            raise KeyboardInterrupt
        appended.append(row)
        real_append(self, row)

    monkeypatch.setattr(bm_run.ResultsFile, "append", ctrl_c_after_the_first_row)
    out = tmp_path / "bench"
    code, _, err = run_cli(capsys, "--suite", "lad", "--cases", 1, "--modes", "sdfcar", "--steps", 2, "--out", out,
                           "--no-progress", "--protocol", "clinical-lao30-rao30", "--workers", 1, *TINY)
    assert code == 130 and "interrupted" in err
    record = json.loads((out / "run.json").read_text())["runs"][-1]
    assert record["interrupted"] == "KeyboardInterrupt" and "stopped" in record and "finished" not in record
    assert record["rows_written"] == 1 and record["rows_failed"] == 0
    _, rows = read_csv(out / "results.csv")
    assert len(rows) == 1 and rows[0]["run_id"] == record["run_id"]
