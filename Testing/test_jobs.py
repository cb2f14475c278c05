"""Background jobs: real worker processes on a tiny case (issue 4)."""

from __future__ import annotations

import json
import os
import signal
import stat
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from job_helpers import alive as _alive, tiny_job_case, wait_for as _wait_for
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.jobs import JobFailed, JobFolderError, ReconstructionJob, prepare_job, run_job
from SDFCARLib.phantoms import Branch, CentrelineTree, make_case

pytestmark = pytest.mark.skipif(os.name != "posix", reason="process-group tests use POSIX signals")


@pytest.fixture(scope="module")
def tiny_case():
    return tiny_job_case()


SMALL = {"preset": "fast", "steps": 400, "levels": 4, "log2_table_size": 12, "width": 16, "depth": 2, "threads": 1}


def test_progress_in_order_to_the_end_and_results(tiny_case, tmp_path):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    settings = dict(SMALL, steps=15)
    job = ReconstructionJob.start(tmp_path / "job", tiny_case.geometry, tiny_case.masks, settings, name="tiny")
    assert job.state == "running"
    seen = []
    deadline = time.monotonic() + 120
    while job.state == "running" and time.monotonic() < deadline:
        seen.extend(job.events())
        time.sleep(0.1)
    seen.extend(job.events())
    assert job.state == "finished", (tmp_path / "job" / "worker.log").read_text()
    steps = [e["step"] for e in seen if e.get("phase") == "optimise"]
    assert steps and steps == sorted(steps) and steps[-1] == 15
    assert seen[-1]["phase"] == "done"
    assert all(e["total"] == 15 for e in seen if "total" in e)
    paths = job.result()
    for key in ("occupancy", "segmentation", "surface", "report"):
        assert Path(paths[key]).is_file(), key
    report = json.loads(Path(paths["report"]).read_text())
    assert report["settings"]["steps"] == 15
    assert not (tmp_path / "job" / "INCOMPLETE").exists()
    assert json.loads((tmp_path / "job" / "status.json").read_text())["state"] == "finished"


def test_cancel_ends_the_whole_process_tree_within_two_seconds(tiny_case, tmp_path):
    # The worker is started through a shell that first starts a long-lived child: cancel must end both.
    wrapper = tmp_path / "python-with-child.sh"
    wrapper.write_text(f'#!/bin/sh\nsleep 600 &\necho $! > "{tmp_path}/child.pid"\nexec "{sys.executable}" "$@"\n')
    wrapper.chmod(wrapper.stat().st_mode | stat.S_IEXEC)
    job_dir = tmp_path / "job"
    prepare_job(job_dir, tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=100000))
    inputs_before = {p.name: p.read_bytes() for p in job_dir.iterdir()}
    job = ReconstructionJob.launch(job_dir, python=str(wrapper))
    assert _wait_for(lambda: (job.poll() or {}).get("phase") == "optimise", 90), (job_dir / "worker.log").read_text()
    child = int((tmp_path / "child.pid").read_text())
    assert _alive(child) and _alive(job.pid)
    start = time.monotonic()
    job.cancel()
    elapsed = time.monotonic() - start
    assert elapsed < 2.0
    assert _wait_for(lambda: not _alive(job.pid) and not _alive(child), 0.5)
    assert job.state == "cancelled"
    with pytest.raises(JobFailed, match="cancel"):
        job.result()
    # The inputs are untouched and the folder says it is incomplete.
    for name, data in inputs_before.items():
        assert (job_dir / name).read_bytes() == data
    assert (job_dir / "INCOMPLETE").exists()


def test_worker_error_is_reported_with_message_and_traceback(tiny_case, tmp_path):
    if __import__("torch").cuda.is_available():
        pytest.skip("needs a machine without CUDA to provoke the device error")
    job = ReconstructionJob.start(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, device="cuda"))
    assert job.wait(timeout=90) == "failed"
    with pytest.raises(JobFailed) as info:
        job.result()
    assert "no CUDA GPU" in info.value.message
    assert "Traceback" in info.value.traceback_text
    assert (tmp_path / "job" / "INCOMPLETE").exists()


def test_killed_worker_is_detected_and_a_second_job_runs(tiny_case, tmp_path):
    job = ReconstructionJob.start(tmp_path / "job1", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=100000))
    assert _wait_for(lambda: job.poll() is not None, 90)
    os.kill(job.pid, signal.SIGKILL)  # as the kernel's OOM killer would
    assert job.wait(timeout=10) == "failed"
    with pytest.raises(JobFailed, match="signal 9"):
        job.result()
    # The next job starts and finishes normally.
    second = ReconstructionJob.start(tmp_path / "job2", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3))
    assert second.wait(timeout=120) == "finished", (tmp_path / "job2" / "worker.log").read_text()


