"""Line-integral evidence from the frames: how much vessel each ray crossed, read off the angiogram.

Why
    A binary mask says only *whether* a ray met vessel. Where one view's ray crosses a vessel, the
    optimiser may add vessel anywhere along it at no cost in that view — this is where ghosts of
    what the other view's mask missed or widened settle (bench/RESULTS.md §12b, §15). The frame
    says *how much* vessel the ray crossed: with it as the occupancy target, a ghost in the shadow
    of a real vessel adds path length the frame does not show.

Model (Beer–Lambert, as ``angiogram.py`` simulates and real cine frames record)
    −log I = μ·L + B, L the mm of contrast-filled vessel along the ray, μ its attenuation per mm,
    B the tissue and exposure, smooth at the scale of a vessel. Per view:

    1. absorbance a = −log I;
    2. the background B̂: a averaged around the vessels — outside the mask widened by
       ``clearance_px`` — by a normalised Gaussian of ``background_scale_mm``, i.e. the tissue under
       a vessel interpolated from beside it;
    3. μ: the blurred-circular-lumen model of ``lumen_profile`` fitted across the thick
       vessels of the mask (skeleton points whose half-width is ≥ ``min_radius_mm`` at the
       isocenter, away from junctions); its amplitude is absorbance per detector-mm of chord, so
       μ = amplitude · magnification. The median over the profiles. The profile's shape fixes the
       radius, so μ does not depend on the mask's width (which is off by tenths of a mm);
    4. optionally (``deblur_iterations`` > 0) max(a − B̂, 0) restored by Richardson–Lucy against the
       detector's Gaussian blur (``psf_sigma_mm``): the frame spreads a thin vessel's path length over
       its neighbours, which a rendering does not;
    5. L̂ = max(a − B̂, 0) / μ on the mask widened by ``reach_px`` (its borders are a pixel off
       either way), 0 elsewhere: outside the vessels the frame's noise would read as faint vessel
       everywhere.

Units: detector mm for the frame's lengths (pixel spacing), mm of vessel for L̂.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage

from .lumen_profile import DEFAULT_PSF_SIGMA_MM, absorbance, fit_lumen, mean_profile
from .geometry import CArmView
from .masks import widened_mask


class EvidenceError(ValueError):
    """The frames cannot give line-integral evidence (the message says why and what to do)."""


@dataclass(frozen=True)
class EvidenceSettings:
    reach_px: int = 2  # the mask is widened by this many pixels before the evidence is kept
    clearance_px: int = 4  # the background is read this far outside the mask
    background_scale_mm: float = 5.0  # Gaussian σ (detector mm) of the background interpolation
    min_radius_mm: float = 0.8  # profiles for μ only across vessels at least this thick (radius at the isocenter)
    max_profiles: int = 150
    min_profiles: int = 5
    psf_sigma_mm: float = DEFAULT_PSF_SIGMA_MM
    deblur_iterations: int = 0  # Richardson–Lucy iterations against psf_sigma_mm before L̂ is read (0: none)


@dataclass
class ViewEvidence:
    line_integral_mm: np.ndarray  # (rows, cols) float32: L̂
    attenuation_per_mm: float  # μ
    info: Dict[str, Any]


#: DICOM Pixel Intensity Relationship (0028,1040) of frames whose grey levels follow the X-ray intensity:
#: PS3.3's LIN. A LOG frame holds a logarithm of it (the DICOM reader brings it to a linear scale first,
#: ``dicom.intensity``), a DISP frame (and a vendor's own term, e.g. GE's DRM) has been processed for
#: display — windowed, contrast-managed, edge-enhanced — so −log of its grey level is no absorbance and no
#: path length can be read from it.
LINEAR_INTENSITY = "LIN"
#: … and of frames processed for display (windowed, contrast-managed, edge-enhanced)
DISPLAY_INTENSITY = "DISP"


def unreadable_intensity(relationship: Optional[str]) -> Optional[str]:
    """Why a frame of this Pixel Intensity Relationship gives no path lengths, or None where it does: LIN,
    or not known (frames handed over as arrays — simulated ones, the user's own images)."""
    if relationship is None or not str(relationship).strip():
        return None
    value = str(relationship).strip().upper()
    if value == LINEAR_INTENSITY:
        return None
    meaning = {"LOG": "a logarithm of the X-ray intensity", "DISP": "processed for display"}.get(
        value, "a vendor's processed image")
    why = (f"its Pixel Intensity Relationship (0028,1040) is {value} ({meaning}), not LIN: its grey levels are not "
           "proportional to the X-ray intensity, so no path length can be read from them")
    if value not in (LINEAR_INTENSITY, "LOG", "DISP"):  # a vendor's term (GE's DRM), or a user's misspelling
        why += (f" ({value} is none of the standard's terms LIN, LOG, DISP, so it is taken as a vendor's own; give "
                "'LIN' if the frame's grey levels follow the X-ray intensity)")
    if value == "LOG":  # handed over as stored; the DICOM readers linearise such frames
        why += (" (read the run with SDFCARLib.dicom.load_xa, or pass the stored frame through "
                "SDFCARLib.dicom.intensity.linearised: either brings LOG frames to a linear scale)")
    return why


#: the brightest grey level of an 8-bit frame. Raw detector frames are 10–16 bit; a frame of 8-bit values whose
#: relationship nobody gave was, as good as always, windowed for display (the GE runs at hand are DISP/DRM at 8 bits;
#: a viewer's PNG or JPEG export is 8 bits), and −log of such grey levels reads path lengths half as thick as the
#: masks (bench/RESULTS.md §76a)
EIGHT_BIT_MAX = 255
#: the share of negative pixels past which a frame is not read as detector intensities: a raw frame's offset
#: correction leaves a few noisy pixels of the collimated border below 0, signed or shifted storage half of them
MAX_NEGATIVE_SHARE = 0.01


def is_eight_bit_frame(frame: np.ndarray) -> bool:
    """Whether a frame holds 8-bit grey levels (uint8, or whole numbers 0–255), more than two of them."""
    a = np.asarray(frame)
    if a.size == 0 or a.dtype.kind not in "uif" or is_binary_image(a):
        return False
    if a.dtype == np.uint8:
        return True
    if a.min() < 0 or a.max() > EIGHT_BIT_MAX:
        return False
    return a.dtype.kind != "f" or bool(np.array_equal(a, np.round(a)))


def assumed_relationship(frame: Optional[np.ndarray], relationship: Optional[str], what: str = "the frame"
                         ) -> Tuple[Optional[str], Optional[str]]:
    """(the relationship a frame is read with, a note where it was assumed): a known one as it is; an 8-bit frame
    whose relationship is not known is taken as processed for display (DISP; ``EIGHT_BIT_MAX``), other frames of
    unknown relationship are read as before (as linear)."""
    if relationship is not None and str(relationship).strip():
        return relationship, None
    if frame is None or not is_eight_bit_frame(frame):
        return relationship, None
    return DISPLAY_INTENSITY, (
        f"{what}: the frame holds 8-bit grey levels and nothing says how they were made (it was not read from a "
        "DICOM run): it is taken as processed for display (DISP) — no path lengths are read off it and its mask's "
        "edge is not trimmed — because raw detector frames are 10–16 bit. If it does hold linear intensities, say so: "
        "reconstruct(…, frame_intensity=['LIN', …]), segment --image-intensity LIN, or in Slicer the view's "
        "Grey levels box: Linear")


def assumed_frame_intensity(frames: Optional[Sequence[Optional[np.ndarray]]],
                            frame_intensity: Optional[Sequence[Optional[str]]]
                            ) -> Tuple[Optional[List[Optional[str]]], List[str]]:
    """(per view the relationship the frames are read with, the notes where one was assumed:
    ``assumed_relationship``); ``frame_intensity`` unchanged where nothing was assumed (or the counts disagree,
    which the fit refuses)."""
    if frames is None or (frame_intensity is not None and len(frame_intensity) != len(frames)):
        return (None if frame_intensity is None else list(frame_intensity)), []
    given = list(frame_intensity) if frame_intensity is not None else [None] * len(frames)
    read = [assumed_relationship(f, r, f"view {n}") for n, (f, r) in enumerate(zip(frames, given), start=1)]
    notes = [note for _, note in read if note]
    if not notes:
        return (None if frame_intensity is None else given), []
    return [r for r, _ in read], notes


def is_binary_image(image: np.ndarray) -> bool:
    """Two grey levels or fewer: a mask shown as a frame (the sample case does), not a recorded X-ray
    frame; there is no intensity profile to read. An image with NaN or infinite pixels is none (np.unique would
    count all its NaNs as one level)."""
    image = np.asarray(image)
    return bool(np.all(np.isfinite(image))) and np.unique(image).size <= 2


def absorbance_above_background(frame: np.ndarray, mask: np.ndarray, pixel_spacing_mm: Sequence[float],
                                settings: EvidenceSettings = EvidenceSettings()) -> np.ndarray:
    """a − B̂ (steps 1–2 of the module docstring), everywhere in the image."""
    absorbances = absorbance(frame)
    outside = ~widened_mask(mask, settings.clearance_px)
    if not outside.any():
        raise EvidenceError("the mask covers the whole frame: no background left to subtract")
    sigma_px = [settings.background_scale_mm / s for s in pixel_spacing_mm]
    weight = ndimage.gaussian_filter(outside.astype(np.float64), sigma_px, mode="nearest")
    total = ndimage.gaussian_filter(np.where(outside, absorbances, 0.0), sigma_px, mode="nearest")
    # Far from any background pixel the weight underflows; the nearest estimate is used there.
    background = total / np.maximum(weight, 1e-12)
    thin = weight < 1e-6
    if thin.any():
        _, (ri, ci) = ndimage.distance_transform_edt(thin, return_indices=True)
        background = background[ri, ci]
    return absorbances - background


def deblurred(image: np.ndarray, pixel_spacing_mm: Sequence[float], psf_sigma_mm: float, iterations: int) -> np.ndarray:
    """``image`` (non-negative) restored by ``iterations`` Richardson–Lucy steps against a Gaussian blur of
    ``psf_sigma_mm`` (detector mm); few steps, because each one also sharpens the frame's noise."""
    from skimage.restoration import richardson_lucy

    sigma_px = np.asarray([psf_sigma_mm / s for s in pixel_spacing_mm], np.float64)
    half = np.ceil(4.0 * sigma_px).astype(int)
    rows, cols = (np.arange(-h, h + 1) for h in half)
    kernel = np.outer(np.exp(-0.5 * (rows / sigma_px[0]) ** 2), np.exp(-0.5 * (cols / sigma_px[1]) ** 2))
    # positional: the count's keyword changed name in scikit-image 0.19 (iterations → num_iter)
    return richardson_lucy(np.asarray(image, np.float64), kernel / kernel.sum(), iterations, False, 1e-12)


def border_trimmed_mask(mask: np.ndarray, line_integral_mm: np.ndarray, min_path_mm: float,
                        smoothing_px: float = 1.0, centre_fraction: float = 0.0) -> np.ndarray:
    """The mask without the pixels whose path length, read off the frame (``view_evidence``) and smoothed
    by a Gaussian of ``smoothing_px``, is below ``min_path_mm``; the mask's centreline always stays.
    ``centre_fraction`` > 0 lowers a pixel's threshold to that fraction of the smoothed path length at
    the nearest centreline pixel where that is less: a thin vessel's whole blurred profile lies below
    an absolute threshold, and its true border with it.

    A segmentation's border falls where a threshold met the blurred, noisy edge: a pixel or so outside
    the lumen on thin vessels. Those pixels show little path length; the mask's own thinning keeps a
    vessel that is faint along its whole width."""
    from skimage.morphology import skeletonize

    mask = np.asarray(mask, bool)
    if np.shape(line_integral_mm) != mask.shape:
        raise ValueError(f"the path lengths have shape {np.shape(line_integral_mm)} but the mask {mask.shape}")
    if not min_path_mm > 0:
        raise ValueError(f"min_path_mm must be positive, got {min_path_mm}")
    if not 0 <= centre_fraction < 1:
        raise ValueError(f"centre_fraction must lie in [0, 1), got {centre_fraction}")
    smoothed = ndimage.gaussian_filter(np.asarray(line_integral_mm, np.float64), smoothing_px)  # σ 0: unchanged
    centreline = skeletonize(mask)
    threshold: Any = min_path_mm
    if centre_fraction > 0 and centreline.any():
        _, (rows, cols) = ndimage.distance_transform_edt(~centreline, return_indices=True)
        threshold = np.minimum(min_path_mm, centre_fraction * smoothed[rows, cols])
    return (mask & (smoothed >= threshold)) | centreline


def _skeleton_directions(skeleton: np.ndarray, spacing: np.ndarray, points: np.ndarray, half_window: int = 3) -> np.ndarray:
    """Unit tangents (row, col in mm) of the skeleton at ``points`` from the principal axis of its pixels nearby."""
    tangents = np.zeros((len(points), 2))
    for n, (r, c) in enumerate(points):
        r0, c0 = max(r - half_window, 0), max(c - half_window, 0)
        rr, cc = np.nonzero(skeleton[r0:r + half_window + 1, c0:c + half_window + 1])
        xy = np.stack([(rr + r0 - r) * spacing[0], (cc + c0 - c) * spacing[1]], axis=1)
        _, _, vt = np.linalg.svd(xy - xy.mean(axis=0), full_matrices=False)
        tangents[n] = vt[0]
    return tangents


def estimate_attenuation_per_mm(frame: np.ndarray, mask: np.ndarray, view: CArmView,
                                settings: EvidenceSettings = EvidenceSettings()) -> Dict[str, Any]:
    """μ (per mm of vessel) from lumen fits across the mask's thick vessels (step 3); raises
    ``EvidenceError`` when fewer than ``settings.min_profiles`` fits succeed."""
    from skimage.morphology import skeletonize

    spacing = np.asarray(view.pixel_spacing_mm, float)
    magnification = float(view.magnification)
    skeleton = skeletonize(mask)
    half_width = ndimage.distance_transform_edt(mask, sampling=spacing)  # detector mm
    neighbours = ndimage.convolve(skeleton.astype(np.int32), np.ones((3, 3), np.int32), mode="constant") - 1
    candidates = skeleton & (neighbours == 2) & (half_width >= settings.min_radius_mm * magnification)
    points = np.argwhere(candidates)
    if len(points) > settings.max_profiles:  # evenly over the candidates: deterministic
        points = points[np.linspace(0, len(points) - 1, settings.max_profiles).round().astype(int)]
    absorbances = absorbance(frame)
    tangents = _skeleton_directions(skeleton, spacing, points)
    pixel_mm = float(spacing.min())
    # A pixel averages the image over its width: a box of variance p²/12 on top of the detector blur.
    sigma = float(np.hypot(settings.psf_sigma_mm, pixel_mm / np.sqrt(12.0)))
    values = []
    for (r, c), (tr, tc) in zip(points, tangents):
        guess = float(half_width[r, c])
        half = 2.0 * guess + 4.0 * sigma + 1.0
        x = np.arange(-half, half + pixel_mm / 4, pixel_mm / 2)
        profile = mean_profile(absorbances, r, c, (tr, tc), (-tc, tr), x, spacing)
        if profile is None:
            continue
        fitted = fit_lumen(x, profile, guess, sigma)
        if fitted is None:
            continue
        (_, radius, amplitude, _, _), _, (lower, upper) = fitted
        if amplitude > 0 and 0.5 * guess < radius < min(2.0 * guess, 0.98 * upper[1]):
            values.append(amplitude * magnification)
    if len(values) < settings.min_profiles:
        raise EvidenceError(
            f"the iodine's attenuation could not be read from the frame: {len(values)} lumen fit(s) across vessels "
            f"of radius ≥ {settings.min_radius_mm:g} mm succeeded (at least {settings.min_profiles} needed); "
            "check that the frame belongs to the mask's view and shows contrast, or reconstruct from the masks alone")
    return {"attenuation_per_mm": float(np.median(values)), "profiles": len(values),
            "spread_per_mm": float(1.4826 * np.median(np.abs(np.asarray(values) - np.median(values))))}


def view_evidence(frame: np.ndarray, mask: np.ndarray, view: CArmView,
                  settings: EvidenceSettings = EvidenceSettings()) -> ViewEvidence:
    """L̂ of one view (module docstring), with μ and what it was read from."""
    frame = np.asarray(frame)
    mask = np.asarray(mask, bool)
    if frame.ndim != 2 or frame.shape != mask.shape:
        raise EvidenceError(f"the frame has shape {frame.shape} but the view's mask {mask.shape}: give the frame "
                            "the mask was drawn or segmented on (same rows and columns)")
    bad = ~np.isfinite(frame)
    if bad.any():
        row, col = map(int, np.argwhere(bad)[0])
        raise EvidenceError(f"{int(bad.sum())} of the frame's pixels are NaN or infinite (the first at row {row}, "
                            f"column {col}): give the recorded X-ray frame with a number in every pixel")
    if float(np.max(frame)) <= 0:
        raise EvidenceError("the frame has no positive finite intensities: give the recorded X-ray frame "
                            "(vessels dark), not a mask or a processed image")
    negative_share = float(np.mean(frame < 0))
    if negative_share > MAX_NEGATIVE_SHARE:
        raise EvidenceError(f"{100 * negative_share:.0f} % of the frame's pixels are negative (the least "
                            f"{float(frame.min()):g}): intensities on the detector's linear scale are not, so these are "
                            "signed or offset values (DICOM Pixel Representation 1, or a rescale intercept); give the "
                            "recorded frame on its linear scale, or reconstruct from the masks alone")
    if not mask.any():
        raise EvidenceError("the view's mask is empty: no vessel to read evidence for")
    above = absorbance_above_background(frame, mask, view.pixel_spacing_mm, settings)
    if not np.median(above[mask]) > 0:
        raise EvidenceError("inside the mask the frame is not darker than around it: give the recorded frame "
                            "with the vessels dark (raw X-ray intensity, not inverted), the one the mask was made on")
    mu = estimate_attenuation_per_mm(frame, mask, view, settings)
    above = np.maximum(above, 0.0)
    if settings.deblur_iterations > 0:
        above = deblurred(above, view.pixel_spacing_mm, settings.psf_sigma_mm, settings.deblur_iterations)
    keep = widened_mask(mask, settings.reach_px)
    line_integral = np.where(keep, above / mu["attenuation_per_mm"], 0.0).astype(np.float32)
    return ViewEvidence(line_integral, mu["attenuation_per_mm"], mu)
