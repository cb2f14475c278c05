"""Running a benchmark: the Dask tasks (prepare a case; reconstruct and score one case × mode),
the Dask client (LocalCluster or ``--scheduler``), and ``run_benchmark``, which resumes from
``results.csv``, runs what is missing and writes the summary and figures."""

from __future__ import annotations

import datetime
import json
import logging
import os
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from tqdm import tqdm

from ..cli_types import one_line
from ..figures import save_overlay_figure
from ..geometry import rotation_matrix
from ..io import write_text_atomically
from .cases import CaseSpec, GridOptions, PreparedCase, prepare_case
from .config import BenchmarkConfig, check_config
from .errors import BenchmarkError
from .registry import HULL, METRIC_COLUMNS
from .report import all_versions, machine_info, write_box_plots, write_summary
from .store import ResultsFile, safe_name, update_run_record, latest_rows
from ..settings import PROTOCOLS, make_settings


# --- one task: a case × mode ------------------------------------------------------------------------
def _reconstruct(geometry, targets, settings, target_kind, frames=None, frame_intensity=None):
    """The optimiser call (a seam: tests replace ``SDFCARLib.benchmark.run._reconstruct`` to inject failures).
    ``frames``: the realistic protocols' angiograms, fitted where ``frame_evidence`` is set and their
    ``frame_intensity`` allows (none off display-processed frames)."""
    from ..optimiser import reconstruct

    return reconstruct(geometry, targets, settings, target_kind=target_kind, frames=frames,
                       frame_intensity=frame_intensity)


def _pack(mask: np.ndarray) -> Tuple[bytes, Tuple[int, ...]]:
    return np.packbits(np.asarray(mask, bool).reshape(-1)).tobytes(), tuple(mask.shape)


def _unpack(packed: Tuple[bytes, Tuple[int, ...]]) -> np.ndarray:
    data, shape = packed
    n = int(np.prod(shape))
    return np.unpackbits(np.frombuffer(data, np.uint8), count=n).astype(bool).reshape(shape)


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except Exception:  # not inside a Dask worker
        return "local"


def _base_row(spec: CaseSpec, mode: str, task: Dict[str, Any]) -> Dict[str, Any]:
    return {"suite": spec.suite, "tree": spec.tree, "case": spec.name, "seed": spec.seed, "protocol": task["protocol"],
            "target_kind": PROTOCOLS[task["protocol"]][1], "mode": mode, "preset": task["preset"],
            "steps": task.get("steps_effective", ""), "overrides": task["overrides_text"], "config": task["config"]}


def prepare_task(spec: CaseSpec, protocol: str, grid: GridOptions) -> Dict[str, Any]:
    """Dask task: the prepared case, or the error that stopped it (so dependents record it)."""
    try:
        return {"case": prepare_case(spec, protocol, grid)}
    except Exception as exc:
        return {"error": f"case preparation failed: {one_line(exc, with_type=True)}",
                "traceback": traceback.format_exc()}


