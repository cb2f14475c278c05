"""Analytic vessel phantoms with known answers for quantitative coronary analysis (QCA).

Every phantom is a ``phantoms.CentrelineTree`` (LPS mm) plus the truth needed to score a
measure against it, and is voxelised with the package's ``phantoms.voxelize`` (voxel-centre test
against the union of tubes, radius linear along each segment).

Lesion profile (``stenosed_tube``)
    Over the lesion length L the diameter follows d(x) = d_ref · (1 − S · w(x)), x ∈ [0, L] from
    the lesion start, with S = %DS / 100 and w a plateau with cosine ramps of length
    ``ramp = min(ramp_mm, L / 4)`` at each end: w = (1 − cos(π x / ramp)) / 2 on the first ramp,
    1 on the throat, mirrored on the last ramp. L is therefore the full extent where the lumen is
    narrower than the reference, MLD = d_ref (1 − S), %AS = 100 (1 − (1 − S)²).

Voxelisation and lengths
    ``voxelize_exact`` gives every cross-section perpendicular to the centreline exactly its disc
    and flat free ends, so a tube's lumen is as long as its centreline (``length_mm``) and the
    lesion's ramps keep their nominal shape; positions along the vessel (``lesion_start_mm`` …)
    are arc lengths from the centreline's first point (the ostium) along the centreline through
    the lumen centres (for an eccentric lesion it steps sideways on the ramps, so its lesion and
    tube lengths exceed the axis values ``lesion_axis_length_mm``, ``axis_length_mm``).

Concentric vs eccentric
    Concentric: the centreline stays on the axis and both walls move in. Eccentric: one wall
    stays where the healthy wall is and the centreline moves by (r_ref − r(x)) towards it, so all
    of the narrowing comes from the opposite wall (a plaque on one side).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence

import numpy as np

from ..geometry import CArmView, VolumeGrid
from ..phantoms import Branch, CentrelineTree

SAMPLE_STEP_MM = 0.1  # phantom centreline sampling: fine enough that linear radii follow the ramps


@dataclass
class AnalyticPhantom:
    """A phantom tree and its truth (lengths in mm, percentages 0–100)."""

    tree: CentrelineTree
    truth: Dict[str, object] = field(default_factory=dict)


def _unit(v: Sequence[float]) -> np.ndarray:
    v = np.asarray(v, float)
    n = np.linalg.norm(v)
    if n == 0:
        raise ValueError("a direction must be a non-zero vector")
    return v / n


def _perpendicular(t: np.ndarray) -> np.ndarray:
    helper = np.array([0.0, 0.0, 1.0]) if abs(t[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n = np.cross(t, helper)
    return n / np.linalg.norm(n)


def grid_around(tree: CentrelineTree, spacing_mm: float, margin_mm: float = 2.0) -> VolumeGrid:
    """The smallest axis-aligned grid at ``spacing_mm`` holding the tree's tubes plus a margin."""
    lo, hi = tree.bounds()
    lo, hi = lo - margin_mm, hi + margin_mm
    shape = tuple(int(np.ceil((h - l) / spacing_mm)) + 1 for l, h in zip(lo, hi))
    return VolumeGrid(shape, (float(spacing_mm),) * 3, tuple(float(c) for c in (lo + hi) / 2))


def straight_tube(length_mm: float = 20.0, diameter_mm: float = 3.0, direction=(1.0, 0.6, 0.3),
                  center_mm=(0.0, 0.0, 0.0)) -> AnalyticPhantom:
    """A straight cylinder (flat ends) of known diameter and length, oblique to the grid axes."""
    t = _unit(direction)
    s = np.linspace(-length_mm / 2, length_mm / 2, max(2, int(round(length_mm / 1.0)) + 1))
    points = np.asarray(center_mm, float) + s[:, None] * t
    tree = CentrelineTree([Branch(points, np.full(len(s), diameter_mm / 2), "tube")], "straight-tube")
    return AnalyticPhantom(tree, {"diameter_mm": diameter_mm, "length_mm": length_mm, "direction": t.tolist()})


def helix(radius_mm: float = 8.0, pitch_mm: float = 12.0, turns: float = 1.5, diameter_mm: float = 2.5,
          axis=(0.0, 0.0, 1.0)) -> AnalyticPhantom:
    """A helical tube; its centreline length is turns · sqrt((2π R)² + pitch²)."""
    a = _unit(axis)
    e1 = _perpendicular(a)
    e2 = np.cross(a, e1)
    length = turns * np.hypot(2 * np.pi * radius_mm, pitch_mm)
    phi = np.linspace(0.0, 2 * np.pi * turns, int(np.ceil(length / SAMPLE_STEP_MM)) + 1)
    points = (radius_mm * np.cos(phi))[:, None] * e1 + (radius_mm * np.sin(phi))[:, None] * e2 \
        + (pitch_mm * phi / (2 * np.pi) - pitch_mm * turns / 2)[:, None] * a
    tree = CentrelineTree([Branch(points, np.full(len(phi), diameter_mm / 2), "helix")], "helix")
    return AnalyticPhantom(tree, {"diameter_mm": diameter_mm, "length_mm": float(length)})


