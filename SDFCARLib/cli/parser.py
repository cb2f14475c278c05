"""The argument parser of every command, and ``main`` (exit status and one-line errors)."""

from __future__ import annotations

import argparse
import math
import sys
import traceback
from typing import Optional, Sequence, Union

from .. import __version__
from ..cli_types import one_line as _one_line
from ..cli_types import positive_float
from ..cli_types import positive_int as _positive_int
from ..dicom import add_dicom_arguments
from ..geometry import VIEW_PAIRS
from ..lumen_profile import MAX_PSF_SIGMA_MM, PSF_BY_FRAMES
from ..settings import DEFAULT_MODE, MASK_THRESHOLD_MM, MODES, PAPER_DETECTOR_SPACING_MM, setting_help
from .common import (EXIT_BAD_INPUT, EXIT_CANCELLED, EXIT_FAILURE, EXIT_TERMINATED, SETTINGS_SET_BY_FLAGS, PartlyWritten,
                     Terminated, TerminateOnSigterm)
from .data import DEFAULT_SID_MM, DEFAULT_SOD_MM, cmd_evaluate, cmd_geometry_template, cmd_segment, cmd_simulate
from .reconstruct import cmd_analyse, cmd_demo, cmd_geometry, cmd_reconstruct

def _blur_sigma(text: str) -> Union[float, None, str]:
    """argparse type of --psf-sigma-mm: 'auto' (None: estimated from the frames) or a blur ≥ 0 in mm (the default,
    ``PSF_BY_FRAMES``, passes through)."""
    if text == PSF_BY_FRAMES:
        return text
    if text.strip().lower() == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a blur in mm (0 or more) or 'auto', got {text!r}") from None
    if not (math.isfinite(value) and 0 <= value <= MAX_PSF_SIGMA_MM):
        raise argparse.ArgumentTypeError(f"must be a blur in mm (0 to {MAX_PSF_SIGMA_MM:g}) or 'auto', got {text}")
    return value


