"""The frames' vessel contrast under their masks: own frame, the same frame inverted, the other view's frame.

    .venv/bin/python bench/frame_contrast.py --cases 3            # RCA and LAD trees, seeds 0–2
    .venv/bin/python bench/frame_contrast.py --tubes              # and the 54 stenosed tubes of bench/qca.py

Trees: the realistic static protocol (LAO 30 / RAO 30, masks segmented from simulated angiograms; coarse grid 80³ at
1.3 mm and 192² at 0.8 mm unless --paper-grid). Tubes: ``bench/qca.py``'s 54 stenosed tubes, masks segmented from their
simulated angiograms (512² at 0.278 mm). Linear frames and the same frames processed for display. Per view,
``analysis.frame_contrast.vessel_contrast`` read under the whole mask and under its core, of: its own frame under its
mask, that frame inverted (largest + smallest − grey), and the other view's frame under its mask (the frames given in
the wrong order). Prints each group's range, how many views fall below the refusal and warning thresholds, and the
machine.
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
GROUPS = ("own", "inverted", "other view's")


def tree_pairs(args):
    for suite, make_tree in (("rca", rca_tree), ("lad", lad_tree)):
        args.suite = suite
        geometry = protocol_setup(args, PROTOCOL, f"{args.first}..{args.first + args.cases - 1}")
        for seed in range(args.first, args.first + args.cases):
            label = voxelize(make_tree(seed), geometry.volume)
            for display in (False, True):
                options = dataclasses.replace(RealisticOptions(**REALISTIC_PROTOCOLS[PROTOCOL]), display=display)
                realistic = realistic_input(label, geometry, seed, options)
                yield f"{suite.upper()}-{seed}", display, realistic.frames, realistic.masks


def tube_pairs():
    import bench.qca as qca
    from SDFCARLib.masks import MaskError

    for display in (False, True):
        qca.DISPLAY_FRAMES = display
        for n, (name, phantom, _) in enumerate(qca.tube_cases()):
            try:
                masks, _, frames, _ = qca.segmented_masks(phantom.tree, n)
            except MaskError:  # seen end-on in one view: bench/qca.py leaves it out too
                continue
            yield name, display, frames, masks


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--cases", type=int, default=3)
    parser.add_argument("--tubes", action="store_true", help="the 54 stenosed tubes as well (about 10 minutes)")
    add_grid_arguments(parser)
    args = parser.parse_args()
    t0 = time.perf_counter()
    suites = {"trees": tree_pairs(args)}
    if args.tubes:
        suites["tubes"] = tube_pairs()
    for suite, pairs in suites.items():
        table = {(core, group): [] for core in (False, True) for group in GROUPS}
        lowest = []
        for name, display, frames, masks in pairs:
            images = [np.asarray(f, np.float64) for f in frames]
            for n, (image, mask) in enumerate(zip(images, masks)):
                for core in (False, True):
                    row = [vessel_contrast(x, mask, core) for x in (image, image.max() + image.min() - image, images[1 - n])]
                    for group, value in zip(GROUPS, row):
                        if value is not None:
                            table[core, group].append(value)
                    if core and row[0] is not None:
                        lowest.append((row[0], name, "DISP" if display else "LIN", n + 1, int(np.count_nonzero(mask))))
        print(f"\n{suite}: refused below {INVERTED_CONTRAST:g}, warned below {MIN_VESSEL_CONTRAST:g}")
        for (core, group), values in table.items():
            v = np.asarray(values)
            print(f"  {'core' if core else 'whole mask':10s} {group:13s} {len(v):4d} views: {v.min():6.2f} … {v.max():6.2f}; "
                  f"below {INVERTED_CONTRAST:g}: {int((v < INVERTED_CONTRAST).sum())}, below {MIN_VESSEL_CONTRAST:g}: "
                  f"{int((v < MIN_VESSEL_CONTRAST).sum())}", flush=True)
        print("  own frames' lowest (core): " + "; ".join(f"{name} {kind} view {n} {c:.2f} ({px} px)"
                                                       for c, name, kind, n, px in sorted(lowest)[:6]))
    print(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
