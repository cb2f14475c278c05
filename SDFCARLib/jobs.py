"""Background reconstruction jobs: one OS process per reconstruction, driven through a folder.

The GUI module, console scripts and tests all use this runner. A job is a folder:

    job.json         what to run: name, target kind, settings (preset, mode, device, seed, …)
    geometry.json    the GEOM.json of the views and the volume
    view1.npy …      one float32 image per view (mask or line integrals), detector-shaped
    progress.jsonl   written by the worker: one JSON object per line (phase, step, total,
                     loss, l_occ, l_geo, elapsed_s, eta_s, device)
    status.json      made at launch (state "running", atomically: a second launch of the folder is
                     refused), written last: state finished | failed | cancelled, message,
                     traceback, output file paths
    worker.log       the worker's stdout and stderr
    output/          the engine's output files (``outputs.write_reconstruction``)
    INCOMPLETE       present until the job has finished successfully
    cancel           created to ask the worker to stop

Inputs travel as files, never as pickled objects, so the worker can be any Python with SDFCARLib
(inside Slicer: Slicer's own Python). The worker runs in its own process group (session), so
``cancel()`` ends it and every process it started.

    job = ReconstructionJob.start("/tmp/job1", geometry, [mask1, mask2], {"preset": "fast"})
    while job.state == "running":
        info = job.poll()          # latest progress dict or None; never blocks
        ...
    paths = job.result()           # or raises JobFailed with the worker's message and traceback

``run_job(job_dir)`` runs a prepared folder synchronously in this process (tests, small cases).

A folder is run once: a finished, failed or running folder is refused by ``launch()`` and ``run_job()``
(prepare a new folder to run again). A worker outlives its parent (Slicer closed mid-run): it runs to the
end and writes status.json; this API has no way to reattach a handle to a running folder.

The 3D-QCA of a finished result (``analysis.outputs.analyse_result_dir``, several seconds) runs the
same way, so that the Slicer module stays responsive: ``AnalysisJob.start(job_dir, result_dir)``
writes ``analysis_job.json`` (and the view masks as mask<n>.png when given as arrays) instead of
job.json and the view images; progress, status.json, cancel and result() are the same.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import traceback
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Union

import numpy as np

from .geometry import Geometry, GeometryError
from .io import write_json

PathLike = Union[str, Path]
JOB_STATES = ("running", "finished", "failed", "cancelled")
_FINAL_STATES = JOB_STATES[1:]  # status.json says "running" from the launch until the worker writes one of these


class JobFailed(RuntimeError):
    """The worker failed; ``message`` is its error, ``traceback_text`` its traceback (may be empty)."""

    def __init__(self, message: str, traceback_text: str = "") -> None:
        super().__init__(message)
        self.message = message
        self.traceback_text = traceback_text


class JobFolderError(ValueError):
    """A job folder is missing inputs or holds invalid ones; nothing was started."""


# --- job folder ---------------------------------------------------------------------------------------
def prepare_job(job_dir: PathLike, geometry: Geometry, targets: Sequence[np.ndarray], settings: Optional[Dict[str, Any]] = None,
                name: str = "reconstruction", target_kind: str = "mask",
                frames: Optional[Sequence[np.ndarray]] = None,
                frame_intensity: Optional[Sequence[Optional[str]]] = None,
                frame_notes: Optional[Sequence[Optional[str]]] = None) -> Path:
    """Write a job folder (refusing a folder that already holds a job) and validate it. ``frames``:
    the X-ray frames the masks were made from (one per view), for ``frame_evidence``; ``frame_intensity``:
    their DICOM Pixel Intensity Relationship per view (None where not known; ``reconstruct``); ``frame_notes``:
    per view, how the frames were read where it matters (e.g. a LOG run brought to a linear scale), or None;
    report.json keeps them (``frame_notes``)."""
    job_dir = Path(job_dir)
    if (job_dir / "job.json").exists():
        raise JobFolderError(f"{job_dir} already holds a job; choose a new folder for a new job")
    _refuse_used_folder(job_dir)
    if name is not None and not isinstance(name, str):  # else found only when writing, after the whole fit
        raise JobFolderError(f"name is the result's name, a text such as 'patient 8 LAD', got {name!r} "
                             f"({type(name).__name__})")
    given = _check_inputs(geometry, targets, settings if settings is not None else {}, target_kind)[1]
    if frames is not None:
        _check_frames(geometry, frames)
    intensity = _checked_intensity(geometry, frame_intensity)
    notes = _checked_per_view(geometry, frame_notes, "frame_notes", "note on how the view's frame was read (a string)")
    _make_job_folder(job_dir)
    geometry.save(job_dir / "geometry.json")
    for n, target in enumerate(targets, start=1):
        np.save(job_dir / f"view{n}.npy", np.asarray(target, dtype=np.float32))
    for n, frame in enumerate(frames or [], start=1):
        np.save(job_dir / f"frame{n}.npy", np.asarray(frame, dtype=np.float32))
    manifest = {"name": name, "target_kind": target_kind, "settings": given, "views": len(targets)}
    if intensity is not None:
        manifest["frame_intensity"] = intensity
    if notes is not None:
        manifest["frame_notes"] = notes
    write_json(job_dir / "job.json", manifest)
    validate_job_folder(job_dir)
    return job_dir


def _refuse_used_folder(job_dir: Path) -> None:
    """A job writes its inputs (geometry.json, view1.npy …, mask1.png …) and results there: a folder holding anything
    else would have the user's own files replaced, so only a new or empty folder is taken."""
    if job_dir.exists() and not job_dir.is_dir():
        raise JobFolderError(f"{job_dir} is a file, not a folder; choose a new folder for the job")
    held = sorted(p.name for p in job_dir.iterdir()) if job_dir.is_dir() else []
    if held:
        shown = ", ".join(held[:5]) + (f" and {len(held) - 5} more" if len(held) > 5 else "")
        raise JobFolderError(f"{job_dir} already holds files ({shown}); a job writes its inputs and results there: "
                             f"choose a new or empty folder")


