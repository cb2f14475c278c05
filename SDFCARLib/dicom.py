"""X-ray angiography DICOM input: frames, frame choice and the C-arm geometry from the tags.

Command-line wiring (for ``cli.py``)
    ``add_dicom_arguments(parser)`` adds to an argparse (sub)parser::

        --dicom1 F1 [--frame1 N] --dicom2 F2 [--frame2 N]
        [--sod1 MM] [--sid1 MM] [--pixel-spacing1 ROW COL] [--primary1 DEG] [--secondary1 DEG]
        [--sod2 MM] [--sid2 MM] [--pixel-spacing2 ROW COL] [--primary2 DEG] [--secondary2 DEG]
        [--volume-shape I J K] [--volume-spacing MM] [--volume-center X Y Z]

    and ``cli_geometry_from_args(args) -> (Geometry, provenance)`` turns the parsed arguments into
    the geometry (``geometry`` writes it with ``write_geometry_json``; ``reconstruct --dicom1 …
    --dicom2 …`` uses it in place of ``--geometry``, with the masks checked against its detector
    shapes). Frame numbers on the command line are 0-based, like everywhere in SDFCARLib.

Frames
    ``load_xa(path)`` reads X-Ray Angiographic (XA), X-Ray Radiofluoroscopic (XRF) and their
    Enhanced SOP classes, single- or multi-frame, 8–16 bit, in any transfer syntax pydicom can
    decode with the plugins installed (pylibjpeg + pylibjpeg-libjpeg: JPEG baseline, extended,
    lossless and JPEG-LS; pylibjpeg-openjpeg: JPEG 2000; RLE natively). Frames come back as float32
    ``(n, rows, cols)`` with the modality rescale applied and MONOCHROME1 inverted, so that larger
    always means brighter (more X-ray intensity): contrast-filled vessels are dark.

Frame choice (``choose_frame``), 0-based indices
    1. A frame index given by the user (range-checked).
    2. End diastole, where the object says when it is: per-frame Cardiac Cycle Position
       (0018,9236) = END_DIASTOLE (enhanced objects); R Wave Pointer (0028,6040) (DICOM frame
       numbers, from 1); R Wave Time Vector (0018,6060) (ms from the first frame, taken as such)
       mapped through the frame times; or the R peaks of an ECG channel of a Waveform Sequence
       (5400,0100) in the object (time 0 = first frame, shifted by Multiplex Group Time Offset
       (0018,1068); Heart Rate (0018,1088) sets the shortest R–R spacing accepted). Frame times
       are Frame Time Vector (0018,1065) (increments, the first 0) or Frame Time (0018,1063) × n.
       End diastole is the R wave: the ventricles are fullest and the coronaries move least. Of
       the end-diastolic frames the one with the most contrast-filled vessel is taken (early R
       waves often come before the contrast arrives).
    3. Otherwise the frame with the most contrast-filled vessel (``contrast_scores``): the
       iodine signal of thin dark structures, summed. Each frame is reduced to at most 256 pixels
       a side, log-transformed (by Beer–Lambert, −log I is proportional to the iodine path
       length, and a change of exposure only adds a constant), and a grey-level black top-hat
       with a 15-pixel window (closing minus image) keeps the dark structures narrower than the
       window — vessels — and removes the slowly varying background (soft tissue, diaphragm,
       exposure drift). The score is the sum of the top-hat above a noise floor (median + 4 ×
       the robust standard deviation of the top-hat). It grows as the contrast fills the tree and
       falls as it washes out; it costs a few milliseconds a frame, so long runs are cheap, unlike
       a Hessian vesselness filter on every frame.

Geometry from the tags (``view_from_dicom``, ``geometry_from_dicom``)
    The XA Positioner Module (DICOM PS3.3 C.8.7.5) defines the angles with the patient supine:
    Positioner Primary Angle (0018,1510) in the transaxial plane, 0° perpendicular to the chest,
    +90° at the patient's left (LAO), −90° at the right (RAO); Positioner Secondary Angle (0018,1511)
    in the sagittal plane, +90° cranial; at 0°/0° the patient faces the image intensifier /
    detector (C.8.7.5.1.2). These are the angles of the detector direction d in ``geometry.py``
    (LAO +, CRA +), so they are used unchanged. The tags apply to the first frame; for rotational
    runs the Positioner Primary/Secondary Angle Increment (0018,1520/1521) hold either one value,
    the average change per frame (angle of frame n = start + n · increment, n from 0), or one
    offset per frame from the initial angle (angle of frame n = start + increment[n])
    (C.8.7.5.1.3; any other number of values is an error).
    Distances: Distance Source to Detector (0018,1110) is the SID; Distance Source to Patient
    (0018,1111) is, in the XA Positioner Module, the distance from the source to the isocenter
    (centre of the field of view), which is our SOD (other IODs measure it to the table: not used
    here). Estimated Radiographic Magnification Factor (0018,1114) = SID / SOD gives one of them
    from the other. Enhanced objects hold these in the X-Ray Geometry (0018,9476; Distance Source
    to Isocenter (0018,9402)), Positioner Position (0018,9405) and Frame Pixel Data Properties
    (0028,9443) functional groups; they are read there.
    Pixel spacing at the detector, first found of: Imager Pixel Spacing (0018,1164); Pixel
    Spacing (0028,0030) — at the patient when Pixel Spacing Calibration Type (0028,0A02) is present
    (then × the magnification (0018,1114), or SID / SOD), otherwise taken as the detector spacing,
    which is what projection images without a calibration store; Field of View Dimensions
    (0018,1149) / the image size (assumes the stored image spans the field of view); Intensifier
    Size (0018,1162) / the larger image side. No tag gives the principal point: the image centre.
    XA images carry no image orientation: SDFCAR's convention (columns towards the patient's left,
    rows towards the feet near AP, as frontal runs are displayed) is assumed, and a Patient
    Orientation (0020,0020), Field of View Horizontal Flip (0018,7034), Field of View Rotation or
    detector tilt (0018,1530/1531) that says otherwise is reported in the provenance's ``notes``.
    Anything missing is an error naming the tag and how to supply the value — an ``overrides``
    dict (``{"sod_mm": 765, "pixel_spacing_mm": [0.3, 0.3]}``) or ``--sod1`` … on the command
    line — never a silent default. A user value replaces the tag's. Every value used is reported
    with its source in the provenance, which ``write_geometry_json`` stores in GEOM.json.

Writing (``write_xa``)
    A valid XA object (multi-frame for a 3-D array) with the positioner tags of a ``CArmView``,
    native or compressed with the encoders pydicom has here (RLE Lossless always; JPEG 2000 with
    pylibjpeg-openjpeg). pydicom has no JPEG baseline / JPEG lossless encoder: those are refused
    with a message.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import CArmView, Geometry, GeometryError, VolumeGrid
from .io import atomic_write, json_compatible, write_text_atomically

PathLike = Union[str, Path]


# --- command-line wiring ---------------------------------------------------------------------------
def add_dicom_arguments(parser: Any, required: bool = True) -> None:
    """Add the DICOM input options (two views, frames, per-view overrides, volume) to ``parser``."""
    for n in (1, 2):
        parser.add_argument(f"--dicom{n}", required=required, metavar=f"F{n}",
                            help=f"X-ray angiography DICOM file (XA/XRF, multi-frame allowed) of view {n}")
        parser.add_argument(f"--frame{n}", type=int, default=None, metavar="N",
                            help=f"0-based frame of view {n} (default: end-diastolic frame from the ECG tags, "
                                 "else the frame with the most contrast)")
        parser.add_argument(f"--sod{n}", type=float, default=None, metavar="MM",
                            help=f"source-to-isocenter distance of view {n} in mm (replaces tag (0018,1111))")
        parser.add_argument(f"--sid{n}", type=float, default=None, metavar="MM",
                            help=f"source-to-detector distance of view {n} in mm (replaces tag (0018,1110))")
        parser.add_argument(f"--pixel-spacing{n}", type=float, nargs=2, default=None, metavar=("ROW", "COL"),
                            help=f"detector pixel spacing of view {n} in mm (replaces tag (0018,1164))")
        parser.add_argument(f"--primary{n}", type=float, default=None, metavar="DEG",
                            help=f"primary angle of view {n}, LAO + / RAO − (replaces tag (0018,1510))")
        parser.add_argument(f"--secondary{n}", type=float, default=None, metavar="DEG",
                            help=f"secondary angle of view {n}, CRA + / CAU − (replaces tag (0018,1511))")
    parser.add_argument("--volume-shape", type=int, nargs=3, default=None, metavar=("I", "J", "K"),
                        help="reconstruction grid size in voxels (default 128 128 128)")
    parser.add_argument("--volume-spacing", type=float, default=None, metavar="MM",
                        help="reconstruction voxel size in mm (default 0.8)")
    parser.add_argument("--volume-center", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="centre of the reconstruction grid, LPS mm (default: the isocenter 0 0 0)")


def _overrides_from_args(args: Any, n: int) -> Dict[str, Any]:
    values = {
        "sod_mm": getattr(args, f"sod{n}", None),
        "sid_mm": getattr(args, f"sid{n}", None),
        "pixel_spacing_mm": getattr(args, f"pixel_spacing{n}", None),
        "primary_deg": getattr(args, f"primary{n}", None),
        "secondary_deg": getattr(args, f"secondary{n}", None),
    }
    return {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in values.items() if v is not None}


def cli_geometry_from_args(args: Any) -> Tuple[Geometry, Dict[str, Any]]:
    """Geometry and provenance from the options of ``add_dicom_arguments``."""
    if not (getattr(args, "dicom1", None) and getattr(args, "dicom2", None)):
        raise DicomInputError("--dicom1 and --dicom2 are both needed: one X-ray angiography file per view")
    volume = None
    shape, spacing, center = (getattr(args, k, None) for k in ("volume_shape", "volume_spacing", "volume_center"))
    if shape is not None or spacing is not None or center is not None:
        volume = VolumeGrid(
            tuple(int(v) for v in (shape or DEFAULT_VOLUME.shape)),
            (float(spacing),) * 3 if spacing is not None else DEFAULT_VOLUME.spacing_mm,
            tuple(float(v) for v in (center or DEFAULT_VOLUME.center_mm)),
        )
    return geometry_from_dicom(
        args.dicom1, args.dicom2, frame1=args.frame1, frame2=args.frame2, volume=volume,
        overrides1=_overrides_from_args(args, 1), overrides2=_overrides_from_args(args, 2),
    )


# --- constants -----------------------------------------------------------------------------------
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

DEFAULT_VOLUME = VolumeGrid((128, 128, 128), (0.8, 0.8, 0.8), (0.0, 0.0, 0.0))
OVERRIDE_KEYS = ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_spacing_mm", "principal_point_px")
_CLI_OPTION = {"primary_deg": "--primary", "secondary_deg": "--secondary", "sid_mm": "--sid", "sod_mm": "--sod",
               "pixel_spacing_mm": "--pixel-spacing", "principal_point_px": None}

CONTRAST_MAX_SIDE_PX = 256
CONTRAST_TOPHAT_PX = 15
CONTRAST_NOISE_K = 4.0


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


def _floats(value: Any) -> List[float]:
    if isinstance(value, (list, tuple)) or type(value).__name__ == "MultiValue":
        return [float(v) for v in value]
    return [float(value)]


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

    def lookup(self, keyword: str, frame: int = 0) -> Tuple[Any, Optional[str]]:
        """(value, where) of a non-empty attribute: top level, else the per-frame then shared
        functional groups of an enhanced object; (None, None) when absent or empty."""
        ds = self.dataset
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

    def source(self, keyword: str, where: Optional[str]) -> str:
        return f"tag {tag_label(keyword)}{where or ''}"


def _sop_class_check(ds: Any, path: Path) -> str:
    sop = str(ds.get("SOPClassUID", "") or getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", "") or "")
    if sop in XA_SOP_CLASSES:
        return sop
    from pydicom.uid import UID

    name = UID(sop).name if sop else "no SOP Class UID"
    modality = str(ds.get("Modality", "") or "?")
    raise DicomInputError(
        f"{path} is not an X-ray angiography image: its SOP class is {name} ({sop or 'missing'}), modality {modality}. "
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
    slope, _ = run.lookup("RescaleSlope")
    intercept, _ = run.lookup("RescaleIntercept")
    return (1.0 if slope is None else float(slope), 0.0 if intercept is None else float(intercept))


def load_xa(path: PathLike) -> XARun:
    """Read an XA/XRF (or enhanced) DICOM file: frames as float32 (n, rows, cols), larger = brighter."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    path = Path(path)
    if not path.is_file():
        raise DicomInputError(f"DICOM file not found: {path}")
    try:
        ds = pydicom.dcmread(str(path))
    except InvalidDicomError:
        raise DicomInputError(
            f"{path} is not a DICOM file (no DICOM header); give the X-ray angiography DICOM file, or read "
            "PNG/TIFF/NRRD images with the geometry typed in by hand") from None
    except Exception as exc:  # truncated or corrupt files
        raise DicomInputError(f"{path} cannot be read as DICOM: {exc}") from None
    sop = _sop_class_check(ds, path)
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
    run.frames = values
    return run