def run_task(prepared: Dict[str, Any], spec: CaseSpec, mode: str, task: Dict[str, Any]) -> Dict[str, Any]:
    """Dask task: reconstruct one case with one mode (or the hull) and score it. Never raises."""
    import torch

    row = _base_row(spec, mode, task)
    row.update(worker=_worker_name(), status="failed")
    if "error" in prepared:
        row["error"] = prepared["error"]
        return {"row": row, "traceback": prepared["traceback"]}
    case: PreparedCase = prepared["case"]
    row["prepare_s"] = case.prepare_s
    threads = task.get("torch_threads")
    previous_threads = torch.get_num_threads()
    try:
        if threads:
            torch.set_num_threads(int(threads))  # this worker's share of the cores
        grid, views = case.geometry.volume, case.geometry.views
        t0 = time.perf_counter()
        if mode == HULL:
            from ..hull import visual_hull

            prediction = visual_hull(case.masks, views, grid)
            row["device"] = "cpu (numpy)"
            row["wall_s"] = time.perf_counter() - t0
        else:
            settings = make_settings(task["preset"], mode=mode, seed=spec.seed, steps=task["steps"], **task["overrides"])
            row["steps"] = settings.optimisation.steps
            result = _reconstruct(case.geometry, case.targets, settings, case.target_kind, case.frames,
                                  case.frame_intensity)
            prediction = result.segmentation
            row["device"] = result.report.get("device", "")
            row["wall_s"] = float(result.report.get("timings_s", {}).get("total", time.perf_counter() - t0))
            row.update(_calibration_columns(result.report.get("calibration"), case.info.get("realistic")))
        t1 = time.perf_counter()
        from ..metrics import evaluate

        metrics = evaluate(prediction, case.label, grid, views, case.masks)
        row["eval_s"] = time.perf_counter() - t1
        for key in METRIC_COLUMNS:
            if key in metrics:
                row[key] = metrics[key]
        for n, value in enumerate(metrics.get("reprojection_dice", []), start=1):
            row[f"reprojection_dice_view{n}"] = value
        realistic = case.info.get("realistic")
        if realistic:  # what the input masks lost, and how far the heart moved
            for n, view in enumerate(realistic["views"], start=1):
                row[f"input_mask_cldice_view{n}"] = view["mask_cldice"]
            row["motion_mm"] = max(float(np.linalg.norm(m["translation_mm"])) for m in realistic["motion"])
            row["motion_deg"] = max(float(np.linalg.norm(m["rotation_deg"])) for m in realistic["motion"])
            if row["motion_mm"] > 0 or row["motion_deg"] > 0:  # the tree's depth along view 1's axis is barely seen
                from ..metrics import depth_aligned_metrics

                row.update(depth_aligned_metrics(prediction, case.label, grid, views[0].detector_direction))
        row["status"], row["error"] = "ok", ""
        out: Dict[str, Any] = {"row": row}
        if task.get("overlay"):
            out["overlay"] = (_pack(prediction), _pack(case.label))
        return out
    except Exception as exc:
        row["error"] = one_line(exc, with_type=True)
        return {"row": row, "traceback": traceback.format_exc()}
    finally:
        torch.set_num_threads(previous_threads)


def _calibration_columns(calibration: Optional[Dict[str, Any]], realistic: Optional[Dict[str, Any]]) -> Dict[str, float]:
    """View 2's motion found by the calibration (shift, in-plane and tilt rotation) and, for realistic
    cases, the simulated motion's same components (what the search can recover)."""
    found = next((v for v in (calibration or {}).get("views", []) if v.get("view") == 2 and "shift_mm" in v), None)
    if found is None:
        return {}
    out = {"calibration_shift_mm_view2": float(found["shift_mm"])}
    for name in ("rotation_in_plane", "rotation_tilt"):
        if name in found:
            out[f"calibration_{name}_deg_view2"] = float(found[name]["value"])
    if realistic and len(realistic.get("motion", [])) > 1:
        motion = realistic["motion"][1]
        rotation = np.asarray(motion["rotation_deg"], float)
        # the simulated motion turns about the isocenter; the search about the region's centre c:
        # x → R x + t = R (x − c) + c + (t + R c − c)
        centre = np.asarray(found.get("rotation_centre_mm", (0.0, 0.0, 0.0)), float)
        shift = np.asarray(motion["translation_mm"], float) + rotation_matrix(rotation) @ centre - centre
        out["true_shift_mm_view2"] = float(np.dot(shift, found["direction_lps"]))
        for name in ("rotation_in_plane", "rotation_tilt"):
            if name in found:
                out[f"true_{name}_deg_view2"] = float(np.dot(rotation, found[name]["axis_lps"]))
    return out


def task_options(config: BenchmarkConfig) -> Dict[str, Any]:
    """What every ``run_task`` of a run shares (small, picklable)."""
    modes = [m for m in config.modes if m != HULL]
    steps = make_settings(config.preset, mode=modes[0], steps=config.steps, **config.overrides).optimisation.steps if modes else ""
    return {"protocol": config.protocol, "preset": config.preset, "steps": config.steps, "steps_effective": steps,
            "overrides": dict(config.overrides),
            "overrides_text": json.dumps(config.overrides, sort_keys=True) if config.overrides else "",
            "config": config.config_id(), "torch_threads": config.threads_per_worker, "overlay": False}


# --- the run --------------------------------------------------------------------------------------
@dataclass
class BenchmarkOutcome:
    """What ``run_benchmark`` did: rows written, failed and skipped, and the files it wrote."""

    out: Path
    rows_written: int
    failed: int
    skipped: int
    summary: Path
    figures: List[Path]


WORKER_ENVIRON_KEY = "distributed.nanny.pre-spawn-environ"
UNSET_WORKER_ENVIRON = ("MALLOC_TRIM_THRESHOLD_",)


