"""The segmentation's threshold rule side by side on the same fitted field: occupancy ≥ 0.5 alone
(``grow_threshold`` 0) against the hysteresis rule (grown from ≥ 0.5 into 26-connected voxels ≥ a lower
value; ``fast`` grows into 0.3).

    .venv/bin/python bench/grow_threshold.py --suite rca --cases 10 --protocol realistic-static-lao30-rao30 --grow 0.3 0.2

Per case the field is fitted once (``fast``, as ``reconstruct`` runs it: frames as evidence and the
motion read off them where the protocol gives frames) and finished once per rule, pruning, dropping
and joining fragments included, so the rows differ only in the rule. Coarse grid (80³ at 1.3 mm,
192² at 0.8 mm) unless --paper-grid. Prints each rule's metrics per case, the means, how many cases
each rule beats the threshold alone on clDice, and the machine. (§23b's "fast" rows are the "0.5 only"
rule: `fast` did not grow then.)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from bench.realistic_cases import add_grid_arguments, protocol_setup  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import fit_field  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, simulate_views, voxelize  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import MASK_THRESHOLD_MM, REALISTIC_PROTOCOLS, make_settings  # noqa: E402

KEYS = ("cldice", "tprec", "tsens", "dice", "chamfer_l2_mm", "components")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad"), default="rca")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--cases", type=int, default=4)
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30",
                        help="a realistic protocol (frames and segmented masks) or clinical-lao30-rao30 (true masks, no frames)")
    parser.add_argument("--grow", type=float, nargs="+", default=[0.3, 0.2], help="grow thresholds to compare with the threshold alone")
    add_grid_arguments(parser)
    args = parser.parse_args()
    geometry = protocol_setup(args, args.protocol, f"{args.first}..{args.first + args.cases - 1}")
    rules = [("0.5 only", 0.0)] + [(f"grow {g:g}", g) for g in args.grow]
    table = {name: [] for name, _ in rules}
    for seed in range(args.first, args.first + args.cases):
        name = f"{args.suite.upper()}-{seed}"
        label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(seed), geometry.volume)
        if args.protocol in REALISTIC_PROTOCOLS:
            realistic = realistic_input(label, geometry, seed, RealisticOptions(**REALISTIC_PROTOCOLS[args.protocol]))
            masks, frames = realistic.masks, realistic.frames
        else:
            masks, frames = simulate_views(label, geometry.volume, geometry.views, MASK_THRESHOLD_MM)[1], None
        settings = make_settings("fast", seed=seed)
        fitted = fit_field(geometry, masks, settings, "mask", frames=frames)
        fit_s = time.perf_counter() - fitted.t_start
        for rule, grow in rules:
            variant = make_settings("fast", seed=seed, grow_threshold=grow)
            result = fitted.finished(variant)
            m = evaluate(result.segmentation, label, geometry.volume, geometry.views, masks)
            table[rule].append(m)
            print(f"{name} {rule:9s} clDice {m['cldice']:.3f} Tprec {m['tprec']:.3f} Tsens {m['tsens']:.3f} Dice {m['dice']:.3f} "
                  f"Chamfer {m['chamfer_l2_mm']:.2f} pieces {m.get('components')}/{m.get('components_label')} "
                  f"largest {m.get('largest_component_fraction', float('nan')):.3f}  fit {fit_s:.0f} s", flush=True)
    print("# means (clDice, Tprec, Tsens, Dice in %; Chamfer mm; pieces); cases better than the threshold alone on clDice")
    base = np.array([m["cldice"] for m in table["0.5 only"]])
    for rule, rows in table.items():
        means = {k: float(np.mean([r[k] for r in rows])) for k in KEYS}
        better = int(np.sum(np.array([r["cldice"] for r in rows]) > base))
        worse = int(np.sum(np.array([r["cldice"] for r in rows]) < base))
        print(f"{rule:9s} " + "  ".join(f"{k} {means[k]:.2f}" if k in ("chamfer_l2_mm", "components") else f"{k} {100 * means[k]:.2f}"
                                        for k in KEYS) + ("" if rule == "0.5 only" else f"  better/worse {better}/{worse}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
