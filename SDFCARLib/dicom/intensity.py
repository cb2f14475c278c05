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
    Enhanced XA/XRF objects may say it exactly: a Pixel Intensity Relationship LUT (0028,9422) item whose
    LUT Function (0028,9474) is ``TO_LINEAR`` maps the stored values onto a scale linear in the X-ray
    intensity (required where the relationship is LOG; PS3.3 C.7.6.16.2.13, PS3.17 FFF.2.3.1.3.4); a classic
    XA/XRF object's Modality LUT does the same for LOG and DISP frames (required for LOG; not a display
    step there, PS3.3 C.8.7.1.1.2, PS3.4 N.2.1.2 — and so never applied forward by ``load_xa``). Where
    one is present it is used instead of the assumed span, for LOG and for other pointwise encodings
    (e.g. SQRT). A DISP frame is read through it only where Image Processing Applied (0028,9446) says no
    spatial filter was applied: a LUT undoes a grey-level mapping, not an edge enhancement. The LUT's
    output is taken as proportional to the intensity, rising or falling as its slope and the stored
    values' direction say; a LUT that is not monotonic is not used (and said so).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, List, Optional, Tuple

import numpy as np

from ..evidence import DISPLAY_INTENSITY, LINEAR_INTENSITY

#: e-folds of X-ray intensity the full stored range of a LOG frame is taken to span (the slope is not recorded)
LOG_SPAN_E_FOLDS = 8.0
#: the linearised frame's brightest count; its darkest is e^−LOG_SPAN_E_FOLDS of it (≈ 22), above the count
#: floor of 1 that −log I applies (``lumen_profile.absorbance``)
LINEAR_PEAK_COUNTS = 65535.0
LOG_INTENSITY = "LOG"
#: LUT Function (0028,9474) of the Pixel Intensity Relationship LUT that gives values linear in the intensity
TO_LINEAR = "TO_LINEAR"
#: Image Processing Applied (0028,9446) terms after which a DISP frame's grey levels are still a pointwise map of
#: the intensity (frame averaging is temporal and linear); anything else (HIGH_PASS_FILTER, …) filtered the frame
POINTWISE_PROCESSING = frozenset({"NONE", "FRAME_AVERAGING"})
RELATIONSHIP_LUT = "TO_LINEAR Pixel Intensity Relationship LUT (0028,9422)"
#: where a classic XA/XRF object holds its LUT back to linear: for LOG and DISP frames the Modality LUT is not
#: applied before display but maps the stored values back to a linear relationship (PS3.3 C.8.7.1.1.2, PS3.4 N.2.1.2)
MODALITY_LUT = "Modality LUT (0028,3000)"


@dataclass(frozen=True)
class IntensityLUT:
    """A TO_LINEAR Pixel Intensity Relationship LUT: stored value v maps to ``values[v − first_mapped]``
    (clamped to the first and last entry, as every DICOM LUT)."""

    first_mapped: int
    values: np.ndarray  # float64, one entry per stored value from first_mapped on
    bits: int  # bits per entry (LUT Descriptor's third value)
    source: str = RELATIONSHIP_LUT  # which attribute held it

    def __call__(self, stored: np.ndarray) -> np.ndarray:
        index = np.clip(np.rint(np.asarray(stored, np.float64)).astype(np.int64) - self.first_mapped, 0,
                        self.values.size - 1)
        return self.values[index]

    @property
    def direction(self) -> int:
        """+1 where the LUT rises with the stored value, −1 where it falls, 0 where it is neither (not monotonic or flat)."""
        step = np.diff(self.values)
        if self.values.size < 2 or not np.any(step):
            return 0
        return 1 if np.all(step >= 0) else -1 if np.all(step <= 0) else 0


def lut_from_item(item: Any) -> IntensityLUT:
    """An ``IntensityLUT`` from a LUT item's LUT Descriptor (0028,3002) and LUT Data (0028,3006): number of entries
    (0 means 65536), first stored value mapped, bits per entry; the data one entry per 16-bit word (US or OW)."""
    descriptor = [int(v) for v in item.LUTDescriptor]
    entries, first, bits = descriptor[0] or 65536, descriptor[1], descriptor[2]
    data = item.LUTData
    if isinstance(data, (bytes, bytearray)):
        data = np.frombuffer(bytes(data), dtype="<u2")  # OW in an explicit or implicit little-endian object
    values = np.asarray(data, np.float64).ravel()[:entries]
    if values.size == 0:
        raise ValueError("the LUT has no data")
    return IntensityLUT(first, values, bits)


