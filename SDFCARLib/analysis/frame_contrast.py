"""Whether a view's frame shows the vessels its mask outlines, dark as the lumen model expects.

The frames' widths are fitted to a lumen that absorbs (``frame_widths.py``: vessels darker than their
surroundings). Contrast is the median grey a few pixels around the mask minus the median grey under it, in
units of the surroundings' spread (1.4826 × median absolute deviation): positive where the vessels are dark.
A frame with the vessels bright (a negative display, an export storing the absorbance) would have every
width fitted to the wrong profile; it is refused by ``INVERTED_CONTRAST``. A frame whose vessels hardly stand
out under the mask (under ``MIN_VESSEL_CONTRAST``) is not the frame that mask was drawn on (another view's,
another run's) or holds no contrast there; its widths are warned of, as is a view whose frame gave no width at
all. The thresholds sit between the measured groups (bench/RESULTS.md §85): frames under their own masks 1.2
and above, the same frames inverted −1.2 and below, another view's frame under the mask −0.43 to 0.18.
"""

from __future__ import annotations

from typing import List, Optional, Sequence

import numpy as np

from ..masks import widened_mask
from .lesion import robust_sigma

INVERTED_CONTRAST = -0.75  # below: the vessels are bright, the frame inverted
MIN_VESSEL_CONTRAST = 0.6  # below: no vessel stands out under the mask
EDGE_SKIP_PX = 2  # the blurred border beside the mask is neither lumen nor background
SURROUND_PX = 8  # the surroundings reach this far from the mask


def vessel_contrast(frame: np.ndarray, mask: np.ndarray) -> Optional[float]:
    """The frame's vessel contrast under ``mask`` (module docstring); None where the mask or its surroundings
    are empty or the surroundings have no spread."""
    image = np.asarray(frame, np.float64)
    inside = np.asarray(mask) > 0
    if image.shape != inside.shape:
        raise ValueError(f"frame shape {image.shape} differs from its mask's {inside.shape}: give the frame the mask "
                         f"was drawn on")
    if not inside.any():
        return None
    around = widened_mask(inside, SURROUND_PX) & ~widened_mask(inside, EDGE_SKIP_PX)
    if not around.any():
        return None
    spread = robust_sigma(image[around])
    if not spread > 0:
        return None
    return (float(np.median(image[around])) - float(np.median(image[inside]))) / spread


def check_vessels_dark(frames: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> List[Optional[float]]:
    """Each view's ``vessel_contrast``; ValueError naming the first view whose vessels are bright."""
    contrasts = []
    for n, (frame, mask) in enumerate(zip(frames, masks), start=1):
        try:
            contrasts.append(vessel_contrast(frame, mask))
        except ValueError as exc:
            raise ValueError(f"frame of view {n}: {exc}") from None
    for n, c in enumerate(contrasts, start=1):
        if c is not None and c < INVERTED_CONTRAST:
            raise ValueError(
                f"frame of view {n}: the vessels its mask outlines are brighter than their surroundings (contrast {c:.1f}; "
                f"a frame as acquired has them dark, above {MIN_VESSEL_CONTRAST:g}): the frame is inverted (a negative "
                f"display, an export of the absorbance) or is not the one the mask was drawn on; give the frame as "
                f"acquired, or invert its grey levels (largest + smallest - grey)")
    return contrasts


def frame_contrast_warning(contrasts: Sequence[Optional[float]], measured: Sequence[Optional[float]]) -> Optional[str]:
    """The warning for views whose frame shows no vessel under the mask (``contrasts``) or gave no width
    (``measured``: the share of the centreline points with a frame width, per view)."""
    faint = [n for n, c in enumerate(contrasts, start=1) if c is not None and c < MIN_VESSEL_CONTRAST]
    empty = [n for n, share in enumerate(measured, start=1) if share is not None and share == 0.0]
    if not faint and not empty:
        return None
    said = []
    for n in sorted(set(faint) | set(empty)):
        text = f"view {n}: "
        if n in faint:
            text += (f"the vessels hardly stand out under its mask (contrast {round(contrasts[n - 1], 1) + 0.0:.1f}; a frame under its "
                     f"own mask: above {MIN_VESSEL_CONTRAST:g})")
        if n in empty:
            text += (" and " if n in faint else "") + "the frame gave no width at any centreline point"
        said.append(text)
    text = ("frames: " + "; ".join(said) + ". Is each the frame its mask was drawn on, of the same run, in the views' "
            "order? Widths fitted on such a frame are not the vessel's.")
    if empty:
        others = [n for n in range(1, len(measured) + 1) if n not in empty]
        if len(others) == 1:
            text += f" The frames' diameters rest on view {others[0]} alone (a round lumen assumed)."
        elif others:
            text += f" The frames' diameters rest on views {', '.join(map(str, others))}."
        else:
            text += " No frame diameter was measured."
    return text
