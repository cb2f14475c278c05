"""Simulated X-ray angiograms: the detector frame a C-arm would record of a contrast-filled tree.

``simulate_angiogram(line_integral_mm, pixel_spacing_mm, seed, settings) -> (frame, info)``
turns the iodine line-integral image of one view (``phantoms.make_case(...).line_integrals[v]``,
mm of contrast-filled vessel crossed by each ray) into detector counts, in this order:

1. Attenuation. The exponent is ``μ·L`` of the vessels (the model of
   ``phantoms.beer_lambert_counts``, same μ by default) plus an anatomical background ``B`` that
   has no unit (it is ``μ_tissue · path`` of the tissue, already multiplied out): a constant body
   attenuation, a smooth random field (Gaussian-filtered white noise of correlation length
   ``background_scale_mm``), a few soft rib-like bands and a diaphragm-like dome with a soft edge.
   Every structure of ``B`` is smoothed by at least ``background_edge_mm``, so the background is
   low-pass: it has no structure at the scale of a vessel.
2. Collimator (optional). Shutters of transmission ``collimator_transmission`` cover
   ``collimator_fraction`` of the field on each side, with cut corners (octagonal iris, as on
   many systems) and a soft edge.
3. Counts ``I = i0 · exp(−μ·L − B) · shutter``; ``i0`` is set so that the median of the exposed
   background lies at ``background_level`` of the full scale ``2**bits_stored − 1``.
4. Detector blur: a Gaussian point-spread function of ``psf_sigma_mm`` (at the detector).
5. Quantum noise, Poisson-like: Gaussian of variance proportional to the blurred counts,
   ``σ(I) = sqrt(I · I_ref) / snr`` with ``I_ref`` the median exposed background, so that the
   signal-to-noise ratio of the background (mean / standard deviation) is ``snr``.
6. Rounding and clipping to ``bits_stored`` bits (uint8 for 8 bits, uint16 otherwise).

Contrast-filled vessels come out dark, as in X-ray intensity. Everything is drawn from
``numpy.random.default_rng(seed)``: the same seed gives the same frame. ``info`` holds the
noiseless blurred counts, the background ``B``, the shutter mask, ``i0``, the reference level and
the noise standard deviation at it, and the settings as a dict.

Physical units: lengths are mm at the detector (the image's pixel spacing), μ is per mm of
contrast-filled vessel. The defaults aim at a clinical cine frame (12-bit, SNR ≈ 25 in the
background, a 2–3 pixel wide blur edge, a body attenuation that leaves the vessels a contrast of
roughly 20–50 %).
"""

from __future__ import annotations

import math

import inspect
from dataclasses import asdict, dataclass
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np
from scipy import ndimage

from .phantoms import beer_lambert_counts

__all__ = ["AngiogramSettings", "pixel_spacing_pair", "simulate_angiogram"]

# μ of phantoms.beer_lambert_counts (its default): one vessel attenuation across SDFCARLib.
_DEFAULT_MU = float(inspect.signature(beer_lambert_counts).parameters["mu_per_mm"].default)


