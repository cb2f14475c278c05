"""Do the masks and the geometry agree? An epipolar check of every view against the others.

Why
    A wrong angle sign, a secondary angle of the wrong sense, a mask drawn on another frame or a
    large patient motion make the views disagree: no 3D tree explains both masks, and minutes of
    optimisation end in ghosts and lost vessels. With the masks and the geometry alone this shows
    in seconds.

Measure
    A centreline pixel p of view k has a partner when its ray passes through a point that lies on
    the vessels of every other view: partner(p) = max over points x on the ray of
    Π_j exp(−d_j(x)² / 2σ²), d_j the distance (mm at the isocenter) from x's projection to mask j,
    read bilinearly from the distance map (exact to a fraction of a pixel). A view's consistency is
    the mean over its centreline pixels (about 1 for a correct pair; bench/RESULTS.md has the
    values measured on correct, swapped and sign-flipped pairs). Centreline pixels weigh every
    vessel by its length, not its width.

Vessels one view cannot see
    A vessel that runs behind another view's collimator, into a clipped part of its frame or off
    its detector has no partner there, though nothing is wrong. Its centreline loses the partner
    where it enters: the partnered pixels just before the stretch have a partner next to that view's
    unseen part. Such stretches (``ViewAgreement.one_view_share``) are named for what they are
    (``agreement_warnings``: missing from the result, or placed by one view); their centreline pixels
    (``ViewAgreement.one_view_pixels_rc``) are drawn on the view's QA overlay (``qa.py``). The rule is
    strict: it finds a part of such vessels, mostly right (RESULTS §93). A wrong angle behind
    a collimator can look the same (lonely stretches next to partners at the shutter's edge: on
    collimated pairs with a flipped secondary angle most were explained so, RESULTS §92), so the
    geometry checks are still named whenever the consistency is low.

Views along one line
    Two views whose projection lines are (nearly) parallel, either way round, see the same shadow: depth
    between them is not resolved (``view_separation_warnings``). 3D-QCA systems ask for views at least 25°
    apart; a separation under 1° is a run given twice.

What it cannot see
    A ray crosses many vessels of the other view, so the measure is lenient: rigid motions of a
    few millimetres between the acquisitions, and swapping the two views of a mirror-symmetric
    pair (LAO 30 / RAO 30), leave it near 1 — two views alone cannot tell these apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage
from skimage.morphology import skeletonize

from .geometry import CArmView, Geometry


@dataclass(frozen=True)
class ConsistencyOptions:
    sigma_mm: float = 0.5  # how far (at the isocenter) a ray may pass beside a vessel and still meet it
    # centreline pixels per view: every one up to it (a fixed random subset beyond it, which has no stretches to follow)
    max_rays_per_view: int = 20000
    ray_step_mm: float = 0.4  # sampling along the rays, below the thinnest vessel's width
    warn_below: float = 0.97  # below this: a warning (correct pairs measure 1.000, faults ≤ 0.94; RESULTS §8)
    seed: int = 0
    # a partnered centreline pixel with a partner that projects this close (pixels) to another view's unseen part
    # marks where a vessel may run into it; a stretch without partners this close (pixels) to it continues it
    unseen_edge_px: float = 6.0
    stretch_gap_px: int = 6
    # a share of a view's centreline seen by it alone above this is named (open fields measure 0; RESULTS §92)
    one_view_warn_share: float = 0.02


RAYS_PER_BATCH = 512  # rays whose sample points are held at once (memory: batch × samples × 3 doubles)


@dataclass(frozen=True)
class ViewAgreement:
    """One view's epipolar agreement with the others (``view_agreement``)."""

    consistency: float  # soft share of its centreline with a partner in every other view's mask
    # share of its centreline without a partner that continues a vessel running into another view's unseen part
    # (collimator, clipped, off the detector): seen by this view only, most likely (a wrong angle can look the same)
    one_view_share: float
    hidden_by: Tuple[int, ...]  # the views (numbered from 1) whose unseen part those vessels run into
    # the consistency with those pixels counted as partnered: whether they explain what has no partner
    visible_consistency: float
    # (2, N) row and column of those centreline pixels, for the QA overlay (``qa.qa_overlay_rgb``)
    one_view_pixels_rc: np.ndarray = field(default_factory=lambda: np.zeros((2, 0), dtype=np.int64),
                                           compare=False, repr=False)

    def one_view_image(self, shape: Sequence[int]) -> np.ndarray:
        """Bool image (the view's detector ``shape``) of its centreline pixels seen by it alone."""
        image = np.zeros(tuple(shape), dtype=bool)
        image[self.one_view_pixels_rc[0], self.one_view_pixels_rc[1]] = True
        return image


