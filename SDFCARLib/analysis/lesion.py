"""Lesions on a diameter profile: reference diameter, MLD, % stenosis and lesion extent.

Reference diameter (``reference_fit``)
    Healthy vessels taper slowly, lesions only narrow. The reference is a straight line
    D_ref(s) = a + b·s fitted to the profile D(s) robustly and one-sidedly: a Theil–Sen start
    (breakdown ~29 %), then least squares on the points not far below the line, repeated until
    the kept set no longer changes. "Far below" is more than max(k·σ, ``min_drop`` · D_ref) under
    the line, σ the normalised median absolute deviation of the kept residuals; points far above
    (side-branch mouths) are dropped likewise. Branches shorter than ``min_fit_length_mm`` get a
    constant reference (a slope is not defined by so few healthy points).

Lesion (``find_lesions``)
    The profile is first smoothed along s with a Gaussian of ``smoothing_mm`` (0.5 mm): the
    sections of a voxel volume scatter by ± a fifth of a voxel, and the minimum of a noisy
    profile is biased low (on a 1 mm throat at 0.25 mm voxels by ~0.1 mm without it).
    narrowing n(s) = 1 − D(s) / D_ref(s). The worst point is the minimal lumen diameter (MLD);
    %DS = 100 (1 − MLD / D_ref(s_MLD)), %AS = 100 (1 − A_min / A_ref) with A_ref = π D_ref² / 4
    (A_min the measured area when given, else π MLD² / 4).
    Extent: on each side of the MLD, the flank is located where n crosses 25 % and 75 % of its
    maximum, and the lesion edge is where the line through those two points reaches n = 0 (the
    tangent to the flank meets the reference). Tail noise does not move that edge, unlike a fixed
    threshold on n, and for a cosine ramp of length R it lies R/6 inside the true edge.
    After a lesion is found its extent is masked and the next worst point is examined, up to
    ``max_lesions`` with %DS >= ``min_stenosis_pct``.

The same lesion on another profile (``same_lesion_on``, ``is_same_lesion``)
    The 3D sections find a lesion; the frames' diameters of the same centreline are searched the
    same way, and the worst of their lesions that is the same lesion is that lesion as the frames
    measure it. Same: its MLD lies in the 3D lesion's extent widened by half its length each side,
    or the 3D lesion's MLD lies in its extent — a rough reconstruction reads a long lesion as a
    short bump near one end of it (RESULTS §38a).

A lesion at a given extent (``lesion_within``)
    A profile's narrowing over an extent found on another profile: the MLD is the smallest
    (smoothed) diameter inside it, the reference the profile's own line there.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Dict, List, Optional

import numpy as np
from scipy import ndimage, stats


@dataclass
class ReferenceFit:
    intercept_mm: float
    slope_mm_per_mm: float
    kept: np.ndarray  # bool, points used in the final fit

    def __call__(self, s_mm: np.ndarray) -> np.ndarray:
        return self.intercept_mm + self.slope_mm_per_mm * np.asarray(s_mm, float)


@dataclass
class Lesion:
    mld_mm: float
    mld_position_mm: float
    reference_diameter_mm: float
    diameter_stenosis_pct: float
    area_stenosis_pct: float
    start_mm: float
    end_mm: float
    length_mm: float

    def to_dict(self) -> Dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def robust_sigma(residuals: np.ndarray) -> float:
    """The standard deviation a normal scatter of ``residuals`` would have: 1.4826 × median absolute deviation."""
    return float(1.4826 * np.median(np.abs(residuals - np.median(residuals))))


def reference_fit(s_mm: np.ndarray, diameter_mm: np.ndarray, usable: Optional[np.ndarray] = None, k: float = 2.5,
                  min_drop: float = 0.05, min_fit_length_mm: float = 10.0, max_iterations: int = 20) -> ReferenceFit:
    """One-sided robust straight-line reference of a diameter profile (module docstring)."""
    s = np.asarray(s_mm, float)
    d = np.asarray(diameter_mm, float)
    ok = np.isfinite(d) & (d > 0)
    if usable is not None:
        ok &= np.asarray(usable, bool)
    if ok.sum() < 3:
        raise ValueError("fewer than 3 usable diameters on this branch: it is too short, or every section "
                         "lies at a junction or an end")
    span = float(s[ok].max() - s[ok].min())
    constant = span < min_fit_length_mm
    if constant:
        a, b = float(np.median(d[ok])), 0.0
    else:
        b, a = stats.theilslopes(d[ok], s[ok])[:2]
    kept = ok.copy()
    for _ in range(max_iterations):
        fit = a + b * s
        res = d - fit
        sigma = max(robust_sigma(res[kept]), 1e-3)
        tol = np.maximum(k * sigma, min_drop * fit)
        new = ok & (res > -tol) & (res < 2 * tol)
        if new.sum() < 3:
            break
        if constant:
            a, b = float(np.mean(d[new])), 0.0
        else:
            b, a = np.polyfit(s[new], d[new], 1)
        if np.array_equal(new, kept):
            break
        kept = new
    return ReferenceFit(float(a), float(b), kept)


def relative_scatter(s_mm: np.ndarray, diameter_mm: np.ndarray, reference: ReferenceFit) -> float:
    """The robust scatter of a profile about its reference, as a share of the reference (on the points the
    fit kept): how far a healthy stretch of this profile strays, against which a narrowing is read."""
    ref = reference(np.asarray(s_mm, float))
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = np.asarray(diameter_mm, float) / ref - 1.0
    use = reference.kept & np.isfinite(relative)
    return robust_sigma(relative[use]) if use.any() else float("nan")


def _crossing(s: np.ndarray, n: np.ndarray, start: int, step: int, level: float) -> Optional[float]:
    """Arc length where n first falls below ``level`` walking from index ``start`` by ``step``."""
    i = start
    while 0 <= i + step < len(n):
        if n[i + step] < level:
            f = (n[i] - level) / max(n[i] - n[i + step], 1e-12)
            return float(s[i] + f * (s[i + step] - s[i]))
        i += step
    return None


def _edge(s: np.ndarray, n: np.ndarray, i_min: int, step: int) -> float:
    peak = n[i_min]
    s25 = _crossing(s, n, i_min, step, 0.25 * peak)
    s75 = _crossing(s, n, i_min, step, 0.75 * peak)
    if s25 is None:  # the lesion runs to the end of the measured profile
        return float(s[0] if step < 0 else s[-1])
    if s75 is None or s75 == s25:
        return s25
    edge = s25 + (s25 - s75) / 2.0  # the flank line through (s75, 0.75) and (s25, 0.25) reaches 0 here
    return float(np.clip(edge, s[0], s[-1]))


def smooth_profile(s_mm: np.ndarray, values: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Gaussian smoothing of a profile along its arc length; NaN gaps are bridged linearly first."""
    s = np.asarray(s_mm, float)
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    if sigma_mm <= 0 or ok.sum() < 2:
        return v.copy()
    filled = np.interp(s, s[ok], v[ok])
    step = float(np.median(np.diff(s))) if len(s) > 1 else 1.0
    out = ndimage.gaussian_filter1d(filled, sigma_mm / max(step, 1e-6), mode="nearest")
    return np.where(ok, out, np.nan)