def test_two_jobs_in_sequence_and_in_process_run(tiny_case, tmp_path):
    for n in (1, 2):
        job = ReconstructionJob.start(tmp_path / f"job{n}", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3, seed=n))
        assert job.wait(timeout=120) == "finished"
    prepare_job(tmp_path / "inproc", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3))
    events = []
    paths = run_job(tmp_path / "inproc", progress=events.append)
    assert Path(paths["segmentation"]).is_file() and events[-1]["phase"] == "done"


def test_a_job_with_three_views(tiny_case, tmp_path):
    views = tiny_case.geometry.views + (CArmView(0.0, 30.0, 1000.0, 750.0, (1.0, 1.0), (64, 64)),)
    tube = CentrelineTree([Branch(np.array([[-12.0, 0, -10], [10.0, 4, 12]]), np.array([3.0, 2.5]))])
    case = make_case(tube, Geometry(tiny_case.geometry.volume, views))
    job = ReconstructionJob.start(tmp_path / "job", case.geometry, case.masks, dict(SMALL, steps=3))
    assert job.wait(timeout=120) == "finished", (tmp_path / "job" / "worker.log").read_text()
    assert sorted(p.name for p in (tmp_path / "job").glob("view*.npy")) == ["view1.npy", "view2.npy", "view3.npy"]
    report = json.loads(Path(job.result()["report"]).read_text())
    assert len(report["geometry"]["views"]) == 3 and len(report["view_consistency"]) == 3
    assert (tmp_path / "job" / "output" / "qa_view3.png").is_file()
    # A mask short is refused before anything runs, naming both numbers.
    with pytest.raises(JobFolderError, match="2 .*3 view"):
        prepare_job(tmp_path / "short", case.geometry, case.masks[:2], SMALL)
    assert not (tmp_path / "short").exists()


def test_bad_job_folders_are_rejected_before_start(tiny_case, tmp_path):
    with pytest.raises(JobFolderError, match="job.json"):
        ReconstructionJob.launch(tmp_path / "empty")
    folder = prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, SMALL)
    (folder / "view2.npy").unlink()
    with pytest.raises(JobFolderError, match="view2.npy"):
        ReconstructionJob.launch(folder)
    np.save(folder / "view2.npy", np.zeros((10, 10), np.float32))
    with pytest.raises(JobFolderError, match="detector shape"):
        ReconstructionJob.launch(folder)
    (folder / "geometry.json").write_text("{not json")
    with pytest.raises(JobFolderError, match="not valid JSON"):
        ReconstructionJob.launch(folder)
    with pytest.raises(JobFolderError, match="already holds a job"):
        prepare_job(folder, tiny_case.geometry, tiny_case.masks, SMALL)
    bad = [np.ones(v.detector_shape, np.float32) for v in tiny_case.geometry.views]
    with pytest.raises(JobFolderError, match="covers the whole image"):
        ReconstructionJob.start(tmp_path / "ones", tiny_case.geometry, bad, SMALL)
    with pytest.raises(JobFolderError, match="unknown mode"):
        ReconstructionJob.start(tmp_path / "mode", tiny_case.geometry, tiny_case.masks, dict(SMALL, mode="nope"))
    # Nothing was started: no progress or status files anywhere.
    assert not list(tmp_path.glob("*/progress.jsonl")) and not list(tmp_path.glob("*/status.json"))


def test_a_folder_holding_the_users_files_is_refused_and_left_as_it_was(tiny_case, tmp_path):
    """A job writes geometry.json, view1.npy … there: a folder with anything in it is refused before a byte is
    written, so a user's own files are never replaced (an empty folder is taken)."""
    from SDFCARLib.jobs import prepare_analysis_job

    used = tmp_path / "patient8"
    used.mkdir()
    (used / "geometry.json").write_text('{"description": "mine"}')
    np.save(used / "view1.npy", np.arange(4.0))
    with pytest.raises(JobFolderError, match=r"already holds files \(geometry.json, view1.npy\).*new or empty folder"):
        ReconstructionJob.start(used, tiny_case.geometry, tiny_case.masks, SMALL)
    assert sorted(p.name for p in used.iterdir()) == ["geometry.json", "view1.npy"]
    assert (used / "geometry.json").read_text() == '{"description": "mine"}'
    np.testing.assert_array_equal(np.load(used / "view1.npy"), np.arange(4.0))
    with pytest.raises(JobFolderError, match="already holds files"):
        prepare_analysis_job(used, tmp_path)
    (tmp_path / "a file").write_text("x")
    with pytest.raises(JobFolderError, match="is a file, not a folder"):
        prepare_job(tmp_path / "a file", tiny_case.geometry, tiny_case.masks, SMALL)
    (tmp_path / "empty").mkdir()
    assert (prepare_job(tmp_path / "empty", tiny_case.geometry, tiny_case.masks, SMALL) / "job.json").is_file()


