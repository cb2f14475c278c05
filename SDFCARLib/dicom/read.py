"""Reading X-ray angiography DICOM files: SOP class check, decoders, modality rescale, ``load_xa``.

``load_xa(path)`` reads X-Ray Angiographic (XA), X-Ray Radiofluoroscopic (XRF) and their Enhanced
SOP classes, single- or multi-frame, 8–16 bit, in any transfer syntax pydicom can decode with the
plugins installed (pylibjpeg + pylibjpeg-libjpeg: JPEG baseline, extended, lossless and JPEG-LS;
pylibjpeg-openjpeg: JPEG 2000; RLE natively). Frames come back as float32 ``(n, rows, cols)`` with
the modality rescale applied and MONOCHROME1 inverted, so that larger always means brighter (more
X-ray intensity): contrast-filled vessels are dark; LOG frames are brought to a linear scale
(``intensity``). ``XARun.lookup`` finds an attribute at the top
level or in the functional groups of an enhanced object, for ``frames`` and ``geometry``.

pydicom is imported inside the functions: the command line imports this package for its options
(``cli``), and a run without DICOM input must neither need pydicom nor pay for loading it (Slicer
installs it on demand, the first time a DICOM view is used).
"""

from __future__ import annotations

import math

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np

from .intensity import intensity_tags, linearised, luts_per_frame

PathLike = Union[str, Path]

XA_SOP_CLASSES: Dict[str, str] = {
    "1.2.840.10008.5.1.4.1.1.12.1": "X-Ray Angiographic Image (XA)",
    "1.2.840.10008.5.1.4.1.1.12.2": "X-Ray Radiofluoroscopic Image (XRF)",
    "1.2.840.10008.5.1.4.1.1.12.1.1": "Enhanced XA Image",
    "1.2.840.10008.5.1.4.1.1.12.2.1": "Enhanced XRF Image",
}
ENHANCED_SOP_CLASSES = {"1.2.840.10008.5.1.4.1.1.12.1.1", "1.2.840.10008.5.1.4.1.1.12.2.1"}
XA_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.12.1"
XRF_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.12.2"

#: What to install when pydicom has no working decoder for a transfer syntax.
_DECODER_PACKAGES: Dict[str, str] = {
    "1.2.840.10008.1.2.4.50": "pylibjpeg pylibjpeg-libjpeg",  # JPEG baseline
    "1.2.840.10008.1.2.4.51": "pylibjpeg pylibjpeg-libjpeg",  # JPEG extended
    "1.2.840.10008.1.2.4.57": "pylibjpeg pylibjpeg-libjpeg",  # JPEG lossless
    "1.2.840.10008.1.2.4.70": "pylibjpeg pylibjpeg-libjpeg",  # JPEG lossless SV1
    "1.2.840.10008.1.2.4.80": "pylibjpeg pylibjpeg-libjpeg",  # JPEG-LS lossless
    "1.2.840.10008.1.2.4.81": "pylibjpeg pylibjpeg-libjpeg",  # JPEG-LS near-lossless
    "1.2.840.10008.1.2.4.90": "pylibjpeg pylibjpeg-openjpeg",  # JPEG 2000 lossless
    "1.2.840.10008.1.2.4.91": "pylibjpeg pylibjpeg-openjpeg",  # JPEG 2000
    "1.2.840.10008.1.2.4.201": "pylibjpeg pylibjpeg-openjpeg",  # HTJ2K lossless
    "1.2.840.10008.1.2.4.202": "pylibjpeg pylibjpeg-openjpeg",  # HTJ2K lossless RPCL
    "1.2.840.10008.1.2.4.203": "pylibjpeg pylibjpeg-openjpeg",  # HTJ2K
    "1.2.840.10008.1.2.5": "pylibjpeg pylibjpeg-rle",  # RLE (pydicom also decodes it natively)
}


class DicomInputError(ValueError):
    """A DICOM input cannot be used; the message names the file, the problem and the fix."""


# --- tag helpers -----------------------------------------------------------------------------------
def tag_label(keyword: str) -> str:
    """``"(0018,1110) DistanceSourceToDetector"`` for a DICOM keyword."""
    from pydicom.datadict import tag_for_keyword

    tag = tag_for_keyword(keyword)
    if tag is None:
        return keyword
    return f"({tag >> 16:04X},{tag & 0xFFFF:04X}) {keyword}"