def find_lesions(s_mm: np.ndarray, diameter_mm: np.ndarray, reference: ReferenceFit,
                 searchable: Optional[np.ndarray] = None, area_mm2: Optional[np.ndarray] = None,
                 min_stenosis_pct: float = 20.0, max_lesions: int = 3, smoothing_mm: float = 0.5) -> List[Lesion]:
    """The lesions of a profile, worst first (module docstring)."""
    s = np.asarray(s_mm, float)
    d = smooth_profile(s, diameter_mm, smoothing_mm)
    if area_mm2 is not None:
        area_mm2 = smooth_profile(s, area_mm2, smoothing_mm)
    ref = reference(s)
    measured = np.isfinite(d)
    # A section that could not be measured inside a lesion must not end it there: the flanks are
    # walked on the profile bridged across such gaps; the MLD is taken at measured sections only.
    bridged = np.interp(s, s[measured], d[measured]) if measured.sum() >= 2 else d
    with np.errstate(invalid="ignore", divide="ignore"):
        walk = np.where(np.isfinite(bridged) & (ref > 0), 1.0 - bridged / ref, 0.0)
    n = np.where(measured, walk, 0.0)
    open_ = np.ones(len(s), bool) if searchable is None else np.asarray(searchable, bool).copy()
    lesions: List[Lesion] = []
    for _ in range(max_lesions):
        candidates = np.where(open_, n, -np.inf)
        i = int(np.argmax(candidates))
        if not np.isfinite(candidates[i]) or 100 * n[i] < min_stenosis_pct:
            break
        # Flanks are read on the whole profile (a lesion may run into a junction zone).
        start, end = _edge(s, walk, i, -1), _edge(s, walk, i, +1)
        lesions.append(_lesion_at(s, d, ref, area_mm2, i, start, end))
        open_ &= (s < start) | (s > end)
    return lesions


