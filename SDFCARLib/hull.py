"""Visual hull of two (or more) vessel masks.

The visual hull is every voxel whose centre projects inside the mask of every view. It is the
largest shape the masks allow and includes "ghost" branches wherever vessels of different views
share epipolar lines; it serves twice:

* as a baseline in every report (a reconstruction that does not beat it is not working), and
* dilated by a margin, as the support of the fast presets: voxels outside it cannot be vessel
  without contradicting a mask, so the field is evaluated only inside it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy import ndimage

from .geometry import CArmView, VolumeGrid
from .projector import footprint_radius_px


def _distance_to_mask_px(mask: np.ndarray) -> np.ndarray:
    """Distance (pixels) from every pixel to the nearest mask pixel (0 on the mask)."""
    if not mask.any():
        return np.full(mask.shape, np.inf)
    return ndimage.distance_transform_edt(~mask)


def visual_hull(
    masks: Sequence[np.ndarray],
    views: Sequence[CArmView],
    grid: VolumeGrid,
    margin_px: float = 0.0,
    include_footprint: bool = False,
    slab: int = 16,
) -> np.ndarray:
    """Boolean volume ``[i, j, k]`` of voxels whose centres project onto every mask.

    ``margin_px`` widens each mask by that many pixels; ``include_footprint`` adds each voxel's
    own shadow radius, so that a voxel whose shadow merely touches the mask is kept. With both
    left at their defaults this is the plain visual hull (nearest pixel of the centre).
    """
    if len(masks) != len(views):
        raise ValueError(f"{len(masks)} masks for {len(views)} views")
    hull = np.ones(grid.shape, dtype=bool)
    for mask, view in zip(masks, views):
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != tuple(view.detector_shape):
            raise ValueError(f"mask shape {mask.shape} differs from the detector shape {tuple(view.detector_shape)}")
        distance = _distance_to_mask_px(mask)
        allowed = margin_px + (footprint_radius_px(view, grid) if include_footprint else 0.0)
        rows, cols = mask.shape
        # Slabs along i keep the memory of the projected coordinates small.
        for i0 in range(0, grid.shape[0], slab):
            i1 = min(i0 + slab, grid.shape[0])
            flat = np.arange(i0 * grid.shape[1] * grid.shape[2], i1 * grid.shape[1] * grid.shape[2])
            candidates = hull[i0:i1].reshape(-1)
            if not candidates.any():
                continue
            idx = flat[candidates]
            r, c, _ = view.project(grid.voxel_centers(idx))
            ri, ci = np.rint(r), np.rint(c)
            inside = (ri >= 0) & (ri < rows) & (ci >= 0) & (ci < cols)
            ok = np.zeros(idx.shape, dtype=bool)
            ok[inside] = distance[ri[inside].astype(np.int64), ci[inside].astype(np.int64)] <= allowed
            sub = hull[i0:i1].reshape(-1)
            sub[np.flatnonzero(candidates)[~ok]] = False
            hull[i0:i1] = sub.reshape(hull[i0:i1].shape)
    return hull


def support_mask(
    masks: Sequence[np.ndarray],
    views: Sequence[CArmView],
    grid: VolumeGrid,
    margin_mm: float = 0.5,
) -> np.ndarray:
    """The hull widened by each voxel's footprint and ``margin_mm`` (at the isocenter)."""
    margins = [margin_mm * v.magnification / min(v.pixel_spacing_mm) for v in views]
    hull = np.ones(grid.shape, dtype=bool)
    for mask, view, margin_px in zip(masks, views, margins):
        hull &= visual_hull([mask], [view], grid, margin_px=margin_px, include_footprint=True)
    return hull