def _unseen_distance_px(unseen: Optional[np.ndarray], shape: Sequence[int]) -> np.ndarray:
    """Distance (pixels) from every pixel to what the view cannot show: the frame's unseen pixels where given,
    and always the outside of the detector (a ring of unseen pixels just beyond its edge)."""
    padded = np.ones((shape[0] + 2, shape[1] + 2), dtype=bool)
    padded[1:-1, 1:-1] = False if unseen is None else np.asarray(unseen, dtype=bool)
    return ndimage.distance_transform_edt(~padded)[1:-1, 1:-1]


def _pixel_coordinates(view: CArmView, points: np.ndarray) -> np.ndarray:
    """(2, N) row and column of the points' projections (far off the detector where they have none)."""
    row, col, _ = view.project(points.reshape(-1, 3))
    inside = np.isfinite(row) & np.isfinite(col)
    return np.vstack([np.where(inside, row, -1e6), np.where(inside, col, -1e6)])


def _read(image: np.ndarray, coordinates: np.ndarray, outside: float, shape: Tuple[int, ...]) -> np.ndarray:
    return ndimage.map_coordinates(image, coordinates, order=1, mode="constant", cval=outside).reshape(shape)


def view_agreement(geometry: Geometry, masks: Sequence[np.ndarray],
                   unseen: Optional[Sequence[Optional[np.ndarray]]] = None,
                   options: ConsistencyOptions = ConsistencyOptions()) -> List[ViewAgreement]:
    """Per view, how much of its centreline has a partner in every other view, and how much of the rest is a vessel
    that runs on where another view cannot show it (``unseen``: per view, a bool image of the pixels its frame
    cannot show a vessel in, ``masks.unseen_pixels``, or None; off the detector counts as unseen always)."""
    views = list(geometry.views)
    if len(masks) != len(views):
        raise ValueError(f"{len(masks)} masks for {len(views)} views")
    if unseen is not None and len(unseen) != len(views):
        raise ValueError(f"{len(unseen)} unseen images for {len(views)} views")
    masks = [np.asarray(m, dtype=bool) for m in masks]
    if len(views) < 2:
        return [ViewAgreement(1.0, 0.0, (), 1.0) for _ in views]
    rng = np.random.default_rng(options.seed)
    distance_mm = [ndimage.distance_transform_edt(~m) * min(v.isocenter_pixel_spacing_mm) for m, v in zip(masks, views)]
    unseen_px = [_unseen_distance_px(None if unseen is None else unseen[j], v.detector_shape)
                 for j, v in enumerate(views)]
    grid = geometry.volume
    half_depth = 0.5 * float(np.linalg.norm(np.asarray(grid.shape) * np.asarray(grid.spacing_mm)))
    depths = np.arange(-half_depth, half_depth + 1e-9, options.ray_step_mm)
    centre = np.asarray(grid.center_mm, dtype=np.float64)
    out = []
    for k, (mask, view) in enumerate(zip(masks, views)):
        skeleton = skeletonize(mask)
        rows, cols = np.nonzero(skeleton)
        if rows.size == 0:
            out.append(ViewAgreement(0.0, 0.0, (), 0.0))
            continue
        if rows.size > options.max_rays_per_view:  # a fixed random subset: no stretches to follow
            keep = np.sort(rng.choice(rows.size, options.max_rays_per_view, replace=False))
            rows, cols = rows[keep], cols[keep]
        partner = np.empty(rows.size)
        # per other view: how close (pixels) the nearest point of the ray that meets every other view's vessels
        # projects to that view's unseen part (inf: no such point)
        edge_px = {j: np.full(rows.size, np.inf) for j in range(len(views)) if j != k}
        for start in range(0, rows.size, RAYS_PER_BATCH):
            r, c = rows[start:start + RAYS_PER_BATCH], cols[start:start + RAYS_PER_BATCH]
            origin, direction = view.rays(r.astype(np.float64), c.astype(np.float64))
            # The stretch of each ray across the volume: ± half its diagonal around the grid's centre.
            along = (centre - origin) @ direction.T
            points = origin + (along[:, None] + depths[None, :])[..., None] * direction[:, None, :]
            agreement = np.ones(points.shape[:2])
            coordinates = {j: _pixel_coordinates(views[j], points) for j in edge_px}
            for j, at in coordinates.items():
                # Off the detector a view shows no vessel: far from its vessels.
                agreement *= np.exp(-0.5 * (_read(distance_mm[j], at, 1e3, agreement.shape) / options.sigma_mm) ** 2)
            partner[start:start + r.size] = agreement.max(axis=1)
            meets = agreement >= 0.5
            if meets.any():
                for j, at in coordinates.items():
                    near = np.where(meets, _read(unseen_px[j], at, 0.0, agreement.shape), np.inf)
                    edge_px[j][start:start + r.size] = near.min(axis=1)
        explained = np.zeros(rows.size, dtype=bool)
        hidden_by: List[int] = []
        lonely = partner < 0.5
        if lonely.any() and not lonely.all() and rows.size == int(skeleton.sum()):
            # A vessel this view shows that runs into another view's unseen part: its centreline loses its partner
            # where it enters, and the last partnered pixels have a partner next to that part of the other view (any
            # of their partners: a ray crossing a vessel meets it over its whole width, and may meet others).
            lonely_image = np.zeros(mask.shape, dtype=bool)
            lonely_image[rows[lonely], cols[lonely]] = True
            labels, _ = ndimage.label(lonely_image, structure=np.ones((3, 3), dtype=bool))
            for j in edge_px:
                at_edge = ~lonely & (edge_px[j] <= options.unseen_edge_px)
                if not at_edge.any():
                    continue
                edge_image = np.zeros(mask.shape, dtype=bool)
                edge_image[rows[at_edge], cols[at_edge]] = True
                near_edge = ndimage.binary_dilation(edge_image, structure=np.ones((3, 3), dtype=bool),
                                                    iterations=options.stretch_gap_px)
                touching = np.unique(labels[near_edge & lonely_image])
                if touching.size:
                    explained |= np.isin(labels[rows, cols], touching)
                    hidden_by.append(j + 1)
        out.append(ViewAgreement(float(partner.mean()), float(explained.mean()), tuple(hidden_by),
                                 float(np.where(explained, 1.0, partner).mean()),
                                 np.vstack([rows[explained], cols[explained]]).astype(np.int64)))
    return out


