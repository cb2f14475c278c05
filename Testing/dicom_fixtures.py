"""Helpers that build X-ray angiography DICOM test objects with pydicom (no binary fixtures).

* ``encode_jpeg_lossless_sv1`` — a minimal JPEG Lossless encoder (ITU-T T.81 process 14,
  first-order prediction = selection value 1, one fixed Huffman table), written from the standard
  because no encoder for this syntax is installed here; the decoders under test are pydicom's
  (pylibjpeg-libjpeg).
* ``raw_xa`` — an XA dataset assembled by hand from stored values (independent of ``xa_writer.write_xa``).
* ``recompress`` — re-encapsulate a native file as JPEG Lossless SV1 or JPEG baseline (Pillow).
* ``make_enhanced`` — turn a classic XA file into an Enhanced XA object with the geometry in the
  functional groups.
* ``add_ecg`` — embed an ECG channel (Waveform Sequence) with R peaks at given times.
* ``contrast_run`` — a synthetic cine run in which contrast fills a vessel tree and washes out.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.sequence import Sequence as DicomSequence
from pydicom.uid import (ExplicitVRLittleEndian, JPEGBaseline8Bit, JPEGLosslessSV1, UID,
                         XRayAngiographicImageStorage, generate_uid)

ENHANCED_XA = "1.2.840.10008.5.1.4.1.1.12.1.1"


def encode_jpeg_lossless_sv1(frame: np.ndarray, precision: int) -> bytes:
    """One greyscale frame as a JPEG Lossless (process 14, predictor 1) codestream."""
    a = np.asarray(frame).astype(np.int64)
    rows, cols = a.shape
    # Predictors (T.81 H.1.2.1): first sample 2^(P-1), first row left, first column above, else left.
    pred = np.empty_like(a)
    pred[0, 0] = 1 << (precision - 1)
    pred[0, 1:] = a[0, :-1]
    pred[1:, 0] = a[:-1, 0]
    pred[1:, 1:] = a[1:, :-1]
    diff = (a - pred) % 65536
    diff = np.where(diff >= 32768, diff - 65536, diff)
    out = bytearray(b"\xff\xd8")
    out += b"\xff\xc3" + struct.pack(">HBHHB", 11, precision, rows, cols, 1) + bytes([1, 0x11, 0])
    # Huffman table: the 17 difference categories all get 5-bit codes 0..16 (never all ones).
    bits = [0] * 16
    bits[4] = 17
    table = bytes([0x00]) + bytes(bits) + bytes(range(17))
    out += b"\xff\xc4" + struct.pack(">H", 2 + len(table)) + table
    out += b"\xff\xda" + struct.pack(">HB", 8, 1) + bytes([1, 0x00, 1, 0, 0])
    data = bytearray()
    acc, nacc = 0, 0
    for d in diff.reshape(-1).tolist():
        s = 16 if d == -32768 else (0 if d == 0 else abs(d).bit_length())
        acc, nacc = (acc << 5) | s, nacc + 5
        if 0 < s < 16:
            acc, nacc = (acc << s) | ((d if d > 0 else d - 1) & ((1 << s) - 1)), nacc + s
        while nacc >= 8:
            nacc -= 8
            byte = (acc >> nacc) & 0xFF
            data.append(byte)
            if byte == 0xFF:
                data.append(0)  # byte stuffing
        acc &= (1 << nacc) - 1
    if nacc:
        byte = ((acc << (8 - nacc)) | ((1 << (8 - nacc)) - 1)) & 0xFF
        data.append(byte)
        if byte == 0xFF:
            data.append(0)
    return bytes(out + data + b"\xff\xd9")


def _save(ds: Dataset, path: Path) -> Path:
    ds.save_as(str(path), enforce_file_format=True)
    return path


def raw_xa(path: Path, stored: np.ndarray, bits_stored: int, photometric: str = "MONOCHROME2",
           sop_class: str = XRayAngiographicImageStorage, **tags) -> Path:
    """An XA file from stored pixel values, built attribute by attribute (explicit VR little endian)."""
    stored = np.asarray(stored)
    if stored.ndim == 2:
        stored = stored[None]
    n, rows, cols = stored.shape
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = sop_class
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality = "XA"
    ds.Rows, ds.Columns = rows, cols
    if n > 1:
        ds.NumberOfFrames = n
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = photometric
    ds.BitsAllocated = 8 if bits_stored == 8 else 16
    ds.BitsStored, ds.HighBit, ds.PixelRepresentation = bits_stored, bits_stored - 1, 0
    for keyword, value in tags.items():
        setattr(ds, keyword, value)
    ds.PixelData = stored.astype(np.uint8 if bits_stored == 8 else np.uint16).tobytes()
    return _save(ds, path)


def recompress(src: Path, dst: Path, syntax: str) -> Path:
    """Re-encapsulate a native XA file as JPEG Lossless SV1 or JPEG baseline (8 bit, Pillow)."""
    ds = pydicom.dcmread(str(src))
    frames = ds.pixel_array.reshape(int(ds.get("NumberOfFrames", 1) or 1), ds.Rows, ds.Columns)
    if UID(syntax) == JPEGLosslessSV1:
        encoded = [encode_jpeg_lossless_sv1(f, int(ds.BitsStored)) for f in frames]
    elif UID(syntax) == JPEGBaseline8Bit:
        from PIL import Image

        if int(ds.BitsStored) != 8:
            raise ValueError("JPEG baseline holds 8-bit frames only")
        encoded = []
        for f in frames:
            buffer = io.BytesIO()
            Image.fromarray(f.astype(np.uint8)).save(buffer, format="JPEG", quality=95)
            encoded.append(buffer.getvalue())
        ds.LossyImageCompression = "01"
    else:
        raise ValueError(f"recompress does not make {syntax}")
    ds.PixelData = encapsulate(encoded)
    ds["PixelData"].VR = "OB"
    ds.file_meta.TransferSyntaxUID = syntax
    return _save(ds, dst)


_ENHANCED_GEOMETRY = {
    # keyword in the classic object → (functional group sequence, keyword inside it)
    "PositionerPrimaryAngle": ("PositionerPositionSequence", "PositionerPrimaryAngle"),
    "PositionerSecondaryAngle": ("PositionerPositionSequence", "PositionerSecondaryAngle"),
    "DistanceSourceToDetector": ("XRayGeometrySequence", "DistanceSourceToDetector"),
    "DistanceSourceToPatient": ("XRayGeometrySequence", "DistanceSourceToIsocenter"),
    "ImagerPixelSpacing": ("FramePixelDataPropertiesSequence", "ImagerPixelSpacing"),
}


def make_enhanced(src: Path, dst: Path, per_frame_primary: Optional[Sequence[float]] = None,
                  end_diastole: Sequence[int] = ()) -> Path:
    """An Enhanced XA copy of a classic XA file: geometry moved into the functional groups.

    Distances and spacing go to the shared groups; the angles go per frame (``per_frame_primary``
    replaces the primary angle of each frame); frames in ``end_diastole`` (0-based) get
    Cardiac Cycle Position END_DIASTOLE in their Frame Content.
    """
    ds = pydicom.dcmread(str(src))
    n = int(ds.get("NumberOfFrames", 1) or 1)
    ds.SOPClassUID = ENHANCED_XA
    ds.file_meta.MediaStorageSOPClassUID = ENHANCED_XA
    shared = Dataset()
    per_frame = [Dataset() for _ in range(n)]
    for keyword, (group, inner) in _ENHANCED_GEOMETRY.items():
        if keyword not in ds:
            continue
        value = ds[keyword].value
        del ds[keyword]
        if group == "PositionerPositionSequence":
            for f, item in enumerate(per_frame):
                sequence = getattr(item, group, None)
                if sequence is None:
                    setattr(item, group, DicomSequence([Dataset()]))
                    sequence = getattr(item, group)
                angle = float(value)
                if inner == "PositionerPrimaryAngle" and per_frame_primary is not None:
                    angle = float(per_frame_primary[f])
                setattr(sequence[0], inner, angle)
        else:
            sequence = getattr(shared, group, None)
            if sequence is None:
                setattr(shared, group, DicomSequence([Dataset()]))
                sequence = getattr(shared, group)
            setattr(sequence[0], inner, [float(v) for v in value] if inner == "ImagerPixelSpacing" else float(value))
    for f, item in enumerate(per_frame):
        content = Dataset()
        content.FrameAcquisitionNumber = f + 1
        if f in end_diastole:
            content.CardiacCyclePosition = "END_DIASTOLE"
        item.FrameContentSequence = DicomSequence([content])
    for keyword in ("PositionerPrimaryAngleIncrement", "PositionerSecondaryAngleIncrement", "RWavePointer"):
        if keyword in ds:
            del ds[keyword]
    ds.SharedFunctionalGroupsSequence = DicomSequence([shared])
    ds.PerFrameFunctionalGroupsSequence = DicomSequence(per_frame)
    return _save(ds, dst)


def add_ecg(path: Path, r_peaks_ms: Sequence[float], duration_ms: float, rate_hz: float = 500.0,
            offset_ms: float = 0.0, inverted: bool = False) -> Path:
    """Embed a one-channel ECG (narrow R spikes on a small T wave) in the file's Waveform Sequence."""
    ds = pydicom.dcmread(str(path))
    t = np.arange(0.0, duration_ms, 1000.0 / rate_hz)
    signal = np.zeros_like(t)
    for r in r_peaks_ms:
        signal += 1000.0 * np.exp(-0.5 * ((t - r) / 8.0) ** 2)  # QRS
        signal += 250.0 * np.exp(-0.5 * ((t - r - 250.0) / 40.0) ** 2)  # T wave
    if inverted:
        signal = -signal
    samples = np.round(signal).astype(np.int16)
    group = Dataset()
    group.MultiplexGroupTimeOffset = offset_ms
    group.WaveformOriginality = "ORIGINAL"
    group.NumberOfWaveformChannels = 1
    group.NumberOfWaveformSamples = int(samples.size)
    group.SamplingFrequency = rate_hz
    channel = Dataset()
    source = Dataset()
    source.CodeValue, source.CodingSchemeDesignator, source.CodeMeaning = "2:1", "MDC", "Lead I (Einthoven)"
    channel.ChannelSourceSequence = DicomSequence([source])
    channel.ChannelSensitivity = 1.0
    channel.ChannelSensitivityCorrectionFactor = 1.0
    channel.ChannelBaseline = 0.0
    channel.ChannelSampleSkew = 0.0
    channel.WaveformBitsStored = 16
    group.ChannelDefinitionSequence = DicomSequence([channel])
    group.WaveformBitsAllocated = 16
    group.WaveformSampleInterpretation = "SS"
    group.WaveformData = samples.tobytes()
    ds.WaveformSequence = DicomSequence([group])
    return _save(ds, path)


