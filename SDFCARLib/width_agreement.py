"""Width agreement of the views: pieces of a reconstruction whose views see different vessel widths.

Why
    A vessel is a tube, so every view sees the same diameter across it, scaled by the magnification
    at its depth. A ghost sits where the rays of two *different* vessels cross (one vessel in each
    view), and the widths of those two vessels need not agree. Pruning (``pruning.py``) removes the
    ghosts no mask pixel needs; this check looks at the ghosts that survive it because every pixel
    they cover is theirs alone in some view.

Method
    1. Per view, the mask's half-width along its 2D centreline: the in-mask distance map read at
       the nearest pixel of the mask's skeleton, in detector pixels (to the first pixel outside: half
       a pixel more than the edge, in every view alike). Or (``measure="thickness"``) the mask's local
       thickness: per pixel, the radius of the largest disk centred on the skeleton that fits in the
       mask and covers it (Hildebrand & Rüegsegger 1997), the nearest covered pixel's outside the disks.
       The two agree along a vessel; at a free end the skeleton stops short and its last pixels read
       the thin tip, while the cap's pixels lie in the disks of the full-width vessel behind it. Or
       (``measure="open_ends"``) the centreline's, unread (NaN) where the nearest skeleton pixel lies
       within ``END_CAP_WIDTHS`` half-widths of a skeleton end and reads less than ``END_CAP_SHARE`` of the
       vessel's half-width there: a free end's cap has no width of its own. Or (``measure="axis"``) the
       in-mask distance map itself, its largest value within a voxel's projected half-diagonal, read at the
       projections of the segmentation's 3D skeleton only: a vessel that runs alongside another in one
       view, the two merged into one wide band there, reads its own edge's distance instead of the band's
       half-width, while a ghost's axis still projects onto the middles of two different vessels.
    2. Per segmented voxel, each view's half-width at the voxel's projection, in mm at the voxel's
       depth (pixel spacing × depth / SID); the voxel's agreement is the smallest over the largest
       of those half-widths (1: the views agree; a ghost of a 3 mm and a 1.5 mm vessel reads 0.5). With three
       views or more, ``views="best_pair"`` takes the best-agreeing pair's ratio instead: a vessel that another
       crosses in one view reads that view's wider shadow, and a third view, which rules ghosts out on its own
       (its mask), need not also agree on the width.
    3. The segmentation is cut into the skeleton pieces pruning weighs (``pruning.skeleton_pieces``,
       ``piece_mm``); a piece whose median agreement is below ``min_ratio`` is removed whole (single
       voxels are too noisy: a mask's border is a pixel off either way).

Units: mm for lengths, detector pixels for the masks' distance maps (converted once, in step 2).
"""

from __future__ import annotations

import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.morphology import skeletonize

from .geometry import CArmView, Geometry
from .metrics import component_labels
from .pruning import neighbour_positions, skeleton_pieces

END_CAP_WIDTHS = 1.5  # "open_ends": a skeleton end's cap, the skeleton pixels within this many half-widths of the vessel behind
END_CAP_SHARE = 0.75  # ... that read less than this share of its half-width


