"""Vessels every view shows and the result leaves out, filled in from the hull of the unexplained mask pixels.

Why
    On masks segmented from images the fit leaves about a sixth of the true centreline empty although both masks
    show it (bench/RESULTS.md §64a, §97): where the occupancy saturated early, σ(−α·s) gives the fit almost no
    gradient, and the stretch is never placed. Such a vessel's pixels stay unexplained in every view. Few of a
    mask's pixels are unexplained at the end of a fit, so the hull of the unexplained pixels alone holds the missing
    vessel and few of the crossings (ghosts) that the hull of the whole masks holds.

Method
    1. Per view, the mask's pixels farther than ``EXPLAINED_MARGIN_MM`` (on the detector) from the result's
       reprojection are unexplained (a border a pixel or two off is not); a pixel the view cannot see (``unknown``)
       is not; 8-connected blobs smaller than ``MIN_BLOB_MM2`` (on the detector) are a border's noise and dropped.
    2. The strict visual hull of those pixels, inside the support and outside the result, is the candidate fill.
    3. Its skeleton pieces whose views see different widths are dropped (``width_agreement.disagreeing_pieces`` at
       ``MIN_WIDTH_RATIO``): where two *different* unexplained vessels' rays cross.
    4. Its 26-connected components whose skeleton is shorter than ``MIN_LENGTH_MM`` are dropped: a crossing of two
       blobs is as short as the blobs are wide, a missing vessel's stretch is longer.
    Joining the fill to the tree (and dropping what stays apart) is the optimiser's step (``optimiser.fill_unexplained``),
    through the field as every other join.

Units: mm (on the detector for the pixel rules, in the volume for lengths); the masks are detector images.
"""

from __future__ import annotations

import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage
from skimage.morphology import skeletonize

from .geometry import CArmView, Geometry
from .hull import visual_hull
from .metrics import component_labels
from .width_agreement import disagreeing_pieces

EXPLAINED_MARGIN_MM = 0.55  # a mask pixel this close (detector mm) to the reprojection counts as explained: 2 px at 0.278 mm
MIN_BLOB_MM2 = 3.0  # unexplained blobs smaller than this (detector mm², about 40 px at 0.278 mm) are dropped
MIN_WIDTH_RATIO = 0.8  # the fill's pieces whose views' widths agree less than this (smaller / larger) are dropped
MIN_LENGTH_MM = 2.0  # the fill's components whose skeleton is shorter than this are dropped


def unexplained_pixels(mask: np.ndarray, explained: np.ndarray, view: CArmView,
                       unknown: Optional[np.ndarray] = None) -> np.ndarray:
    """The mask's pixels farther than ``EXPLAINED_MARGIN_MM`` from ``explained`` (the result's reprojection), in
    blobs of at least ``MIN_BLOB_MM2``, less the ``unknown`` ones (bool detector images)."""
    mask, explained = np.asarray(mask, bool), np.asarray(explained, bool)
    if mask.shape != tuple(view.detector_shape) or explained.shape != mask.shape:
        raise ValueError(f"mask {mask.shape} and reprojection {explained.shape} must have the detector's shape "
                         f"{tuple(view.detector_shape)}")
    pixel_mm = float(np.mean(view.pixel_spacing_mm))
    margin_px = max(1, int(round(EXPLAINED_MARGIN_MM / pixel_mm)))
    left = mask & ~ndimage.binary_dilation(explained, iterations=margin_px) if explained.any() else mask.copy()
    if unknown is not None:
        left &= ~np.asarray(unknown, bool)
    labels, count = ndimage.label(left, structure=np.ones((3, 3)))
    if not count:
        return left
    areas_mm2 = ndimage.sum(left, labels, np.arange(1, count + 1)) * float(np.prod(view.pixel_spacing_mm))
    return np.isin(labels, 1 + np.flatnonzero(areas_mm2 >= MIN_BLOB_MM2))


def unexplained_fill(segmentation: np.ndarray, masks: Sequence[np.ndarray], explained: Sequence[np.ndarray],
                     geometry: Geometry, support: Optional[np.ndarray] = None,
                     unknown: Optional[Sequence[Optional[np.ndarray]]] = None,
                     piece_mm: float = 6.0) -> Tuple[np.ndarray, Dict[str, Any]]:
    """The voxels to add to ``segmentation`` where every view shows vessel it does not explain (module docstring).

    ``explained``: per view the segmentation's reprojected mask; ``support``: where the fill may lie (None: anywhere);
    ``unknown``: per view None or the pixels whose mask value says nothing; ``piece_mm``: the width check's pieces.
    Returns (fill, info: unexplained pixels per view, candidate, width-dropped, short-dropped and filled voxels, seconds).
    """
    t0 = time.perf_counter()
    segmentation = np.asarray(segmentation, bool)
    views = geometry.views
    if not (len(masks) == len(explained) == len(views)):
        raise ValueError(f"{len(masks)} masks and {len(explained)} reprojections for {len(views)} views: give one of each per view")
    if segmentation.shape != tuple(geometry.volume.shape):
        raise ValueError(f"segmentation {segmentation.shape} is not on the geometry's grid {tuple(geometry.volume.shape)}")
    unseen: List[Optional[np.ndarray]] = list(unknown) if unknown is not None else [None] * len(views)
    left = [unexplained_pixels(m, e, v, u) for m, e, v, u in zip(masks, explained, views, unseen)]
    info: Dict[str, Any] = {"unexplained_pixels": [int(p.sum()) for p in left], "candidate_voxels": 0,
                            "width_dropped_voxels": 0, "short_dropped_voxels": 0, "fill_voxels": 0}
    fill = np.zeros(segmentation.shape, bool)
    if all(p.any() for p in left):
        fill = visual_hull(left, views, geometry.volume) & ~segmentation
        if support is not None:
            fill &= np.asarray(support, bool)
    info["candidate_voxels"] = int(fill.sum())
    if fill.any():
        agreeing, _ = disagreeing_pieces(fill, masks, geometry, MIN_WIDTH_RATIO, piece_mm, unknown=unknown)
        info["width_dropped_voxels"] = int((fill & ~agreeing).sum())
        fill = agreeing
    if fill.any():
        labels, sizes = component_labels(fill)
        count = sizes.size
        voxel_mm = float(np.mean(geometry.volume.spacing_mm))
        lengths_mm = ndimage.sum(skeletonize(fill).astype(bool), labels, np.arange(1, count + 1)) * voxel_mm
        long_enough = np.isin(labels, 1 + np.flatnonzero(lengths_mm >= MIN_LENGTH_MM))
        info["short_dropped_voxels"] = int((fill & ~long_enough).sum())
        fill = long_enough
    info.update(fill_voxels=int(fill.sum()), seconds=time.perf_counter() - t0)
    return fill, info