def lesion_weight(x_mm: np.ndarray, lesion_length_mm: float, ramp_mm: float = 2.0) -> np.ndarray:
    """The plateau-with-cosine-ramps narrowing weight w(x) in [0, 1] (module docstring)."""
    x = np.asarray(x_mm, float)
    ramp = min(ramp_mm, lesion_length_mm / 4)
    w = np.zeros_like(x)
    inside = (x > 0) & (x < lesion_length_mm)
    w[inside] = 1.0
    up = inside & (x < ramp)
    w[up] = (1 - np.cos(np.pi * x[up] / ramp)) / 2
    down = inside & (x > lesion_length_mm - ramp)
    w[down] = (1 - np.cos(np.pi * (lesion_length_mm - x[down]) / ramp)) / 2
    return w


def stenosed_tube(length_mm: float = 40.0, diameter_mm: float = 3.0, stenosis_pct: float = 50.0,
                  lesion_length_mm: float = 10.0, lesion_center_mm: Optional[float] = None,
                  eccentric: bool = False, direction=(1.0, 0.5, 0.25), curvature_radius_mm: Optional[float] = None,
                  ramp_mm: float = 2.0, center_mm=(0.0, 0.0, 0.0)) -> AnalyticPhantom:
    """A tube with one focal stenosis (module docstring); optionally bent on a circular arc.

    ``curvature_radius_mm`` bends the axis in a plane (arc length = ``length_mm``), so that the
    cross-sections must follow the centreline's tangent. The truth holds the reference diameter,
    MLD, %DS, %AS, lesion start/end/length along the centreline from its first point (the ostium).
    """
    if not 0 <= stenosis_pct < 100:
        raise ValueError(f"stenosis_pct must lie in [0, 100), got {stenosis_pct}")
    if lesion_center_mm is None:
        lesion_center_mm = length_mm / 2
    start = lesion_center_mm - lesion_length_mm / 2
    if start < 0 or start + lesion_length_mm > length_mm:
        raise ValueError("the lesion must lie inside the tube: check lesion_center_mm and lesion_length_mm")
    s = np.linspace(0.0, length_mm, int(np.ceil(length_mm / SAMPLE_STEP_MM)) + 1)
    t0 = _unit(direction)
    n0 = _perpendicular(t0)
    if curvature_radius_mm:
        angle = s / curvature_radius_mm
        axis = curvature_radius_mm * (np.sin(angle)[:, None] * t0 + (1 - np.cos(angle))[:, None] * n0)
        # The eccentric wall shift goes along the binormal, which is perpendicular to the tangent all along.
        normal = np.tile(np.cross(t0, n0), (len(s), 1))
    else:
        axis = s[:, None] * t0
        normal = np.tile(n0, (len(s), 1))
    axis = axis - (axis.max(axis=0) + axis.min(axis=0)) / 2 + np.asarray(center_mm, float)
    r_ref = diameter_mm / 2
    radii = r_ref * (1 - stenosis_pct / 100 * lesion_weight(s - start, lesion_length_mm, ramp_mm))
    points = axis + (r_ref - radii)[:, None] * normal if eccentric else axis
    kind = "eccentric" if eccentric else "concentric"
    tree = CentrelineTree([Branch(points, radii, "vessel")], f"stenosis-{stenosis_pct:g}-{kind}")
    mld = diameter_mm * (1 - stenosis_pct / 100)
    # Lengths and positions along the centreline through the lumen centres: for an eccentric lesion
    # it steps sideways by r_ref − r on each ramp and is longer than the straight axis.
    arc = branch_arc_length_mm(Branch(points, radii))
    a0, a1 = float(np.interp(start, s, arc)), float(np.interp(start + lesion_length_mm, s, arc))
    truth = {
        "reference_diameter_mm": diameter_mm, "mld_mm": mld, "diameter_stenosis_pct": stenosis_pct,
        "area_stenosis_pct": 100 * (1 - (1 - stenosis_pct / 100) ** 2), "lesion_start_mm": a0,
        "lesion_end_mm": a1, "lesion_length_mm": a1 - a0, "lesion_axis_length_mm": lesion_length_mm,
        "length_mm": float(arc[-1]), "axis_length_mm": length_mm, "eccentric": eccentric,
        "ostium_mm": points[0].tolist(),
    }
    return AnalyticPhantom(tree, truth)


