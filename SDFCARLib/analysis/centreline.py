"""Centreline tree of a vessel volume: branches as smoothed 3D curves ordered from the ostium.

Method (chosen after measuring the options, see bench/RESULTS.md "3D-QCA")
    1. Binary lumen = volume >= level, its enclosed cavities filled (``fill_lumen_cavities``) and its one-
       to two-voxel tunnels closed (``close_tunnels``); its 3D thinning (``skimage.morphology.skeletonize``, Lee's method)
       gives a one-voxel-wide skeleton.
    2. The skeleton voxels form a graph (26-neighbours, edge weight = the step's length in mm).
       Each connected piece longer than ``min_component_mm`` is analysed on its own.
    3. The ostium is the thick root end: the skeleton end point whose largest inscribed radius
       (Euclidean distance transform) within 3 mm along the skeleton is the greatest, unless the
       caller gives ``ostium_mm``.
    4. Shortest paths from the ostium (Dijkstra) make a tree even where the skeleton holds loops
       (touching vessels). The tree is cut into branches by the long-path decomposition: at every
       node the branch continues into the child with the longest path below it; every other child
       starts a side branch at that node (the junction). This equals taking, again and again, the
       longest path not yet covered.
    5. Spurs: a side branch shorter than ``min_branch_mm`` + the inscribed radius at its junction
       is dropped with everything below it (thinning leaves such stubs on the surface of thick
       vessels; the radius term scales the cut with the parent).
    6. Each branch's voxel path is resampled by arc length, smoothed with a Gaussian of
       ``smoothing_mm`` (removes the voxel staircase, which lengthens paths by up to ~8 %), and
       resampled at ``step_mm``. Free ends are first cut back by 1.5 vessel radii (near an end
       the skeleton fans out towards the rim instead of following the axis) and, after smoothing,
       extended along their end tangent to the lumen surface; a root's start (the ostium) also along
       the lumen's sections, and the longer of the two is kept (a bent ostium: ``extend_ostium``).
       A side branch starts at the point of its parent nearest its junction.

Conventions
    Points are LPS mm (``geometry.py``); a branch runs from its proximal end (ostium or junction)
    to its distal end; ``branch_id`` 0 is the main vessel from the ostium, ids increase with the
    generation (breadth first), ``parent_id`` is None for roots.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from skimage.morphology import skeletonize

from ..geometry import VolumeGrid

ROOT_RADIUS_REACH_MM = 3.0  # how far along the skeleton an end point's "thickness" is looked for
END_TRIM_RADII = 1.5  # a free end's skeleton is cut back by this many vessel radii before its extension
# >0: the extension reads the lumen across a disk of this many vessel radii about its line, not on the line
# alone (a segmented-mask tip is uneven: one hole on the line stops it a millimetre or more short). 0: the line
# alone; 0.25 put the segmented-mask tubes' ends right but ran the clean-mask tubes' long (RESULTS §63c)
END_PROBE_RADII = 0.0
END_FOLLOWS_LUMEN = False  # every free end's extension follows the lumen's sections (``follow_to_surface``)
OSTIUM_FOLLOWS_LUMEN = True  # a root's start (the ostium) reaches as far as the straight or the followed extension


class CentrelineError(ValueError):
    """The volume holds no vessel to analyse; the message says what to check."""


@dataclass
class CentrelineBranch:
    branch_id: int
    points_mm: np.ndarray  # (N, 3) LPS, proximal → distal
    inscribed_radius_mm: np.ndarray  # (N,) distance-transform radius, a rough calibre
    parent_id: Optional[int] = None
    parent_index: Optional[int] = None  # index of the junction point on the parent
    tree_id: int = 0  # which connected piece of the volume

    @property
    def arc_length_mm(self) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.points_mm, axis=0), axis=1))])

    @property
    def length_mm(self) -> float:
        return float(self.arc_length_mm[-1])

    def tangents(self) -> np.ndarray:
        """Unit tangents (N, 3) by central differences."""
        t = np.gradient(self.points_mm, axis=0)
        return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


@dataclass
class CentrelineTree:
    branches: List[CentrelineBranch] = field(default_factory=list)
    # where an ostium was given: its skeleton's thickness beside the thickest end's (``_given_root_check``)
    given_root: Optional[Dict[str, Any]] = None

    def branch(self, branch_id: int) -> CentrelineBranch:
        for b in self.branches:
            if b.branch_id == branch_id:
                return b
        raise KeyError(f"no branch {branch_id}; the tree has ids {[b.branch_id for b in self.branches]}")

    def children(self, branch_id: int) -> List[CentrelineBranch]:
        return [b for b in self.branches if b.parent_id == branch_id]

    def junctions(self) -> List[Dict[str, object]]:
        """One entry per side branch: where it leaves its parent."""
        out = []
        for b in self.branches:
            if b.parent_id is None:
                continue
            parent = self.branch(b.parent_id)
            out.append({"parent_id": b.parent_id, "child_id": b.branch_id, "parent_index": b.parent_index,
                        "parent_arc_mm": float(parent.arc_length_mm[b.parent_index]),
                        "point_mm": [float(v) for v in parent.points_mm[b.parent_index]]})
        return out

    def total_length_mm(self) -> float:
        return float(sum(b.length_mm for b in self.branches))


# --- lumen ---------------------------------------------------------------------------------------
def fill_lumen_cavities(volume: np.ndarray, level: float):
    """(volume, number of voxels filled): the voxels under ``level`` that no face-connected path joins to the
    grid's border are raised to ``level`` (True in a label volume).

    A vessel's lumen encloses no cavity, yet a fitted field dips under the level at a voxel here and there inside
    a thick vessel; thinning then rings the cavity with a loop, and where that ring sits at the ostium the tree
    has no end there and is rooted at a distal one (bench/RESULTS.md §104a)."""
    volume = np.asarray(volume)
    lumen = volume if volume.dtype == bool else volume >= level
    # face-connected background: a cavity touching the outside only by an edge or a corner is still enclosed
    cavities = ndimage.binary_fill_holes(lumen) & ~lumen
    n_filled = int(cavities.sum())
    if n_filled == 0:
        return volume, 0
    filled = volume.copy()
    if volume.dtype == bool:
        filled[cavities] = True
    else:  # the least value of the dtype that still reads as lumen (level itself may round below it)
        value = np.asarray(level).astype(volume.dtype)
        if value < level:
            value = (np.nextafter(value, np.inf, dtype=volume.dtype) if np.issubdtype(volume.dtype, np.floating)
                     else np.asarray(np.ceil(level)).astype(volume.dtype))
        filled[cavities] = value
    return filled, n_filled


#: Close tunnels one or two voxels wide through the lumen before thinning (``close_tunnels``); False only to measure without.
CLOSE_TUNNELS = True


def close_tunnels(lumen: np.ndarray) -> np.ndarray:
    """The binary lumen closed by one face-connected voxel: tunnels and gaps up to two voxels wide are filled.

    A fitted field leaves the lumen of a thick vessel lumpy, pierced here and there by a channel a voxel wide; thinning
    rings each with a loop (the realistic reconstructions hold 1 to 16 such loops), and a loop at the ostium leaves the
    tree no end there: it is then rooted at a distal one (bench/RESULTS.md §104b). The skeleton and its radii are taken
    from the closed lumen; the sections read the volume as it is."""
    padded = np.pad(np.asarray(lumen, bool), 1)
    closed = ndimage.binary_closing(padded, structure=ndimage.generate_binary_structure(3, 1))
    return closed[1:-1, 1:-1, 1:-1] | lumen


# --- skeleton graph ------------------------------------------------------------------------------
_OFFSETS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                     if (a, b, c) > (0, 0, 0)])  # 13 "forward" neighbours: each edge once


def skeleton_graph(skeleton: np.ndarray, spacing_mm: Sequence[float]):
    """(voxel indices (N, 3), sparse symmetric adjacency with mm weights) of a skeleton."""
    coords = np.argwhere(skeleton)
    index = np.full(skeleton.shape, -1, dtype=np.int64)
    index[tuple(coords.T)] = np.arange(len(coords))
    padded = np.pad(index, 1, constant_values=-1)
    rows, cols, weights = [], [], []
    spacing = np.asarray(spacing_mm, float)
    for off in _OFFSETS:
        nb = padded[tuple((coords + 1 + off).T)]
        ok = nb >= 0
        rows.append(np.nonzero(ok)[0])
        cols.append(nb[ok])
        weights.append(np.full(int(ok.sum()), float(np.linalg.norm(off * spacing))))
    r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    graph = sparse.coo_matrix((np.concatenate([w, w]), (np.concatenate([r, c]), np.concatenate([c, r]))),
                              shape=(len(coords), len(coords))).tocsr()
    return coords, graph


def _thickness_mm(graph, radius: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Each node's "thickness": the largest inscribed radius within ``ROOT_RADIUS_REACH_MM`` along the skeleton."""
    reach = csgraph.dijkstra(graph, indices=nodes, limit=ROOT_RADIUS_REACH_MM)
    return np.where(np.isfinite(reach), radius[None, :], 0.0).max(axis=1)


