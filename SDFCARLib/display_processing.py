"""Display processing: what an X-ray system does to a frame before it stores it as ``DISP``.

Why
    Most runs a user exports were processed for viewing — Pixel Intensity Relationship (0028,1040)
    ``DISP`` or a vendor's term such as GE's ``DRM`` — not the detector's linear counts the
    simulated angiograms of ``angiogram.py`` are. SDFCAR reads no path lengths off such frames
    (``evidence.unreadable_intensity``), segments its masks on them and fits vessel edges on them
    (``analysis.frame_widths``). The benchmark's realistic display protocols
    (``settings.REALISTIC_PROTOCOLS``) apply this module to the simulated counts so that what those
    steps give on processed frames is measured, not assumed.

Model (the usual chain of a cardiac C-arm's image processing, in this order)
    1. Logarithm: ``L = ln I`` (a count below 1 reads as 1).
    2. Dynamic range compression: ``L ← L − c · (G_R ∗ L − median L)``, a Gaussian low-pass of σ
       ``range_scale_mm``: large-scale brightness (lung against spine and diaphragm) is flattened by the
       fraction ``c`` = ``range_compression`` while vessel-sized detail is kept.
    3. Edge enhancement (unsharp masking): ``L ← L + k · (L − G_E ∗ L)``, σ ``edge_scale_mm``, gain
       ``k`` = ``edge_gain``: detail finer than σ is amplified by 1 + k, edges overshoot on both sides.
    4. Window: the ``window_percentiles`` of ``L`` are mapped to 0 and the full scale of ``bits``, clipped
       and rounded. Larger is more intensity, vessels dark (MONOCHROME2).

Units: lengths are mm at the detector (the frame's pixel spacing). The defaults are a moderate setting
of each step, not any vendor's: the vendors do not publish theirs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence, Tuple, Union

import numpy as np
from scipy import ndimage

from .angiogram import pixel_spacing_pair
from .evidence import DISPLAY_INTENSITY

__all__ = ["DISPLAY_INTENSITY", "DisplaySettings", "display_processed", "processed_log_intensity"]


@dataclass(frozen=True)
class DisplaySettings:
    """Parameters of ``display_processed`` (lengths in mm at the detector)."""

    range_compression: float = 0.6  # share of the large-scale log-intensity removed (0: off, < 1)
    range_scale_mm: float = 15.0  # σ of the large scale
    edge_gain: float = 1.0  # unsharp-masking gain (0: off)
    edge_scale_mm: float = 0.8  # σ of the unsharp mask's blur
    window_percentiles: Tuple[float, float] = (0.5, 99.5)
    bits: int = 8

    def check(self) -> None:
        problems = []
        if not 0.0 <= self.range_compression < 1.0:
            problems.append(f"range_compression must lie in [0, 1), got {self.range_compression}")
        if not (self.range_scale_mm > 0 and self.edge_scale_mm > 0):
            problems.append(f"range_scale_mm and edge_scale_mm must be positive, got {self.range_scale_mm}, "
                            f"{self.edge_scale_mm}")
        if not self.edge_gain >= 0:
            problems.append(f"edge_gain must not be negative, got {self.edge_gain}")
        lo, hi = self.window_percentiles
        if not 0.0 <= lo < hi <= 100.0:
            problems.append(f"window_percentiles must be two percentiles low < high in [0, 100], got {self.window_percentiles}")
        if self.bits not in (8, 10, 12, 16):
            problems.append(f"bits must be 8, 10, 12 or 16, got {self.bits}")
        if problems:
            raise ValueError("; ".join(problems))


def _sigma_px(sigma_mm: float, spacing_mm: Sequence[float]) -> Tuple[float, float]:
    return float(sigma_mm / spacing_mm[0]), float(sigma_mm / spacing_mm[1])


def processed_log_intensity(frame: Any, pixel_spacing_mm: Union[float, Sequence[float]],
                            settings: DisplaySettings = DisplaySettings()) -> np.ndarray:
    """Steps 1–3 of the module docstring: the frame's log-intensity after range compression and edge
    enhancement (float64, before the window)."""
    settings.check()
    image = np.asarray(frame, np.float64)
    if image.ndim != 2:
        raise ValueError(f"frame must be one 2-D image, got shape {image.shape}")
    spacing = pixel_spacing_pair(pixel_spacing_mm)
    log_intensity = np.log(np.maximum(image, 1.0))
    if settings.range_compression > 0:
        large = ndimage.gaussian_filter(log_intensity, _sigma_px(settings.range_scale_mm, spacing), mode="nearest")
        log_intensity = log_intensity - settings.range_compression * (large - float(np.median(large)))
    if settings.edge_gain > 0:
        blurred = ndimage.gaussian_filter(log_intensity, _sigma_px(settings.edge_scale_mm, spacing), mode="nearest")
        log_intensity = log_intensity + settings.edge_gain * (log_intensity - blurred)
    return log_intensity


def display_processed(frame: Any, pixel_spacing_mm: Union[float, Sequence[float]],
                      settings: DisplaySettings = DisplaySettings()) -> np.ndarray:
    """The frame as a system stores it for display (module docstring): uint8 for 8 bits, uint16 otherwise."""
    processed = processed_log_intensity(frame, pixel_spacing_mm, settings)
    lo, hi = np.percentile(processed, settings.window_percentiles)
    top = 2 ** settings.bits - 1
    scale = (hi - lo) if hi > lo else 1.0
    grey = np.rint(top * np.clip((processed - lo) / scale, 0.0, 1.0))
    return grey.astype(np.uint8 if settings.bits == 8 else np.uint16)
