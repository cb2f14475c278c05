"""Reconnection of fragments: join the pieces of a thresholded reconstruction through the field.

Why
    A coronary tree is one connected tree per ostium, but a field fitted to two views often dips
    just below the threshold along a thin or foreshortened stretch of vessel, so the thresholded
    result falls apart into pieces although the field still shows a ridge of raised occupancy
    across the gap. Dropping the small pieces loses true vessel (clDice); this module bridges them
    instead, and only where a bridge is supported: inside the reconstruction's support (in ``fast``
    the masks' visual hull, so both views show vessel all along the bridge), after the fragments
    that some view does not confirm (ghosts) were removed (``optimiser.drop_then_join_fragments``).

Method
    1. Label the 26-connected components of the segmentation; the largest is the tree.
    2. Minimal paths from the tree (``skimage.graph.MCP_Geometric``, voxel spacing in mm) in the
       cost per mm ``−log(occupancy)`` outside the segmentation and almost nothing inside it, so
       that a path runs inside vessel wherever it can and crosses a gap where the field is
       highest. Voxels outside the support (where the field was never evaluated) and farther than
       ``max_gap_mm`` from the segmentation are impassable.
    3. For each other component, the cheapest path to it is accepted when the stretch outside
       the segmentation (the gap) is at most ``max_gap_mm`` long and the geometric mean of the
       occupancy on its voxels (exp of minus the mean cost) is at least ``min_occupancy``. By
       default no occupancy is asked (0): σ(−α·s) with α = 50 is nearly binary, so true and false
       gaps both read 1e-6–1e-2 (RESULTS §5), while the support already says that both views see
       vessel along the path (RESULTS §19). A piece farther away, or one the support does not
       reach, stays apart; nothing is ever removed.
    4. An accepted gap is filled with a tube whose radius is the smaller of the vessel radii at
       its two ends (largest distance-transform value of the segmentation within 2 mm of each
       end, less half a voxel). In the tube the occupancy is raised to at least the threshold
       (falling linearly to 0 over one voxel outside it), so the surface at the threshold
       includes the bridge; the caller writes the matching field values (``field_values``).
    5. Joined components become part of the tree and the search repeats from the grown tree
       until a round joins nothing, so a chain of fragments can be joined link by link.
    6. ``every_component``: then the largest component still apart is taken as a tree of its own and
       steps 2–5 repeat from it (the trees already done impassable), and so on until none is left: a
       second tree (another ostium, a phantom's separate tubes) is mended too, not only the largest.

Each bridge is reported (``bridges``: the gap's voxel indices, the tube's radius): the vessel was
broken there and the bridge is thinner than the vessel by construction, so the 3D-QCA
(``analysis/fragments.py``) does not report a narrowing on it as a reliable lesion.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage
from skimage.graph import MCP_Geometric

from .metrics import component_labels

# Cost per mm inside the segmentation: not zero, so that among paths through vessel the short
# one is taken, but far below −log(0.5) ≈ 0.69, the cheapest step across a gap.
_INSIDE_COST = 1e-3
_FLOOR = 1e-6  # occupancy floor of the cost (−log 0 is infinite) and of the logit
_RADIUS_WINDOW_MM = 2.0  # the vessel radius at a gap end is read this far around it


@dataclass
class ReconnectSettings:
    max_gap_mm: float = 8.0  # longest stretch outside the segmentation a bridge may cross
    min_occupancy: float = 0.0  # lowest geometric-mean occupancy along that stretch (0: not asked)
    threshold: float = 0.5  # the segmentation's occupancy threshold
    every_component: bool = False  # after the largest, each component still apart in turn joins what it reaches


def field_values(occupancy: np.ndarray, field_kind: str, alpha: float) -> np.ndarray:
    """The raw field that gives ``occupancy``: s = −logit(o)/α (SDF modes) or the logit itself."""
    o = np.clip(np.asarray(occupancy, np.float64), _FLOOR, 1.0 - _FLOOR)
    logit = np.log(o) - np.log1p(-o)
    return (-logit / alpha if field_kind == "sdf" else logit).astype(np.float32)


def reconnect_fragments(
    segmentation: np.ndarray,
    occupancy: np.ndarray,
    spacing_mm: Sequence[float],
    support: Optional[np.ndarray] = None,
    settings: Optional[ReconnectSettings] = None,
) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Dict[str, Any]]:
    """Join the smaller components of ``segmentation`` to the largest (``every_component``: and to each other
    tree in turn) through the field (module docstring).

    Returns (segmentation, occupancy, changed, report): new arrays (the inputs are not modified),
    the voxels whose occupancy was raised, and what was joined (components before and after,
    joined count, gap lengths in mm and mean occupancies of the accepted paths, the bridges' gap
    voxels and radii, components left apart).
    """
    t0 = time.perf_counter()
    settings = settings or ReconnectSettings()
    segmentation = np.array(segmentation, dtype=bool)
    occupancy = np.array(occupancy, dtype=np.float32)
    if segmentation.shape != occupancy.shape or (support is not None and np.shape(support) != segmentation.shape):
        raise ValueError(f"reconnect: segmentation {segmentation.shape}, occupancy {occupancy.shape} and support "
                         f"{None if support is None else np.shape(support)} must have the same shape")
    spacing = np.asarray(spacing_mm, dtype=float)
    changed = np.zeros(segmentation.shape, bool)
    labels, sizes = component_labels(segmentation)
    info: Dict[str, Any] = {"components_before": int(sizes.size), "joined": 0, "gap_mm": [], "gap_occupancy": [],
                            "bridges": [], "left_apart": 0, "max_gap_mm": settings.max_gap_mm,
                            "min_occupancy": settings.min_occupancy}
    if sizes.size < 2:
        info.update(components_after=int(sizes.size), seconds=time.perf_counter() - t0)
        return segmentation, occupancy, changed, info

    # Only voxels within max_gap_mm of the segmentation can lie on an acceptable gap.
    reach = ndimage.distance_transform_edt(~segmentation, sampling=spacing) <= settings.max_gap_mm
    if support is not None:
        reach &= np.asarray(support, bool) | segmentation
    radius_map = ndimage.distance_transform_edt(segmentation, sampling=spacing)
    done = np.zeros(segmentation.shape, bool)  # the trees whose turn is over (every_component)
    done_labels: set = set()  # their labels in ``labels``
    tree = int(np.argmax(sizes)) + 1
    whole = tuple(slice(0, n) for n in labels.shape)
    window = whole  # the whole grid for the largest; a later tree searches its own surroundings
    margin = np.ceil(settings.max_gap_mm / spacing).astype(int) + 2
    trees = 1
    while True:
        tree_seed = tuple(np.argwhere(labels[window] == tree)[0] + [w.start for w in window])
        joined_now = _join_round(segmentation, occupancy, changed, labels, reach, done, radius_map, spacing, settings,
                                 tree, info, window)
        if joined_now:
            labels, sizes = component_labels(segmentation)
            done_labels = {int(n) for n in np.unique(labels[done])} - {0}
            tree = int(labels[tree_seed])
            window = whole if trees == 1 else _around(labels, tree, margin)
            continue
        if not settings.every_component:
            break
        done |= labels == tree
        done_labels.add(tree)
        apart = np.array([n for n in range(1, sizes.size + 1) if n not in done_labels], dtype=int)
        if apart.size < 2:  # one component left apart has nothing to join
            break
        tree = int(apart[np.argmax(sizes[apart - 1])])
        window = _around(labels, tree, margin)
        trees += 1
    if settings.every_component:
        info["trees_grown"] = trees
    info.update(components_after=int(sizes.size), left_apart=int(sizes.size) - 1, seconds=time.perf_counter() - t0)
    return segmentation, occupancy, changed, info


def _around(labels: np.ndarray, label: int, margin: np.ndarray) -> Tuple[slice, ...]:
    """The bounding box of component ``label`` widened by ``margin`` voxels per axis (clipped to the grid)."""
    box = ndimage.find_objects((labels == label).astype(np.int8))[0]
    return tuple(slice(max(b.start - m, 0), min(b.stop + m, n)) for b, m, n in zip(box, margin, labels.shape))


def _join_round(segmentation: np.ndarray, occupancy: np.ndarray, changed: np.ndarray, labels: np.ndarray,
                reach: np.ndarray, done: np.ndarray, radius_map: np.ndarray, spacing: np.ndarray,
                settings: ReconnectSettings, tree: int, info: Dict[str, Any], window: Tuple[slice, ...]) -> int:
    """One round from component ``tree`` (label of ``labels``): each other component whose cheapest path through
    voxels in ``reach`` but not ``done``, within ``window``, has an acceptable gap is bridged (in place; ``info``
    records the bridges). Returns how many."""
    origin = np.array([w.start for w in window])
    local_labels = labels[window]
    cost = np.where(segmentation[window], _INSIDE_COST, -np.log(np.maximum(occupancy[window], _FLOOR))).astype(np.float64)
    cost[~reach[window] | done[window]] = np.inf
    mcp = MCP_Geometric(cost, sampling=tuple(spacing))
    cumulative, _ = mcp.find_costs(np.argwhere(local_labels == tree))
    joined_now = 0
    reached = {tree}  # the components on the tree's side of the bridges laid this round
    for label, box in enumerate(ndimage.find_objects(local_labels), start=1):
        if label in reached or box is None:
            continue
        members = np.argwhere(local_labels[box] == label) + [b.start for b in box]
        costs = cumulative[tuple(members.T)]
        if not np.isfinite(costs).any():
            continue
        end = tuple(members[int(np.argmin(costs))])
        path = np.asarray(mcp.traceback(end)) + origin
        gap = ~segmentation[tuple(path.T)]
        if not gap.any():  # a bridge laid earlier in this round already touches it
            reached.add(label)
            continue
        steps = np.linalg.norm(np.diff(path, axis=0) * spacing, axis=1)
        gap_mm = float(steps[gap[1:] | gap[:-1]].sum())
        mean_occupancy = float(np.exp(np.mean(np.log(np.maximum(occupancy[tuple(path[gap].T)], _FLOOR)))))
        if gap_mm > settings.max_gap_mm or mean_occupancy < settings.min_occupancy:
            continue
        radius = _bridge_radius(path, gap, radius_map, spacing)
        _fill_tube(segmentation, occupancy, changed, path[gap], radius, spacing, settings.threshold)
        reached.update(int(n) for n in np.unique(labels[tuple(path.T)]) if n)  # components it crosses too
        info["gap_mm"].append(round(gap_mm, 3))
        info["gap_occupancy"].append(round(mean_occupancy, 4))
        info["bridges"].append({"gap_mm": round(gap_mm, 3), "radius_mm": round(radius, 3),
                                "voxels_ijk": path[gap].astype(int).tolist()})
        joined_now += 1
    info["joined"] += joined_now
    return joined_now


def _bridge_radius(path: np.ndarray, gap: np.ndarray, radius_map: np.ndarray, spacing: np.ndarray) -> float:
    """The smaller vessel radius (mm) at the two ends of the path's gap, at least half a voxel."""
    gap_index = np.flatnonzero(gap)
    ends = [path[max(gap_index[0] - 1, 0)], path[min(gap_index[-1] + 1, len(path) - 1)]]
    window = np.maximum(np.ceil(_RADIUS_WINDOW_MM / spacing).astype(int), 1)
    radii: List[float] = []
    for end in ends:
        lo = np.maximum(end - window, 0)
        hi = np.minimum(end + window + 1, radius_map.shape)
        radii.append(float(radius_map[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].max()))
    # The distance transform measures to the nearest outside voxel's centre, half a voxel beyond the wall.
    return max(min(radii) - 0.5 * float(spacing.min()), 0.5 * float(spacing.min()))


def _fill_tube(segmentation: np.ndarray, occupancy: np.ndarray, changed: np.ndarray, centre: np.ndarray,
               radius: float, spacing: np.ndarray, threshold: float) -> None:
    """Mark the voxels within ``radius`` of the centre voxels as segmented and raise the occupancy (in place)."""
    h = float(spacing.min())
    margin = np.ceil((radius + h) / spacing).astype(int)
    lo = np.maximum(centre.min(axis=0) - margin, 0)
    hi = np.minimum(centre.max(axis=0) + margin + 1, segmentation.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    seeds = np.ones(tuple(hi - lo), bool)
    seeds[tuple((centre - lo).T)] = False
    distance = ndimage.distance_transform_edt(seeds, sampling=spacing)
    inside = distance <= radius
    # Linear in the distance: 1 a voxel inside the tube's wall, the threshold on it, 0 a voxel outside.
    slope = np.where(inside, (1.0 - threshold) / h, threshold / h)
    target = np.clip(threshold + slope * (radius - distance), 0.0, 1.0).astype(np.float32)
    target[inside] = np.maximum(target[inside], threshold)
    raised = target > occupancy[box]
    occupancy[box] = np.maximum(occupancy[box], target)
    segmentation[box] |= inside
    changed[box] |= raised
