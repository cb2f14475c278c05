"""The frames' grey levels against the X-ray intensity: Pixel Intensity Relationship (0028,1040) and its Sign (0028,1041).

Why
    The frames' path lengths (``evidence.py``), the motion search and the 3D-QCA's densitometry read
    −log I as absorbance, which holds for grey levels proportional to the intensity (``LIN``). A ``LOG``
    frame stores a logarithm of it: its values are affine in ln I, of unknown slope and offset (PS3.3
    C.8.11.3.1.2). They are brought back to a linear scale here, once, where the frames are read, so
    that everything downstream sees ``LIN`` frames. ``DISP`` and vendors' terms (GE's ``DRM``) were
    processed for display — windowed, contrast-managed, edge-enhanced — and no fixed rule undoes that:
    they stay as they are and give no path lengths (``evidence.unreadable_intensity``).

Conventions
    The Sign is about the *stored* values: +1, lower values mean less X-ray intensity; −1, higher
    values mean less. Where a LOG run omits it, the display convention is assumed: after the
    photometric interpretation, brighter means more intensity (vessels dark).
    The slope is not recorded: the full stored range (2^BitsStored values) is taken as
    ``LOG_SPAN_E_FOLDS`` e-folds of intensity. The slope only multiplies each view's absorbance, and
    every reader of it divides the same factor out — the path lengths by the attenuation per mm read
    off the same frame (``evidence.estimate_attenuation_per_mm``), the motion search by each view's
    total, the densitometry by its own fit of the frame. The offset is a constant absorbance, which
    the background subtraction removes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Tuple

import numpy as np

from ..evidence import LINEAR_INTENSITY

#: e-folds of X-ray intensity the full stored range of a LOG frame is taken to span (the slope is not recorded)
LOG_SPAN_E_FOLDS = 8.0
#: the linearised frame's brightest count; its darkest is e^−LOG_SPAN_E_FOLDS of it (≈ 22), above the count
#: floor of 1 that −log I applies (``lumen_profile.absorbance``)
LINEAR_PEAK_COUNTS = 65535.0
LOG_INTENSITY = "LOG"


@dataclass(frozen=True)
class IntensityTags:
    """What a frame's DICOM header says about its grey levels."""

    relationship: Optional[str]  # (0028,1040), upper case; None when absent
    sign: Optional[int]  # (0028,1041): +1, −1; None when absent or not ±1
    photometric: str  # MONOCHROME1 / MONOCHROME2
    bits_stored: int

    def larger_means_more_intensity(self, inverted: bool) -> Tuple[bool, str]:
        """Whether larger values of the frame as handed over mean more X-ray intensity, and from what:
        ``inverted`` says the stored values were mirrored for MONOCHROME1 (``load_xa`` does)."""
        if self.sign is not None:
            stored, source = self.sign, f"Pixel Intensity Relationship Sign (0028,1041) {self.sign:+d}"
        else:
            stored = 1 if self.photometric != "MONOCHROME1" else -1
            source = (f"no Pixel Intensity Relationship Sign (0028,1041): taken as {stored:+d} from "
                      f"{self.photometric} (brighter is more intensity)")
        return (stored > 0) != bool(inverted), source


def intensity_tags(ds: Any) -> IntensityTags:
    """``IntensityTags`` of a pydicom dataset (top level or an enhanced object's functional groups)."""
    from .read import lookup

    relationship, _ = lookup(ds, "PixelIntensityRelationship")
    sign, _ = lookup(ds, "PixelIntensityRelationshipSign")
    try:
        sign = int(sign) if sign is not None and int(sign) in (-1, 1) else None
    except (TypeError, ValueError):
        sign = None
    bits = ds.get("BitsStored", ds.get("BitsAllocated", 16))
    return IntensityTags(None if relationship is None else str(relationship).strip().upper() or None, sign,
                         str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip().upper(), int(bits or 16))


def intensity_tags_of_file(path: Any) -> Optional[IntensityTags]:
    """``IntensityTags`` read from a DICOM file's header alone (no pixel data decoded); None when the file
    cannot be read as DICOM."""
    import pydicom

    try:
        return intensity_tags(pydicom.dcmread(str(path), stop_before_pixels=True))
    except Exception:  # not DICOM, unreadable: nothing is known of its grey levels
        return None


def linear_from_log(values: np.ndarray, larger_means_more_intensity: bool, bits_stored: int) -> np.ndarray:
    """A LOG frame (or run) on a linear intensity scale (float32, larger = more intensity): its brightest
    value becomes ``LINEAR_PEAK_COUNTS`` and each stored step LOG_SPAN_E_FOLDS / 2^bits_stored e-folds less."""
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return v.astype(np.float32)
    darker = (v.max() - v) if larger_means_more_intensity else (v - v.min())
    return (LINEAR_PEAK_COUNTS * np.exp(-darker * (LOG_SPAN_E_FOLDS / 2.0 ** int(bits_stored)))).astype(np.float32)


def rising_from_falling(values: np.ndarray, bits_stored: int) -> np.ndarray:
    """Linear values that fall as the intensity rises, mirrored onto the stored range (0 … 2^bits_stored − 1,
    or up to the largest value where one lies above it) so that larger means more intensity."""
    v = np.asarray(values, np.float64)
    top = max(2.0 ** int(bits_stored) - 1.0, float(v.max()) if v.size else 0.0)
    return (top - v).astype(np.float32)


def linearised(values: np.ndarray, tags: Optional[IntensityTags], inverted: bool = False
               ) -> Tuple[np.ndarray, Optional[str], Optional[str]]:
    """(frames, the relationship of the frames returned, a note or None): LOG frames on a linear scale
    (then ``LIN``), LIN frames whose explicit Sign says their values fall with intensity mirrored (module
    docstring); any other frames unchanged with their own relationship (None when not known)."""
    if tags is not None and tags.relationship == LINEAR_INTENSITY and tags.sign is not None:
        larger, source = tags.larger_means_more_intensity(inverted)
        if larger:
            return values, LINEAR_INTENSITY, None
        note = (f"its Pixel Intensity Relationship (0028,1040) is LIN with values falling as the intensity rises "
                f"({source}{', after the reader mirrored MONOCHROME1' if inverted else ''}): the frames were mirrored "
                "onto their stored range, so that larger means more intensity")
        return rising_from_falling(values, tags.bits_stored), LINEAR_INTENSITY, note
    if tags is None or tags.relationship != LOG_INTENSITY:
        return values, None if tags is None else tags.relationship, None
    larger, source = tags.larger_means_more_intensity(inverted)
    note = (f"its Pixel Intensity Relationship (0028,1040) is LOG: the frames were brought to a linear scale "
            f"({source}; the slope is not recorded and each view's is fitted away), so their path lengths are read")
    return linear_from_log(values, larger, tags.bits_stored), LINEAR_INTENSITY, note
