"""The suite cases of the benches that run no fit (``view_agreement.py``, ``untruncated_gain.py``): their command-line
arguments and the cases, simulated as the benchmark simulates them (paper grid)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Iterator, Tuple

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case
from SDFCARLib.settings import PROTOCOLS


def add_case_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--protocol", required=True, choices=list(PROTOCOLS))
    parser.add_argument("--suite", required=True, choices=("lad", "rca"))
    parser.add_argument("--cases", type=int, default=10)
    parser.add_argument("--masks", default="{}", help="JSON: realistic.RealisticOptions fields over the protocol's")


def prepared_cases(args: argparse.Namespace) -> Iterator[Tuple[Any, Any]]:
    """(spec, case) for the suite's first ``args.cases`` cases, with ``args.masks``' overrides."""
    overrides = json.loads(args.masks) or None
    specs = build_cases(BenchmarkConfig(args.suite, Path("unused"), cases=args.cases, grid=GridOptions(),
                                        protocol=args.protocol))
    for spec in specs[:args.cases]:
        yield spec, prepare_case(spec, args.protocol, GridOptions(), overrides)
