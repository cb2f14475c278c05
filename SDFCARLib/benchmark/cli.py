"""The ``benchmark`` command: its argparse options, the configuration they make, and the command."""

from __future__ import annotations

import argparse
import sys
import traceback
from pathlib import Path

from ..cli_types import non_negative_int, positive_float, positive_int
from .cases import SUITE_HELP, GridOptions
from .config import DEFAULT_MODES, BenchmarkConfig, parse_overrides
from .errors import BenchmarkError
from ..settings import PROTOCOLS
from .run import run_benchmark


def add_benchmark_command(commands, common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add ``benchmark`` to the CLI's sub-parsers (``commands``), with ``common``'s --verbose."""
    p = commands.add_parser(
        "benchmark", parents=[common], help="measure the modes on many simulated cases (the paper's tables)",
        description="For every case of a suite: simulate the protocol's views (two or more), compute the visual-hull "
                    "baseline, reconstruct with each mode and score every metric. Writes results.csv (appended, "
                    "resumable), summary.md (tables like the paper's), run.json and figures/ in --out. Cases run in "
                    "parallel on a local Dask cluster or on --scheduler.")
    p.add_argument("--suite", required=True, help=SUITE_HELP)
    p.add_argument("--modes", default=",".join(DEFAULT_MODES),
                   help=f"comma-separated modes (default {','.join(DEFAULT_MODES)}); the visual hull is always added")
    p.add_argument("--preset", default="fast", help="optimiser preset (fast, paper, …)")
    p.add_argument("--protocol", default="paper", choices=sorted(PROTOCOLS),
                   help="paper: line integrals, the NeCA views; clinical-…: binary masks of the clinical views the name lists "
                        "(two or three); realistic-…: masks segmented from simulated angiograms (default paper)")
    p.add_argument("--cases", type=positive_int, default=None,
                   help="number of cases (default: 10 procedural, 1 for 721a, every file of a folder ×2 trees)")
    p.add_argument("--out", required=True, help="results folder (created; rows already there are kept and skipped)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="first case seed (case i uses seed+i for its tree and optimiser)")
    p.add_argument("--steps", type=positive_int, default=None, help="optimisation steps (default: the preset's)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="optimiser override, repeatable (e.g. --set learning_rate=1e-3 --set device=cuda)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="address of an existing Dask scheduler (e.g. tcp://host:8786); default: a local cluster")
    p.add_argument("--workers", type=positive_int, default=None, help="local cluster workers (default: cores / threads per worker)")
    p.add_argument("--threads-per-worker", type=positive_int, default=1, help="torch threads per case (default 1)")
    p.add_argument("--centreline", "--centerline", dest="centreline", default=None,
                   help="721a suite: the centreline file (default ../shared/data/721A_Centreline.vtk beside the repository)")
    p.add_argument("--volume-shape", type=positive_int, nargs=3, default=None, metavar=("NI", "NJ", "NK"),
                   help="override the protocol's grid shape (default 128 128 128)")
    p.add_argument("--spacing-mm", type=positive_float, default=None, help="override the grid spacing (default 0.8; folder 1)")
    p.add_argument("--detector-shape", type=positive_int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                   help="override the detector shape (default 512 512)")
    p.add_argument("--detector-spacing-mm", type=positive_float, default=None, help="override the detector pixel spacing (default 0.278)")
    p.add_argument("--overlays", type=int, default=3, help="overlay figures for the first N cases (default 3)")
    p.add_argument("--retry-failed", action="store_true", help="run failed rows again (default: keep them, skip)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_benchmark)
    return p


def config_from_args(args: argparse.Namespace) -> BenchmarkConfig:
    modes = tuple(m.strip() for m in str(args.modes).split(",") if m.strip())
    grid = GridOptions(
        volume_shape=tuple(args.volume_shape) if args.volume_shape else None, spacing_mm=args.spacing_mm,
        detector_shape=tuple(args.detector_shape) if args.detector_shape else None,
        detector_spacing_mm=args.detector_spacing_mm)
    return BenchmarkConfig(
        suite=args.suite, out=Path(args.out), modes=modes, preset=args.preset, protocol=args.protocol, cases=args.cases,
        seed=args.seed, steps=args.steps, overrides=parse_overrides(args.overrides), grid=grid,
        centreline=Path(args.centreline) if args.centreline else None, scheduler=args.scheduler, workers=args.workers,
        threads_per_worker=args.threads_per_worker, overlays=args.overlays, retry_failed=args.retry_failed,
        progress=not args.no_progress)


def cmd_benchmark(args: argparse.Namespace) -> int:
    """The ``benchmark`` command: 0 done (failed runs are recorded, not fatal), 2 bad input, 130 interrupted."""
    try:
        config = config_from_args(args)
        outcome = run_benchmark(config, argv=sys.argv)
    except BenchmarkError as exc:
        if getattr(args, "verbose", False):
            traceback.print_exc()
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"interrupted: finished runs are kept in {Path(args.out) / 'results.csv'}; run the same command to resume",
              file=sys.stderr)
        return 130
    print(outcome.summary.read_text(encoding="utf-8"))
    print(f"{outcome.rows_written} run(s) written, {outcome.skipped} skipped (already done), {outcome.failed} failed; "
          f"results in {outcome.out}", file=sys.stderr)
    if outcome.failed:
        print(f"warning: {outcome.failed} run(s) failed; their errors are in {outcome.out / 'errors'}", file=sys.stderr)
    return 0
