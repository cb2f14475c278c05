"""The frames' path lengths as the occupancy target (``frame_evidence``) against the masks alone.

    .venv/bin/python bench/frame_evidence.py --suite rca --cases 10

Realistic static protocol (LAO 30 / RAO 30, masks segmented from simulated angiograms, no motion, or
with ``--motion`` the heart moved up to 3 mm / 2° between the acquisitions;
coarse grid 80³ at 1.3 mm and 192² at 0.8 mm unless --paper-grid). Per case, from the same masks
and seed, ``fast`` is run on the masks alone and with the frames as evidence at the segmentation
thresholds given (``threshold``) and with any ``--variant`` settings; prints each variant's metrics against the truth,
the attenuation read off the frames (the simulator's is 0.25 per mm), the means, and the machine.
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
from SDFCARLib.optimiser import reconstruct  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, voxelize  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS, make_settings, parse_setting_overrides  # noqa: E402

PROTOCOL = "realistic-static-lao30-rao30"
MOVING = "realistic-lao30-rao30"  # the same with the heart moving up to 3 mm / 2° between the acquisitions
KEYS = ("cldice", "tprec", "tsens", "dice", "chamfer_l2_mm")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad"), default="rca")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--cases", type=int, default=4)
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.5])
    parser.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE[,KEY=VALUE]",
                        help="one more variant with the frames and these settings (threshold 0.5), e.g. support_margin_mm=1.5")
    parser.add_argument("--no-masks-only", action="store_true", help="skip the masks-only variant")
    parser.add_argument("--motion", action="store_true", help=f"protocol {MOVING} (the preset's calibrate_from_frames corrects what the frames show)")
    add_grid_arguments(parser)
    args = parser.parse_args()
    protocol = MOVING if args.motion else PROTOCOL
    geometry = protocol_setup(args, protocol, f"{args.first}..{args.first + args.cases - 1}")
    variants = ([] if args.no_masks_only else ["masks"]) + [f"frames@{t:g}" for t in args.thresholds] + [f"frames+{v}" for v in args.variant]
    table = {v: [] for v in variants}
    for seed in range(args.first, args.first + args.cases):
        name = f"{args.suite.upper()}-{seed}"
        label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(seed), geometry.volume)
        options = RealisticOptions(**REALISTIC_PROTOCOLS[protocol])
        realistic = realistic_input(label, geometry, seed, options)
        for variant in variants:
            t0 = time.perf_counter()
            if variant == "masks":
                settings, frames = make_settings("fast", seed=seed), None
            elif variant.startswith("frames+"):
                overrides = parse_setting_overrides(variant[len("frames+"):].split(","))
                settings = make_settings("fast", seed=seed, frame_evidence=True, **overrides)
                frames = realistic.frames
            else:
                settings = make_settings("fast", seed=seed, frame_evidence=True, threshold=float(variant.split("@")[1]))
                frames = realistic.frames
            result = reconstruct(geometry, realistic.masks, settings, "mask", frames=frames)
            m = evaluate(result.segmentation, label, geometry.volume, geometry.views, realistic.masks)
            m["pieces"] = m.get("components")
            table[variant].append(m)
            evidence = result.report.get("frame_evidence") or {}
            mu = " / ".join(f"{v['attenuation_per_mm']:.3f}" for v in evidence.get("views", []))
            print(f"{name} {variant:11s} clDice {m['cldice']:.3f} Tprec {m['tprec']:.3f} Tsens {m['tsens']:.3f} "
                  f"Dice {m['dice']:.3f} Chamfer {m['chamfer_l2_mm']:.2f} pieces {m['pieces']}/{m.get('components_label')} "
                  f"{time.perf_counter() - t0:.0f} s" + (f"  mu {mu}" if mu else ""), flush=True)
    print(f"# means over the cases (clDice, Tprec, Tsens, Dice in %; Chamfer mm; pieces); better than {variants[0]} on clDice")
    base = np.array([m["cldice"] for m in table[variants[0]]])
    for variant, rows in table.items():
        means = {k: float(np.mean([r[k] for r in rows])) for k in KEYS + ("pieces",)}
        better = int(np.sum(np.array([r["cldice"] for r in rows]) > base))
        print(f"{variant:11s} " + "  ".join(f"{k} {100 * means[k]:.2f}" if k not in ("chamfer_l2_mm", "pieces")
                                            else f"{k} {means[k]:.2f}" for k in KEYS + ("pieces",))
              + ("" if variant == variants[0] else f"  better {better}/{len(rows)}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
