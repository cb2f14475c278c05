"""Foreshortening and overlap of a vessel segment in C-arm views, and the best-view map.

Foreshortening (``foreshortening``)
    A segment's apparent length in a view is the length of its projection; foreshortening is
    F = 1 − L_projected / L_3D, 0 when the segment lies parallel to the detector, 1 when it runs
    along the ray. Each element Δp of the polyline contributes |Δp − (Δp·r̂) r̂|, r̂ the unit ray
    through its midpoint: from the source (perspective, what the C-arm shows once the image is
    scaled back to the element's depth) or the central ray d (``perspective=False``, the
    parallel-projection value, independent of the source distance). For a straight segment of
    unit direction t, the parallel value is 1 − √(1 − (t·d)²).

Overlap (``overlap_fraction``)
    The segment's centreline samples and the rest of the tree's are projected in parallel onto
    the detector plane (u, v of ``geometry.CArmView``). A segment sample is overlapped when its
    disc (radius r) meets the disc of any other tree sample (r_seg + r_other > their distance).
    Tree samples within ``attach_mm`` (3D) of the segment — its own continuation and the mouths
    of its side branches — are not "others": they touch it in space, not only in the image.
    The overlap is the fraction of the segment's samples overlapped.

Clearance (``other_vessel_clearance``)
    Per centreline sample of a vessel, in one acquisition view (perspective), the detector distance
    from its projection to the nearest projected edge of another vessel (each other sample's radius
    times its magnification), the same "others" as above: how far a measurement across the vessel in
    that view's image can reach before it takes in another vessel's iodine.

Epipolar angle (``epipolar_angles_deg``)
    Two views place a point in depth by matching it along their epipolar lines: the plane through
    both sources and the point meets each detector in one line. Where a vessel crosses those planes
    its match is sharp; where it runs along them a lateral error δ of its projection moves its depth
    by about δ / sin θ (θ the angle between the vessel's direction and the plane: ×3.9 at 15°), and
    at 0° the two views say nothing of its course within the plane but its ends. Per centreline
    point θ is the largest over pairs of views; tangents are chords over ±``half_window_mm`` of arc,
    so that voxel steps do not set them. ``depth_view`` is the view to add: over the clinical range,
    the view whose pairs with the acquired ones cross a segment at the largest median θ (sources at
    the acquired views' mean SOD; within 1° of the largest, the least foreshortened).

Best-view map (``view_map``)
    Over primary α ∈ [−60°, 60°] (LAO +) and secondary β ∈ [−40°, 40°] (CRA +) the score is
    F + w·overlap (``overlap_weight`` w = 1); the suggested view minimises it. Views 180° apart
    show the same projection mirrored, so the clinical range is enough.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import CArmView

PRIMARY_RANGE_DEG = (-60.0, 60.0)
SECONDARY_RANGE_DEG = (-40.0, 40.0)
MAX_VIEW_STEP_DEG = 30.0  # the map then still has 5 × 3 views over the clinical range (quick looks; 2 is the default)
MIN_VIEW_STEP_DEG = 0.5  # 241 × 161 views; finer steps only cost memory (a C-arm is set to a degree)
DEPTH_VIEW_SAMPLES = 100  # points of a segment ``depth_view`` weighs (every view of the range against each)
EPIPOLAR_WEAK_DEG = 15.0  # below it a mask's lateral error moves the depth over 3.9 times as far (module docstring)


def view_direction(primary_deg, secondary_deg) -> np.ndarray:
    """d = (sin α cos β, −cos α cos β, sin β) (``geometry.py``), broadcast over the angles."""
    a, b = np.radians(primary_deg), np.radians(secondary_deg)
    return np.stack(np.broadcast_arrays(np.sin(a) * np.cos(b), -np.cos(a) * np.cos(b), np.sin(b)), axis=-1)


def image_axes(primary_deg: float, secondary_deg: float):
    """Detector axes u (columns) and v (rows) of a view (``geometry.py``)."""
    a = math.radians(primary_deg)
    u = np.array([math.cos(a), math.sin(a), 0.0])
    return u, np.cross(u, view_direction(primary_deg, secondary_deg))


def foreshortening(points_mm: np.ndarray, view: CArmView, perspective: bool = True) -> float:
    """1 − projected length / 3D length of a polyline in a view (module docstring)."""
    p = np.asarray(points_mm, float)
    if len(p) < 2:
        raise ValueError("a segment needs at least 2 points to have a length")
    delta = np.diff(p, axis=0)
    if perspective:
        ray = (p[:-1] + p[1:]) / 2 - view.source_position
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    else:
        ray = np.broadcast_to(view.detector_direction, delta.shape)
    along = np.einsum("ij,ij->i", delta, ray)
    projected = np.linalg.norm(delta - along[:, None] * ray, axis=1).sum()
    length = np.linalg.norm(delta, axis=1).sum()
    if length == 0:
        raise ValueError("the segment has zero length")
    return float(1.0 - projected / length)


def foreshortening_map(points_mm: np.ndarray, primary_deg: np.ndarray, secondary_deg: np.ndarray) -> np.ndarray:
    """Parallel-projection foreshortening of a polyline for every (α, β) of a grid (arrays broadcast)."""
    delta = np.diff(np.asarray(points_mm, float), axis=0)
    lengths = np.linalg.norm(delta, axis=1)
    d = view_direction(primary_deg, secondary_deg)  # (..., 3)
    along = d @ delta.T  # (..., M)
    perp = np.sqrt(np.maximum(lengths ** 2 - along ** 2, 0.0))
    return 1.0 - perp.sum(axis=-1) / lengths.sum()


def _others_for(segment_mm: np.ndarray, segment_radii: np.ndarray, others_mm: np.ndarray, others_radii: np.ndarray,
                attach_mm: float):
    if len(others_mm) == 0:
        return others_mm, others_radii
    dist, _ = cKDTree(segment_mm).query(others_mm)
    keep = dist > attach_mm + float(np.max(segment_radii)) + others_radii
    return others_mm[keep], others_radii[keep]


def overlap_fraction(segment_mm: np.ndarray, segment_radii: np.ndarray, others_mm: np.ndarray,
                     others_radii: np.ndarray, primary_deg: float, secondary_deg: float,
                     attach_mm: float = 2.0, _filtered: bool = False) -> float:
    """Fraction of the segment's samples whose projected disc meets another tree sample's (module docstring)."""
    seg = np.asarray(segment_mm, float)
    seg_r = np.broadcast_to(np.asarray(segment_radii, float), (len(seg),))
    oth, oth_r = np.asarray(others_mm, float).reshape(-1, 3), np.broadcast_to(np.asarray(others_radii, float), (len(others_mm),))
    if not _filtered:
        oth, oth_r = _others_for(seg, seg_r, oth, oth_r, attach_mm)
    if len(oth) == 0:
        return 0.0
    u, v = image_axes(primary_deg, secondary_deg)
    basis = np.stack([u, v], axis=1)
    tree2d = cKDTree(oth @ basis)
    reach = float(seg_r.max() + oth_r.max())
    hits = tree2d.query_ball_point(seg @ basis, reach)
    q = seg @ basis
    o2 = oth @ basis
    covered = np.zeros(len(seg), bool)
    for i, idx in enumerate(hits):
        if idx:
            idx = np.asarray(idx)
            covered[i] = bool(np.any(np.linalg.norm(o2[idx] - q[i], axis=1) < seg_r[i] + oth_r[idx]))
    return float(covered.mean())


def other_vessel_clearance(points_mm: np.ndarray, radii_mm: np.ndarray, others_mm: np.ndarray,
                           others_radii_mm: np.ndarray, view: CArmView, attach_mm: float = 2.0,
                           neighbours: int = 16) -> np.ndarray:
    """Per sample of a vessel, the detector distance (mm) from its projected centre to the nearest
    projected edge of another vessel in ``view`` (inf where none): how far across the vessel a
    measurement can reach before it sees another. Projected in perspective, each other sample's radius
    scaled by its magnification. Samples within ``attach_mm`` of the vessel in 3D are not others
    (``overlap_fraction``); the edge is taken over the ``neighbours`` nearest other samples."""
    seg = np.asarray(points_mm, float).reshape(-1, 3)
    spacing = np.asarray(view.pixel_spacing_mm, float)
    row, col, _ = view.project(seg)
    return distance_to_other_vessels(np.stack([row * spacing[0], col * spacing[1]], axis=1),
                                     *other_vessels_projected(seg, radii_mm, others_mm, others_radii_mm, view, attach_mm),
                                     neighbours)


def other_vessels_projected(points_mm: np.ndarray, radii_mm, others_mm: np.ndarray, others_radii_mm, view: CArmView,
                            attach_mm: float = 2.0):
    """The other vessels of ``other_vessel_clearance`` in ``view``: their samples' detector positions (M, 2),
    (row mm, column mm), and projected radii (M,)."""
    seg = np.asarray(points_mm, float).reshape(-1, 3)
    seg_r = np.broadcast_to(np.asarray(radii_mm, float), (len(seg),))
    oth = np.asarray(others_mm, float).reshape(-1, 3)
    oth_r = np.broadcast_to(np.asarray(others_radii_mm, float), (len(oth),))
    oth, oth_r = _others_for(seg, seg_r, oth, oth_r, attach_mm)
    if len(oth) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    spacing = np.asarray(view.pixel_spacing_mm, float)
    orow, ocol, odepth = view.project(oth)
    return np.stack([orow * spacing[0], ocol * spacing[1]], axis=1), oth_r * view.sid_mm / odepth


def distance_to_other_vessels(detector_mm: np.ndarray, others_detector_mm: np.ndarray, others_radii_mm: np.ndarray,
                              neighbours: int = 16) -> np.ndarray:
    """Per detector position (N, 2), the distance to the nearest projected edge of the other vessels
    (``other_vessels_projected``; negative inside one, inf where none), over the ``neighbours`` nearest samples."""
    where = np.asarray(detector_mm, float).reshape(-1, 2)
    if len(others_detector_mm) == 0 or len(where) == 0:
        return np.full(len(where), np.inf)
    k = min(neighbours, len(others_detector_mm))
    known = np.isfinite(where).all(axis=1)
    out = np.full(len(where), np.nan)
    if not known.any():
        return out
    dist, idx = cKDTree(others_detector_mm).query(where[known], k=k)
    dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
    out[known] = np.min(dist - others_radii_mm[idx], axis=1)
    return out


def chord_tangents(points_mm: np.ndarray, half_window_mm: float = 1.0) -> np.ndarray:
    """Unit tangents (N, 3) of a polyline, each the chord between the points ``half_window_mm`` of arc before and after
    (clipped at the ends)."""
    p = np.asarray(points_mm, float).reshape(-1, 3)
    if len(p) < 2:
        return np.full(p.shape, np.nan)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    before = np.clip(np.searchsorted(s, s - half_window_mm, side="left"), 0, len(p) - 1)
    after = np.clip(np.searchsorted(s, s + half_window_mm, side="right") - 1, 0, len(p) - 1)
    chord = p[after] - p[before]
    norm = np.linalg.norm(chord, axis=1, keepdims=True)
    return np.where(norm > 0, chord / np.maximum(norm, 1e-12), np.nan)


def _plane_angles_deg(points_mm: np.ndarray, tangents: np.ndarray, source_a: np.ndarray, source_b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between each tangent and the plane through its point and both sources (broadcast; NaN where the
    point lies on the sources' line)."""
    normal = np.cross(source_a - points_mm, source_b - points_mm)
    norm = np.linalg.norm(normal, axis=-1)
    sine = np.abs(np.sum(normal * tangents, axis=-1)) / np.where(norm > 0, norm, np.nan)
    return np.degrees(np.arcsin(np.clip(sine, 0.0, 1.0)))


