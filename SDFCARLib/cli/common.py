"""What the commands share: progress bar and Ctrl-C cancellation, metric tables, settings from the options, file helpers."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np

from ..calibration import calibration_lines
from ..settings import GROUND_TRUTH_METRICS, METRICS, make_settings, parse_setting_overrides
from ..qa import ensemble_choice_line, pieces_line

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_CANCELLED = 0, 1, 2, 130
EXIT_TERMINATED = 143  # 128 + SIGTERM, as a shell reports a process ended by it


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a batch system's time limit): raised at once, like a second Ctrl-C, so that the staging
    folders of unfinished writes are removed on the way out (``outputs.staged_directory``)."""


class PartlyWritten(KeyboardInterrupt):
    """Ctrl-C or SIGTERM after some results were written; ``written`` says what is kept and what is not."""

    def __init__(self, written: str, terminated: bool = False) -> None:
        super().__init__(written)
        self.written = written
        self.terminated = terminated


class _HandlerWhileActive:
    """A context in which the signal named ``SIGNAL`` goes to ``_handle`` (in the main thread, where Python delivers
    signals; elsewhere, or where the platform lacks the signal, nothing changes); the previous handler comes back after."""

    SIGNAL = ""

    def __init__(self) -> None:
        self._previous: Any = None

    def _handle(self, signum, frame) -> None:
        raise NotImplementedError

    def __enter__(self):
        number = getattr(signal, self.SIGNAL, None)
        if number is not None and threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc_info) -> None:
        if self._previous is not None:
            signal.signal(getattr(signal, self.SIGNAL), self._previous)
            self._previous = None


class TerminateOnSigterm(_HandlerWhileActive):
    """While active, SIGTERM raises ``Terminated`` in the main thread (the default would end the process at once,
    leaving half-written staging folders beside the user's output)."""

    SIGNAL = "SIGTERM"

    def _handle(self, signum, frame) -> None:
        raise Terminated


METRIC_ROWS = [(key, METRICS[key].title + (f" ({METRICS[key].unit})" if METRICS[key].unit else ""))
               for key in GROUND_TRUTH_METRICS]


class ProgressBar:
    """Turns ``reconstruct(progress=…)`` reports into a tqdm bar on stderr (step, loss, ETA)."""

    def __init__(self, enabled: bool = True, stream=None) -> None:
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.bar = None

    def __call__(self, info: Dict[str, Any]) -> None:
        if not self.enabled:
            return
        phase = info.get("phase")
        if phase == "setup":
            print("preparing the reconstruction (visual hull, projectors)…", file=self.stream)
        elif phase == "optimise":
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=int(info["total"]), desc="optimising", unit="step", file=self.stream,
                                dynamic_ncols=True, mininterval=0.5)
            self.bar.set_postfix(loss=f"{info.get('loss', float('nan')):.4f}", refresh=False)
            self.bar.update(int(info["step"]) - self.bar.n)
        elif phase == "output":
            self.close()
            print("evaluating the field on the grid…", file=self.stream)
        elif phase == "prune":
            print("pruning the branches that no mask pixel needs…", file=self.stream)
        elif phase == "warning":
            print(f"warning: {info.get('message', '')}", file=self.stream)
        elif phase == "calibrate":
            print(f"calibrating the views' poses: {info.get('message', '')}", file=self.stream)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class CancelOnInterrupt(_HandlerWhileActive):
    """While active, Ctrl-C asks the reconstruction to stop at its next step (a second one aborts). With ``at_once``
    (set while the results are written: no step there to stop at) the first one aborts."""

    SIGNAL = "SIGINT"

    def __init__(self) -> None:
        super().__init__()
        self.requested = False
        self.at_once = False

    def __call__(self) -> bool:
        return self.requested

    def _handle(self, signum, frame) -> None:
        if self.requested or self.at_once:
            raise KeyboardInterrupt
        self.requested = True
        print("\ncancelling… (press Ctrl-C again to abort at once)", file=sys.stderr)


def run_reconstruction(geometry, targets, settings, target_kind: str, show_progress: bool, frames=None,
                       frame_intensity=None, cancel: Optional[CancelOnInterrupt] = None):
    """``reconstruct`` with a progress bar, Ctrl-C asking it to stop; ``cancel``: an active CancelOnInterrupt of the
    caller's (that then also covers what the caller does after the fit), else one for the fit alone."""
    from ..optimiser import reconstruct

    bar = ProgressBar(show_progress)
    try:
        if cancel is not None:
            return reconstruct(geometry, targets, settings, target_kind=target_kind, progress=bar, cancel=cancel,
                               frames=frames, frame_intensity=frame_intensity)
        with CancelOnInterrupt() as cancel:
            return reconstruct(geometry, targets, settings, target_kind=target_kind, progress=bar, cancel=cancel,
                               frames=frames, frame_intensity=frame_intensity)
    finally:
        bar.close()