def voxelize_exact(tree: CentrelineTree, grid: VolumeGrid, spacing_along_mm: float = 0.05) -> np.ndarray:
    """Boolean label of the tree whose cross-sections are exactly its nominal discs.

    ``phantoms.voxelize`` takes the union of cones with rounded ends, i.e. the envelope of
    spheres of radius r(s): where r changes fast (a lesion's ramps) that envelope is wider than
    r(s) by up to √(1 + r′²), which shortens a steep lesion and thickens its flanks. Here a voxel
    centre x is inside a branch when, with c(s) its nearest point on the finely resampled
    centreline and t(s) the tangent there, its distance to the line through c(s) along t(s) is at
    most r(s) (and, at the two end samples, it lies on the inner side), so every cross-section
    perpendicular to the centreline is the disc of radius r(s) and free ends are flat.
    Valid while the tube's radius stays below the centreline's radius of curvature.
    """
    from scipy.spatial import cKDTree

    label = np.zeros(grid.shape, dtype=bool)
    for branch in tree.branches:
        s = branch_arc_length_mm(branch)
        fine = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / spacing_along_mm)) + 1))
        c = np.stack([np.interp(fine, s, branch.points[:, a]) for a in range(3)], axis=1)
        r = np.interp(fine, s, branch.radii)
        t = np.gradient(c, axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        lo = np.floor(grid.world_to_index(c.min(axis=0) - r.max())).astype(int)
        hi = np.ceil(grid.world_to_index(c.max(axis=0) + r.max())).astype(int)
        lo, hi = np.clip(lo, 0, np.asarray(grid.shape) - 1), np.clip(hi, 0, np.asarray(grid.shape) - 1)
        box = tuple(slice(int(a), int(b) + 1) for a, b in zip(lo, hi))
        ijk = np.stack(np.meshgrid(*(np.arange(a.start, a.stop) for a in box), indexing="ij"), axis=-1).reshape(-1, 3)
        x = grid.index_to_world(ijk)
        dist, k = cKDTree(c).query(x, distance_upper_bound=float(r.max()) * 1.5 + spacing_along_mm)
        near = np.isfinite(dist)
        w = x[near] - c[k[near]]
        axial = np.einsum("ij,ij->i", w, t[k[near]])
        radial = np.linalg.norm(w - axial[:, None] * t[k[near]], axis=1)
        # Only the end samples bound the axial offset (flat ends); an interior test would punch holes
        # on the outside of bends, where neighbouring samples lie farther apart than the step.
        kk = k[near]
        inside = (radial <= r[kk]) & ~((kk == 0) & (axial < 0)) & ~((kk == len(fine) - 1) & (axial > 0))
        hit = ijk[near][inside]
        label[tuple(hit.T)] = True
    return label


def render_mask(tree: CentrelineTree, view: CArmView, step_mm: float = 0.1) -> np.ndarray:
    """Clean binary mask of a tree in a view: the pixels whose ray meets the tube of ``voxelize_exact``.

    Each branch is cut into short cylinders between centreline samples ``step_mm`` apart (radius the
    mean of the two samples', caps perpendicular to the segment), whose union has the nominal disc as
    every cross-section and flat free ends, the solid ``voxelize_exact`` labels. The ray through a
    pixel centre meets a capped cylinder when the stretch of it within the radius of the axis line
    overlaps the stretch between the two cap planes. (A union of spheres would add a cap of one
    radius at every free end, so the masks would show a longer vessel than the truth scored.)
    """
    from scipy.spatial import cKDTree

    starts, axes, lengths, radii = [], [], [], []
    for branch in tree.branches:
        s = branch_arc_length_mm(branch)
        fine = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step_mm)) + 1))
        c = np.stack([np.interp(fine, s, branch.points[:, a]) for a in range(3)], axis=1)
        r = np.interp(fine, s, branch.radii)
        seg = np.diff(c, axis=0)
        length = np.linalg.norm(seg, axis=1)
        keep = length > 1e-9
        starts.append(c[:-1][keep])
        axes.append(seg[keep] / length[keep, None])
        lengths.append(length[keep])
        radii.append(0.5 * (r[:-1] + r[1:])[keep])
    rows, cols = view.detector_shape
    mask = np.zeros((rows, cols), bool)
    if not starts or sum(len(x) for x in starts) == 0:
        return mask
    start, axis, length, radius = (np.concatenate(x) for x in (starts, axes, lengths, radii))
    # Candidate pixels of each cylinder: within its bounding sphere's image (plus a pixel) of its midpoint.
    middle = start + 0.5 * length[:, None] * axis
    row, col, depth = view.project(middle)
    reach_px = (np.hypot(radius, 0.5 * length) * view.sid_mm / depth) / np.asarray(view.pixel_spacing_mm).min() + 1.0
    lo = np.maximum([np.floor((row - reach_px).min()), np.floor((col - reach_px).min())], 0).astype(int)
    hi = np.minimum([np.ceil((row + reach_px).max()), np.ceil((col + reach_px).max())], [rows - 1, cols - 1]).astype(int)
    if np.any(hi < lo):
        return mask
    rr, cc = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    rr, cc = rr.ravel(), cc.ravel()
    near = cKDTree(np.stack([rr, cc], 1)).query_ball_point(np.stack([row, col], 1), reach_px)
    counts = np.fromiter((len(n) for n in near), int, len(near))
    cyl = np.repeat(np.arange(len(near)), counts)
    pix = np.fromiter((k for n in near for k in n), int, int(counts.sum()))
    source, direction = view.rays(rr[pix].astype(float), cc[pix].astype(float))
    a, w = axis[cyl], source - start[cyl]
    e_along, w_along = np.einsum("ij,ij->i", direction, a), np.einsum("ij,ij->i", w, a)
    e_across, w_across = direction - e_along[:, None] * a, w - w_along[:, None] * a
    # Within the radius: |w_across + λ e_across|² ≤ r², a quadratic in the ray parameter λ.
    qa = np.einsum("ij,ij->i", e_across, e_across)
    qb = np.einsum("ij,ij->i", w_across, e_across)
    qc = np.einsum("ij,ij->i", w_across, w_across) - radius[cyl] ** 2
    parallel = qa < 1e-12
    disc = qb ** 2 - qa * qc
    root = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        in_lo = np.where(parallel, -np.inf, (-qb - root) / qa)
        in_hi = np.where(parallel, np.inf, (-qb + root) / qa)
        # Between the caps: 0 ≤ w_along + λ e_along ≤ length.
        t0, t1 = -w_along / e_along, (length[cyl] - w_along) / e_along
    across = np.abs(e_along) < 1e-12
    cap_lo = np.where(across, -np.inf, np.minimum(t0, t1))
    cap_hi = np.where(across, np.inf, np.maximum(t0, t1))
    meets = np.where(parallel, qc <= 0, disc >= 0) & np.where(across, (w_along >= 0) & (w_along <= length[cyl]), True)
    meets &= np.maximum(in_lo, cap_lo) <= np.minimum(in_hi, cap_hi)
    mask[rr[pix[meets]], cc[pix[meets]]] = True
    return mask


