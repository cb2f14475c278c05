"""What the realistic-input bench scripts share: the grid options, the machine line, the geometry."""

from __future__ import annotations

import argparse
import os
import platform

import torch

from SDFCARLib.benchmark.cases import GridOptions, protocol_geometry
from SDFCARLib.geometry import Geometry

#: the benchmarks' coarse grid: 80³ voxels of 1.3 mm, a 192² detector of 0.8 mm pixels
COARSE_GRID = GridOptions((80, 80, 80), 1.3, (192, 192), 0.8)


def add_grid_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--paper-grid", action="store_true", help="128³ at 0.8 mm, 512² at 0.278 mm")
    parser.add_argument("--threads", type=int, default=1)


def protocol_setup(args: argparse.Namespace, protocol: str, cases: str) -> Geometry:
    """Torch's threads as asked, the machine and run printed, and the protocol's geometry on the chosen grid."""
    torch.set_num_threads(args.threads)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {args.suite} cases {cases}, {protocol}, "
          f"{'paper grid' if args.paper_grid else 'grid80'}", flush=True)
    return protocol_geometry(protocol, args.suite, None if args.paper_grid else COARSE_GRID)
