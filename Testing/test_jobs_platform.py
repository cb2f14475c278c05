"""The job runner's platform details: progress offsets with any line ending, no console window on Windows."""

from __future__ import annotations

import json

from SDFCARLib import jobs
from SDFCARLib.jobs import ReconstructionJob


def _reader(tmp_path):
    return ReconstructionJob(tmp_path, process=None)  # events() only reads the folder


def test_progress_reader_counts_bytes_with_crlf_and_non_ascii(tmp_path):
    # What a text-mode writer on Windows leaves: "\r\n" line ends; non-ASCII text makes characters != bytes.
    lines = [json.dumps({"step": n, "device": "CPU – ünïcode"}, ensure_ascii=False) for n in range(5)]
    path = tmp_path / "progress.jsonl"
    job = _reader(tmp_path)
    path.write_bytes(("\r\n".join(lines[:2]) + "\r\n" + lines[2][:7]).encode("utf-8"))  # third line half written
    assert [e["step"] for e in job.events()] == [0, 1]
    assert job.events() == []  # nothing complete since: no re-read
    with open(path, "ab") as handle:
        handle.write((lines[2][7:] + "\r\n" + lines[3] + "\r\n").encode("utf-8"))
    assert [e["step"] for e in job.events()] == [2, 3]
    with open(path, "ab") as handle:
        handle.write((lines[4] + "\r\n").encode("utf-8"))
    assert [e["step"] for e in job.events()] == [4]
    assert job._offset == path.stat().st_size
    assert job.poll()["step"] == 4


SMALL = {"steps": 2, "levels": 4, "log2_table_size": 12, "width": 16, "depth": 2, "threads": 1, "seed": 0}


def test_progress_writer_writes_bare_newlines(tmp_path, tiny_geometry, tiny_case, monkeypatch):
    """run_job writes "\\n" only, whatever the platform's text-mode line ending."""
    opened = []
    real_open = open

    def spy_open(file, mode="r", *args, **kwargs):
        if str(file).endswith("progress.jsonl"):
            opened.append((mode, kwargs.get("newline")))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr("builtins.open", spy_open)
    job_dir = jobs.prepare_job(tmp_path / "job", tiny_geometry, tiny_case.masks, SMALL)
    jobs.run_job(job_dir)
    assert opened, "run_job did not open progress.jsonl"
    mode, newline = opened[0]
    assert "b" in mode or newline == "\n", f"progress.jsonl opened in text mode {mode!r}: Windows would write \\r\\n"
    assert b"\r\n" not in (job_dir / "progress.jsonl").read_bytes()


def test_worker_has_no_console_window_on_windows():
    options = jobs.worker_process_options(windows=True)
    assert options["creationflags"] & jobs.CREATE_NO_WINDOW, "PythonSlicer.exe would open a console window"
    assert options["creationflags"] & jobs.CREATE_NEW_PROCESS_GROUP, "cancel must reach the worker's process group"
    assert "start_new_session" not in options
    assert jobs.worker_process_options(windows=False) == {"start_new_session": True}