def _lut_items(ds: Any, frame: int) -> List[Any]:
    """The items of the Pixel Intensity Relationship LUT Sequence (0028,9422) of ``frame``: a functional group, so
    the sequence sits directly in the per-frame or shared group item (or, in a non-enhanced object, at the top)."""
    keyword = "PixelIntensityRelationshipLUTSequence"
    if ds.get(keyword):
        return list(ds[keyword].value)
    for groups, index in ((ds.get("PerFrameFunctionalGroupsSequence"), frame), (ds.get("SharedFunctionalGroupsSequence"), 0)):
        if groups and index < len(groups) and groups[index].get(keyword):
            return list(groups[index][keyword].value)
    return []


def luts_per_frame(ds: Any) -> bool:
    """Whether an enhanced object gives Pixel Intensity Relationship LUTs frame by frame (per-frame functional groups)."""
    return any(item.get("PixelIntensityRelationshipLUTSequence") for item in (ds.get("PerFrameFunctionalGroupsSequence") or ()))


def _to_linear_items(ds: Any, frame: int, relationship: Optional[str]) -> List[Tuple[Any, str]]:
    """(item, what it is) of each LUT that maps the frame's stored values onto a linear scale: an enhanced object's
    TO_LINEAR items, else a classic object's Modality LUT where its relationship is LOG or DISP."""
    items = [(item, RELATIONSHIP_LUT) for item in _lut_items(ds, frame)
             if str(item.get("LUTFunction", "")).strip().upper() == TO_LINEAR]
    if not items and relationship in (LOG_INTENSITY, DISPLAY_INTENSITY) and ds.get("ModalityLUTSequence"):
        items = [(ds.ModalityLUTSequence[0], MODALITY_LUT)]
    return items


def to_linear_lut(ds: Any, frame: int = 0, relationship: Optional[str] = None
                  ) -> Tuple[Optional[IntensityLUT], Optional[str]]:
    """(the frame's LUT back to linear or None, why a present one cannot be used or None); ``relationship``: the
    frame's (0028,1040), upper case (a classic object's Modality LUT counts for LOG and DISP only)."""
    for item, what in _to_linear_items(ds, frame, relationship):
        try:
            lut = lut_from_item(item)
        except Exception as exc:  # a damaged item: the frames are read as without it
            return None, f"its {what} cannot be read ({exc})"
        if lut.direction == 0:
            return None, (f"its {what} is not monotonic, so it cannot map the stored values onto the intensity: it "
                          "was not used")
        return replace(lut, source=what), None
    return None, None


@dataclass(frozen=True)
class IntensityTags:
    """What a frame's DICOM header says about its grey levels."""

    relationship: Optional[str]  # (0028,1040), upper case; None when absent
    sign: Optional[int]  # (0028,1041): +1, −1; None when absent or not ±1
    photometric: str  # MONOCHROME1 / MONOCHROME2
    bits_stored: int
    to_linear: Optional[IntensityLUT] = None  # an enhanced object's TO_LINEAR LUT (0028,9422) of the frame
    image_processing: Tuple[str, ...] = ()  # Image Processing Applied (0028,9446), upper case; () when absent
    lut_problem: Optional[str] = None  # why a TO_LINEAR LUT present could not be used

    def usable_lut(self) -> Optional[IntensityLUT]:
        """The TO_LINEAR LUT where the frames are read through it (module docstring), else None."""
        if self.to_linear is None or self.relationship == LINEAR_INTENSITY:
            return None
        if self.relationship == DISPLAY_INTENSITY and not (self.image_processing and
                                                           set(self.image_processing) <= POINTWISE_PROCESSING):
            return None
        return self.to_linear

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


