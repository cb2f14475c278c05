"""The C-arm geometry of a view from the DICOM tags (``view_from_dicom``, ``geometry_from_dicom_runs``).

The XA Positioner Module (DICOM PS3.3 C.8.7.5) defines the angles with the patient supine:
Positioner Primary Angle (0018,1510) in the transaxial plane, 0° perpendicular to the chest,
+90° at the patient's left (LAO), −90° at the right (RAO); Positioner Secondary Angle (0018,1511)
in the sagittal plane, +90° cranial; at 0°/0° the patient faces the image intensifier /
detector (C.8.7.5.1.2). These are the angles of the detector direction d in ``SDFCARLib.geometry``
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
dict (``{"sod_mm": 765, "pixel_spacing_mm": [0.3, 0.3]}``) or ``--sod1`` / ``--sod`` … on the
command line — never a silent default. A user value replaces the tag's. Every value used is reported
with its source in the provenance, which ``write_geometry_json`` stores in GEOM.json.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

from .. import __version__
from ..evidence import unreadable_intensity
from ..geometry import CArmView, Geometry, GeometryError, VolumeGrid
from ..io import json_compatible, write_text_atomically
from ..settings import PAPER_SPACING_MM, PAPER_VOLUME_SHAPE
from .frames import choose_frame
from .read import DicomInputError, PathLike, XARun, load_xa, tag_floats, tag_label, tag_number

#: The reconstruction grid when none is given: 128³ voxels of 0.8 mm centred at the isocenter.
DEFAULT_VOLUME = VolumeGrid(PAPER_VOLUME_SHAPE, (PAPER_SPACING_MM,) * 3, (0.0, 0.0, 0.0))


# --- overrides -------------------------------------------------------------------------------------
#: a C-arm's source-to-detector distance is 900–1200 mm; under this a value in cm is the likely cause
MIN_PLAUSIBLE_SID_MM = 300.0
OVERRIDE_KEYS = ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_spacing_mm", "principal_point_px")
# The command-line options of ``cli.add_dicom_arguments`` per key, for the messages saying how to
# supply a value (named here because ``cli`` imports this module).
_CLI_OPTION = {"primary_deg": "--primary", "secondary_deg": "--secondary", "sid_mm": "--sid", "sod_mm": "--sod",
               "pixel_spacing_mm": "--pixel-spacing", "principal_point_px": None}


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
    numbered = view_number is not None and view_number <= 2  # --sod1/--sod2 exist for two runs only
    if view_number is None or numbered:
        text = f"Supply it as overrides{'' if view_number is None else view_number} = {{'{key}': {example}}}"
    else:
        text = f"Supply it as {{'{key}': {example}}} in the overrides of view {view_number}"
    option = _CLI_OPTION.get(key)
    if option:
        arg = "ROW COL" if key == "pixel_spacing_mm" else ("MM" if key.endswith("_mm") else "DEG")
        spacing = "; ROW,COL for unequal spacings" if key == "pixel_spacing_mm" else ""
        listed = f"{option} with one value per --dicom run ('auto' keeps a run's tags{spacing})"
        if view_number is None:
            text += f" in Python, or on the command line as {option}N {arg} (--dicom1/--dicom2) or {listed}"
        elif numbered:
            text += f" in Python or {option}{view_number} {arg} on the command line (with --dicom A B …: {listed})"
        else:
            text += f" in Python, or on the command line as value {view_number} of {listed}"
    return text


# --- angles, pixel spacing and what is not modelled --------------------------------------------------
def _wrap_angle(angle: float) -> float:
    if -180.0 <= angle <= 180.0:
        return angle  # the modulo below moves an in-range angle by rounding (−0.8 → −0.8000000000000114)
    wrapped = (angle + 180.0) % 360.0 - 180.0
    return 180.0 if wrapped == -180.0 and angle > 0 else wrapped


def _frame_angle(run: XARun, keyword: str, increment_keyword: str, frame: int,
                 start: float, start_source: str) -> Tuple[float, str]:
    increments, where = run.lookup(increment_keyword)
    if increments is None or run.enhanced:
        return start, start_source
    try:
        values = tag_floats(increments)
    except (TypeError, ValueError):
        raise DicomInputError(
            f"{run.path}: {run.source(increment_keyword, where)} = {str(increments).strip()!r} is not a list of numbers; "
            f"give the angle by hand with {'primary_deg' if 'Primary' in keyword else 'secondary_deg'} in the "
            "overrides") from None
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


def _numbers_or_none(value: Any) -> List[float]:
    """A spacing tag's finite numbers, or [] when absent or not numbers (named by the missing-spacing message)."""
    try:
        numbers = [] if value is None else tag_floats(value)
    except (TypeError, ValueError):
        return []
    return numbers if all(math.isfinite(v) for v in numbers) else []


