"""Vessel masks of the views: binarising label images, and a vesselness helper to start from.

Binarising (``binarise_mask``)
    The one mask rule of the package (the file reader, the engine and the MRML bridge call it):
    one binary image per view, of the view's detector shape, with 0 for background and one
    non-zero value for vessel. Label images and segmentations often hold several labels: give
    ``label`` to keep one of them; without it an image of more than two values is refused, since
    a grey frame given as a mask would otherwise pass. Checked: 2-D, numeric, finite, the
    detector's size, binary, not empty, not everything — each with a message that says how to
    fix the input. An RGB(A) image is accepted only when its colour channels are equal (a grey
    image saved as colour).

Vesselness (``vesselness_mask``), for when no mask exists — the user edits the result
    Multi-scale Hessian ridge filter of scikit-image (``frangi`` or ``sato``) on the frame scaled
    to [0, 1] by its 1st–99th percentiles, dark ridges by default (contrast-filled vessels are dark
    in X-ray intensity), then a threshold on the response and removal of connected components
    (8-connected) smaller than ``min_component_px``. The default threshold is Otsu's, computed on
    the pixels with a non-negligible response (above 1e-3 of the maximum) so that the large flat
    background does not drag it to zero; for ``frangi`` on the logarithm of the response, which
    spans several decades (on simulated angiograms Otsu on the raw Frangi response kept only the
    vessel cores, Dice ≈ 0.5 against ≈ 0.8 on its logarithm; Sato's response is closer to linear
    and Otsu applies to it directly, Dice ≈ 0.7–0.85). The parameters used are returned next to
    the mask so that the choice can be reported and repeated.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np

PathLike = Union[str, Path]


class MaskError(ValueError):
    """A mask cannot be used; the message names the problem and the fix."""


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
    a = np.asarray(array)
    if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise MaskError(f"{source}: data type {a.dtype} is not numeric; give a label image with numbers")
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        colour = a[..., :3]
        if not (np.array_equal(colour[..., 0], colour[..., 1]) and np.array_equal(colour[..., 0], colour[..., 2])):
            raise MaskError(f"{source}: a colour image ({a.shape[-1]} channels with different values) is not a mask; "
                            "save the segmentation as a single-channel label image")
        a = colour[..., 0]
    if a.ndim == 3 and 1 in (a.shape[0], a.shape[-1]):
        a = a.reshape(a.shape[1:] if a.shape[0] == 1 else a.shape[:-1])
    if a.ndim != 2:
        raise MaskError(f"{source}: a mask is a 2-D image (rows, cols), got shape {a.shape}; give one view's mask")
    if detector_shape is not None:
        expected = tuple(int(v) for v in detector_shape)
        if a.shape != expected:
            hint = " (rows and columns are swapped: transpose the image)" if a.shape == expected[::-1] else ""
            raise MaskError(f"{source}: mask shape {a.shape} differs from the detector shape {expected} of its view"
                            f"{hint}; the mask must be drawn on the frame of that view, pixel for pixel")
    if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        raise MaskError(f"{source}: the mask contains NaN or infinite values; fix the image")
    present = np.unique(a)
    if label is not None:
        if not np.any(present == label):
            shown = ", ".join(f"{v:g}" for v in present[:10].astype(float)) + ("…" if present.size > 10 else "")
            raise MaskError(f"{source}: label {label:g} does not occur in the image (values present: {shown}); "
                            "choose one of those, or give no label to take every non-zero pixel as vessel")
        mask = a == label
    else:
        # Without a label only 0 and one other value are unambiguous: a grey frame or a label image
        # of several structures given by mistake would otherwise pass as a mask.
        if np.count_nonzero(present) > 1 or np.any(present < 0):
            shown = ", ".join(f"{v:g}" for v in present[:6].astype(float)) + (", …" if present.size > 6 else "")
            raise MaskError(f"{source}: the mask is not binary (values {shown}); give a mask with 0 for background and "
                            "one non-zero value (e.g. 1 or 255) for vessel, threshold it first, or choose the vessel "
                            "label of a label image")
        mask = a != 0
    if not mask.any():
        raise MaskError(f"{source}: the mask is empty (no vessel pixel); segment the vessels of this view first")
    if mask.all():
        raise MaskError(f"{source}: the mask covers the whole image: it marks every pixel as vessel, so it is not a "
                        "vessel segmentation (is it inverted, or was the background saved as non-zero? give the label of "
                        "the vessels)")
    return mask


def _normalise(frame: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(frame, [1.0, 99.0])
    if not hi > lo:
        raise MaskError("the frame is flat (no contrast between its 1st and 99th percentiles): nothing to segment")
    return np.clip((frame - lo) / (hi - lo), 0.0, 1.0)


def vesselness_mask(
    frame: Any,
    sigmas: Sequence[float] = (1.0, 2.0, 3.0, 4.0),
    method: str = "frangi",
    black_ridges: bool = True,
    threshold: Optional[float] = None,
    min_component_px: int = 30,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """Vessel mask of one frame by a ridge filter, threshold and small-component removal.

    Returns ``(mask, parameters)``; ``parameters`` holds every value used (the Otsu threshold
    when ``threshold`` is None) and the fraction of the image marked vessel.
    """
    from skimage.filters import frangi, sato, threshold_otsu
    from skimage.morphology import remove_small_objects

    image = np.asarray(frame, dtype=np.float64)
    if image.ndim != 2:
        raise MaskError(f"vesselness works on one 2-D frame, got shape {image.shape}; pick a frame first")
    if not np.all(np.isfinite(image)):
        raise MaskError("the frame contains NaN or infinite values")
    sigmas = tuple(float(s) for s in sigmas)
    if not sigmas or any(s <= 0 for s in sigmas):
        raise MaskError(f"sigmas must be positive scales in pixels (about the vessel radius), got {sigmas}")
    if method not in ("frangi", "sato"):
        raise MaskError(f"method must be 'frangi' or 'sato', got {method!r}")
    if int(min_component_px) < 0:
        raise MaskError(f"min_component_px must be 0 or more, got {min_component_px}")
    scaled = _normalise(image)
    if method == "frangi":
        response = frangi(scaled, sigmas=sigmas, black_ridges=black_ridges)
    else:
        response = sato(scaled, sigmas=sigmas, black_ridges=black_ridges)
    response = np.nan_to_num(response, nan=0.0)
    if threshold is None:
        # Otsu on the pixels that respond at all: the flat background would otherwise dominate.
        active = response[response > 1e-3 * float(response.max())] if response.max() > 0 else response
        if active.size < 2 or float(active.max()) == float(active.min()):
            raise MaskError("the ridge filter found no vessel-like structure; check black_ridges and sigmas")
        if method == "frangi":
            # Frangi's response spans decades; on a linear scale Otsu keeps only the vessel cores.
            value = float(np.exp(threshold_otsu(np.log(active))))
            threshold_source = "Otsu on the logarithm of the non-negligible response"
        else:
            value, threshold_source = float(threshold_otsu(active)), "Otsu on the non-negligible response"
    else:
        value, threshold_source = float(threshold), "user"
    mask = response > value
    if min_component_px > 0:
        mask = remove_small_objects(mask, max_size=int(min_component_px) - 1, connectivity=2) if _has_max_size() \
            else remove_small_objects(mask, min_size=int(min_component_px), connectivity=2)
    parameters = {
        "method": method,
        "sigmas": list(sigmas),
        "black_ridges": bool(black_ridges),
        "threshold": value,
        "threshold_source": threshold_source,
        "response_max": float(response.max()),
        "min_component_px": int(min_component_px),
        "vessel_fraction": float(mask.mean()),
    }
    return mask, parameters


def _has_max_size() -> bool:
    """scikit-image ≥ 0.26 names the size limit ``max_size`` (objects up to it are removed)."""
    import inspect

    from skimage.morphology import remove_small_objects

    return "max_size" in inspect.signature(remove_small_objects).parameters
