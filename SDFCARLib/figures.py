"""Figures: the paper's overlay view (green overlap, red predicted only, blue missed) as MIPs.

``save_overlay_figure`` writes the benchmark's overlay PNGs; ``save_result_figure`` is the
one-picture summary of a reconstruction shown in the README (``Resources/Screenshots/demo-result.png``).
"""

from __future__ import annotations

import math
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


def save_overlay_figure(path: PathLike, prediction: np.ndarray, label: np.ndarray, min_panel_px: int = 256) -> Path:
    """The paper's overlay (green overlap, red predicted only, blue missed) as MIPs along the three
    axes, enlarged by whole pixels so that a 128³ case is readable; a PNG at ``path``."""
    # imageio costs ~0.1 s to import, and the CLI's parser imports this module (via the benchmark).
    import imageio.v3 as iio

    path = Path(path)
    panels = [overlay_mip(prediction, label, axis) for axis in (1, 0, 2)]
    factor = max(1, int(math.ceil(min_panel_px / max(max(p.shape[:2]) for p in panels))))
    panels = [np.repeat(np.repeat(p, factor, axis=0), factor, axis=1) for p in panels]
    height = max(p.shape[0] for p in panels)
    padded = [np.pad(p, ((0, height - p.shape[0]), (0, 6), (0, 0)), constant_values=255) for p in panels]
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(str(path), np.concatenate(padded, axis=1))
    return path


def save_result_figure(path: PathLike, masks: Sequence[np.ndarray], vertices_lps: np.ndarray, faces: np.ndarray,
                       pred: np.ndarray, label: np.ndarray, titles: Sequence[str] = ()) -> None:
    """A one-picture summary of a reconstruction: the two masks, the surface in 3D (RAS view from
    the front, head up) and the overlay with the ground truth (green both, red extra, blue missed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    titles = list(titles) + [""] * 4
    fig = plt.figure(figsize=(16, 4.2), dpi=110)
    for n, mask in enumerate(masks[:2]):
        ax = fig.add_subplot(1, 4, n + 1)
        ax.imshow(np.asarray(mask, bool), cmap="gray", interpolation="nearest")
        ax.set_title(titles[n] or f"mask, view {n + 1}")
        ax.axis("off")
    ax = fig.add_subplot(1, 4, 3, projection="3d")
    if len(faces):
        # Display in RAS (x and y negated), seen from the patient's front.
        ras = np.asarray(vertices_lps, float) * np.array([-1.0, -1.0, 1.0])
        triangles = ras[np.asarray(faces)]
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
        light = np.array([0.3, 1.0, 0.6]) / np.linalg.norm([0.3, 1.0, 0.6])  # from the front, above
        shade = 0.35 + 0.65 * np.abs(normals @ light)
        colours = np.clip(np.outer(shade, (0.9, 0.3, 0.25)), 0, 1)
        ax.add_collection3d(Poly3DCollection(triangles, facecolors=colours, edgecolor="none"))
        lo, hi = ras.min(axis=0), ras.max(axis=0)
        centre, half = (lo + hi) / 2, float((hi - lo).max()) / 2
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.view_init(elev=10, azim=90)  # from anterior: the patient's left on the right, as in AP
    ax.set_title(titles[2] or "reconstructed surface")
    ax.set_axis_off()
    ax = fig.add_subplot(1, 4, 4)
    ax.imshow(overlay_mip(pred, label, axis=1), interpolation="nearest")
    ax.set_title(titles[3] or "vs ground truth (MIP, front)")
    ax.axis("off")
    fig.tight_layout(rect=(0, 0, 1, 0.94))  # room for the titles above the 3D panel
    fig.savefig(str(path))
    plt.close(fig)