def _tag_pixel_spacing(run: XARun, f: int, sid_over_sod: float, magnification: Any,
                       mag_source: str) -> Tuple[Optional[List[float]], str]:
    """Detector pixel spacing (row, col) from the tags and fallbacks, or (None, "")."""
    rows, cols = run.detector_shape
    spacing_value = None
    spacing_source = ""
    imager, where = run.lookup("ImagerPixelSpacing", f)
    if len(_numbers_or_none(imager)) == 2:
        spacing_value, spacing_source = tag_floats(imager), run.source("ImagerPixelSpacing", where)
    if spacing_value is None:
        pixel, where = run.lookup("PixelSpacing", f)
        if len(_numbers_or_none(pixel)) == 2:
            calibration, _ = run.lookup("PixelSpacingCalibrationType", f)
            if calibration is None:
                spacing_value = tag_floats(pixel)
                spacing_source = (f"fallback: {run.source('PixelSpacing', where)}, taken as the detector-plane spacing "
                                  "(no ImagerPixelSpacing; without a PixelSpacingCalibrationType projection images "
                                  "store the detector spacing there)")
            else:
                if magnification is not None:
                    m, m_source = float(magnification), mag_source
                else:
                    m, m_source = sid_over_sod, "SID / SOD"
                spacing_value = [v * m for v in tag_floats(pixel)]
                spacing_source = (f"fallback: {run.source('PixelSpacing', where)} {tag_floats(pixel)} calibrated at the "
                                  f"patient ({tag_label('PixelSpacingCalibrationType')} = {calibration}) × "
                                  f"magnification {m:g} ({m_source})")
    if spacing_value is None:
        fov, where = run.lookup("FieldOfViewDimensions", f)
        if fov is None:
            fov, where = run.lookup("FieldOfViewDimensionsInFloat", f)
            fov_keyword = "FieldOfViewDimensionsInFloat"
        else:
            fov_keyword = "FieldOfViewDimensions"
        dims = _numbers_or_none(fov)
        if len(dims) in (1, 2):  # a square or round field (one value), or rows × columns; anything else is unusable
            if len(dims) == 2:
                spacing_value = [dims[0] / rows, dims[1] / cols]
            else:
                spacing_value = [dims[0] / max(rows, cols)] * 2
            spacing_source = (f"fallback: {run.source(fov_keyword, where)} {dims} mm / image size [{rows}, {cols}] "
                              "(assumes the stored image spans the field of view at the detector)")
    if spacing_value is None:
        size, where = run.lookup("IntensifierSize", f)
        try:
            size = None if size is None else tag_number(size)
        except ValueError:
            size = None  # named by view_from_dicom's message when no spacing is found
        if size is not None:
            spacing_value = [size / max(rows, cols)] * 2
            spacing_source = (f"fallback: {run.source('IntensifierSize', where)} {size:g} mm / larger image side "
                              f"{max(rows, cols)} (assumes the image spans the intensifier's field)")
    return spacing_value, spacing_source


def burned_in_annotation_note(run: XARun, frame: int = 0) -> Optional[str]:
    """The note for a run whose pixels carry burned-in annotation (0028,0301 YES), else None: text or marks drawn
    dark stand out of the background as vessels do, and the mask pipeline keeps them (bench/RESULTS.md §103d)."""
    value, where = run.lookup("BurnedInAnnotation", frame)
    if value is None or str(value).strip().upper() != "YES":
        return None
    return (f"{run.source('BurnedInAnnotation', where)} = YES: text or marks are drawn into this run's pixels; "
            "where they are drawn dark, a mask segmented from the frame takes them for vessels: check the masks there "
            "and erase them (Segment Editor, or an image editor), or export the run without the annotation")


