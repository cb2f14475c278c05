"""Does the reconstruction tell a view's motion? The field re-fitted at candidate poses of view 2.

    .venv/bin/python bench/pose_scan.py --suite rca --case 0 --axis 2 --true-mm 3 --candidates 0 1.5 3 4.5

Masks of a benchmark case are simulated (clean, ``clinical-lao30-rao30``, grid 80³ at 1.3 mm, 192² at
0.8 mm) with the object translated by ``--true-mm`` along LPS axis ``--axis`` at view 2; each candidate
translation is then given to an ordinary ``fast`` reconstruction as view 2's object motion. Prints the
final losses, clDice, Dice, components and reprojection Dice per candidate, and the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case  # noqa: E402
from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import reconstruct  # noqa: E402
from SDFCARLib.phantoms import simulate_views  # noqa: E402
from SDFCARLib.settings import MASK_THRESHOLD_MM, make_settings  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="rca")
    parser.add_argument("--case", type=int, default=0)
    parser.add_argument("--protocol", default="clinical-lao30-rao30")
    parser.add_argument("--axis", type=int, default=2, choices=(0, 1, 2), help="LPS axis of the translation")
    parser.add_argument("--true-mm", type=float, default=3.0)
    parser.add_argument("--candidates", type=float, nargs="+", default=[0.0, 1.5, 3.0, 4.5])
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    grid = GridOptions((80, 80, 80), 1.3, (192, 192), 0.8)
    config = BenchmarkConfig(args.suite, Path("unused"), cases=args.case + 1, grid=grid, protocol=args.protocol)
    spec = build_cases(config)[args.case]
    case = prepare_case(spec, args.protocol, grid)
    views = case.geometry.views

    def moved(mm: float):
        translation = [0.0, 0.0, 0.0]
        translation[args.axis] = mm
        return (views[0], views[1].with_object_motion([0.0, 0.0, 0.0], translation)) + tuple(views[2:])

    _, masks = simulate_views(case.label, case.geometry.volume, moved(args.true_mm), MASK_THRESHOLD_MM)
    targets = [m.astype(np.float32) for m in masks]
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {spec.name}, {args.protocol}, view 2 moved {args.true_mm} mm along axis {args.axis}")
    for candidate in args.candidates:
        t0 = time.perf_counter()
        geometry = Geometry(case.geometry.volume, moved(candidate))
        result = reconstruct(geometry, targets, make_settings("fast", seed=spec.seed), "mask")
        m = evaluate(result.segmentation, case.label, geometry.volume, geometry.views, masks)
        last = np.mean([[h["l_occ"], h["l_geo"]] for h in result.history[-20:]], axis=0)
        print(json.dumps({"candidate_mm": candidate, "l_occ": round(float(last[0]), 5), "l_geo": round(float(last[1]), 5),
                          "cldice": round(m["cldice"], 3), "dice": round(m["dice"], 3), "components": m.get("components"),
                          "reprojection_dice": [round(v, 3) for v in m["reprojection_dice"]],
                          "seconds": round(time.perf_counter() - t0)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
