"""Vessel masks of the views: binarising label images, and segmenting X-ray angiography frames.

Binarising (``binarise_mask``)
    The one mask rule of the package (the file reader, the engine and the MRML bridge call it):
    one binary image per view, of the view's detector shape, with 0 for background and one
    non-zero value for vessel. Label images and segmentations often hold several labels: give
    ``label`` to keep one of them; without it an image of more than two values is refused, since
    a grey frame given as a mask would otherwise pass. Checked: 2-D, numeric, finite, the
    detector's size, binary, not empty, not everything — each with a message that says how to
    fix the input. An RGB(A) image is accepted only when its colour channels are equal (a grey
    image saved as colour).

Angiogram masks (``segment_angiogram`` / ``angiogram_mask``), for when no mask exists
    One frame (intensity, vessels dark), its detector pixel spacing and magnification SID/SOD
    (typical values when unknown, reported as such) → a mask of the vessel tree, the border that
    was excluded, and every parameter used. All sizes are physical (``AngioMaskSettings``, mm at
    the isocenter) and converted to pixels with the frame's geometry. Steps:

    1. ``−log I`` (Beer–Lambert: proportional to the iodine path; exposure and the tissue in
       front only add to it).
    2. Collimator and image border: the regions wider than the thinnest vessels whose intensity
       differs from the centre of the image by more than ``shutter_ratio`` and that run along the
       image edge for more than twice the widest vessel (a vessel leaving the field touches it over
       its width only); widened, with the image edge, by the filters' reach (2 × the largest σ).
       They are filled with the nearest field values before filtering, and are never vessel.
       A frame whose field is under ``min_field_fraction`` is refused.
       Polarity, on the field less its broad bright regions along the edge: vessels absorb, so the
       fine structures of ``−log I`` reach further above its background than below
       (``thin_structure_contrasts``; their ratio is ``dark_vessel_asymmetry`` in the parameters),
       read at the 1 % tails and at the 0.1 % ones, where a lone tube speaks (``judge_polarity``); a
       frame where the bright ones reach much further shows its vessels bright (an inverted display
       or export) and is refused, naming ``bright_vessels`` (its grey levels inverted first); a
       doubtful one gets a warning.
    3. Background: grey opening (a window wider than the widest vessel) of the log image, box
       smoothed and subtracted (a top-hat): soft tissue, ribs, diaphragm and exposure go.
    4. Ridge filter (Sato by default; Frangi and Meijering selectable) at σ = r/√3 for radii
       geometric between the smallest and largest vessel radius, at least one pixel.
    5. Hysteresis on the response in noise units (median and robust spread, 1.4826 × MAD, of the
       field): seeds above ``high_noise_units``, grown through ``low_noise_units``, so faint
       vessels connected to the tree are kept and isolated noise is not.
    6. Silhouette: of those, the pixels whose top-hat (σ = 1 pixel smoothed) stands
       ``silhouette_noise_units`` above its own noise (the ridge response is wider than the vessel)
       and, where ``min_contrast`` is set, dims the frame by that much at least (in −log I): on a
       clean frame (high SNR, a denoised or simulated one) what the background removal leaves of
       ribs and the diaphragm stands many noise units high but dims the frame by a few per cent
       only. Off by default: on frames with the usual noise it also cuts faint distal vessels,
       which the reconstruction needs more than it is hurt by the remains. A frame whose
       strongest ridges (95th percentile) dim it by less than ``min_vessel_contrast`` holds no
       contrast-filled vessel and is refused (a frame before the contrast arrived).
    7. Specks: 8-connected components shorter than ``min_length_mm`` along their skeleton, or
       less elongated than ``min_elongation`` (length² / area, i.e. length over mean width), go.
    8. Edges: step 6's level sits at the foot of the blurred profile, so a thin, faint vessel comes
       out a pixel wider on each side than it is, while the ridge filter's reach leaves a thick
       vessel's border a pixel short. A pixel's edge level is a share of the contrast on the nearest
       point of the mask's centreline: ``edge_fraction`` where the mask's radius there is up to
       ``edge_taper_radius_mm``, falling as (taper radius / radius)² beyond (the blurred border of a
       wide lumen sits lower on its profile than a narrow one's). Mask pixels below their level go,
       the centreline always stays, and pixels up to ``edge_grow_mm`` outside the mask that reach
       it and stand out of the noise as step 6 asks are added (pieces of them that touch no vessel
       go: specks). Without a taper the share is
       constant, and ``edge_max_radius_mm`` limits the rule to the thinner vessels (the rule
       before, bench/RESULTS.md §59).
       (Defaults: bench/RESULTS.md §60 — the realistic suites' border errors a quarter fewer, extra
       and missed pixels alike.)
       On frames processed for display (``mask_settings_for_intensity``: DISP, a vendor's term) the
       share is ``DISPLAY_EDGE_FRACTION``, so the trim is as good as off and the growth stays: their
       edges were enhanced, the profile overshoots beside the vessel and the usual share falls inside
       the lumen — such masks came out a fifth too thin (bench/RESULTS.md §79).

    A frame where nothing is left (no contrast, a wrong frame) or where half the image would be
    vessel is refused with a ``MaskError`` that names the problem.

The first helper of the project, a plain Frangi filter with an Otsu threshold, was replaced by this
pipeline (bench/RESULTS.md compares them; the benchmark keeps it as its baseline, bench/masks.py).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
from scipy import ndimage

PathLike = Union[str, Path]


class MaskError(ValueError):
    """A mask cannot be used; the message names the problem and the fix."""


class BrightVesselsError(MaskError):
    """A frame shows its vessels bright; segmented with ``bright_vessels=True`` it would be read the right way up."""


def single_grey_image(array: Any, not_numeric: str, colour: str, not_2d: str) -> np.ndarray:
    """The 2-D grey image in ``array``: RGB(A) with equal colour channels and singleton axes are
    accepted; otherwise a ``MaskError`` with the caller's message, its ``{dtype}``, ``{channels}`` or
    ``{shape}`` filled in (by replacement: a file name in the message may hold braces)."""
    a = np.asarray(array)
    if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise MaskError(not_numeric.replace("{dtype}", str(a.dtype)))
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        rgb = a[..., :3]
        if not (np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2])):
            raise MaskError(colour.replace("{channels}", str(a.shape[-1])))
        a = rgb[..., 0]
    if a.ndim == 3 and 1 in (a.shape[0], a.shape[-1]):
        a = a.reshape(a.shape[1:] if a.shape[0] == 1 else a.shape[:-1])
    if a.ndim != 2:
        raise MaskError(not_2d.replace("{shape}", str(a.shape)))
    return a


def widened_mask(mask: np.ndarray, pixels: int) -> np.ndarray:
    """The mask (nonzero pixels) grown by ``pixels`` (4-connected steps); as it is for 0."""
    inside = np.asarray(mask) > 0
    # scipy dilates until nothing changes when iterations < 1
    return ndimage.binary_dilation(inside, iterations=int(pixels)) if pixels > 0 else inside


def binary_values_problem(array: np.ndarray) -> Optional[str]:
    """What keeps a numeric array from being a binary mask (0 for background, one other value for vessel), to follow
    "the mask …" in a message: NaN or infinite values, a negative value, several non-zero values; None when it is one."""
    if np.issubdtype(array.dtype, np.floating) and not np.all(np.isfinite(array)):
        return "contains NaN or infinite values"
    present = np.unique(array)
    if np.count_nonzero(present) > 1 or np.any(present < 0):
        shown = ", ".join(f"{v:g}" for v in present[:6].astype(float)) + (", …" if present.size > 6 else "")
        return f"is not binary (values {shown})"
    return None


#: a mask marking more of its image than this as vessel is refused: coronary trees cover about 1–15 % of an angiogram,
#: so a majority is the background (an inverted mask); its support would fill the volume
MAX_VESSEL_SHARE = 0.5


def binarise_mask(
    array: Any,
    detector_shape: Optional[Sequence[int]] = None,
    label: Optional[float] = None,
    source: str = "mask",
) -> np.ndarray:
    """Boolean vessel mask of a binary or label image (see the module docstring).

    ``label``: keep only pixels equal to this value; None: every non-zero pixel is vessel.
    ``detector_shape``: (rows, cols) the mask must have. ``source`` names the input in messages.
    """
    a = single_grey_image(array, f"{source}: data type {{dtype}} is not numeric; give a label image with numbers",
                          f"{source}: a colour image ({{channels}} channels with different values) is not a mask; "
                          "save the segmentation as a single-channel label image",
                          f"{source}: a mask is a 2-D image (rows, cols), got shape {{shape}}; give one view's mask")
    if detector_shape is not None:
        expected = tuple(int(v) for v in detector_shape)
        if a.shape != expected:
            hint = " (rows and columns are swapped: transpose the image)" if a.shape == expected[::-1] else ""
            raise MaskError(f"{source}: mask shape {a.shape} differs from the detector shape {expected} of its view"
                            f"{hint}; the mask must be drawn on the frame of that view, pixel for pixel")
    if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        raise MaskError(f"{source}: the mask contains NaN or infinite values; fix the image")
    if label is not None:
        present = np.unique(a)
        if not np.any(present == label):
            shown = ", ".join(f"{v:g}" for v in present[:10].astype(float)) + ("…" if present.size > 10 else "")
            raise MaskError(f"{source}: label {label:g} does not occur in the image (values present: {shown}); "
                            "choose one of those, or give no label to take every non-zero pixel as vessel")
        mask = a == label
    else:
        # Without a label only 0 and one other value are unambiguous: a grey frame or a label image
        # of several structures given by mistake would otherwise pass as a mask.
        problem = binary_values_problem(a)
        if problem:
            raise MaskError(f"{source}: the mask {problem}; give a mask with 0 for background and "
                            "one non-zero value (e.g. 1 or 255) for vessel, threshold it first, or choose the vessel "
                            "label of a label image")
        mask = a != 0
    if not mask.any():
        raise MaskError(f"{source}: the mask is empty (no vessel pixel); segment the vessels of this view first")
    if mask.all():
        raise MaskError(f"{source}: the mask covers the whole image: it marks every pixel as vessel, so it is not a "
                        "vessel segmentation (is it inverted, or was the background saved as non-zero? give the label of "
                        "the vessels)")
    if mask.mean() > MAX_VESSEL_SHARE:
        raise MaskError(f"{source}: the mask marks {100 * mask.mean():.1f} % of the image as vessel, more than its "
                        "background: it is inverted (the background saved as non-zero) or the background was segmented; "
                        "invert it so that vessel is non-zero and background 0, or give the label of the vessels")
    return mask


# --- angiogram mask pipeline -----------------------------------------------------------------------------
# Defaults when the frame's geometry is unknown: a 512² detector of about 20 cm and a magnification
# SID/SOD of 1.3 (a typical cardiac C-arm), i.e. about 0.3 mm per pixel at the isocenter.
DEFAULT_DETECTOR_SPACING_MM = 0.39
DEFAULT_MAGNIFICATION = 1.3
RIDGE_METHODS = ("sato", "frangi", "meijering")


@dataclass(frozen=True)
class AngioMaskSettings:
    """Parameters of ``angiogram_mask``; lengths in mm at the isocenter (the patient's scale)."""

    vessel_radius_mm: Tuple[float, float] = (0.5, 2.5)  # smallest and largest vessel radius to detect
    scales: int = 5  # ridge-filter scales, geometric between the two radii
    method: str = "sato"
    shutter_ratio: float = 4.0  # intensity ratio to the field beyond which an edge region is collimator
    high_noise_units: float = 6.0  # hysteresis: seeds above median + this × robust spread of the response
    low_noise_units: float = 2.0  # ... grown through pixels above median + this × spread
    silhouette_noise_units: float = 2.0  # vessel pixels: top-hat above median + this × its robust spread
    min_contrast: float = 0.0  # ... and dimming the frame by at least this (−log I: 0.04 is 4 %); for clean frames; 0: off
    min_vessel_contrast: float = 0.15  # a frame whose strongest ridges dim it by less (−log I) holds no vessel; 0: off
    min_length_mm: float = 6.0  # a component's centreline must be at least this long
    min_elongation: float = 3.0  # and length / mean width at least this (specks are round)
    min_field_fraction: float = 0.25  # refuse frames whose exposed field is smaller than this
    bright_vessels: bool = False  # the frame shows vessels bright (an inverted display): its grey levels are inverted first
    edge_fraction: float = 0.25  # >0: a vessel's edge where its contrast falls to this share of its centreline's
    edge_taper_radius_mm: Optional[float] = 1.0  # beyond this mask radius the share falls as (this / radius)²; None: constant
    edge_grow_mm: float = 0.45  # pixels this near the mask that reach the edge level (and the noise level) join; 0: trim only
    edge_max_radius_mm: Optional[float] = None  # the edge rule only on vessels this thin (mask radius); None: all

    def check(self) -> None:
        r0, r1 = (float(v) for v in self.vessel_radius_mm)
        if not 0 < r0 <= r1:
            raise MaskError(f"vessel_radius_mm must be (smallest, largest) positive radii, got {self.vessel_radius_mm}")
        if self.method not in RIDGE_METHODS:
            raise MaskError(f"method must be one of {', '.join(RIDGE_METHODS)}, got {self.method!r}")
        if int(self.scales) < 1:
            raise MaskError(f"scales must be 1 or more, got {self.scales}")
        if not self.shutter_ratio > 1:
            raise MaskError(f"shutter_ratio must be above 1, got {self.shutter_ratio}")
        if not 0 < self.low_noise_units <= self.high_noise_units:
            raise MaskError("hysteresis levels must satisfy 0 < low_noise_units <= high_noise_units, got "
                            f"{self.low_noise_units} and {self.high_noise_units}")
        if not 0 <= self.edge_fraction < 1:
            raise MaskError(f"edge_fraction must be in [0, 1) (0: no edge rule; 0.5: half the centreline's contrast), "
                            f"got {self.edge_fraction}")
        if self.edge_max_radius_mm is not None and not self.edge_max_radius_mm > 0:
            raise MaskError(f"edge_max_radius_mm must be a positive radius in mm (the edge rule acts on vessels up to it) "
                            f"or None (on every vessel), got {self.edge_max_radius_mm}")
        if self.edge_taper_radius_mm is not None and not self.edge_taper_radius_mm > 0:
            raise MaskError(f"edge_taper_radius_mm must be a positive radius in mm (the edge share falls beyond it) "
                            f"or None (the same share on every vessel), got {self.edge_taper_radius_mm}")
        if not 0 <= self.edge_grow_mm <= max(self.vessel_radius_mm):
            raise MaskError(f"edge_grow_mm must be between 0 (no growth) and the largest vessel radius "
                            f"{max(self.vessel_radius_mm):g} mm, got {self.edge_grow_mm}")
        if not (0 <= self.min_contrast < 1 and 0 <= self.min_vessel_contrast < 5):
            raise MaskError(f"min_contrast and min_vessel_contrast are contrasts in −log I (0.04: 4 % of the intensity; "
                            f"0: off), got {self.min_contrast} and {self.min_vessel_contrast}")
        if self.min_length_mm < 0 or self.min_elongation < 0:
            raise MaskError("min_length_mm and min_elongation must be 0 or more")


@dataclass
class AngioMask:
    """Result of ``segment_angiogram``: the mask and what it was made from."""

    mask: np.ndarray  # bool, vessel
    border: np.ndarray  # bool, collimator/shutter and image edge (never vessel)
    response: np.ndarray  # ridge response in noise units (0 in the border)
    parameters: Dict[str, Any]


def _frame_array(frame: Any) -> np.ndarray:
    a = single_grey_image(frame, "the frame has data type {dtype}, not numbers; give a grey-level X-ray frame",
                          "the frame is a colour image ({channels} channels that differ); X-ray frames are grey: give "
                          "the original grey-level frame (DICOM or a single-channel PNG/TIFF)",
                          "a frame is one 2-D image (rows, cols), got shape {shape}; pick one frame of the run")
    if min(a.shape) < 32:
        raise MaskError(f"the frame is {a.shape[0]}×{a.shape[1]} pixels, too small for vessel detection (32 or more a side)")
    image = a.astype(np.float64)
    if not np.all(np.isfinite(image)):
        raise MaskError("the frame contains NaN or infinite values; fix the image")
    return image


def _scales_px(settings: AngioMaskSettings, pixel_spacing_mm: Optional[Sequence[float]],
               magnification: Optional[float]) -> Tuple[float, List[float], Dict[str, Any]]:
    """Pixel size at the isocenter and the ridge-filter σ (pixels) from the physical radii."""
    notes = {}
    if pixel_spacing_mm is None:
        spacing, notes["pixel_spacing_source"] = DEFAULT_DETECTOR_SPACING_MM, "default (not given)"
    else:
        values = np.broadcast_to(np.asarray(pixel_spacing_mm, dtype=float), (2,))
        if not np.all(np.isfinite(values)) or np.any(values <= 0):
            raise MaskError(f"pixel spacing must be positive mm (row, col), got {pixel_spacing_mm}")
        spacing, notes["pixel_spacing_source"] = float(np.mean(values)), "given"
    if magnification is None:
        m, notes["magnification_source"] = DEFAULT_MAGNIFICATION, "default (not given)"
    else:
        m = float(magnification)
        if not (np.isfinite(m) and 1.0 <= m < 5.0):
            raise MaskError(f"magnification SID/SOD must be between 1 and 5, got {magnification}")
        notes["magnification_source"] = "given"
    iso_px_mm = spacing / m
    r0, r1 = (float(v) / iso_px_mm for v in settings.vessel_radius_mm)
    # A cylinder of radius r answers a Hessian filter best at σ ≈ r/√3 (Sato et al. 1998);
    # below one pixel the Hessian only sees noise.
    radii = np.geomspace(r0, r1, int(settings.scales)) if settings.scales > 1 else np.array([r0])
    sigmas = sorted({float(round(max(1.0, float(r) / np.sqrt(3.0)), 2)) for r in radii})
    notes.update({"detector_pixel_spacing_mm": spacing, "magnification": m, "isocenter_pixel_mm": iso_px_mm,
                  "vessel_radius_px": [r0, r1]})
    return iso_px_mm, sigmas, notes


def _border(log_image: np.ndarray, settings: AngioMaskSettings, opening_px: int, margin_px: int,
            min_contact_px: int) -> Tuple[np.ndarray, np.ndarray, Dict[str, Any]]:
    """(border, shutter) masks. The shutter is the part of the image, connected to its edge and
    wider than any vessel, whose intensity differs from the exposed field's by more than
    ``shutter_ratio`` (lead blades are dark, an overexposed or inverted edge bright) and that runs
    along the image edge; the border is
    the shutter and the image edge, widened by ``margin_px`` where the filters see the edge."""
    from skimage.measure import label as label_components

    smooth = ndimage.gaussian_filter(log_image, 2.0)
    rows, cols = smooth.shape
    # Collimators close around the centre of the image, which is always exposed.
    centre = smooth[3 * rows // 8: rows - 3 * rows // 8, 3 * cols // 8: cols - 3 * cols // 8]
    field_level = float(np.median(centre))
    off = np.abs(smooth - field_level) > np.log(settings.shutter_ratio)
    off = ndimage.binary_opening(off, structure=np.ones((2 * opening_px + 1,) * 2, bool))  # no thin vessels
    labels = label_components(off, connectivity=1)
    # A blade or iris lies along the image edge; a vessel leaving the field touches it only over its
    # width, so a region counts as shutter when it runs along the edge for more than
    # ``min_contact_px`` (twice the widest vessel).
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    contact = np.bincount(edge, minlength=labels.max() + 1)
    contact[0] = 0
    shutter = (contact >= min_contact_px)[labels]
    shutter = ndimage.binary_closing(shutter, structure=np.ones((3, 3), bool), iterations=2) | shutter
    border = ndimage.binary_dilation(shutter, structure=np.ones((2 * margin_px + 1,) * 2, bool)) if shutter.any() \
        else shutter.copy()
    border[:margin_px], border[-margin_px:], border[:, :margin_px], border[:, -margin_px:] = True, True, True, True
    info = {"shutter_fraction": float(shutter.mean()), "border_fraction": float(border.mean()),
            "border_margin_px": int(margin_px), "field_log_level": field_level}
    return border, shutter, info


#: the noise level (−log I) assumed at least, 0.1 % of the intensity (a signal-to-noise ratio of 1000): on a frame
#: without noise (simulated, subtracted, an 8-bit export of flat background) the measured level is 0 and every
#: grey-level step stood out by infinitely many noise units (bench/RESULTS.md §89)
MIN_NOISE_LOG = 1e-3


def _log_intensity(image: np.ndarray, high: float) -> np.ndarray:
    """−log I of a frame (``high``: its 99.5th percentile), floored so that zeros stay finite."""
    # Beer–Lambert: −log I is proportional to the path through iodine, and a change of exposure
    # or of the tissue in front only adds to it, which the background removal takes away.
    floor = max(1e-6 * max(abs(high), 1.0), float(np.percentile(image, 50)) * 1e-3)
    return -np.log(np.maximum(image - min(float(image.min()), 0.0), floor))


def _border_sizes(sigmas: Sequence[float], largest_radius_px: float) -> Tuple[int, Tuple[int, int, int]]:
    """The filters' margin (pixels) and ``_border``'s (opening, margin, contact) sizes."""
    margin_px = int(np.ceil(2.0 * max(sigmas))) + 2
    return margin_px, (max(1, int(round(0.5 * largest_radius_px))), margin_px, int(np.ceil(4.0 * largest_radius_px)))


def _clipped_ends(given: np.ndarray, field: np.ndarray) -> List[Tuple[str, float, float]]:
    """(end, value, share of the field) for the frame's highest and lowest value, each where the field holds it
    over less than half its pixels: most of the field at one value is its background, flat (a frame without noise:
    simulated, subtracted), not a part of it over- or underexposed."""
    ends = []
    for end, value in (("highest", float(given.max())), ("lowest", float(given.min()))):  # the values of the user's frame
        share = float(np.mean(given[field] == value)) if field.any() else 0.0
        if share < 0.5:
            ends.append((end, value, share))
    return ends


#: pixels at the frame's highest or lowest value over more than this share of the exposed field are taken as clipped
#: (``unseen_pixels``); a single brightest pixel of a noisy frame is not
MIN_UNSEEN_CLIPPED_SHARE = 0.001


def unseen_pixels(
    frame: Any,
    pixel_spacing_mm: Optional[Union[float, Sequence[float]]] = None,
    magnification: Optional[float] = None,
    settings: Optional[AngioMaskSettings] = None,
) -> np.ndarray:
    """Bool image, True where this frame cannot show a vessel, so that a mask's 0 there says nothing: the border
    ``segment_angiogram`` never marks (the collimator or shutter, and the filters' margin along it and along the image
    edge) and the pixels clipped at the frame's highest or lowest value (over- or underexposed), widened by the
    largest vessel radius. A mask made on it is 0 there because the view did not look, not because nothing is
    there."""
    s = settings if settings is not None else AngioMaskSettings()
    s.check()
    image = _frame_array(frame)
    lo, hi = np.percentile(image, [0.5, 99.5])
    if not hi > lo:
        raise MaskError("the frame is flat (the same value almost everywhere): it shows nothing; check the frame index")
    _, sigmas, geometry = _scales_px(s, pixel_spacing_mm, magnification)
    r_max_px = float(geometry["vessel_radius_px"][1])
    _, border_sizes = _border_sizes(sigmas, r_max_px)
    # the shutter is found by its distance from the field's level, either side: the polarity does not matter here
    border, _, _ = _border(-_log_intensity(image, hi), s, *border_sizes)
    unseen = border.copy()
    for _, value, share in _clipped_ends(image, ~border):
        if share > MIN_UNSEEN_CLIPPED_SHARE:
            unseen |= ndimage.binary_dilation(image == value, iterations=max(1, int(np.ceil(r_max_px))))
    return unseen


def _local_noise(image: np.ndarray, field: np.ndarray, block: int = 32) -> np.ndarray:
    """Smooth map of the noise standard deviation: robust (median) spread of the fine residual
    in blocks of the field, interpolated, ``MIN_NOISE_LOG`` at least; blocks without field or
    without noise (a flat background) take the nearest block's value."""
    residual = np.abs(image - ndimage.gaussian_filter(image, 1.0)).astype(np.float64)
    residual[~field] = np.nan
    rows, cols = image.shape
    nr, nc = -(-rows // block), -(-cols // block)
    padded = np.full((nr * block, nc * block), np.nan)
    padded[:rows, :cols] = residual
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks (border) are filled below
            level = np.nanmedian(padded.reshape(nr, block, nc, block).transpose(0, 2, 1, 3).reshape(nr, nc, -1), axis=2)
    missing = ~np.isfinite(level) | (level <= 0)
    if missing.all():
        return np.full(image.shape, MIN_NOISE_LOG)
    if missing.any():
        _, (ri, ci) = ndimage.distance_transform_edt(missing, return_indices=True)
        level = level[ri, ci]
    level = ndimage.zoom(level, (rows / nr, cols / nc), order=1, mode="nearest", grid_mode=True)[:rows, :cols]
    return np.maximum(level, MIN_NOISE_LOG)


#: more of the exposed field than this at the frame's highest or lowest value is warned of as clipped (over- or
#: underexposed); the realistic protocols' simulated frames hold up to 2.1 % at their top value
MAX_CLIPPED_FIELD_SHARE = 0.05

#: a frame of fewer grey levels is a mask or label image given as a frame (X-ray frames, even 8-bit exports, hold hundreds)
MIN_FRAME_GREY_LEVELS = 16


#: a frame whose fine structures reach further above than below by less than this ratio (``dark_vessel_asymmetry``)
#: is refused as showing its vessels bright, and one below ``DOUBTFUL_DARK_VESSEL_ASYMMETRY`` segmented with a warning:
#: frames with dark vessels measured 1.06–3.97 (the lowest processed for display), inverted ones 0.32–0.96
#: (bench/RESULTS.md §89)
MIN_DARK_VESSEL_ASYMMETRY = 0.8
DOUBTFUL_DARK_VESSEL_ASYMMETRY = 1.0
#: the polarity is read at two tails of the fine structures (% of the field each side): 1 % suits a tree, but a lone
#: tube or short segment covers less than that, and its 1 % tail held the tube's dark halo instead (a dark tube read
#: 0.38–0.98 and was refused); at 0.1 % its core speaks (bench/RESULTS.md §103a)
POLARITY_TAILS_PCT = (1.0, 0.1)
#: a frame either of whose tails reaches this asymmetry shows dark vessels, whatever the other says: dark lone tubes
#: measured 2.49 and over at 0.1 %, every inverted frame (trees, tubes, display-processed, real) 1.87 and under
CLEAR_DARK_VESSEL_ASYMMETRY = 2.2
#: the polarity is measured outside the broad regions along the edge this much brighter than the field
POLARITY_SHUTTER_RATIO = 1.3
#: the polarity is judged where the stronger side's fine structures reach this (−log I); those of frames without
#: contrast measured about 0.05 (bench/RESULTS.md §89)
MIN_POLARITY_CONTRAST = 0.1


def thin_structure_contrasts(log_image: np.ndarray, field: np.ndarray, largest_radius_px: float,
                             tail: float = 1.0) -> Tuple[float, float]:
    """How far the fine structures of ``−log I`` reach above and below its background, over the field: top ``tail`` %
    − median and median − bottom ``tail`` % of the image smoothed at 1 pixel less its smoothing at twice the largest
    vessel radius, in −log I. Vessels absorb, so in a frame with dark vessels the first is the larger (noise and soft
    tissue give about the same to both); a frame showing them bright has them in the second."""
    smooth = ndimage.gaussian_filter(log_image, 1.0)
    fine = (smooth - ndimage.gaussian_filter(smooth, max(2.0 * float(largest_radius_px), 2.0)))[field]
    low, median, high = (float(v) for v in np.percentile(fine, [tail, 50.0, 100.0 - tail]))
    return high - median, median - low


@dataclass(frozen=True)
class PolarityReading:
    """A frame's polarity as ``judge_polarity`` reads it: the asymmetry (dark over bright fine-structure contrast,
    ``thin_structure_contrasts``) at each tail of ``POLARITY_TAILS_PCT``, None where neither side reaches
    ``MIN_POLARITY_CONTRAST`` (that tail does not speak), and the verdict: "dark" (or not judged), "doubtful" or
    "bright"; ``deciding`` is the lowest speaking asymmetry, the one a doubtful or bright verdict rests on."""

    asymmetries: Tuple[Optional[float], ...]
    contrasts: Tuple[Tuple[float, float], ...]
    verdict: str
    deciding: Optional[float]


def judge_polarity(log_image: np.ndarray, field: np.ndarray, largest_radius_px: float) -> PolarityReading:
    """Whether the vessels of ``−log I`` (over ``field``) stand above its background (dark in the frame) or below it."""
    asymmetries, contrasts = [], []
    for tail in POLARITY_TAILS_PCT:
        dark, bright = thin_structure_contrasts(log_image, field, largest_radius_px, tail)
        contrasts.append((dark, bright))
        # a frame without contrast has only its background's thin structures, of either side: not judged (it is
        # refused as holding no vessel further on)
        speaks = max(dark, bright) >= MIN_POLARITY_CONTRAST
        asymmetries.append((dark / bright if bright > 0 else float("inf")) if speaks else None)
    spoken = [a for a in asymmetries if a is not None]
    deciding = min(spoken) if spoken else None
    if not spoken or max(spoken) >= CLEAR_DARK_VESSEL_ASYMMETRY or deciding >= DOUBTFUL_DARK_VESSEL_ASYMMETRY:
        verdict = "dark"
    else:
        verdict = "bright" if deciding < MIN_DARK_VESSEL_ASYMMETRY else "doubtful"
    return PolarityReading(tuple(asymmetries), tuple(contrasts), verdict, deciding)


def _disk_opening(image: np.ndarray, radius: int) -> np.ndarray:
    """Grey opening by a disk: unlike a square it follows curved edges (diaphragm, heart border)."""
    from skimage.morphology import disk, opening

    try:
        footprint = disk(radius, decomposition="crosses")  # scikit-image >= 0.20: fast
    except TypeError:
        footprint = disk(radius)
    return opening(image, footprint)


def _ridge(image: np.ndarray, sigmas: Sequence[float], method: str) -> np.ndarray:
    from skimage.filters import frangi, meijering, sato

    # Vessels are bright in the attenuation image (−log I): bright ridges.
    if method == "sato":
        return sato(image, sigmas=sigmas, black_ridges=False)
    if method == "frangi":
        return frangi(image, sigmas=sigmas, black_ridges=False)
    return meijering(image, sigmas=sigmas, black_ridges=False)


def centreline_radius_px(mask: np.ndarray) -> Tuple[np.ndarray, np.ndarray, Tuple[np.ndarray, np.ndarray]]:
    """The mask's centreline (its skeleton), the mask's radius (px) at the centreline pixel nearest to every
    pixel, and that pixel's (rows, cols) per pixel: a border pixel of a thick vessel reads the thick vessel's
    radius, not its own distance to the border."""
    from skimage.morphology import skeletonize

    mask = np.asarray(mask, bool)
    centreline = skeletonize(mask)
    _, (rows, cols) = ndimage.distance_transform_edt(~centreline, return_indices=True)
    radius = ndimage.distance_transform_edt(mask)[rows, cols]
    return centreline, radius, (rows, cols)


def _redraw_edges(mask: np.ndarray, contrast: np.ndarray, fraction: float, field: np.ndarray,
                  taper_radius_px: Optional[float] = None, grow_px: float = 0.0,
                  max_radius_px: Optional[float] = None, grow_floor: float = 0.0) -> np.ndarray:
    """The mask's border redrawn where the contrast reaches its edge level: ``fraction`` of the
    contrast on the nearest point of the mask's centreline, times (``taper_radius_px`` / r)² where
    the mask's radius r there is larger. Mask pixels below it go (the centreline always stays: no
    vessel is cut); field pixels up to ``grow_px`` outside the mask that reach it and whose contrast
    exceeds ``grow_floor`` (step 6's noise level: no noise grows onto a vessel) join. With
    ``max_radius_px``, nothing changes where r exceeds it."""
    centreline, radius, (rows, cols) = centreline_radius_px(mask)
    # the centreline's contrast, taken as the largest within one pixel (a skeleton drawn off the ridge)
    peak = ndimage.maximum_filter(contrast, size=3)[rows, cols]
    share = np.full(mask.shape, float(fraction))
    if taper_radius_px is not None:
        share *= np.minimum(1.0, (taper_radius_px / np.maximum(radius, 1e-6)) ** 2)
    reaches = contrast >= share * peak
    candidates = mask
    if grow_px > 0:
        candidates = mask | ((ndimage.distance_transform_edt(~mask) <= grow_px) & field & (contrast > grow_floor))
    redrawn = (candidates & reaches) | centreline
    if max_radius_px is not None:
        redrawn = np.where(radius > max_radius_px, mask, redrawn)
    return redrawn


def _component_shape(mask: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per 8-connected component: label image, area, centreline length (skeleton pixels), length²/area."""
    from skimage.measure import label as label_components
    from skimage.morphology import skeletonize

    labels, n = label_components(mask, connectivity=2, return_num=True)
    area = np.bincount(labels.ravel(), minlength=n + 1).astype(float)
    length = np.bincount(labels[skeletonize(mask)].ravel(), minlength=n + 1).astype(float)
    elongation = np.divide(length**2, area, out=np.zeros_like(area), where=area > 0)
    return labels, area, length, elongation


#: the edge rule's share on frames processed for display (step 8; bench/RESULTS.md §79: 0 and 0.05 measured beside it)
DISPLAY_EDGE_FRACTION = 0.02


def frame_processed_for_display(relationship: Optional[str]) -> bool:
    """Whether a frame of this Pixel Intensity Relationship (0028,1040) was processed for display: any value but
    LIN and LOG (DISP, vendors' terms such as GE's DRM); None (not known, e.g. an array or a PNG) is not."""
    from .dicom.intensity import LOG_INTENSITY
    from .evidence import LINEAR_INTENSITY

    value = str(relationship).strip().upper() if relationship is not None else ""
    return value not in ("", LINEAR_INTENSITY, LOG_INTENSITY)


def mask_settings_for_intensity(relationship: Optional[str],
                                settings: Optional[AngioMaskSettings] = None) -> AngioMaskSettings:
    """``settings`` (default: ``AngioMaskSettings()``) for a frame of this Pixel Intensity Relationship: the edge
    rule's share ``DISPLAY_EDGE_FRACTION`` where the frame was processed for display (module docstring, step 8)."""
    base = settings if settings is not None else AngioMaskSettings()
    return replace(base, edge_fraction=DISPLAY_EDGE_FRACTION) if frame_processed_for_display(relationship) else base


def segment_angiogram(
    frame: Any,
    pixel_spacing_mm: Optional[Union[float, Sequence[float]]] = None,
    magnification: Optional[float] = None,
    settings: Optional[AngioMaskSettings] = None,
) -> AngioMask:
    """Vessel mask of one X-ray angiography frame (intensity, vessels dark); see the module docstring.

    ``pixel_spacing_mm``: detector pixel size (row, col) or one value; ``magnification``: SID/SOD.
    Absent values take typical ones (reported in the parameters). Raises ``MaskError`` naming
    the problem for frames it cannot segment (flat, mostly collimator, no vessel, colour…).
    """
    from skimage.filters import apply_hysteresis_threshold

    s = settings if settings is not None else AngioMaskSettings()
    s.check()
    started = time.perf_counter()
    image = _frame_array(frame)
    given = image
    if s.bright_vessels:
        # about robust levels: a hot pixel or a burned-in annotation at the top would otherwise lift the background and
        # shrink the vessels' share of the intensity, which −log I measures
        low, high = (float(v) for v in np.percentile(image, [0.1, 99.9]))
        image = low + high - np.clip(image, low, high)
    iso_px_mm, sigmas, geometry = _scales_px(s, pixel_spacing_mm, magnification)
    lo, hi = np.percentile(image, [0.5, 99.5])
    if not hi > lo:
        raise MaskError("the frame is flat (the same value almost everywhere): there is nothing to segment; "
                        "check the frame index and that the run holds images")
    levels = np.unique(image).size
    if levels < MIN_FRAME_GREY_LEVELS:
        raise MaskError(f"the frame holds only {levels} grey levels: it is a mask or a label image, not an X-ray frame "
                        "(those hold hundreds); give the frame the vessels were seen in, or use the mask as a mask "
                        "(reconstruct --mask)")
    log_image = _log_intensity(image, hi)
    r_max_px = float(geometry["vessel_radius_px"][1])
    margin_px, border_sizes = _border_sizes(sigmas, r_max_px)
    border, _, border_info = _border(-log_image, s, *border_sizes)
    field = ~border
    if field.mean() < s.min_field_fraction and not border_info["shutter_fraction"] > 0:
        raise MaskError(f"the frame is {image.shape[0]}×{image.shape[1]} pixels: the filters' margin of {margin_px} pixels "
                        f"along its edges, for vessels up to {s.vessel_radius_mm[1]:g} mm at "
                        f"{iso_px_mm:.3f} mm per pixel, leaves only {100 * field.mean():.0f}% of it; give the whole frame "
                        "(not a crop), or check its pixel spacing and magnification")
    if field.mean() < s.min_field_fraction:
        raise MaskError(f"the exposed field is only {100 * field.mean():.0f}% of the frame (the rest is collimator or "
                        f"image edge, less than {100 * s.min_field_fraction:.0f}% is left): open the collimator or "
                        "choose another frame/run")
    # Fill the border with the nearest field values so the filters see no shutter edge.
    _, (ri, ci) = ndimage.distance_transform_edt(border, return_indices=True)
    filled = log_image[ri, ci]
    # The polarity is read away from broad regions along the edge brighter than the field, even a little: an inverted
    # export's collimator is white, only 1.5–2× the field (under shutter_ratio), and the field's corners against it
    # would stand out as bright fine structures. (In a frame the right way up these are lungs: nothing is lost.)
    brighter_only = np.maximum(-log_image, float(np.median(-log_image[field])))
    bright_border, _, _ = _border(brighter_only, replace(s, shutter_ratio=POLARITY_SHUTTER_RATIO), *border_sizes)
    polarity_field = field & ~bright_border
    if polarity_field.sum() >= 1000:  # filled as the filters' image is, so that no plateau's edge reaches in
        _, (pi, pc) = ndimage.distance_transform_edt(~polarity_field, return_indices=True)
        polarity_image = log_image[pi, pc]
    else:
        polarity_field, polarity_image = field, filled
    polarity = judge_polarity(polarity_image, polarity_field, r_max_px)
    (dark_contrast, bright_contrast), (fine_dark, fine_bright) = polarity.contrasts
    asymmetry = dark_contrast / bright_contrast if bright_contrast > 0 else float("inf")
    doubtful = polarity.verdict == "doubtful" and not s.bright_vessels
    if polarity.verdict == "bright":
        if s.bright_vessels:
            raise MaskError("bright_vessels (segment --bright-vessels) was given, but the vessels of this frame are dark "
                            "already, as in a raw X-ray frame: inverted they look bright; leave it out")
        raise BrightVesselsError(f"the vessels of this frame look bright, not dark: its bright fine structures stand "
                        f"{1 / max(polarity.deciding, 1e-6):.1f}× further from the background than its dark ones (an inverted "
                        "display or export, or a subtracted frame saved with bright vessels?); vessels absorb X-rays and "
                        "are dark in a raw frame: invert its grey levels (segment --bright-vessels; in Python "
                        "AngioMaskSettings(bright_vessels=True)), or give the raw frame")
    warnings = []
    for end, value, clipped in _clipped_ends(given, field):
        if MAX_CLIPPED_FIELD_SHARE < clipped:
            warnings.append(f"{100 * clipped:.0f} % of the exposed field is clipped at the frame's {end} value "
                            f"({value:g}): vessels there cannot be seen, so the mask misses them and a reconstruction "
                            "takes them as absent; choose a frame or run exposed without it, or paint the vessels there by hand "
                            "where you know them")
    if doubtful:
        warnings.append(f"the frame's dark and bright fine structures stand out about as far (asymmetry {polarity.deciding:.2f}; "
                        "frames with dark vessels measure above 1): if its vessels look bright in the overlay, segment it "
                        "with bright_vessels (segment --bright-vessels)")
    # Background: grey opening by a disk wider than the widest vessel (vessels are bright in −log I)
    # of the lightly smoothed image; subtracting it removes tissue, ribs, diaphragm and exposure.
    # Only the opening's blockiness is smoothed away: a window-wide smoothing bends at kinks
    # (the field's edge) and made false ridges there.
    window = 2 * int(np.ceil(1.5 * r_max_px)) + 3
    base = _disk_opening(ndimage.gaussian_filter(filled, 1.0), window // 2)
    background = ndimage.gaussian_filter(base, 2.0)
    # Quantum noise is larger in −log I where fewer photons arrive (behind the diaphragm, the
    # spine): the top-hat is divided by a local noise level so that thresholds mean the same
    # everywhere.
    noise = _local_noise(filled, field)
    tophat = (filled - background) / noise
    response = np.nan_to_num(_ridge(tophat, sigmas, s.method), nan=0.0)
    values = response[field]
    median = float(np.median(values))
    spread = 1.4826 * float(np.median(np.abs(values - median)))
    if not spread > 0:
        spread = float(np.std(values))
    if not spread > 0:
        raise MaskError("the ridge filter gives the same response everywhere in the field: the frame holds no "
                        "vessel-like structure (flat or saturated frame?)")
    normalised = np.where(field, (response - median) / spread, 0.0)
    high, low = s.high_noise_units, s.low_noise_units
    raw = apply_hysteresis_threshold(normalised, low, high) & field
    # The ridge response spreads beyond the vessel at the large scales: the silhouette is where
    # the (lightly smoothed) top-hat itself stands out of its noise.
    contrast = ndimage.gaussian_filter(tophat, 1.0)
    c_values = contrast[field]
    c_median = float(np.median(c_values))
    c_spread = 1.4826 * float(np.median(np.abs(c_values - c_median))) or float(np.std(c_values)) or 1.0
    raw &= (contrast - c_median) / c_spread > s.silhouette_noise_units
    # Noise units mean nothing where there is little noise: on a clean frame what the background removal leaves of
    # ribs and the diaphragm stands many noise units high. The tree's own contrast (−log I, i.e. the share of the
    # intensity its iodine takes) sets a second level, and a frame whose strongest ridges are faint has no vessel.
    log_contrast = ndimage.gaussian_filter(filled - background, 1.0)
    log_contrast -= float(np.median(log_contrast[field]))
    strongest = float(np.percentile(log_contrast[raw], 95)) if raw.any() else 0.0
    if s.min_vessel_contrast > 0 and raw.any() and strongest < s.min_vessel_contrast:
        raise MaskError(f"no vessel found: the strongest ridges of the frame dim it by only {100 * strongest:.1f} % "
                        f"(a contrast-filled coronary takes {100 * s.min_vessel_contrast:.0f} % or more); a frame "
                        "without contrast, or a wrong frame index? choose the frame with contrast")
    faint = log_contrast < s.min_contrast
    raw &= ~faint
    labels, area, length, elongation = _component_shape(raw)
    min_length_px = s.min_length_mm / iso_px_mm
    keep = (length >= min_length_px) & (elongation >= s.min_elongation)
    keep[0] = False
    mask = keep[labels]
    if s.edge_fraction > 0 and mask.any():
        cleaned = mask
        mask = _redraw_edges(mask, contrast - c_median, s.edge_fraction, field & ~faint,
                             None if s.edge_taper_radius_mm is None else s.edge_taper_radius_mm / iso_px_mm,
                             s.edge_grow_mm / iso_px_mm,
                             None if s.edge_max_radius_mm is None else s.edge_max_radius_mm / iso_px_mm,
                             s.silhouette_noise_units * c_spread)
        # the growth reaches up to edge_grow_mm from the mask: pixels it adds that touch no kept vessel are specks
        from skimage.measure import label as label_components

        pieces = label_components(mask, connectivity=2)
        touching = np.unique(pieces[mask & cleaned])
        mask &= np.isin(pieces, touching[touching > 0])
    if not mask.any():
        raise MaskError("no vessel found: no elongated structure of at least "
                        f"{s.min_length_mm:g} mm stands out of the noise (a frame without contrast, or a wrong "
                        "frame index?); choose the frame with contrast, or lower high_noise_units")
    if mask.mean() > 0.5:
        raise MaskError(f"{100 * mask.mean():.0f}% of the frame was marked vessel, which is not a vessel tree; "
                        "check that vessels are dark in this image (an inverted frame?)")
    kept = np.flatnonzero(keep)
    parameters = {
        "pipeline": "angiogram_mask",
        **{k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(s).items()},
        **geometry,
        "sigmas_px": list(sigmas),
        **border_info,
        "background_window_px": int(window),
        "response_median": median,
        "response_spread": spread,
        "hysteresis_high": median + high * spread,
        "hysteresis_low": median + low * spread,
        "silhouette_level": c_median + s.silhouette_noise_units * c_spread,
        "strongest_contrast": strongest,
        "dark_vessel_asymmetry": asymmetry,
        # at the finer tail, where a lone tube speaks; "polarity_judged_at_pct": the tails strong enough to be read
        "dark_vessel_asymmetry_fine_tail": fine_dark / fine_bright if fine_bright > 0 else float("inf"),
        "polarity_judged_at_pct": [t for t, a in zip(POLARITY_TAILS_PCT, polarity.asymmetries) if a is not None],
        # "doubtful": the warning below DOUBTFUL_DARK_VESSEL_ASYMMETRY was given (the Slicer module then asks)
        "polarity": "inverted as told" if s.bright_vessels else ("doubtful" if doubtful else "dark vessels"),
        "thin_dark_contrast": dark_contrast,
        "thin_bright_contrast": bright_contrast,
        "min_length_px": float(min_length_px),
        "components_before_cleaning": int(area.size - 1),
        "components": int(ndimage.label(mask, structure=np.ones((3, 3), bool))[1]),  # 8-connected, as mask_checks counts
        "component_lengths_mm": [round(float(length[k] * iso_px_mm), 1) for k in kept],
        "vessel_fraction": float(mask.mean()),
        "warnings": warnings,
        "seconds": round(time.perf_counter() - started, 3),
    }
    return AngioMask(mask, border, normalised.astype(np.float32), parameters)


def angiogram_mask(
    frame: Any,
    pixel_spacing_mm: Optional[Union[float, Sequence[float]]] = None,
    magnification: Optional[float] = None,
    settings: Optional[AngioMaskSettings] = None,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """``(mask, parameters)`` of ``segment_angiogram`` ."""
    result = segment_angiogram(frame, pixel_spacing_mm, magnification, settings)
    return result.mask, result.parameters


# --- pictures and files of a segmentation --------------------------------------------------------------
def display_frame(frame: Any) -> np.ndarray:
    """8-bit grey picture of a frame, scaled between its 1st and 99th percentiles."""
    image = np.asarray(frame, dtype=np.float64)
    lo, hi = np.percentile(image, [1.0, 99.0])
    scale = (hi - lo) if hi > lo else 1.0
    return np.rint(255.0 * np.clip((image - lo) / scale, 0.0, 1.0)).astype(np.uint8)


def overlay_rgb(frame: Any, mask: np.ndarray, border: Optional[np.ndarray] = None) -> np.ndarray:
    """RGB picture of the frame with the mask's outline in red and the border's outline in blue."""
    from skimage.segmentation import find_boundaries

    grey = display_frame(frame)
    rgb = np.dstack([grey, grey, grey])
    if border is not None and border.any():
        rgb[find_boundaries(border, mode="inner")] = (40, 120, 255)
    rgb[find_boundaries(mask, mode="inner")] = (255, 30, 30)
    return rgb


def segmentation_paths(out: PathLike) -> Dict[str, Path]:
    """The files ``write_segmentation`` writes for ``out`` = ``NAME.png``."""
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise MaskError(f"--out {out}: the mask is written as PNG; give a name ending in .png")
    stem = out.with_suffix("")
    return {"mask": out, "frame": Path(f"{stem}_frame.png"), "overlay": Path(f"{stem}_overlay.png"),
            "parameters": Path(f"{stem}.json")}


def write_segmentation(out: PathLike, frame: Any, result: AngioMask, source: Dict[str, Any],
                       overwrite: bool = False) -> Dict[str, Path]:
    """Mask (0/255 PNG), the frame used (16-bit PNG of its values when they are whole numbers in
    range, else its 8-bit picture), the overlay PNG and a JSON of the parameters and the source."""
    import imageio.v3 as iio

    from .io import write_json, write_mask_png

    paths = segmentation_paths(out)
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise MaskError(f"{', '.join(existing)} exist(s); choose another --out or add --overwrite")
    paths["mask"].parent.mkdir(parents=True, exist_ok=True)
    image = np.asarray(frame, dtype=np.float64)
    exact = bool(np.all(image == np.rint(image)) and image.min() >= 0 and image.max() <= 65535)
    stored = image.astype(np.uint16) if exact else display_frame(image)
    write_mask_png(paths["mask"], result.mask)
    iio.imwrite(paths["frame"], stored, extension=".png")
    iio.imwrite(paths["overlay"], overlay_rgb(image, result.mask, result.border), extension=".png")
    write_json(paths["parameters"], {"source": source, "frame_png": "frame values" if exact else "8-bit picture",
                                     "parameters": result.parameters})
    return paths
