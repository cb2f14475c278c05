"""Two sets of saved runs (``bench/variants.py --save``) of the same cases, scored side by side.

    .venv/bin/python bench/saved_pairs.py bench/runs/real-c2f/rca bench/runs/excl/real-rca --width-ratio 0.7

Runs are paired by case name (``RCA-3-v0.npz`` and ``RCA-3-v1.npz`` are both case RCA-3). ``--width-ratio``
applies today's last finishing step (``width_agreement.disagreeing_pieces``, keeping the tree whole)
to the first set, for runs saved before that step was in the preset: on one thread the fit is
deterministic, so this is what the preset gives today without repeating the fits. Prints per case
and on average clDice, topology precision / sensitivity, Dice, pieces and the largest piece's share,
the cases the second set made better and worse, and the machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import sys
from pathlib import Path
from typing import Dict, List

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.metrics import cldice, component_labels, dice, topology_precision_sensitivity  # noqa: E402
from SDFCARLib.pruning import PruneSettings  # noqa: E402
from SDFCARLib.width_agreement import disagreeing_pieces  # noqa: E402

COLUMNS = ("clDice", "Tprec", "Tsens", "Dice", "pieces", "largest %")


def runs_by_case(folder: Path) -> Dict[str, Path]:
    return {re.sub(r"-v\d+$", "", p.stem): p for p in sorted(folder.glob("*.npz"))}


def scores(path: Path, width_ratio: float) -> List[float]:
    saved = np.load(path)
    segmentation, label = saved["segmentation"], saved["label"]
    if width_ratio:
        geometry = Geometry.load(path.with_suffix(".json"))
        segmentation = disagreeing_pieces(segmentation, saved["masks"], geometry, width_ratio,
                                          PruneSettings.max_piece_mm, keep_connected=True)[0]
    topology = topology_precision_sensitivity(segmentation, label)
    sizes = component_labels(segmentation)[1]
    return [cldice(segmentation, label), topology["tprec"], topology["tsens"], dice(segmentation, label),
            float(sizes.size), 100 * float(sizes.max(initial=0) / max(sizes.sum(), 1))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path, help="folder of saved runs (the reference)")
    parser.add_argument("second", type=Path, help="folder of saved runs of the same cases (the change)")
    parser.add_argument("--width-ratio", type=float, default=0.0,
                        help="apply the width check (keeping the tree whole) to the first set at this ratio (0: as saved)")
    args = parser.parse_args()
    first, second = runs_by_case(args.first), runs_by_case(args.second)
    cases = sorted(set(first) & set(second), key=lambda name: (len(name), name))
    if not cases:
        parser.error(f"no case is saved in both {args.first} and {args.second}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; {len(cases)} cases; "
          f"first: {args.first}{f' + width check {args.width_ratio}' if args.width_ratio else ''}; second: {args.second}")
    rows = []
    for name in cases:
        a, b = scores(first[name], args.width_ratio), scores(second[name], 0.0)
        rows.append((a, b))
        print(f"{name:7s} " + "  ".join(f"{c} {x:.3f} → {y:.3f}" if c not in ("pieces", "largest %") else f"{c} {x:.0f} → {y:.0f}"
                                        for c, x, y in zip(COLUMNS, a, b)), flush=True)
    a, b = (np.array([r[k] for r in rows]) for k in (0, 1))
    print("mean    " + "  ".join(f"{c} {x:.4f} → {y:.4f}" for c, x, y in zip(COLUMNS, a.mean(0), b.mean(0))))
    print(f"second better / worse clDice on {int((b[:, 0] > a[:, 0]).sum())} / {int((b[:, 0] < a[:, 0]).sum())} of {len(rows)}, "
          f"Dice {int((b[:, 3] > a[:, 3]).sum())} / {int((b[:, 3] < a[:, 3]).sum())}; clDice change per case "
          f"{100 * (b[:, 0] - a[:, 0]).min():+.1f} … {100 * (b[:, 0] - a[:, 0]).max():+.1f} points")
    return 0


if __name__ == "__main__":
    sys.exit(main())
