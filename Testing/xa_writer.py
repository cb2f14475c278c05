"""A DICOM XA writer for the tests: valid single- and multi-frame XA/XRF objects from detector counts.

``write_xa`` writes a valid XA object (multi-frame for a 3-D array) with the positioner tags of a
``CArmView``, native or compressed with the encoders pydicom has here (RLE Lossless always; JPEG
2000 with pylibjpeg-openjpeg). pydicom has no JPEG baseline / JPEG lossless encoder: those are
refused with a message (``dicom_fixtures.recompress`` makes them). It lives with the tests because
SDFCAR only reads DICOM: the product ships no writer.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.datadict import tag_for_keyword
from pydicom.uid import UID, generate_uid
from pydicom.valuerep import format_number_as_ds

from SDFCARLib import __version__
from SDFCARLib.dicom.read import _DECODER_PACKAGES, XA_SOP_CLASS, XRF_SOP_CLASS, PathLike
from SDFCARLib.geometry import CArmView
from SDFCARLib.io import atomic_write

_NATIVE_SYNTAXES = ("1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.1.99")
_LOSSY_SYNTAXES = {"1.2.840.10008.1.2.4.50", "1.2.840.10008.1.2.4.51", "1.2.840.10008.1.2.4.81",
                   "1.2.840.10008.1.2.4.91", "1.2.840.10008.1.2.4.203"}


def _ds(value: float) -> str:
    """A DS string (≤ 16 characters) that reads back as the same float where it can."""
    text = repr(float(value))
    if len(text) <= 16:
        return text
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
