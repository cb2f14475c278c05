"""Frame timing and frame choice: frame times, ECG R peaks, end diastole, contrast scores.

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

scipy and pydicom are imported inside the functions, for the reason given in ``read``: the
command line loads this package for its options, and most runs read no DICOM file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .read import DicomInputError, XARun, tag_floats, tag_label


# --- frame times and end diastole -------------------------------------------------------------------
def frame_times_ms(run: XARun) -> Tuple[Optional[np.ndarray], str]:
    """Times (ms) of the frames relative to the first, and where they came from (None if unknown)."""
    n = run.num_frames
    vector, _ = run.lookup("FrameTimeVector")
    if vector is not None:
        increments = tag_floats(vector)
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
        frames = sorted({int(v) - 1 for v in tag_floats(pointer) if 1 <= int(v) <= n})
        if frames:
            return frames, f"tag {tag_label('RWavePointer')} (DICOM frame numbers {', '.join(str(f + 1) for f in frames)})"
    times, time_source = frame_times_ms(run)
    r_times, _ = run.lookup("RWaveTimeVector")
    if r_times is not None and times is not None:
        frames = _nearest_frames(times, tag_floats(r_times))
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
# Frames are reduced to at most this many pixels a side; top-hat window; noise floor in robust SDs.
CONTRAST_MAX_SIDE_PX = 256
CONTRAST_TOPHAT_PX = 15
CONTRAST_NOISE_K = 4.0


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
