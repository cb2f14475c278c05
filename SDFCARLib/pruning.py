"""Redundant-branch pruning: remove pieces of a reconstruction that no mask pixel needs.

Why
    Two views leave the reconstruction ambiguous: where vessels overlap in one view, the optimiser
    can explain the same mask pixels with "ghost" segments that lie in the visual hull but not in
    the patient. A ghost shows as extra skeleton branches (low topology precision) while the
    reprojection stays perfect, because every pixel it covers is also covered by a true vessel.

Method (a greedy minimal set cover at the level of skeleton pieces)
    1. Skeletonise the segmentation, split the skeleton at its junctions into branches and each
       branch into pieces of at most ``max_piece_mm`` (geodesic length); every segmented voxel
       belongs to the piece of its nearest skeleton voxel.
    2. Project each piece into both views: it covers the mask pixels its line integral crosses by
       more than ``threshold_mm``.
    3. Repeatedly remove the piece whose uniquely covered pixels (pixels no other remaining piece
       covers) are the smallest fraction of its coverage, as long as that fraction is at most
       ``tolerance``; ties go to the piece whose pixels are covered most often by the others.

    Every removed piece therefore explained at most ``tolerance`` of its own pixels alone, so the
    reprojection of what is kept matches the masks almost exactly as before.

    ``keep_connected``: a piece is removed only where the pieces left of its component stay one part
    (26-adjacent pieces), so a ghost spur is peeled from its tip and a detached ghost piece by piece,
    while a stretch of a true vessel whose pixels other vessels happen to cover in both views (where
    it crosses them, or runs along the epipolar lines) is not cut out of its tube.

Pieces of about 6 mm are the default: whole branches are too coarse to separate a ghost from
its true vessel, pieces of a few voxels too short to be told apart (bench/RESULTS.md).

Unconfirmed fragments (``unconfirmed_fragments``)
    A component detached from the tree is kept only if every view that sees it has a mask pixel
    that it alone explains. A ghost is made where one view's rays must explain vessel pixels
    that the other view's mask cannot place (a vessel that mask missed, or a pixel of border
    error): it sits in the other view's shadow of some other vessel, so that view has no pixel
    that needs it. A true fragment of the tree is seen on its own somewhere in each view. The
    pieces still attached to the tree are left to the set cover above.

Small fragments (``small_fragments``)
    What is still detached once every other step is done (but the final reconnection, which comes after
    it when asked), and smaller than ``min_volume_mm3`` (16 mm³
    in ``fast``: 31 voxels at 0.8 mm), is removed: a piece of a vessel that small, seen by nothing that
    joins it to the tree, is noise in a tree a clinician reads, and on realistic input two in three of
    these specks lie away from any true vessel (bench/RESULTS.md §58).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from skimage.morphology import skeletonize

from .geometry import Geometry
from .metrics import component_labels
from .projector import ConeBeamProjector


@dataclass
class PruneSettings:
    max_piece_mm: float = 6.0
    threshold_mm: float = 0.1  # a piece covers a pixel when its line integral there exceeds this
    tolerance: float = 0.02  # largest fraction of its pixels a removed piece may cover alone
    keep_connected: bool = False  # remove only pieces whose component stays one part without them
    # each piece split into its 26-connected parts first (parts_of_pieces): a piece holds the voxels nearest its stretch of
    # skeleton, which need not be one part, and the pieces' graph then joins voxels that do not touch; split, keep_connected
    # keeps the voxels whole (unsplit it cut 3 of 20 realistic trees in two when pruning last: RESULTS §98)
    split_disconnected_pieces: bool = False


def skeleton_pieces(segmentation: np.ndarray, spacing_mm: Sequence[float], max_piece_mm: float) -> Tuple[np.ndarray, int]:
    """Label volume (0 = background, 1..n) of the pieces of ``segmentation`` and their number n."""

    segmentation = np.asarray(segmentation, dtype=bool)
    spacing = np.asarray(spacing_mm, dtype=float)
    labelled = np.zeros(segmentation.shape, np.int64)
    if not segmentation.any():
        return labelled, 0
    points = np.argwhere(skeletonize(segmentation).astype(bool))
    next_label = 1
    if len(points):
        piece, next_label = _pieces_of_skeleton(points, segmentation.shape, spacing, max_piece_mm)
        labelled[tuple(points[piece > 0].T)] = piece[piece > 0]

    # skimage's thinning deletes objects two voxels thick entirely (a 2 × 2 bar has no skeleton),
    # so a thin component can come back without one: cut it along its principal axis instead.
    components, sizes = component_labels(segmentation)
    has_piece = np.zeros(sizes.size + 1, bool)
    has_piece[components[labelled > 0]] = True
    for component in np.flatnonzero(~has_piece[1:]) + 1:
        members = np.argwhere(components == component)
        centred = (members - members.mean(axis=0)) * spacing
        axis = np.linalg.svd(centred, full_matrices=False)[2][0] if len(members) > 1 else np.zeros(3)
        along = centred @ axis
        along -= along.min()
        n_pieces = max(1, int(np.ceil((along.max() + 1e-6) / max_piece_mm)))
        chunk = np.minimum((along / (along.max() + 1e-6) * n_pieces).astype(np.int64), n_pieces - 1)
        labelled[tuple(members.T)] = next_label + chunk
        next_label += n_pieces

    # Every segmented voxel (junctions included) goes to its nearest labelled voxel.
    nearest = ndimage.distance_transform_edt(labelled == 0, sampling=spacing, return_distances=False, return_indices=True)
    owner = np.where(segmentation, labelled[tuple(nearest)], 0)
    # the labels used, renumbered 1.. in order (0, the background, stays 0): by counting, not by sorting the grid
    used = np.flatnonzero(np.bincount(owner.reshape(-1)))
    used = used[used > 0]
    renumber = np.zeros(int(used[-1]) + 1, np.int64)
    renumber[used] = np.arange(1, used.size + 1)
    return renumber[owner], int(used.size)


def _pieces_of_skeleton(points: np.ndarray, shape: Tuple[int, ...], spacing: np.ndarray, max_piece_mm: float) -> Tuple[np.ndarray, int]:
    """Piece label (1..; 0 for junction voxels) of each skeleton voxel, and the next free label."""

    # 26-neighbour graph of skeleton voxels, edge weights in mm; neighbours found among the points' flat indices
    # (sorted: ``points`` come from argwhere) rather than through an index volume of the whole grid
    flat = np.ravel_multi_index(tuple(points.T), shape)
    rows, cols, weights = [], [], []
    for offset in np.argwhere(np.ones((3, 3, 3))) - 1:
        if not offset.any():
            continue
        target = neighbour_positions(points, flat, shape, offset)
        linked = target >= 0
        rows.append(np.flatnonzero(linked))
        cols.append(target[linked])
        weights.append(np.full(int(linked.sum()), float(np.linalg.norm(offset * spacing))))
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(len(points), len(points))).tocsr()

    # Branches: what stays connected once the junction voxels (degree >= 3) are taken out; each
    # is cut into pieces of at most max_piece_mm by geodesic distance from one of its ends.
    branch_voxels = np.flatnonzero(np.diff(graph.indptr) < 3)
    branch_graph = graph[branch_voxels][:, branch_voxels]
    branch_count, branch_of = connected_components(branch_graph, directed=False)
    piece = np.zeros(len(points), np.int64)
    next_label = 1
    for branch in range(branch_count):
        members = np.flatnonzero(branch_of == branch)
        local = branch_graph[members][:, members]
        from_any = dijkstra(local, indices=0)
        end = int(np.argmax(np.where(np.isfinite(from_any), from_any, -1.0)))
        along = dijkstra(local, indices=end)
        along = np.where(np.isfinite(along), along, 0.0)
        length = float(along.max())
        n_pieces = max(1, int(np.ceil((length + 1e-6) / max_piece_mm)))
        chunk = np.minimum((along / (length + 1e-6) * n_pieces).astype(np.int64), n_pieces - 1)
        piece[branch_voxels[members]] = next_label + chunk
        next_label += n_pieces
    return piece, next_label


def neighbour_positions(points: np.ndarray, flat: np.ndarray, shape: Sequence[int], offset: np.ndarray) -> np.ndarray:
    """For each voxel of ``points`` (N × 3 indices; ``flat``: their flat indices, sorted ascending), the position in
    ``flat`` of its neighbour at ``offset`` where that neighbour is one of the points, else −1."""
    neighbour = points + offset
    inside = np.all((neighbour >= 0) & (neighbour < np.asarray(shape)), axis=1)
    target = np.full(len(points), -1, np.int64)
    if not flat.size:
        return target
    wanted = np.ravel_multi_index(tuple(neighbour[inside].T), tuple(shape))
    position = np.minimum(np.searchsorted(flat, wanted), flat.size - 1)
    target[inside] = np.where(flat[position] == wanted, position, -1)
    return target


def prune_redundant_branches(
    segmentation: np.ndarray,
    masks: Sequence[np.ndarray],
    geometry: Geometry,
    settings: Optional[PruneSettings] = None,
    projectors: Optional[Sequence[ConeBeamProjector]] = None,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """The segmentation without the pieces that no mask pixel needs (see module docstring).

    ``masks``: one boolean image per view of ``geometry`` (vessel pixels). ``projectors``: one per
    view whose inputs hold every segmented voxel (the reconstruction's own); otherwise projectors of
    the segmented voxels are built. Returns the pruned segmentation and a report (pieces, pieces
    removed, voxels removed, seconds).
    """
    t0 = time.perf_counter()
    settings = settings or PruneSettings()
    segmentation = np.asarray(segmentation, dtype=bool)
    if len(masks) != len(geometry.views):
        raise ValueError(f"prune: {len(masks)} mask(s) for {len(geometry.views)} view(s)")
    for n, (mask, view) in enumerate(zip(masks, geometry.views), start=1):
        if tuple(np.shape(mask)) != tuple(view.detector_shape):
            raise ValueError(f"prune: mask {n} has shape {np.shape(mask)}, view {n} has detector {tuple(view.detector_shape)}")
    pieces, count = skeleton_pieces(segmentation, geometry.volume.spacing_mm, settings.max_piece_mm)
    if settings.split_disconnected_pieces:
        pieces, count = parts_of_pieces(pieces, count)
    info: Dict[str, Any] = {"pieces": int(count), "removed_pieces": 0, "removed_voxels": 0,
                            "max_piece_mm": settings.max_piece_mm, "tolerance": settings.tolerance}
    if count < 2:
        info["seconds"] = time.perf_counter() - t0
        return segmentation.copy(), info

    voxels = np.flatnonzero(segmentation.reshape(-1))
    if projectors is None or not all(p.covers(voxels) for p in projectors):
        projectors = [ConeBeamProjector(view, geometry.volume, voxels=voxels) for view in geometry.views]
    covered_parts = []
    for mask, projector in zip(masks, projectors):
        piece_integrals, pixels, _ = projector.group_integrals(pieces, count)
        in_mask = np.asarray(mask, dtype=bool).reshape(-1)[pixels]
        covered_parts.append((piece_integrals > settings.threshold_mm) & in_mask[:, None])
    cover = np.concatenate(covered_parts, axis=0)
    cover = cover[cover.any(axis=1)]  # mask pixels that some piece covers
    times_covered = cover.sum(axis=1)
    alive = np.ones(count, dtype=bool)
    adjacency = piece_adjacency(pieces, count) if settings.keep_connected else None
    kept_whole = 0  # redundant pieces left at the end because removing any of them splits its component
    while True:
        unique = (cover & (times_covered == 1)[:, None]).sum(axis=0)
        total = cover.sum(axis=0)
        ratio = np.where(total > 0, unique / np.maximum(total, 1), 0.0)
        candidates = np.flatnonzero(alive & (ratio <= settings.tolerance))
        if candidates.size == 0 or alive.sum() <= 1:
            break
        redundancy = np.array([times_covered[cover[:, k]].mean() if total[k] else np.inf for k in candidates])
        ordered = candidates[np.lexsort((-redundancy, ratio[candidates]))]
        if adjacency is None:
            chosen = ordered[0]
        else:
            chosen = next((k for k in ordered if not _splits_pieces(adjacency, alive, k)), None)
            if chosen is None:
                kept_whole = int(ordered.size)
                break
        alive[chosen] = False
        times_covered -= cover[:, chosen]
        cover[:, chosen] = False
    kept = np.isin(pieces, np.flatnonzero(alive) + 1)
    info.update(removed_pieces=int(count - alive.sum()), removed_voxels=int(segmentation.sum() - kept.sum()),
                seconds=time.perf_counter() - t0)
    if adjacency is not None:
        info["kept_whole_pieces"] = kept_whole
    return kept, info


def parts_of_pieces(pieces: np.ndarray, count: int) -> Tuple[np.ndarray, int]:
    """``pieces`` (labels 1..count) relabelled so that each label is one 26-connected part of one piece, and the
    number of labels: the same voxels, each piece's parts numbered in turn."""
    pieces = np.asarray(pieces)
    parts = np.zeros(pieces.shape, np.int64)
    total = 0
    for label, box in enumerate(ndimage.find_objects(pieces, count), start=1):
        if box is None:
            continue
        inside = pieces[box] == label
        labels, n = ndimage.label(inside, structure=np.ones((3, 3, 3)))
        parts[box][inside] = labels[inside] + total
        total += n
    return parts, total


def piece_adjacency(pieces: np.ndarray, count: int) -> csr_matrix:
    """Symmetric boolean matrix (count × count) of the pieces (labels 1..count of ``pieces``, index
    label − 1) that touch: some voxel of one is a 26-neighbour of a voxel of the other."""
    pieces = np.asarray(pieces)
    nonzero = np.nonzero(pieces)
    if not nonzero[0].size:
        return csr_matrix((count, count), dtype=bool)
    box = tuple(slice(int(a.min()), int(a.max()) + 1) for a in nonzero)
    labels = np.pad(pieces[box], 1)
    core = tuple(slice(1, n - 1) for n in labels.shape)
    rows, cols = [], []
    # half of the 26 offsets: each touching pair is seen once, the matrix is symmetrised below
    for offset in np.argwhere(np.ones((3, 3, 3))) - 1:
        if tuple(offset) <= (0, 0, 0):
            continue
        shifted = labels[tuple(slice(1 + o, n - 1 + o) for o, n in zip(offset, labels.shape))]
        here = labels[core]
        touching = (here > 0) & (shifted > 0) & (here != shifted)
        rows.append(here[touching])
        cols.append(shifted[touching])
    rows_all = np.concatenate(rows) - 1
    cols_all = np.concatenate(cols) - 1
    graph = coo_matrix((np.ones(rows_all.size, bool), (rows_all, cols_all)), shape=(count, count)).tocsr()
    return (graph + graph.T).astype(bool).tocsr()


def _splits_pieces(adjacency: csr_matrix, alive: np.ndarray, piece: int) -> bool:
    """Whether removing ``piece`` leaves the alive pieces it touches in more than one part.

    On the pieces' graph rather than on the voxels (``width_agreement._VoxelGraph``): the greedy loop asks at
    every removal, up to ~130 times per realistic 128³ case, where relabelling the voxels cost ~10 ms; on the graph
    of its 155 pieces a check costs 0.13 ms (the graph 26 ms)."""
    neighbours = adjacency.indices[adjacency.indptr[piece]:adjacency.indptr[piece + 1]]
    neighbours = neighbours[alive[neighbours]]
    if neighbours.size < 2:
        return False
    rest = alive.copy()
    rest[piece] = False
    order = np.flatnonzero(rest)
    _, parts = connected_components(adjacency[order][:, order], directed=False)
    position = np.searchsorted(order, neighbours)
    return np.unique(parts[position]).size > 1


def unconfirmed_fragments(
    segmentation: np.ndarray,
    masks: Sequence[np.ndarray],
    geometry: Geometry,
    threshold_mm: float = PruneSettings.threshold_mm,
    projectors: Optional[Sequence[ConeBeamProjector]] = None,
    unknown: Optional[Sequence[Optional[np.ndarray]]] = None,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """Voxels of the components other than the largest that some view seeing them does not need.

    A component is confirmed by a view when it covers at least one of that view's mask pixels that
    no other component covers (line integral above ``threshold_mm``); a view onto whose detector it
    does not project at all neither confirms nor rejects it. ``projectors``: one per view whose
    voxels hold every segmented voxel (the reconstruction's own, which already traced these rays);
    otherwise projectors of the segmented voxels are built. ``unknown``: per view None or a bool detector
    image, True where the view could not see (collimated, clipped): a component that projects only there is
    not seen by that view. Returns the boolean volume of the unconfirmed components' voxels and a report
    (fragments, removed fragments and voxels, seconds).
    """
    t0 = time.perf_counter()
    segmentation = np.asarray(segmentation, dtype=bool)
    if len(masks) != len(geometry.views):
        raise ValueError(f"unconfirmed_fragments: {len(masks)} mask(s) for {len(geometry.views)} view(s)")
    components, sizes = component_labels(segmentation)
    removed = np.zeros(segmentation.shape, dtype=bool)
    info: Dict[str, Any] = {"fragments": max(int(sizes.size) - 1, 0), "removed_fragments": 0, "removed_voxels": 0}
    if sizes.size < 2:
        info["seconds"] = time.perf_counter() - t0
        return removed, info
    segmented = np.flatnonzero(segmentation.reshape(-1))
    if projectors is None or not all(p.covers(segmented) for p in projectors):
        projectors = [ConeBeamProjector(view, geometry.volume, voxels=segmented) for view in geometry.views]
    unseen = list(unknown) if unknown is not None else [None] * len(masks)
    if len(unseen) != len(masks):
        raise ValueError(f"unconfirmed_fragments: {len(unseen)} unknown-pixel images for {len(masks)} masks")
    confirmed = np.ones(sizes.size, dtype=bool)
    for mask, view, projector, not_seen in zip(masks, geometry.views, projectors, unseen):
        if tuple(np.shape(mask)) != tuple(view.detector_shape):
            raise ValueError(f"unconfirmed_fragments: mask shape {np.shape(mask)} differs from the detector {tuple(view.detector_shape)}")
        integrals, pixels, seen = projector.group_integrals(components, sizes.size)
        if not_seen is not None:  # seen: casting a shadow on a pixel the view could see
            known = ~np.asarray(not_seen, dtype=bool).reshape(-1)[pixels]
            seen = seen & ((integrals > threshold_mm) & known[:, None]).any(axis=0)
        covered = (integrals > threshold_mm) & np.asarray(mask, dtype=bool).reshape(-1)[pixels][:, None]
        alone = (covered & (covered.sum(axis=1) == 1)[:, None]).sum(axis=0)
        confirmed &= (alone > 0) | ~seen
    confirmed[int(np.argmax(sizes))] = True  # the tree itself
    removed = np.isin(components, np.flatnonzero(~confirmed) + 1)
    info.update(removed_fragments=int((~confirmed).sum()), removed_voxels=int(removed.sum()),
                seconds=time.perf_counter() - t0)
    return removed, info


def small_fragments(segmentation: np.ndarray, spacing_mm: Sequence[float], min_volume_mm3: float) -> Tuple[np.ndarray, Dict[str, Any]]:
    """Voxels of the 26-connected components other than the largest whose volume is below
    ``min_volume_mm3``, and a report (fragments, removed fragments and voxels). The largest component
    always stays, however small; another tree (a second ostium) stays when it is at least that large."""
    segmentation = np.asarray(segmentation, dtype=bool)
    if not min_volume_mm3 >= 0:
        raise ValueError(f"min_volume_mm3 must be 0 (off) or a volume in mm³, got {min_volume_mm3}")
    components, sizes = component_labels(segmentation)
    voxel_mm3 = float(np.prod(np.asarray(spacing_mm, dtype=float)))
    small = sizes * voxel_mm3 < min_volume_mm3
    if sizes.size:
        small[int(np.argmax(sizes))] = False
    removed = np.isin(components, np.flatnonzero(small) + 1)
    info = {"fragments": max(int(sizes.size) - 1, 0), "removed_fragments": int(small.sum()),
            "removed_voxels": int(removed.sum()), "min_volume_mm3": float(min_volume_mm3)}
    return removed, info


def removal_zone(segmentation: np.ndarray, kept: np.ndarray, spacing_mm: Sequence[float]) -> np.ndarray:
    """Voxels to clear in the occupancy and field so that they agree with the pruned segmentation.

    The removed voxels plus the one-voxel shell around them that is nearer to them than to what is
    kept (distances between voxel centres, mm): the partial occupancy there would otherwise put a thin
    skin of the ghost into the surface. The shell reaches |spacing| (a voxel's diagonal), so both
    distances are read over the few neighbours within it, not by distance transforms of the whole grid
    (on a 13-million-voxel grid these took seconds per call, bench/RESULTS.md §100d).
    """

    kept = np.asarray(kept, bool)
    removed = np.asarray(segmentation, bool) & ~kept
    if not removed.any():
        return removed
    spacing = np.asarray(spacing_mm, dtype=float)
    reach_mm = float(np.linalg.norm(spacing)) + 1e-6
    offsets, offset_mm = _neighbour_offsets(spacing, reach_mm)
    shape = np.asarray(removed.shape)
    candidates = np.unique((np.argwhere(removed)[:, None, :] + offsets[None]).reshape(-1, 3), axis=0)
    candidates = candidates[np.all((candidates >= 0) & (candidates < shape), axis=1)]
    candidates = candidates[~kept[tuple(candidates.T)] & ~removed[tuple(candidates.T)]]
    to_removed = np.full(len(candidates), np.inf)
    to_kept = np.full(len(candidates), np.inf)  # exact within the reach: all the comparison below needs
    for offset, distance in zip(offsets, offset_mm):
        at = candidates + offset
        inside = np.all((at >= 0) & (at < shape), axis=1)
        index = tuple(at[inside].T)
        to_removed[inside] = np.where(removed[index], np.minimum(to_removed[inside], distance), to_removed[inside])
        to_kept[inside] = np.where(kept[index], np.minimum(to_kept[inside], distance), to_kept[inside])
    shell = candidates[(to_removed <= reach_mm) & (to_removed < to_kept)]
    zone = removed.copy()
    zone[tuple(shell.T)] = True
    return zone


def _neighbour_offsets(spacing: np.ndarray, reach_mm: float) -> Tuple[np.ndarray, np.ndarray]:
    """The voxel offsets other than zero whose length (mm) is at most ``reach_mm``, and those lengths."""
    steps = np.floor(reach_mm / spacing).astype(int)
    grid = np.stack(np.meshgrid(*(np.arange(-n, n + 1) for n in steps), indexing="ij"), axis=-1).reshape(-1, 3)
    lengths = np.linalg.norm(grid * spacing, axis=1)
    near = (lengths <= reach_mm) & np.any(grid != 0, axis=1)
    return grid[near], lengths[near]
