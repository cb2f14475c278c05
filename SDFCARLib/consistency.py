"""Do the masks and the geometry agree? An epipolar check of every view against the others.

Why
    A wrong angle sign, a secondary angle of the wrong sense, a mask drawn on another frame or a
    large patient motion make the views disagree: no 3D tree explains both masks, and minutes of
    optimisation end in ghosts and lost vessels. With the masks and the geometry alone this shows
    in seconds.

Measure
    A centreline pixel p of view k has a partner when its ray passes through a point that lies on
    the vessels of every other view: partner(p) = max over points x on the ray of
    Π_j exp(−d_j(x)² / 2σ²), d_j the distance (mm at the isocenter) from x's projection to mask j,
    read bilinearly from the distance map (exact to a fraction of a pixel). A view's consistency is
    the mean over its centreline pixels (about 1 for a correct pair; bench/RESULTS.md has the
    values measured on correct, swapped and sign-flipped pairs). Centreline pixels weigh every
    vessel by its length, not its width.

Views along one line
    Two views whose projection lines are (nearly) parallel, either way round, see the same shadow: depth
    between them is not resolved (``view_separation_warnings``). 3D-QCA systems ask for views at least 25°
    apart; a separation under 1° is a run given twice.

What it cannot see
    A ray crosses many vessels of the other view, so the measure is lenient: rigid motions of a
    few millimetres between the acquisitions, and swapping the two views of a mirror-symmetric
    pair (LAO 30 / RAO 30), leave it near 1 — two views alone cannot tell these apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np
from scipy import ndimage
from skimage.morphology import skeletonize

from .geometry import CArmView, Geometry


@dataclass(frozen=True)
class ConsistencyOptions:
    sigma_mm: float = 0.5  # how far (at the isocenter) a ray may pass beside a vessel and still meet it
    max_rays_per_view: int = 600  # centreline pixels per view (a fixed random subset beyond it)
    ray_step_mm: float = 0.4  # sampling along the rays, below the thinnest vessel's width
    warn_below: float = 0.97  # below this: a warning (correct pairs measure 1.000, faults ≤ 0.94; RESULTS §8)
    seed: int = 0


def _centreline_pixels(mask: np.ndarray, limit: int, rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    rows, cols = np.nonzero(skeletonize(mask))
    if rows.size > limit:
        keep = np.sort(rng.choice(rows.size, limit, replace=False))
        rows, cols = rows[keep], cols[keep]
    return rows.astype(np.float64), cols.astype(np.float64)


def _distance_at(distance_mm: np.ndarray, view: CArmView, points: np.ndarray) -> np.ndarray:
    row, col, _ = view.project(points.reshape(-1, 3))
    inside = np.isfinite(row) & np.isfinite(col)
    coords = np.vstack([np.where(inside, row, -1e6), np.where(inside, col, -1e6)])
    # Off the detector a view shows no vessel: far from its vessels.
    values = ndimage.map_coordinates(distance_mm, coords, order=1, mode="constant", cval=1e3)
    return values.reshape(points.shape[:-1])


def view_consistency(geometry: Geometry, masks: Sequence[np.ndarray],
                     options: ConsistencyOptions = ConsistencyOptions()) -> List[float]:
    """Per view, the share of its centreline pixels whose ray meets the vessels of every other view."""
    views = list(geometry.views)
    if len(masks) != len(views):
        raise ValueError(f"{len(masks)} masks for {len(views)} views")
    masks = [np.asarray(m, dtype=bool) for m in masks]
    if len(views) < 2:
        return [1.0] * len(views)
    rng = np.random.default_rng(options.seed)
    distance_mm = [ndimage.distance_transform_edt(~m) * min(v.isocenter_pixel_spacing_mm) for m, v in zip(masks, views)]
    grid = geometry.volume
    half_depth = 0.5 * float(np.linalg.norm(np.asarray(grid.shape) * np.asarray(grid.spacing_mm)))
    depths = np.arange(-half_depth, half_depth + 1e-9, options.ray_step_mm)
    centre = np.asarray(grid.center_mm, dtype=np.float64)
    out = []
    for k, (mask, view) in enumerate(zip(masks, views)):
        rows, cols = _centreline_pixels(mask, options.max_rays_per_view, rng)
        if rows.size == 0:
            out.append(0.0)
            continue
        origin, direction = view.rays(rows, cols)
        # The stretch of each ray across the volume: ± half its diagonal around the grid's centre.
        along = (centre - origin) @ direction.T
        points = origin + (along[:, None] + depths[None, :])[..., None] * direction[:, None, :]
        agreement = np.ones(points.shape[:2])
        for j, other in enumerate(views):
            if j != k:
                agreement *= np.exp(-0.5 * (_distance_at(distance_mm[j], other, points) / options.sigma_mm) ** 2)
        out.append(float(agreement.max(axis=1).mean()))
    return out


def consistency_warnings(consistency: Sequence[float], options: ConsistencyOptions = ConsistencyOptions()) -> List[str]:
    """A warning for every view whose consistency is below ``options.warn_below``, naming what to check."""
    warnings = []
    for n, value in enumerate(consistency, start=1):
        if value < options.warn_below:
            warnings.append(
                f"view {n}: only {100 * value:.0f} % of its vessel centreline has a partner in the other view(s) "
                "along the epipolar lines; check the angle signs (LAO +, RAO −, CRA +, CAU −), that each mask "
                "belongs to its view and to the same cardiac phase and is not transposed or flipped, and the SID/SOD "
                "values")
    return warnings


#: the least angle between the projection lines of the two views furthest apart without a warning (3D-QCA
#: systems ask for two views at least 25° apart), and the separation under which two views are one
MIN_VIEW_SEPARATION_DEG = 25.0
SAME_VIEW_SEPARATION_DEG = 1.0


def view_separation_deg(a: CArmView, b: CArmView) -> float:
    """Angle (degrees, 0–90) between two views' projection lines; opposite views (180° apart) are 0."""
    cosine = abs(float(np.dot(a.detector_direction, b.detector_direction)))
    return float(np.degrees(np.arccos(min(cosine, 1.0))))


def view_separation_warnings(geometry: Geometry) -> List[str]:
    """Warnings (possibly none) about views that look along the same line: a run given twice, or views too close
    in angle for any pair to resolve depth."""
    views = geometry.views
    out: List[str] = []
    separations = {(i, j): view_separation_deg(views[i], views[j])
                   for i in range(len(views)) for j in range(i + 1, len(views))}
    for (i, j), angle in separations.items():
        if angle < SAME_VIEW_SEPARATION_DEG:
            out.append(f"views {i + 1} and {j + 1} look along the same line ({views[i].describe()} and "
                       f"{views[j].describe()}, {angle:.1f}° apart): the same run given twice, or the same "
                       "projection from opposite sides; give views of different angles")
    widest = max(separations.values(), default=0.0)
    if SAME_VIEW_SEPARATION_DEG <= widest < MIN_VIEW_SEPARATION_DEG:  # under 1°: named pair by pair above
        out.append(f"the views are at most {widest:.1f}° apart (the angle between their projection lines): depth "
                   f"is poorly resolved and the tree will be smeared along the views' axis; give views at least "
                   f"{MIN_VIEW_SEPARATION_DEG:g}° apart")
    return out
