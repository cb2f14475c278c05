"""Reprojection QA per view: where the result's projection and the view's mask disagree, in mm².

One Dice per view cannot tell a misdrawn mask from a wrong angle or a ghost branch; the place and
size of the disagreement can. Per view (``reprojection_qa``) the pixels split into

* agree        — vessel in the mask and in the projection of the result;
* result only  — the result casts a shadow the mask lacks (a ghost branch, or a mask that misses
                 a vessel);
* mask only    — the mask shows vessel the result does not explain (a vessel only this view
                 shows, a mask drawn on another frame or cardiac phase, wrong angles).

Where the check before the run found vessels that only this view can show (they run where another
view's collimator, clipped frame or detector edge hides them: ``consistency.view_agreement``), their
centreline is drawn over the colours, and the mask-only area along it (and a largest blob mostly
there) is named as such: one view cannot place a vessel in depth, so a blob there is expected. The
check's marks are mostly, not always, right (RESULTS §93a), so the warning still names what to check.

Areas are in mm² at the isocenter plane (pixel count × the view's isocenter pixel spacings), so
that views of different magnification compare. The largest disagreeing blob of each kind is an
8-connected component of that kind after an opening with a 3 × 3 square: the one-pixel rims that
any discretised projection leaves along the vessels' edges are not blobs, a missing or extra
vessel is.

``qa_overlay_rgb`` draws the three kinds in Okabe–Ito colours (distinguishable with the common
colour-vision deficiencies) over an optional grey frame, outlines the largest blob of each kind
and adds a legend strip below the image, so no detector pixel is hidden. ``qa_warnings`` names the
views whose disagreement exceeds ``WARN_SHARE`` of the mask or ``WARN_BLOB_MM2`` (the levels are
chosen from clean and broken simulated cases, bench/RESULTS.md section 8).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
from scipy import ndimage

from .geometry import CArmView

# Okabe & Ito's palette.
AGREE_RGB = (0, 158, 115)  # bluish green
RESULT_ONLY_RGB = (213, 94, 0)  # vermillion
MASK_ONLY_RGB = (0, 114, 178)  # blue
OUTLINE_RGB = (240, 228, 66)  # yellow: the box around the largest blob of each kind
ONE_VIEW_RGB = (204, 121, 167)  # reddish purple: the centreline of vessels only this view can show
LEGEND_BACKGROUND_RGB = (0, 0, 0)
LEGEND_TEXT_RGB = (255, 255, 255)
FRAME_GREY_MAX = 150  # the frame underneath stays darker than the colours drawn over it

LEGEND = (("both", AGREE_RGB), ("result only", RESULT_ONLY_RGB), ("mask only", MASK_ONLY_RGB),
          ("seen by this view only", ONE_VIEW_RGB), ("largest blob", OUTLINE_RGB))
LEGEND_LINE_PX = 12
LEGEND_HEIGHT_PX = LEGEND_LINE_PX * (len(LEGEND) + 1) + 4  # a title line and one line per entry
LEGEND_WIDTH_PX = 200

WARN_SHARE = 0.10  # result-only or mask-only area above this share of the mask's area
WARN_BLOB_MM2 = 5.0  # a disagreeing blob (after the opening) larger than this at the isocenter
# a mask pixel this close (pixels) to the centreline of a vessel only this view shows belongs to that vessel
# (the widest coronary vessels are about 6 pixels across at 0.3 mm)
ONE_VIEW_NEAR_PX = 4
ONE_VIEW_BLOB_SHARE = 0.5  # a mask-only blob mostly along such a vessel is named as one

_EIGHT = np.ones((3, 3), dtype=bool)
KINDS = ("result_only", "mask_only")


def qa_file_name(view_number: int) -> str:
    """The overlay's file name in the result folder (views count from 1)."""
    return f"qa_view{view_number}.png"


def _as_bool(image: np.ndarray, name: str, shape: Optional[Tuple[int, ...]] = None) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2D (rows, cols) image, got shape {a.shape}")
    if shape is not None and a.shape != shape:
        raise ValueError(f"{name} has shape {a.shape} but the other image has {shape}; give images of the same view")
    return a != 0


