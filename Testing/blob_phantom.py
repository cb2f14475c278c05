"""Gaussian blobs whose cone-beam line integrals and plane integrals are known in closed form (test fixture)."""

import math

import numpy as np

from SDFCARLib.geometry import CArmView

SIGMA_MM = 2.5
_RNG = np.random.default_rng(3)
CENTRES = _RNG.uniform(-20.0, 20.0, (6, 3))
AMPLITUDES = _RNG.uniform(0.5, 1.5, 6)
VIEW_1 = CArmView(30.0, 0.0, 1000.0, 757.0, (0.8, 0.8), (128, 128))
VIEW_2 = CArmView(-30.0, 0.0, 1000.0, 757.0, (0.8, 0.8), (128, 128))
VIEW_3 = CArmView(0.0, 30.0, 1000.0, 757.0, (0.8, 0.8), (128, 128))  # AP cranial: baselines off the first pair's


def blob_image(view: CArmView) -> np.ndarray:
    """Line integrals of Σ A exp(−|x − c|² / 2σ²) along each pixel's ray: A √(2π) σ exp(−d² / 2σ²), d the
    distance from c to the ray (the object seen where ``view`` saw it)."""
    rows, cols = view.pixel_grid()
    source, directions = view.rays(rows, cols)
    image = np.zeros(rows.shape)
    for centre, amplitude in zip(CENTRES, AMPLITUDES):
        offset = centre - source
        distance_sq = offset @ offset - (directions @ offset) ** 2
        image += amplitude * math.sqrt(2 * math.pi) * SIGMA_MM * np.exp(-distance_sq / (2 * SIGMA_MM ** 2))
    image[image < 1e-4] = 0.0
    return image
