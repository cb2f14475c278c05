"""Shape priors that binary masks need and line-integral targets do not."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def chord_length_estimate(mask: np.ndarray, pixel_mm: float) -> np.ndarray:
    """Path length (mm) a ray would cross through a round vessel, estimated from a 2D mask.

    For a vessel of radius r seen as a band, a ray at distance x from the centreline crosses
    2·sqrt(r² − x²). r is the inside distance at the nearest skeleton pixel, r − x the pixel's
    own inside distance. 0 outside the mask.
    """
    from skimage.morphology import skeletonize

    mask = np.asarray(mask, bool)
    inside = ndimage.distance_transform_edt(mask) - 0.5  # pixel centre to the mask border
    skeleton = skeletonize(mask)
    if not skeleton.any():
        return np.zeros(mask.shape, np.float32)
    _, (ri, ci) = ndimage.distance_transform_edt(~skeleton, return_indices=True)
    radius = np.maximum(inside[ri, ci], inside)
    chord = 2.0 * np.sqrt(np.clip(radius**2 - (radius - inside) ** 2, 0.0, None))
    return np.where(mask, chord * pixel_mm, 0.0).astype(np.float32)
