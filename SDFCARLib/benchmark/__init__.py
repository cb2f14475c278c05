"""Evaluation harness: the paper's Tables 1–4 measured on many simulated cases, locally or on Dask.

``python -m SDFCARLib benchmark --suite rca --modes sdfcar,neca --preset fast --cases 10 --out DIR``

For every case of a suite the harness simulates the protocol's views (two, or three for the
three-view protocol) of the ground-truth label, computes the visual hull of their masks (the
baseline row ``hull``), reconstructs with
every requested mode and scores each result with ``metrics.evaluate`` against the label and the
masks. Cases run as Dask tasks (one task prepares a case, one task per mode reconstructs it) on a
``LocalCluster`` or on an existing cluster given by ``--scheduler``.

Suites
    ``rca``, ``lad``   procedural trees ``phantoms.rca_tree`` / ``lad_tree``, seeds seed … seed+N−1.
    ``721a``           the 721A centreline (``--centreline``), centred on the isocenter; N cases
                       are N optimiser seeds on that one anatomy.
    ``folder:PATH``    label volumes (NRRD/NIfTI, e.g. ImageCAS) with the DeepCA/NeCA preprocessing
                       (``preprocess_label_volume``): each file gives two cases, ``<stem>-lad`` and
                       ``<stem>-rca``.

Protocols
    ``paper``          line-integral targets, the NeCA views (``VIEW_PAIRS["paper"]``), 512² detector
                       at 0.278 mm, 128³ grid at 0.8 mm (1 mm for folder suites).
    ``clinical-…``     binary-mask targets with the named clinical pair, same detector and grid.

Files in ``--out``
    ``results.csv``    one row per case × mode (and the hull), appended as each task finishes, so
                       nothing finished is lost; a re-run of the same command skips rows already
                       there (failed ones too, unless ``--retry-failed``).
    ``summary.md``     mean ± std tables laid out like the paper's, the sdfcar-vs-neca ordering,
                       the command, seeds, versions, machine and date.
    ``run.json``       every invocation's configuration, cases, seeds, versions, machine, cluster.
    ``errors/``        the traceback of every failed case × mode.
    ``figures/``       per-metric box plots per mode, and overlay MIPs (green overlap, red predicted
                       only, blue missed) of the first ``--overlays`` cases.

Rows are keyed by (suite, case, mode, config): ``config`` is a short hash of everything besides
the case and mode that changes a result (protocol, preset, steps, ``--set`` overrides, grid and
detector overrides, base seed), so variants can share one folder without mixing; ``summary.md``
covers the rows of the command that wrote it.

Modules
    ``registry``  modes and their titles, the metric table, the protocols (shared tables, to move
                  into ``SDFCARLib/settings.py``).
    ``errors``    ``BenchmarkError``.
    ``cases``     suites and case specs, protocol geometry, label-volume preprocessing, prepared cases.
    ``config``    ``BenchmarkConfig`` (identity hash, command line), ``--set``, ``build_cases``, checks.
    ``store``     ``results.csv`` (``ResultsFile``, ``latest_rows``) and ``run.json``.
    ``report``    summary tables, ``summary.md``, ordering lines, box plots, machine and versions.
    ``run``       the Dask tasks and client, ``run_benchmark``.
    ``cli``       the ``benchmark`` command's options and entry point.

torch- and scipy-backed modules (optimiser, phantoms, hull, metrics) are imported inside the
functions that use them, and dask, distributed and matplotlib (optional, ``[bench]``) too: the
CLI's parser imports this package, and must stay fast and work without them.
"""

from .cases import (FOLDER_SPACING_MM, PROCEDURAL_SUITES, SUITE_HELP, VOLUME_SUFFIXES, CaseSpec, GridOptions, PathLike,
                    PreparedCase, default_centreline, parse_suite, prepare_case, preprocess_label_file,
                    preprocess_label_volume, protocol_geometry)
from .cli import add_benchmark_command, cmd_benchmark, config_from_args
from .config import DEFAULT_MODES, HARNESS_VERSION, BenchmarkConfig, build_cases, check_config, parse_overrides
from .errors import BenchmarkError
from .registry import HULL, METRIC_COLUMNS, MODE_NAMES, TABLE_METRICS, mode_title
from ..settings import (PAPER_DETECTOR_SHAPE, PAPER_DETECTOR_SPACING_MM, PAPER_METRICS, PAPER_SPACING_MM,
                        PAPER_VOLUME_SHAPE, PROTOCOLS)
from .report import _table_markdown  # noqa: F401 (used by the tests)
from .report import (all_versions, machine_info, ordering_lines, side_by_side_lines, summary_tables, write_box_plots,
                     write_summary)
from .run import BenchmarkOutcome, prepare_task, run_benchmark, run_task, task_options
from .store import COLUMNS, IDENTITY_COLUMNS, ResultsFile, latest_rows

__all__ = [
    "BenchmarkConfig", "BenchmarkError", "BenchmarkOutcome", "COLUMNS", "CaseSpec", "DEFAULT_MODES", "FOLDER_SPACING_MM",
    "GridOptions", "HARNESS_VERSION", "HULL", "IDENTITY_COLUMNS", "METRIC_COLUMNS", "MODE_NAMES", "PAPER_DETECTOR_SHAPE",
    "PAPER_DETECTOR_SPACING_MM", "PAPER_METRICS", "PAPER_SPACING_MM", "PAPER_VOLUME_SHAPE", "PROCEDURAL_SUITES",
    "PROTOCOLS", "PathLike", "PreparedCase", "ResultsFile", "SUITE_HELP", "TABLE_METRICS", "VOLUME_SUFFIXES",
    "add_benchmark_command", "all_versions", "build_cases", "check_config", "cmd_benchmark", "config_from_args",
    "default_centreline", "latest_rows", "machine_info", "mode_title", "ordering_lines", "parse_overrides", "side_by_side_lines",
    "parse_suite", "prepare_case", "prepare_task", "preprocess_label_file", "preprocess_label_volume",
    "protocol_geometry", "run_benchmark", "run_task", "summary_tables", "task_options", "write_box_plots",
    "write_summary",
]