def _is_empty(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, (str, bytes)) and len(value.strip() if isinstance(value, str) else value) == 0:
        return True
    try:
        return len(value) == 0  # empty MultiValue / sequence
    except TypeError:
        return False


def _is_multi_value(value: Any) -> bool:
    return isinstance(value, (list, tuple)) or type(value).__name__ == "MultiValue"


def tag_floats(value: Any) -> List[float]:
    """A numeric attribute's value(s) (one number or a multi-value) as a list of floats."""
    if _is_multi_value(value):
        return [float(v) for v in value]
    return [float(value)]


def tag_number(value: Any) -> float:
    """A single-valued numeric attribute as a finite float. ValueError, its message what is wrong (to follow the
    tag's name), for several values, text that is no number, or NaN."""
    if _is_multi_value(value):
        if len(value) != 1:
            shown = "\\".join(str(v) for v in value)
            raise ValueError(f"holds {len(value)} values ({shown}) where it has one")
        value = value[0]
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"= {str(value).strip()!r} is not a number") from None
    if not math.isfinite(number):
        raise ValueError(f"= {str(value).strip()!r} is not a finite number")
    return number



# --- the run -----------------------------------------------------------------------------------------
@dataclass
class XARun:
    """One XA/XRF object: its frames (float32, larger = brighter) and the pydicom dataset."""

    path: Path
    dataset: Any  # pydicom.Dataset
    frames: np.ndarray  # float32 (n, rows, cols)
    sop_class_uid: str
    transfer_syntax: str  # UID
    photometric: str
    bits_stored: int
    inverted: bool  # MONOCHROME1 was inverted
    linearised_note: Optional[str] = None  # how the frames were brought to a linear scale, or why not (``intensity``)
    read_relationship: Optional[str] = None  # the relationship of ``frames`` (``intensity.linearised``)

    @property
    def sop_class_name(self) -> str:
        return XA_SOP_CLASSES.get(self.sop_class_uid, self.sop_class_uid)

    @property
    def transfer_syntax_name(self) -> str:
        from pydicom.uid import UID

        return UID(self.transfer_syntax).name

    @property
    def enhanced(self) -> bool:
        return self.sop_class_uid in ENHANCED_SOP_CLASSES

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def detector_shape(self) -> Tuple[int, int]:
        return (int(self.frames.shape[1]), int(self.frames.shape[2]))

    @property
    def pixel_intensity_relationship(self) -> Optional[str]:
        """(0028,1040), upper case — LIN, LOG, DISP or a vendor's term (``evidence.unreadable_intensity``);
        None when absent."""
        return intensity_tags(self.dataset).relationship

    @property
    def frames_relationship(self) -> Optional[str]:
        """The relationship of ``frames`` as read: LIN where they were brought to a linear scale (a TO_LINEAR LUT, LOG
        frames) or LIN ones mirrored, else the tag's."""
        return self.read_relationship

    def lookup(self, keyword: str, frame: int = 0) -> Tuple[Any, Optional[str]]:
        """(value, where) of a non-empty attribute: top level, else the per-frame then shared
        functional groups of an enhanced object; (None, None) when absent or empty."""
        return lookup(self.dataset, keyword, frame)

    def source(self, keyword: str, where: Optional[str]) -> str:
        return f"tag {tag_label(keyword)}{where or ''}"


def lookup(ds: Any, keyword: str, frame: int = 0) -> Tuple[Any, Optional[str]]:
    """``XARun.lookup`` on a pydicom dataset (e.g. a header read without its pixels)."""
    if keyword in ds and not _is_empty(ds[keyword].value):
        return ds[keyword].value, ""
    for label, seq_keyword, index in (("per-frame", "PerFrameFunctionalGroupsSequence", frame),
                                      ("shared", "SharedFunctionalGroupsSequence", 0)):
        groups = ds.get(seq_keyword)
        if not groups or index >= len(groups):
            continue
        for element in groups[index]:
            if element.VR != "SQ" or len(element.value) == 0:
                continue
            item = element.value[0]
            if keyword in item and not _is_empty(item[keyword].value):
                return item[keyword].value, f" in {tag_label(element.keyword)} ({label} functional groups)"
    return None, None