def _unmodelled_notes(run: XARun, f: int, primary_deg: float) -> List[str]:
    """What the geometry does not model (tilts, flips, mirrored storage): say so rather than mislead."""
    notes: List[str] = []
    for keyword in ("DetectorPrimaryAngle", "DetectorSecondaryAngle", "FieldOfViewRotation"):
        value, where = run.lookup(keyword, f)
        if value is None:
            continue
        try:
            angle = tag_number(value)
        except ValueError as exc:
            notes.append(f"{run.source(keyword, where)} {exc}: not read; the geometry assumes 0")
            continue
        if angle != 0.0:
            notes.append(f"{run.source(keyword, where)} = {angle:g}°: not modelled; the geometry assumes 0")
    note = burned_in_annotation_note(run, f)
    if note:
        notes.append(note)
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


# --- the views and the geometry ----------------------------------------------------------------------
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

    def tag_value(key: Optional[str], keyword: str, value: Any, where: Optional[str]) -> Optional[float]:
        """The tag's one number; one that holds no single number is refused naming the fix, or noted and
        left out where the user gives ``key`` (or, with ``key`` None, where a fallback only may use it)."""
        if value is None:
            return None
        try:
            return tag_number(value)
        except ValueError as exc:
            problem = f"{run.source(keyword, where)} {exc}"
        if key is None or key in user:
            notes.append(f"{problem}: not used")
            return None
        raise DicomInputError(f"{label}: {problem}. {_how_to_supply(key, view_number)}")

    # Angles (first frame + increments for rotational runs).
    for key, keyword, increment_keyword, what in (
        ("primary_deg", "PositionerPrimaryAngle", "PositionerPrimaryAngleIncrement", "primary angle (LAO +/RAO −)"),
        ("secondary_deg", "PositionerSecondaryAngle", "PositionerSecondaryAngleIncrement", "secondary angle (CRA +/CAU −)"),
    ):
        value, where = run.lookup(keyword, f)
        source = run.source(keyword, where)
        angle = None
        start = tag_value(key, keyword, value, where)
        if start is not None:
            angle, source = _frame_angle(run, keyword, increment_keyword, f, start, source)
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
    magnification = tag_value(None, "EstimatedRadiographicMagnificationFactor", magnification, mag_where)
    if magnification is not None and not magnification > 0:
        notes.append(f"{mag_source} = {magnification:g} is not positive and was ignored")
        magnification = None
    sid_value = tag_value("sid_mm", "DistanceSourceToDetector", sid, sid_where)
    sod_value = tag_value("sod_mm", sod_keyword, sod, sod_where)
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
            keywords = ("ImagerPixelSpacing", "PixelSpacing", "FieldOfViewDimensions", "IntensifierSize")
            unusable = [f"{tag_label(k)} = {str(run.lookup(k, f)[0]).strip()!r}" for k in keywords
                        if run.lookup(k, f)[0] is not None]
            raise missing("pixel_spacing_mm", "detector pixel spacing",
                          f"none of {', '.join(tag_label(k) for k in keywords)} gives it"
                          f"{' (present but not usable: ' + '; '.join(unusable) + ')' if unusable else ' (none is present)'} "
                          "(the spacing is the detector element pitch times the binning; the system's DICOM "
                          "conformance statement gives it)")
        fields["pixel_spacing_mm"] = {"value": [float(v) for v in spacing_value], "source": spacing_source}

    fields["detector_shape"] = {"value": [rows, cols], "source": f"tags {tag_label('Rows')}, {tag_label('Columns')}"}
    if not from_user("principal_point_px"):
        fields["principal_point_px"] = {"value": [(rows - 1) / 2.0, (cols - 1) / 2.0],
                                        "source": "default: the image centre (no DICOM tag gives the principal point)"}

    notes.extend(_unmodelled_notes(run, f, fields["primary_deg"]["value"]))
    processed = unreadable_intensity(run.frames_relationship)
    if run.linearised_note:
        notes.append(f"this run's frames: {run.linearised_note}")
    if processed:  # said with the geometry, before the run: its frames' path lengths will not be fitted
        notes.append(f"this run's frames give no path lengths — {processed}; reconstructing fits the masks alone "
                     "(the frames still place the views)")

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


