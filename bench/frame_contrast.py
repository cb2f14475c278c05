"""The frames' vessel contrast under their masks: own frame, the same frame inverted, the other view's frame.

    .venv/bin/python bench/frame_contrast.py --cases 3

Realistic static protocol (LAO 30 / RAO 30, masks segmented from simulated angiograms; coarse grid 80³ at
1.3 mm and 192² at 0.8 mm unless --paper-grid), linear frames and the same frames processed for display.
Per view, ``analysis.frame_contrast.vessel_contrast`` of: its own frame under its mask, that frame inverted
(largest + smallest − grey), and the other view's frame under its mask (the frames given in the wrong order).
The refusal and warning thresholds must separate the three groups; prints their ranges and the machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from bench.realistic_cases import add_grid_arguments, protocol_setup  # noqa: E402
from SDFCARLib.analysis.frame_contrast import INVERTED_CONTRAST, MIN_VESSEL_CONTRAST, vessel_contrast  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, voxelize  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS  # noqa: E402

PROTOCOL = "realistic-static-lao30-rao30"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--cases", type=int, default=3)
    add_grid_arguments(parser)
    args = parser.parse_args()
    args.suite = "rca+lad"
    groups = {"own": [], "inverted": [], "other view's": []}
    t0 = time.perf_counter()
    print(f"{'case':8s} {'frames':8s} view  {'own':>6s} {'inverted':>9s} {'other':>6s}")
    for suite, make_tree in (("rca", rca_tree), ("lad", lad_tree)):
        args.suite = suite
        geometry = protocol_setup(args, PROTOCOL, f"{args.first}..{args.first + args.cases - 1}")
        for seed in range(args.first, args.first + args.cases):
            label = voxelize(make_tree(seed), geometry.volume)
            for display in (False, True):
                options = dataclasses.replace(RealisticOptions(**REALISTIC_PROTOCOLS[PROTOCOL]), display=display)
                realistic = realistic_input(label, geometry, seed, options)
                frames = [f.astype(np.float64) for f in realistic.frames]
                for n, (frame, mask) in enumerate(zip(frames, realistic.masks)):
                    row = (vessel_contrast(frame, mask), vessel_contrast(frame.max() + frame.min() - frame, mask),
                           vessel_contrast(frames[1 - n], mask))
                    for group, value in zip(groups, row):
                        groups[group].append(value)
                    print(f"{suite.upper()}-{seed:<4d} {'DISP' if display else 'LIN':8s} {n + 1:4d}  {row[0]:6.2f} "
                          f"{row[1]:9.2f} {row[2]:6.2f}", flush=True)
    print(f"\nthresholds: refused below {INVERTED_CONTRAST:g}, warned below {MIN_VESSEL_CONTRAST:g}")
    for group, values in groups.items():
        print(f"{group:13s} {len(values):3d} views: {min(values):6.2f} … {max(values):6.2f}")
    print(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