def _sop_class_check(ds: Any, path: Path) -> str:
    sop = str(ds.get("SOPClassUID", "") or getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", "") or "")
    if sop in XA_SOP_CLASSES:
        return sop
    from pydicom.uid import UID

    what = f"its SOP class is {UID(sop).name} ({sop})" if sop else "it has no SOP Class UID (0008,0016)"
    modality = str(ds.get("Modality", "") or "?")
    raise DicomInputError(
        f"{path} is not an X-ray angiography image: {what}, modality {modality}. "
        "SDFCAR reads X-Ray Angiographic (1.2.840.10008.5.1.4.1.1.12.1), X-Ray Radiofluoroscopic (…12.2) and "
        "Enhanced XA/XRF (…12.1.1, …12.2.1) objects: export the original angiography run from the archive, "
        "or give a PNG/TIFF/NRRD image with the geometry typed in by hand")


def check_decodable(transfer_syntax: Any, path: PathLike = "") -> None:
    """Raise ``DicomInputError`` when pydicom cannot decode ``transfer_syntax`` with what is installed."""
    try:
        from pydicom.pixels.decoders.base import get_decoder
    except ImportError:
        get_decoder = None
    from pydicom.uid import UID

    uid = UID(str(transfer_syntax))
    where = f"{path}: " if str(path) else ""
    if get_decoder is None:  # pydicom 2: no decoder registry; decoding errors are explained by load_xa
        return
    try:
        decoder = get_decoder(uid)
    except NotImplementedError:
        raise DicomInputError(
            f"{where}the pixel data use transfer syntax {uid.name} ({uid}), which pydicom cannot decode (video and "
            "private syntaxes have no decoder); export the run from the archive as uncompressed or JPEG-compressed "
            "frames, or convert it (DCMTK: dcmdjpeg / dcmconv +te, GDCM: gdcmconv --raw)") from None
    if decoder.is_available:
        return
    package = _DECODER_PACKAGES.get(str(uid), "pylibjpeg pylibjpeg-libjpeg pylibjpeg-openjpeg")
    missing = "; ".join(decoder.missing_dependencies) or "no plugin"
    raise DicomInputError(
        f"{where}the pixel data use transfer syntax {uid.name} ({uid}) and no decoder for it is installed "
        f"({missing}). Install one: pip install {package} (in Slicer's Python console: "
        f"slicer.util.pip_install('{package}')), then load the file again")


def _rescale(run: "XARun") -> Tuple[float, float]:
    """Modality rescale (top level, or the Pixel Value Transformation functional group)."""
    numbers = []
    for keyword, default in (("RescaleSlope", 1.0), ("RescaleIntercept", 0.0)):
        value, where = run.lookup(keyword)
        try:
            numbers.append(default if value is None else tag_number(value))
        except ValueError as exc:
            raise DicomInputError(f"{run.path}: {run.source(keyword, where)} {exc}; the frames' grey levels cannot be "
                                  "read: export the run again from the system or the archive") from None
    return numbers[0], numbers[1]


def _dataset_without_preamble(path: Path) -> Any:
    """A dataset written without the 128-byte preamble and file meta (some archives export these); None when
    the file is no dataset."""
    import pydicom

    try:
        ds = pydicom.dcmread(str(path), force=True)
    except Exception:
        return None
    return ds if "SOPClassUID" in ds and "PixelData" in ds else None


def _record_transfer_syntax(ds: Any) -> None:
    """A file meta without a Transfer Syntax UID gets the encoding its reader found, so that its pixels decode."""
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRBigEndian, ExplicitVRLittleEndian, ImplicitVRLittleEndian

    meta = getattr(ds, "file_meta", None)
    if meta is not None and "TransferSyntaxUID" in meta:
        return
    encoding = getattr(ds, "original_encoding", None)  # pydicom 3; pydicom 2 sets the two flags
    implicit, little = encoding if encoding and encoding[0] is not None else (ds.is_implicit_VR, ds.is_little_endian)
    if meta is None:
        meta = ds.file_meta = FileMetaDataset()
    meta.TransferSyntaxUID = (ImplicitVRLittleEndian if implicit else
                              ExplicitVRLittleEndian if little else ExplicitVRBigEndian)


def load_xa(path: PathLike) -> XARun:
    """Read an XA/XRF (or enhanced) DICOM file: frames as float32 (n, rows, cols), larger = brighter."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    path = Path(path)
    if path.is_dir():
        raise DicomInputError(f"{path} is a folder; give one run's DICOM file in it (one file per view)")
    if not path.is_file():
        raise DicomInputError(f"DICOM file not found: {path}")
    try:
        ds = pydicom.dcmread(str(path))
    except InvalidDicomError:
        ds = _dataset_without_preamble(path)
        if ds is None:
            raise DicomInputError(
                f"{path} is not a DICOM file (no DICOM header); give the X-ray angiography DICOM file, or read "
                "PNG/TIFF/NRRD images with the geometry typed in by hand") from None
    except Exception as exc:  # truncated or corrupt files
        raise DicomInputError(f"{path} cannot be read as DICOM: {exc}") from None
    sop = _sop_class_check(ds, path)
    if "PixelData" in ds:
        _record_transfer_syntax(ds)
    if "PixelData" not in ds:
        raise DicomInputError(f"{path} has no pixel data (7FE0,0010): it holds no image frames")
    meta = getattr(ds, "file_meta", None)
    transfer_syntax = str(getattr(meta, "TransferSyntaxUID", "") or "1.2.840.10008.1.2")
    check_decodable(transfer_syntax, path)
    samples = int(ds.get("SamplesPerPixel", 1) or 1)
    if samples != 1:
        raise DicomInputError(f"{path} is a colour image ({samples} samples per pixel); X-ray angiography frames "
                              "are greyscale: export the original run, not a screen capture")
    try:
        try:
            from pydicom.pixels import pixel_array  # pydicom 3: does not cache the array on the dataset
        except ImportError:
            raw = ds.pixel_array
        else:
            raw = pixel_array(ds)
    except Exception as exc:
        from pydicom.uid import UID

        package = _DECODER_PACKAGES.get(transfer_syntax)
        hint = f"; if a decoder is missing: pip install {package}" if package else ""
        raise DicomInputError(f"{path}: the pixel data ({UID(transfer_syntax).name}) could not be decoded: {exc}{hint}") from None
    rows, cols = int(ds.Rows), int(ds.Columns)
    n = int(ds.get("NumberOfFrames", 1) or 1)
    raw = np.asarray(raw)
    if raw.size != n * rows * cols:
        raise DicomInputError(f"{path}: the decoded pixel data have {raw.size} values, not NumberOfFrames × Rows × "
                              f"Columns = {n} × {rows} × {cols}; the file is damaged")
    raw = raw.reshape(n, rows, cols)
    run = XARun(path, ds, np.empty((0, rows, cols), np.float32), sop, transfer_syntax,
                str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip().upper(),
                int(ds.get("BitsStored", ds.get("BitsAllocated", 16))), False)
    if run.photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise DicomInputError(f"{path}: photometric interpretation {run.photometric} is not greyscale "
                              "(MONOCHROME1/MONOCHROME2); export the original run, not a screen capture")
    slope, intercept = _rescale(run)
    values = raw.astype(np.float32)  # exact for stored values of up to 16 bits
    if (slope, intercept) != (1.0, 0.0):
        values = values * np.float32(slope) + np.float32(intercept)
    if run.photometric == "MONOCHROME1":
        # Mirror the stored range onto itself so that larger = brighter, as for MONOCHROME2.
        bits = run.bits_stored
        signed = int(ds.get("PixelRepresentation", 0) or 0) == 1
        lo, hi = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if signed else (0, 2**bits - 1)
        values = np.float32((lo * slope + intercept) + (hi * slope + intercept)) - values
        run.inverted = True
    # LOG frames (or through a TO_LINEAR LUT) on a linear scale, so that −log I is absorbance wherever they are read
    if not luts_per_frame(ds):  # one LUT (shared, or a classic object's) or none: the whole run at once
        run.frames, run.read_relationship, run.linearised_note = linearised(values, intensity_tags(ds), run.inverted)
        return run
    # LUTs in the per-frame functional groups: each frame is read through its own
    read = [linearised(values[f], intensity_tags(ds, f), run.inverted) for f in range(n)]
    run.frames = np.stack([np.asarray(frame, np.float32) for frame, _, _ in read])
    relationships = {relationship for _, relationship, _ in read}
    notes = list(dict.fromkeys(note for _, _, note in read if note))
    if len(relationships) > 1:
        raise DicomInputError(f"{path}: its frames' Pixel Intensity Relationship LUTs (0028,9422) read some frames on "
                              f"a linear scale and not others ({'; '.join(notes)}); export the run again, or one frame")
    run.read_relationship, run.linearised_note = relationships.pop(), "; ".join(notes) or None
    return run