def geometry_from_dicom_runs(
    runs: Sequence[Union[XARun, PathLike]],
    frames: Optional[Sequence[Optional[int]]] = None,
    volume: Optional[Union[VolumeGrid, Dict[str, Any]]] = None,
    overrides: Optional[Sequence[Optional[Dict[str, Any]]]] = None,
) -> Tuple[Geometry, Dict[str, Any]]:
    """``Geometry`` of any number (at least two) of XA runs, view n from run n, and its provenance.

    ``frames`` and ``overrides`` hold one entry per run (0-based frame or None = automatic; an
    overrides dict or None). The default volume is 128³ voxels of 0.8 mm centred at the isocenter.
    """
    runs = list(runs)
    if len(runs) < 2:
        raise DicomInputError(f"a reconstruction needs at least two XA runs (one per view), got {len(runs)}")
    frames = [None] * len(runs) if frames is None else list(frames)
    overrides = [None] * len(runs) if overrides is None else list(overrides)
    for what, values in (("frames", frames), ("overrides", overrides)):
        if len(values) != len(runs):
            raise DicomInputError(f"{len(values)} {what} for {len(runs)} runs: give one per run, in the runs' order "
                                  "(None for the automatic choice)")
    if volume is None:
        grid, volume_source = DEFAULT_VOLUME, "default: 128³ voxels of 0.8 mm centred at the isocenter"
    elif isinstance(volume, VolumeGrid):
        grid, volume_source = volume, "user"
    else:
        grid, volume_source = VolumeGrid.from_dict(volume), "user"
    read = [view_from_dicom(run, frame, extra, view_number=n)
            for n, (run, frame, extra) in enumerate(zip(runs, frames, overrides), start=1)]
    try:
        geometry = Geometry(volume=grid, views=tuple(view for view, _ in read))
    except GeometryError as exc:
        text = str(exc)
        for n, (_, prov) in enumerate(read):
            text = text.replace(f"views[{n}]", f"view {n + 1} ({prov.get('file')})")
        short = [str(n) for n, (view, _) in enumerate(read, start=1) if view.sid_mm < MIN_PLAUSIBLE_SID_MM]
        if short:
            text += (f"; the source-to-detector distance of view {', '.join(short)} is under {MIN_PLAUSIBLE_SID_MM:g} mm: "
                     "DICOM gives distances in mm (was the tag written in cm?)")
        raise DicomInputError(text) from None
    from ..consistency import view_separation_warnings  # scipy and scikit-image: not at the command line's start

    provenance = {
        "generator": f"SDFCARLib {__version__} dicom.geometry_from_dicom_runs",
        "volume": {"value": grid.to_dict(), "source": volume_source},
        "views": [prov for _, prov in read],
        "warnings": view_separation_warnings(geometry),
    }
    return geometry, provenance


def geometry_from_dicom(
    path1: Union[XARun, PathLike],
    path2: Union[XARun, PathLike],
    frame1: Optional[int] = None,
    frame2: Optional[int] = None,
    volume: Optional[Union[VolumeGrid, Dict[str, Any]]] = None,
    overrides1: Optional[Dict[str, Any]] = None,
    overrides2: Optional[Dict[str, Any]] = None,
) -> Tuple[Geometry, Dict[str, Any]]:
    """Two-view ``Geometry`` from two XA files (``geometry_from_dicom_runs`` for any number)."""
    return geometry_from_dicom_runs([path1, path2], [frame1, frame2], volume, [overrides1, overrides2])


def write_geometry_json(path: PathLike, geometry: Geometry, provenance: Optional[Dict[str, Any]] = None) -> Path:
    """Write GEOM.json (the geometry plus a top-level ``provenance``); returns the path."""
    path = Path(path)
    data = geometry.to_dict()
    if provenance is not None:
        data["provenance"] = json_compatible(provenance)
    Geometry.from_dict(data)  # what is written must load
    write_text_atomically(path, json.dumps(data, indent=2, ensure_ascii=False) + "\n")
    return path