def _add_optimiser_options(p: argparse.ArgumentParser, preset_default: str = "fast") -> None:
    p.add_argument("--preset", default=preset_default,
                   help="fast: sized for a CPU (default); ensemble: fast fitted three times from different seeds and "
                        "averaged (1-2 clDice points better, three times the fit's time: for a GPU); paper: the published "
                        "recipe (5000 steps, needs a GPU)")
    p.add_argument("--mode", default=None,
                   help="; ".join(f"{key}: {mode.title}" for key, mode in MODES.items()) + f" (default {DEFAULT_MODE})")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="auto: CUDA when available")
    p.add_argument("--seed", type=int, default=None, help="random seed (repeatable on the same device)")
    p.add_argument("--steps", type=_positive_int, default=None, help="optimisation steps (default: the preset's)")
    p.add_argument("--threads", type=_positive_int, default=None, help="CPU threads for torch")
    p.add_argument("--correct-motion", action="store_true",
                   help="search each view's shift across its epipolar lines with view 1 before reconstructing (table, "
                        "patient or heart moved between the acquisitions; 7 short fits per view, so several times "
                        "slower); --set calibration_rotation_range_deg=3 searches two rotations as well; what was found "
                        "is in report.json (calibrate=true)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="any other setting, repeatable (e.g. --set support_margin_mm=1 --set memory_check=false); "
                        "the settings with the published recipe's values: "
                        + setting_help(exclude=SETTINGS_SET_BY_FLAGS).replace("%", "%%"))
    p.add_argument("--name", default=None, help="name of the result in Slicer (default: the output folder's name)")
    p.add_argument("--overwrite", action="store_true", help="replace result files the output folder already holds")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m SDFCARLib",
        description="SDF-CAR: 3D coronary artery reconstruction from two or more X-ray angiography views.",
        epilog="Exit status: 0 success, 2 bad input, 130 cancelled, 1 unexpected failure.")
    parser.add_argument("--version", action="version", version=f"SDFCARLib {__version__}")
    parser.add_argument("--verbose", action="store_true", help="show tracebacks of errors")
    # --verbose is accepted after the command too; SUPPRESS keeps the sub-parser from resetting it.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS, help="show tracebacks of errors")
    commands = parser.add_subparsers(dest="command", metavar="command")
    commands.required = True

    p = commands.add_parser("reconstruct", parents=[common], help="reconstruct the vessel tree from two or more views",
                            description="Reconstruct the 3D vessel tree seen in two or more views and write occupancy.nrrd, "
                                        "field.nrrd, segmentation.seg.nrrd, surface.vtk, report.json and scene.mrml.")
    p.add_argument("--geometry", help="GEOM.json with the volume grid and the views (or give the XA runs with --dicom A B …)")
    add_dicom_arguments(p)
    p.add_argument("--mask1", help="vessel mask of view 1 (PNG/TIFF/NRRD, non-zero = vessel)")
    p.add_argument("--mask2", help="vessel mask of view 2")
    p.add_argument("--lineint1", help="line-integral image of view 1 (mm; NRRD/TIFF), instead of --mask1")
    p.add_argument("--lineint2", help="line-integral image of view 2, instead of --mask2")
    p.add_argument("--mask", dest="masks", nargs="+", metavar="MASK",
                   help="the vessel masks of all views, in the order of GEOM.json's views (any number, e.g. three)")
    p.add_argument("--lineint", dest="lineints", nargs="+", metavar="IMAGE",
                   help="the line-integral images of all views, in the order of GEOM.json's views")
    p.add_argument("--auto-masks", action="store_true",
                   help="with --dicom A B …: make each run's mask with the segment pipeline (written as auto_maskN*.png "
                        "in --out, their parameters in report.json) instead of --mask")
    p.add_argument("--target-kind", choices=("mask", "line_integral"), default=None,
                   help="what the view images are (default: from which options are given)")
    p.add_argument("--label", help="optional ground truth (volume, .seg.nrrd or centreline) for metrics in report.json")
    p.add_argument("--auto-volume", action="store_true",
                   help="place the grid on the region where the masks' back-projections meet (plus a margin), keeping "
                        "the geometry's voxel size; the default when GEOM.json's volume is \"auto\" or absent, or "
                        "when --dicom runs come without --volume-shape/--volume-center")
    p.add_argument("--out", required=True, help="output folder (created; existing results are kept unless --overwrite)")
    p.add_argument("--analyse", action="store_true", help="also run the 3D-QCA (`analyse`) into OUT/analysis")
    _add_optimiser_options(p)
    p.set_defaults(func=cmd_reconstruct)

    p = commands.add_parser("analyse", parents=[common], help="3D-QCA of a result folder: centrelines, diameters, lesions",
                            description="Centreline tree, diameter profiles (3D sections and, with the masks, two-view "
                                        "widths), lesions (MLD, %DS, %AS, length), bifurcation angles, foreshortening, each "
                                        "vessel's angle to the views' epipolar planes (where two views place it in depth "
                                        "weakly) and the best-view map of a reconstruction: analysis.json, centrelines.vtk, "
                                        "profile_branchNN.csv, diameter_profiles.png, view_map.png. Narrowings where the "
                                        "reconstruction is broken (a piece cut off, a gap beside it, a bridged gap) are "
                                        "flagged unreliable with the reason, apart from the lesions.")
    p.add_argument("result_dir", help="folder written by reconstruct (occupancy.nrrd or segmentation.seg.nrrd, report.json)")
    p.add_argument("--out", help="output folder (default RESULT_DIR/analysis)")
    p.add_argument("--masks", nargs="+", help="view masks for the 2D diameters (default: the masks report.json names)")
    p.add_argument("--frames", nargs="+", metavar="IMAGE",
                   help="the views' frames (PNG, TIFF or NRRD as recorded, vessels dark), one per view: the 2D widths are "
                        "also fitted to their intensity profiles, sharper than a segmented mask's border")
    p.add_argument("--psf-sigma-mm", type=_blur_sigma, default=PSF_BY_FRAMES, metavar="MM|auto",
                   help="detector blur assumed by the --frames fit: Gaussian σ in mm at the detector, or 'auto' to "
                        "estimate it from the frames (default: 0.3, and estimated where report.json says the frames "
                        "were processed for display, whose sharpening is no detector blur; analysis.json settings say "
                        "what was used)")
    p.add_argument("--centreline", choices=("auto", "masks", "volume"), default="auto",
                   help="masks: the centreline re-placed on the masks' midlines for lengths, positions, angles and "
                        "foreshortening (the 3D sections and widths stay on the volume's); volume: the volume's own; "
                        "auto (default): masks where the masks of two views or more are found")
    p.add_argument("--ostium", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="ostium in LPS mm (default: the thickest end of the tree)")
    p.add_argument("--view-step-deg", type=positive_float, default=2.0,
                   help="angle step of the best-view map in degrees, 0.5 to 30 (default 2)")
    p.add_argument("--segment", type=float, nargs=6, metavar=("X1", "Y1", "Z1", "X2", "Y2", "Z2"),
                   help="two points in LPS mm marking the segment to measure (its 3D length, its foreshortening in "
                        "each acquired view) and to find the best view of, on one branch within 5 mm of its "
                        "centreline (default: the worst lesion with 2.5 mm either side)")
    p.add_argument("--min-component-share", type=float, default=None, metavar="SHARE",
                   help="analyse only the pieces of a fragmented reconstruction that hold at least this share of the "
                        "main tree's voxels (default 0.1; 0 analyses every piece)")
    p.add_argument("--overwrite", action="store_true", help="replace analysis files the output folder already holds")
    p.set_defaults(func=cmd_analyse)

    p = commands.add_parser("geometry", parents=[common], help="write GEOM.json from two or more XA DICOM runs",
                            description="Read the C-arm geometry of X-ray angiography DICOM runs (one per view, any "
                                        "number) from their tags and write GEOM.json, listing every value used and where "
                                        "it came from. Missing tags are errors that say which option supplies the value "
                                        "(e.g. --sod 765 auto auto, or --sod1).")
    add_dicom_arguments(p)
    p.add_argument("--mask", dest="masks", nargs="+", metavar="MASK",
                   help="vessel masks, one per run in the same order: without --volume-shape/--volume-center the grid "
                        "is placed on where the masks' back-projections meet")
    p.add_argument("--mask1", help="vessel mask of view 1 (with --dicom1/--dicom2; or use --mask)")
    p.add_argument("--mask2", help="vessel mask of view 2")
    p.add_argument("--out", required=True, help="GEOM.json to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p.set_defaults(func=cmd_geometry)

    p = commands.add_parser("segment", parents=[common], help="vessel mask of one XA DICOM frame or a plain image",
                            description="Segment the contrast-filled vessels of one X-ray angiography frame (collimator "
                                        "and border excluded, specks removed) and write the mask (0/255 PNG), the frame "
                                        "used (NAME_frame.png), an overlay to check by eye (NAME_overlay.png) and every "
                                        "parameter (NAME.json). Vessel sizes are physical: the pixel spacing and "
                                        "magnification come from the DICOM tags, the options, or typical values.")
    p.add_argument("--dicom", help="XA DICOM run")
    p.add_argument("--frame", type=int, default=None, help="0-based frame of the run (default: chosen automatically)")
    p.add_argument("--image", help="a plain frame instead (PNG/TIFF/NRRD, grey, vessels dark)")
    p.add_argument("--pixel-spacing", type=float, nargs=2, metavar=("ROW", "COL"), default=None,
                   help="detector pixel size in mm (default: the DICOM tags, else 0.39)")
    p.add_argument("--magnification", type=float, default=None, help="SID/SOD (default: the DICOM tags, else 1.3)")
    p.add_argument("--vessel-radius-mm", type=float, nargs=2, metavar=("MIN", "MAX"), default=None,
                   help="vessel radii to detect, mm at the isocenter (default 0.5 2.5)")
    p.add_argument("--method", choices=("sato", "frangi", "meijering"), default=None, help="ridge filter (default sato)")
    p.add_argument("--image-intensity", choices=("LIN", "LOG", "DISP"), default=None,
                   help="with --image: how its grey levels were made, as DICOM's Pixel Intensity Relationship would say "
                        "(DISP: processed for display, as a viewer's export or a screen capture is; then the mask's edge "
                        "rule does not trim it); default: not known — an image of 8-bit grey levels is taken as DISP "
                        "(raw detector frames are 10–16 bit; a note says so), any other gets the usual rule. A --dicom "
                        "run says it itself")
    p.add_argument("--bright-vessels", action="store_true",
                   help="the frame shows its vessels bright (an inverted display or export): its grey levels are "
                        "inverted (about their 0.1 and 99.9 percentiles) before it is segmented. Without it a frame whose "
                        "vessels look bright is refused, saying so")
    p.add_argument("--out", required=True, help="mask PNG to write (NAME.png; the other files are named after it)")
    p.add_argument("--overwrite", action="store_true", help="replace existing files")
    p.set_defaults(func=cmd_segment)

    p = commands.add_parser("simulate", parents=[common], help="simulate the views of a label volume or centreline",
                            description="Project a label (NRRD/NIfTI volume with its own spacing and origin, or a "
                                        "centreline .vtk/.vtp with radii, voxelised on the geometry's grid) into every "
                                        "view of GEOM.json: viewN_mask.png (0/255) and viewN_lineint.nrrd (mm).")
    p.add_argument("--label", required=True, help="label volume or centreline")
    p.add_argument("--geometry", required=True, help="GEOM.json")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--mask-threshold-mm", type=float, default=MASK_THRESHOLD_MM,
                   help=f"mask = line integral > this (default {MASK_THRESHOLD_MM} mm)")
    p.add_argument("--overwrite", action="store_true", help="replace files the output folder already holds")
    p.set_defaults(func=cmd_simulate)

    p = commands.add_parser("evaluate", parents=[common], help="metrics of a prediction against a label",
                            description="clDice, skeleton Dice, Dice, IoU and Chamfer distance of a prediction against a "
                                        "label on the same grid; with --geometry also reError, reMSE, reprojection Dice and "
                                        "the visual-hull baseline of the label's simulated masks.")
    p.add_argument("--prediction", required=True, help=".seg.nrrd, labelmap or volume (NRRD/NIfTI)")
    p.add_argument("--label", required=True, help="ground truth: .seg.nrrd, labelmap (NRRD/NIfTI) or centreline (.vtk/.vtp)")
    p.add_argument("--geometry", help="GEOM.json, for the projection metrics and the visual-hull baseline")
    p.add_argument("--threshold", type=float, default=None,
                   help="vessel = value >= threshold, for a continuous prediction (e.g. 0.5 for occupancy.nrrd)")
    p.add_argument("--json", help="also write the metrics to this JSON file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    p.set_defaults(func=cmd_evaluate)

    p = commands.add_parser("demo", parents=[common], help="reconstruct the bundled sample case",
                            description="Reconstruct the bundled sample case (LAO 30 / RAO 30, 128³ at 0.8 mm) and print "
                                        "the metrics against its ground truth and the visual-hull baseline.")
    p.add_argument("--out", required=True, help="output folder")
    _add_optimiser_options(p)
    p.set_defaults(func=cmd_demo)

    p = commands.add_parser("geometry-template", parents=[common],
                            help="write a GEOM.json for a standard protocol or any list of view angles",
                            description="Write a GEOM.json as a starting point: a standard protocol (--view-pair) or "
                                        "any number of views given by their angles (--view, repeated).")
    p.add_argument("--view-pair", default=None, choices=sorted(VIEW_PAIRS),
                   help="paper: the SDF-CAR/NeCA simulation views; lao30-rao30-cra30: three views; the others are "
                        "clinical pairs (default lao30-rao30 when no --view is given)")
    p.add_argument("--view", dest="views", action="append", type=float, nargs=2, metavar=("PRIMARY", "SECONDARY"),
                   help="one view by its angles in degrees (LAO +/RAO −, CRA +/CAU −); repeat for each view, e.g. "
                        "--view 30 0 --view -30 0 --view 0 30 (instead of --view-pair)")
    p.add_argument("--sid-mm", type=positive_float, default=None,
                   help=f"source-to-detector distance of every view (default {DEFAULT_SID_MM:g} for --view views; a "
                        "--view-pair's own distances otherwise)")
    p.add_argument("--sod-mm", type=positive_float, default=None,
                   help=f"source-to-isocenter distance of every view (default {DEFAULT_SOD_MM:g} for --view views; a "
                        "--view-pair's own distances otherwise)")
    p.add_argument("--out", help="file to write (default: print to stdout)")
    p.add_argument("--shape", type=_positive_int, nargs=3, default=[128, 128, 128], metavar=("NI", "NJ", "NK"))
    p.add_argument("--spacing-mm", type=float, default=0.8)
    p.add_argument("--center-mm", type=float, nargs=3, default=[0.0, 0.0, 0.0], metavar=("X", "Y", "Z"),
                   help="volume centre in LPS mm (isocenter = 0 0 0)")
    p.add_argument("--detector-shape", type=_positive_int, nargs=2, default=[512, 512], metavar=("ROWS", "COLS"))
    p.add_argument("--detector-spacing-mm", type=float, default=PAPER_DETECTOR_SPACING_MM)
    p.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p.set_defaults(func=cmd_geometry_template)

    from ..benchmark import add_benchmark_command

    add_benchmark_command(commands, common)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version and usage errors
        return int(exc.code or 0)
    verbose = bool(args.verbose)
    try:
        from ..optimiser import ReconstructionCancelled

        with TerminateOnSigterm():
            return args.func(args)
    except (KeyboardInterrupt, ReconstructionCancelled) as exc:
        terminated = isinstance(exc, Terminated) or getattr(exc, "terminated", False)
        written = exc.written if isinstance(exc, PartlyWritten) else "nothing was written"
        print(f"{'terminated (SIGTERM)' if terminated else 'cancelled'}: {written}", file=sys.stderr)
        return EXIT_TERMINATED if terminated else EXIT_CANCELLED
    except (ValueError, OSError) as exc:  # GeometryError, ReconstructionError, InputError, OutputError, files
        if verbose:
            traceback.print_exc()
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:
        if verbose:
            traceback.print_exc()
        print(f"error: unexpected {type(exc).__name__}: {_one_line(exc)} (run with --verbose for the traceback)",
              file=sys.stderr)
        return EXIT_FAILURE
