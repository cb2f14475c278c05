"""Lumen diameters along a centreline, from the 3D volume and from the 2D view masks.

(Widths fitted to the frames' intensity profiles, sharper than any mask: ``frame_widths.py``.)

3D cross-section (``cross_sections``)
    At each centreline point p with unit tangent t, the plane through p perpendicular to t is
    sampled along ``n_rays`` rays at angles θ_k (in-plane basis e1, e2 ⟂ t). Along each ray the
    volume is interpolated trilinearly and the lumen radius r_k is the first crossing of
    ``level`` going out from p (linear between samples). The cross-section is the star-shaped
    polygon r(θ):  area A = ½ Σ r_k² Δθ,  equivalent circular diameter D = 2 √(A / π);
    minimum and maximum diameters are min/max over θ of r(θ) + r(θ + π).
    Rays are capped at ``ray_cap`` × the median ray: a ray that runs into a side branch (or a
    touching vessel) would otherwise swell the area; an ellipse up to that aspect ratio is kept.
    Trilinear interpolation of a binary label puts its 0.5 level half-way between the last
    inside and first outside voxel centres, i.e. on the voxelised surface on average.

2D widths (``projected_widths``)
    For each view the centreline point and its tangent are projected; the vessel's width is
    measured in the mask along the image normal of the projected tangent (first 0.5 crossings of
    the bilinearly interpolated mask on each side), then scaled to mm at the point's depth
    (magnification SID / depth). Two views give two diameters of the cross-section; combined as
    an ellipse of those diameters, D = √(w₁ w₂) (area π w₁ w₂ / 4), exact for a circular lumen and
    for an elliptical one whose axes the two views see. Points whose tangent is foreshortened
    by more than ``max_foreshortening`` in a view (the width would mix the vessel's length in)
    get NaN for that view.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import numpy as np
from scipy import ndimage

from ..geometry import CArmView, VolumeGrid
from .centreline import CentrelineBranch, CentrelineTree


def plane_basis(tangents: np.ndarray):
    """Two unit vectors (N, 3) each, perpendicular to the tangents and to each other."""
    t = np.asarray(tangents, float)
    helper = np.where(np.abs(t[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(t, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(t, e1)


def first_crossing(values: np.ndarray, step: float, level: float) -> np.ndarray:
    """Distance (in units of ``step``·index) of the first fall below ``level`` along the last axis.

    values[..., 0] is the centre; NaN where the centre itself is below the level; the last
    sample's distance where the profile never falls below it.
    """
    below = values < level
    k = np.argmax(below, axis=-1)
    never = ~below.any(axis=-1)
    k_safe = np.maximum(k, 1)
    v0 = np.take_along_axis(values, (k_safe - 1)[..., None], -1)[..., 0]
    v1 = np.take_along_axis(values, k_safe[..., None], -1)[..., 0]
    frac = np.clip((v0 - level) / np.maximum(v0 - v1, 1e-9), 0.0, 1.0)
    r = (k_safe - 1 + frac) * step
    r = np.where(never, (values.shape[-1] - 1) * step, r)
    return np.where(below[..., 0], np.nan, r)


@dataclass
class CrossSections:
    area_mm2: np.ndarray
    equivalent_diameter_mm: np.ndarray
    min_diameter_mm: np.ndarray
    max_diameter_mm: np.ndarray
    centres_mm: Optional[np.ndarray] = None  # where the rays were cast from after re-centring


def _cast(values_volume: np.ndarray, grid: VolumeGrid, centres: np.ndarray, directions: np.ndarray,
          radii: np.ndarray, level: float, step: float) -> np.ndarray:
    samples = centres[:, None, None, :] + radii[None, None, :, None] * directions[:, :, None, :]
    ijk = grid.world_to_index(samples.reshape(-1, 3)).T
    values = ndimage.map_coordinates(values_volume, ijk, order=1, mode="constant", cval=0.0)
    return first_crossing(values.reshape(len(centres), directions.shape[1], len(radii)), step, level)


def cross_sections(volume: np.ndarray, grid: VolumeGrid, points_mm: np.ndarray, tangents: np.ndarray,
                   level: float = 0.5, n_rays: int = 48, max_radius_mm: float = 4.0,
                   radial_step_mm: Optional[float] = None, ray_cap: float = 2.0, recentre: int = 2) -> CrossSections:
    """Cross-sectional area and diameters of the lumen perpendicular to the centreline (module docstring).

    ``recentre``: times the rays are cast again from the centroid of the section found, in its
    plane: a smoothed centreline can sit off the centre of a narrow eccentric lumen, and rays
    from near a wall see a thin sliver. A centre outside the lumen first moves to the nearest
    lumen sample in its plane.
    """
    points = np.asarray(points_mm, float)
    if len(points) == 0:
        empty = np.zeros(0)
        return CrossSections(empty, empty, empty, empty, np.zeros((0, 3)))
    vol = np.asarray(volume, np.float32)
    step = radial_step_mm or min(grid.spacing_mm) / 5.0
    radii = np.arange(0.0, max_radius_mm + step, step)
    theta = np.arange(n_rays) * 2 * np.pi / n_rays
    e1, e2 = plane_basis(tangents)
    directions = np.cos(theta)[None, :, None] * e1[:, None, :] + np.sin(theta)[None, :, None] * e2[:, None, :]
    centres = points.copy()
    for it in range(recentre + 1):
        r = _cast(vol, grid, centres, directions, radii, level, step)
        outside = np.isnan(r).all(axis=1)
        if outside.any():
            # Nearest in-lumen sample along the rays (searched out to 1 mm).
            near = radii[radii <= 1.0]
            samples = centres[outside, None, None, :] + near[None, None, :, None] * directions[outside, :, None, :]
            vals = ndimage.map_coordinates(vol, grid.world_to_index(samples.reshape(-1, 3)).T, order=1,
                                           mode="constant").reshape(int(outside.sum()), n_rays, len(near))
            inside = vals >= level
            first = np.where(inside.any(axis=2), np.argmax(inside, axis=2), len(near))
            ray = np.argmin(first, axis=1)
            k = first[np.arange(len(ray)), ray]
            found = k < len(near)
            moved = centres[outside].copy()
            moved[found] += (near[np.minimum(k[found] + 1, len(near) - 1)])[:, None] * directions[outside][found, ray[found]]
            centres[outside] = moved
        if it == recentre:
            break
        # Centroid of the star polygon: (2/3) Σ r³ (cos θ, sin θ) Δθ/2 / A, in the section's plane.
        rr = np.nan_to_num(r)
        area = 0.5 * np.sum(rr ** 2, axis=1) * (2 * np.pi / n_rays)
        cx = np.sum(rr ** 3 * np.cos(theta), axis=1) * (2 * np.pi / n_rays) / 3
        cy = np.sum(rr ** 3 * np.sin(theta), axis=1) * (2 * np.pi / n_rays) / 3
        ok = (area > 0) & ~outside
        shift = np.zeros_like(centres)
        shift[ok] = (cx[ok] / area[ok])[:, None] * e1[ok] + (cy[ok] / area[ok])[:, None] * e2[ok]
        centres = centres + shift
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: the centre is outside
        median = np.nanmedian(r, axis=1)
    r = np.minimum(r, ray_cap * median[:, None])
    area = 0.5 * np.sum(r ** 2, axis=1) * (2 * np.pi / n_rays)
    chords = r[:, : n_rays // 2] + r[:, n_rays // 2: 2 * (n_rays // 2)]
    return CrossSections(area, 2 * np.sqrt(area / np.pi), np.min(chords, axis=1), np.max(chords, axis=1), centres)


def branch_cross_sections(volume: np.ndarray, grid: VolumeGrid, branch: CentrelineBranch, level: float = 0.5,
                          **kwargs) -> CrossSections:
    return cross_sections(volume, grid, branch.points_mm, branch.tangents(), level, **kwargs)


@dataclass
class ProjectedCentreline:
    """Centreline points in one view: pixel position, magnification, foreshortening and the image-plane
    unit tangent and normal of the projected centreline (in detector mm: rows and columns may differ)."""

    row: np.ndarray
    col: np.ndarray
    magnification: np.ndarray  # SID / depth of each point
    foreshortening: np.ndarray  # 1 − projected / true length of a short step along the tangent
    tangent_rc: np.ndarray  # (2, N): detector-mm unit tangent (row, col components)
    normal_rc: np.ndarray  # (2, N): the tangent turned by 90°


def project_centreline(points_mm: np.ndarray, tangents: np.ndarray, view: CArmView) -> ProjectedCentreline:
    points = np.asarray(points_mm, float)
    t = np.asarray(tangents, float)
    row, col, depth = view.project(points)
    row2, col2, _ = view.project(points + 0.5 * t)
    spacing = np.asarray(view.pixel_spacing_mm, float)
    dr, dc = (row2 - row) * spacing[0], (col2 - col) * spacing[1]
    norm = np.hypot(dr, dc)
    mag = view.sid_mm / depth
    tr, tc = dr / np.maximum(norm, 1e-12), dc / np.maximum(norm, 1e-12)
    return ProjectedCentreline(row, col, mag, 1.0 - norm / (0.5 * mag), np.stack([tr, tc]), np.stack([-tc, tr]))


def projected_edges(points_mm: np.ndarray, tangents: np.ndarray, mask: np.ndarray, view: CArmView,
                    max_width_mm: float = 8.0, edgeless: Optional[float] = None):
    """The mask's two edges on either side of each projected centreline point, along the image normal.

    Returns (plus_mm, minus_mm, projected): detector-mm distances from the projection to the first 0.5
    crossing of the bilinearly interpolated mask along +normal and −normal; NaN where the projection
    lies outside the mask. Where no edge lies within half of ``max_width_mm`` (magnified), the distance
    searched (``edgeless`` None), or ``edgeless``.
    """
    projected = project_centreline(points_mm, tangents, view)
    row, col, mag = projected.row, projected.col, projected.magnification
    nr, nc = projected.normal_rc
    spacing = np.asarray(view.pixel_spacing_mm, float)
    half_px = max_width_mm * float(np.max(mag)) / float(np.min(spacing)) / 2  # half the widest vessel, magnified
    step_px = 0.1
    offs = np.arange(0.0, half_px + step_px, step_px)
    image = np.asarray(mask, np.float32)
    sides = []
    for sign in (1.0, -1.0):
        rr = row[:, None] + sign * offs[None, :] * nr[:, None] * (np.min(spacing) / spacing[0])
        cc = col[:, None] + sign * offs[None, :] * nc[:, None] * (np.min(spacing) / spacing[1])
        values = ndimage.map_coordinates(image, [rr.ravel(), cc.ravel()], order=1, mode="constant", cval=0.0)
        values = values.reshape(rr.shape)
        side = first_crossing(values, step_px, 0.5) * np.min(spacing)
        if edgeless is not None:
            side = np.where((values >= 0.5).all(axis=-1), edgeless, side)
        sides.append(side)
    return sides[0], sides[1], projected


def projected_widths(points_mm: np.ndarray, tangents: np.ndarray, mask: np.ndarray, view: CArmView,
                     max_width_mm: float = 8.0, max_foreshortening: float = 0.7) -> np.ndarray:
    """Width (mm at each point's depth) of the vessel in one view's mask, perpendicular to its projection."""
    plus, minus, projected = projected_edges(points_mm, tangents, mask, view, max_width_mm)
    width_mm = (plus + minus) / projected.magnification
    return np.where(projected.foreshortening > max_foreshortening, np.nan, width_mm)


def mask_diameters(points_mm: np.ndarray, tangents: np.ndarray, masks: Sequence[np.ndarray],
                   views: Sequence[CArmView], **kwargs) -> Dict[str, np.ndarray]:
    """Per-view widths and their elliptical combination (geometric mean) along a centreline."""
    if len(masks) != len(views):
        raise ValueError(f"{len(masks)} masks for {len(views)} views: give one mask per view")
    widths = np.stack([projected_widths(points_mm, tangents, m, v, **kwargs) for m, v in zip(masks, views)])
    return {"view_widths_mm": widths, "equivalent_diameter_mm": ellipse_diameter(widths)}


def ellipse_diameter(view_widths_mm: np.ndarray) -> np.ndarray:
    """Per point, the equivalent diameter of the ellipse whose axes the views measured: the geometric
    mean of the widths the views have there (NaN where none has)."""
    widths = np.asarray(view_widths_mm, float)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # points no view measured stay NaN
        return np.exp(np.nanmean(np.log(np.where(widths > 0, widths, np.nan)), axis=0))


def views_to_use(available: np.ndarray, preferred: np.ndarray) -> np.ndarray:
    """(views, N) bool: per point, the available views that are preferred where any is, else all the
    available ones (e.g. the views no other vessel crowds, else every view that measured)."""
    available = np.asarray(available, bool)
    chosen = available & np.asarray(preferred, bool)
    return np.where(chosen.any(axis=0), chosen, available)


def junction_zones(tree: CentrelineTree, branch: CentrelineBranch, margin: float = 1.0,
                   side_branch_mouths: bool = True) -> np.ndarray:
    """Points of ``branch`` whose cross-section is not its own lumen's: near a junction or a free end.

    A side branch's first (parent radius · (1 + margin)) mm lie inside or against the parent; a
    parent's section at a junction includes the side branch's mouth (left out with
    ``side_branch_mouths`` False); a free end's last radius is the rounded end cap.
    """
    s = branch.arc_length_mm
    flags = np.zeros(len(s), bool)
    r = np.nan_to_num(branch.inscribed_radius_mm)
    if branch.parent_id is not None:
        parent = tree.branch(branch.parent_id)
        r_parent = float(parent.inscribed_radius_mm[branch.parent_index])
        flags |= s < r_parent * (1 + margin) + float(r[min(len(r) - 1, 0)])
    else:
        flags |= s < (1 + margin) * float(np.max(r[: max(1, len(r) // 10)]))
    end_r = float(np.max(r[-max(1, len(r) // 10):]))
    flags |= s > s[-1] - (1 + margin) * end_r
    for child in (tree.children(branch.branch_id) if side_branch_mouths else ()):
        at = s[child.parent_index]
        r_child = float(np.max(child.inscribed_radius_mm[: max(2, len(child.points_mm) // 5)]))
        flags |= np.abs(s - at) < (1 + margin) * r_child + float(r[child.parent_index])
    return flags
