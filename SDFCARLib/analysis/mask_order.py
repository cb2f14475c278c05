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


def shares_on_masks(points_mm: np.ndarray, masks: Sequence[np.ndarray], views: Sequence[CArmView],
                    tolerance_px: int = MASK_TOLERANCE_PX) -> List[List[Optional[float]]]:
    """``shares[k][n]``: the share of the points projected onto view ``n``'s detector that fall on mask ``k`` (within
    ``tolerance_px``); None where none projects onto that detector, or the mask has another shape than it (it cannot be
    that view's). Each view is projected once, each mask widened once."""
    near = [widened_mask(m, tolerance_px) for m in masks]
    pixels = [_detector_pixels(points_mm, view) for view in views]
    return [[None if at is None or mask.shape != tuple(view.detector_shape) else float(mask[at].mean())
             for at, view in zip(pixels, views)] for mask in near]


def share_on_masks(points_mm: np.ndarray, masks: Sequence[np.ndarray], views: Sequence[CArmView],
                   tolerance_px: int = MASK_TOLERANCE_PX) -> List[Optional[float]]:
    """Per view, the share of the points that project onto the view's detector and fall on its own mask."""
    shares = shares_on_masks(points_mm, masks, views, tolerance_px)
    return [shares[n][n] for n in range(len(views))]


def _detector_pixels(points_mm: np.ndarray, view: CArmView):
    """(rows, cols) of the points that project onto the view's detector, rounded to its pixels; None if none does."""
    row, col, _ = view.project(np.asarray(points_mm, float))
    rows, cols = view.detector_shape
    with np.errstate(invalid="ignore"):
        on_detector = np.isfinite(row) & np.isfinite(col) & (row > -0.5) & (col > -0.5) & (row < rows - 0.5) & (col < cols - 0.5)
    if not on_detector.any():
        return None
    return np.round(row[on_detector]).astype(int), np.round(col[on_detector]).astype(int)


def better_order(shares: Sequence[Sequence[Optional[float]]]) -> Optional[List[int]]:
    """From ``shares_on_masks``: the order of the masks (mask index per view) other than the given one that puts
    every view at or above ``MIN_SHARE_ON_MASK`` with the largest least share, if any (up to
    ``MAX_VIEWS_REORDERED`` views); else None."""
    n_views = len(shares)
    if n_views > MAX_VIEWS_REORDERED:
        return None
    best, best_least = None, MIN_SHARE_ON_MASK
    for order in permutations(range(n_views)):
        if list(order) == list(range(n_views)):
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
