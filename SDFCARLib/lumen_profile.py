"""The image model of a contrast-filled lumen across a projected vessel, and its fit.

Across the vessel's projection (detector mm x from its centre line) a lumen of radius r centred at c
is crossed over the chord 2·√(r² − (x − c)²); Beer–Lambert makes the absorbance −log I linear in it;
the detector blurs with a Gaussian of σ; the anatomical background is smooth, linear over the short
window:

    a(x) = b₀ + b₁·x + A · (chord(·, c, r) ⊛ G_σ)(x)

A is absorbance per detector-mm of chord. The convolution is a fixed quadrature over the Gaussian
(``_QUADRATURE`` nodes within ±4σ). Used for widths (``analysis/frame_widths.py``) and for the
iodine's attenuation (``evidence.py``).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import ndimage, optimize

_QUADRATURE = np.linspace(-4.0, 4.0, 41)  # Gaussian nodes, in units of σ
_WEIGHTS = np.exp(-0.5 * _QUADRATURE ** 2) / np.exp(-0.5 * _QUADRATURE ** 2).sum()
DEFAULT_PSF_SIGMA_MM = 0.3  # a flat-panel detector's blur, about 1.5–2 pixels (the simulated angiograms' too)
#: the 3D-QCA's default blur: DEFAULT_PSF_SIGMA_MM on frames that keep the intensity, estimated on frames processed
#: for display, whose sharpening is no detector blur (``analysis.pipeline.psf_for_frames``)
PSF_BY_FRAMES = "by frames"
SIGMA_RANGE_MM = (0.01, 2.0)  # bounds of a free blur fit
#: the largest detector blur a user may give, the free fit's bound (a clinical detector's σ is 0.2–0.5 mm; the
#: profile's kernel grows with it)
MAX_PSF_SIGMA_MM = SIGMA_RANGE_MM[1]


def absorbance(frame: np.ndarray) -> np.ndarray:
    """−log I of a frame's counts (a count below 1 reads as 1): linear in the path through iodine."""
    return -np.log(np.maximum(np.asarray(frame, np.float64), 1.0))


def mean_profile(image: np.ndarray, row: float, col: float, tangent_rc, normal_rc, x_mm: np.ndarray,
                 spacing_mm: np.ndarray) -> Optional[np.ndarray]:
    """``image`` sampled (bilinear) across a vessel at pixel (row, col): the mean of three profiles at
    offsets ``x_mm`` (detector mm) along the unit ``normal_rc``, a pixel apart along ``tangent_rc``
    (the noise averages, the lumen does not change over a pixel); None if one leaves the image."""
    pixel_mm = float(np.min(spacing_mm))
    profiles = []
    for along in (-1.0, 0.0, 1.0):
        rr = row + (x_mm * normal_rc[0] + along * pixel_mm * tangent_rc[0]) / spacing_mm[0]
        cc = col + (x_mm * normal_rc[1] + along * pixel_mm * tangent_rc[1]) / spacing_mm[1]
        if rr.min() < 0 or cc.min() < 0 or rr.max() > image.shape[0] - 1 or cc.max() > image.shape[1] - 1:
            return None
        profiles.append(ndimage.map_coordinates(image, [rr, cc], order=1))
    return np.mean(profiles, axis=0)


def chord_mm(x: np.ndarray, radius: float) -> np.ndarray:
    """Path length through a circle of ``radius`` of a ray at distance ``x`` from its centre."""
    return 2.0 * np.sqrt(np.clip(radius * radius - np.square(x), 0.0, None))


def blurred_chord(x: np.ndarray, centre: float, radius: float, sigma: float) -> np.ndarray:
    """The chord profile convolved with a Gaussian of standard deviation ``sigma`` (same units)."""
    shifted = np.asarray(x, float)[:, None] - centre - sigma * _QUADRATURE[None, :]
    return chord_mm(shifted, radius) @ _WEIGHTS


def fit_lumen(x: np.ndarray, a: np.ndarray, guess_radius_mm: float, psf_sigma_mm: Optional[float]):
    """Least-squares fit of the module's model to one profile: (centre, radius, amplitude, base, slope[,
    sigma]) and the RMS residual, with σ fixed when given and a free sixth parameter when None; None
    when the optimiser fails."""
    span = float(x.max() - x.min())
    base = float(np.median(np.r_[a[:3], a[-3:]]))
    lower = [-span / 4, 0.02, 0.0, -np.inf, -np.inf]
    upper = [span / 4, span / 2, np.inf, np.inf, np.inf]
    p0 = [0.0, float(np.clip(guess_radius_mm, lower[1] * 1.01, upper[1] * 0.99)),
          max(float(a.max() - base), 1e-6) / max(2.0 * guess_radius_mm, 1e-3), base, 0.0]
    if psf_sigma_mm is None:
        lower, upper, p0 = lower + [SIGMA_RANGE_MM[0]], upper + [SIGMA_RANGE_MM[1]], p0 + [DEFAULT_PSF_SIGMA_MM]

    def model(xx, c, r, amp, b0, slope, sigma=psf_sigma_mm):
        return b0 + slope * xx + amp * blurred_chord(xx, c, r, sigma)

    try:
        params, _ = optimize.curve_fit(model, x, a, p0=p0, bounds=(lower, upper), maxfev=3000)
    except (RuntimeError, ValueError):
        return None
    return params, float(np.sqrt(np.mean(np.square(model(x, *params) - a)))), (lower, upper)