def contrast_run(n_frames: int, peak: int, shape=(96, 96), seed: int = 0, gain_drift: float = 0.15,
                 bits: int = 12) -> np.ndarray:
    """Detector counts (n, rows, cols) of a run: dark vessels whose contrast rises to frame ``peak``
    and washes out, over a bright, smoothly varying, noisy background with a drifting exposure."""
    rng = np.random.default_rng(seed)
    rows, cols = shape
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    path = np.zeros(shape)
    for k in range(4):  # a few curved tubes, 2–5 px wide
        centre = rows * (0.2 + 0.2 * k) + 6.0 * np.sin(xx / (9.0 + 3 * k))
        width = 1.0 + 0.6 * k
        path += 2.0 * np.exp(-0.5 * ((yy - centre) / width) ** 2) * (xx > 5 + 7 * k)
    path += 1.5 * np.exp(-0.5 * ((xx - cols * 0.55) / 1.8) ** 2)
    background = 0.6 + 0.3 * xx / cols + 0.1 * np.cos(yy / rows * 3.0)  # tissue, in attenuation units
    times = np.arange(n_frames)
    contrast = np.exp(-0.5 * ((times - peak) / 2.0) ** 2)  # fills in, washes out
    top = 2**bits - 1
    frames = []
    for f in range(n_frames):
        gain = 1.0 + gain_drift * np.sin(1.7 * f)
        counts = 0.8 * top * gain * np.exp(-(background + 0.8 * contrast[f] * path))
        counts = counts + rng.normal(0.0, 0.01 * top, shape)
        frames.append(np.clip(np.rint(counts), 0, top))
    return np.asarray(frames, dtype=np.uint16)