def _skeleton_and_depth(mask: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(the mask's 2D skeleton, its in-mask distance map in pixels), or None where there is no skeleton."""
    skeleton = skeletonize(mask) if mask.any() else mask
    return (skeleton, ndimage.distance_transform_edt(mask)) if skeleton.any() else None


def _at_nearest(where: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per pixel: ``values`` at the nearest pixel of ``where``."""
    rows, cols = ndimage.distance_transform_edt(~where, return_distances=False, return_indices=True)
    return values[rows, cols]


def centreline_half_width_px(mask: np.ndarray) -> np.ndarray:
    """Per detector pixel: the mask's half-width (pixels) at the nearest pixel of its 2D centreline.

    An empty mask, or one with no skeleton, gives zeros.
    """
    mask = np.asarray(mask, bool)
    found = _skeleton_and_depth(mask)
    if found is None:
        return np.zeros(mask.shape)
    skeleton, inside_px = found
    return _at_nearest(skeleton, inside_px)


def local_thickness_px(mask: np.ndarray) -> np.ndarray:
    """Per detector pixel: the radius (pixels) of the largest skeleton-centred disk inside the mask that
    covers it; a pixel no disk covers (outside the mask, or missed by the skeleton's discretisation) reads
    the nearest covered pixel's. An empty mask, or one with no skeleton, gives zeros."""
    mask = np.asarray(mask, bool)
    found = _skeleton_and_depth(mask)
    if found is None:
        return np.zeros(mask.shape)
    skeleton, radius = found
    thickness = np.zeros(mask.shape)
    # one distance transform per one-pixel band of radii: each pixel learns its nearest centre of that band,
    # and is covered when it lies within that centre's own radius
    for band in np.unique(np.ceil(radius[skeleton]).astype(int)):
        centres = skeleton & (np.ceil(radius) == band)
        distance, (rows, cols) = ndimage.distance_transform_edt(~centres, return_indices=True)
        own = radius[rows, cols]
        thickness = np.where(distance < own, np.maximum(thickness, own), thickness)
    return _at_nearest(thickness > 0, thickness)


def open_ends_half_width_px(mask: np.ndarray) -> np.ndarray:
    """``centreline_half_width_px``, NaN where the nearest skeleton pixel lies in a skeleton end's cap: within
    ``END_CAP_WIDTHS`` times the largest half-width nearby of an end (a pixel with one skeleton neighbour or
    none), reading less than ``END_CAP_SHARE`` of that half-width."""
    mask = np.asarray(mask, bool)
    found = _skeleton_and_depth(mask)
    if found is None:
        return np.zeros(mask.shape)
    skeleton, inside_px = found
    on_skeleton = np.where(skeleton, inside_px, 0.0)
    window = 2 * int(np.ceil(2.0 * on_skeleton.max())) + 1
    vessel_px = ndimage.maximum_filter(on_skeleton, size=window)  # the half-width of the vessel an end belongs to
    neighbours = ndimage.convolve(skeleton.astype(np.int32), np.ones((3, 3), np.int32), mode="constant") - 1
    ends = skeleton & (neighbours <= 1)
    # near an end, where the skeleton reads less than the vessel behind it (a blunt end's skeleton stops a
    # half-width short of the end and reads it right; its forks into the corners read the thin tip)
    cap = (skeleton & (ndimage.distance_transform_edt(~ends) <= END_CAP_WIDTHS * vessel_px)
           & (inside_px < END_CAP_SHARE * vessel_px))
    return _at_nearest(skeleton, np.where(cap, np.nan, inside_px))


def in_mask_distance_px(mask: np.ndarray) -> np.ndarray:
    """Per detector pixel: its distance (pixels) to the nearest pixel outside the mask (0 outside)."""
    return ndimage.distance_transform_edt(np.asarray(mask, bool))


HALF_WIDTH_MEASURES = {"centreline": centreline_half_width_px, "thickness": local_thickness_px,
                       "open_ends": open_ends_half_width_px, "axis": in_mask_distance_px}
#: the measures read at the projections of the segmentation's 3D skeleton only (``disagreeing_pieces``)
AXIS_MEASURES = ("axis",)


def _largest_within(values: np.ndarray, radius_px: float) -> np.ndarray:
    """Per pixel: the largest of ``values`` within ``radius_px`` (a disk)."""
    reach = int(np.floor(radius_px))
    if reach < 1:
        return values
    offsets = np.arange(-reach, reach + 1)
    disk = offsets[:, None] ** 2 + offsets[None, :] ** 2 <= radius_px ** 2
    return ndimage.grey_dilation(values, footprint=disk, mode="nearest")


def voxel_reach_px(geometry: Geometry, view: CArmView) -> float:
    """Half a voxel's diagonal projected at the isocenter, in detector pixels: how far a 3D skeleton voxel's
    projection may lie from the true axis's on voxel quantisation alone."""
    half_diagonal_mm = 0.5 * float(np.linalg.norm(geometry.volume.spacing_mm))
    return half_diagonal_mm / float(np.mean(view.isocenter_pixel_spacing_mm))


def half_widths_mm(half_width_px: np.ndarray, view: CArmView, points_mm: np.ndarray) -> np.ndarray:
    """The view's half-width map read at the points' projections (nearest pixel), in mm at their depth."""
    row, col, depth_mm = view.project(np.asarray(points_mm, float))
    rows = np.clip(np.round(np.nan_to_num(row)).astype(int), 0, half_width_px.shape[0] - 1)
    cols = np.clip(np.round(np.nan_to_num(col)).astype(int), 0, half_width_px.shape[1] - 1)
    pixel_mm = float(np.mean(view.pixel_spacing_mm))
    return half_width_px[rows, cols] * pixel_mm * np.asarray(depth_mm, float) / view.sid_mm


#: which views' half-widths a point's agreement compares: "all", the smallest over the largest of every view's;
#: "best_pair", with three views or more, the best-agreeing pair's (the same as "all" with two). A true vessel crossed
#: by another vessel in one of three views reads that view's wider shadow, which "all" takes for a ghost's; a ghost of
#: three views needs two of them to see one vessel's width by chance.
AGREEMENT_VIEWS = ("all", "best_pair")


def width_agreement(masks: Sequence[np.ndarray], geometry: Geometry, points_mm: np.ndarray,
                    measure: str = "centreline", unknown: Optional[Sequence[Optional[np.ndarray]]] = None,
                    views: str = "all") -> np.ndarray:
    """Per point: the smallest over the largest of the views' half-widths at its projections (0–1), of every view
    or of the best-agreeing pair (``views``, ``AGREEMENT_VIEWS``); ``measure``: how a view's half-width map is made
    (``HALF_WIDTH_MEASURES``, module docstring). ``unknown``: per view None or a bool detector image, True where the
    view could not see (its mask's 0 there is no width): a point projecting there is unread (NaN) — with
    "best_pair", read by the pairs of views that see it."""
    if len(masks) != len(geometry.views):
        raise ValueError(f"{len(masks)} masks for {len(geometry.views)} views: give one mask per view, in the views' order")
    if measure not in HALF_WIDTH_MEASURES:
        raise ValueError(f"unknown half-width measure {measure!r}: choose one of {', '.join(HALF_WIDTH_MEASURES)}")
    if views not in AGREEMENT_VIEWS:
        raise ValueError(f"unknown choice of views {views!r}: choose one of {', '.join(AGREEMENT_VIEWS)}")
    unseen = list(unknown) if unknown is not None else [None] * len(masks)
    if len(unseen) != len(masks):
        raise ValueError(f"{len(unseen)} unknown-pixel images for {len(masks)} masks: give one per view (None: all known)")

    def half_width_px(mask: np.ndarray, view: CArmView) -> np.ndarray:
        read = HALF_WIDTH_MEASURES[measure](mask)
        return _largest_within(read, voxel_reach_px(geometry, view)) if measure in AXIS_MEASURES else read

    widths = np.stack([half_widths_mm(half_width_px(m, v) if u is None else np.where(u, np.nan, half_width_px(m, v)),
                                      v, points_mm)
                       for m, v, u in zip(masks, geometry.views, unseen)])
    if views == "all" or len(masks) < 3:
        # NaN where a view leaves the width unread (open_ends): the point has no agreement
        return widths.min(axis=0) / np.maximum(widths.max(axis=0), 1e-9)
    best = np.full(widths.shape[1], np.nan)
    for i in range(len(masks)):
        for j in range(i + 1, len(masks)):
            pair = widths[[i, j]]
            best = np.fmax(best, pair.min(axis=0) / np.maximum(pair.max(axis=0), 1e-9))  # fmax: an unread pair abstains
    return best


def _median_read(values: np.ndarray) -> float:
    read = values[np.isfinite(values)]
    return float(np.median(read)) if read.size else 1.0


class _VoxelGraph:
    """The 26-adjacency of a segmentation's voxels, to ask whether removing a piece leaves the rest of its
    component in parts: over the component's own voxels, not by relabelling a box of the grid around it (a tree
    spread over a 13-million-voxel grid spans half of it, and the width check asks up to ~140 times,
    bench/RESULTS.md §100d)."""

    def __init__(self, segmentation: np.ndarray, labels: np.ndarray, pieces: np.ndarray):
        self.flat = np.flatnonzero(segmentation)
        self.label = labels.reshape(-1)[self.flat]  # components of the segmentation (or of a superset)
        self.piece = pieces.reshape(-1)[self.flat]
        self.alive = np.ones(self.flat.size, bool)
        ijk = np.stack(np.unravel_index(self.flat, segmentation.shape), axis=1)
        rows, cols = [], []
        for offset in np.argwhere(np.ones((3, 3, 3), bool)) - 1:  # half of the 26 offsets; symmetrised below
            if tuple(offset) <= (0, 0, 0):
                continue
            target = neighbour_positions(ijk, self.flat, segmentation.shape, offset)
            rows.append(np.flatnonzero(target >= 0))
            cols.append(target[target >= 0])
        row, col = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(row.size, bool), (row, col)), shape=(self.flat.size,) * 2).tocsr()
        self.graph = (graph + graph.T).tocsr()

    def splits_its_component(self, piece: int) -> bool:
        """Whether removing ``piece`` from the voxels still alive leaves the rest of its component(s) in parts."""
        in_piece = self.alive & (self.piece == piece)
        own = np.unique(self.label[in_piece])
        rest = np.flatnonzero(self.alive & np.isin(self.label, own[own > 0]) & ~in_piece)
        if not rest.size:
            return False  # the piece is a whole fragment
        parts, _ = connected_components(self.graph[rest][:, rest], directed=False)
        return parts > 1

    def remove(self, piece: int) -> None:
        self.alive &= self.piece != piece


def disagreeing_pieces(segmentation: np.ndarray, masks: Sequence[np.ndarray], geometry: Geometry,
                       min_ratio: float, piece_mm: float = 6.0,
                       keep_connected: bool = False, measure: str = "centreline",
                       unknown: Optional[Sequence[Optional[np.ndarray]]] = None,
                       views: str = "all") -> Tuple[np.ndarray, Dict[str, Any]]:
    """The segmentation without its pieces whose median width agreement is below ``min_ratio``
    (``unknown``, ``views``: as for ``width_agreement``; a piece no point of which is read is kept).

    ``keep_connected``: a piece is removed only where the rest of its component stays in one part
    (the least agreeing first, each decision on what is left, repeated until nothing more goes): a
    ghost between two true vessels is kept rather than the tree cut there; a ghost spur goes.
    Returns (kept segmentation, info: pieces, removed pieces and voxels, each piece's median
    agreement, seconds).
    """
    t0 = time.perf_counter()
    segmentation = np.asarray(segmentation, bool)
    if not 0.0 <= min_ratio <= 1.0:
        raise ValueError(f"min_ratio {min_ratio} is not an agreement: give a value from 0 (keep every piece) to 1")
    voxels = np.argwhere(segmentation)
    info: Dict[str, Any] = {"min_ratio": float(min_ratio), "measure": measure, "views": views, "pieces": 0,
                            "removed_pieces": 0, "removed_voxels": 0}
    if not len(voxels):
        info["seconds"] = time.perf_counter() - t0
        return segmentation.copy(), info
    pieces, count = skeleton_pieces(segmentation, geometry.volume.spacing_mm, piece_mm)
    if measure in AXIS_MEASURES:
        # read on the pieces' axes (a piece too thin to have one: on all of it); every other voxel unread
        axis = skeletonize(segmentation).astype(bool)
        without_axis = ~np.isin(np.arange(count + 1), np.unique(pieces[axis]))
        read = axis | (segmentation & without_axis[pieces])
        voxels = np.argwhere(read)
        agreement = np.where(segmentation, np.nan, 1.0)
    else:
        agreement = np.ones(segmentation.shape)
    agreement[tuple(voxels.T)] = width_agreement(masks, geometry, geometry.volume.index_to_world(voxels.astype(float)),
                                                 measure, unknown, views)
    medians = np.ones(count + 1)
    if count and np.isnan(agreement).any():  # the median of the points read; a piece with none is kept
        medians[1:] = ndimage.labeled_comprehension(agreement, pieces, np.arange(1, count + 1), _median_read, float, 1.0)
    elif count:
        medians[1:] = ndimage.median(agreement, pieces, index=np.arange(1, count + 1))
    candidates = [int(k) for k in np.argsort(medians, kind="stable") if k > 0 and medians[k] < min_ratio]
    if keep_connected:
        removed_labels: List[int] = []
        changed = True
        # the components once: only pieces that split none are removed, so each stays one part
        graph = _VoxelGraph(segmentation, component_labels(segmentation)[0], pieces)
        while changed:  # a spur is peeled from its tip: its inner piece becomes removable once the tip is gone
            changed = False
            for k in [k for k in candidates if k not in removed_labels]:
                if not graph.splits_its_component(k):
                    graph.remove(k)
                    removed_labels.append(k)
                    changed = True
    else:
        removed_labels = candidates
    kept = segmentation & ~np.isin(pieces, removed_labels)
    info.update(pieces=int(count), removed_pieces=len(removed_labels), removed_voxels=int((segmentation & ~kept).sum()),
                median_agreement=[round(float(m), 3) for m in medians[1:]], seconds=time.perf_counter() - t0)
    return kept, info
