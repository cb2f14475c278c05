"""Per-pixel weights of L_occ that give a thin vessel's pixels the say a thick vessel's have.

Why
    L_occ is a mean over the image's pixels. A thin vessel covers few pixels and, fitted on the frames'
    path lengths, asks for little at each (its path length is its diameter): left out, it costs a small
    fraction of what a thick vessel's border a pixel off costs. The realistic results lose a sixth of the
    truth's centreline, almost all of it on vessels one voxel thick (bench/RESULTS.md §64a, §65).

Rule
    A mask pixel weighs (r_ref / max(r, r_min))^power, r the mask's radius (px) at its nearest centreline
    pixel (``masks.centreline_radius_px``: a thick vessel's border pixel reads the thick vessel's radius),
    r_ref the median of r over the mask's pixels; the mask's weights are then scaled to a mean of 1, so that
    λ_occ keeps its meaning. Pixels outside the mask weigh 1. power 0: every pixel 1.

Measured (``thin_vessel_weight_power`` 1 on the realistic suites, §65): the thin stretches are lost about as often as
without it (LAD level, RCA lower): what loses them is the two views' ambiguity, not their weight. Off in every preset.
"""

from __future__ import annotations

import numpy as np

from .masks import centreline_radius_px

MIN_RADIUS_PX = 1.0  # a one-pixel-wide centreline reads radius 1: nothing thinner is resolved


def thin_vessel_weights(mask: np.ndarray, power: float, min_radius_px: float = MIN_RADIUS_PX) -> np.ndarray:
    """(H, W) float32 weights of the rule above for a binary ``mask``."""
    mask = np.asarray(mask, bool)
    if mask.ndim != 2:
        raise ValueError(f"the mask must be a 2D image, got shape {mask.shape}")
    if not power >= 0:
        raise ValueError(f"the thin-vessel weight's power must be 0 or more, got {power}")
    if not min_radius_px > 0:
        raise ValueError(f"min_radius_px must be positive, got {min_radius_px}")
    weights = np.ones(mask.shape, np.float32)
    if power == 0 or not mask.any():
        return weights
    _, radius, _ = centreline_radius_px(mask)
    radius = np.maximum(radius[mask], min_radius_px)
    inside = (np.median(radius) / radius) ** power
    weights[mask] = inside / inside.mean()
    return weights