def intensity_tags(ds: Any, frame: int = 0) -> IntensityTags:
    """``IntensityTags`` of a pydicom dataset's ``frame`` (top level or an enhanced object's functional groups)."""
    from .read import lookup

    relationship, _ = lookup(ds, "PixelIntensityRelationship", frame)
    sign, _ = lookup(ds, "PixelIntensityRelationshipSign", frame)
    processing, _ = lookup(ds, "ImageProcessingApplied", frame)
    processing = () if processing is None else tuple(
        str(v).strip().upper() for v in ([processing] if isinstance(processing, str) else processing))
    relationship = None if relationship is None else str(relationship).strip().upper() or None
    lut, problem = to_linear_lut(ds, frame, relationship)
    try:
        sign = int(sign) if sign is not None and int(sign) in (-1, 1) else None
    except (TypeError, ValueError):
        sign = None
    bits = ds.get("BitsStored", ds.get("BitsAllocated", 16))
    return IntensityTags(relationship, sign,
                         str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip().upper(), int(bits or 16),
                         lut, processing, problem)


def intensity_tags_of_file(path: Any, frame: int = 0) -> Optional[IntensityTags]:
    """``IntensityTags`` of a frame read from a DICOM file's header alone (no pixel data decoded); None when the
    file cannot be read as DICOM. A negative ``frame`` (Slicer's "the current one") reads frame 0."""
    import pydicom

    try:
        return intensity_tags(pydicom.dcmread(str(path), stop_before_pixels=True), max(int(frame), 0))
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


def linear_from_lut(values: np.ndarray, tags: IntensityTags, lut: IntensityLUT, inverted: bool
                    ) -> Tuple[np.ndarray, str]:
    """(frames on the LUT's linear scale, float32, larger = more intensity; the note saying so). ``values`` as
    handed over: mirrored for MONOCHROME1 where ``inverted`` (undone here: the LUT maps the stored values)."""
    stored = (2.0 ** tags.bits_stored - 1.0) - np.asarray(values, np.float64) if inverted else values
    stored_rises, source = tags.larger_means_more_intensity(False)
    linear = lut(stored)
    rises = (lut.direction > 0) == stored_rises
    if not rises:  # a LUT falling where the stored values rise (or the reverse): linear, but upside down
        linear = rising_from_falling(linear, lut.bits)
    note = (f"its Pixel Intensity Relationship (0028,1040) is {tags.relationship or 'not given'}: the frames were read "
            f"through its {lut.source}, which maps them back to linear ({lut.values.size} entries from stored "
            f"value {lut.first_mapped}, {lut.bits} bits; {source}), so their path lengths are read")
    return np.asarray(linear, np.float32), note


def linearised(values: np.ndarray, tags: Optional[IntensityTags], inverted: bool = False
               ) -> Tuple[np.ndarray, Optional[str], Optional[str]]:
    """(frames, the relationship of the frames returned, a note or None): frames through a usable TO_LINEAR LUT
    and LOG frames on a linear scale (then ``LIN``), LIN frames whose explicit Sign says their values fall with
    intensity mirrored (module docstring); any other frames unchanged with their own relationship (None when not
    known), a present LUT that could not be used said in the note."""
    lut = tags.usable_lut() if tags is not None else None
    if lut is not None:
        frames, note = linear_from_lut(values, tags, lut, inverted)
        return frames, LINEAR_INTENSITY, note
    if tags is not None and tags.relationship == LINEAR_INTENSITY and tags.sign is not None:
        larger, source = tags.larger_means_more_intensity(inverted)
        if larger:
            return values, LINEAR_INTENSITY, None
        note = (f"its Pixel Intensity Relationship (0028,1040) is LIN with values falling as the intensity rises "
                f"({source}{', after the reader mirrored MONOCHROME1' if inverted else ''}): the frames were mirrored "
                "onto their stored range, so that larger means more intensity")
        return rising_from_falling(values, tags.bits_stored), LINEAR_INTENSITY, note
    unused = None
    if tags is not None and tags.relationship != LINEAR_INTENSITY:
        unused = tags.lut_problem or (
            f"its {tags.to_linear.source} was not used: Image Processing Applied (0028,9446) is "
            f"{'/'.join(tags.image_processing) or 'not given'}, and a LUT does not undo a spatial filter"
            if tags.to_linear is not None else None)
    if tags is None or tags.relationship != LOG_INTENSITY:
        return values, None if tags is None else tags.relationship, unused
    larger, source = tags.larger_means_more_intensity(inverted)
    note = (f"its Pixel Intensity Relationship (0028,1040) is LOG: the frames were brought to a linear scale "
            f"({source}; the slope is not recorded and each view's is fitted away), so their path lengths are read")
    if unused:
        note = f"{unused}; {note}"
    return linear_from_log(values, larger, tags.bits_stored), LINEAR_INTENSITY, note
