"""Background jobs: one run per folder, cancels that come late or find the folder gone, what a cancel leaves behind,
and inputs refused before a worker starts (the tiny case of job_helpers.py)."""

from __future__ import annotations

import json
import os
import shutil
import stat
import sys
import time
from pathlib import Path

import pytest

from job_helpers import alive as _alive, tiny_job_case, wait_for as _wait_for
from SDFCARLib.jobs import (AnalysisJob, JobFailed, JobFolderError, ReconstructionJob, prepare_analysis_job, prepare_job,
                            run_job)

pytestmark = pytest.mark.skipif(os.name != "posix", reason="process-group tests use POSIX signals")

SMALL = {"preset": "fast", "steps": 400, "levels": 4, "log2_table_size": 12, "width": 16, "depth": 2, "threads": 1}
LONG = dict(SMALL, steps=100000)


@pytest.fixture(scope="module")
def tiny_case():
    return tiny_job_case()


def _state(job_dir: Path) -> str:
    return json.loads((job_dir / "status.json").read_text())["state"]


def _python_that_lingers(tmp_path: Path) -> str:
    """An interpreter whose process outlives the worker by 30 s, as a worker still exiting after writing its result."""
    wrapper = tmp_path / "python-lingering.sh"
    wrapper.write_text(f'#!/bin/sh\n"{sys.executable}" "$@"\nrc=$?\nsleep 30\nexit $rc\n')
    wrapper.chmod(wrapper.stat().st_mode | stat.S_IEXEC)
    return str(wrapper)


# --- one run per folder -------------------------------------------------------------------------------
def test_a_second_launch_of_a_folder_is_refused_at_once(tiny_case, tmp_path):
    job_dir = prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, LONG)
    first = ReconstructionJob.launch(job_dir)
    try:
        # at once: the worker makes its own files only seconds later
        with pytest.raises(JobFolderError, match="already being run.*prepare a new job folder"):
            ReconstructionJob.launch(job_dir)
        with pytest.raises(JobFolderError, match="already being run"):
            run_job(job_dir)
        assert first.state == "running"
    finally:
        first.cancel()
    assert first.state == "cancelled"


def test_two_analyses_of_one_result_get_two_folders(tmp_path):
    result = tmp_path / "result"
    result.mkdir()
    (result / "occupancy.nrrd").write_bytes(b"")  # all prepare_analysis_job looks for
    one = json.loads((prepare_analysis_job(tmp_path / "a1", result) / "analysis_job.json").read_text())["out_dir"]
    two = json.loads((prepare_analysis_job(tmp_path / "a2", result) / "analysis_job.json").read_text())["out_dir"]
    assert (Path(one).name, Path(two).name) == ("analysis", "analysis-2")


def test_a_finished_folder_is_not_run_again(tiny_case, tmp_path):
    job_dir = prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3))
    run_job(job_dir)
    started = time.monotonic()
    with pytest.raises(JobFolderError, match="holds a finished job.*prepare a new job folder"):
        run_job(job_dir)
    assert time.monotonic() - started < 1.0  # refused, not fitted again
    assert _state(job_dir) == "finished" and not (job_dir / "INCOMPLETE").exists()
    with pytest.raises(JobFolderError, match="holds a finished job"):
        ReconstructionJob.launch(job_dir)


# --- cancel ------------------------------------------------------------------------------------------
def test_cancel_after_the_job_finished_keeps_its_result(tiny_case, tmp_path):
    job_dir = prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3))
    job = ReconstructionJob.launch(job_dir, python=_python_that_lingers(tmp_path))
    assert _wait_for(lambda: (job_dir / "status.json").is_file() and _state(job_dir) != "running", 120)
    assert job.process.poll() is None  # the worker has written its result but not exited yet
    job.cancel()
    assert job.state == "finished" and _state(job_dir) == "finished"
    assert Path(job.result()["report"]).is_file()


def test_cancel_of_a_job_whose_folder_was_deleted_stops_the_worker(tiny_case, tmp_path):
    job = ReconstructionJob.start(tmp_path / "job", tiny_case.geometry, tiny_case.masks, LONG)
    assert _wait_for(lambda: (job.poll() or {}).get("phase") == "optimise", 90)
    shutil.rmtree(tmp_path / "job")
    job.cancel()
    assert _wait_for(lambda: not _alive(job.pid), 2.0)
    with pytest.raises(JobFailed, match="job folder .* was deleted"):
        job.result()
    assert not (tmp_path / "job").exists()  # not made again by a late write


