"""Whether the masks given to an analysis belong to their views, in the views' order.

A reconstruction is fitted to its masks, so its centreline projects onto each view's own mask (within
``MASK_TOLERANCE_PX``) almost everywhere, and onto another view's far less (the sample case: bench/RESULTS.md
§85). A view whose mask holds under ``MIN_SHARE_ON_MASK`` of its
projected centreline was given another view's mask, or another acquisition's; every measure read on the
masks there (the widths, the centreline placed on their midlines, the masks' lesions) is then wrong.
Where another order of the masks puts every view above that share, the warning names it.
"""

from __future__ import annotations

from itertools import permutations
from typing import List, Optional, Sequence

import numpy as np

from ..geometry import CArmView
from ..masks import widened_mask

MASK_TOLERANCE_PX = 2  # a centreline point this close to the mask is on it (a segmentation a pixel off)
MIN_SHARE_ON_MASK = 0.5
MAX_VIEWS_REORDERED = 4  # other orders are tried up to this many views (4! = 24 orders)


def share_on_masks(points_mm: np.ndarray, masks: Sequence[np.ndarray], views: Sequence[CArmView],
                   tolerance_px: int = MASK_TOLERANCE_PX) -> List[Optional[float]]:
    """Per view, the share of the points that project onto the view's detector and fall on its mask
    (within ``tolerance_px``); None where none projects onto that detector."""
    near = [widened_mask(m, tolerance_px) for m in masks]
    return [_share_on(points_mm, mask, view) for mask, view in zip(near, views)]


def _share_on(points_mm: np.ndarray, near_mask: np.ndarray, view: CArmView) -> Optional[float]:
    row, col, _ = view.project(np.asarray(points_mm, float))
    rows, cols = near_mask.shape
    with np.errstate(invalid="ignore"):
        on_detector = np.isfinite(row) & np.isfinite(col) & (row > -0.5) & (col > -0.5) & (row < rows - 0.5) & (col < cols - 0.5)
    if not on_detector.any():
        return None
    return float(near_mask[np.round(row[on_detector]).astype(int), np.round(col[on_detector]).astype(int)].mean())


def better_order(points_mm: np.ndarray, masks: Sequence[np.ndarray], views: Sequence[CArmView],
                 tolerance_px: int = MASK_TOLERANCE_PX) -> Optional[List[int]]:
    """Where the given order leaves a view under ``MIN_SHARE_ON_MASK``: the order of the masks (mask index per
    view) that puts every view at or above it with the largest least share, if any; else None."""
    if len(views) > MAX_VIEWS_REORDERED or len(masks) != len(views):
        return None
    near = [widened_mask(m, tolerance_px) for m in masks]
    # each mask against each view once: shares[k][n] is mask k in view n
    shares = [[_share_on(points_mm, mask, view) for view in views] for mask in near]
    best, best_least = None, MIN_SHARE_ON_MASK
    for order in permutations(range(len(views))):
        if list(order) == list(range(len(views))):
            continue
        least = min((shares[k][n] if shares[k][n] is not None else 1.0) for n, k in enumerate(order))
        if least >= best_least:
            best, best_least = list(order), least
    return best


def mask_order_warning(shares: Sequence[Optional[float]], order: Optional[Sequence[int]]) -> Optional[str]:
    """The warning for views whose mask misses their projected centreline (``shares``), naming a better order."""
    low = [(n, s) for n, s in enumerate(shares, start=1) if s is not None and s < MIN_SHARE_ON_MASK]
    if not low:
        return None
    where = ", ".join(f"view {n}'s mask holds {100 * s:.0f} %" for n, s in low)
    text = (f"the masks do not match their views: of the reconstruction's centreline projected into its view, {where} "
            f"(a view's own mask holds nearly all of it). The masks' widths, the centreline placed on them and the "
            f"lesions found on them are wrong there.")
    if order is not None:
        text += (" With " + ", ".join(f"mask {k + 1} for view {n}" for n, k in enumerate(order, start=1))
                 + " they match: give the masks in the views' order.")
    else:
        text += " Give each view the mask drawn on its own frame, in the views' order."
    return text
