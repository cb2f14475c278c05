"""Figures: the paper's overlay view (green overlap, red predicted only, blue missed) as MIPs."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence, Union

import numpy as np

PathLike = Union[str, Path]


def overlay_mip(pred: np.ndarray, label: np.ndarray, axis: int) -> np.ndarray:
    """RGB uint8 maximum-intensity projection along ``axis``: green both, red pred only, blue label only.

    Arrays are ``[i, j, k]`` (LPS); the image is oriented for display with the patient's head up.
    """
    p, l = np.asarray(pred, bool), np.asarray(label, bool)
    both = (p & l).any(axis=axis)
    pred_only = (p & ~l).any(axis=axis) & ~both
    label_only = (l & ~p).any(axis=axis) & ~both
    rgb = np.zeros(both.shape + (3,), dtype=np.uint8)
    rgb[pred_only] = (220, 40, 40)
    rgb[label_only] = (40, 90, 255)
    rgb[both] = (40, 200, 60)
    # Remaining in-plane axes are in (i, j, k) order; put superior (k) up when present.
    if axis != 2:
        rgb = np.flip(np.swapaxes(rgb, 0, 1), axis=0)  # rows: k from top (superior) down
    return rgb


def save_overlay(path: PathLike, pred: np.ndarray, label: np.ndarray, titles: Sequence[str] = ()) -> None:
    """Save a PNG with the overlay MIPs along the three axes side by side."""
    import imageio.v3 as iio

    panels = [overlay_mip(pred, label, axis) for axis in (1, 0, 2)]
    height = max(p.shape[0] for p in panels)
    padded = [np.pad(p, ((0, height - p.shape[0]), (0, 4), (0, 0)), constant_values=255) for p in panels]
    iio.imwrite(str(path), np.concatenate(padded, axis=1))
