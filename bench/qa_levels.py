"""Reprojection QA numbers on clean and broken simulated cases, to choose the warning levels of qa.py.

    python bench/qa_levels.py [--steps 150] [--out DIR]

Cases: RCA/LAD-like trees (seed 0) on a 64³ grid at 1.5 mm, LAO 30 / RAO 30, 128² detector
at 1.0 mm. Clean: the simulated masks. Broken: view 2's mask shifted by 4 mm at the isocenter (a
mask of another frame), view 2's primary angle off by 8° in the geometry given to the
reconstruction, and a vessel only view 2 shows (a bar added to mask 2), on the RCA-like tree. Prints, per run and view,
Dice, result-only and mask-only share of the mask and the largest blobs (mm² at the isocenter).
"""

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from SDFCARLib.geometry import Geometry, standard_geometry
from SDFCARLib.optimiser import reconstruct
from SDFCARLib.phantoms import lad_tree, make_case, rca_tree
from SDFCARLib.qa import qa_warnings, write_qa_png, qa_title
from SDFCARLib.settings import make_settings


def row(name, result):
    qa = result.report["reprojection_qa"]
    cells = []
    for q in qa:
        blobs = [q["largest_blob"][k]["area_mm2"] if q["largest_blob"][k] else 0.0 for k in ("result_only", "mask_only")]
        cells.append(f"{q['dice']:.3f} | {100 * q['share_of_mask']['result_only']:.1f} / {100 * q['share_of_mask']['mask_only']:.1f} "
                     f"| {blobs[0]:.1f} / {blobs[1]:.1f}")
    warned = len(qa_warnings(qa))
    print(f"| {name} | " + " | ".join(cells) + f" | {warned} |", flush=True)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--out", default="")
    args = parser.parse_args()
    geometry = standard_geometry("lao30-rao30", volume_shape=(64, 64, 64), spacing_mm=1.5,
                                 detector_shape=(128, 128), detector_spacing_mm=1.0)
    settings = make_settings("fast", steps=args.steps, threads=2)
    print("| run | view 1 Dice | result-only / mask-only (% of mask) | largest blobs (mm²) | view 2 Dice | "
          "result-only / mask-only (% of mask) | largest blobs (mm²) | warnings |")
    for tree in (rca_tree(0), lad_tree(0)):
        case = make_case(tree, geometry)
        masks = [m.astype(bool) for m in case.masks]
        name = f"{tree.name}"
        t = time.perf_counter()
        result = reconstruct(geometry, masks, settings)
        row(f"{name} clean ({time.perf_counter() - t:.0f} s)", result)
        if args.out:
            for n, (p, m) in enumerate(result.qa_masks, start=1):
                write_qa_png(Path(args.out) / f"{name}_clean_view{n}.png", None, p, m, qa_title(n, result.report["reprojection_qa"][n - 1]))
        if not tree.name.startswith("RCA"):
            continue  # the broken runs on one tree only: about 3 min a run on the loaded 2-core machine
        shift_px = int(round(4.0 / geometry.views[1].isocenter_pixel_spacing_mm[0]))
        shifted = [masks[0], np.roll(masks[1], shift_px, axis=0)]
        row(f"{name} mask 2 shifted 4 mm", reconstruct(geometry, shifted, settings))
        wrong = Geometry(geometry.volume, (geometry.views[0], dataclasses.replace(geometry.views[1], primary_deg=geometry.views[1].primary_deg + 8.0)))
        row(f"{name} view 2 angle +8°", reconstruct(wrong, masks, settings))
        extra = masks[1].copy()
        extra[100:104, 20:70] = True
        result = reconstruct(geometry, [masks[0], extra], settings)
        row(f"{name} bar only in mask 2", result)
        if args.out:
            for n, (p, m) in enumerate(result.qa_masks, start=1):
                write_qa_png(Path(args.out) / f"{name}_bar_view{n}.png", None, p, m, qa_title(n, result.report["reprojection_qa"][n - 1]))


if __name__ == "__main__":
    main()