def view_consistency(geometry: Geometry, masks: Sequence[np.ndarray],
                     options: ConsistencyOptions = ConsistencyOptions()) -> List[float]:
    """Per view, the share of its centreline pixels whose ray meets the vessels of every other view."""
    return [a.consistency for a in view_agreement(geometry, masks, None, options)]


GEOMETRY_CHECKS = ("check the angle signs (LAO +, RAO −, CRA +, CAU −), that each mask belongs to its view and to the "
                   "same cardiac phase and is not transposed or flipped, and the SID/SOD values")


def _geometry_warning(view_number: int, consistency: float) -> str:
    return (f"view {view_number}: only {100 * consistency:.0f} % of its vessel centreline has a partner in the other "
            f"view(s) along the epipolar lines; {GEOMETRY_CHECKS}; a vessel that runs behind another view's collimator "
            "has no partner either (given the frames, that is read and named)")


def consistency_warnings(consistency: Sequence[float], options: ConsistencyOptions = ConsistencyOptions()) -> List[str]:
    """A warning for every view whose consistency is below ``options.warn_below``, naming what to check."""
    return [_geometry_warning(n, value) for n, value in enumerate(consistency, start=1) if value < options.warn_below]


def _one_view_clause(agreement: ViewAgreement, pronoun: str) -> str:
    others = " and ".join(f"view {j}" for j in agreement.hidden_by)
    return (f"where {others} cannot show {pronoun} (behind a collimator or shutter, in a clipped part of the frame, or off "
            "the detector): seen by one view only, those vessels cannot be placed in depth and will be missing from "
            "the result or placed less well; a view whose field includes them would show them")