@dataclass(frozen=True)
class AngiogramSettings:
    """Parameters of ``simulate_angiogram`` (lengths in mm at the detector)."""

    mu_per_mm: float = _DEFAULT_MU  # attenuation of contrast-filled vessel, per mm of path
    bits_stored: int = 12
    background_level: float = 0.45  # median exposed background as a fraction of full scale
    snr: float = 25.0  # background mean / noise standard deviation
    psf_sigma_mm: float = 0.3  # detector blur (Gaussian σ)
    body_attenuation: float = 1.5  # constant tissue exponent (sets how much of i0 reaches the detector)
    background_amplitude: float = 0.25  # standard deviation of the smooth random tissue field (exponent)
    background_scale_mm: float = 25.0  # correlation length of that field
    background_edge_mm: float = 4.0  # softness of rib and diaphragm edges (Gaussian σ); keeps B low-pass
    ribs: int = 3  # number of rib-like bands
    rib_width_mm: float = 14.0
    rib_attenuation: float = 0.12
    diaphragm: bool = True  # a dome of extra attenuation entering from the bottom of the image
    diaphragm_attenuation: float = 0.5
    collimator_fraction: float = 0.0  # fraction of each side under the shutter; 0: no collimator
    collimator_transmission: float = 0.06
    collimator_edge_mm: float = 0.8

    def check(self) -> None:
        if self.bits_stored not in (8, 10, 12, 14, 16):
            raise ValueError(f"bits_stored must be 8, 10, 12, 14 or 16, got {self.bits_stored}")
        if not 0.0 < self.background_level < 1.0:
            raise ValueError(f"background_level is a fraction of the full scale in (0, 1), got {self.background_level}")
        if not self.snr > 0:
            raise ValueError(f"snr must be positive (background mean / noise standard deviation), got {self.snr}")
        for name in ("mu_per_mm", "psf_sigma_mm", "background_amplitude", "background_scale_mm", "background_edge_mm",
                     "rib_width_mm", "rib_attenuation", "diaphragm_attenuation", "collimator_edge_mm"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be 0 or more, got {getattr(self, name)}")
        if not 0.0 <= self.collimator_fraction < 0.4:
            raise ValueError(f"collimator_fraction must be in [0, 0.4), got {self.collimator_fraction}")
        if not 0.0 <= self.collimator_transmission < 1.0:
            raise ValueError(f"collimator_transmission must be in [0, 1), got {self.collimator_transmission}")


def pixel_spacing_pair(pixel_spacing_mm: Union[float, Sequence[float]]) -> Tuple[float, float]:
    """A detector pixel spacing given as one value or (row, col), as (row, col) mm; ValueError unless positive."""
    spacing = np.broadcast_to(np.asarray(pixel_spacing_mm, dtype=float), (2,))
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ValueError(f"pixel_spacing_mm must be positive (row, col) mm, got {pixel_spacing_mm}")
    return float(spacing[0]), float(spacing[1])


def _background(shape: Tuple[int, int], spacing: Tuple[float, float], s: AngiogramSettings,
                rng: np.random.Generator) -> np.ndarray:
    """Tissue exponent B: constant + smooth random field + rib bands + diaphragm dome, low-pass."""
    rows, cols = shape
    y = (np.arange(rows) - rows / 2.0)[:, None] * spacing[0]
    x = (np.arange(cols) - cols / 2.0)[None, :] * spacing[1]
    sigma_px = [s.background_scale_mm / spacing[0], s.background_scale_mm / spacing[1]]
    field = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_px, mode="reflect")
    # centred before it is scaled: on a field of view a few correlation lengths wide or less the smoothed noise is
    # nearly flat, and its mean, scaled with its small spread, would overflow exp(−B) (the level is set by i0 anyway)
    field -= field.mean()
    field *= s.background_amplitude / max(float(field.std()), 1e-12)
    structures = np.zeros(shape)
    extent = max(rows * spacing[0], cols * spacing[1])
    for _ in range(int(s.ribs)):
        # A rib: a gently curved band crossing the image at a random angle and offset.
        angle = rng.uniform(-0.6, 0.6)  # radians from the horizontal, ribs run obliquely
        offset = rng.uniform(-0.45, 0.45) * extent
        bend = rng.uniform(-1.0, 1.0) / extent
        along = x * np.cos(angle) + y * np.sin(angle)
        across = -x * np.sin(angle) + y * np.cos(angle) - offset - bend * along**2
        structures += s.rib_attenuation * (np.abs(across) < s.rib_width_mm / 2.0)
    if s.diaphragm:
        centre_x = rng.uniform(-0.3, 0.3) * extent
        top = rng.uniform(0.15, 0.35) * extent  # dome apex below the centre
        radius = rng.uniform(0.6, 1.0) * extent
        dome = (x - centre_x) ** 2 + (y - top - radius) ** 2 < radius**2
        structures += s.diaphragm_attenuation * dome
    edge_px = [s.background_edge_mm / spacing[0], s.background_edge_mm / spacing[1]]
    structures = ndimage.gaussian_filter(structures, edge_px, mode="nearest")
    return s.body_attenuation + field + structures


