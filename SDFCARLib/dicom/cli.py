"""Command-line wiring of the DICOM input, for ``SDFCARLib.cli``.

``add_dicom_arguments(parser)`` adds to an argparse (sub)parser::

    --dicom1 F1 [--frame1 N] --dicom2 F2 [--frame2 N]
    [--sod1 MM] [--sid1 MM] [--pixel-spacing1 ROW COL] [--primary1 DEG] [--secondary1 DEG]
    [--sod2 MM] [--sid2 MM] [--pixel-spacing2 ROW COL] [--primary2 DEG] [--secondary2 DEG]
    [--volume-shape I J K] [--volume-spacing MM] [--volume-center X Y Z]

and ``cli_geometry_from_args(args) -> (Geometry, provenance)`` turns the parsed arguments into
the geometry (``geometry`` writes it with ``write_geometry_json``; ``reconstruct --dicom1 …
--dicom2 …`` uses it in place of ``--geometry``, with the masks checked against its detector
shapes). Frame numbers on the command line are 0-based, like everywhere in SDFCARLib. The option
names per override key are also in ``geometry._CLI_OPTION``, which error messages quote.
"""

from __future__ import annotations

from typing import Any, Dict, Tuple

from ..geometry import Geometry, VolumeGrid
from .geometry import DEFAULT_VOLUME, geometry_from_dicom
from .read import DicomInputError


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
                        help="reconstruction grid size in voxels (default: placed on the masks' region when masks are "
                             "given, else 128 128 128)")
    parser.add_argument("--volume-spacing", type=float, default=None, metavar="MM",
                        help="reconstruction voxel size in mm (default 0.8)")
    parser.add_argument("--volume-center", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="centre of the reconstruction grid, LPS mm (default: placed on the masks' region when masks are "
                             "given, else the isocenter 0 0 0)")


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