def agreement_warnings(agreements: Sequence[ViewAgreement],
                       options: ConsistencyOptions = ConsistencyOptions()) -> List[str]:
    """Per view, what its epipolar agreement says: the geometry warning of ``consistency_warnings`` where the missing
    partners are not explained; where they continue vessels another view cannot show, that first — with the
    geometry checks still named, because a wrong angle behind a collimator can look the same (RESULTS §92) — and
    that alone where the consistency is not low."""
    out = []
    for n, agreement in enumerate(agreements, start=1):
        if agreement.consistency < options.warn_below:
            if agreement.visible_consistency < options.warn_below or not agreement.hidden_by:
                out.append(_geometry_warning(n, agreement.consistency))
                continue
            out.append(f"view {n}: {100 * (1 - agreement.consistency):.0f} % of its vessel centreline has no partner in "
                       "the other view(s) along the epipolar lines, and those stretches continue vessels "
                       f"{_one_view_clause(agreement, 'them')}. If the other views do show those vessels, the geometry is "
                       f"wrong instead: {GEOMETRY_CHECKS}")
        elif agreement.one_view_share > options.one_view_warn_share:
            out.append(f"view {n}: {100 * agreement.one_view_share:.0f} % of its vessel centreline runs on "
                       f"{_one_view_clause(agreement, 'it')}")
    return out


#: the least angle between the projection lines of the two views furthest apart without a warning (3D-QCA
#: systems ask for two views at least 25° apart), and the separation under which two views are one
MIN_VIEW_SEPARATION_DEG = 25.0
SAME_VIEW_SEPARATION_DEG = 1.0


def view_separation_deg(a: CArmView, b: CArmView) -> float:
    """Angle (degrees, 0–90) between two views' projection lines; opposite views (180° apart) are 0."""
    cosine = abs(float(np.dot(a.detector_direction, b.detector_direction)))
    return float(np.degrees(np.arccos(min(cosine, 1.0))))


def view_separation_warnings(geometry: Geometry) -> List[str]:
    """Warnings (possibly none) about views that look along the same line: a run given twice, or views too close
    in angle for any pair to resolve depth."""
    views = geometry.views
    out: List[str] = []
    separations = {(i, j): view_separation_deg(views[i], views[j])
                   for i in range(len(views)) for j in range(i + 1, len(views))}
    for (i, j), angle in separations.items():
        if angle < SAME_VIEW_SEPARATION_DEG:
            out.append(f"views {i + 1} and {j + 1} look along the same line ({views[i].describe()} and "
                       f"{views[j].describe()}, {angle:.1f}° apart): the same run given twice, or the same "
                       "projection from opposite sides; give views of different angles")
    widest = max(separations.values(), default=0.0)
    if SAME_VIEW_SEPARATION_DEG <= widest < MIN_VIEW_SEPARATION_DEG:  # under 1°: named pair by pair above
        out.append(f"the views are at most {widest:.1f}° apart (the angle between their projection lines): depth "
                   f"is poorly resolved and the tree will be smeared along the views' axis; give views at least "
                   f"{MIN_VIEW_SEPARATION_DEG:g}° apart")
    return out