def test_a_job_whose_folder_is_deleted_mid_run_says_so(tiny_case, tmp_path):
    job = ReconstructionJob.start(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=200))
    assert _wait_for(lambda: (job.poll() or {}).get("phase") == "optimise", 90)
    shutil.rmtree(tmp_path / "job")
    assert job.wait(120) == "failed"
    with pytest.raises(JobFailed, match="job folder .* was deleted.*new folder"):
        job.result()
    assert not (tmp_path / "job").exists()


def test_cancel_while_the_results_are_written_leaves_no_staging_folder(tiny_case, tmp_path, monkeypatch):
    # The worker writes slowly (a QA overlay takes 60 s), so that the cancel comes while the staging folder is filled.
    patch = tmp_path / "patch"
    patch.mkdir()
    (patch / "sitecustomize.py").write_text(
        "import time\n"
        "import SDFCARLib.outputs as outputs\n"
        "real = outputs.write_qa_png\n"
        "def slow(*args, **kwargs):\n"
        "    real(*args, **kwargs)\n"
        "    time.sleep(60)\n"
        "outputs.write_qa_png = slow\n")
    monkeypatch.setenv("PYTHONPATH", str(patch))
    job_dir = prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3))
    job = ReconstructionJob.launch(job_dir)
    assert _wait_for(lambda: list(job_dir.glob(".output.sdfcar-*/qa_view1.png")), 120), (job_dir / "worker.log").read_text()
    job.cancel()
    assert job.state == "cancelled"
    assert sorted(p.name for p in job_dir.iterdir() if p.name.startswith(".")) == []
    assert not (job_dir / "output").exists()
    with pytest.raises(JobFailed, match="cancel"):
        job.result()


# --- refused before a worker starts -------------------------------------------------------------------
def test_inputs_the_worker_would_fail_on_are_refused_up_front(tiny_case, tmp_path):
    g, m = tiny_case.geometry, tiny_case.masks
    for given, message in [({"seed": 2**70}, "seed must be a whole number from 0 to 4294967295"),
                           ({"seed": -1}, "seed must be a whole number from 0")]:
        with pytest.raises(JobFolderError, match=message):
            prepare_job(tmp_path / "job", g, m, dict(SMALL, **given))
    with pytest.raises(JobFolderError, match="name is the result's name, a text.*got 123 \\(int\\)"):
        prepare_job(tmp_path / "job", g, m, SMALL, name=123)
    for geometry in (None, g.to_dict()):
        with pytest.raises(JobFolderError, match="geometry must be an SDFCARLib.geometry.Geometry.*Geometry.load"):
            prepare_job(tmp_path / "job", geometry, m, SMALL)
    with pytest.raises(JobFolderError, match="is a path .*SDFCARLib.io.read_mask"):
        prepare_job(tmp_path / "job", g, [str(tmp_path / "m1.png"), str(tmp_path / "m2.png")], SMALL)
    assert not (tmp_path / "job").exists()
    (tmp_path / "a file").write_text("x")
    with pytest.raises(JobFolderError, match="cannot make the job folder .*choose a folder you can write to"):
        prepare_job(tmp_path / "a file" / "job", g, m, SMALL)


def test_a_missing_interpreter_is_named_and_the_folder_can_be_launched_again(tiny_case, tmp_path):
    job_dir = prepare_job(tmp_path / "job", tiny_case.geometry, tiny_case.masks, dict(SMALL, steps=3))
    before = sorted(p.name for p in job_dir.iterdir())
    with pytest.raises(JobFolderError, match="cannot start the worker with /nonexistent/python.*give python="):
        ReconstructionJob.launch(job_dir, python="/nonexistent/python")
    assert sorted(p.name for p in job_dir.iterdir()) == before  # no INCOMPLETE, worker.log or status.json
    job = ReconstructionJob.launch(job_dir)
    assert job.wait(120) == "finished", (job_dir / "worker.log").read_text()


def test_analysis_cancel_after_it_finished_keeps_it(tmp_path):
    from test_analysis import _result_folder

    folder, _ = _result_folder(tmp_path)
    job = AnalysisJob.start(tmp_path / "qca", folder, options={"view_step_deg": 30.0},
                            python=_python_that_lingers(tmp_path))
    assert _wait_for(lambda: (job.job_dir / "status.json").is_file() and _state(job.job_dir) != "running", 300)
    assert job.process.poll() is None
    job.cancel()
    assert job.state == "finished"
    assert Path(job.result()["analysis.json"]).is_file()
