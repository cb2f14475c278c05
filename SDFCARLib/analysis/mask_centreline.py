"""The centreline re-placed on the views' mask midlines: 3D-QCA's centreline from the 2D edges.

Why
    A reconstruction from segmented masks puts its lumen's centre a fraction of a millimetre off the
    vessel's axis, wandering over a few millimetres (the frames' path lengths bend it), while the
    masks' midlines lie several times nearer the projected axis (bench/RESULTS.md §33a–b). The wander lengthens
    the 3D centreline and skews its foreshortening; clinical 3D-QCA takes the centreline from the 2D
    edges for the same reason.

Method (``place_on_masks``)
    At each centreline point p (unit tangent t), in each view: the mask's edges on either side of
    p's projection, along the image normal n of the projected centreline (``diameter.projected_edges``,
    detector mm a₊, a₋); the midline lies o = (a₊ − a₋) / 2 along n. The displacement δ ⟂ t that
    moves p's projection onto every view's midline solves  nᵥᵀ Jᵥ δ = oᵥ  (Jᵥ: the derivative of
    view v's detector position, mm, with respect to p; two views, two unknowns in the plane ⟂ t;
    least squares for more).
    A point is measured only where every view finds both edges, foreshortens the tangent by at most
    ``MAX_FORESHORTENING`` (a vessel seen more end-on shows its own neighbouring length across its
    width, and the midline of that blob would set the depth in the other view), and shows the vessel
    within a factor ``MAX_WIDTH_CHANGE`` of that view's running median width (another vessel
    overlapping in one view, or a side branch's mouth, widens that view's mask there; a lesion narrows
    it, and its lumen may lie off the axis, which would bend the centreline), where neither edge found
    in that view lies on another branch's projection or within ``CROWDING_MARGIN_MM`` of it
    (``edge_on_other_vessel``: a vessel running beside over a stretch as long as the width window
    merges into the mask there and widens the running median with it, so the width rule alone keeps
    points whose edge is the other vessel's), outside the branch's own start inside its parent and its
    free-end cap (``diameter.junction_zones``), and where |δ| ≤ ``max_shift_mm``; a run of such points
    spanning less than ``min_run_mm`` of arc is not used (a single point that passes inside a lesion's
    unmeasured stretch would move all of it). The other points take δ interpolated along the arc (the
    nearest measured value beyond the ends); a side branch's first point keeps its parent's junction point.
    δ is then smoothed along the arc (Gaussian, ``smoothing_mm``) and added. A branch with fewer than
    ``min_measured`` measured points keeps its shape: a root stays, a side branch moves with its junction point.
    The normals are taken across the centreline smoothed over ``TANGENT_SMOOTHING_MM``: a wandering
    centreline's own tangent tilts with the wander, and across it the edges give only part of the
    offset (a second pass across the corrected line's tangents only adds the edges' pixel noise).
    Only the points move: their number, the branch ids and the junction indices stay, so sections
    taken at the volume's own centreline still belong to the same points.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage

from ..geometry import CArmView
from .centreline import CentrelineBranch, CentrelineTree, shift_along_arc
from .diameter import junction_zones, plane_basis, projected_edges
from .views import distance_to_other_vessels, other_vessels_projected

#: the defaults measured on the QCA suites (bench/RESULTS.md §33f, §35)
MAX_SHIFT_MM = 1.5
MIN_RUN_MM = 1.0  # measured points in a run shorter than this set no shift: one section that passes every check
# inside a long unmeasured stretch (a lesion) would move the whole stretch (RESULTS §72)
SMOOTHING_MM = 1.0
TANGENT_SMOOTHING_MM = 3.0
MAX_WIDTH_CHANGE = 1.25  # a view's width over (an overlap) or under (a lesion) its running median
WIDTH_WINDOW_MM = 10.0
ANOMALY_MARGIN_MM = 1.0
MAX_FORESHORTENING = 0.7  # a view that sees the tangent foreshortened more sees its own length across it (0.5: RESULTS §49)
CROWDING_MARGIN_MM = 1.0  # detector mm another branch's projection must keep clear of a view's mask edges; 1.0, not 0.5: a reconstructed neighbour comes out thinner than its mask (RESULTS §53)


@dataclass
class MaskPlacement:
    """What ``place_on_masks`` did to one branch."""

    branch_id: int
    measured_share: float  # of the branch's points, measured in every view
    mean_shift_mm: float  # |δ| after smoothing, mean over the branch
    moved: bool

    def to_dict(self) -> Dict[str, object]:
        return {"branch_id": self.branch_id, "measured_share": round(self.measured_share, 3),
                "mean_shift_mm": round(self.mean_shift_mm, 3), "moved": self.moved}


def detector_jacobian(view: CArmView, points_mm: np.ndarray, step_mm: float = 1e-3) -> np.ndarray:
    """(N, 2, 3): d(row mm, column mm on the detector) / d(world mm) at each point (central differences)."""
    points = np.asarray(points_mm, float)
    spacing = np.asarray(view.pixel_spacing_mm, float)
    jac = np.zeros((len(points), 2, 3))
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = step_mm
        r1, c1, _ = view.project(points + e)
        r0, c0, _ = view.project(points - e)
        jac[:, 0, axis] = (r1 - r0) * spacing[0] / (2 * step_mm)
        jac[:, 1, axis] = (c1 - c0) * spacing[1] / (2 * step_mm)
    return jac


def smooth_tangents(points_mm: np.ndarray, smoothing_mm: float) -> np.ndarray:
    """Unit tangents of the polyline smoothed along its arc (Gaussian σ ``smoothing_mm``)."""
    points = np.asarray(points_mm, float)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    step = float(np.median(np.diff(arc))) if len(arc) > 1 else 0.0
    if smoothing_mm > 0 and step > 0:
        points = ndimage.gaussian_filter1d(points, smoothing_mm / step, axis=0, mode="nearest")
    t = np.gradient(points, axis=0)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


def midline_shifts(points_mm: np.ndarray, tangents: np.ndarray, masks: Sequence[np.ndarray], views: Sequence[CArmView],
                   max_foreshortening: float = MAX_FORESHORTENING, max_width_change: float = MAX_WIDTH_CHANGE,
                   radii_mm=None, others_mm: Optional[np.ndarray] = None, others_radii_mm=None,
                   crowding_margin_mm: float = CROWDING_MARGIN_MM) -> np.ndarray:
    """(N, 3) displacement ⟂ tangent putting each point's projections on the masks' midlines; NaN where a
    view gives no clean edge pair (module docstring, without the junction and shift limits). ``others_mm``
    (with ``others_radii_mm``, and the vessel's own ``radii_mm``): the tree's other branches, whose
    projected edges must keep ``crowding_margin_mm`` clear of a view's edges for that view to count."""
    points = np.asarray(points_mm, float)
    t = np.asarray(tangents, float)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    offsets, rows = [], []
    for mask, view in zip(masks, views):
        plus, minus, projected = projected_edges(points, t, mask, view, edgeless=np.nan)
        width_mm = (plus + minus) / projected.magnification
        usable = (projected.foreshortening <= max_foreshortening) & ~width_anomalies(width_mm, arc, max_width_change)
        if others_mm is not None and len(others_mm):
            usable &= ~edge_on_other_vessel(points, plus, minus, projected, view, radii_mm, others_mm, others_radii_mm,
                                            crowding_margin_mm)
        offsets.append(np.where(usable, 0.5 * (plus - minus), np.nan))
        # the displacement's effect on the offset along n: nᵀ J, (N, 3)
        rows.append(np.einsum("nk,nkj->nj", projected.normal_rc.T, detector_jacobian(view, points)))
    offsets = np.stack(offsets)
    valid = np.isfinite(offsets).all(axis=0)
    shifts = np.full((len(points), 3), np.nan)
    e1, e2 = plane_basis(t)
    for i in np.flatnonzero(valid):
        basis = np.stack([e1[i], e2[i]], axis=1)  # (3, 2): the plane ⟂ t
        system = np.stack([r[i] @ basis for r in rows])  # (views, 2)
        solution, *_ = np.linalg.lstsq(system, offsets[:, i], rcond=1e-6)
        shifts[i] = basis @ solution
    return shifts


def edge_on_other_vessel(points_mm: np.ndarray, plus_mm: np.ndarray, minus_mm: np.ndarray, projected, view: CArmView,
                         radii_mm, others_mm: np.ndarray, others_radii_mm, margin_mm: float = CROWDING_MARGIN_MM) -> np.ndarray:
    """Per point, whether either mask edge found in ``view`` (``projected_edges``) lies on another branch's
    projection or within ``margin_mm`` of it: there the mask may be two vessels merged. Another branch
    seen inside the vessel's own edges (a ghost spur of a reconstruction lies on rays through the vessel
    in every view) does not count."""
    others_xy, others_r = other_vessels_projected(points_mm, radii_mm, others_mm, others_radii_mm, view)
    spacing = np.asarray(view.pixel_spacing_mm, float)
    centre = np.stack([projected.row * spacing[0], projected.col * spacing[1]], axis=1)
    normal = np.asarray(projected.normal_rc, float).T
    edges = np.concatenate([centre + plus_mm[:, None] * normal, centre - minus_mm[:, None] * normal])
    with np.errstate(invalid="ignore"):
        near = distance_to_other_vessels(edges, others_xy, others_r) < margin_mm
    return near[:len(centre)] | near[len(centre):]


def running_median(values: np.ndarray, arc_mm: np.ndarray, window_mm: float) -> np.ndarray:
    """Median of the finite values within ``window_mm`` / 2 along the arc of each point (NaN where none)."""
    values = np.asarray(values, float)
    out = np.full(len(values), np.nan)
    for i, centre in enumerate(arc_mm):
        near = values[np.abs(arc_mm - centre) <= window_mm / 2]
        near = near[np.isfinite(near)]
        if near.size:
            out[i] = np.median(near)
    return out


def width_anomalies(widths: np.ndarray, arc_mm: np.ndarray, max_change: float, window_mm: float = WIDTH_WINDOW_MM,
                    margin_mm: float = ANOMALY_MARGIN_MM) -> np.ndarray:
    """Points where one view's mask is wider than ``max_change`` × its running median width (over
    ``window_mm``: another vessel overlapping there, or a junction) or narrower than 1 / ``max_change``
    of it (a lesion, whose lumen may lie off the vessel's axis), and ``margin_mm`` either side."""
    widths = np.asarray(widths, float)
    median = running_median(widths, arc_mm, window_mm)
    with np.errstate(invalid="ignore"):
        wide = (widths > max_change * median) | (widths < median / max_change)
    out = wide.copy()
    for centre in arc_mm[wide]:
        out |= np.abs(arc_mm - centre) <= margin_mm
    return out


def runs_at_least(flags: np.ndarray, arc_mm: np.ndarray, min_run_mm: float) -> np.ndarray:
    """``flags`` less its runs of consecutive True points that span under ``min_run_mm`` of arc."""
    flags = np.asarray(flags, bool)
    kept = flags.copy()
    if min_run_mm <= 0 or not flags.any():
        return kept
    edges = np.diff(np.r_[0, flags.astype(np.int8), 0])
    for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        if arc_mm[stop - 1] - arc_mm[start] < min_run_mm:
            kept[start:stop] = False
    return kept


def place_on_masks(tree: CentrelineTree, masks: Sequence[np.ndarray], views: Sequence[CArmView],
                   max_shift_mm: float = MAX_SHIFT_MM, smoothing_mm: float = SMOOTHING_MM, min_measured: int = 5,
                   min_run_mm: float = MIN_RUN_MM, **kwargs) -> Tuple[CentrelineTree, List[MaskPlacement]]:
    """The tree with every branch re-placed on the masks' midlines (module docstring), and what moved."""
    if len(masks) != len(views):
        raise ValueError(f"{len(masks)} masks for {len(views)} views: give one mask per view, in the views' order")
    if len(views) < 2:
        raise ValueError("placing a centreline on the masks' midlines needs two views or more (one view cannot "
                         "tell the displacement in depth)")
    moved: Dict[int, CentrelineBranch] = {}
    report: List[MaskPlacement] = []
    for branch in sorted(tree.branches, key=lambda b: b.branch_id):  # parents first: ids grow with the generation
        points = branch.points_mm
        if len(points) < 2:
            moved[branch.branch_id] = branch
            report.append(MaskPlacement(branch.branch_id, 0.0, 0.0, False))
            continue
        arc = branch.arc_length_mm
        rest = [b for b in tree.branches if b.branch_id != branch.branch_id]
        others = np.concatenate([b.points_mm for b in rest]) if rest else np.zeros((0, 3))
        others_radii = np.concatenate([b.inscribed_radius_mm for b in rest]) if rest else np.zeros(0)
        shifts = midline_shifts(points, smooth_tangents(points, TANGENT_SMOOTHING_MM), masks, views,
                                radii_mm=branch.inscribed_radius_mm, others_mm=others, others_radii_mm=others_radii,
                                **kwargs)
        # a side branch's mouth on this branch widens the masks there (``width_anomalies``); its own start,
        # inside its parent, and a free end's cap have no edges of their own
        ok = np.isfinite(shifts).all(axis=1) & ~junction_zones(tree, branch, side_branch_mouths=False)
        ok[ok] = np.linalg.norm(shifts[ok], axis=1) <= max_shift_mm
        ok &= runs_at_least(ok, arc, min_run_mm)
        parent = moved.get(branch.parent_id) if branch.parent_id is not None else None
        # the side branch stays on its parent's (moved) junction point
        junction_shift = (parent.points_mm[branch.parent_index] - tree.branch(branch.parent_id).points_mm[branch.parent_index]
                          if parent is not None else None)
        delta = shift_along_arc(arc, ok, shifts, junction_shift, smoothing_mm, min_measured)
        moved[branch.branch_id] = replace(branch, points_mm=points + delta)
        # unmeasured (fewer than min_measured): kept as it is, moved with its junction (its length stays)
        placed = int(ok.sum()) >= min_measured or bool(np.any(delta))
        report.append(MaskPlacement(branch.branch_id, float(ok.mean()), float(np.linalg.norm(delta, axis=1).mean()), placed))
    return CentrelineTree([moved[b.branch_id] for b in tree.branches]), report
