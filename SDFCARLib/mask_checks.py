"""Sanity checks of a vessel mask before a run: say what looks wrong and how to fix it.

A mask can be a valid binary image (``masks.binarise_mask`` accepts it) and still be a poor
target: real X-ray frames put the collimator's edges, noise and the frame border into automatic
masks. Such masks do not stop a run; they slow it down (every speck back-projects into a cone
that meets the other view's vessels, and the support grows) and give a poor tree, and nothing
said why. ``mask_warnings`` names each problem with the number that shows it and the fix:

* border: the share of the image's outermost ``BORDER_PX`` pixels that are vessel. Vessels
  leaving the field cross the border at a few places (a few per cent at most); a collimator edge
  or the frame border segmented as vessel runs along it.
* straight lines: a component that runs along a row or column over most of the image, its two ends
  as far from their sides, and is thin across (``LINE_SPAN``, ``LINE_END``, ``LINE_THICKNESS``): a
  collimator blade's edge inside the image, which the border ring does not see, running from shutter
  to shutter (a catheter enters at one side and ends inside). One joined to the tree is not found.
* specks: 8-connected components smaller than ``SPECK_MM2`` at the detector (``SPECK_PX`` when
  the pixel spacing is unknown). A vessel mask is a few connected trees; hundreds of specks are
  noise from a vesselness filter or a threshold.
* coverage: the share of the image that is vessel. Coronary trees cover about 1–15 % of an
  angiogram; above ``MAX_COVERAGE`` the background was segmented, below ``MIN_COVERAGE`` the
  mask holds almost nothing.

``support_masks(masks, views, grid)`` gives the masks the support (``hull.support_mask``) is built
from, for ``optimiser.build_problem``: when a mask has ``MAX_SPECKS`` specks or more, a speck is
noise more likely than vessel (and one no larger than a voxel's shadow cannot be told from noise
by the reconstruction at all); each back-projects into a cone that meets the other view's vessels,
so the support — and the time per step — grows with their number (bench/RESULTS.md: 1000 specks of
4 px made the support 11× and the step 20× larger). They are left out of the support only — never
out of the user's mask, which the loss still uses — and a warning says how many pixels.
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage

from .geometry import CArmView, VolumeGrid

BORDER_PX = 2  # width of the image border ring that is checked
MAX_BORDER_SHARE = 0.05  # more of the border ring than this is vessel: a collimator or frame edge
SPECK_MM2 = 2.0  # components smaller than this (at the detector) are specks: 1 mm × 2 mm of vessel
SPECK_PX = 15  # the same without a pixel spacing
MAX_SPECKS = 20
MAX_COVERAGE = 0.25
LINE_SPAN = 0.8  # a component this long a share of the image side, …
LINE_END = 0.05  # … its ends as far from their sides within this share, …
LINE_THICKNESS = 0.06  # … and at most this share of the other side across is a straight edge, not a vessel
MIN_COVERAGE = 0.0005

_EIGHT = np.ones((3, 3), dtype=bool)


def _components(mask: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(labels, sizes in pixels of components 1..n) of the 8-connected components."""
    labels, count = ndimage.label(mask, structure=_EIGHT)
    sizes = np.bincount(labels.reshape(-1), minlength=count + 1)[1:]
    return labels, sizes


def _spans(extent: slice, size: int) -> bool:
    """Whether ``extent`` covers ``LINE_SPAN`` of an axis of ``size`` pixels or more with its two ends as far from
    their sides of the image, within ``LINE_END`` of the side: a blade's edge runs from shutter to shutter (or margin
    to margin), a catheter enters at one side and ends inside."""
    before, after = extent.start, size - extent.stop
    return extent.stop - extent.start >= LINE_SPAN * size and abs(before - after) <= LINE_END * size


def _straight_lines_across(labels: np.ndarray) -> List[str]:
    """The components (``labels``, as ``_components`` gives them) that run nearly straight along a row or a column
    (``_spans``) and are at most ``LINE_THICKNESS`` of the image across (a blade's edge, slightly tilted), described for
    a message; those along the image's edge are the border check's."""
    rows, cols = labels.shape
    found = []
    for box in ndimage.find_objects(labels):
        if box is None:
            continue
        height, width = box[0].stop - box[0].start, box[1].stop - box[1].start
        if box[0].start < BORDER_PX and width > height or box[0].stop > rows - BORDER_PX and width > height \
                or box[1].start < BORDER_PX and height > width or box[1].stop > cols - BORDER_PX and height > width:
            continue
        if _spans(box[1], cols) and height <= LINE_THICKNESS * rows:
            found.append(f"across the image near row {(box[0].start + box[0].stop) // 2} ({width} pixels long)")
        elif _spans(box[0], rows) and width <= LINE_THICKNESS * cols:
            found.append(f"down the image near column {(box[1].start + box[1].stop) // 2} ({height} pixels long)")
    return found