# --- frame times and end diastole -------------------------------------------------------------------
def frame_times_ms(run: XARun) -> Tuple[Optional[np.ndarray], str]:
    """Times (ms) of the frames relative to the first, and where they came from (None if unknown)."""
    n = run.num_frames
    vector, _ = run.lookup("FrameTimeVector")
    if vector is not None:
        increments = _floats(vector)
        if len(increments) == n:
            return np.cumsum([0.0] + increments[1:]), f"tag {tag_label('FrameTimeVector')}"
    frame_time, _ = run.lookup("FrameTime")
    if frame_time is not None and float(frame_time) > 0:
        return float(frame_time) * np.arange(n, dtype=np.float64), f"tag {tag_label('FrameTime')}"
    if run.enhanced:
        stamps = []
        for f in range(n):
            value, _ = run.lookup("FrameReferenceDateTime", f)
            if value is None:
                break
            try:
                from pydicom.valuerep import DT

                stamps.append(DT(str(value)))
            except ValueError:
                break
        if len(stamps) == n:
            return (np.array([(s - stamps[0]).total_seconds() * 1000.0 for s in stamps]),
                    f"per-frame tag {tag_label('FrameReferenceDateTime')}")
    return None, "no frame times (looked for FrameTimeVector (0018,1065), FrameTime (0018,1063))"


