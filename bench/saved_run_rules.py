"""Finishing rules tried offline on saved reconstructions (``bench/variants.py --save DIR``).

    .venv/bin/python bench/saved_run_rules.py 'bench/runs/c2f-clean/*/*-v0.npz'

No fit is repeated: each rule edits the saved segmentation, which is scored against the saved truth.
Two families, both candidates for dropping ghosts after the fit:

``width``  a vessel is a tube, so its projected width (perpendicular to its course) is the same
           diameter in every view, scaled by the magnification at its depth. A ghost lies where the
           rays of two *different* vessels cross, and their widths need not agree. Each segmented
           voxel gets the ratio (smaller / larger) of the masks' half-widths at its projections (the
           distance map read at the nearest 2D centreline pixel, in mm at the voxel's depth); the rule
           drops voxels (``vox<q>``) or whole 6 mm skeleton pieces (``piece<q>``, median ratio) below q,
           or only those pieces whose removal leaves the rest of their component in one part (``joined<q>``).
``frag``   detached components holding less than a share f of the segmented voxels are dropped
           (also after ``joined<q>``: ``joined<q>+frag<f>``).

Prints one line per run (clDice / components for every rule), the means (with the largest piece's
share of the voxels) and the number of runs each rule made better and worse, and the machine.
"""

from __future__ import annotations

import argparse
import glob
import os
import platform
import sys
from pathlib import Path
from typing import Dict, List, Tuple

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.metrics import cldice, component_labels, dice  # noqa: E402
from SDFCARLib.pruning import PruneSettings  # noqa: E402
from SDFCARLib.width_agreement import disagreeing_pieces, width_agreement  # noqa: E402

WIDTH_RATIOS = (0.5, 0.6, 0.7)
FRAGMENT_SHARES = (0.002, 0.005, 0.01, 0.02)
PIECE_MM = PruneSettings.max_piece_mm  # the pieces pruning weighs


def rules(segmentation: np.ndarray, masks: np.ndarray, geometry: Geometry,
          width_ratios=WIDTH_RATIOS, only=None) -> Dict[str, np.ndarray]:
    """Each rule's result by name; ``only`` (name prefixes) skips computing the others."""
    def wanted(name: str) -> bool:
        return not only or name.startswith(tuple(only))

    voxels = np.argwhere(segmentation)
    ratio = width_agreement(masks, geometry, geometry.volume.index_to_world(voxels.astype(float)))
    out = {"fast": segmentation}
    joined = {}
    for q in width_ratios:
        if wanted(f"vox{q}"):
            kept = segmentation.copy()
            kept[tuple(voxels[ratio < q].T)] = False
            out[f"vox{q}"] = kept
        if wanted(f"piece{q}"):
            out[f"piece{q}"] = disagreeing_pieces(segmentation, masks, geometry, q, PIECE_MM)[0]
        if wanted(f"joined{q}"):
            joined[q] = out[f"joined{q}"] = disagreeing_pieces(segmentation, masks, geometry, q, PIECE_MM,
                                                              keep_connected=True)[0]
    for f in FRAGMENT_SHARES:
        if wanted(f"frag{f}"):
            out[f"frag{f}"] = without_small_fragments(segmentation, f)
    for q in width_ratios[1:]:
        name = f"joined{q}+frag{FRAGMENT_SHARES[1]}"
        if q in joined and wanted(name):
            out[name] = without_small_fragments(joined[q], FRAGMENT_SHARES[1])
    return out


def without_small_fragments(segmentation: np.ndarray, min_share: float) -> np.ndarray:
    """The components holding at least ``min_share`` of the segmented voxels."""
    labels, sizes = component_labels(segmentation)
    share = sizes / max(int(sizes.sum()), 1)
    return np.isin(labels, np.flatnonzero(share >= min_share) + 1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="glob(s) of saved .npz runs (each with its geometry .json)")
    parser.add_argument("--width-ratios", type=float, nargs="+", default=list(WIDTH_RATIOS),
                        help=f"the ratios q the width rules are tried at (default {' '.join(map(str, WIDTH_RATIOS))})")
    parser.add_argument("--only", nargs="+", default=None, metavar="PREFIX",
                        help="keep only the rules whose names start with one of these (e.g. joined); 'fast' is always kept")
    args = parser.parse_args()
    paths = sorted({p for pattern in args.runs for p in glob.glob(pattern)})
    if not paths:
        parser.error(f"no saved run matches {args.runs}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; {len(paths)} saved runs")
    scores: Dict[str, List[Tuple[float, float, int, float]]] = {}
    for path in paths:
        saved = np.load(path)
        geometry = Geometry.load(path[:-len(".npz")] + ".json")
        label = saved["label"]
        line = []
        for name, result in rules(saved["segmentation"], saved["masks"], geometry, tuple(args.width_ratios),
                                  args.only).items():
            sizes = component_labels(result)[1]
            row = (cldice(result, label), dice(result, label), int(sizes.size), float(sizes.max(initial=0) / max(sizes.sum(), 1)))
            scores.setdefault(name, []).append(row)
            line.append(f"{name} {row[0]:.3f}/{row[2]}")
        print("/".join(Path(path).parts[-2:]), "  ".join(line), flush=True)
    base = np.array(scores["fast"])
    for name, rows in scores.items():
        rows = np.array(rows)
        print(f"mean {name:9s} clDice {100 * rows[:, 0].mean():6.2f}  Dice {100 * rows[:, 1].mean():6.2f}  "
              f"pieces {rows[:, 2].mean():5.1f}  largest {100 * rows[:, 3].mean():5.1f} %  better / worse clDice {int((rows[:, 0] > base[:, 0]).sum())} / "
              f"{int((rows[:, 0] < base[:, 0]).sum())} of {len(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