def _thickest_end(graph, radius: np.ndarray) -> int:
    degree = np.diff(graph.indptr)
    ends = np.nonzero(degree == 1)[0]
    if len(ends) == 0:  # a closed loop: start where it is thickest
        return int(np.argmax(radius))
    return int(ends[np.argmax(_thickness_mm(graph, radius, ends))])


def _pick_root(graph, radius: np.ndarray, world: np.ndarray, ostium_mm: Optional[np.ndarray]) -> int:
    if ostium_mm is not None:
        return int(np.argmin(np.linalg.norm(world - ostium_mm, axis=1)))
    return _thickest_end(graph, radius)


def _given_root_check(graph, radius: np.ndarray, world: np.ndarray, root: int) -> Dict[str, Any]:
    """How thick the skeleton is where a given ostium roots the tree, beside its thickest end (the root it
    would have been given): a point at a distal tip orders the whole tree backwards."""
    thickest = _thickest_end(graph, radius)
    given, best = _thickness_mm(graph, radius, np.array([root, thickest]))
    return {"given_radius_mm": float(given), "thickest_end_radius_mm": float(best),
            "thickest_end_mm": world[thickest].tolist(),
            "distance_to_thickest_end_mm": float(np.linalg.norm(world[root] - world[thickest]))}


def _decompose(graph, root: int, radius: np.ndarray, min_branch_mm: float):
    """Long-path decomposition of the shortest-path tree from ``root``: [(node path, parent k, junction node)]."""
    dist, pred = csgraph.dijkstra(graph, indices=root, return_predecessors=True)
    nodes = np.nonzero(np.isfinite(dist))[0]
    order = nodes[np.argsort(dist[nodes])]
    height = np.zeros(len(dist))
    best = np.full(len(dist), -1)
    children: Dict[int, List[int]] = {}
    for n in order[::-1]:  # farthest first: children before parents
        p = pred[n]
        if p < 0:
            continue
        children.setdefault(int(p), []).append(int(n))
        h = height[n] + dist[n] - dist[p]
        if best[p] < 0 or h > height[p]:
            height[p], best[p] = h, n
    branches = []
    queue = deque([(root, None, None)])  # (first node, parent branch number, junction node)
    while queue:
        start, parent, junction = queue.popleft()
        path = [junction, start] if junction is not None else [start]
        node = start
        while True:
            for c in children.get(node, []):
                if c != best[node] and height[c] + dist[c] - dist[node] >= min_branch_mm + radius[node]:
                    queue.append((c, len(branches), node))
            if best[node] < 0:
                break
            node = int(best[node])
            path.append(node)
        branches.append((path, parent, junction))
    return branches