def branch_arc_length_mm(branch: Branch) -> np.ndarray:
    """Cumulative arc length (mm) along a branch's points, 0 at its first point."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(branch.points, axis=0), axis=1))])


def stenosed_tree(tree: CentrelineTree, branch_name: str, stenosis_pct: float, lesion_length_mm: float,
                  lesion_center_fraction: float = 0.4, ramp_mm: float = 2.0) -> AnalyticPhantom:
    """A copy of ``tree`` with a concentric focal stenosis on one branch (resampled at 0.1 mm).

    The reference diameter at the lesion is the branch's own (tapering) healthy diameter.
    """
    names = [b.name for b in tree.branches]
    if branch_name not in names:
        raise ValueError(f"the tree has no branch {branch_name!r}; it has {', '.join(names)}")
    branches = []
    truth: Dict[str, object] = {}
    for b in tree.branches:
        if b.name != branch_name:
            branches.append(Branch(b.points.copy(), b.radii.copy(), b.name))
            continue
        s = branch_arc_length_mm(b)
        fine = np.linspace(0.0, s[-1], int(np.ceil(s[-1] / SAMPLE_STEP_MM)) + 1)
        points = np.stack([np.interp(fine, s, b.points[:, a]) for a in range(3)], axis=1)
        healthy = np.interp(fine, s, b.radii)
        start = lesion_center_fraction * s[-1] - lesion_length_mm / 2
        if start < 0 or start + lesion_length_mm > s[-1]:
            raise ValueError(f"branch {branch_name!r} ({s[-1]:.1f} mm) is too short for a {lesion_length_mm} mm lesion there")
        radii = healthy * (1 - stenosis_pct / 100 * lesion_weight(fine - start, lesion_length_mm, ramp_mm))
        branches.append(Branch(points, radii, b.name))
        ref = 2 * float(np.interp(start + lesion_length_mm / 2, fine, healthy))
        truth = {"branch": branch_name, "reference_diameter_mm": ref, "mld_mm": ref * (1 - stenosis_pct / 100),
                 "diameter_stenosis_pct": stenosis_pct, "lesion_start_mm": start,
                 "lesion_end_mm": start + lesion_length_mm, "lesion_length_mm": lesion_length_mm}
    return AnalyticPhantom(CentrelineTree(branches, f"{tree.name}-stenosis"), truth)