def _make_job_folder(job_dir: Path) -> None:
    try:
        job_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # under a file, or in a folder one may not write to
        raise JobFolderError(f"cannot make the job folder {job_dir} ({exc.strerror or exc}); choose a folder you can "
                             "write to") from None


def _check_inputs(geometry: Geometry, targets: Sequence[np.ndarray], settings: Dict[str, Any], target_kind: str):
    from .optimiser import ReconstructionError, validate_targets

    if not isinstance(geometry, Geometry):
        raise JobFolderError(f"geometry must be an SDFCARLib.geometry.Geometry, got {type(geometry).__name__}: read a "
                             "GEOM.json with Geometry.load(path), or make one from a dict with Geometry.from_dict(d)")
    for n, target in enumerate(targets, start=1):
        if isinstance(target, (str, Path)):
            raise JobFolderError(f"view {n}'s image is a path ({target}), not an image: read it first, e.g. with "
                                 "SDFCARLib.io.read_mask(path, view.detector_shape) (read_line_integral for line "
                                 "integrals), and pass the arrays")
    from .settings import settings_from_values

    try:
        checked = settings_from_values(settings)
        validate_targets(targets, geometry, target_kind)
    except ReconstructionError as exc:
        raise JobFolderError(str(exc)) from exc
    # what was given, for job.json, as the checked settings hold it (plain Python values: numpy numbers become
    # JSON's); None leaves a setting at the preset's value, as make_settings has it
    values = checked.to_dict()
    return checked, {key: values[key] for key, value in settings.items() if value is not None}


def _checked_intensity(geometry: Geometry, frame_intensity: Optional[Sequence[Optional[str]]]) -> Optional[List[Optional[str]]]:
    """The frames' Pixel Intensity Relationships as job.json keeps them (one string or None per view)."""
    return _checked_per_view(geometry, frame_intensity, "frame_intensity", "Pixel Intensity Relationship (a string such as 'LIN')")


def _checked_per_view(geometry: Geometry, values: Optional[Sequence[Optional[str]]], key: str,
                      what: str) -> Optional[List[Optional[str]]]:
    """``values`` as job.json keeps them: one string or None per view (None: not given)."""
    if values is None:
        return None
    values = list(values)
    if len(values) != len(geometry.views) or not all(v is None or isinstance(v, str) for v in values):
        raise JobFolderError(f"{key} must give one {what} or None per view: {len(geometry.views)} views, got {values!r}")
    return values


def _check_frames(geometry: Geometry, frames: Sequence[np.ndarray]) -> None:
    if len(frames) != len(geometry.views):
        raise JobFolderError(f"{len(frames)} frame(s) for {len(geometry.views)} views: give one frame per view or none")
    for n, (frame, view) in enumerate(zip(frames, geometry.views), start=1):
        if np.shape(frame) != tuple(view.detector_shape):
            raise JobFolderError(f"frame {n} has shape {np.shape(frame)} but view {n}'s detector is "
                                 f"{tuple(view.detector_shape)}: give the frame the mask was made from")


