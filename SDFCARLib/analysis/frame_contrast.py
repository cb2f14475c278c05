"""Whether a view's frame shows the vessels its mask outlines, dark as the lumen model expects.

The frames' widths are fitted to a lumen that absorbs (``frame_widths.py``: vessels darker than their
surroundings). Contrast is the median grey a few pixels around the mask minus the median grey under the mask's
core (its inner half, where a thin vessel's blurred lumen is darkest), in units of the surroundings' spread
(1.4826 × median absolute deviation): positive where the vessels are dark. Frames with the vessels bright under
every mask (a negative display, an export storing the absorbance) would have every width fitted to the wrong
profile: refused below ``INVERTED_CONTRAST``. One view so, or one whose vessels hardly stand out under its mask
(under ``MIN_VESSEL_CONTRAST``: another view's or another run's frame, a vessel seen end-on, no contrast there), is
warned of, as is a view whose frame gave no width at all. Measured (bench/RESULTS.md §85b): on the realistic trees
own frames 1.94 and above, inverted −1.94 and below, another view's frame −0.53 to 0.35; on the 54 stenosed tubes
3 of 208 own views fall below 0.6, all small blobs of a tube seen end-on (and one of them below −0.75).
"""

from __future__ import annotations

from typing import List, Optional, Sequence

import numpy as np
from scipy import ndimage

from ..masks import widened_mask
from .lesion import robust_sigma

INVERTED_CONTRAST = -0.75  # below: the vessels are bright, the frame inverted
MIN_VESSEL_CONTRAST = 0.6  # below: no vessel stands out under the mask
EDGE_SKIP_PX = 2  # the blurred border beside the mask is neither lumen nor background
SURROUND_PX = 8  # the surroundings reach this far from the mask


def vessel_contrast(frame: np.ndarray, mask: np.ndarray, core: bool = True) -> Optional[float]:
    """The frame's vessel contrast under ``mask`` (module docstring); None where the mask or its surroundings
    are empty or the surroundings have no spread. ``core``: read under the mask's inner half only (at least half
    its greatest depth from its border), where a thin vessel's blurred lumen is darkest."""
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
    if core:
        depth = ndimage.distance_transform_edt(inside)
        inside = depth >= max(1.0, 0.5 * float(depth.max()))
    return (float(np.median(image[around])) - float(np.median(image[inside]))) / spread


def check_vessels_dark(frames: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> List[Optional[float]]:
    """Each view's ``vessel_contrast``; ValueError where every view's vessels are bright (the frames inverted: one
    view alone so is warned of, ``frame_contrast_warning``, as a vessel seen end-on can read so)."""
    contrasts = []
    for n, (frame, mask) in enumerate(zip(frames, masks), start=1):
        try:
            contrasts.append(vessel_contrast(frame, mask))
        except ValueError as exc:
            raise ValueError(f"frame of view {n}: {exc}") from None
    read = [c for c in contrasts if c is not None]
    if read and max(read) < INVERTED_CONTRAST:
        said = ", ".join(f"view {n} {c:.1f}" for n, c in enumerate(contrasts, start=1) if c is not None)
        raise ValueError(
            f"the frames' vessels are brighter than their surroundings under every mask (contrast {said}; frames as "
            f"acquired have them dark, above {MIN_VESSEL_CONTRAST:g}): the frames are inverted (a negative display, an "
            f"export of the absorbance) or are not the ones the masks were drawn on; give the frames as acquired, or "
            f"invert their grey levels (largest + smallest - grey)")
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
            c = round(contrasts[n - 1], 1) + 0.0
            text += ("its frame is brighter under its mask than around it (inverted, or no vessel there: seen end-on?)"
                     if c < INVERTED_CONTRAST else "the vessels hardly stand out under its mask")
            text += f" (contrast {c:.1f}; a frame under its own mask: above {MIN_VESSEL_CONTRAST:g})"
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