def largest_blob(disagreement: np.ndarray, pixel_area_mm2: float,
                 one_view_near: Optional[np.ndarray] = None) -> Optional[Dict[str, Any]]:
    """The largest 8-connected blob of ``disagreement`` after a 3 × 3 opening, or None when none is left;
    with ``one_view_near`` (bool image: the pixels of vessels only this view shows) also the share of the
    blob's pixels that lie there."""
    opened = ndimage.binary_opening(disagreement, structure=_EIGHT)
    labels, count = ndimage.label(opened, structure=_EIGHT)
    if count == 0:
        return None
    sizes = np.bincount(labels.reshape(-1), minlength=count + 1)[1:]
    index = int(np.argmax(sizes)) + 1
    rows, cols = np.nonzero(labels == index)
    blob: Dict[str, Any] = {
        "pixels": int(rows.size),
        "area_mm2": float(rows.size * pixel_area_mm2),
        "centroid_rc": [float(rows.mean()), float(cols.mean())],
        # inclusive pixel bounds: [row_min, col_min, row_max, col_max]
        "bbox_rc": [int(rows.min()), int(cols.min()), int(rows.max()), int(cols.max())],
    }
    if one_view_near is not None:
        blob["one_view_share"] = float(one_view_near[rows, cols].mean())
    return blob


def one_view_region(one_view: Optional[np.ndarray], mask: np.ndarray) -> Optional[np.ndarray]:
    """The mask's pixels within ``ONE_VIEW_NEAR_PX`` of the centreline pixels only this view shows (None: none)."""
    if one_view is None:
        return None
    centreline = _as_bool(one_view, "the one-view centreline image", mask.shape)
    if not centreline.any():
        return np.zeros(mask.shape, dtype=bool)
    return (ndimage.distance_transform_edt(~centreline) <= ONE_VIEW_NEAR_PX) & mask


def reprojection_qa(projected_mask: np.ndarray, mask: np.ndarray, view: CArmView,
                    one_view: Optional[np.ndarray] = None) -> Dict[str, Any]:
    """Agreement of one view's mask with the projection of the result (see the module docstring).

    ``one_view``: bool image of the centreline pixels of vessels only this view shows
    (``consistency.ViewAgreement.one_view_image``); with it each largest blob carries the share of its
    pixels along those vessels (``one_view_share``), and ``one_view_area_mm2`` the area of the mask there
    (``mask``) and of the mask-only pixels there (``mask_only``)."""
    projected = _as_bool(projected_mask, "the projected mask")
    reference = _as_bool(mask, "the mask", projected.shape)
    if projected.shape != tuple(view.detector_shape):
        raise ValueError(f"the images have shape {projected.shape} but the view's detector is "
                         f"{tuple(view.detector_shape)}; give the images of this view")
    spacing = view.isocenter_pixel_spacing_mm
    pixel_area = float(spacing[0] * spacing[1])
    parts = {"agree": projected & reference, "result_only": projected & ~reference, "mask_only": reference & ~projected}
    counts = {k: int(v.sum()) for k, v in parts.items()}
    mask_pixels = int(reference.sum())
    total = 2 * counts["agree"] + counts["result_only"] + counts["mask_only"]
    out: Dict[str, Any] = {
        "area_plane": "isocenter",
        "pixel_area_mm2": pixel_area,
        "pixels": counts,
        "area_mm2": {k: v * pixel_area for k, v in counts.items()},
        "mask_area_mm2": mask_pixels * pixel_area,
        "result_area_mm2": int(projected.sum()) * pixel_area,
        # Empty on both sides is perfect agreement.
        "dice": 2.0 * counts["agree"] / total if total else 1.0,
        "share_of_mask": {k: counts[k] / mask_pixels if mask_pixels else float(counts[k] > 0) for k in KINDS},
    }
    near = one_view_region(one_view, reference)
    out["largest_blob"] = {k: largest_blob(parts[k], pixel_area, near) for k in KINDS}
    if near is not None:
        out["one_view_area_mm2"] = {"mask": int(near.sum()) * pixel_area,
                                    "mask_only": int((near & parts["mask_only"]).sum()) * pixel_area}
    return out