def _load_job(job_dir: Path):

    manifest_path = job_dir / "job.json"
    if not manifest_path.is_file():
        raise JobFolderError(f"{job_dir} has no job.json; create the folder with prepare_job()")
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise JobFolderError(f"{manifest_path} is not valid JSON: {exc.msg}") from exc
    if not isinstance(manifest, dict) or not isinstance(manifest.get("settings", {}), dict):
        raise JobFolderError(f"{manifest_path} must be an object with a 'settings' object")
    try:
        geometry = Geometry.load(job_dir / "geometry.json")
    except GeometryError as exc:
        raise JobFolderError(str(exc)) from exc
    targets = []
    for n in range(1, len(geometry.views) + 1):
        path = job_dir / f"view{n}.npy"
        if not path.is_file():
            raise JobFolderError(f"{job_dir} lacks {path.name}: one image per view of geometry.json is needed")
        try:
            targets.append(np.load(path, allow_pickle=False))
        except (ValueError, OSError) as exc:
            raise JobFolderError(f"{path} is not a readable .npy image: {exc}") from exc
    kind = manifest.get("target_kind", "mask")
    settings = _check_inputs(geometry, targets, manifest.get("settings", {}), kind)[0]
    frame_paths = [job_dir / f"frame{n}.npy" for n in range(1, len(geometry.views) + 1)]
    frames = None
    if any(p.is_file() for p in frame_paths):
        try:
            frames = [np.load(p, allow_pickle=False) for p in frame_paths]
        except (ValueError, OSError) as exc:
            raise JobFolderError(f"{job_dir}: the frames (frame1.npy …) must be one readable .npy image per view: "
                                 f"{exc}") from exc
        _check_frames(geometry, frames)
    _checked_intensity(geometry, manifest.get("frame_intensity"))
    _checked_per_view(geometry, manifest.get("frame_notes"), "frame_notes", "note on how the view's frame was read (a string)")
    return manifest, geometry, targets, settings, kind, frames


def validate_job_folder(job_dir: PathLike) -> None:
    """Raise JobFolderError unless the folder holds a complete, valid job."""
    _load_job(Path(job_dir))