def test_settings_of_the_wrong_type_are_refused_by_name_before_start(tiny_case, tmp_path):
    for given, message in [({"calibrate": "false"}, "calibrate is a switch: give True or False, got 'false'"),
                           ({"steps": "3"}, "steps takes a whole number, got '3'"),
                           ({"steps": 2.5}, "steps takes a whole number, got 2.5"),
                           ({"seed": "x"}, "seed takes a whole number")]:
        with pytest.raises(JobFolderError, match=message):
            ReconstructionJob.start(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, **given))
        assert not (tmp_path / "job").exists()
    # numpy's numbers (a script's arithmetic) are taken, and job.json holds them as plain JSON
    folder = prepare_job(tmp_path / "np", tiny_case.geometry, tiny_case.masks,
                         dict(SMALL, steps=np.int64(5), memory_check=np.bool_(False), learning_rate=np.float32(0.01)))
    stored = json.loads((folder / "job.json").read_text())["settings"]
    assert stored["steps"] == 5 and stored["memory_check"] is False and stored["learning_rate"] == pytest.approx(0.01)
    # None leaves a setting at the preset's value, as make_settings and reconstruct have it
    folder = prepare_job(tmp_path / "none", tiny_case.geometry, tiny_case.masks, dict(SMALL, seed=None, steps=None))
    assert "seed" not in json.loads((folder / "job.json").read_text())["settings"]


# --- the 3D-QCA of a result in a worker process ------------------------------------------------------
def test_analysis_job_writes_a_new_folder_each_time(tmp_path):
    from test_analysis import _result_folder

    from SDFCARLib.jobs import AnalysisJob, free_analysis_folder

    folder, phantom = _result_folder(tmp_path)
    options = {"view_step_deg": 10.0, "ostium_mm": list(phantom.truth["ostium_mm"])}
    job = AnalysisJob.start(tmp_path / "qca-job", folder, options=options)
    assert job.wait(300) == "finished", (job.job_dir / "worker.log").read_text()
    files = job.result()
    assert files["folder"] == str(folder / "analysis") and Path(files["analysis.json"]).is_file()
    assert job.poll()["phase"] == "done"
    data = json.loads(Path(files["analysis.json"]).read_text())
    assert data["lesions"] and data["best_view"]
    # An earlier analysis is never replaced: the next one goes beside it.
    assert free_analysis_folder(folder) == folder / "analysis-2"


def test_analysis_job_reports_the_worker_error(tmp_path):
    from test_analysis import _result_folder

    from SDFCARLib.jobs import AnalysisJob, prepare_analysis_job, run_analysis_job

    folder, _ = _result_folder(tmp_path)
    # One mask for a two-view result: the analysis refuses it, and the job says why.
    job = AnalysisJob.start(tmp_path / "bad", folder, masks=[np.ones((8, 8), bool)], options={"view_step_deg": 30.0})
    assert job.wait(300) == "failed"
    with pytest.raises(JobFailed, match="1 masks for 2 views"):
        job.result()
    with pytest.raises(JobFolderError, match="does not exist"):
        prepare_analysis_job(tmp_path / "none", tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(JobFolderError, match="not the folder of a reconstruction"):
        prepare_analysis_job(tmp_path / "none", tmp_path / "empty")
    with pytest.raises(JobFolderError, match="already holds a job"):
        prepare_analysis_job(tmp_path / "bad", folder)
    with pytest.raises(JobFolderError, match="has no analysis_job.json"):
        run_analysis_job(tmp_path / "empty")
    assert json.loads((tmp_path / "empty" / "status.json").read_text())["state"] == "failed"


def test_job_masks_of_a_reconstruction_folder(tiny_case, tmp_path):
    from SDFCARLib.jobs import job_masks

    prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, SMALL, name="tiny")
    masks = job_masks(tmp_path / "job")
    assert len(masks) == 2 and all(np.array_equal(m, t != 0) for m, t in zip(masks, tiny_case.masks))
    assert job_masks(tmp_path / "nowhere") is None


