"""Visual hull of two (or more) vessel masks.

The visual hull is every voxel whose centre projects inside the mask of every view that sees it.
It is the largest shape the masks allow and includes "ghost" branches wherever vessels of
different views share epipolar lines; it serves twice:

* as a baseline in every report (a reconstruction that does not beat it is not working), and
* dilated by a margin, as the support of the fast presets: voxels outside it cannot be vessel
  without contradicting a mask, so the field is evaluated only inside it.

Field of view
    A view constrains only the voxels it sees: those whose centre projects onto its detector and,
    when a ``fields_of_view`` image is given for it, onto an exposed (True) pixel of that image
    (not the collimated border). A voxel that projects off view k's detector or into its
    collimated border is not evidence against a vessel there: view k's mask is empty at that spot
    because the view did not look, not because nothing is there. So such a voxel is kept when
    every view that sees it agrees (its mask, widened by the margin, covers it) and at least one
    view sees it (``fov_aware=True``, what ``support_mask`` uses). A region seen by one view only is
    the back-projection of that view's mask clipped to the grid: weakly constrained, a sheet as
    deep as the grid. Two bounds keep it from swamping the support: the grid is placed on where
    the views' back-projections meet (``region.py``) rather than made large, and such voxels are
    kept only within ``one_view_reach_mm`` of the part every view sees and agrees on (a vessel that
    leaves a view's field continues from there; beyond that reach one view cannot place it in
    depth anyway). On the real phantom pair of bench/RESULTS.md the one-view sheets tripled the
    support of the placed grid without the reach, and add a few per cent with 15 mm. Of three or
    more views, a voxel two of them see is placed in depth by those two and is not bounded so.

    The baseline keeps its definition, the strict hull (``fov_aware=False``, the default: every
    view must see the voxel and agree), so that its numbers stay comparable across versions and
    it never credits a view with what it did not see; ``region.place_volume`` uses the strict hull
    too, to find where the masks meet.
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import numpy as np
from scipy import ndimage

from .geometry import CArmView, VolumeGrid
from .projector import footprint_radius_px
from .settings import RegionSettings

ONE_VIEW_REACH_MM = RegionSettings.one_view_reach_mm  # how far beyond the part all views see the support follows a single view


def _distance_to_mask_px(mask: np.ndarray) -> np.ndarray:
    """Distance (pixels) from every pixel to the nearest mask pixel (0 on the mask)."""
    if not mask.any():
        return np.full(mask.shape, np.inf)
    return ndimage.distance_transform_edt(~mask)


def _field_of_view(field_of_view: Optional[np.ndarray], shape: Sequence[int], n: int) -> Optional[np.ndarray]:
    if field_of_view is None:
        return None
    fov = np.asarray(field_of_view, dtype=bool)
    if fov.shape != tuple(shape):
        raise ValueError(f"view {n}: field-of-view image shape {fov.shape} differs from the detector shape "
                         f"{tuple(shape)}; give one boolean image per view, True where the view is exposed")
    return fov


def visual_hull(
    masks: Sequence[np.ndarray],
    views: Sequence[CArmView],
    grid: VolumeGrid,
    margin_px: Union[float, Sequence[float]] = 0.0,
    include_footprint: bool = False,
    slab: int = 16,
    fields_of_view: Optional[Sequence[Optional[np.ndarray]]] = None,
    fov_aware: bool = False,
    one_view_reach_mm: Optional[float] = None,
) -> np.ndarray:
    """Boolean volume ``[i, j, k]`` of voxels whose centres project onto the mask of every view that sees them.

    ``margin_px`` (one value, or one per view) widens each mask by that many pixels;
    ``include_footprint`` adds each voxel's own shadow radius, so that a voxel whose shadow merely
    touches the mask is kept. ``fields_of_view``: per view None (the whole detector) or a boolean
    detector image, True where the view is exposed. ``fov_aware=False`` (the default, the
    baseline's definition): every view must see the voxel and agree (the strict hull);
    ``fov_aware=True``: only the views that see it must agree, and one must see it (the support's
    rule). ``one_view_reach_mm`` (with ``fov_aware``): keep a voxel that not every view sees only
    within this distance of the voxels every view sees and agrees on; None: no limit. See the
    module docstring.
    """
    if len(masks) != len(views):
        raise ValueError(f"{len(masks)} masks for {len(views)} views")
    margins = [float(margin_px)] * len(views) if np.ndim(margin_px) == 0 else [float(m) for m in margin_px]
    if len(margins) != len(views):
        raise ValueError(f"{len(margins)} margins for {len(views)} views")
    fovs = list(fields_of_view) if fields_of_view is not None else [None] * len(views)
    if len(fovs) != len(views):
        raise ValueError(f"{len(fovs)} field-of-view images for {len(views)} views")
    hull = np.ones(grid.shape, dtype=bool)
    seen_by_any = np.zeros(grid.shape, dtype=bool)
    seen_by_all = np.ones(grid.shape, dtype=bool)
    seeing_views = np.zeros(grid.shape, dtype=np.uint8)  # how many views see each voxel (fov_aware)
    for n, (mask, view, margin, fov) in enumerate(zip(masks, views, margins, fovs), start=1):
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != tuple(view.detector_shape):
            raise ValueError(f"mask shape {mask.shape} differs from the detector shape {tuple(view.detector_shape)}")
        fov = _field_of_view(fov, view.detector_shape, n)
        distance = _distance_to_mask_px(mask)
        allowed = margin + (footprint_radius_px(view, grid) if include_footprint else 0.0)
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
            inside = (ri >= 0) & (ri < rows) & (ci >= 0) & (ci < cols)  # NaN (behind the source) is outside
            rr, cc = ri[inside].astype(np.int64), ci[inside].astype(np.int64)
            seen = inside.copy()
            if fov is not None:
                seen[inside] = fov[rr, cc]
            ok = np.zeros(idx.shape, dtype=bool)
            ok[inside] = distance[rr, cc] <= allowed
            if fov_aware:
                ok |= ~seen  # a view does not constrain what it does not see
                seen_flat = seen_by_any[i0:i1].reshape(-1)
                seen_flat[np.flatnonzero(candidates)[seen]] = True
                seen_by_any[i0:i1] = seen_flat.reshape(seen_by_any[i0:i1].shape)
                all_flat = seen_by_all[i0:i1].reshape(-1)
                all_flat[np.flatnonzero(candidates)[~seen]] = False
                seen_by_all[i0:i1] = all_flat.reshape(seen_by_all[i0:i1].shape)
                count_flat = seeing_views[i0:i1].reshape(-1)
                count_flat[np.flatnonzero(candidates)[seen]] += 1
                seeing_views[i0:i1] = count_flat.reshape(seeing_views[i0:i1].shape)
            else:
                ok &= seen
            sub = hull[i0:i1].reshape(-1)
            sub[np.flatnonzero(candidates)[~ok]] = False
            hull[i0:i1] = sub.reshape(hull[i0:i1].shape)
    if fov_aware:
        hull &= seen_by_any  # a voxel no view sees is not constrained at all: leave it out
        # two views place a voxel in depth: of three views, those two are enough where the third cannot see
        placed = seen_by_all | (seeing_views >= 2)
        one_view = hull & ~placed
        if one_view_reach_mm is not None and one_view.any():
            every_view = hull & seen_by_all
            if every_view.any():
                near = ndimage.distance_transform_edt(~every_view, sampling=grid.spacing_mm) <= one_view_reach_mm
            else:
                near = np.zeros(grid.shape, dtype=bool)
            hull &= placed | near
    return hull


def support_mask(
    masks: Sequence[np.ndarray],
    views: Sequence[CArmView],
    grid: VolumeGrid,
    margin_mm: float = 0.5,
    fields_of_view: Optional[Sequence[Optional[np.ndarray]]] = None,
    one_view_reach_mm: Optional[float] = ONE_VIEW_REACH_MM,
) -> np.ndarray:
    """The field-of-view-aware hull widened by each voxel's footprint and ``margin_mm`` (at the isocenter),
    following a single view at most ``one_view_reach_mm`` beyond the part every view sees."""
    margins = [margin_mm * v.magnification / min(v.pixel_spacing_mm) for v in views]
    return visual_hull(masks, views, grid, margin_px=margins, include_footprint=True, fields_of_view=fields_of_view,
                       fov_aware=True, one_view_reach_mm=one_view_reach_mm)
