"""Lumen area from a frame by densitometry: the absorbance integrated across the vessel's projection.

Why
    Edges give one width per view. An eccentric or slit-like throat seen face-on keeps its full width
    in that view, so the ellipse of the two widths reads the lesion too mild (bench/RESULTS.md §14,
    §20b). The iodine in a cross-section is seen whole from any side: by Beer–Lambert the absorbance
    integrated across the projection is proportional to the lumen's area, whatever its shape
    (videodensitometry).

Model
    For a point of the centreline whose axis is tilted out of the detector plane by φ
    (cos φ = 1 − foreshortening) and projected with magnification m,

        ∫ (a(x) − background(x)) dx = μ · m · A / cos φ          (x in detector mm)

    with μ the absorbance per mm of iodinated lumen and A the lumen area (mm²) at the vessel. The
    background is the straight line fitted to the window's outer samples, beyond the guessed half
    width + 3σ of blur (the window of ``frame_widths``). ``densities`` returns μ·A per point; μ is not
    known in absolute terms (iodine concentration, kV, scatter), so ``attenuation_per_mm`` calibrates it
    per view as the median of μ·A / (π w²/4) over the healthy points where the edge fit measured the
    width w: a healthy vessel is round. ``density_diameter`` is then the equivalent diameter of the
    views' median area: with two views their mean; with three or more, a view whose area disagrees
    (crowded by a vessel no rule caught, its attenuation misread) is outvoted (bench/RESULTS.md §71f).

Limits
    A branch crossing or running beside the window adds its iodine to the area or to the background;
    the edges see that too (a spike in the width), but the area cannot tell which side it came from.
    ``density_diameter`` therefore takes, per point, the views the caller marks ``usable`` (the
    analysis: those no other branch of the tree crowds, ``pipeline.py``).
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from ..geometry import CArmView
from ..lumen_profile import DEFAULT_PSF_SIGMA_MM
from .diameter import views_to_use
from .frame_widths import frame_profiles

# Fewest healthy points whose ratio the per-view attenuation takes the median of.
MIN_CALIBRATION_POINTS = 5


def integrated_absorbance(x_mm: np.ndarray, profile: np.ndarray, inner_half_width_mm: float) -> Optional[float]:
    """∫ (profile − background) dx over the window, the background being the straight line fitted to
    the samples with |x| > ``inner_half_width_mm``; None when either side has fewer than 3 such samples."""
    x = np.asarray(x_mm, float)
    a = np.asarray(profile, float)
    outer = np.abs(x) > inner_half_width_mm
    if np.count_nonzero(outer & (x < 0)) < 3 or np.count_nonzero(outer & (x > 0)) < 3:
        return None
    slope, intercept = np.polyfit(x[outer], a[outer], 1)
    above = a - (intercept + slope * x)
    return float(np.sum(0.5 * (above[1:] + above[:-1]) * np.diff(x)))  # the trapezoid rule


def densities(points_mm: np.ndarray, tangents: np.ndarray, frame: np.ndarray, view: CArmView,
              guess_widths_mm: np.ndarray, psf_sigma_mm: float = DEFAULT_PSF_SIGMA_MM,
              max_foreshortening: float = 0.7) -> np.ndarray:
    """μ·A (absorbance · mm²) per centreline point in one view's frame; NaN where no profile is taken
    (see ``frame_widths.frame_widths``)."""
    out = np.full(len(np.asarray(points_mm)), np.nan)
    for i, x, profile, mag, guess, foreshortening in frame_profiles(points_mm, tangents, frame, view, guess_widths_mm,
                                                                     psf_sigma_mm, max_foreshortening):
        integral = integrated_absorbance(x, profile, guess / 2 + 3.0 * psf_sigma_mm)
        if integral is not None:
            out[i] = integral * (1.0 - foreshortening) / mag
    return out


def attenuation_per_mm(view_densities: np.ndarray, widths_mm: np.ndarray, healthy: np.ndarray) -> Optional[float]:
    """μ of one view: the median of μ·A / (π w²/4) over healthy points with a positive density and an edge
    width; None with fewer than ``MIN_CALIBRATION_POINTS`` of them."""
    d = np.asarray(view_densities, float)
    w = np.asarray(widths_mm, float)
    use = np.asarray(healthy, bool) & np.isfinite(d) & (d > 0) & np.isfinite(w) & (w > 0)
    if np.count_nonzero(use) < MIN_CALIBRATION_POINTS:
        return None
    return float(np.median(d[use] / (np.pi * w[use] ** 2 / 4.0)))


def _view_areas(view_densities: np.ndarray, attenuations: Sequence[Optional[float]]) -> np.ndarray:
    d = np.asarray(view_densities, float)
    areas = np.full(d.shape, np.nan)
    for n, mu in enumerate(attenuations):
        if mu is not None and mu > 0:
            areas[n] = np.where(d[n] > 0, d[n] / mu, np.nan)
    return areas


def density_views(view_densities: np.ndarray, attenuations: Sequence[Optional[float]],
                  usable: Optional[np.ndarray] = None) -> np.ndarray:
    """(views, N) bool: the views whose areas ``density_diameter`` takes the median of at each point: those
    whose attenuation is known and whose density is positive, and among them the ``usable`` ones where there
    are any."""
    has_area = np.isfinite(_view_areas(view_densities, attenuations))
    return has_area if usable is None else views_to_use(has_area, usable)


def density_diameter(view_densities: np.ndarray, attenuations: Sequence[Optional[float]],
                     usable: Optional[np.ndarray] = None) -> np.ndarray:
    """Per point, the equivalent diameter (mm) of the median lumen area over ``density_views`` (two
    views: their mean); NaN where no view has an area. ``usable`` ((views, N) bool): the views to take
    where one of them has an area (e.g. those no other vessel crowds); all of them where none has."""
    areas = np.where(density_views(view_densities, attenuations, usable), _view_areas(view_densities, attenuations), np.nan)
    measured = np.isfinite(areas).any(axis=0)
    # the columns no view measured get a placeholder, so nanmedian does not warn about them
    median_area = np.where(measured, np.nanmedian(np.where(measured, areas, 0.0), axis=0), np.nan)
    return np.sqrt(4.0 * median_area / np.pi)