def _shutter(shape: Tuple[int, int], spacing: Tuple[float, float], s: AngiogramSettings) -> Tuple[np.ndarray, np.ndarray]:
    """(transmission in [t, 1], bool mask of the shuttered region) for the octagonal collimator."""
    rows, cols = shape
    if s.collimator_fraction <= 0:
        return np.ones(shape), np.zeros(shape, bool)
    r = np.arange(rows)[:, None] / max(rows - 1, 1)
    c = np.arange(cols)[None, :] / max(cols - 1, 1)
    f = s.collimator_fraction
    # Distance inside the open field in units of the image side (positive inside).
    r, c = np.broadcast_arrays(r, c)
    inside = np.minimum.reduce([r - f, 1 - f - r, c - f, 1 - f - c])
    corner = 0.12  # the cut corners of an octagonal iris
    diagonal = np.minimum.reduce([(r + c) - (2 * f + corner), (1 - r + c) - (2 * f + corner),
                                  (r + 1 - c) - (2 * f + corner), (2 - r - c) - (2 * f + corner)]) / np.sqrt(2)
    covered = np.minimum(inside, diagonal) < 0
    edge_px = [max(s.collimator_edge_mm / spacing[0], 1e-3), max(s.collimator_edge_mm / spacing[1], 1e-3)]
    soft = ndimage.gaussian_filter(covered.astype(float), edge_px, mode="nearest")
    transmission = 1.0 - (1.0 - s.collimator_transmission) * soft
    return transmission, covered


def simulate_angiogram(
    line_integral_mm: Any,
    pixel_spacing_mm: Union[float, Sequence[float]],
    seed: Union[int, np.random.Generator, None] = 0,
    settings: Optional[AngiogramSettings] = None,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """Detector frame (uint8/uint16 counts, vessels dark) of a line-integral image (see module doc).

    ``pixel_spacing_mm``: detector pixel size, one value or (row, col). ``seed``: an int or a
    ``numpy.random.Generator``.
    """
    s = settings if settings is not None else AngiogramSettings()
    s.check()
    line_integral = np.asarray(line_integral_mm, dtype=np.float64)
    if line_integral.ndim != 2:
        raise ValueError(f"line_integral_mm must be one view's 2-D image, got shape {line_integral.shape}")
    if not np.all(np.isfinite(line_integral)) or line_integral.min() < 0:
        raise ValueError("line_integral_mm must be finite and non-negative (mm of vessel along each ray)")
    spacing = pixel_spacing_pair(pixel_spacing_mm)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    shape = line_integral.shape
    background = _background(shape, spacing, s, rng)
    transmission, covered = _shutter(shape, spacing, s)
    top = 2**s.bits_stored - 1
    relative = np.exp(-s.mu_per_mm * line_integral - background) * transmission
    open_background = np.exp(-background)[~covered] if (~covered).any() else np.exp(-background).ravel()
    median = float(np.median(open_background))
    if not (math.isfinite(median) and median > 0):
        raise ValueError(f"the simulated background transmits nothing (median {median:g}): the background settings "
                         "(amplitude, ribs, diaphragm attenuation) are too strong for this field of view")
    i0 = s.background_level * top / median
    psf_px = [s.psf_sigma_mm / spacing[0], s.psf_sigma_mm / spacing[1]]
    noiseless = ndimage.gaussian_filter(i0 * relative, psf_px, mode="nearest") if s.psf_sigma_mm > 0 else i0 * relative
    reference = s.background_level * top
    sigma = np.sqrt(np.maximum(noiseless, 0.0) * reference) / s.snr
    noisy = noiseless + sigma * rng.standard_normal(shape)
    frame = np.clip(np.rint(noisy), 0, top).astype(np.uint8 if s.bits_stored == 8 else np.uint16)
    info = {
        "noiseless": noiseless,
        "background": background,
        "collimator": covered,
        "i0": float(i0),
        "reference_level": float(reference),
        "noise_sigma_at_reference": float(reference / s.snr),
        "pixel_spacing_mm": list(spacing),
        "settings": asdict(s),
    }
    return frame, info
