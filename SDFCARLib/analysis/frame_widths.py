"""Vessel width from a frame's intensity profile: a blurred circular lumen fitted across the vessel.

Why
    A mask's border is where a segmentation threshold fell on a blurred, noisy edge: for thin
    vessels it lies outside the lumen (the blur widens them), for thick ones inside (the threshold
    is relative to the vessel's own contrast). Widths read from masks segmented from angiograms
    are off by several tenths of a millimetre either way (bench/RESULTS.md). Clinical 2D-QCA
    measures on the image itself; this module fits the image model the frame was formed by.

Model
    The blurred circular lumen on a linear background of ``lumen_profile.py`` (σ = ``psf_sigma_mm``).
    Fitted by least squares (c, r, A, b₀, b₁; σ known) on three parallel profiles a pixel apart,
    averaged, reaching the guessed width + 4σ + 1 mm to each side of the projected centreline point.
    Width = 2r divided by the point's magnification (SID / source distance): mm at the vessel.

What the model is fitted to
    Linear counts (LIN, simulated frames): −log I, the absorbance. A frame whose grey level is itself
    a logarithm of the intensity — a LOG run as stored, or one processed for display (DISP, a
    vendor's term), whose processing runs on the log image — is read as it is (``grey_is_log_intensity``:
    −grey, affine in the absorbance; the model's free amplitude and background take the unknown scale
    and offset). −log of such a grey level would bend the profile and narrow every width (on
    display-processed angiograms of the QCA tubes by 0.3–0.7 mm, bench/RESULTS.md §79).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..geometry import CArmView
from ..lumen_profile import DEFAULT_PSF_SIGMA_MM, SIGMA_RANGE_MM, absorbance, blurred_chord, fit_lumen, mean_profile
from .diameter import project_centreline

# Peak absorbance a lumen must reach to count as measured: a 0.3 mm vessel at a tenth of the iodine of
# the simulated angiograms still peaks near 0.002 after the blur; noise-free flat profiles fit far below.
_MIN_CONTRAST = 1e-3
_SIGMA_WINDOW_MM = 0.5  # the blur the profiles' window is sized for while σ is being estimated


def fit_profile(x_mm: np.ndarray, absorbance: np.ndarray, psf_sigma_mm: float, guess_radius_mm: float) -> Optional[float]:
    """Lumen radius (detector mm) fitted to one absorbance profile; None if the fit fails or is implausible."""
    x = np.asarray(x_mm, float)
    a = np.asarray(absorbance, float)
    if x.size < 8 or not np.all(np.isfinite(a)):
        return None
    fitted = fit_lumen(x, a, guess_radius_mm, psf_sigma_mm)
    if fitted is None:
        return None
    (centre, radius, amplitude, _, _), noise, (lower, upper) = fitted
    peak = amplitude * float(blurred_chord(np.array([centre]), centre, radius, psf_sigma_mm)[0])
    if radius >= 0.98 * upper[1] or radius <= 1.02 * lower[1] or not peak > max(3.0 * noise, _MIN_CONTRAST):
        return None  # the lumen fills the window, or no vessel stands out of the noise: not a measurement
    return float(radius)


def profile_values(frame: np.ndarray, grey_is_log_intensity: bool = False) -> np.ndarray:
    """What the lumen model is fitted to (module docstring): −log I of linear counts, −grey of a frame whose
    grey level is a logarithm of the intensity."""
    image = np.asarray(frame, np.float64)
    return -image if grey_is_log_intensity else absorbance(image)


def frame_profiles(points_mm, tangents, frame, view, guess_widths_mm, psf_sigma_mm, max_foreshortening,
                   grey_is_log_intensity=False):
    """(index, offsets in detector mm, mean absorbance profile, magnification, guessed width in detector mm,
    foreshortening) of each measurable point: the window reaches the guessed width + 4σ + 1 mm to each
    side of the projected centreline point. ``grey_is_log_intensity``: see ``profile_values``."""
    image = np.asarray(frame, np.float64)
    if image.shape != tuple(view.detector_shape):
        raise ValueError(f"frame shape {image.shape} differs from the view's detector {tuple(view.detector_shape)}")
    absorbances = profile_values(image, grey_is_log_intensity)
    projected = project_centreline(points_mm, tangents, view)
    row, col, mag, fore = projected.row, projected.col, projected.magnification, projected.foreshortening
    (tr, tc), (nr, nc) = projected.tangent_rc, projected.normal_rc
    spacing = np.asarray(view.pixel_spacing_mm, float)
    pixel_mm = float(np.min(spacing))
    step = 0.5 * pixel_mm
    guesses = np.asarray(guess_widths_mm, float) * mag
    for i in range(len(row)):
        if not np.isfinite(guesses[i]) or guesses[i] <= 0 or fore[i] > max_foreshortening:
            continue
        half = guesses[i] + 4.0 * psf_sigma_mm + 1.0
        x = np.arange(-half, half + step / 2, step)
        profile = mean_profile(absorbances, row[i], col[i], (tr[i], tc[i]), (nr[i], nc[i]), x, spacing)
        if profile is not None:
            yield i, x, profile, float(mag[i]), guesses[i], float(fore[i])


def frame_widths(points_mm: np.ndarray, tangents: np.ndarray, frame: np.ndarray, view: CArmView,
                 guess_widths_mm: np.ndarray, psf_sigma_mm: float = DEFAULT_PSF_SIGMA_MM, max_foreshortening: float = 0.7,
                 grey_is_log_intensity: bool = False) -> np.ndarray:
    """Width (mm at each point's depth) of the vessel in one view's frame, perpendicular to its projection.

    ``frame``: the view's intensity image (vessels dark, as recorded). ``guess_widths_mm``: a first
    width per point (e.g. the mask's), which sets the fitting window; NaN guesses give NaN.
    ``psf_sigma_mm``: the detector blur (Gaussian σ at the detector; ``estimate_psf_sigma_mm``
    when unknown). NaN where the tangent is foreshortened by more than ``max_foreshortening``, the
    window leaves the frame, or the fit fails. ``grey_is_log_intensity``: the frame's grey level is a logarithm
    of the intensity (LOG as stored, processed for display; module docstring).
    """
    if not psf_sigma_mm >= 0:
        raise ValueError(f"psf_sigma_mm must not be negative, got {psf_sigma_mm}")
    widths = np.full(len(np.asarray(points_mm)), np.nan)
    for i, x, profile, mag, guess, _ in frame_profiles(points_mm, tangents, frame, view, guess_widths_mm, psf_sigma_mm,
                                                       max_foreshortening, grey_is_log_intensity):
        radius = fit_profile(x, profile, psf_sigma_mm, guess / 2)
        if radius is not None:
            widths[i] = 2.0 * radius / mag
    return widths


#: fewest profiles whose free fit the blur estimate takes the median of
MIN_BLUR_PROFILES = 10


def estimate_psf_sigma_mm(points_mm: np.ndarray, tangents: np.ndarray, frame: np.ndarray, view: CArmView,
                          guess_widths_mm: np.ndarray, max_foreshortening: float = 0.7,
                          grey_is_log_intensity: bool = False) -> Optional[float]:
    """The detector blur (Gaussian σ, mm at the detector) as the median of free fits of σ along the
    vessels (the model above with σ a sixth parameter); None with fewer than ``MIN_BLUR_PROFILES``
    successful fits. Thick vessels tell it best: their two edges are the blur's own profile."""
    sigmas = []
    # The window is sized for a blur up to _SIGMA_WINDOW_MM, as σ is not known yet.
    for _, x, a, _, guess, _ in frame_profiles(points_mm, tangents, frame, view, guess_widths_mm, _SIGMA_WINDOW_MM,
                                               max_foreshortening, grey_is_log_intensity):
        fitted = fit_lumen(x, a, guess / 2, None)
        if fitted is None:
            continue
        params = fitted[0]
        if 1.1 * SIGMA_RANGE_MM[0] < params[5] < 0.99 * SIGMA_RANGE_MM[1] and params[2] > 0:  # not at a bound
            sigmas.append(float(params[5]))
    return float(np.median(sigmas)) if len(sigmas) >= MIN_BLUR_PROFILES else None