def _start_client(config: BenchmarkConfig, processes: bool):
    """A Dask client on ``--scheduler`` or on a new LocalCluster; (client, cluster or None, description)."""
    from distributed import Client, LocalCluster

    if config.scheduler:
        try:
            client = Client(config.scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise BenchmarkError(f"cannot reach the Dask scheduler at {config.scheduler} ({exc}); start it "
                                 "(dask scheduler / dask worker) or leave out --scheduler for a local cluster") from None
        try:
            client.wait_for_workers(1, timeout=60)
        except TimeoutError:
            client.close()
            raise BenchmarkError(f"the Dask scheduler at {config.scheduler} has no worker after 60 s; start workers "
                                 f"(dask worker {config.scheduler}) and run the command again") from None
        slots = client.nthreads()
        description = f"scheduler {config.scheduler}: {len(slots)} worker(s), {sum(slots.values())} task slots"
        return client, None, description
    import dask

    cores = os.cpu_count() or 1
    workers = config.workers or max(1, cores // config.threads_per_worker)
    # One task slot per worker; the worker's cores go to torch inside the task (threads_per_worker).
    # Dask's nanny starts each worker with MALLOC_TRIM_THRESHOLD_ set, which turns off glibc's adaptive mmap threshold:
    # every large tensor is then mapped and unmapped afresh and a fit's step takes twice as long (RESULTS §70a).
    with dask.config.set({f"{WORKER_ENVIRON_KEY}.{name}": None for name in UNSET_WORKER_ENVIRON}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=":0",
                               silence_logs=logging.ERROR)
    client = Client(cluster)
    description = (f"LocalCluster: {workers} {'process' if processes else 'thread'} worker(s), one case at a time each, "
                   f"{config.threads_per_worker} torch thread(s) per case")
    return client, cluster, description


def _workers_with_slow_malloc(client) -> List[str]:
    """Addresses of the workers whose environment carries a variable ``UNSET_WORKER_ENVIRON`` names."""
    try:
        environ = client.run(lambda: [name for name in UNSET_WORKER_ENVIRON if os.environ.get(name) is not None])
    except Exception:  # a worker that cannot run the check only costs the warning
        return []
    return sorted(address for address, names in environ.items() if names)


def run_benchmark(config: BenchmarkConfig, processes: bool = True, argv: Optional[Sequence[str]] = None,
                  log: Callable[[str], None] = lambda text: print(text, file=sys.stderr)) -> BenchmarkOutcome:
    """Run (or resume) a benchmark and write results.csv, summary.md, run.json and figures in ``config.out``.

    ``processes`` False runs the LocalCluster's workers as threads of this process (tests).
    """
    cases = check_config(config)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    results = ResultsFile(out / "results.csv")
    config_id = config.config_id()
    all_modes = [HULL] + [m for m in config.modes if m != HULL]
    case_names = {c.name for c in cases}

    done = latest_rows(r for r in results.rows() if r.get("config") == config_id)
    todo: List[Tuple[CaseSpec, List[str]]] = []
    skipped = 0
    for spec in cases:
        modes = []
        for mode in all_modes:
            previous = done.get((spec.suite, spec.name, mode, config_id))
            if previous is not None and (previous["status"] == "ok" or not config.retry_failed):
                skipped += 1
            else:
                modes.append(mode)
        if modes:
            todo.append((spec, modes))

    run_id = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
    record: Dict[str, Any] = {
        "run_id": run_id, "command": config.command_line(), "argv": list(argv) if argv is not None else None,
        "config_id": config_id, "configuration": config.identity(), "suite": config.suite,
        "modes": list(config.modes), "cases": [c.name for c in cases], "seeds": [c.seed for c in cases],
        "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "versions": all_versions(), "machine": machine_info(),
        "cluster": {"description": "none (nothing to run)"}, "skipped_rows": skipped,
    }
    update_run_record(out, record)
    n_tasks = sum(len(m) for _, m in todo)
    written = failed = 0
    overlay_figures: List[Path] = []
    if n_tasks:
        log(f"benchmark: {len(todo)} case(s), {n_tasks} run(s) to do ({skipped} already in {results.path.name}) → {out}")
        try:
            written, failed, overlay_figures = _execute(config, todo, results, record, processes, log)
        except BaseException as exc:  # Ctrl-C, a lost scheduler: run.json says the run stopped and what it kept
            kept = [r for r in results.rows() if r.get("run_id") == run_id]
            record.update(interrupted=one_line(exc, with_type=True),
                          stopped=datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                          rows_written=len(kept), rows_failed=sum(r["status"] != "ok" for r in kept))
            update_run_record(out, record)
            raise
    else:
        log(f"benchmark: all {skipped} run(s) already in {results.path} — nothing to run")

    rows = [r for key, r in latest_rows(results.rows()).items()
            if key[3] == config_id and key[1] in case_names and key[2] in all_modes]
    order = {c.name: c.index for c in cases}
    rows.sort(key=lambda r: (order[r["case"]], all_modes.index(r["mode"])))
    record.update(finished=datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                  rows_written=written, rows_failed=failed)
    update_run_record(out, record)
    summary = write_summary(out, config, rows, record)
    figures = write_box_plots(out, rows, all_modes) + overlay_figures
    return BenchmarkOutcome(out, written, failed, skipped, summary, figures)


def _execute(config: BenchmarkConfig, todo: List[Tuple[CaseSpec, List[str]]], results: ResultsFile,
             record: Dict[str, Any], processes: bool, log: Callable[[str], None]) -> Tuple[int, int, List[Path]]:
    from distributed import as_completed

    client, cluster, description = _start_client(config, processes)
    slowed = _workers_with_slow_malloc(client) if config.scheduler else []  # the local cluster's workers start without it
    if slowed:
        log(f"benchmark: warning: {len(slowed)} worker(s) run with {', '.join(UNSET_WORKER_ENVIRON)} set (Dask's nanny sets it); "
            "glibc then maps every large tensor afresh and each fit takes about twice as long — start the workers "
            "without a nanny (dask worker --no-nanny ADDRESS) or leave out --scheduler")
    record["cluster"] = {"description": description, "scheduler": config.scheduler,
                         "workers": _worker_machines(client)}
    update_run_record(config.out, record)
    task = task_options(config)
    errors_dir = Path(config.out) / "errors"
    figures_dir = Path(config.out) / "figures"
    token = record["run_id"]
    futures = {}
    written = failed = 0
    overlays: List[Path] = []
    bar = None
    try:
        for spec, modes in todo:
            prepared = client.submit(prepare_task, spec, config.protocol, config.grid, key=f"sdfcar-prepare-{token}-{spec.index}",
                                     priority=-spec.index)
            for mode in modes:
                task_mode = dict(task, overlay=spec.index < config.overlays)
                future = client.submit(run_task, prepared, spec, mode, task_mode, key=f"sdfcar-run-{token}-{spec.index}-{mode}",
                                       priority=-spec.index)
                futures[future] = (spec, mode)
            del prepared  # held by its dependents, released with them
        bar = tqdm(total=len(futures), desc="benchmark", unit="run", disable=not config.progress, file=sys.stderr,
                   dynamic_ncols=True)
        for future in as_completed(list(futures)):
            spec, mode = futures.pop(future)
            if future.status == "finished":
                outcome = future.result()
            else:  # the task itself died (worker lost, unpicklable result…)
                exc = future.exception()
                tb = "".join(traceback.format_exception(type(exc), exc, future.traceback()))
                row = _base_row(spec, mode, task)
                row.update(status="failed", error=f"task failed: {one_line(exc, with_type=True)}")
                outcome = {"row": row, "traceback": tb}
            future.release()
            row = outcome["row"]
            row["finished_at"] = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
            row["run_id"] = token  # the run.json record of this invocation: its machine, workers and command
            if row["status"] != "ok":
                failed += 1
                path = errors_dir / f"{safe_name(spec.name)}__{safe_name(mode)}.txt"
                write_text_atomically(path, f"case {spec.name}, mode {mode}\n{row.get('error', '')}\n\n{outcome.get('traceback', '')}")
                row["traceback_file"] = str(path.relative_to(config.out))
                bar.write(f"failed: {spec.name} × {mode}: {row.get('error', '')}", file=sys.stderr)
            results.append(row)
            written += 1
            if "overlay" in outcome:
                path = figures_dir / f"overlay_{safe_name(spec.name)}_{safe_name(mode)}.png"
                save_overlay_figure(path, _unpack(outcome["overlay"][0]), _unpack(outcome["overlay"][1]))
                overlays.append(path)
            bar.update(1)
    finally:
        if bar is not None:
            bar.close()
        for future in futures:
            future.cancel()
        client.close()
        if cluster is not None:
            cluster.close()
    return written, failed, overlays


def _worker_machines(client) -> Dict[str, Any]:
    try:
        return client.run(machine_info)
    except Exception as exc:  # informative only
        return {"error": one_line(exc, with_type=True)}
