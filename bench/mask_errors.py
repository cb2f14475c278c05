"""Which errors of masks segmented from angiograms cost the reconstruction: missed or extra pixels?

    .venv/bin/python bench/mask_errors.py --suite rca --case 0 2

For each case of the realistic static protocol (LAO 30 / RAO 30, no motion; coarse grid 80³ at
1.3 mm, 192² at 0.8 mm unless --paper-grid) the same field is fitted (``fast``, the case's seed) on
four sets of masks: the true silhouettes, the masks SDFCAR segments from the simulated angiograms,
their intersection (only the segmentation's missed pixels remain as errors) and their union (only
its extra pixels remain). Prints each variant's metrics against the truth and the machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


from bench.realistic_cases import add_grid_arguments, protocol_setup  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import reconstruct  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, voxelize  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import make_settings  # noqa: E402

PROTOCOL = "realistic-static-lao30-rao30"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad"), default="rca")
    parser.add_argument("--case", type=int, nargs="+", default=[0], help="case seeds")
    add_grid_arguments(parser)
    args = parser.parse_args()
    geometry = protocol_setup(args, PROTOCOL, str(args.case))
    for seed in args.case:
        name = f"{args.suite.upper()}-{seed}"
        label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(seed), geometry.volume)
        realistic = realistic_input(label, geometry, seed, RealisticOptions(max_shift_mm=0.0, max_rotation_deg=0.0))
        true, segmented = realistic.true_masks, realistic.masks
        for n, (t, s) in enumerate(zip(true, segmented), start=1):
            print(f"{name} view {n}: true {int(t.sum())} pixels, segmented {int(s.sum())}, missed {int((t & ~s).sum())}, "
                  f"extra {int((s & ~t).sum())}", flush=True)
        variants = {"true silhouettes": true, "segmented": segmented,
                    "misses only (segmented ∩ true)": [s & t for s, t in zip(segmented, true)],
                    "extras only (segmented ∪ true)": [s | t for s, t in zip(segmented, true)]}
        for variant, masks in variants.items():
            t0 = time.perf_counter()
            result = reconstruct(geometry, masks, make_settings("fast", seed=seed), "mask")
            m = evaluate(result.segmentation, label, geometry.volume, geometry.views, masks)
            print(f"{name} {variant:32s} clDice {m['cldice']:.3f}  Tprec {m['tprec']:.3f}  Tsens {m['tsens']:.3f}  "
                  f"Dice {m['dice']:.3f}  components {m.get('components')}/{m.get('components_label')}  "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