# --- curves ------------------------------------------------------------------------------------
def resample_polyline(points: np.ndarray, step_mm: float) -> np.ndarray:
    """Points at equal arc-length steps (the last point kept)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    if s[-1] == 0:
        return points[:1].copy()
    n = max(2, int(np.ceil(s[-1] / step_mm)) + 1)
    fine = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(fine, s, points[:, a]) for a in range(3)], axis=1)


def smooth_polyline(points: np.ndarray, smoothing_mm: float, step_mm: float) -> np.ndarray:
    """Gaussian smoothing along the arc length, ends held (``mode='nearest'``), then resampling."""
    dense_step = min(step_mm, 0.25)
    dense = resample_polyline(points, dense_step)
    if smoothing_mm > 0 and len(dense) > 3:
        dense = ndimage.gaussian_filter1d(dense, smoothing_mm / dense_step, axis=0, mode="nearest")
    return resample_polyline(dense, step_mm)


def shift_along_arc(arc_mm: np.ndarray, counted: np.ndarray, shifts: np.ndarray, junction_shift: Optional[np.ndarray],
                    smoothing_mm: float, min_measured: int) -> np.ndarray:
    """(N, 3) displacement of a branch's points from the shifts measured where ``counted``: interpolated along the
    arc between them (the nearest beyond the ends), smoothed (Gaussian, ``smoothing_mm``); a side branch's
    ``junction_shift`` (its parent's at the junction) anchors its first point, after the smoothing too. Fewer than
    ``min_measured`` counted points: the whole branch moves with its junction (a root stays)."""
    n = len(arc_mm)
    if int(np.sum(counted)) < min_measured:
        return np.zeros((n, 3)) if junction_shift is None else np.tile(junction_shift, (n, 1))
    anchors_arc, anchors = arc_mm[counted], shifts[counted]
    if junction_shift is not None:
        anchors_arc, anchors = np.r_[0.0, anchors_arc], np.vstack([junction_shift, anchors])
    order = np.argsort(anchors_arc, kind="stable")
    delta = np.stack([np.interp(arc_mm, anchors_arc[order], anchors[order, a]) for a in range(3)], axis=1)
    step = float(np.median(np.diff(arc_mm)))
    if smoothing_mm > 0 and step > 0:
        delta = ndimage.gaussian_filter1d(delta, smoothing_mm / step, axis=0, mode="nearest")
    if junction_shift is not None:
        delta[0] = junction_shift  # exactly on the junction point
    return delta


def sample_volume(volume: np.ndarray, grid: VolumeGrid, points_mm: np.ndarray, order: int = 1) -> np.ndarray:
    """Trilinear (``order=1``) samples of ``volume`` at world points; outside the grid = 0."""
    ijk = grid.world_to_index(np.asarray(points_mm, float).reshape(-1, 3)).T
    values = ndimage.map_coordinates(np.asarray(volume, np.float32), ijk, order=order, mode="constant", cval=0.0)
    return values.reshape(np.asarray(points_mm).shape[:-1])


def trim_free_end(points: np.ndarray, radius: np.ndarray, at_start: bool = False):
    """(points, vessel radius) with a free end's last ``END_TRIM_RADII`` vessel radii of skeleton cut off.

    Within about a radius of a vessel's end the thinned skeleton no longer follows the axis: on a
    blunt or uneven end it fans out towards the rim, and the longest path runs into a corner, which
    adds up to a radius of length and bends the end tangent. The vessel radius is the largest
    inscribed radius within ``ROOT_RADIUS_REACH_MM`` of the end; at least half the path is kept.
    """
    pts, rad = (points[::-1], radius[::-1]) if at_start else (points, radius)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    vessel_radius = float(rad[s >= s[-1] - ROOT_RADIUS_REACH_MM].max())
    keep = s <= max(s[-1] - END_TRIM_RADII * vessel_radius, s[-1] / 2)
    keep[:2] = True
    pts = pts[keep]
    return (pts[::-1] if at_start else pts), vessel_radius


def extend_to_surface(points: np.ndarray, volume: np.ndarray, grid: VolumeGrid, level: float,
                      reach_mm: float, step_mm: float, at_start: bool = False, probe_radius_mm: float = 0.0) -> np.ndarray:
    """Extend a polyline's end along its end tangent up to where the volume falls below ``level`` — on the
    line, or (``probe_radius_mm`` > 0) everywhere on the disk of that radius about it across the tangent."""
    pts = points[::-1] if at_start else points
    if len(pts) < 2:
        return points
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    back = pts[np.searchsorted(s, max(s[-1] - 1.0, 0.0))]  # ~1 mm back: a tangent above voxel noise
    t = pts[-1] - back
    if np.linalg.norm(t) == 0:
        return points
    t /= np.linalg.norm(t)
    fine = 0.02
    d = np.arange(fine, reach_mm + fine, fine)
    along = pts[-1] + d[:, None] * t
    if probe_radius_mm > 0:  # the centre and eight points on the disk's rim
        from .diameter import plane_basis  # here: diameter imports this module

        a, b = (x[0] for x in plane_basis(t[None]))
        angles = np.arange(8) * np.pi / 4
        offsets = np.vstack([np.zeros(3), probe_radius_mm * (np.cos(angles)[:, None] * a + np.sin(angles)[:, None] * b)])
        inside = (sample_volume(volume, grid, (along[:, None, :] + offsets[None]).reshape(-1, 3))
                  .reshape(len(d), len(offsets)) >= level).any(axis=1)
    else:
        inside = sample_volume(volume, grid, along) >= level
    if inside.all():
        length = d[-1]
    else:
        length = d[np.argmin(inside)] - fine  # first sample outside; the surface lies in that step
    if length < step_mm / 2:
        return points
    extra = pts[-1] + np.arange(step_mm, length + 1e-9, step_mm)[:, None] * t
    if len(extra) == 0 or np.linalg.norm(extra[-1] - (pts[-1] + length * t)) > 1e-6:
        extra = np.vstack([extra, pts[-1] + length * t]) if len(extra) else (pts[-1] + length * t)[None]
    out = np.vstack([pts, extra])
    return out[::-1] if at_start else out


def follow_to_surface(points: np.ndarray, volume: np.ndarray, grid: VolumeGrid, level: float,
                      reach_mm: float, step_mm: float, at_start: bool = False) -> np.ndarray:
    """Extend a polyline's end step by step along its end tangent, each new point moved onto the centroid of
    its cross-section (by at most a step), up to where the volume falls below ``level``: on a bend the straight
    extension of ``extend_to_surface`` leaves through the side wall."""
    from .diameter import cross_sections  # here: diameter imports this module

    pts = points[::-1] if at_start else points
    if len(pts) < 2:
        return points
    path = [np.asarray(p, float) for p in pts]
    fine = 0.02
    travelled = 0.0
    while travelled < reach_mm:
        arr = np.asarray(path[-12:])
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(arr, axis=0), axis=1))])
        t = arr[-1] - arr[np.searchsorted(s, max(s[-1] - 1.0, 0.0))]
        if np.linalg.norm(t) == 0:
            break
        t /= np.linalg.norm(t)
        ahead = arr[-1] + step_mm * t
        if sample_volume(volume, grid, ahead[None])[0] < level:  # the surface lies within this step
            d = np.arange(fine, step_mm + fine, fine)
            inside = sample_volume(volume, grid, arr[-1] + d[:, None] * t) >= level
            length = d[np.argmin(inside)] - fine if not inside.all() else step_mm
            if length >= fine:
                path.append(arr[-1] + length * t)
            break
        centre = cross_sections(volume, grid, ahead[None], t[None], level, recentre=1).centres_mm[0]
        if np.all(np.isfinite(centre)) and np.linalg.norm(centre - ahead) <= step_mm \
                and sample_volume(volume, grid, centre[None])[0] >= level:
            ahead = centre
        path.append(ahead)
        travelled += step_mm
    out = np.asarray(path)
    return out[::-1] if at_start else out


def extend_ostium(points: np.ndarray, volume: np.ndarray, grid: VolumeGrid, level: float, reach_mm: float,
                  step_mm: float, probe_radius_mm: float = 0.0) -> np.ndarray:
    """Extend a root's start (the ostium end) to the lumen's surface: the longer of the straight and the
    followed extension. Each stops at the first point below ``level`` it meets — the straight one at the side
    wall of a bend, the followed one at a hole beside the axis of a rough reconstruction — so the lumen runs at
    least as far as the longer (RESULTS §73a). A followed distal end runs into a reconstruction's blurred tip
    (§72d), so distal ends stay straight unless ``END_FOLLOWS_LUMEN``."""
    if END_FOLLOWS_LUMEN:
        return follow_to_surface(points, volume, grid, level, reach_mm, step_mm, at_start=True)
    straight = extend_to_surface(points, volume, grid, level, reach_mm, step_mm, at_start=True,
                                 probe_radius_mm=probe_radius_mm)
    if not OSTIUM_FOLLOWS_LUMEN:
        return straight
    followed = follow_to_surface(points, volume, grid, level, reach_mm, step_mm, at_start=True)

    def added_mm(extended):
        return float(np.linalg.norm(np.diff(extended[:len(extended) - len(points) + 1], axis=0), axis=1).sum())

    return followed if added_mm(followed) > added_mm(straight) else straight


def crop_to(mask: np.ndarray, grid: VolumeGrid, arrays: Sequence[np.ndarray], margin: int = 3):
    """(sub-grid, arrays cropped) to the bounding box of ``mask`` plus ``margin`` voxels.

    Thinning and the distance transform cost in proportion to the voxels they see; a tree fills
    a few per cent of a reconstruction grid.
    """
    idx = np.argwhere(mask)
    lo = np.maximum(idx.min(axis=0) - margin, 0)
    hi = np.minimum(idx.max(axis=0) + margin + 1, np.asarray(mask.shape))
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    spacing = np.asarray(grid.spacing_mm, float)
    centre = grid.index_to_world((lo + hi - 1) / 2.0)
    sub = VolumeGrid(tuple(int(b - a) for a, b in zip(lo, hi)), tuple(spacing), tuple(float(c) for c in centre))
    return sub, [np.asarray(a)[box] for a in arrays]


# --- the tree ------------------------------------------------------------------------------------
def extract_centrelines(volume: np.ndarray, grid: VolumeGrid, level: float = 0.5,
                        ostium_mm: Optional[Sequence[float]] = None, min_branch_mm: float = 3.0,
                        min_component_mm: float = 5.0, smoothing_mm: float = 1.0, step_mm: float = 0.25,
                        extend_ends: bool = True) -> CentrelineTree:
    """The centreline tree of ``volume`` (occupancy, probability or label on ``grid``; module docstring)."""
    volume = np.asarray(volume)
    if volume.shape != tuple(grid.shape):
        raise CentrelineError(f"the volume's shape {volume.shape} does not match its grid {tuple(grid.shape)}")
    lumen = volume >= level if volume.dtype != bool else volume
    if not lumen.any():
        raise CentrelineError(f"no voxel reaches the level {level:g}: the volume is empty; check the reconstruction "
                              "(its report.json's warnings say what went wrong)")
    grid, (lumen, volume) = crop_to(lumen, grid, [lumen, volume], margin=3)
    # on the crop (cheap: analyse_volume has filled the whole grid already): the background margin it keeps
    # around the lumen joins every open path to its border, so it encloses the same cavities as the whole grid
    volume, _ = fill_lumen_cavities(volume, level)
    lumen = volume >= level if volume.dtype != bool else volume
    if CLOSE_TUNNELS:
        lumen = close_tunnels(lumen)
    spacing = np.asarray(grid.spacing_mm, float)
    edt = ndimage.distance_transform_edt(lumen, sampling=spacing)
    coords, graph = skeleton_graph(skeletonize(lumen), spacing)
    if len(coords) == 0:
        raise CentrelineError("thinning the lumen left no skeleton (the vessel is thinner than a voxel)")
    world = grid.index_to_world(coords)
    radius = edt[tuple(coords.T)]
    fvol = volume.astype(np.float32)
    n_pieces, piece = csgraph.connected_components(graph, directed=False)
    ostium = None if ostium_mm is None else np.asarray(ostium_mm, float)
    # The piece nearest a given ostium is rooted there; the others at their own thickest end.
    nearest_piece = None if ostium is None else piece[np.argmin(np.linalg.norm(world - ostium, axis=1))]
    tree = CentrelineTree()
    pieces = sorted(range(n_pieces), key=lambda p: -int(np.sum(piece == p)))
    for tree_id, p in enumerate(pieces):
        members = np.nonzero(piece == p)[0]
        sub = graph[members][:, members]
        if sub.sum() / 2 < min_component_mm:
            continue
        root = _pick_root(sub, radius[members], world[members], ostium if p == nearest_piece else None)
        if p == nearest_piece:
            tree.given_root = _given_root_check(sub, radius[members], world[members], root)
        raw = _decompose(sub, root, radius[members], min_branch_mm)
        first_id = len(tree.branches)
        for k, (path, parent, _junction) in enumerate(raw):
            pts = world[members[np.asarray(path)]]
            rad = radius[members[np.asarray(path)]]
            if extend_ends:
                pts, end_radius = trim_free_end(pts, rad)
                if parent is None:
                    pts, start_radius = trim_free_end(pts, rad[:len(pts)], at_start=True)
            smooth = smooth_polyline(pts, smoothing_mm, step_mm)
            parent_id = parent_index = None
            if parent is not None:
                parent_branch = tree.branches[first_id + parent]
                parent_id = parent_branch.branch_id
                parent_index = int(np.argmin(np.linalg.norm(parent_branch.points_mm - pts[0], axis=1)))
                smooth[0] = parent_branch.points_mm[parent_index]
            if extend_ends:  # the surface lies about a radius beyond the thinned end, plus what was trimmed
                reach = (END_TRIM_RADII + 2.0) * end_radius + 2.0 * float(spacing.max())
                smooth = (follow_to_surface(smooth, fvol, grid, level, reach, step_mm) if END_FOLLOWS_LUMEN else
                          extend_to_surface(smooth, fvol, grid, level, reach, step_mm,
                                            probe_radius_mm=END_PROBE_RADII * end_radius))
                if parent is None:
                    reach = (END_TRIM_RADII + 2.0) * start_radius + 2.0 * float(spacing.max())
                    smooth = extend_ostium(smooth, fvol, grid, level, reach, step_mm,
                                           probe_radius_mm=END_PROBE_RADII * start_radius)
            r = sample_volume(edt, grid, smooth)
            tree.branches.append(CentrelineBranch(first_id + k, smooth, r, parent_id, parent_index, tree_id))
    if not tree.branches:
        raise CentrelineError(f"every connected piece of the lumen is shorter than {min_component_mm} mm; "
                              "check the reconstruction or lower min_component_mm")
    return tree


def bifurcation_angles(tree: CentrelineTree, reach_mm: float = 4.0) -> List[Dict[str, float]]:
    """Angle (degrees) between each side branch and its parent's continuation, and the parent's inflow.

    Each limb's direction is the chord between the points ``skip`` and ``skip + reach_mm`` along it
    from the junction, ``skip`` the parent's inscribed radius there: the first part of a side
    branch's centreline lies inside the parent's lumen, where thinning and smoothing bend it.
    """
    out = []
    for j in tree.junctions():
        parent, child = tree.branch(int(j["parent_id"])), tree.branch(int(j["child_id"]))
        i = int(j["parent_index"])
        skip = float(parent.inscribed_radius_mm[i])
        s_p, s_c = parent.arc_length_mm, child.arc_length_mm

        def limb(points, s, a, b):
            ka = int(np.clip(np.searchsorted(s, a), 0, len(s) - 1))
            kb = int(np.clip(np.searchsorted(s, b), 0, len(s) - 1))
            v = points[kb] - points[ka]
            n = np.linalg.norm(v)
            return v / n if n > 0 else None

        distal = limb(parent.points_mm, s_p, s_p[i] + skip, s_p[i] + skip + reach_mm)
        proximal = limb(parent.points_mm, s_p, s_p[i] - skip, s_p[i] - skip - reach_mm)
        side = limb(child.points_mm, s_c, skip, skip + reach_mm)

        def angle(a, b):
            return None if a is None or b is None else float(np.degrees(np.arccos(np.clip(a @ b, -1, 1))))

        out.append({"parent_id": int(j["parent_id"]), "child_id": int(j["child_id"]),
                    "parent_arc_mm": float(j["parent_arc_mm"]),
                    "distal_angle_deg": angle(distal, side),  # side branch against the main's continuation
                    "proximal_angle_deg": angle(proximal, side)})
    return out
