"""Epipolar consistency of two line-integral images, and the rigid motion that restores it.

Why
    Two views are acquired seconds apart; the heart, patient and table move in between, and the
    nominal C-arm poses then disagree with the images by millimetres. Searching the pose by re-fitting
    the field (``calibration.py``) costs minutes per candidate and, on segmented masks, does not locate
    rotations. Where the frames are given, their vessel path lengths (``evidence.py``) are line integrals
    of one object, and line integrals of one object seen from two sources must agree on every plane
    through both sources (Grangeat; Aichert et al., "Epipolar consistency in transmission imaging",
    IEEE TMI 2015). That check needs no reconstruction: a pose is scored in milliseconds.

Maths
    For a plane through the source S with unit normal n, the derivative of the object's plane
    integrals R(t) = ∫ f(x) δ(x·n − S·n − t) dx at t = 0 is, from the view's line integrals P(ω)
    along unit directions ω from S,  R'(0) = −∫_{S²} δ'(ω·n) P(ω) dω  (substitute x = S + rω,
    dx = r² dr dω and δ'(a/r) = r² δ'(a)). With δ' replaced by the derivative of a normalised Gaussian
    g_ε of width ε = blur_mm / |S − c| (c: the object's centre) the same sum is the derivative of R
    blurred by a Gaussian of about ``blur_mm`` — the same quantity in both views, smooth enough to
    optimise. On the detector, a pixel of area A seen along ω covers dω = A (ω·d)³ / SID².
    Planes through both sources S₁, S₂ contain the baseline b = S₂ − S₁; their normals
    n(κ) = cos κ n₀ + sin κ m (n₀, m ⊥ b; n₀ that of the plane through the centre) are sampled over
    the angles κ the images' vessel pixels span. A ray meets only the planes within a few ε of its
    own κ, so each plane sums only those rays (the rays sorted by κ once per evaluation).

Observable motion
    A translation of one view's object along the baseline leaves every such plane and its integrals
    unchanged: two views cannot see it. A rotation about n₀ and a shift along m change them only
    through the perspective, too little to be found on segmented input (bench/RESULTS.md, section
    16). Searched are the three that move the images across the planes or turn them: the shift along
    n₀ and the rotations (about the region's centre) about the baseline and about m.

Truncation
    The consistency holds only where both views see the whole object on a plane. A vessel that runs
    into one view's collimator or off its detector continues where that view cannot see: on the
    planes through it that view's integral misses what the other view's holds, and the search turns
    the view to hide the difference (on collimated static pairs it applied 1.5–3.8° that were not
    there, bench/RESULTS.md §91). Where each view's unseen part is given (``truncated_rays``: its
    vessel pixels next to it), the planes through those rays are left out of the comparison. That
    stops the spurious turns on static pairs, but a vessel hidden further along still reaches planes
    that are compared, and with real motion the poses found so scored lower (§91): the run asks for it
    only with ``calibration_skip_truncated_planes``. What the run does instead: it searches every plane,
    then scores the motion found on the untruncated planes alone (``untruncated_gain``). A real motion
    makes those planes more consistent too; a turn that only hides what a collimator cuts does not
    (on the collimated static pairs it made them less consistent, §93), and is not applied.

Three views or more
    Each pair has its own baseline, so what view 1–k cannot see moves view k across the planes of
    its pair with a third view. ``estimate_motions`` matches each view to view 1 first, then makes
    every pair consistent at once over all six motions of each view (Gauss–Newton on the plane
    derivatives' differences, with a weak preference for no motion). Three pairs still observe only
    nine of the twelve motions strongly: a shift of every other view together along view 1's axis
    (the whole tree moved in depth for view 1, which sees depth only through its magnification) and
    two more combinations are held mainly by that preference; every pair is made consistent, but
    the motion is not recovered exactly (section 17 of the results). Even the true line integrals
    leave those three combinations about a millimetre off (§68): they change the planes' integrals
    only through the perspective, a hundredth as strongly as the motions the pairs observe.
    Where the joint search ends at the end of its range for any view, the views are matched one pair
    at a time (each to the already corrected view it agrees with best) and the joint search runs
    again from there; only if that ends at the range too are those matches kept. On the real
    three-run phantom the search from each view matched to view 1 ended at the range and left every
    view as given; from the matches in turn it ends inside it (§94).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares, minimize

from .geometry import CArmView, rotation_matrix

#: blurs (mm) of the coarse-to-fine search: the wide one finds the basin, the narrow one the minimum
SEARCH_BLURS_MM = (4.0, 2.0, 1.0)
#: blurs of the joint search over all pairs of three or more views (it starts from the pairs' answers); the
#: last at 0.5 mm: the realistic suites' rotations come out about half as far off as after 1 mm (§68)
JOINT_BLURS_MM = (2.0, 1.0, 0.5)
#: the joint search's preference for no motion, per deg² or mm² (pair costs are of order 0.1): what no
#: pair observes — a common shift of the other views along view 1's axis — then stays near zero
MOTION_PRIOR_WEIGHT = 1e-3
#: the joint search's finite-difference step (deg or mm): below ~0.05 the plane derivatives' differences
#: are rough and the Gauss–Newton steps wander (bench/RESULTS.md §17)
JOINT_DIFF_STEP = 0.05
#: residual evaluations per blur of the joint search (each: every pair's plane derivatives once)
JOINT_MAX_EVALUATIONS = 60


class EpipolarError(ValueError):
    """Two images whose consistency cannot be measured; the message names the reason."""


@dataclass(frozen=True)
class LineIntegralImage:
    """A view's nonzero line integrals (mm of vessel) as rays: enough to integrate over any plane."""

    source_mm: np.ndarray  # (3,) reference frame
    directions: np.ndarray  # (N, 3) unit rays through the nonzero pixels
    weights: np.ndarray  # (N,) P · dω: path length times the pixel's solid angle

    def moved(self, rotation_deg: np.ndarray, translation_mm: np.ndarray, centre_mm: np.ndarray) -> "LineIntegralImage":
        """The same rays when the view's object is moved further, as ``calibration.moved`` moves a view:
        x → R(x − c) + c + t comes first, so the rays go back by its inverse."""
        inverse = rotation_matrix(rotation_deg).T
        centre = np.asarray(centre_mm, float)
        source = inverse @ (self.source_mm - centre - np.asarray(translation_mm, float)) + centre
        return LineIntegralImage(source, self.directions @ inverse.T, self.weights)