_ONE_VIEW_WHY = ("their centreline reddish purple: the check before the run traced them into a part another view "
                 "cannot show, and one view cannot place a vessel in depth")


def qa_warnings(per_view: Sequence[Dict[str, Any]], share: float = WARN_SHARE,
                blob_mm2: float = WARN_BLOB_MM2) -> List[str]:
    """A warning per view whose disagreement exceeds ``share`` of its mask or has a blob over ``blob_mm2``."""
    out = []
    for n, qa in enumerate(per_view, start=1):
        for kind in KINDS:
            blob = qa["largest_blob"][kind]
            big_share = qa["share_of_mask"][kind] > share
            big_blob = blob is not None and blob["area_mm2"] > blob_mm2
            if not (big_share or big_blob):
                continue
            where = ""
            if blob is not None:
                r, c = blob["centroid_rc"]
                where = f"; its largest blob, {blob['area_mm2']:.1f} mm², is at row {r:.0f}, column {c:.0f}"
            amount = f"{qa['area_mm2'][kind]:.1f} mm² ({100 * qa['share_of_mask'][kind]:.0f} % of the mask's area)"
            one_view_mm2 = qa.get("one_view_area_mm2", {}).get("mask_only", 0.0)
            if kind == "mask_only" and blob is not None and blob.get("one_view_share", 0.0) >= ONE_VIEW_BLOB_SHARE:
                out.append(
                    f"view {n}: the result does not explain {amount} of the mask{where} ({qa_file_name(n)}, blue); "
                    f"it lies along vessels that only this view shows ({_ONE_VIEW_WHY}). A view whose field includes "
                    "them would; if the other views do show them, check the angles and masks instead")
            elif kind == "mask_only":
                along = (f"; {one_view_mm2:.1f} mm² of it lies along vessels that only this view shows ({_ONE_VIEW_WHY})"
                         if one_view_mm2 > 0 else "")
                out.append(
                    f"view {n}: the result does not explain {amount} of the mask{where} ({qa_file_name(n)}, blue){along}; "
                    "check that the mask was drawn on this view's frame and cardiac phase, the view's angles "
                    "(LAO +, RAO −, CRA +, CAU −) and SID/SOD, or whether that vessel is seen in this view only")
            else:
                out.append(
                    f"view {n}: the result casts {amount} of shadow outside the mask{where} ({qa_file_name(n)}, "
                    "vermillion); check for a ghost branch in the 3D result, a vessel the mask missed, "
                    "and the view's angles")
    return out