def _nearest_frames(times: np.ndarray, events_ms: Sequence[float]) -> List[int]:
    step = float(np.median(np.diff(times))) if times.size > 1 else 0.0
    out = []
    for t in events_ms:
        if times.size == 0 or t < times[0] - step / 2 or t > times[-1] + step / 2:
            continue
        out.append(int(np.argmin(np.abs(times - t))))
    return sorted(set(out))


def _ecg_r_peaks_ms(run: XARun) -> Tuple[List[float], str]:
    """R-peak times (ms from the first frame) from an ECG channel of the object's Waveform Sequence."""
    from scipy.signal import find_peaks

    ds = run.dataset
    for index, group in enumerate(ds.get("WaveformSequence") or []):
        channels = group.get("ChannelDefinitionSequence") or []
        ecg = None
        for c, channel in enumerate(channels):
            sources = channel.get("ChannelSourceSequence") or []
            meaning = " ".join(str(s.get("CodeMeaning", "")) for s in sources).lower()
            if "ecg" in meaning or "lead" in meaning or "electrocardiog" in meaning:
                ecg = c
                break
        if ecg is None:
            continue
        try:
            signal = np.asarray(ds.waveform_array(index), dtype=np.float64)[:, ecg]
            rate = float(group.SamplingFrequency)
        except Exception:
            continue
        if signal.size < 3 or rate <= 0:
            continue
        offset = float(group.get("MultiplexGroupTimeOffset", 0.0) or 0.0)
        centred = signal - np.median(signal)
        if abs(centred.min()) > abs(centred.max()):  # inverted lead: R peaks point down
            centred = -centred
        heart_rate, _ = run.lookup("HeartRate")
        # R peaks are at least 0.6 R–R apart (0.33 s, i.e. 180 bpm, without a heart rate): T waves are skipped.
        spacing_s = 0.6 * 60.0 / float(heart_rate) if heart_rate not in (None, 0) else 0.33
        peaks, _ = find_peaks(centred, height=0.6 * centred.max(), distance=max(1, int(spacing_s * rate)))
        hr_text = f", shortest R–R 0.6 × 60/{float(heart_rate):g} bpm from {tag_label('HeartRate')}" if heart_rate else ""
        return ([offset + 1000.0 * p / rate for p in peaks],
                f"R peaks of the ECG channel {ecg + 1} of {tag_label('WaveformSequence')} item {index + 1}{hr_text}")
    return [], ""


def end_diastolic_frames(run: XARun) -> Tuple[List[int], str]:
    """0-based end-diastolic frames and where they came from; ([], why not) when nothing tells."""
    n = run.num_frames
    if run.enhanced:
        marked = []
        for f in range(n):
            value, _ = run.lookup("CardiacCyclePosition", f)
            if value is not None and str(value).strip().upper() == "END_DIASTOLE":
                marked.append(f)
        if marked:
            return marked, f"per-frame tag {tag_label('CardiacCyclePosition')} = END_DIASTOLE"
    pointer, _ = run.lookup("RWavePointer")
    if pointer is not None:
        frames = sorted({int(v) - 1 for v in _floats(pointer) if 1 <= int(v) <= n})
        if frames:
            return frames, f"tag {tag_label('RWavePointer')} (DICOM frame numbers {', '.join(str(f + 1) for f in frames)})"
    times, time_source = frame_times_ms(run)
    r_times, _ = run.lookup("RWaveTimeVector")
    if r_times is not None and times is not None:
        frames = _nearest_frames(times, _floats(r_times))
        if frames:
            return frames, f"tag {tag_label('RWaveTimeVector')} with frame times from {time_source}"
    if times is not None:
        peaks, peak_source = _ecg_r_peaks_ms(run)
        frames = _nearest_frames(times, peaks)
        if frames:
            return frames, f"{peak_source}, frame times from {time_source}"
    return [], ("no R-wave information (looked for CardiacCyclePosition (0018,9236), RWavePointer (0028,6040), "
                "RWaveTimeVector (0018,6060) and an ECG waveform (5400,0100) with frame times)")