def _fmt(value: Any) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    if isinstance(value, (list, tuple)):
        return " / ".join(_fmt(v) for v in value)
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return f"{float(value):.3f}"


def metrics_table(columns: Dict[str, Dict[str, Any]]) -> str:
    """A plain-text table: one row per metric, one column per method."""
    names = list(columns)
    rows = [("metric", *names)]
    for key, title in METRIC_ROWS + [("reprojection_dice", "reprojection Dice"), ("voxels_predicted", "voxels")]:
        if any(key in columns[n] for n in names):
            rows.append((title, *(_fmt(columns[n].get(key)) for n in names)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths)))
                     for r in rows)


def print_metrics(metrics: Dict[str, Dict[str, Any]], stream=None) -> None:
    columns = {"reconstruction" if "visual_hull" in metrics else "prediction": metrics["prediction"]}
    if "visual_hull" in metrics:
        columns["visual hull (baseline)"] = metrics["visual_hull"]
    print(metrics_table(columns), file=stream or sys.stdout)


# the settings that reconstruct/demo set by their own flags, so that --set refuses them (and its help leaves them out)
SETTINGS_SET_BY_FLAGS = {**{key: f"use --{key}" for key in ("mode", "device", "seed", "steps", "threads", "preset")},
                         "calibrate": "use --correct-motion"}


def settings_from_args(args: argparse.Namespace):
    named = {"mode": args.mode, "device": args.device, "seed": args.seed, "steps": args.steps, "threads": args.threads}
    reserved = SETTINGS_SET_BY_FLAGS
    if getattr(args, "correct_motion", False):
        named["calibrate"] = True
    return make_settings(args.preset, **{**parse_setting_overrides(args.overrides, reserved), **named})


def absolute_path(path: Optional[str]) -> Optional[str]:
    return str(Path(path).absolute()) if path else None


def load_geometry(path: str):
    from ..geometry import Geometry

    return Geometry.load(path)


def print_provenance(provenance: Dict[str, Any], warnings: bool = True, volume: bool = True) -> None:
    """Every geometry value read from DICOM and where it came from, so a clinician can check it (and, with
    ``warnings``, the geometry's warnings: ``reconstruct`` leaves them to the fit, which gives them too).
    ``volume`` False: the grid is not printed (it is about to be placed on the masks, which prints the grid used)."""
    for n, view in enumerate(provenance.get("views", []), start=1):
        frame = view.get("frame", {})
        print(f"view {n}: {view.get('file')} frame {frame.get('index')} ({frame.get('reason', '')})", file=sys.stderr)
        for name, entry in view.get("fields", {}).items():
            print(f"  {name} = {_fmt(entry.get('value'))}  [{entry.get('source', '?')}]", file=sys.stderr)
        for note in view.get("notes", []):
            print(f"  note: {note}", file=sys.stderr)
    grid = provenance.get("volume") if volume else None
    if grid:
        print(f"volume: {grid.get('value')}  [{grid.get('source')}]", file=sys.stderr)
    for warning in provenance.get("warnings", []) if warnings else []:
        print(f"warning: {warning}", file=sys.stderr)


def print_summary(files: Dict[str, Path]) -> None:
    report = json.loads(files["report"].read_text(encoding="utf-8"))
    timings = report.get("timings_s", {})
    total = timings.get("total")
    print(f"{report.get('method', 'reconstruction')}: {report.get('segmented_voxels', 0)} voxels segmented in "
          f"{total if total is None else round(float(total), 1)} s on {report.get('device', '?')}")
    print(f"reprojection Dice per view: {_fmt(report.get('reprojection_dice'))}")
    pieces = pieces_line(report)
    if pieces:
        print(pieces)
    choice = ensemble_choice_line(report)
    if choice:
        print(choice)
    for line in calibration_lines(report):
        print(line)
    if "metrics" in report:
        print_metrics(report["metrics"])
    warnings = report.get("warnings", [])
    if warnings:  # with progress on they were printed as they arose too: the header says these are the run's record
        print(f"{len(warnings)} warning(s) of this run (report.json → warnings):", file=sys.stderr)
    for message in warnings:
        print(f"warning: {message}", file=sys.stderr)
    print(f"results in {files['report'].parent}: {', '.join(sorted(p.name for p in files.values()))}")