def epipolar_angles_deg(points_mm: np.ndarray, tangents: np.ndarray, sources_mm: Sequence[np.ndarray]) -> np.ndarray:
    """Per point (N,), the largest over pairs of sources of the angle between the vessel's tangent and the epipolar
    plane through the point (module docstring); NaN with fewer than two distinct sources."""
    p = np.asarray(points_mm, float).reshape(-1, 3)
    t = np.asarray(tangents, float).reshape(-1, 3)
    out = np.full(len(p), np.nan)
    src = [np.asarray(x, float) for x in sources_mm]
    for i in range(len(src)):
        for j in range(i + 1, len(src)):
            out = np.fmax(out, _plane_angles_deg(p, t, src[i], src[j]))
    return out


def depth_view(segment_mm: np.ndarray, views: Sequence[CArmView], step_deg: float = 2.0,
               primary_range_deg: Sequence[float] = PRIMARY_RANGE_DEG,
               secondary_range_deg: Sequence[float] = SECONDARY_RANGE_DEG,
               half_window_mm: float = 1.0) -> Optional[Dict[str, float]]:
    """The view to add so that the segment crosses the epipolar planes (module docstring): its angles, label, the
    segment's median epipolar angle with it and its parallel foreshortening there; None without an acquired view."""
    if not views:
        return None
    seg = np.asarray(segment_mm, float)
    tangent = chord_tangents(seg, half_window_mm)
    # a median over DEPTH_VIEW_SAMPLES points spread along the segment: the centreline is sampled far finer
    every = np.unique(np.linspace(0, len(seg) - 1, min(len(seg), DEPTH_VIEW_SAMPLES)).round().astype(int))
    seg, tangent = seg[every], tangent[every]
    acquired = epipolar_angles_deg(seg, tangent, [v.source_position for v in views])
    a = np.arange(primary_range_deg[0], primary_range_deg[1] + 1e-9, step_deg)
    b = np.arange(secondary_range_deg[0], secondary_range_deg[1] + 1e-9, step_deg)
    aa, bb = np.meshgrid(a, b)
    sod = float(np.mean([v.sod_mm for v in views]))
    candidate = -sod * view_direction(aa, bb)[..., None, :]  # (B, A, 1, 3)
    best = np.broadcast_to(acquired, aa.shape + acquired.shape)
    for v in views:
        best = np.fmax(best, _plane_angles_deg(seg, tangent, v.source_position, candidate))
    median = np.nanmedian(np.where(np.isfinite(best), best, np.nan), axis=-1) if np.isfinite(best).any() else np.zeros(aa.shape)
    fs = foreshortening_map(seg, aa, bb)
    near_best = median >= np.nanmax(median) - 1.0
    j, i = np.unravel_index(int(np.argmin(np.where(near_best, fs, np.inf))), fs.shape)
    return {"primary_deg": float(a[i]), "secondary_deg": float(b[j]), "label": view_label(a[i], b[j]),
            "epipolar_angle_median_deg": float(median[j, i]), "foreshortening": float(fs[j, i])}