def _lesion_at(s: np.ndarray, d: np.ndarray, ref: np.ndarray, area_mm2: Optional[np.ndarray], i: int,
               start_mm: float, end_mm: float) -> Lesion:
    """The lesion whose MLD is section ``i`` of the (smoothed) profile ``d`` (module docstring: %DS, %AS)."""
    mld, r = float(d[i]), float(ref[i])
    a_ref = np.pi * r * r / 4
    a_min = float(area_mm2[i]) if area_mm2 is not None else np.pi * mld * mld / 4
    return Lesion(mld, float(s[i]), r, 100 * (1 - mld / r), 100 * (1 - a_min / a_ref), float(start_mm), float(end_mm),
                  float(end_mm - start_mm))


def minimal_lumen(s_mm: np.ndarray, diameter_mm: np.ndarray, searchable: Optional[np.ndarray] = None) -> Dict[str, float]:
    """The smallest diameter and where it is, whether or not it makes a lesion."""
    d = np.where(np.isfinite(diameter_mm), diameter_mm, np.inf)
    if searchable is not None:
        d = np.where(searchable, d, np.inf)
    i = int(np.argmin(d))
    return {"mld_mm": float(d[i]) if np.isfinite(d[i]) else float("nan"), "position_mm": float(np.asarray(s_mm)[i])}


def same_lesion_on(s_mm: np.ndarray, diameter_mm: np.ndarray, usable: np.ndarray, lesion: Lesion,
                   min_stenosis_pct: float = 20.0) -> Optional[Lesion]:
    """The lesion of another diameter profile of the same centreline (e.g. the frames') that is ``lesion``:
    its own reference and lesions (as above), the worst whose MLD lies within ``lesion``'s extent widened by
    half its length on each side; None if there is none or the profile has too few usable points."""
    try:
        reference = reference_fit(s_mm, diameter_mm, usable)
        found = find_lesions(s_mm, diameter_mm, reference, usable, min_stenosis_pct=min_stenosis_pct)
    except ValueError:
        return None
    near = [x for x in found if is_same_lesion(lesion, x)]
    return max(near, key=lambda x: x.diameter_stenosis_pct) if near else None


def is_same_lesion(lesion: Lesion, other: Lesion) -> bool:
    """Whether ``other`` (found on another profile of the same centreline) is ``lesion`` (module docstring)."""
    pad = 0.5 * lesion.length_mm
    return (lesion.start_mm - pad <= other.mld_position_mm <= lesion.end_mm + pad
            or other.start_mm <= lesion.mld_position_mm <= other.end_mm)


def lesion_within(s_mm: np.ndarray, diameter_mm: np.ndarray, reference: ReferenceFit, start_mm: float, end_mm: float,
                  area_mm2: Optional[np.ndarray] = None, smoothing_mm: float = 0.5) -> Optional[Lesion]:
    """The narrowing of a profile between ``start_mm`` and ``end_mm`` (module docstring); None where no
    section inside was measured."""
    s = np.asarray(s_mm, float)
    d = smooth_profile(s, diameter_mm, smoothing_mm)
    inside = (s >= start_mm) & (s <= end_mm) & np.isfinite(d)
    if not inside.any():
        return None
    i = int(np.flatnonzero(inside)[np.argmin(d[inside])])
    area = smooth_profile(s, area_mm2, smoothing_mm) if area_mm2 is not None else None
    return _lesion_at(s, d, reference(s), area, i, start_mm, end_mm)
