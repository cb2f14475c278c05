"""Where two views place vessels badly: the error of saved reconstructions by the vessel's angle to the epipolar planes.

    .venv/bin/python bench/epipolar_depth.py 'DIR/LAD-*-v1.npz' 'DIR/RCA-*-v1.npz'

Reads runs ``bench/variants.py --save DIR`` kept (segmentation, truth label, geometry; no fit is repeated). Both
skeletons (scikit-image) get a tangent per point (the principal axis of the skeleton points within ``--radius-mm``)
and the angle to the views' epipolar planes (``analysis.views.epipolar_angles_deg``: the largest over pairs of views).
Per bin of that angle, for each glob (a suite):

    truth   points of the truth's skeleton: the share farther than 3 voxels from the result's skeleton (lost), and
            of the others the mean distance (voxels) to it
    result  points of the result's skeleton: the share farther than 3 voxels from the truth's (ghost), of the others the
            mean distance, and the angle (degrees) between the result's tangent and the nearest truth point's

then per case the share of each skeleton under ``views.EPIPOLAR_WEAK_DEG``, and the machine.
"""

from __future__ import annotations

import argparse
import glob
import json
import platform
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from skimage.morphology import skeletonize  # noqa: E402

from SDFCARLib.analysis.views import EPIPOLAR_WEAK_DEG, epipolar_angles_deg  # noqa: E402
from SDFCARLib.geometry import Geometry  # noqa: E402

BINS_DEG = (0.0, 10.0, 20.0, 30.0, 45.0, 90.0)
FAR_VOXELS = 3.0


def skeleton_tangents(points_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """Unit principal axis of the skeleton points within ``radius_mm`` of each (NaN with fewer than 3)."""
    out = np.full(points_mm.shape, np.nan)
    for i, near in enumerate(cKDTree(points_mm).query_ball_point(points_mm, radius_mm)):
        if len(near) >= 3:
            q = points_mm[near] - points_mm[near].mean(axis=0)
            out[i] = np.linalg.eigh(q.T @ q)[1][:, -1]
    return out


def case_rows(path: Path, radius_mm: float):
    saved = np.load(path)
    geometry = Geometry.from_dict(json.loads(path.with_suffix(".json").read_text()))
    sources = [v.source_position for v in geometry.views]
    skeletons = {}
    for kind, key in (("truth", "label"), ("result", "segmentation")):
        voxels = np.argwhere(skeletonize(saved[key].astype(bool)))
        points = geometry.volume.index_to_world(voxels.astype(float))
        tangents = skeleton_tangents(points, radius_mm)
        skeletons[kind] = (voxels, tangents, epipolar_angles_deg(points, tangents, sources))
    rows = {}
    for kind, other in (("truth", "result"), ("result", "truth")):
        voxels, tangents, angles = skeletons[kind]
        distance, nearest = cKDTree(skeletons[other][0]).query(voxels)
        turn = np.degrees(np.arccos(np.clip(np.abs(np.sum(tangents * skeletons[other][1][nearest], axis=1)), 0, 1)))
        rows[kind] = np.c_[angles, distance, turn]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("globs", nargs="+", help="saved runs (.npz beside their .json), one glob per suite")
    parser.add_argument("--radius-mm", type=float, default=2.0, help="skeleton points a tangent is fitted to")
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {platform.system()} {platform.release()}, "
          f"Python {platform.python_version()}")
    for pattern in args.globs:
        paths = sorted(Path(p) for p in glob.glob(pattern))
        if not paths:
            raise SystemExit(f"no saved run matches {pattern}")
        per_case = [case_rows(p, args.radius_mm) for p in paths]
        print(f"\n{pattern}: {len(paths)} runs")
        print("| skeleton | angle to the epipolar planes | points | far (> 3 voxels) | mean distance of the rest (voxels) "
              "| direction off (median, degrees) |")
        print("|---|---|---:|---:|---:|---:|")
        for kind in ("truth", "result"):
            rows = np.concatenate([c[kind] for c in per_case])
            rows = rows[np.isfinite(rows).all(axis=1)]
            for lo, hi in zip(BINS_DEG[:-1], BINS_DEG[1:]):
                inside = (rows[:, 0] >= lo) & ((rows[:, 0] < hi) | (hi == BINS_DEG[-1]))
                near = inside & (rows[:, 1] <= FAR_VOXELS)
                print(f"| {kind} | {lo:g}–{hi:g}° | {inside.sum()} | {np.mean(rows[inside, 1] > FAR_VOXELS):.3f} | "
                      f"{rows[near, 1].mean():.2f} | {np.median(rows[near, 2]):.1f} |")
        for kind in ("truth", "result"):
            shares = [np.nanmean(c[kind][:, 0] < EPIPOLAR_WEAK_DEG) for c in per_case]
            print(f"{kind} skeleton under {EPIPOLAR_WEAK_DEG:g}°, per case: " + " ".join(f"{s:.2f}" for s in shares))


if __name__ == "__main__":
    main()