@dataclass
class ViewMap:
    primary_deg: np.ndarray  # (A,)
    secondary_deg: np.ndarray  # (B,)
    foreshortening: np.ndarray  # (B, A), rows = secondary
    overlap: np.ndarray  # (B, A)
    score: np.ndarray  # (B, A)
    best_primary_deg: float
    best_secondary_deg: float

    def best(self) -> Dict[str, float]:
        j = int(np.argmin(np.abs(self.secondary_deg - self.best_secondary_deg)))
        i = int(np.argmin(np.abs(self.primary_deg - self.best_primary_deg)))
        return {"primary_deg": self.best_primary_deg, "secondary_deg": self.best_secondary_deg,
                "foreshortening": float(self.foreshortening[j, i]), "overlap": float(self.overlap[j, i]),
                "label": view_label(self.best_primary_deg, self.best_secondary_deg)}


def view_label(primary_deg: float, secondary_deg: float) -> str:
    """'LAO 30 CRA 20'-style name of a view."""
    a, b = round(primary_deg), round(secondary_deg)
    text = "AP" if a == 0 else f"{'LAO' if a > 0 else 'RAO'} {abs(a)}"
    return text + ("" if b == 0 else f" {'CRA' if b > 0 else 'CAU'} {abs(b)}")


def view_map(segment_mm: np.ndarray, segment_radii, others_mm: Optional[np.ndarray] = None, others_radii=None,
             primary_range_deg: Sequence[float] = PRIMARY_RANGE_DEG,
             secondary_range_deg: Sequence[float] = SECONDARY_RANGE_DEG, step_deg: float = 2.0,
             overlap_weight: float = 1.0, attach_mm: float = 2.0) -> ViewMap:
    """Foreshortening, overlap and their score over the clinical range of angles (module docstring).

    Ties (a straight segment is unforeshortened on a whole great circle of views) go to the view
    closest to AP (smallest α² + β²), the easiest to reach.
    """
    if not MIN_VIEW_STEP_DEG <= step_deg <= MAX_VIEW_STEP_DEG:
        raise ValueError(f"the view map's angle step must be from {MIN_VIEW_STEP_DEG:g}° (a C-arm is set to a degree; finer "
                         f"maps only cost memory) to {MAX_VIEW_STEP_DEG:g}° (coarser maps miss the best view), got "
                         f"{step_deg:g}°; the default is 2°")
    seg = np.asarray(segment_mm, float)
    seg_r = np.broadcast_to(np.asarray(segment_radii, float), (len(seg),))
    a = np.arange(primary_range_deg[0], primary_range_deg[1] + 1e-9, step_deg)
    b = np.arange(secondary_range_deg[0], secondary_range_deg[1] + 1e-9, step_deg)
    aa, bb = np.meshgrid(a, b)
    fs = foreshortening_map(seg, aa, bb)
    ov = np.zeros_like(fs)
    if others_mm is not None and len(others_mm):
        oth = np.asarray(others_mm, float)
        oth_r = np.broadcast_to(np.asarray(others_radii, float), (len(oth),))
        oth, oth_r = _others_for(seg, seg_r, oth, oth_r, attach_mm)
        for j in range(len(b)):
            for i in range(len(a)):
                ov[j, i] = overlap_fraction(seg, seg_r, oth, oth_r, a[i], b[j], attach_mm, _filtered=True)
    score = fs + overlap_weight * ov
    tol = 1e-4
    candidates = score <= score.min() + tol
    order = np.where(candidates, aa ** 2 + bb ** 2, np.inf)
    j, i = np.unravel_index(int(np.argmin(order)), order.shape)
    return ViewMap(a, b, fs, ov, score, float(a[i]), float(b[j]))
