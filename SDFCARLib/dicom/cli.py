"""Command-line wiring of the DICOM input, for ``SDFCARLib.cli``.

``add_dicom_arguments(parser)`` adds to an argparse (sub)parser two ways to name the XA runs,
one run per view, which are not mixed::

    --dicom F1 F2 [F3 …]                       any number of runs (at least two), in view order
        [--frame N|auto …] [--sod MM|auto …] [--sid MM|auto …] [--primary DEG|auto …]
        [--secondary DEG|auto …] [--pixel-spacing S|ROW,COL|auto …]
                                               one value per run, in the same order; ``auto``
                                               keeps the automatic frame or the tag's value
    --dicom1 F1 --dicom2 F2                    two runs (the older form)
        [--frame1 N] [--sod1 MM] [--sid1 MM] [--pixel-spacing1 ROW COL] [--primary1 DEG]
        [--secondary1 DEG] and the same with 2
    [--volume-shape I J K] [--volume-spacing MM] [--volume-center X Y Z]

``dicom_runs_from_args(args)`` turns either form into one ``DicomRun`` per view (path, frame,
overrides), and ``cli_geometry_from_args(args) -> (Geometry, provenance)`` reads the geometry
from them (``geometry`` writes it with ``write_geometry_json``; ``reconstruct --dicom …`` uses it
in place of ``--geometry``, with the masks checked against its detector shapes). Frame numbers on
the command line are 0-based, like everywhere in SDFCARLib. The option names per override key are
also in ``geometry._CLI_OPTION``, which error messages quote.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

from ..cli_types import positive_float
from ..geometry import Geometry, VolumeGrid
from .geometry import DEFAULT_VOLUME, geometry_from_dicom_runs
from .read import DicomInputError

# Per-run option (without the number) → override key of ``view_from_dicom`` (None: the frame).
_PER_RUN = {"frame": None, "sod": "sod_mm", "sid": "sid_mm", "pixel_spacing": "pixel_spacing_mm",
            "primary": "primary_deg", "secondary": "secondary_deg"}
AUTO = "auto"


@dataclass
class DicomRun:
    """One XA run named on the command line: its file, frame (None = automatic) and overrides."""

    path: str
    frame: Optional[int] = None
    overrides: Dict[str, Any] = field(default_factory=dict)


def _option(key: str, n: Optional[int] = None) -> str:
    return "--" + key.replace("_", "-") + ("" if n is None else str(n))


def add_dicom_arguments(parser: Any) -> None:
    """Add the DICOM input options (runs, frames, per-run overrides, volume) to ``parser``."""
    parser.add_argument("--dicom", dest="dicoms", nargs="+", metavar="RUN",
                        help="X-ray angiography DICOM files (XA/XRF, multi-frame allowed), one per view, any number "
                             "(e.g. three); --frame, --sod, --sid, --pixel-spacing, --primary and --secondary then take "
                             "one value per run in the same order, 'auto' for the automatic frame or the tag's value")
    per_run = {
        "frame": ("N", "0-based frame of each run (default: the end-diastolic frame from the ECG tags, else the frame "
                       "with the most contrast)"),
        "sod": ("MM", "source-to-isocenter distance of each run in mm (replaces tag (0018,1111))"),
        "sid": ("MM", "source-to-detector distance of each run in mm (replaces tag (0018,1110))"),
        "pixel_spacing": ("S", "detector pixel spacing of each run in mm: one number, or ROW,COL (replaces tag "
                               "(0018,1164))"),
        "primary": ("DEG", "primary angle of each run, LAO + / RAO − (replaces tag (0018,1510))"),
        "secondary": ("DEG", "secondary angle of each run, CRA + / CAU − (replaces tag (0018,1511))"),
    }
    for key, (metavar, text) in per_run.items():
        parser.add_argument(_option(key), dest=f"{key}_per_run", nargs="+", default=None, metavar=metavar,
                            help=f"with --dicom: {text}; one value per run or 'auto'")
    for n in (1, 2):
        parser.add_argument(f"--dicom{n}", metavar=f"F{n}",
                            help=f"X-ray angiography DICOM file of view {n} (two runs; --dicom takes any number)")
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
                        help="reconstruction grid size in voxels (default: placed on the masks' region when masks are "
                             "given, else 128 128 128)")
    parser.add_argument("--volume-spacing", type=positive_float, default=None, metavar="MM",
                        help="reconstruction voxel size in mm (default 0.8)")
    parser.add_argument("--volume-center", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="centre of the reconstruction grid, LPS mm (default: placed on the masks' region when masks are "
                             "given, else the isocenter 0 0 0)")


def _parse_listed(key: str, text: str, position: int, count: int) -> Any:
    """One value of a per-run list (``--sod 765 auto …``): None for ``auto``."""
    if text.strip().lower() == AUTO:
        return None
    where = f"{_option(key)} value {position} of {count} ({text!r})"
    try:
        if key == "frame":
            return int(text)
        if key == "pixel_spacing":
            parts = [float(v) for v in text.split(",")]
            if len(parts) not in (1, 2):
                raise ValueError
            return parts * 2 if len(parts) == 1 else parts
        return float(text)
    except ValueError:
        wanted = {"frame": "a whole 0-based frame number", "pixel_spacing": "a spacing in mm, ROW,COL"}.get(key, "a number")
        raise DicomInputError(f"{where} is not {wanted} or '{AUTO}'") from None


def dicom_runs_from_args(args: Any) -> List[DicomRun]:
    """The XA runs named by ``--dicom F1 F2 …`` or ``--dicom1/--dicom2`` with their frames and overrides ([] if none).

    The two forms are not mixed: a numbered option (``--frame2``) belongs to ``--dicom1/--dicom2``, a
    list (``--frame 3 auto 7``) to ``--dicom``; the error says which to use instead.
    """
    listed = list(getattr(args, "dicoms", None) or [])
    numbered_runs = [getattr(args, f"dicom{n}", None) for n in (1, 2)]
    numbered_options = [(key, n) for n in (1, 2) for key in _PER_RUN if getattr(args, f"{key}{n}", None) is not None]
    listed_options = [_option(key) for key in _PER_RUN if getattr(args, f"{key}_per_run", None) is not None]
    if listed and any(numbered_runs):
        raise DicomInputError("give the XA runs either as --dicom A B C … (any number of views) or as --dicom1/--dicom2 "
                              "(two), not both")
    if listed:
        if numbered_options:
            key, n = numbered_options[0]
            value = getattr(args, f"{key}{n}")
            value = ",".join(f"{v:g}" for v in value) if isinstance(value, (list, tuple)) else f"{value:g}"
            example = " ".join(value if k == n else AUTO for k in range(1, len(listed) + 1))
            names = [_option(k, m) for k, m in numbered_options]
            raise DicomInputError(
                f"{', '.join(names)} {'is' if len(names) == 1 else 'are'} for --dicom1/--dicom2; with --dicom A B … give "
                f"one value per run instead, e.g. {_option(key)} {example} (or name the runs with --dicom1/--dicom2)")
        if len(listed) < 2:
            raise DicomInputError(f"--dicom names {len(listed)} run; a reconstruction needs at least two XA runs, one "
                                  "per view (--dicom A B, or more)")
        runs = [DicomRun(str(path)) for path in listed]
        for key, override in _PER_RUN.items():
            values = getattr(args, f"{key}_per_run", None)
            if values is None:
                continue
            if len(values) != len(runs):
                raise DicomInputError(f"{_option(key)} has {len(values)} value(s) but --dicom names {len(runs)} runs: "
                                      f"give one per run, in the same order ('{AUTO}' for the automatic frame or the "
                                      "tag's value)")
            for n, (run, text) in enumerate(zip(runs, values), start=1):
                value = _parse_listed(key, str(text), n, len(runs))
                if value is None:
                    continue
                if override is None:
                    run.frame = value
                else:
                    run.overrides[override] = value
        return runs
    if listed_options:
        if not any(numbered_runs):
            raise DicomInputError(f"{', '.join(listed_options)} give one value per run of --dicom A B …; name the runs "
                                  "with --dicom")
        raise DicomInputError(f"{', '.join(listed_options)} {'is' if len(listed_options) == 1 else 'are'} for "
                              "--dicom A B …; with --dicom1/--dicom2 use the "
                              f"numbered options ({', '.join(f'{o}1/{o}2' for o in listed_options)})")
    if not any(numbered_runs):
        if numbered_options:
            raise DicomInputError(f"{', '.join(_option(k, m) for k, m in numbered_options)} need the runs: give "
                                  "--dicom1 and --dicom2")
        return []
    if not all(numbered_runs):
        raise DicomInputError("--dicom1 and --dicom2 are both needed: one X-ray angiography file per view "
                              "(or give any number of runs with --dicom A B C …)")
    runs = []
    for n, path in enumerate(numbered_runs, start=1):
        overrides = {}
        for key, override in _PER_RUN.items():
            value = getattr(args, f"{key}{n}", None)
            if override is not None and value is not None:
                overrides[override] = list(value) if isinstance(value, (list, tuple)) else value
        runs.append(DicomRun(str(path), getattr(args, f"frame{n}", None), overrides))
    return runs


def cli_geometry_from_args(args: Any) -> Tuple[Geometry, Dict[str, Any]]:
    """Geometry and provenance from the options of ``add_dicom_arguments``."""
    runs = dicom_runs_from_args(args)
    if not runs:
        raise DicomInputError("no XA runs: give one X-ray angiography file per view with --dicom A B C … "
                              "(or --dicom1 and --dicom2)")
    volume = None
    shape, spacing, center = (getattr(args, k, None) for k in ("volume_shape", "volume_spacing", "volume_center"))
    if shape is not None or spacing is not None or center is not None:
        volume = VolumeGrid(
            tuple(int(v) for v in (shape or DEFAULT_VOLUME.shape)),
            (float(spacing),) * 3 if spacing is not None else DEFAULT_VOLUME.spacing_mm,
            tuple(float(v) for v in (center or DEFAULT_VOLUME.center_mm)),
        )
    return geometry_from_dicom_runs([r.path for r in runs], [r.frame for r in runs], volume,
                                    [r.overrides for r in runs])
