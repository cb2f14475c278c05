"""The mask pipeline's edge rule (``AngioMaskSettings.edge_fraction``) on the realistic protocol's frames.

    .venv/bin/python bench/mask_edges.py --suite rca --cases 3 --fractions 0 0.15 0.25          # masks only, seconds
    .venv/bin/python bench/mask_edges.py --suite rca --cases 4 --fractions 0 0.15 --reconstruct  # + fast, minutes per case
    .venv/bin/python bench/mask_edges.py --suite lad --cases 3 --fractions 0 0.2 --max-radius-mm 1.5   # the rule on thin vessels only
    .venv/bin/python bench/mask_edges.py --suite lad --cases 10 --rules '{}' \
        '{"mask_edge_fraction": 0.2, "mask_edge_taper_radius_mm": null, "mask_edge_grow_mm": 0, "mask_edge_max_radius_mm": 1.5}'

``--fractions`` (with ``--max-radius-mm``) sets the rule's share as §26b/§59 measured it: a constant share, no
growth; ``--rules`` gives whole rules instead, as JSON objects of ``realistic.RealisticOptions``' mask_* fields
(``{}``: today's defaults).

Masks segmented from each case's simulated angiograms with each edge fraction, scored against the
true silhouettes (mask Dice, clDice, extra and missed pixels as shares of the silhouette); with
``--reconstruct`` also ``fast`` on each set of masks, side by side, at the paper grid (128³ / 512²).
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
from SDFCARLib.metrics import cldice, evaluate, mask_dice  # noqa: E402
from SDFCARLib.optimiser import reconstruct  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS, make_settings  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad"), default="rca")
    parser.add_argument("--cases", type=int, default=3)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30", choices=sorted(REALISTIC_PROTOCOLS))
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.0, 0.15, 0.25])
    parser.add_argument("--reconstruct", action="store_true")
    parser.add_argument("--max-radius-mm", type=lambda t: None if t.lower() == "none" else float(t), default=None,
                        help="the rule only on vessels up to this mask radius (AngioMaskSettings.edge_max_radius_mm); "
                             "default none: on every vessel, as RESULTS §26b measured it")
    parser.add_argument("--rules", nargs="+", default=None,
                        help="JSON objects of realistic.RealisticOptions mask_* overrides, one rule each (instead of --fractions)")
    args = parser.parse_args()
    if args.rules is not None:
        rules = []
        for text in args.rules:
            try:
                overrides = json.loads(text)
            except json.JSONDecodeError as exc:
                parser.error(f"--rules {text!r} is not JSON ({exc}); give e.g. '{{\"mask_edge_grow_mm\": 0}}'")
            known = [k for k in RealisticOptions.__dataclass_fields__ if k.startswith("mask_")]
            if not isinstance(overrides, dict) or not all(k in known for k in overrides):
                parser.error(f"--rules {text!r}: give an object of RealisticOptions' fields {', '.join(known)}")
            rules.append((json.dumps(overrides, sort_keys=True), overrides))
    else:
        rules = [(f"edge {f:.2f}", {"mask_edge_fraction": f, "mask_edge_taper_radius_mm": None, "mask_edge_grow_mm": 0.0,
                                    "mask_edge_max_radius_mm": args.max_radius_mm}) for f in args.fractions]
    torch.set_num_threads(1)
    grid = GridOptions()
    config = BenchmarkConfig(args.suite, Path("unused"), cases=args.first + args.cases, grid=grid, protocol=args.protocol)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, 1 thread; "
          f"{args.suite} cases {args.first}–{args.first + args.cases - 1}, {args.protocol}, paper grid", flush=True)
    masks_rows = {name: [] for name, _ in rules}
    recon_rows = {name: [] for name, _ in rules}
    for spec in build_cases(config)[args.first:]:
        truths = None
        for name, overrides in rules:
            case = prepare_case(spec, args.protocol, grid, realistic_overrides=overrides)
            if truths is None:  # the true silhouettes (of the moved views) do not depend on the masks' rule
                simulated = realistic_input(case.label, case.geometry, spec.seed,
                                            RealisticOptions(**REALISTIC_PROTOCOLS[args.protocol]))
                truths = [t.astype(bool) for t in simulated.true_masks]
            scores = np.mean([(mask_dice(m, t), cldice(m, t), (m & ~t).sum() / t.sum(), (t & ~m).sum() / t.sum())
                              for m, t in zip(case.masks, truths)], axis=0)
            masks_rows[name].append(scores)
            line = (f"{spec.name:7s} {name}  masks: Dice {scores[0]:.3f} clDice {scores[1]:.3f} "
                    f"extra {scores[2]:.3f} missed {scores[3]:.3f}")
            if args.reconstruct:
                t0 = time.perf_counter()
                result = reconstruct(case.geometry, case.targets, make_settings("fast", seed=spec.seed), case.target_kind,
                                     frames=case.frames)
                m = evaluate(result.segmentation, case.label, case.geometry.volume, case.geometry.views, case.masks)
                recon_rows[name].append((m["cldice"], m["dice"], m.get("components")))
                line += (f"  fast: clDice {m['cldice']:.3f} Dice {m['dice']:.3f} components {m.get('components')}  "
                         f"{time.perf_counter() - t0:.0f} s")
            print(line, flush=True)
    first_name = rules[0][0]
    for name, _ in rules:
        a = np.array(masks_rows[name])
        line = (f"mean    {name}  masks: Dice {a[:, 0].mean():.4f} clDice {a[:, 1].mean():.4f} "
                f"extra {a[:, 2].mean():.3f} missed {a[:, 3].mean():.3f}")
        if args.reconstruct:
            r, base = np.array(recon_rows[name]), np.array(recon_rows[first_name])
            line += (f"  fast: clDice {r[:, 0].mean():.3f} Dice {r[:, 1].mean():.3f} "
                     f"better than {first_name} on {int(np.sum(r[:, 0] > base[:, 0]))}/{len(r)}")
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