def test_a_three_view_job_runs_and_writes_three_overlays(tmp_path):
    """The module hands the worker one mask per view, however many views (here three)."""
    grid = VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0))
    views = [CArmView(a, b, 1000.0, 750.0, (1.0, 1.0), (64, 64)) for a, b in ((30.0, 0.0), (-30.0, 0.0), (0.0, 30.0))]
    tube = CentrelineTree([Branch(np.array([[-12.0, 0, -10], [10.0, 4, 12]]), np.array([3.0, 2.5]))])
    case = make_case(tube, Geometry(grid, views))
    job_dir = prepare_job(tmp_path / "job", case.geometry, case.masks, dict(SMALL, steps=10), name="three")
    assert json.loads((job_dir / "job.json").read_text())["views"] == 3
    files = run_job(job_dir)
    assert {"qa_view1", "qa_view2", "qa_view3"} <= set(files)
    report = json.loads(Path(files["report"]).read_text())
    assert len(report["reprojection_qa"]) == 3 and len(report["geometry"]["views"]) == 3


def test_frames_travel_with_the_job_and_are_checked_first(tiny_case, tmp_path):
    from SDFCARLib.angiogram import simulate_angiogram
    from SDFCARLib.jobs import job_frames

    frames = [simulate_angiogram(li, v.pixel_spacing_mm, n)[0]
              for n, (li, v) in enumerate(zip(tiny_case.line_integrals, tiny_case.geometry.views))]
    folder = prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3, frame_evidence=True),
                         frames=frames)
    assert sorted(p.name for p in folder.glob("frame*.npy")) == ["frame1.npy", "frame2.npy"]
    assert job_frames(folder) == [str(folder / "frame1.npy"), str(folder / "frame2.npy")]  # for the 3D-QCA's widths
    assert job_frames(prepare_job(tmp_path / "plain", tiny_case.geometry, tiny_case.masks, SMALL)) is None
    masks_as_frames = [m.astype(np.float32) * 255 for m in tiny_case.masks]  # the sample case's "frames"
    assert job_frames(prepare_job(tmp_path / "binary", tiny_case.geometry, tiny_case.masks, SMALL,
                                  frames=masks_as_frames)) is None
    report = json.loads(Path(run_job(folder)["report"]).read_text())
    assert report["frame_evidence"]["used"] is True and len(report["frame_evidence"]["views"]) == 2
    with pytest.raises(JobFolderError, match="frame 2 has shape"):
        prepare_job(tmp_path / "bad", tiny_case.geometry, tiny_case.masks, SMALL, frames=[frames[0], frames[1][:10]])
    assert not (tmp_path / "bad").exists()
    # the frames' Pixel Intensity Relationship goes with them: a frame processed for display gives no path lengths
    processed = prepare_job(tmp_path / "disp", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3, frame_evidence=True),
                            frames=frames, frame_intensity=["DISP", "LIN"])
    assert json.loads((processed / "job.json").read_text())["frame_intensity"] == ["DISP", "LIN"]
    evidence = json.loads(Path(run_job(processed)["report"]).read_text())["frame_evidence"]
    assert evidence["used"] is False and "view 1" in evidence["why"] and "DISP" in evidence["why"]
    for bad in (["LIN"], ["LIN", 3]):
        with pytest.raises(JobFolderError, match="frame_intensity must give one Pixel Intensity Relationship"):
            prepare_job(tmp_path / "bad-intensity", tiny_case.geometry, tiny_case.masks, SMALL, frames=frames,
                        frame_intensity=bad)
        assert not (tmp_path / "bad-intensity").exists()
    # how each frame was read (a LOG run brought to a linear scale) goes into the result's report
    note = "LOG frames (sign −1) brought to a linear scale"
    noted = prepare_job(tmp_path / "noted", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3), frames=frames,
                        frame_intensity=["LIN", None], frame_notes=[note, None])
    assert json.loads(Path(run_job(noted)["report"]).read_text())["frame_notes"] == [note, None]
    for bad in ([note], [note, 3]):
        with pytest.raises(JobFolderError, match="frame_notes must give one note"):
            prepare_job(tmp_path / "bad-notes", tiny_case.geometry, tiny_case.masks, SMALL, frames=frames, frame_notes=bad)
        assert not (tmp_path / "bad-notes").exists()