def speck_area_px(pixel_spacing_mm: Optional[Sequence[float]] = None) -> float:
    """The area (pixels) below which a component counts as a speck."""
    if pixel_spacing_mm is None:
        return float(SPECK_PX)
    row, col = (float(v) for v in pixel_spacing_mm)
    return max(SPECK_MM2 / (row * col), 2.0)


def mask_warnings(mask: np.ndarray, pixel_spacing_mm: Optional[Sequence[float]] = None,
                  source: str = "mask") -> List[str]:
    """Warnings (possibly none) about a binary vessel mask, each naming the problem and the fix.

    ``pixel_spacing_mm``: (row, col) at the detector, for the speck size in mm²; ``source`` names
    the mask in the messages (e.g. "view 1").
    """
    m = np.asarray(mask).astype(bool)
    out: List[str] = []
    if m.ndim != 2 or m.size == 0:
        return [f"{source}: the mask is not a 2-D image (shape {m.shape})"]
    total = int(m.sum())
    coverage = total / m.size
    if coverage > MAX_COVERAGE:
        out.append(f"{source}: the mask covers {100 * coverage:.1f} % of the image, implausibly much for vessels "
                   f"(coronary trees cover about 1–15 %): the background or the collimated border was segmented, or "
                   "the mask is inverted; raise the threshold of the segmentation or check the mask's vessel label")
    elif coverage < MIN_COVERAGE:
        out.append(f"{source}: the mask covers only {100 * coverage:.3f} % of the image ({total} pixels): almost no "
                   "vessel to reconstruct; check that it is the right mask and that the contrast-filled frame was used")
    b = min(BORDER_PX, min(m.shape) // 2)
    if b > 0:
        ring = np.ones(m.shape, dtype=bool)
        ring[b:-b, b:-b] = False
        border_share = float(m[ring].mean())
        if border_share > MAX_BORDER_SHARE:
            out.append(f"{source}: {100 * border_share:.1f} % of the image's border ({b}-pixel ring) is marked as "
                       "vessel: the collimator's edge or the frame border was segmented (vessels that leave the field "
                       "cross the border at a few places only); erase it from the mask or mask the collimated border")
    if total:
        labels, sizes = _components(m)
        for line in _straight_lines_across(labels):
            out.append(f"{source}: a straight line {line} is marked as vessel: a collimator blade's edge or the "
                       "frame's edge inside the image was segmented (no coronary runs straight across the image); "
                       "erase it from the mask")
        limit = speck_area_px(pixel_spacing_mm)
        specks = sizes[sizes < limit]
        if specks.size >= MAX_SPECKS:
            unit = (f"{SPECK_MM2:g} mm² ({limit:.0f} pixels)" if pixel_spacing_mm is not None
                    else f"{limit:.0f} pixels")
            out.append(f"{source}: the mask has {specks.size} specks (connected pieces smaller than {unit}, "
                       f"{int(specks.sum())} pixels in all, of {sizes.size} pieces): noise of the vesselness filter or "
                       "threshold; remove small components (Slicer's Segment Editor: Islands, minimum size; the "
                       "segment pipeline: a larger min_length_mm) or raise the threshold — specks slow the run down "
                       "and add false branches")
    return out


def voxel_shadow_area_px(view: CArmView, grid: VolumeGrid) -> float:
    """Area (pixels) of one voxel's shadow at the isocenter: a disc of half the mean voxel size, magnified."""
    radius_px = 0.5 * float(np.mean(grid.spacing_mm)) * view.magnification / float(min(view.pixel_spacing_mm))
    return math.pi * radius_px**2


def support_masks(masks: Sequence[np.ndarray], views: Sequence[CArmView],
                  grid: VolumeGrid) -> Tuple[List[np.ndarray], List[str]]:
    """The masks without the components the support should not follow, and a message per changed mask.

    Left out: the specks of a mask with ``MAX_SPECKS`` specks or more — pieces smaller than
    ``speck_area_px`` or than one voxel's shadow, whichever is larger. See the module docstring.
    """
    out: List[np.ndarray] = []
    messages: List[str] = []
    for n, (mask, view) in enumerate(zip(masks, views), start=1):
        m = np.asarray(mask).astype(bool)
        labels, sizes = _components(m)
        speck = max(speck_area_px(view.pixel_spacing_mm), voxel_shadow_area_px(view, grid))
        small = sizes < speck
        if small.sum() < MAX_SPECKS or small.all():  # a clean mask keeps everything; never leave nothing
            out.append(m)
            continue
        left_out = np.concatenate([[False], small])[labels]
        out.append(m & ~left_out)
        messages.append(f"view {n}: the mask's {int(small.sum())} specks (pieces smaller than {speck:.0f} pixels), "
                        f"{int(left_out.sum())} pixels in all, "
                        "were left out of the support (the region where the field is evaluated) so that they do not "
                        "slow the run down; the loss still uses the whole mask; clean the mask to remove this warning")
    return out, messages