#: detector pixels are summed in blocks up to this size before they become rays: finer pixels add rays
#: (time) but no information at the search's finest blur (1 mm at the object, ~1.5 mm on the detector)
RAY_PIXEL_MM = 0.8


def rays_of(image: np.ndarray, view: CArmView, pool: Optional[int] = None) -> LineIntegralImage:
    """The nonzero pixels of ``image`` (line integrals in mm on ``view``'s detector) as weighted rays;
    ``pool`` × ``pool`` pixels summed into one ray through the block's centre (default: blocks of about
    ``RAY_PIXEL_MM``)."""
    image = np.asarray(image, float)
    if image.shape != tuple(view.detector_shape):
        raise EpipolarError(f"the image has shape {image.shape} but the view's detector {tuple(view.detector_shape)}")
    if pool is None:
        pool = max(1, int(round(RAY_PIXEL_MM / float(min(view.pixel_spacing_mm)))))
    if pool > 1:
        padded = np.zeros((-(-image.shape[0] // pool) * pool, -(-image.shape[1] // pool) * pool))
        padded[:image.shape[0], :image.shape[1]] = image
        image = padded.reshape(padded.shape[0] // pool, pool, padded.shape[1] // pool, pool).sum(axis=(1, 3))
    rows, cols = np.nonzero(image > 0)
    if rows.size == 0:
        raise EpipolarError("the image has no vessel (no positive line integral)")
    centre_offset = (pool - 1) / 2.0
    source, directions = view.rays(rows * float(pool) + centre_offset, cols * float(pool) + centre_offset)
    cosine = directions @ view.detector_direction
    area = float(view.pixel_spacing_mm[0] * view.pixel_spacing_mm[1])
    solid_angle = area * cosine ** 3 / view.sid_mm ** 2
    return LineIntegralImage(source, directions, image[rows, cols] * solid_angle)


#: a vessel pixel this close (pixels) to the view's unseen part (collimator, clipped or image edge) runs into it
TRUNCATION_REACH_PX = 3
#: a plane within this many ε (the search's blur as an angle) of a truncated ray is left out of the comparison
TRUNCATION_PLANE_MARGIN = 3.0
#: fewer planes than this (a quarter of those sampled) left at any blur: the pair's motion is not measured (on 21 planes
#: the search turned RCA-8 of the collimated motion suite 1.4° off, §91)
MIN_UNTRUNCATED_PLANES = 64


def truncated_rays(image: np.ndarray, unseen: Optional[np.ndarray], view: CArmView,
                   reach_px: int = TRUNCATION_REACH_PX) -> Optional[LineIntegralImage]:
    """The rays of ``image``'s vessel pixels (line integral > 0) within ``reach_px`` of ``unseen`` (bool, True where
    the view cannot show a vessel: ``masks.unseen_pixels``), weight 1 each; None where no vessel reaches it."""
    if unseen is None:
        return None
    image, unseen = np.asarray(image, float), np.asarray(unseen, bool)
    if unseen.shape != image.shape:
        raise EpipolarError(f"the unseen-pixel image has shape {unseen.shape} but the frame {image.shape}")
    touching = (image > 0) & ndimage.binary_dilation(unseen, iterations=int(reach_px))
    if not touching.any():
        return None
    rows, cols = np.nonzero(touching)
    source, directions = view.rays(rows.astype(float), cols.astype(float))
    return LineIntegralImage(source, directions, np.ones(len(rows)))


def _moved(rays: Optional[LineIntegralImage], motion: np.ndarray, centre: np.ndarray) -> Optional[LineIntegralImage]:
    return None if rays is None else rays.moved(motion[:3], motion[3:], centre)


def with_equal_totals(rays: Sequence[LineIntegralImage], centre_mm: Sequence[float]) -> List[LineIntegralImage]:
    """The views' rays with their weights scaled to one common total, the geometric mean of theirs.

    Every view of one object has nearly the same Σ P·dω·|S − c|² (= ∫ f(x) |S − c|² / |x − S|² dx, the
    object's volume for an object near c), but each view's path lengths carry that frame's own
    attenuation estimate (``evidence.py``), which differs between frames by up to a sixth on the
    realistic suites: a scale the consistency would read as motion (bench/RESULTS.md §68)."""
    return [LineIntegralImage(r.source_mm, r.directions, r.weights * f)
            for r, f in zip(rays, equal_total_factors(rays, centre_mm))]


def equal_total_factors(rays: Sequence[LineIntegralImage], centre_mm: Sequence[float]) -> List[float]:
    """The factor on each view's path lengths that brings its Σ P·dω·|S − c|² to the views' geometric
    mean (``with_equal_totals``); their product is 1."""
    centre = np.asarray(centre_mm, float)
    totals = [float(np.sum(r.weights)) * float(np.sum((r.source_mm - centre) ** 2)) for r in rays]
    if min(totals) <= 0:
        raise EpipolarError("an image has no vessel (no positive line integral)")
    common = math.exp(sum(math.log(t) for t in totals) / len(totals))
    return [common / t for t in totals]


#: the kernel −g' is summed out to this many ε from a plane (its tail beyond is below 4e-5 of its peak)
KERNEL_REACH = 6.0


def _kernel(y: np.ndarray, epsilon: float) -> np.ndarray:
    # −g'_ε(y·ε) = y·exp(−y²/2) / (ε² √(2π))
    return y * np.exp(-0.5 * y * y) / (epsilon ** 2 * math.sqrt(2.0 * math.pi))


def plane_derivatives(rays: LineIntegralImage, ray_kappa: np.ndarray, plane_kappa: np.ndarray,
                      frame: Tuple[np.ndarray, np.ndarray], blur_mm: float, centre_mm: np.ndarray) -> np.ndarray:
    """R'(0) of the epipolar planes n(``plane_kappa``) (``frame`` = (n₀, m), see ``epipolar_frame``),
    blurred by about ``blur_mm``, from the rays whose own planes lie at ``ray_kappa`` (``plane_angles``)."""
    n0, m = frame
    normals = np.cos(plane_kappa)[:, None] * n0 + np.sin(plane_kappa)[:, None] * m
    epsilon = blur_mm / float(np.linalg.norm(rays.source_mm - np.asarray(centre_mm, float)))
    # |ω·n(κ)| = q |sin(κ − κ_ray)|, q = |ω × b̂|: a ray reaches a plane within asin(reach·ε / q) of it
    q_min = float(np.min(np.linalg.norm(np.cross(rays.directions, np.cross(n0, m)), axis=1)))
    reach = math.asin(min(1.0, KERNEL_REACH * epsilon / max(q_min, 1e-6)))
    order = np.argsort(ray_kappa)
    sorted_kappa, directions, weights = ray_kappa[order], rays.directions[order], rays.weights[order]
    low = np.searchsorted(sorted_kappa, plane_kappa - reach)
    high = np.searchsorted(sorted_kappa, plane_kappa + reach)
    out = np.zeros(len(normals))
    for k, (a, b) in enumerate(zip(low, high)):
        if b > a:
            out[k] = weights[a:b] @ _kernel(directions[a:b] @ normals[k] / epsilon, epsilon)
    return out


def epipolar_frame(source_a: np.ndarray, source_b: np.ndarray, centre_mm: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Unit normals n₀, m orthogonal to the baseline: n₀ that of the plane through both sources and the
    centre, m = b̂ × n₀; the epipolar planes' normals are n(κ) = cos κ n₀ + sin κ m."""
    baseline = source_b - source_a
    baseline = baseline / np.linalg.norm(baseline)
    central = np.cross(baseline, np.asarray(centre_mm, float) - source_a)
    central = central / np.linalg.norm(central)
    return central, np.cross(baseline, central)


def plane_angles(rays: LineIntegralImage, other_source: np.ndarray, n0: np.ndarray, m: np.ndarray) -> np.ndarray:
    """κ of the plane through both sources that contains each ray (in (−π/2, π/2])."""
    baseline = other_source - rays.source_mm
    normals = np.cross(baseline, rays.directions)
    kappa = np.arctan2(normals @ m, normals @ n0)
    return (kappa + math.pi / 2) % math.pi - math.pi / 2


def plane_sampling(a: LineIntegralImage, b: LineIntegralImage, blur_mm: float, centre_mm: np.ndarray,
                   planes: int = 256,
                   truncated: Sequence[Optional[LineIntegralImage]] = (None, None)) -> np.ndarray:
    """The angles κ of ``planes`` epipolar planes spanning both images' vessel rays (plus a blur's margin),
    less those within ``TRUNCATION_PLANE_MARGIN`` ε of a ``truncated`` ray of either view (``truncated_rays``,
    moved as the view's rays are)."""
    centre = np.asarray(centre_mm, float)
    n0, m = epipolar_frame(a.source_mm, b.source_mm, centre)
    kappa_a = plane_angles(a, b.source_mm, n0, m)
    kappa_b = plane_angles(b, a.source_mm, n0, m)
    low = min(np.percentile(kappa_a, 0.5), np.percentile(kappa_b, 0.5))
    high = max(np.percentile(kappa_a, 99.5), np.percentile(kappa_b, 99.5))
    epsilon = blur_mm / float(np.linalg.norm(a.source_mm - centre))
    kappa = np.linspace(low - 3.0 * epsilon, high + 3.0 * epsilon, planes)
    cut = [plane_angles(t, other.source_mm, n0, m) for t, other in zip(truncated, (b, a)) if t is not None]
    if not cut:
        return kappa
    cut_kappa = np.sort(np.concatenate(cut))
    position = np.searchsorted(cut_kappa, kappa)
    nearest = np.minimum(np.abs(cut_kappa[np.clip(position - 1, 0, len(cut_kappa) - 1)] - kappa),
                         np.abs(cut_kappa[np.clip(position, 0, len(cut_kappa) - 1)] - kappa))
    return kappa[nearest > TRUNCATION_PLANE_MARGIN * epsilon]


def consistency(a: LineIntegralImage, b: LineIntegralImage, blur_mm: float, centre_mm: np.ndarray,
                planes: int = 256, kappa: Optional[np.ndarray] = None,
                truncated: Sequence[Optional[LineIntegralImage]] = (None, None)) -> Dict[str, Any]:
    """How far two views' plane derivatives disagree over the epipolar planes through both sources
    (sampled by ``plane_sampling``, without the ``truncated`` planes, unless ``kappa`` gives the planes' angles).

    ``cost`` = Σ(ρ_a − ρ_b)² / ½Σ(ρ_a² + ρ_b²): 0 when consistent, 2 when unrelated."""
    centre = np.asarray(centre_mm, float)
    n0, m = epipolar_frame(a.source_mm, b.source_mm, centre)
    if kappa is None:
        kappa = plane_sampling(a, b, blur_mm, centre, planes, truncated)
    rho_a = plane_derivatives(a, plane_angles(a, b.source_mm, n0, m), kappa, (n0, m), blur_mm, centre)
    rho_b = plane_derivatives(b, plane_angles(b, a.source_mm, n0, m), kappa, (n0, m), blur_mm, centre)
    scale = 0.5 * float(np.sum(rho_a ** 2 + rho_b ** 2))
    cost = float(np.sum((rho_a - rho_b) ** 2) / scale) if scale > 0 else float("nan")
    return {"cost": cost, "kappa": kappa, "rho_a": rho_a, "rho_b": rho_b, "scale": scale}


def untruncated_gain(reference: CArmView, reference_image: np.ndarray, view: CArmView, image: np.ndarray,
                     centre_mm: Sequence[float], added: np.ndarray, unseen: Sequence[Optional[np.ndarray]],
                     blur_mm: float = SEARCH_BLURS_MM[-1]) -> Optional[Tuple[float, int]]:
    """How much the motion ``added`` (``MotionEstimate.added``, of ``view``'s object) divides the two views'
    inconsistency on the epipolar planes no truncated vessel ray lies on (``truncated_rays`` of ``unseen``, moved
    with the view), and the fewest planes so compared; None where no vessel of either view runs into its unseen part
    (then every plane is untruncated: the search's own gain says it)."""
    centre = np.asarray(centre_mm, float)
    cut = (truncated_rays(reference_image, unseen[0], reference), truncated_rays(image, unseen[1], view))
    if cut[0] is None and cut[1] is None:
        return None
    ref_rays, view_rays = with_equal_totals([rays_of(reference_image, reference), rays_of(image, view)], centre)
    added = np.asarray(added, float)
    before = consistency(ref_rays, view_rays, blur_mm, centre, truncated=cut)
    after = consistency(ref_rays, view_rays.moved(added[:3], added[3:], centre), blur_mm, centre,
                        truncated=(cut[0], _moved(cut[1], added, centre)))
    return before["cost"] / max(after["cost"], 1e-12), min(len(before["kappa"]), len(after["kappa"]))


@dataclass
class MotionEstimate:
    """The object motion of a view found against a reference view (the form ``CArmView`` carries)."""

    rotation_deg: np.ndarray  # the view's whole object motion, as ``CArmView`` carries it (about the origin)
    translation_mm: np.ndarray
    centre_mm: np.ndarray
    added: np.ndarray  # (6,) what was found on top of the motion the view carried: rotation (deg) about
    # ``centre_mm``, then translation (mm), as ``calibration.moved`` takes them
    parameters: Dict[str, float]  # the same as each searched motion's size (deg or mm, ``motion_axes``)
    at_limit: List[str]  # the searched motions that ended at the end of their range
    cost_before: float
    cost_after: float
    seconds: float
    # per view of the pair (or of the views, jointly), its vessel pixels next to its unseen part (``truncated_rays``)
    truncated_pixels: Tuple[int, ...] = ()
    # the fewest epipolar planes compared at any blur (truncated ones left out); below ``MIN_UNTRUNCATED_PLANES``
    # nothing was searched and the motion is none
    planes_compared: int = 0
    # found over every pair of views at once (all six motions); False: matched to the reference view alone
    jointly: bool = False
    # why a view of three or more was matched to one other view ("" where it was not, or there are two views)
    joint_fallback: str = ""
    # the view (0-based) it was matched to where not found jointly: the reference, or an already corrected view
    reference_view: int = 0
    # where the joint search started, when not from each view matched to the reference ("" otherwise)
    joint_start: str = ""

    @property
    def measured(self) -> bool:
        return self.planes_compared >= MIN_UNTRUNCATED_PLANES

    def report(self) -> Dict[str, Any]:
        return {"parameters": {k: round(v, 4) for k, v in self.parameters.items()},
                "rotation_deg": [round(float(v), 4) for v in self.rotation_deg],
                "translation_mm": [round(float(v), 4) for v in self.translation_mm],
                "rotation_centre_mm": [round(float(v), 3) for v in self.centre_mm],
                "consistency_before": round(self.cost_before, 5), "consistency_after": round(self.cost_after, 5),
                "truncated_pixels": list(self.truncated_pixels), "planes_compared": self.planes_compared,
                "seconds": round(self.seconds, 2)}


#: the motions of a view's object two views observe, strongest first (module docstring, "Observable motion")
OBSERVED_MOTIONS = ("shift_across", "rotation_about_baseline", "rotation_about_depth")
#: the pair two views barely tell apart (a turn about the epipolar planes' normal, a shift in depth)
WEAK_MOTIONS = ("rotation_about_normal", "shift_in_depth")


def motion_axes(reference: CArmView, view: CArmView, centre_mm: np.ndarray) -> Dict[str, np.ndarray]:
    """Each searchable motion as a (rotation (3), translation (3)) unit vector pair, in LPS."""
    n0, m = epipolar_frame(reference.source_position, view.source_position, centre_mm)
    baseline = np.cross(n0, m)
    zero = np.zeros(3)
    return {"shift_across": np.concatenate([zero, n0]), "rotation_about_baseline": np.concatenate([baseline, zero]),
            "rotation_about_depth": np.concatenate([m, zero]), "rotation_about_normal": np.concatenate([n0, zero]),
            "shift_in_depth": np.concatenate([zero, m]), "shift_along_baseline": np.concatenate([zero, baseline])}


#: every rigid motion of a view's object, named by the axes of its pair with the reference view
ALL_MOTIONS = OBSERVED_MOTIONS + WEAK_MOTIONS + ("shift_along_baseline",)


def estimate_motion(reference: CArmView, reference_image: np.ndarray, view: CArmView, image: np.ndarray,
                    centre_mm: Sequence[float], max_rotation_deg: float = 4.0, max_translation_mm: float = 6.0,
                    blurs_mm: Sequence[float] = SEARCH_BLURS_MM,
                    searched: Sequence[str] = OBSERVED_MOTIONS,
                    unseen: Sequence[Optional[np.ndarray]] = (None, None)) -> MotionEstimate:
    """The object motion of ``view`` (on top of what it carries) that makes its line integrals consistent
    with ``reference``'s: the ``searched`` motions (module docstring), coarse to fine over ``blurs_mm``.
    ``unseen``: per image, None or a bool image, True where that view cannot show a vessel; the planes
    through vessels that run into it are not compared ("Truncation"). Too few planes left: no search, no motion."""
    from .calibration import moved

    t0 = time.perf_counter()
    centre = np.asarray(centre_mm, float)
    ref_rays, view_rays = with_equal_totals([rays_of(reference_image, reference), rays_of(image, view)], centre)
    cut = (truncated_rays(reference_image, unseen[0], reference), truncated_rays(image, unseen[1], view))
    cut_pixels = tuple(0 if c is None else len(c.weights) for c in cut)
    axes = motion_axes(reference, view, centre)
    unknown = [name for name in searched if name not in axes]
    if unknown or not searched:
        raise EpipolarError(f"unknown motion(s) {unknown or searched}; choose among {', '.join(axes)}")
    basis = np.stack([axes[name] for name in searched])
    limits = _limits(searched, axes, max_rotation_deg, max_translation_mm)
    planes = min(len(plane_sampling(ref_rays, view_rays, blur, centre, truncated=cut)) for blur in blurs_mm)
    if planes < MIN_UNTRUNCATED_PLANES:
        return MotionEstimate(np.asarray(view.object_rotation_deg, float), np.asarray(view.object_translation_mm, float),
                              centre, np.zeros(6), {name: 0.0 for name in searched}, [], float("nan"), float("nan"),
                              time.perf_counter() - t0, cut_pixels, planes)

    def cost(params: np.ndarray, blur: float) -> float:
        if np.any(np.abs(params) > limits):
            return 10.0  # outside the range searched: worse than any pair of images (costs ≤ 4)
        motion = params @ basis
        return consistency(ref_rays, view_rays.moved(motion[:3], motion[3:], centre), blur, centre,
                           truncated=(cut[0], _moved(cut[1], motion, centre)))["cost"]

    params = np.zeros(len(searched))
    before = cost(params, blurs_mm[-1])
    for blur in blurs_mm:
        params = minimize(cost, params, args=(blur,), method="Powell",
                          options={"xtol": 0.01, "ftol": 1e-6, "maxfev": 2000}).x
    motion = params @ basis
    final = moved(view, motion[:3], motion[3:], centre)
    at_limit = [name for name, value, limit in zip(searched, params, limits) if abs(value) >= 0.99 * limit]
    return MotionEstimate(np.asarray(final.object_rotation_deg), np.asarray(final.object_translation_mm), centre, motion,
                          {name: float(v) for name, v in zip(searched, params)}, at_limit,
                          before, cost(params, blurs_mm[-1]), time.perf_counter() - t0, cut_pixels, planes)


def _limits(names: Sequence[str], axes: Dict[str, np.ndarray], max_rotation_deg: float, max_translation_mm: float) -> np.ndarray:
    return np.array([max_rotation_deg if np.any(axes[name][:3]) else max_translation_mm for name in names])


def estimate_motions(views: Sequence[CArmView], images: Sequence[np.ndarray], centre_mm: Sequence[float],
                     max_rotation_deg: float = 4.0, max_translation_mm: float = 6.0,
                     blurs_mm: Sequence[float] = SEARCH_BLURS_MM, joint_blurs_mm: Sequence[float] = JOINT_BLURS_MM,
                     prior_weight: float = MOTION_PRIOR_WEIGHT, progress=None,
                     unseen: Optional[Sequence[Optional[np.ndarray]]] = None,
                     min_gain: float = 1.0) -> List[MotionEstimate]:
    """The object motion of every view after the first (the reference), one estimate each.

    Each view is first matched to view 1 alone (``estimate_motion``: the three motions that pair
    observes). With three views or more, every pair of views is then made consistent at once over all
    six motions of each view: the shift along view 1–k's baseline, invisible to that pair, moves view
    k across the planes of its pair with a third view. ``progress(k, total, message)`` is told each step.
    ``unseen``: per view None or its bool image of what it cannot show (``estimate_motion``).

    Where the joint search cannot be used — a pair has too few planes left, or it ends at the end of its range for
    any view (its motions are found together, so one motion forced to the limit leaves the others suspect too) —
    the views are matched one pair at a time instead (``joint_fallback`` says why): starting from view 1, the view
    not yet placed whose match to a placed view (its pose as corrected) agrees best after the correction is placed
    next, against that view (``reference_view``); a match that ends at its range or has too few planes is not
    used, and a view with none left is matched to view 1. A placed view whose correction makes its pair less than
    ``min_gain`` times more consistent stays as given for the views placed after it, as the caller leaves it. Where
    the joint search ended at its range, it is run once more from the poses so matched (a start far from the views'
    agreement can end in a wrong minimum at the limit); only if that ends at the range too are the matches in turn
    kept (``joint_start`` says when the joint result came from that second start)."""
    from .calibration import moved

    t0 = time.perf_counter()
    views, centre = list(views), np.asarray(centre_mm, float)
    if len(views) != len(images) or len(views) < 2:
        raise EpipolarError(f"need one image per view and two views at least (got {len(views)} views, {len(images)} images)")
    unseen = list(unseen) if unseen is not None else [None] * len(views)
    if len(unseen) != len(views):
        raise EpipolarError(f"{len(unseen)} unseen-pixel images for {len(views)} views")
    total = len(views) - 1 + (len(views) > 2)
    pairwise = []
    for k in range(1, len(views)):
        if progress:
            progress(k, total, f"view {k + 1}: consistency of its frame with view 1's")
        pairwise.append(estimate_motion(views[0], images[0], views[k], images[k], centre, max_rotation_deg,
                                        max_translation_mm, blurs_mm, unseen=(unseen[0], unseen[k])))
    if len(views) == 2:
        return pairwise
    if progress:
        progress(total, total, "every pair of views at once")
    rays = with_equal_totals([rays_of(image, view) for image, view in zip(images, views)], centre)
    cut = [truncated_rays(image, u, view) for image, u, view in zip(images, unseen, views)]
    axes = [motion_axes(views[0], view, centre) for view in views[1:]]
    bases = [np.stack([a[name] for name in ALL_MOTIONS]) for a in axes]  # orthonormal: rows are unit, orthogonal
    limits = np.concatenate([_limits(ALL_MOTIONS, a, max_rotation_deg, max_translation_mm) for a in axes])
    pairs = [(i, j) for i in range(len(views)) for j in range(i + 1, len(views))]
    size = len(ALL_MOTIONS)

    def motions(params: np.ndarray) -> List[np.ndarray]:
        return [np.zeros(6)] + [params[size * k:size * (k + 1)] @ basis for k, basis in enumerate(bases)]

    def moved_rays(params: np.ndarray) -> List[LineIntegralImage]:
        return [r.moved(m[:3], m[3:], centre) if k else r for k, (r, m) in enumerate(zip(rays, motions(params)))]

    def moved_cut(params: np.ndarray) -> List[Optional[LineIntegralImage]]:
        return [_moved(c, m, centre) if k else c for k, (c, m) in enumerate(zip(cut, motions(params)))]

    def pair_cost(params: np.ndarray, blur: float) -> float:
        current, edges = moved_rays(params), moved_cut(params)
        return sum(consistency(current[i], current[j], blur, centre, truncated=(edges[i], edges[j]))["cost"]
                   for i, j in pairs)

    def residuals(params: np.ndarray, blur: float, planes: List[np.ndarray], scales: List[float]) -> np.ndarray:
        current = moved_rays(params)
        parts = []
        for (i, j), kappa, scale in zip(pairs, planes, scales):
            found = consistency(current[i], current[j], blur, centre, kappa=kappa)
            parts.append((found["rho_a"] - found["rho_b"]) / math.sqrt(scale))
        return np.concatenate(parts + [math.sqrt(prior_weight) * params])

    def starting_point(estimates: Sequence[MotionEstimate]) -> np.ndarray:
        return np.clip(np.concatenate([basis @ e.added for basis, e in zip(bases, estimates)]), -0.98 * limits, 0.98 * limits)

    fewest = min(len(plane_sampling(rays[i], rays[j], blur, centre, truncated=(cut[i], cut[j])))
                 for i, j in pairs for blur in joint_blurs_mm)
    chain_options = dict(max_rotation_deg=max_rotation_deg, max_translation_mm=max_translation_mm, blurs_mm=blurs_mm,
                         unseen=unseen, min_gain=min_gain)
    if fewest < MIN_UNTRUNCATED_PLANES:
        return _matched_in_turn(views, images, centre, pairwise, f"a pair of views has only {fewest} epipolar planes no "
                                f"collimator or image edge cuts ({MIN_UNTRUNCATED_PLANES} needed)", **chain_options)
    before = pair_cost(np.zeros(len(limits)), joint_blurs_mm[-1])

    def joint_search(params: np.ndarray) -> List[MotionEstimate]:
        for blur in joint_blurs_mm:
            # Gauss–Newton on the plane derivatives' differences, the planes and scales held for the stage
            current, edges = moved_rays(params), moved_cut(params)
            planes = [plane_sampling(current[i], current[j], blur, centre, truncated=(edges[i], edges[j])) for i, j in pairs]
            scales = [consistency(current[i], current[j], blur, centre, kappa=k)["scale"] for (i, j), k in zip(pairs, planes)]
            params = least_squares(residuals, params, args=(blur, planes, scales), bounds=(-limits, limits),
                                   diff_step=JOINT_DIFF_STEP, x_scale=1.0, max_nfev=JOINT_MAX_EVALUATIONS).x
        after = pair_cost(params, joint_blurs_mm[-1])
        seconds = time.perf_counter() - t0
        out = []
        for k, (motion, view) in enumerate(zip(motions(params)[1:], views[1:])):
            own = params[size * k:size * (k + 1)]
            final = moved(view, motion[:3], motion[3:], centre)
            at_limit = [name for name, value, limit in zip(ALL_MOTIONS, own, limits[size * k:size * (k + 1)])
                        if abs(value) >= 0.99 * limit]
            out.append(MotionEstimate(np.asarray(final.object_rotation_deg), np.asarray(final.object_translation_mm),
                                      centre, motion, {name: float(v) for name, v in zip(ALL_MOTIONS, own)}, at_limit,
                                      before, after, seconds, tuple(0 if c is None else len(c.weights) for c in cut),
                                      fewest, jointly=True))
        return out

    def limited(estimates: Sequence[MotionEstimate]) -> str:
        return "; ".join(f"view {k + 2}: {', '.join(n.replace('_', ' ') for n in e.at_limit)}"
                         for k, e in enumerate(estimates) if e.at_limit)

    out = joint_search(starting_point(pairwise))
    if not limited(out):
        return out
    why = f"the search over every pair of views at once reached the end of its range ({limited(out)})"
    chained = _matched_in_turn(views, images, centre, pairwise, why, **chain_options)
    # the joint search again, from the poses the views matched in turn found: a start inside the range may end there
    again = joint_search(starting_point(chained))
    if not limited(again):
        return [replace(e, joint_start="the views matched in turn (the search from each view matched to view 1 "
                                       f"reached the end of its range: {limited(out)})") for e in again]
    return chained


def _matched_in_turn(views: Sequence[CArmView], images: Sequence[np.ndarray], centre: np.ndarray,
                     to_first: Sequence[MotionEstimate], why: str, max_rotation_deg: float, max_translation_mm: float,
                     blurs_mm: Sequence[float], unseen: Sequence[Optional[np.ndarray]], min_gain: float) -> List[MotionEstimate]:
    """Each view after the first matched to one placed view, the best-agreeing match first (``estimate_motions``).
    ``to_first``: each view's match to view 1, already found."""
    from .calibration import moved

    current = list(views)  # the placed views as corrected
    matches: Dict[Tuple[int, int], MotionEstimate] = {(0, k): e for k, e in enumerate(to_first, start=1)}
    placed, pending = [0], list(range(1, len(views)))
    chosen: Dict[int, MotionEstimate] = {}
    while pending:
        usable = []
        for k in pending:
            for j in placed:
                if (j, k) not in matches:
                    matches[(j, k)] = estimate_motion(current[j], images[j], views[k], images[k], centre, max_rotation_deg,
                                                      max_translation_mm, blurs_mm, unseen=(unseen[j], unseen[k]))
                match = matches[(j, k)]
                if match.measured and not match.at_limit:
                    usable.append((match.cost_after, k, j))
        if not usable:
            chosen.update({k: matches[(0, k)] for k in pending})
            break
        _, k, j = min(usable)
        match = chosen[k] = replace(matches[(j, k)], reference_view=j)
        if match.cost_before >= min_gain * match.cost_after:
            current[k] = moved(views[k], match.added[:3], match.added[3:], centre)
        placed.append(k)
        pending.remove(k)
    return [replace(chosen[k], joint_fallback=why) for k in range(1, len(views))]