# --- contrast --------------------------------------------------------------------------------------
def contrast_scores(frames: np.ndarray) -> np.ndarray:
    """Contrast-filled vessel signal of each frame (see the module docstring); larger = more contrast."""
    from scipy import ndimage

    frames = np.asarray(frames)
    if frames.ndim == 2:
        frames = frames[None]
    if frames.ndim != 3:
        raise ValueError(f"frames must be (n, rows, cols), got shape {frames.shape}")
    factor = max(1, int(math.ceil(max(frames.shape[1:]) / CONTRAST_MAX_SIDE_PX)))
    scores = np.zeros(frames.shape[0])
    floor = float(frames.min())
    for n, frame in enumerate(frames):
        frame = frame.astype(np.float64)  # one frame at a time: long runs stay in float32
        if factor > 1:
            r, c = (frame.shape[0] // factor) * factor, (frame.shape[1] // factor) * factor
            frame = frame[:r, :c].reshape(r // factor, factor, c // factor, factor).mean(axis=(1, 3))
        # The same offset for every frame keeps the log comparable across the run.
        log_image = np.log(frame - floor + 1.0)
        tophat = ndimage.grey_closing(log_image, size=(CONTRAST_TOPHAT_PX, CONTRAST_TOPHAT_PX)) - log_image
        median = float(np.median(tophat))
        noise = 1.4826 * float(np.median(np.abs(tophat - median)))
        keep = tophat > median + CONTRAST_NOISE_K * noise
        scores[n] = float(tophat[keep].sum()) * factor * factor
    return scores


# --- frame choice ----------------------------------------------------------------------------------
@dataclass
class FrameChoice:
    index: int  # 0-based
    method: str  # "user" | "single" | "end-diastole" | "contrast"
    reason: str
    candidates: List[int] = field(default_factory=list)

    def to_dict(self) -> Dict[str, Any]:
        return {"index": int(self.index), "dicom_frame_number": int(self.index) + 1, "method": self.method,
                "reason": self.reason, "candidates": [int(c) for c in self.candidates]}


def check_frame_index(run: XARun, frame: Any) -> int:
    n = run.num_frames
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
        raise DicomInputError(f"{run.path}: the frame must be a whole number (0-based), got {frame!r}")
    if not 0 <= int(frame) < n:
        raise DicomInputError(
            f"{run.path}: frame {int(frame)} is out of range: this run has {n} frame{'s' if n != 1 else ''}, "
            f"numbered 0 to {n - 1} (0-based; DICOM frame number = index + 1)")
    return int(frame)


def choose_frame(run: XARun, frame: Optional[int] = None) -> FrameChoice:
    """The frame to use: ``frame`` if given (0-based), else end diastole, else the most contrast."""
    if frame is not None:
        index = check_frame_index(run, frame)
        return FrameChoice(index, "user", f"frame {index} (0-based) chosen by the user")
    if run.num_frames == 1:
        return FrameChoice(0, "single", "single-frame image")
    scores = contrast_scores(run.frames)
    best_overall = int(np.argmax(scores))
    top = float(scores[best_overall]) or 1.0
    candidates, source = end_diastolic_frames(run)
    if candidates:
        best = max(candidates, key=lambda f: scores[f])
        return FrameChoice(
            best, "end-diastole",
            f"end-diastolic frame from {source}; of the {len(candidates)} end-diastolic frame(s) "
            f"{', '.join(map(str, candidates))} (0-based), frame {best} has the most contrast-filled vessel "
            f"({100.0 * scores[best] / top:.0f}% of the run's best, frame {best_overall})", candidates)
    return FrameChoice(
        best_overall, "contrast",
        f"{source}; chose the frame with the most contrast-filled vessel: frame {best_overall} (0-based) "
        "(summed black top-hat of the log image above the noise floor)", [])


# --- geometry from tags --------------------------------------------------------------------------------
def _check_overrides(overrides: Optional[Dict[str, Any]], path: Path) -> Dict[str, Any]:
    if overrides is None:
        return {}
    if not isinstance(overrides, dict):
        raise DicomInputError(f"{path}: overrides must be a dict such as {{'sod_mm': 765}}, got {type(overrides).__name__}")
    unknown = sorted(set(overrides) - set(OVERRIDE_KEYS))
    if unknown:
        raise DicomInputError(f"{path}: unknown override(s) {', '.join(unknown)}; allowed: {', '.join(OVERRIDE_KEYS)}")
    out: Dict[str, Any] = {}
    for key, value in overrides.items():
        if value is None:
            continue
        if key in ("pixel_spacing_mm", "principal_point_px"):
            values = [value, value] if isinstance(value, (int, float)) and key == "pixel_spacing_mm" else value
            try:
                values = [float(v) for v in values]
            except (TypeError, ValueError):
                values = []
            if len(values) != 2 or not all(math.isfinite(v) for v in values):
                raise DicomInputError(f"{path}: override {key} must be two numbers [row, col], got {value!r}")
            out[key] = values
        else:
            try:
                number = float(value)
            except (TypeError, ValueError):
                number = float("nan")
            if isinstance(value, bool) or not math.isfinite(number):
                raise DicomInputError(f"{path}: override {key} must be a number, got {value!r}")
            out[key] = number
    return out


def _how_to_supply(key: str, view_number: Optional[int]) -> str:
    example = {"sod_mm": "765", "sid_mm": "1000", "pixel_spacing_mm": "[0.3, 0.3]", "primary_deg": "30",
               "secondary_deg": "-20"}.get(key, "…")
    text = f"Supply it as overrides{'' if view_number is None else view_number} = {{'{key}': {example}}}"
    option = _CLI_OPTION.get(key)
    if option:
        n = "N" if view_number is None else str(view_number)
        arg = "ROW COL" if key == "pixel_spacing_mm" else ("MM" if key.endswith("_mm") else "DEG")
        text += f" in Python or {option}{n} {arg} on the command line"
    return text


def _wrap_angle(angle: float) -> float:
    wrapped = (angle + 180.0) % 360.0 - 180.0
    return 180.0 if wrapped == -180.0 and angle > 0 else wrapped


def _frame_angle(run: XARun, keyword: str, increment_keyword: str, frame: int,
                 start: float, start_source: str) -> Tuple[float, str]:
    increments, _ = run.lookup(increment_keyword)
    if increments is None or run.enhanced:
        return start, start_source
    values = _floats(increments)
    n = run.num_frames
    if len(values) == 1:
        angle = start + frame * values[0]
        how = f"start + {frame} × {values[0]:g}° (single average increment per frame)"
    elif len(values) == n:
        angle = start + values[frame]
        how = f"start + increment[{frame}] = {values[frame]:g}°"
    else:
        raise DicomInputError(
            f"{run.path}: {tag_label(increment_keyword)} has {len(values)} values; DICOM (PS3.3 C.8.7.5.1.3) allows "
            f"one (the average change per frame) or one per frame ({n}); give the angle by hand with "
            f"{'primary_deg' if 'Primary' in keyword else 'secondary_deg'} in the overrides")
    if all(v == 0.0 for v in values):
        return start, start_source
    return angle, f"{start_source} of the first frame, {how} from tag {tag_label(increment_keyword)}"


def _tag_pixel_spacing(run: XARun, f: int, sid_over_sod: float, magnification: Any,
                       mag_source: str) -> Tuple[Optional[List[float]], str]:
    """Detector pixel spacing (row, col) from the tags and fallbacks, or (None, "")."""
    rows, cols = run.detector_shape
    spacing_value = None
    spacing_source = ""
    imager, where = run.lookup("ImagerPixelSpacing", f)
    if imager is not None and len(_floats(imager)) == 2:
        spacing_value, spacing_source = _floats(imager), run.source("ImagerPixelSpacing", where)
    if spacing_value is None:
        pixel, where = run.lookup("PixelSpacing", f)
        if pixel is not None and len(_floats(pixel)) == 2:
            calibration, _ = run.lookup("PixelSpacingCalibrationType", f)
            if calibration is None:
                spacing_value = _floats(pixel)
                spacing_source = (f"fallback: {run.source('PixelSpacing', where)}, taken as the detector-plane spacing "
                                  "(no ImagerPixelSpacing; without a PixelSpacingCalibrationType projection images "
                                  "store the detector spacing there)")
            else:
                if magnification is not None:
                    m, m_source = float(magnification), mag_source
                else:
                    m, m_source = sid_over_sod, "SID / SOD"
                spacing_value = [v * m for v in _floats(pixel)]
                spacing_source = (f"fallback: {run.source('PixelSpacing', where)} {_floats(pixel)} calibrated at the "
                                  f"patient ({tag_label('PixelSpacingCalibrationType')} = {calibration}) × "
                                  f"magnification {m:g} ({m_source})")
    if spacing_value is None:
        fov, where = run.lookup("FieldOfViewDimensions", f)
        if fov is None:
            fov, where = run.lookup("FieldOfViewDimensionsInFloat", f)
            fov_keyword = "FieldOfViewDimensionsInFloat"
        else:
            fov_keyword = "FieldOfViewDimensions"
        if fov is not None:
            dims = _floats(fov)
            if len(dims) == 2:
                spacing_value = [dims[0] / rows, dims[1] / cols]
            else:
                spacing_value = [dims[0] / max(rows, cols)] * 2
            spacing_source = (f"fallback: {run.source(fov_keyword, where)} {dims} mm / image size [{rows}, {cols}] "
                              "(assumes the stored image spans the field of view at the detector)")
    if spacing_value is None:
        size, where = run.lookup("IntensifierSize", f)
        if size is not None:
            spacing_value = [float(size) / max(rows, cols)] * 2
            spacing_source = (f"fallback: {run.source('IntensifierSize', where)} {float(size):g} mm / larger image side "
                              f"{max(rows, cols)} (assumes the image spans the intensifier's field)")
    return spacing_value, spacing_source


def _unmodelled_notes(run: XARun, f: int, primary_deg: float) -> List[str]:
    """What the geometry does not model (tilts, flips, mirrored storage): say so rather than mislead."""
    notes: List[str] = []
    for keyword in ("DetectorPrimaryAngle", "DetectorSecondaryAngle", "FieldOfViewRotation"):
        value, where = run.lookup(keyword, f)
        if value is not None and float(value) != 0.0:
            notes.append(f"{run.source(keyword, where)} = {float(value):g}°: not modelled; the geometry assumes 0")
    flip, where = run.lookup("FieldOfViewHorizontalFlip", f)
    if flip is not None and str(flip).strip().upper() == "YES":
        notes.append(f"{run.source('FieldOfViewHorizontalFlip', where)} = YES: the image is mirrored; flip it back "
                     "before reconstructing")
    orientation, _ = run.lookup("PatientOrientation", f)
    if orientation is not None and abs(primary_deg) < 60:
        labels = [str(v).upper() for v in (orientation if not isinstance(orientation, str) else orientation.split("\\"))]
        if len(labels) == 2 and (labels[0].startswith("R") or labels[1].startswith("H")):
            shown = "/".join(labels)
            notes.append(f"{tag_label('PatientOrientation')} = {shown}: "
                         "the image is stored mirrored relative to SDFCAR's convention (columns towards the patient's "
                         "left, rows towards the feet near AP); flip it before reconstructing")
    return notes


def view_from_dicom(
    run: Union[XARun, PathLike],
    frame: Optional[int] = None,
    overrides: Optional[Dict[str, Any]] = None,
    view_number: Optional[int] = None,
) -> Tuple[CArmView, Dict[str, Any]]:
    """The ``CArmView`` of one frame of an XA run and the provenance of every value used.

    ``frame`` is 0-based (None: ``choose_frame``). ``overrides`` replaces or supplies values:
    keys ``primary_deg, secondary_deg, sid_mm, sod_mm, pixel_spacing_mm, principal_point_px``.
    """
    if not isinstance(run, XARun):
        run = load_xa(run)
    user = _check_overrides(overrides, run.path)
    choice = choose_frame(run, frame)
    f = choice.index
    fields: Dict[str, Dict[str, Any]] = {}
    notes: List[str] = []
    label = f"view {view_number} ({run.path})" if view_number is not None else str(run.path)

    def from_user(key: str, tag_value: Any = None, tag_source: str = "") -> bool:
        if key not in user:
            return False
        source = "user"
        if tag_value is not None:
            source += f" (replaces {tag_source} = {tag_value})"
        fields[key] = {"value": user[key], "source": source}
        return True

    def missing(key: str, what: str, looked: str) -> DicomInputError:
        return DicomInputError(f"{label}: the {what} is missing: {looked}. {_how_to_supply(key, view_number)}")

    # Angles (first frame + increments for rotational runs).
    for key, keyword, increment_keyword, what in (
        ("primary_deg", "PositionerPrimaryAngle", "PositionerPrimaryAngleIncrement", "primary angle (LAO +/RAO −)"),
        ("secondary_deg", "PositionerSecondaryAngle", "PositionerSecondaryAngleIncrement", "secondary angle (CRA +/CAU −)"),
    ):
        value, where = run.lookup(keyword, f)
        source = run.source(keyword, where)
        angle = None
        if value is not None:
            angle, source = _frame_angle(run, keyword, increment_keyword, f, float(value), source)
            if angle != _wrap_angle(angle) and key == "primary_deg":
                source += f", wrapped from {angle:g}° into [-180, 180]"
                angle = _wrap_angle(angle)
        if from_user(key, None if angle is None else round(angle, 6), source):
            continue
        if angle is None:
            raise missing(key, what, f"tag {tag_label(keyword)} is absent or empty")
        fields[key] = {"value": float(angle), "source": source}

    # Distances.
    sid, sid_where = run.lookup("DistanceSourceToDetector", f)
    sod, sod_where = run.lookup("DistanceSourceToPatient", f)
    sod_keyword = "DistanceSourceToPatient"
    if sod is None:
        sod, sod_where = run.lookup("DistanceSourceToIsocenter", f)
        sod_keyword = "DistanceSourceToIsocenter"
    magnification, mag_where = run.lookup("EstimatedRadiographicMagnificationFactor", f)
    mag_source = run.source("EstimatedRadiographicMagnificationFactor", mag_where)
    if magnification is not None and not float(magnification) > 0:
        notes.append(f"{mag_source} = {magnification} is not positive and was ignored")
        magnification = None
    sid_value = None if sid is None else float(sid)
    sod_value = None if sod is None else float(sod)
    sid_source = run.source("DistanceSourceToDetector", sid_where)
    sod_source = run.source(sod_keyword, sod_where)
    if not from_user("sid_mm", sid_value, sid_source):
        if sid_value is not None:
            fields["sid_mm"] = {"value": sid_value, "source": sid_source}
        elif "sod_mm" in user or sod_value is not None:
            pass  # resolved from SOD × magnification below
        else:
            raise missing("sid_mm", "source-to-detector distance (SID)",
                          f"tag {tag_label('DistanceSourceToDetector')} is absent or empty")
    if not from_user("sod_mm", sod_value, sod_source):
        if sod_value is not None:
            fields["sod_mm"] = {"value": sod_value, "source": sod_source}
        elif magnification is not None and "sid_mm" in fields:
            m = float(magnification)
            fields["sod_mm"] = {"value": fields["sid_mm"]["value"] / m,
                                "source": f"fallback: SID / {mag_source} ({fields['sid_mm']['value']:g} / {m:g})"}
        else:
            raise missing("sod_mm", "source-to-isocenter distance (SOD)",
                          f"tag {tag_label('DistanceSourceToPatient')} is absent or empty and no fallback applies "
                          f"(SID / {tag_label('EstimatedRadiographicMagnificationFactor')} needs both tags)")
    if "sid_mm" not in fields:
        if magnification is None:
            raise missing("sid_mm", "source-to-detector distance (SID)",
                          f"tag {tag_label('DistanceSourceToDetector')} is absent or empty and no fallback applies "
                          f"(SOD × {tag_label('EstimatedRadiographicMagnificationFactor')} needs that tag)")
        m = float(magnification)
        fields["sid_mm"] = {"value": fields["sod_mm"]["value"] * m,
                            "source": f"fallback: SOD × {mag_source} ({fields['sod_mm']['value']:g} × {m:g})"}

    # Pixel spacing at the detector.
    rows, cols = run.detector_shape
    spacing_value, spacing_source = _tag_pixel_spacing(run, f, fields["sid_mm"]["value"] / fields["sod_mm"]["value"],
                                                       magnification, mag_source)
    if not from_user("pixel_spacing_mm", spacing_value, spacing_source):
        if spacing_value is None:
            raise missing("pixel_spacing_mm", "detector pixel spacing",
                          f"none of {tag_label('ImagerPixelSpacing')}, {tag_label('PixelSpacing')}, "
                          f"{tag_label('FieldOfViewDimensions')}, {tag_label('IntensifierSize')} is present "
                          "(the spacing is the detector element pitch times the binning; the system's DICOM "
                          "conformance statement gives it)")
        fields["pixel_spacing_mm"] = {"value": [float(v) for v in spacing_value], "source": spacing_source}

    fields["detector_shape"] = {"value": [rows, cols], "source": f"tags {tag_label('Rows')}, {tag_label('Columns')}"}
    if not from_user("principal_point_px"):
        fields["principal_point_px"] = {"value": [(rows - 1) / 2.0, (cols - 1) / 2.0],
                                        "source": "default: the image centre (no DICOM tag gives the principal point)"}

    notes.extend(_unmodelled_notes(run, f, fields["primary_deg"]["value"]))

    try:
        view = CArmView(
            primary_deg=float(fields["primary_deg"]["value"]),
            secondary_deg=float(fields["secondary_deg"]["value"]),
            sid_mm=float(fields["sid_mm"]["value"]),
            sod_mm=float(fields["sod_mm"]["value"]),
            pixel_spacing_mm=tuple(float(v) for v in fields["pixel_spacing_mm"]["value"]),
            detector_shape=(rows, cols),
            principal_point_px=tuple(user["principal_point_px"]) if "principal_point_px" in user else None,
        )
    except GeometryError as exc:
        sources = "; ".join(f"{k} from {v['source']}" for k, v in fields.items() if k in str(exc))
        raise DicomInputError(f"{label}: {exc}" + (f" ({sources})" if sources else "")) from None
    provenance = {
        "file": str(run.path),
        "sop_class": run.sop_class_name,
        "transfer_syntax": run.transfer_syntax_name,
        "frames": run.num_frames,
        "frame": choice.to_dict(),
        "fields": fields,
        "notes": notes,
    }
    return view, provenance


def geometry_from_dicom(
    path1: Union[XARun, PathLike],
    path2: Union[XARun, PathLike],
    frame1: Optional[int] = None,
    frame2: Optional[int] = None,
    volume: Optional[Union[VolumeGrid, Dict[str, Any]]] = None,
    overrides1: Optional[Dict[str, Any]] = None,
    overrides2: Optional[Dict[str, Any]] = None,
) -> Tuple[Geometry, Dict[str, Any]]:
    """Two-view ``Geometry`` from two XA files (frames 0-based, None = automatic) and its provenance.

    The default volume is 128³ voxels of 0.8 mm centred at the isocenter.
    """
    from . import __version__

    if volume is None:
        grid, volume_source = DEFAULT_VOLUME, "default: 128³ voxels of 0.8 mm centred at the isocenter"
    elif isinstance(volume, VolumeGrid):
        grid, volume_source = volume, "user"
    else:
        grid, volume_source = VolumeGrid.from_dict(volume), "user"
    view1, prov1 = view_from_dicom(path1, frame1, overrides1, view_number=1)
    view2, prov2 = view_from_dicom(path2, frame2, overrides2, view_number=2)
    geometry = Geometry(volume=grid, views=(view1, view2))
    provenance = {
        "generator": f"SDFCARLib {__version__} dicom.geometry_from_dicom",
        "volume": {"value": grid.to_dict(), "source": volume_source},
        "views": [prov1, prov2],
    }
    return geometry, provenance


def write_geometry_json(path: PathLike, geometry: Geometry, provenance: Optional[Dict[str, Any]] = None) -> Path:
    """Write GEOM.json (the geometry plus a top-level ``provenance``); returns the path."""
    path = Path(path)
    data = geometry.to_dict()
    if provenance is not None:
        data["provenance"] = json_compatible(provenance)
    Geometry.from_dict(data)  # what is written must load
    write_text_atomically(path, json.dumps(data, indent=2, ensure_ascii=False) + "\n")
    return path


# --- writing XA ------------------------------------------------------------------------------------
_NATIVE_SYNTAXES = ("1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.1.99")
_LOSSY_SYNTAXES = {"1.2.840.10008.1.2.4.50", "1.2.840.10008.1.2.4.51", "1.2.840.10008.1.2.4.81",
                   "1.2.840.10008.1.2.4.91", "1.2.840.10008.1.2.4.203"}


def _ds(value: float) -> str:
    """A DS string (≤ 16 characters) that reads back as the same float where it can."""
    text = repr(float(value))
    if len(text) <= 16:
        return text
    from pydicom.valuerep import format_number_as_ds

    return format_number_as_ds(float(value))


def write_xa(
    path: PathLike,
    frames: np.ndarray,
    view: Optional[CArmView] = None,
    *,
    transfer_syntax: str = "1.2.840.10008.1.2.1",
    photometric: str = "MONOCHROME2",
    bits_stored: Optional[int] = None,
    omit: Sequence[str] = (),
    sop_class: str = "XA",
    frame_time_ms: Optional[float] = None,
    frame_time_vector_ms: Optional[Sequence[float]] = None,
    heart_rate_bpm: Optional[float] = None,
    r_wave_frames: Optional[Sequence[int]] = None,
    angle_increments_deg: Optional[Tuple[Sequence[float], Sequence[float]]] = None,
    pixel_spacing_tag: str = "ImagerPixelSpacing",
    extra: Optional[Dict[str, Any]] = None,
    overwrite: bool = False,
) -> Path:
    """Write ``frames`` (rows, cols) or (n, rows, cols), unsigned integers, larger = brighter, as XA.

    ``view`` supplies the positioner tags (angles of the first frame, SID, SOD, magnification and
    the detector spacing under ``pixel_spacing_tag``). MONOCHROME1 stores ``2^bits − 1 − frames``
    so ``load_xa`` gives ``frames`` back. ``r_wave_frames`` are 0-based (stored 1-based).
    ``omit`` lists keywords to leave out; ``extra`` sets further keywords. Multi-frame runs get a
    Frame Time of ``frame_time_ms`` (default 1000/15 ms) unless a Frame Time Vector is given.
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.datadict import tag_for_keyword
    from pydicom.uid import UID, generate_uid

    from . import __version__

    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; choose another name or pass overwrite=True")
    array = np.asarray(frames)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or array.shape[0] < 1:
        raise ValueError(f"frames must be (rows, cols) or (n, rows, cols), got shape {np.shape(frames)}")
    if not np.issubdtype(array.dtype, np.integer) or (array.size and array.min() < 0):
        raise ValueError("frames must be non-negative integers (uint8 or uint16 detector counts); "
                         "make them from line integrals with phantoms.beer_lambert_counts()")
    bits = bits_stored if bits_stored is not None else (8 if array.dtype.itemsize == 1 else 16)
    if bits not in (8, 10, 12, 16):
        raise ValueError(f"bits_stored must be 8, 10, 12 or 16 for XA, got {bits}")
    top = 2**bits - 1
    if array.size and int(array.max()) > top:
        raise ValueError(f"frames reach {int(array.max())}, more than {bits} bits hold ({top})")
    photometric = photometric.upper()
    if photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise ValueError(f"photometric must be MONOCHROME1 or MONOCHROME2, got {photometric!r}")
    sop_uid = {"XA": XA_SOP_CLASS, "XRF": XRF_SOP_CLASS}.get(sop_class.upper())
    if sop_uid is None:
        raise ValueError(f"sop_class must be 'XA' or 'XRF', got {sop_class!r}")
    n, rows, cols = array.shape
    if view is not None and tuple(view.detector_shape) != (rows, cols):
        raise ValueError(f"the view's detector shape {tuple(view.detector_shape)} differs from the frames' {(rows, cols)}")
    if view is not None and view.principal_point_px is not None:
        raise ValueError("the view has a principal point; XA tags cannot carry one (it is read back as the image centre)")
    if pixel_spacing_tag not in ("ImagerPixelSpacing", "PixelSpacing"):
        raise ValueError("pixel_spacing_tag must be 'ImagerPixelSpacing' or 'PixelSpacing'")
    unknown = [k for k in list(omit) + list((extra or {}).keys()) if tag_for_keyword(k) is None]
    if unknown:
        raise ValueError(f"unknown DICOM keyword(s): {', '.join(unknown)}")
    ts = UID(str(transfer_syntax))

    stored = (top - array) if photometric == "MONOCHROME1" else array
    stored = stored.astype(np.uint8 if bits == 8 else np.uint16)

    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = sop_uid
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.1"
    ds.file_meta.ImplementationVersionName = f"SDFCAR_{__version__}"[:16]
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = sop_uid
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = generate_uid(), generate_uid(), generate_uid()
    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = "SDFCAR^Phantom", "SDFCAR", "", ""
    ds.StudyDate = ds.ContentDate = ds.SeriesDate = "20000101"
    ds.StudyTime = ds.ContentTime = ds.SeriesTime = "000000"
    ds.ReferringPhysicianName, ds.StudyID, ds.AccessionNumber = "", "1", ""
    ds.Modality = "XA" if sop_uid == XA_SOP_CLASS else "RF"
    ds.SeriesNumber, ds.InstanceNumber = 1, 1
    ds.Manufacturer = "SDFCAR (simulated)"
    ds.ImageType = ["DERIVED", "PRIMARY", "SINGLE PLANE"]
    ds.PatientOrientation = ["L", "F"]  # columns → patient's left, rows → feet (SDFCAR's convention near AP)
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = photometric
    ds.Rows, ds.Columns = rows, cols
    ds.BitsAllocated = 8 if bits == 8 else 16
    ds.BitsStored, ds.HighBit, ds.PixelRepresentation = bits, bits - 1, 0
    ds.PixelIntensityRelationship = "LIN"
    ds.PixelIntensityRelationshipSign = 1 if photometric == "MONOCHROME2" else -1
    ds.KVP, ds.RadiationSetting = "", "GR"
    ds.LossyImageCompression = "00"
    if n > 1:
        ds.NumberOfFrames = n
        if frame_time_vector_ms is not None:
            vector = [float(v) for v in frame_time_vector_ms]
            if len(vector) != n:
                raise ValueError(f"frame_time_vector_ms needs {n} values (the first 0), got {len(vector)}")
            ds.FrameTimeVector = [_ds(v) for v in vector]
            ds.FrameIncrementPointer = tag_for_keyword("FrameTimeVector")
        else:
            ds.FrameTime = _ds(1000.0 / 15.0 if frame_time_ms is None else float(frame_time_ms))
            ds.FrameIncrementPointer = tag_for_keyword("FrameTime")
    elif frame_time_ms is not None:
        ds.FrameTime = _ds(float(frame_time_ms))
    if heart_rate_bpm is not None:
        ds.HeartRate = int(round(float(heart_rate_bpm)))
    if r_wave_frames is not None:
        values = [int(v) for v in r_wave_frames]
        if any(not 0 <= v < n for v in values):
            raise ValueError(f"r_wave_frames are 0-based frame indices in [0, {n - 1}], got {values}")
        ds.RWavePointer = [v + 1 for v in values]
    if view is not None:
        ds.PositionerMotion = "STATIC"
        ds.PositionerPrimaryAngle = _ds(view.primary_deg)
        ds.PositionerSecondaryAngle = _ds(view.secondary_deg)
        ds.DistanceSourceToDetector = _ds(view.sid_mm)
        ds.DistanceSourceToPatient = _ds(view.sod_mm)
        ds.EstimatedRadiographicMagnificationFactor = _ds(view.sid_mm / view.sod_mm)
        setattr(ds, pixel_spacing_tag, [_ds(v) for v in view.pixel_spacing_mm])
    if angle_increments_deg is not None:
        primary_inc, secondary_inc = ([float(v) for v in np.atleast_1d(a)] for a in angle_increments_deg)
        for name, values in (("primary", primary_inc), ("secondary", secondary_inc)):
            if len(values) not in (1, n):
                raise ValueError(f"{name} angle increments need 1 or {n} values, got {len(values)}")
        ds.PositionerMotion = "DYNAMIC"
        ds.PositionerPrimaryAngleIncrement = [_ds(v) for v in primary_inc]
        ds.PositionerSecondaryAngleIncrement = [_ds(v) for v in secondary_inc]
    for keyword, value in (extra or {}).items():
        setattr(ds, keyword, value)
    for keyword in omit:
        if keyword in ds:
            del ds[keyword]

    ds.PixelData = stored.tobytes()
    if str(ts) in _NATIVE_SYNTAXES:
        ds.file_meta.TransferSyntaxUID = ts
    else:
        try:
            from pydicom.pixels.encoders.base import get_encoder
        except ImportError:  # pydicom 2
            from pydicom.encoders import get_encoder

        try:
            encoder = get_encoder(ts)
        except NotImplementedError:
            raise ValueError(
                f"pydicom has no encoder for {ts.name} ({ts}); write RLE Lossless (1.2.840.10008.1.2.5) or JPEG 2000 "
                "Lossless (1.2.840.10008.1.2.4.90) instead, or convert afterwards (DCMTK dcmcjpeg, GDCM gdcmconv)") from None
        if not encoder.is_available:
            package = _DECODER_PACKAGES.get(str(ts), "pylibjpeg")
            raise ValueError(f"the {ts.name} encoder is not available here ({'; '.join(encoder.missing_dependencies)}); "
                             f"pip install {package}, or write RLE Lossless, which pydicom encodes itself")
        ds.compress(ts, stored.reshape(n, rows, cols) if n > 1 else stored[0], generate_instance_uid=False)
        if str(ts) in _LOSSY_SYNTAXES:
            ds.LossyImageCompression = "01"

    def save(tmp: Path) -> None:
        try:
            ds.save_as(str(tmp), enforce_file_format=True)
        except TypeError:  # pydicom 2
            ds.save_as(str(tmp), write_like_original=False)

    atomic_write(path, save)
    return path