def _grey(frame: np.ndarray, shape: Tuple[int, int]) -> np.ndarray:
    f = np.asarray(frame, dtype=np.float64)
    if f.shape != shape:
        raise ValueError(f"the frame has shape {f.shape} but the masks have {shape}; give the frame of this view")
    finite = f[np.isfinite(f)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    scaled = np.clip((np.nan_to_num(f, nan=lo) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return np.round(scaled * FRAME_GREY_MAX).astype(np.uint8)


def _outline(image: np.ndarray, bbox: Sequence[int], rows: int, cols: int) -> None:
    """A one-pixel box two pixels outside ``bbox`` (clipped to the detector), so the blob stays visible."""
    r0, c0 = max(bbox[0] - 2, 0), max(bbox[1] - 2, 0)
    r1, c1 = min(bbox[2] + 2, rows - 1), min(bbox[3] + 2, cols - 1)
    image[r0, c0:c1 + 1] = OUTLINE_RGB
    image[r1, c0:c1 + 1] = OUTLINE_RGB
    image[r0:r1 + 1, c0] = OUTLINE_RGB
    image[r0:r1 + 1, c1] = OUTLINE_RGB


def _legend(width: int, title: str) -> np.ndarray:
    from PIL import Image, ImageDraw, ImageFont  # pillow comes with imageio; only the legend needs it

    font = ImageFont.load_default()
    # Wide enough for the title even on a small detector.
    width = max(width, int(np.ceil(ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(title, font=font))) + 8)
    strip = Image.new("RGB", (width, LEGEND_HEIGHT_PX), LEGEND_BACKGROUND_RGB)
    draw = ImageDraw.Draw(strip)
    draw.text((4, 2), title, fill=LEGEND_TEXT_RGB, font=font)
    for n, (label, colour) in enumerate(LEGEND, start=1):
        top = 2 + n * LEGEND_LINE_PX
        draw.rectangle([4, top + 1, 13, top + 9], fill=colour)
        draw.text((18, top), label, fill=LEGEND_TEXT_RGB, font=font)
    return np.asarray(strip, dtype=np.uint8)


def qa_overlay_rgb(frame: Optional[np.ndarray], projected_mask: np.ndarray, mask: np.ndarray,
                   title: str = "", one_view: Optional[np.ndarray] = None) -> np.ndarray:
    """RGB uint8 image: the detector (rows × cols, colours as in ``LEGEND``) above a legend strip.

    ``one_view``: bool image of the centreline pixels of vessels only this view shows, drawn over the
    other colours one pixel wide (the colours either side still say whether the result explains them).

    The image is ``(rows + LEGEND_HEIGHT_PX, max(cols, LEGEND_WIDTH_PX, title width), 3)``; detector pixel
    (r, c) is image pixel (r, c). Without a frame the background is black.
    """
    projected = _as_bool(projected_mask, "the projected mask")
    reference = _as_bool(mask, "the mask", projected.shape)
    rows, cols = projected.shape
    detector = np.zeros((rows, cols, 3), dtype=np.uint8)
    if frame is not None:
        detector[...] = _grey(frame, (rows, cols))[..., None]
    parts = {"result_only": projected & ~reference, "mask_only": reference & ~projected}
    detector[projected & reference] = AGREE_RGB
    detector[parts["result_only"]] = RESULT_ONLY_RGB
    detector[parts["mask_only"]] = MASK_ONLY_RGB
    if one_view is not None:
        detector[_as_bool(one_view, "the one-view centreline image", projected.shape)] = ONE_VIEW_RGB
    for kind in KINDS:
        blob = largest_blob(parts[kind], 1.0)
        if blob is not None:
            _outline(detector, blob["bbox_rc"], rows, cols)
    legend = _legend(max(cols, LEGEND_WIDTH_PX), title)
    image = np.zeros((rows + LEGEND_HEIGHT_PX, legend.shape[1], 3), dtype=np.uint8)
    image[:rows, :cols] = detector
    image[rows:] = legend
    return image


def qa_title(view_number: int, qa: Dict[str, Any]) -> str:
    """One line for the legend: the view, Dice and the two disagreeing areas."""
    a = qa["area_mm2"]
    return (f"view {view_number}: Dice {qa['dice']:.3f}, result only {a['result_only']:.1f} mm2, "
            f"mask only {a['mask_only']:.1f} mm2")


def write_qa_png(path: Union[str, Path], frame: Optional[np.ndarray], projected_mask: np.ndarray, mask: np.ndarray,
                 title: str = "", one_view: Optional[np.ndarray] = None) -> Path:
    """Write ``qa_overlay_rgb`` as a PNG; returns the path."""
    import imageio.v3 as iio  # as in io.py: the PNG writer is only needed when writing

    path = Path(path)
    iio.imwrite(path, qa_overlay_rgb(frame, projected_mask, mask, title, one_view), extension=".png")
    return path


def view_warnings(warnings: Sequence[str], view_number: int) -> List[str]:
    """The warnings of a report that name view ``view_number`` (they start with "view <n>:")."""
    prefix = f"view {view_number}:"
    return [str(w) for w in warnings if str(w).startswith(prefix)]


def qa_summary(report: Dict[str, Any]) -> List[Dict[str, Any]]:
    """Per view of a report.json: Dice, the disagreeing areas and shares, the file and the view's warnings.

    One dict per view, in view order: ``view``, ``dice``, ``result_only_mm2``, ``mask_only_mm2``,
    ``result_only_share``, ``mask_only_share`` (of the mask's area), ``largest_blob_mm2`` (the larger
    of the two kinds, or None), ``one_view_mask_only_mm2`` (the mask-only area along vessels only this
    view shows, or None where the check did not run), ``file`` (the overlay's name) and ``warnings``.
    [] for a report without reprojection QA (written before it existed).
    """
    per_view = report.get("reprojection_qa") or []
    warnings = report.get("warnings") or []
    rows = []
    for n, qa in enumerate(per_view, start=1):
        if not isinstance(qa, dict):
            continue
        areas = qa.get("area_mm2") or {}
        shares = qa.get("share_of_mask") or {}
        blobs = [b["area_mm2"] for b in (qa.get("largest_blob") or {}).values() if isinstance(b, dict) and "area_mm2" in b]
        rows.append({
            "view": n,
            "dice": qa.get("dice"),
            "result_only_mm2": areas.get("result_only"),
            "mask_only_mm2": areas.get("mask_only"),
            "result_only_share": shares.get("result_only"),
            "mask_only_share": shares.get("mask_only"),
            "largest_blob_mm2": max(blobs) if blobs else None,
            "one_view_mask_only_mm2": (qa.get("one_view_area_mm2") or {}).get("mask_only"),
            "file": qa_file_name(n),
            "warnings": view_warnings(warnings, n),
        })
    return rows


def _formatted(value: Any, pattern: str, scale: float = 1.0) -> str:
    return pattern.format(scale * value) if isinstance(value, (int, float)) and not isinstance(value, bool) else "?"


def qa_summary_lines(report: Dict[str, Any]) -> List[str]:
    """One line per view for a status panel: Dice, result-only and mask-only areas, warning count."""
    lines = []
    for row in qa_summary(report):
        line = (f"View {row['view']}: Dice {_formatted(row['dice'], '{:.3f}')}, "
                f"result only {_formatted(row['result_only_mm2'], '{:.1f}')} mm² "
                f"({_formatted(row['result_only_share'], '{:.0f}', 100)} % of the mask), "
                f"mask only {_formatted(row['mask_only_mm2'], '{:.1f}')} mm² "
                f"({_formatted(row['mask_only_share'], '{:.0f}', 100)} %)")
        if row["one_view_mask_only_mm2"]:
            line += f", {_formatted(row['one_view_mask_only_mm2'], '{:.1f}')} mm² of it where only this view sees"
        if row["warnings"]:
            line += f"; {len(row['warnings'])} warning(s)"
        lines.append(line)
    return lines


def pieces_line(report: Dict[str, Any]) -> Optional[str]:
    """How many 26-connected pieces the result is in, and the largest's share of its voxels (``report.json`` →
    ``components``), for the summary a user reads first; None where the report does not say."""
    counts = report.get("components")
    if not isinstance(counts, dict) or not counts.get("components"):
        return None
    pieces = int(counts["components"])
    if pieces == 1:
        return "The result is one piece (26-connected voxels)."
    largest = counts.get("largest_component_fraction")
    gap = (report.get("reconnection") or {}).get("max_gap_mm")
    if isinstance(gap, (int, float)):
        others = f"the others are vessels the field gave no bridge to within {gap:g} mm, or ghosts"
    elif "reconnection" in report:  # None: `reconnect` off (the paper's preset), nothing tried to join them
        others = "this run joined no pieces (the reconnect setting is off), so the others are broken-off vessels or ghosts"
    else:
        others = "the others are broken-off vessels or ghosts"
    return (f"The result is in {pieces} pieces (26-connected voxels); the largest holds "
            f"{_formatted(largest, '{:.0f}', 100)} % of them. A coronary tree is one piece per ostium: {others}; "
            "look at them in 3D and on the QA overlays.")


def ensemble_choice_line(report: Dict[str, Any]) -> Optional[str]:
    """Which of several fits a result kept and why (``ensemble_combine`` "best_reprojection"), or None."""
    choice = report.get("ensemble_choice")
    if not isinstance(choice, dict) or not choice.get("reprojection_dice"):
        return None
    means = ", ".join(f"{sum(dice) / len(dice):.4f}" if dice else "?" for dice in choice["reprojection_dice"])
    seeds = choice.get("seeds") or []
    return (f"Kept the fit of seed {choice.get('chosen_seed')} of {len(seeds)} (seeds {', '.join(str(s) for s in seeds)}): "
            f"the highest mean reprojection Dice ({means}).")
