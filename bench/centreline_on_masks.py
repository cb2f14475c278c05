"""The main branch's centreline re-placed on the two masks' midlines, offline on saved QCA reconstructions (RESULTS §33f).

    .venv/bin/python bench/qca.py --suite recon --cases 10 --max-foreshortening-pct 15 --masks segmented --save DIR
    .venv/bin/python bench/centreline_on_masks.py DIR --max-foreshortening-pct 15
    (and with the clean masks: qca.py without --masks, this script with --masks clean)

§33a: the segmented masks' midlines lie within 0.1 mm of the true axis, the reconstructed lumen's
centre 0.45 mm (the frames' path lengths bend it, §33b). Here each point of the main branch's
centreline (``analyse_volume``'s tree, the branch from the ostium) is moved by the least displacement
across the branch that puts both its projections on the masks' midlines (``mask_midlines.measure_view``
across the branch's own projected course, ``mask_midlines`` triangulation); displacements over
``--max-shift-mm`` or without an edge pair in both views are left out and interpolated, then smoothed
along the branch (Gaussian ``--smoothing-mm``). Prints, per tube, the 3D length error, the mean
distance from the true centreline (3 mm from either end left out) and the worst view's foreshortening
error of the whole branch, before and after, and the machine. Nothing of the product changes.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import mask_midlines  # noqa: E402
import qca  # noqa: E402
from SDFCARLib.analysis.phantoms import stenosed_tube  # noqa: E402
from SDFCARLib.analysis.pipeline import analyse_volume  # noqa: E402
from SDFCARLib.analysis.views import foreshortening  # noqa: E402
from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.io import read_volume  # noqa: E402


def on_masks(points: np.ndarray, masks, views, radius_mm: float, max_shift_mm: float, smoothing_mm: float):
    """The polyline moved onto the masks' midlines (module docstring); and the share of points measured."""
    tangents = np.gradient(points, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    measured = [mask_midlines.measure_view(m, v, points, tangents, np.full(len(points), radius_mm)) for m, v in zip(masks, views)]
    shift = mask_midlines.triangulate(points, tangents, measured, views)
    ok = np.isfinite(shift).all(axis=1)
    ok[ok] = np.linalg.norm(shift[ok], axis=1) <= max_shift_mm
    if ok.sum() < 5:
        return points, float(ok.mean())
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    filled = np.stack([np.interp(arc, arc[ok], shift[ok, a]) for a in range(3)], 1)
    filled = ndimage.gaussian_filter1d(filled, smoothing_mm / np.median(np.diff(arc)), axis=0, mode="nearest")
    return points + filled, float(ok.mean())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("load", type=Path, help="a folder bench/qca.py --save wrote (recon suite, --masks segmented)")
    ap.add_argument("--max-foreshortening-pct", type=float, default=None, help="as the run that saved them")
    ap.add_argument("--masks", choices=("segmented", "clean"), default="segmented", help="as the run that saved them")
    ap.add_argument("--max-shift-mm", type=float, default=1.5)
    ap.add_argument("--smoothing-mm", type=float, default=1.0)
    args = ap.parse_args()
    t_start = time.perf_counter()
    before, after = [], []
    for n, (name, kw) in enumerate(qca.RECON_TUBES):
        path = args.load / f"recon{n}_occupancy.nrrd"
        if not path.exists():
            continue
        phantom = stenosed_tube(length_mm=40.0, direction=qca.tube_direction(n, args.max_foreshortening_pct), **kw)
        masks = (qca.segmented_masks(phantom.tree, n)[0] if args.masks == "segmented"
                 else [qca.render_mask(phantom.tree, v) for v in qca.VIEWS])
        occupancy, grid = read_volume(path)
        views = Geometry.from_dict(json.loads((args.load / f"recon{n}_geometry.json").read_text())).views
        ostium = np.asarray(phantom.truth["ostium_mm"], float)
        result = analyse_volume(occupancy, grid, level=0.5, views=views, masks=masks, ostium_mm=ostium, best_view=False)
        main_branch = min((b for b in result.tree.branches if b.parent_id is None),
                          key=lambda b: np.linalg.norm(b.points_mm[0] - ostium))
        truth = phantom.tree.branches[0].points
        nearest = cKDTree(truth)

        def scores(points):
            arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
            inner = (arc >= 3.0) & (arc <= arc[-1] - 3.0)
            fs = max(abs(foreshortening(points, v) - foreshortening(truth, v)) for v in qca.VIEWS)
            return (100 * (arc[-1] - phantom.truth["length_mm"]) / phantom.truth["length_mm"],
                    float(nearest.query(points[inner])[0].mean()), 100 * fs)

        moved, share = on_masks(main_branch.points_mm, masks, views, 0.5 * kw["diameter_mm"], args.max_shift_mm, args.smoothing_mm)
        before.append(scores(main_branch.points_mm))
        after.append(scores(moved))
        (a, b) = before[-1], after[-1]
        print(f"{name:20s} measured {share:.2f}  length {a[0]:+.2f} → {b[0]:+.2f} %  from the axis {a[1]:.3f} → {b[1]:.3f} mm  "
              f"foreshortening {a[2]:.2f} → {b[2]:.2f} points", flush=True)
    a, b = np.array(before), np.array(after)
    for k, label in enumerate(("3D length error (%)", "from the true axis (mm)", "foreshortening error (points)")):
        print(f"{label}: {a[:, k].mean():+.2f} ± {a[:, k].std():.2f} (max |·| {np.abs(a[:, k]).max():.2f}) → "
              f"{b[:, k].mean():+.2f} ± {b[:, k].std():.2f} (max |·| {np.abs(b[:, k]).max():.2f})"
              + (f"; within 2 %: {int(np.sum(np.abs(a[:, k]) <= 2))} → {int(np.sum(np.abs(b[:, k]) <= 2))} of {len(a)}" if k == 0 else ""))
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
