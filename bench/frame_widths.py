"""2D widths of straight tubes from masks segmented from simulated angiograms, and from the frames.

For each diameter and seed: a straight tube (``analysis.phantoms.straight_tube``, 30 mm, a random
direction that both views see with ≤ 15 % foreshortening), voxelised at 0.2 mm, its angiograms in
the benchmark's LAO 30 / RAO 30 views at 512² (``realistic.realistic_input``, no motion), the masks
SDFCAR segments from them; then along the true centreline (ends excluded) the width in each view
from the mask (``diameter.projected_widths``) and from the frame (``frame_widths.frame_widths``,
the mask width as the first guess). Prints, per diameter, mean error ± SD and mean absolute error
of each, in mm at the vessel.

    .venv/bin/python bench/frame_widths.py --diameters 1.5 2 3 4 --seeds 3
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's SDFCARLib

from SDFCARLib.analysis.diameter import projected_widths  # noqa: E402
from SDFCARLib.analysis.frame_widths import estimate_psf_sigma_mm, frame_widths  # noqa: E402
from SDFCARLib.analysis.phantoms import grid_around, straight_tube, voxelize_exact  # noqa: E402
from SDFCARLib.angiogram import AngiogramSettings  # noqa: E402
from SDFCARLib.geometry import Geometry, standard_geometry  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402

VIEWS = standard_geometry("lao30-rao30").views


def foreshortening(direction: np.ndarray) -> float:
    return max(1.0 - float(np.sqrt(max(0.0, 1.0 - float(direction @ view.detector_direction) ** 2))) for view in VIEWS)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--diameters", type=float, nargs="+", default=[1.5, 2.0, 3.0, 4.0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--fit-psf-sigma-mm", default=None,
                        help="the blur the fit assumes (default: the simulator's, 0.3 mm): how wrong may it be? "
                             "'auto': estimated from each frame (estimate_psf_sigma_mm)")
    args = parser.parse_args()
    psf = AngiogramSettings().psf_sigma_mm
    auto = args.fit_psf_sigma_mm == "auto"
    fit_psf = psf if args.fit_psf_sigma_mm is None else (None if auto else float(args.fit_psf_sigma_mm))
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; views "
          f"{', '.join(v.describe() for v in VIEWS)}, {VIEWS[0].detector_shape}, psf σ {psf} mm, assumed by the fit {'estimated' if auto else fit_psf} mm", flush=True)
    print("diameter (mm) | mask: error ± SD, MAE (mm) | frame: error ± SD, MAE (mm) | frame points measured | s")
    for diameter in args.diameters:
        errors = {"mask": [], "frame": []}
        measured, total, t0, estimates = 0, 0, time.perf_counter(), []
        for seed in range(args.seeds):
            rng = np.random.default_rng(seed)
            while True:
                direction = rng.normal(size=3)
                direction /= np.linalg.norm(direction)
                if foreshortening(direction) <= 0.15:
                    break
            tube = straight_tube(30.0, diameter, direction)
            grid = grid_around(tube.tree, 0.2)
            realistic = realistic_input(voxelize_exact(tube.tree, grid), Geometry(grid, VIEWS), seed,
                                        RealisticOptions(max_shift_mm=0.0, max_rotation_deg=0.0))
            branch = tube.tree.branches[0]
            s = np.linspace(4.0, 26.0, 45)  # 4 mm clear of the flat ends
            arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(branch.points, axis=0), axis=1))]
            points = np.stack([np.interp(s, arc, branch.points[:, a]) for a in range(3)], axis=1)
            tangents = np.repeat(np.asarray(direction)[None], len(s), axis=0)
            for frame, mask, view in zip(realistic.frames, realistic.masks, VIEWS):
                from_mask = projected_widths(points, tangents, mask, view)
                sigma = estimate_psf_sigma_mm(points, tangents, frame, view, from_mask) if auto else fit_psf
                estimates.append(sigma)
                from_frame = frame_widths(points, tangents, frame, view, from_mask, psf_sigma_mm=sigma)
                errors["mask"] += list(from_mask[np.isfinite(from_mask)] - diameter)
                errors["frame"] += list(from_frame[np.isfinite(from_frame)] - diameter)
                measured += int(np.isfinite(from_frame).sum())
                total += len(s)
        cells = [f"{np.mean(e):+.3f} ± {np.std(e):.3f}, {np.mean(np.abs(e)):.3f}" for e in (errors["mask"], errors["frame"])]
        blur = f" | σ estimated {np.mean(estimates):.3f} ({np.min(estimates):.3f}–{np.max(estimates):.3f})" if auto else ""
        print(f"{diameter:.1f} | {cells[0]} | {cells[1]} | {measured}/{total} | {time.perf_counter() - t0:.0f}{blur}", flush=True)


if __name__ == "__main__":
    main()
