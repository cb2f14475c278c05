"""Where the analysis roots saved reconstructions when no ostium is given, and which roots it warns of.

    .venv/bin/python bench/saved_roots.py 'DIR/*-v1.npz'

Reads ``bench/variants.py --save`` results (``LAD-<case>-v<k>.npz`` / ``RCA-…``, the truth tree is
``lad_tree(case)`` / ``rca_tree(case)``), analyses each occupancy as ``analyse`` does without ``--ostium``
(masks given, no view map) and prints per run: the root's distance from the true ostium, the two root
checks of ``analysis/root_check.py`` (``narrow_root``, ``through_vessel_root`` with its likeliest ostium's
distance from the true one), and every side branch
leaving the root branch within ``--reach-mm`` of the root (mm from the root, angle to the root branch
beyond it, the shorter way's length in mm). Then the tallies: rooted more than ``--off-mm`` from the
ostium, how many of those and of the others are warned of; and the machine.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from SDFCARLib.analysis import root_check  # noqa: E402
from SDFCARLib.analysis.pipeline import analyse_volume  # noqa: E402
from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("paths", nargs="+", help="saved results (.npz beside their .json geometry); globs allowed")
    ap.add_argument("--off-mm", type=float, default=10.0, help="a root farther than this from the ostium is wrong")
    ap.add_argument("--reach-mm", type=float, default=20.0, help="list the root branch's junctions this near the root")
    args = ap.parse_args()
    paths = sorted({p for pattern in args.paths for p in glob.glob(pattern)})
    if not paths:
        ap.error(f"no saved result matches {args.paths}")
    makers = {"LAD": lad_tree, "RCA": rca_tree}
    rows, t0 = [], time.perf_counter()
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; {len(paths)} saved runs", flush=True)
    for path in paths:
        suite, case = Path(path).stem.split("-")[:2]
        name = f"{Path(path).parent.name}/{Path(path).stem}"  # the same stems recur in other folders
        if suite not in makers:
            print(f"{name}: skipped (not LAD-… or RCA-…)")
            continue
        saved = np.load(path)
        geometry = Geometry.from_dict(json.loads(Path(path).with_suffix(".json").read_text()))
        result = analyse_volume(saved["occupancy"].astype(np.float32), geometry.volume, 0.5, geometry.views,
                                list(saved["masks"]), best_view=False)
        ostium = makers[suite](int(case)).branches[0].points[0]
        off = float(np.linalg.norm(result.tree.branch(0).points_mm[0] - ostium))
        narrow, through = result.settings["narrow_root"], result.settings["through_vessel_root"]
        near = [(round(mm, 1), round(angle), round(length)) for _, mm, angle, length in
                root_check.root_junctions(result.tree, args.reach_mm)]
        likeliest = float(np.linalg.norm(np.asarray(through["likeliest_ostium_mm"]) - ostium)) if through else None
        rows.append((off, bool(narrow), bool(through), likeliest))
        print(f"{name}: root {off:5.1f} mm from the ostium; narrow_root {'yes' if narrow else 'no '}; "
              f"through_vessel_root {f'yes, its likeliest ostium {likeliest:.1f} mm from it' if through else 'no'}; "
              f"junctions (mm, °, mm) {near}", flush=True)
    wrong = [r for r in rows if r[0] > args.off_mm]
    right = [r for r in rows if r[0] <= args.off_mm]
    print(f"\nrooted more than {args.off_mm:g} mm from the ostium: {len(wrong)} of {len(rows)}; warned of: "
          f"{sum(r[1] or r[2] for r in wrong)} (narrow_root {sum(r[1] for r in wrong)}, through_vessel_root "
          f"{sum(r[2] for r in wrong)}); rooted at it and warned of: {sum(r[1] or r[2] for r in right)} of {len(right)}; "
          f"through_vessel_root's likeliest ostium within {args.off_mm:g} mm of the true one: "
          f"{sum(r[3] is not None and r[3] <= args.off_mm for r in rows)} of {sum(r[2] for r in rows)}; "
          f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