# --- worker side ------------------------------------------------------------------------------------
def _claim(job_dir: Path) -> None:
    """Mark the folder as taken by one run: status.json made with O_EXCL, so that of two launches (or a launch and a
    run_job) of one folder the second is refused at once, instead of both workers writing the folder."""
    try:
        handle = os.open(job_dir / "status.json", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except FileExistsError:
        raise JobFolderError(_taken_message(job_dir)) from None
    except OSError as exc:
        raise JobFolderError(f"cannot write in the job folder {job_dir} ({exc.strerror or exc}); choose a folder you can "
                             "write to") from None
    with os.fdopen(handle, "w", encoding="utf-8") as out:
        out.write(json.dumps({"state": "running", "message": "", "pid": os.getpid()}) + "\n")


def _taken_message(job_dir: Path) -> str:
    try:
        status = json.loads((job_dir / "status.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        status = {}
    state = status.get("state") if isinstance(status, dict) else None
    if state == "finished":
        return (f"{job_dir} holds a finished job (its results are in {job_dir / 'output'}); to run it again, prepare "
                "a new job folder")
    if state == "running":
        return (f"{job_dir} is already being run (launched by process {status.get('pid', '?')}); wait for that run or "
                "cancel it, or prepare a new job folder")
    return f"{job_dir} has already been run{f' ({state})' if state else ''}; prepare a new job folder"


def _write_status(job_dir: Path, status: Dict[str, Any]) -> None:
    """status.json, unless the job folder was deleted meanwhile (writing would make it again, holding only that)."""
    if job_dir.is_dir():
        try:
            write_json(job_dir / "status.json", status)
        except FileNotFoundError:  # deleted just now
            pass


def _folder_deleted(job_dir: Path) -> JobFolderError:
    return JobFolderError(f"the job folder {job_dir} was deleted while the job ran; nothing was written: run the job "
                          "again in a new folder")


# Whether a SIGTERM should stop the worker at once (the worker's handler reads it): while the results are written,
# there is no step at which the cancel file would be seen, and a kill after the grace time would leave them half written.
_stop_at_once = False


def run_job(job_dir: PathLike, progress: Optional[Callable[[Dict[str, Any]], None]] = None) -> Dict[str, str]:
    """Run a prepared job folder in this process; returns the output paths.

    Progress lines go to progress.jsonl (and to ``progress``), status.json is written at the
    end whatever happens, and the folder keeps its INCOMPLETE marker unless the job finished.
    A folder that has been run (or is being run) is refused at once with JobFolderError.
    """
    job_dir = Path(job_dir)
    if not (job_dir / "job.json").is_file():  # before the claim: nothing is written in a folder that holds no job
        _load_job(job_dir)
    _claim(job_dir)
    return _run_claimed(job_dir, progress)


def _run_claimed(job_dir: Path, progress: Optional[Callable[[Dict[str, Any]], None]] = None) -> Dict[str, str]:
    global _stop_at_once
    from .optimiser import ReconstructionCancelled, reconstruct
    from .outputs import write_reconstruction

    (job_dir / "INCOMPLETE").touch()
    cancel_flag = job_dir / "cancel"
    progress_file, on_progress = _progress_writer(job_dir, progress)
    try:
        manifest, geometry, targets, settings, kind, frames = _load_job(job_dir)
        result = reconstruct(geometry, targets, settings, target_kind=kind, progress=on_progress,
                             cancel=cancel_flag.exists, frames=frames, frame_intensity=manifest.get("frame_intensity"))
        if cancel_flag.exists():
            raise ReconstructionCancelled("cancelled before writing the results")
        if not (job_dir / "job.json").is_file():
            raise _folder_deleted(job_dir)
        on_progress({"phase": "writing", "step": settings.optimisation.total_steps, "total": settings.optimisation.total_steps})
        notes = manifest.get("frame_notes")
        _stop_at_once = True
        try:
            paths = write_reconstruction(result, job_dir / "output", name=manifest.get("name"),
                                         extra={"frame_notes": notes} if notes else None)
        finally:
            _stop_at_once = False
        paths = {k: str(v) for k, v in paths.items()}
        _finished(job_dir, paths, on_progress, settings.optimisation.total_steps)
        return paths
    except ReconstructionCancelled as exc:
        _write_status(job_dir, {"state": "cancelled", "message": str(exc)})
        raise
    except BaseException as exc:  # noqa: BLE001 - the status file must say why, whatever it was
        _failed(job_dir, exc)
        raise
    finally:
        progress_file.close()


def _progress_writer(job_dir: Path, progress: Optional[Callable[[Dict[str, Any]], None]]):
    """(open progress.jsonl, a callback appending one JSON line per progress dict and passing it on)."""
    # Binary: text mode on Windows would write "\r\n", and the reader counts bytes.
    progress_file = open(job_dir / "progress.jsonl", "ab")

    def on_progress(info: Dict[str, Any]) -> None:
        progress_file.write((json.dumps(info) + "\n").encode("utf-8"))
        progress_file.flush()
        if progress is not None:
            progress(info)

    return progress_file, on_progress


def _finished(job_dir: Path, paths: Dict[str, str], on_progress: Callable[[Dict[str, Any]], None], total: int) -> None:
    write_json(job_dir / "status.json", {"state": "finished", "message": "", "outputs": paths})
    (job_dir / "INCOMPLETE").unlink()
    on_progress({"phase": "done", "step": total, "total": total})


def _failed(job_dir: Path, exc: BaseException) -> None:
    _write_status(job_dir, {"state": "failed", "message": f"{type(exc).__name__}: {exc}",
                            "traceback": traceback.format_exc()})


def _worker_main(job_dir: str) -> int:
    from .optimiser import ReconstructionCancelled

    # A polite SIGTERM becomes a cancellation so the worker can record it: at the next step, or at once while the
    # results are written (the staging folder is then removed) or when the job folder is gone.
    def on_term(signum, frame):  # pragma: no cover - exercised through the parent
        try:
            Path(job_dir, "cancel").touch()
        except OSError:
            raise ReconstructionCancelled("cancelled: the job folder was deleted") from None
        if _stop_at_once:
            raise ReconstructionCancelled("cancelled while writing the results; nothing was kept")

    if hasattr(signal, "SIGTERM"):
        signal.signal(signal.SIGTERM, on_term)
    try:
        _run_claimed(Path(job_dir))
    except ReconstructionCancelled:
        return 3
    except BaseException:  # noqa: BLE001 - status.json already holds the error
        return 1
    return 0


# --- parent side --------------------------------------------------------------------------------------
# Windows process-creation flags (winbase.h), spelled out because subprocess only defines them on Windows.
CREATE_NEW_PROCESS_GROUP = 0x00000200
CREATE_NO_WINDOW = 0x08000000
STARTF_USESHOWWINDOW = 0x00000001
SW_HIDE = 0


def worker_process_options(windows: bool) -> Dict[str, Any]:
    """Popen options for the worker: its own process group, and on Windows no console window.

    Inside Slicer the worker is PythonSlicer.exe, a console program: without CREATE_NO_WINDOW
    (and a hidden STARTUPINFO, as slicer.util.launchConsoleProcess does) Windows opens a console
    window for the whole reconstruction.
    """
    if not windows:
        return {"start_new_session": True}  # own process group: cancel reaches every child
    options: Dict[str, Any] = {"creationflags": CREATE_NEW_PROCESS_GROUP | CREATE_NO_WINDOW}
    if hasattr(subprocess, "STARTUPINFO"):  # pragma: no cover - Windows only
        info = subprocess.STARTUPINFO()
        info.dwFlags |= STARTF_USESHOWWINDOW
        info.wShowWindow = SW_HIDE
        options["startupinfo"] = info
    return options


class ReconstructionJob:
    """Handle on a worker process running one job folder (see module docstring)."""

    def __init__(self, job_dir: Path, process: subprocess.Popen) -> None:
        self.job_dir = job_dir
        self.process = process
        self._offset = 0
        self._latest: Optional[Dict[str, Any]] = None
        self._state_override: Optional[str] = None
        self._log = None

    @classmethod
    def start(cls, job_dir: PathLike, geometry: Geometry, targets: Sequence[np.ndarray], settings: Optional[Dict[str, Any]] = None,
              name: str = "reconstruction", target_kind: str = "mask", python: Optional[str] = None,
              frames: Optional[Sequence[np.ndarray]] = None,
              frame_intensity: Optional[Sequence[Optional[str]]] = None,
              frame_notes: Optional[Sequence[Optional[str]]] = None) -> "ReconstructionJob":
        """Write the job folder, validate it, and start the worker. Bad inputs raise before any start."""
        prepare_job(job_dir, geometry, targets, settings, name, target_kind, frames, frame_intensity, frame_notes)
        return cls.launch(job_dir, python)

    @classmethod
    def launch(cls, job_dir: PathLike, python: Optional[str] = None) -> "ReconstructionJob":
        """Start the worker on a prepared folder (validated first). ``python``: interpreter to use."""
        job_dir = Path(job_dir).resolve()
        validate_job_folder(job_dir)
        return cls._spawn(job_dir, "worker", python)

    @classmethod
    def _spawn(cls, job_dir: Path, command: str, python: Optional[str]):
        if (job_dir / "progress.jsonl").exists():
            raise JobFolderError(_taken_message(job_dir))
        _claim(job_dir)  # before the worker starts: it makes its own files only seconds later
        (job_dir / "INCOMPLETE").touch()
        env = dict(os.environ)
        package_root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = package_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env["PYTHONUNBUFFERED"] = "1"
        log = open(job_dir / "worker.log", "ab")
        kwargs: Dict[str, Any] = {"stdout": log, "stderr": subprocess.STDOUT, "stdin": subprocess.DEVNULL, "env": env}
        kwargs.update(worker_process_options(os.name == "nt"))
        try:
            process = subprocess.Popen([python or sys.executable, "-m", "SDFCARLib.jobs", command, str(job_dir)], **kwargs)
        except OSError as exc:  # no such interpreter, or not executable: nothing started, the folder can be launched again
            log.close()
            for name in ("worker.log", "INCOMPLETE", "status.json"):
                (job_dir / name).unlink(missing_ok=True)
            raise JobFolderError(f"cannot start the worker with {python or sys.executable} ({exc.strerror or exc}): give "
                                 "python= a Python interpreter that has SDFCARLib's requirements (inside Slicer, "
                                 "PythonSlicer), or leave it out to use this one") from None
        job = cls(job_dir, process)
        job._log = log
        return job

    @property
    def pid(self) -> int:
        return self.process.pid

    def _status(self) -> Optional[Dict[str, Any]]:
        """status.json once the worker has written its outcome (finished, failed or cancelled), else None."""
        path = self.job_dir / "status.json"
        if not path.is_file():
            return None
        try:
            status = json.loads(path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, OSError):
            return None
        return status if isinstance(status, dict) and status.get("state") in _FINAL_STATES else None

    def _staging_folders(self) -> List[Path]:
        """The staging folders of results being written (``outputs.staged_directory``): a worker killed while writing
        leaves one behind."""
        return list(self.job_dir.glob(".output.sdfcar-*")) if self.job_dir.is_dir() else []

    def _clean_up(self) -> None:
        """After the worker has ended: remove what a killed worker left half written."""
        import shutil

        for folder in self._staging_folders():
            shutil.rmtree(folder, ignore_errors=True)

    def events(self) -> List[Dict[str, Any]]:
        """Progress events written since the last call (in order); never blocks."""
        path = self.job_dir / "progress.jsonl"
        if not path.is_file():
            return []
        # Bytes, so the offset is exact whatever the line endings ("\r\n" from a text-mode writer
        # on Windows) and whatever the characters.
        with open(path, "rb") as handle:
            handle.seek(self._offset)
            chunk = handle.read()
        # Keep a partly written last line for the next call.
        end = chunk.rfind(b"\n")
        if end < 0:
            return []
        self._offset += end + 1
        out = []
        for line in chunk[:end].split(b"\n"):
            if line.strip():
                try:
                    out.append(json.loads(line.decode("utf-8")))
                except (UnicodeDecodeError, json.JSONDecodeError):
                    continue
        if out:
            self._latest = out[-1]
        return out

    def poll(self) -> Optional[Dict[str, Any]]:
        """The latest progress dict (or None before the first); never blocks."""
        self.events()
        return self._latest

    @property
    def state(self) -> str:
        if self._state_override:
            return self._state_override
        if self.process.poll() is None:
            return "running"
        self._close_log()
        status = self._status()
        return status["state"] if status else "failed"

    def wait(self, timeout: Optional[float] = None) -> str:
        """Wait for the worker to end (or ``timeout`` seconds); returns the state."""
        try:
            self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pass
        return self.state

    def cancel(self, grace_s: float = 1.0) -> None:
        """Stop the worker and every process it started; returns within about grace_s + 0.5 s.

        A job that has finished stays finished: its worker may still be exiting when the cancel comes."""
        if self.process.poll() is not None:
            self._clean_up()
            return
        # The signal first: the folder may be gone (deleted by the user), and the worker must stop all the same.
        self._signal_group(signal.SIGTERM if os.name == "posix" else None)
        try:
            (self.job_dir / "cancel").touch()
        except OSError:
            pass
        try:
            self.process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            self._signal_group(signal.SIGKILL if os.name == "posix" else None)
            self.process.wait(timeout=5)
        if os.name == "posix":  # children that outlived the leader
            self._signal_group(signal.SIGKILL)
        self._clean_up()
        status = self._status()
        if status and status.get("state") == "finished":
            for name in ("cancel", "INCOMPLETE"):  # INCOMPLETE: killed between writing status.json and removing it
                (self.job_dir / name).unlink(missing_ok=True)
        elif not status or status.get("state") != "cancelled":
            _write_status(self.job_dir, {"state": "cancelled", "message": "cancelled by the user"})
        self._close_log()

    def _signal_group(self, sig) -> None:
        if os.name == "posix":
            try:
                os.killpg(self.process.pid, sig)
            except (ProcessLookupError, PermissionError):
                pass
        else:  # pragma: no cover - Windows: end the whole tree
            subprocess.run(["taskkill", "/F", "/T", "/PID", str(self.process.pid)], capture_output=True)

    def _close_log(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None

    def result(self) -> Dict[str, str]:
        """Output paths of a finished job; raises JobFailed (with the worker's message) otherwise."""
        state = self.state
        if state == "running":
            raise JobFailed("the job is still running; wait() for it first")
        self._clean_up()
        if not self.job_dir.is_dir():
            raise JobFailed(f"the job folder {self.job_dir} was deleted while the job ran, and its results with it: run "
                            "the job again in a new folder")
        status = self._status() or {}
        if state == "finished":
            return dict(status.get("outputs", {}))
        if state == "cancelled":
            raise JobFailed(status.get("message") or "the job was cancelled")
        message = status.get("message")
        if not message:
            code = self.process.returncode
            if code is not None and code < 0:
                message = (f"the worker process was killed by signal {-code}"
                           + (" (out of memory?)" if -code == getattr(signal, "SIGKILL", 9) else ""))
            else:
                message = f"the worker process exited with status {code} without writing a result; see {self.job_dir / 'worker.log'}"
        raise JobFailed(message, status.get("traceback", ""))


# --- 3D-QCA of a result, in the background ----------------------------------------------------------
ANALYSIS_MANIFEST = "analysis_job.json"


def free_analysis_folder(result_dir: PathLike) -> Path:
    """``result_dir/analysis``, or analysis-2, analysis-3, … when taken: an earlier analysis is never replaced."""
    result_dir = Path(result_dir)
    candidate, n = result_dir / "analysis", 1
    while candidate.exists():
        n += 1
        candidate = result_dir / f"analysis-{n}"
    return candidate


def _claim_analysis_folder(result_dir: Path) -> Path:
    """A free analysis folder (``free_analysis_folder``), made now (mkdir is atomic): two analyses of one result
    started together then get two folders instead of the second failing at its end on the first's files."""
    while True:
        candidate = free_analysis_folder(result_dir)
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:  # taken between the look and the mkdir
            continue
        except OSError as exc:
            raise JobFolderError(f"cannot make the analysis folder {candidate} ({exc.strerror or exc}): the result folder "
                                 f"{result_dir} must be writable, or give out_dir a folder you can write to") from None


def _release_analysis_folder(manifest: Dict[str, Any]) -> None:
    """Remove the folder ``_claim_analysis_folder`` made, when the analysis wrote nothing into it."""
    if manifest.get("out_dir_claimed"):
        try:
            Path(manifest["out_dir"]).rmdir()  # only if empty
        except OSError:
            pass


def job_masks(job_dir: PathLike) -> Optional[List[np.ndarray]]:
    """The view masks of a reconstruction job folder (view<n>.npy), or None when it ran on line integrals
    or its files are gone."""
    job_dir = Path(job_dir)
    try:
        manifest = json.loads((job_dir / "job.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(manifest, dict) or manifest.get("target_kind", "mask") != "mask":
        return None
    count = int(manifest.get("views") or 0)
    paths = [job_dir / f"view{n}.npy" for n in range(1, count + 1)]
    if not paths or not all(p.is_file() for p in paths):
        return None
    try:
        return [np.load(p, allow_pickle=False) != 0 for p in paths]
    except (ValueError, OSError):
        return None


def job_frames(job_dir: PathLike) -> Optional[List[str]]:
    """The paths of the X-ray frames stored with a reconstruction job folder (frame<n>.npy, one per
    view), or None when the job had none, its files are gone, or they are binary images (the sample
    case shows its masks as frames: no intensity profile to fit)."""
    job_dir = Path(job_dir)
    try:
        count = int(json.loads((job_dir / "job.json").read_text(encoding="utf-8")).get("views") or 0)
    except (OSError, ValueError, AttributeError, TypeError):
        return None
    paths = [job_dir / f"frame{n}.npy" for n in range(1, count + 1)]
    if not paths or not all(p.is_file() for p in paths):
        return None
    from .evidence import is_binary_image

    try:
        if any(is_binary_image(np.load(p, allow_pickle=False)) for p in paths):
            return None
    except (ValueError, OSError):
        return None
    return [str(p) for p in paths]


def prepare_analysis_job(job_dir: PathLike, result_dir: PathLike, out_dir: Optional[PathLike] = None,
                         masks: Optional[Sequence[Any]] = None, options: Optional[Dict[str, Any]] = None) -> Path:
    """Write an analysis job folder: the result to analyse, where to write, the view masks (arrays are
    written as mask<n>.png; paths are kept), ``analyse_result_dir`` keyword options."""
    from .io import write_mask_png

    job_dir = Path(job_dir)
    result_dir = Path(result_dir).absolute()
    if (job_dir / "job.json").exists() or (job_dir / ANALYSIS_MANIFEST).exists():
        raise JobFolderError(f"{job_dir} already holds a job; choose a new folder for a new job")
    _refuse_used_folder(job_dir)
    if not result_dir.is_dir():
        raise JobFolderError(f"result folder {result_dir} does not exist; the result's files were moved or deleted")
    if not any((result_dir / f).is_file() for f in ("occupancy.nrrd", "segmentation.seg.nrrd")):
        raise JobFolderError(f"{result_dir} holds neither occupancy.nrrd nor segmentation.seg.nrrd: it is not the "
                             "folder of a reconstruction")
    _make_job_folder(job_dir)
    out = Path(out_dir).absolute() if out_dir is not None else _claim_analysis_folder(result_dir)
    mask_files: Optional[List[str]] = None
    if masks is not None:
        mask_files = []
        for n, mask in enumerate(masks, start=1):
            if isinstance(mask, (str, Path)):
                mask_files.append(str(Path(mask).absolute()))
            else:
                mask_files.append(str(write_mask_png(job_dir / f"mask{n}.png", np.asarray(mask))))
    write_json(job_dir / ANALYSIS_MANIFEST, {"result_dir": str(result_dir), "out_dir": str(out), "masks": mask_files,
                                             "options": dict(options or {}), "out_dir_claimed": out_dir is None})
    return job_dir


def _load_analysis_job(job_dir: Path) -> Dict[str, Any]:
    path = job_dir / ANALYSIS_MANIFEST
    if not path.is_file():
        raise JobFolderError(f"{job_dir} has no {ANALYSIS_MANIFEST}; create the folder with prepare_analysis_job()")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise JobFolderError(f"{path} is not valid JSON: {exc.msg}") from exc
    if not isinstance(manifest, dict) or not manifest.get("result_dir") or not manifest.get("out_dir"):
        raise JobFolderError(f"{path} must name result_dir and out_dir")
    return manifest


def run_analysis_job(job_dir: PathLike, progress: Optional[Callable[[Dict[str, Any]], None]] = None) -> Dict[str, str]:
    """Run a prepared analysis job folder in this process; returns {file name: path} and "folder"."""
    job_dir = Path(job_dir)
    _claim(job_dir)
    return _run_analysis_claimed(job_dir, progress)


def _run_analysis_claimed(job_dir: Path, progress: Optional[Callable[[Dict[str, Any]], None]] = None) -> Dict[str, str]:
    from .analysis.outputs import analyse_result_dir
    from .optimiser import ReconstructionCancelled

    (job_dir / "INCOMPLETE").touch()
    progress_file, on_progress = _progress_writer(job_dir, progress)
    manifest: Dict[str, Any] = {}
    try:
        manifest = _load_analysis_job(job_dir)
        on_progress({"phase": "analyse", "step": 0, "total": 1})
        files = analyse_result_dir(manifest["result_dir"], manifest["out_dir"], overwrite=False,
                                   masks=manifest.get("masks") or None, **dict(manifest.get("options") or {}))
        paths = {name: str(path) for name, path in files.items()}
        paths["folder"] = str(Path(manifest["out_dir"]))
        _finished(job_dir, paths, on_progress, 1)
        return paths
    except ReconstructionCancelled as exc:
        _release_analysis_folder(manifest)
        _write_status(job_dir, {"state": "cancelled", "message": str(exc)})
        raise
    except BaseException as exc:  # noqa: BLE001 - the status file must say why, whatever it was
        _release_analysis_folder(manifest)
        _failed(job_dir, exc)
        raise
    finally:
        progress_file.close()


def _analysis_main(job_dir: str) -> int:
    from .optimiser import ReconstructionCancelled

    # The analysis has no step to stop at: a SIGTERM stops it at once, and the staging folder of its files is removed
    # on the way out (a SIGKILL would leave it beside the result).
    def on_term(signum, frame):  # pragma: no cover - exercised through the parent
        raise ReconstructionCancelled("cancelled by the user; the analysis was not written")

    if hasattr(signal, "SIGTERM"):
        signal.signal(signal.SIGTERM, on_term)
    try:
        _run_analysis_claimed(Path(job_dir))
    except BaseException:  # noqa: BLE001 - status.json already holds the error
        return 1
    return 0


class AnalysisJob(ReconstructionJob):
    """Handle on a worker process running the 3D-QCA of a result (module docstring)."""

    @classmethod
    def start(cls, job_dir: PathLike, result_dir: PathLike, out_dir: Optional[PathLike] = None,  # type: ignore[override]
              masks: Optional[Sequence[Any]] = None, options: Optional[Dict[str, Any]] = None,
              python: Optional[str] = None) -> "AnalysisJob":
        """Write the job folder and start the worker. Bad inputs raise before any start."""
        prepare_analysis_job(job_dir, result_dir, out_dir, masks, options)
        return cls.launch(job_dir, python)

    @classmethod
    def launch(cls, job_dir: PathLike, python: Optional[str] = None) -> "AnalysisJob":
        job_dir = Path(job_dir).resolve()
        _load_analysis_job(job_dir)
        return cls._spawn(job_dir, "analyse", python)

    def _manifest(self) -> Dict[str, Any]:
        try:
            return _load_analysis_job(self.job_dir)
        except (JobFolderError, OSError):
            return {}

    def _staging_folders(self) -> List[Path]:
        out = self._manifest().get("out_dir")
        return list(Path(out).parent.glob(f".{Path(out).name}.sdfcar-*")) if out and Path(out).parent.is_dir() else []

    def _clean_up(self) -> None:
        super()._clean_up()
        if self._status() is None or self._status().get("state") != "finished":
            _release_analysis_folder(self._manifest())


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) == 2 and argv[0] == "worker":
        return _worker_main(argv[1])
    if len(argv) == 2 and argv[0] == "analyse":
        return _analysis_main(argv[1])
    sys.stderr.write("usage: python -m SDFCARLib.jobs worker|analyse JOB_DIR\n")
    return 2


if __name__ == "__main__":
    sys.exit(main())
