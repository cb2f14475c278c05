"""The data commands: ``segment``, ``simulate``, ``evaluate`` and ``geometry-template``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np

from ..io import write_text_atomically
from .common import EXIT_OK, absolute_path, load_geometry, print_metrics

# geometry-template's distances for views given by their angles (a common C-arm's SID and isocentre distance)
DEFAULT_SID_MM = 1000.0
DEFAULT_SOD_MM = 757.0


def cmd_segment(args: argparse.Namespace) -> int:
    from ..masks import (AngioMaskSettings, frame_processed_for_display, mask_settings_for_intensity, segment_angiogram,
                         segmentation_paths, write_segmentation)

    spacing, magnification = args.pixel_spacing, args.magnification
    spacing_source = magnification_source = None  # None: as segment_angiogram names it (given, or its default)
    if bool(args.dicom) == bool(args.image):
        raise ValueError("give one input: --dicom RUN.dcm (with --frame N) or --image FRAME.png")
    if args.dicom and getattr(args, "image_intensity", None):
        raise ValueError("--image-intensity says how an --image was made; a --dicom run's Pixel Intensity Relationship "
                         "is read from its tags: remove --image-intensity")
    written = segmentation_paths(args.out)  # a wrong --out fails before the work
    given = Path(args.dicom or args.image)
    clash = [str(path) for path in written.values() if path.exists() and given.exists() and path.samefile(given)]
    if clash:
        raise ValueError(f"--out {args.out} would write {clash[0]}, the input frame itself; choose another --out")
    if args.dicom:
        from ..dicom import choose_frame, load_xa

        run = load_xa(args.dicom)
        choice = choose_frame(run, args.frame)
        frame = run.frames[choice.index]
        source = {"dicom": absolute_path(args.dicom), "frame": choice.to_dict()}
        relationship = run.frames_relationship
        if relationship:
            source["pixel_intensity_relationship"] = relationship
        tag_spacing, tag_magnification, problems = _scale_from_tags(run, choice.index)
        if not spacing and tag_spacing:
            spacing, spacing_source = tag_spacing, "the DICOM tags"
        if not magnification and tag_magnification:
            magnification, magnification_source = tag_magnification, "the DICOM tags' SID/SOD"
        source["geometry"] = "pixel spacing and SID/SOD from the DICOM tags unless given"
        for what, option, given, problem in (("pixel spacing", "--pixel-spacing", spacing, problems.get("spacing")),
                                             ("magnification", "--magnification", magnification,
                                              problems.get("magnification"))):
            if problem and not given:
                source["geometry"] += f"; the {what} is not in the tags ({problem})"
                print(f"note: the {what} could not be read from the tags, so a typical value is assumed: {problem}; "
                      f"give it with {option}", file=sys.stderr)
        print(f"frame {choice.index} (0-based): {choice.reason}", file=sys.stderr)
    else:
        if args.frame is not None:
            raise ValueError("--frame picks a frame of a --dicom run; an --image is one frame")
        from ..io import read_image

        frame = read_image(args.image, what="frame")
        source = {"image": absolute_path(args.image)}
        relationship = args.image_intensity  # an image file does not say how its grey levels were made
        if relationship:
            source["pixel_intensity_relationship"] = f"{relationship} (--image-intensity)"
        else:
            from ..evidence import assumed_relationship

            relationship, note = assumed_relationship(frame, None, str(args.image))
            if note:
                source["pixel_intensity_relationship"] = f"{relationship} (assumed: an 8-bit image)"
                print(f"note: {note}", file=sys.stderr)
    settings = mask_settings_for_intensity(relationship, AngioMaskSettings(
        **({"method": args.method} if args.method else {}),
        **({"vessel_radius_mm": tuple(args.vessel_radius_mm)} if args.vessel_radius_mm else {}),
        bright_vessels=bool(getattr(args, "bright_vessels", False))))
    if frame_processed_for_display(relationship):
        print(f"the run's frames were processed for display (Pixel Intensity Relationship {relationship}): their edges "
              "are enhanced, so the mask's edge rule does not trim them", file=sys.stderr)
    result = segment_angiogram(frame, spacing, magnification, settings)
    if spacing_source:
        result.parameters["pixel_spacing_source"] = spacing_source
    if magnification_source:
        result.parameters["magnification_source"] = magnification_source
    from ..mask_checks import mask_warnings

    # what a reconstruction from this mask would warn of, said now, where the mask can still be redone
    detector_spacing = None if spacing is None else tuple(float(v) for v in np.broadcast_to(np.asarray(spacing, float), (2,)))
    warnings = list(result.parameters.get("warnings", [])) + mask_warnings(result.mask, detector_spacing, source="mask")
    if args.dicom:
        from ..dicom import burned_in_annotation_note

        annotation = burned_in_annotation_note(run, choice.index)
        if annotation:
            warnings.append(annotation)
    result.parameters["warnings"] = warnings
    paths = write_segmentation(args.out, frame, result, source, overwrite=args.overwrite)
    for warning in warnings:
        print(f"warning: {warning}", file=sys.stderr)
    p = result.parameters
    print(f"mask: {p['components']} component(s), {100 * p['vessel_fraction']:.1f}% of the frame, border "
          f"{100 * p['border_fraction']:.0f}% excluded, σ {p['sigmas_px']} px at {p['isocenter_pixel_mm']:.3f} mm/px "
          f"(pixel spacing {p['pixel_spacing_source']}, magnification {p['magnification_source']}), {p['seconds']:.1f} s")
    for path in paths.values():
        print(f"wrote {path}")
    return EXIT_OK


def _scale_from_tags(run, frame: int):
    """(detector pixel spacing (row, col) or None, SID/SOD or None, {"spacing"/"magnification": why not}) of a
    run's frame: each read from the tags on its own, so that one missing tag does not lose the other (the
    angles do not matter for a mask and are not read)."""
    from ..dicom import DicomInputError, view_from_dicom

    angles = {"primary_deg": 0.0, "secondary_deg": 0.0}
    try:
        view, _ = view_from_dicom(run, frame, angles)
        return list(view.pixel_spacing_mm), view.sid_mm / view.sod_mm, {}
    except DicomInputError:
        pass
    spacing = magnification = None
    problems = {}
    try:  # the distances stood in for, twice: a spacing that follows them is one calibrated at the patient
        spacings = [list(view_from_dicom(run, frame, {**angles, "sid_mm": 1000.0, "sod_mm": sod})[0].pixel_spacing_mm)
                    for sod in (750.0, 600.0)]
        if spacings[0] == spacings[1]:
            spacing = spacings[0]
        else:
            problems["spacing"] = "the tags give the spacing at the patient, which needs the missing distances"
    except DicomInputError as exc:
        problems["spacing"] = str(exc)
    try:  # the spacing stood in for: what fails is the distances
        view, _ = view_from_dicom(run, frame, {**angles, "pixel_spacing_mm": [1.0, 1.0]})
        magnification = view.sid_mm / view.sod_mm
    except DicomInputError as exc:
        problems["magnification"] = str(exc)
    return spacing, magnification, problems


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..io import label_file_warnings, read_label, write_image_nrrd, write_mask_png
    from ..outputs import check_destination, staged_directory
    from ..phantoms import simulate_views

    geometry = load_geometry(args.geometry)
    if not args.mask_threshold_mm > 0:
        raise ValueError(f"--mask-threshold-mm must be positive, got {args.mask_threshold_mm}")
    names = [f"view{n}_{kind}" for n in range(1, len(geometry.views) + 1) for kind in ("mask.png", "lineint.nrrd")]
    check_destination(args.out, names, args.overwrite)
    # a centreline is voxelised on the volume's lattice grown to hold the whole tree: the views see all of it
    label, label_grid = read_label(args.label, grid=_grid_holding_centreline(args.label, geometry.volume), what="label")
    if not label.any():
        raise ValueError(f"{args.label}: the label is empty (no vessel voxel); nothing to project")
    _warn_outside(label, label_grid, geometry.volume)
    for warning in label_file_warnings(args.label):  # the part beyond the volume is warned of just above
        print(f"warning: {warning}", file=sys.stderr)
    line_integrals, masks = simulate_views(label, label_grid, geometry.views, args.mask_threshold_mm)
    for n, (mask, view) in enumerate(zip(masks, geometry.views), start=1):
        if not mask.any():
            raise ValueError(f"view {n} ({view.describe()}): the label leaves no shadow above {args.mask_threshold_mm} mm "
                             "on the detector; check the label's position and the view's angles")
        if mask.all():
            raise ValueError(f"view {n} ({view.describe()}): the label's shadow covers the whole detector; "
                             "check the label (is it inverted?) and the detector size")
    with staged_directory(args.out, names, args.overwrite) as staging:
        for n, (li, mask, view) in enumerate(zip(line_integrals, masks, geometry.views), start=1):
            write_mask_png(staging / f"view{n}_mask.png", mask)
            write_image_nrrd(staging / f"view{n}_lineint.nrrd", li, view.pixel_spacing_mm,
                             content=f"SDFCAR line integral (mm), view {n} {view.describe()}")
    for n, (li, mask) in enumerate(zip(line_integrals, masks), start=1):
        print(f"view {n}: {int(mask.sum())} vessel pixels, longest path {float(li.max()):.2f} mm")
    print(f"wrote {', '.join(names)} in {args.out}")
    return EXIT_OK


#: how many times the volume's voxels ``simulate`` takes to hold a centreline that reaches beyond the volume
MAX_GROWN_GRID_FACTOR = 8


def _centreline_or_none(path):
    """The centreline tree at ``path``; None for other label files and for a file that cannot be read (``read_label``
    names what is wrong with it)."""
    if Path(path).suffix.lower() not in (".vtk", ".vtp"):
        return None
    from ..phantoms import load_centreline_vtk

    try:
        return load_centreline_vtk(path)
    except (ValueError, OSError):
        return None


def _grid_holding_centreline(path, grid):
    """``grid``, grown to hold the tree when ``path`` is a centreline (other labels carry their own grid)."""
    tree = _centreline_or_none(path)
    if tree is None:
        return grid
    grown = grid.grown_to_hold(*tree.bounds())
    # a tree far from the volume (another frame's coordinates) is not worth gigabytes: read_label then says it misses
    return grown if grown.num_voxels <= MAX_GROWN_GRID_FACTOR * grid.num_voxels else grid


def _warn_outside(label: np.ndarray, label_grid, grid) -> None:
    ijk = np.argwhere(label)
    lo, hi = grid.bounds()
    if np.any(label_grid.index_to_world(ijk.min(axis=0)) < lo) or np.any(label_grid.index_to_world(ijk.max(axis=0)) > hi):
        print("warning: part of the label lies outside the geometry's volume; a reconstruction on that volume "
              "cannot recover it (check volume.center_mm and volume.shape)", file=sys.stderr)


def centreline_outside_warning(path, grid, what: str = "label") -> Optional[str]:
    """A warning when the centreline at ``path`` reaches beyond ``grid``: it is voxelised on the grid, so
    the metrics score only the part inside. None for other label files (their own grid is checked when aligned)."""
    tree = _centreline_or_none(path)
    if tree is None:
        return None
    outside_mm, total_mm = tree.length_outside_mm(*grid.bounds()), tree.total_length_mm()
    if outside_mm <= 0:
        return None
    return (f"{outside_mm:.1f} mm of the {what} centreline's {total_mm:.1f} mm ({100 * outside_mm / total_mm:.0f} %) lie "
            "outside the volume: it is voxelised on the volume, so the metrics score the part inside only "
            "(enlarge volume.shape or move volume.center_mm to score all of it)")


def label_warnings(path, grid, what: str = "label") -> list:
    """The warnings on a label file as read on ``grid``: its header's surprises and a centreline beyond the grid."""
    from ..io import label_file_warnings

    outside = centreline_outside_warning(path, grid, what)
    return label_file_warnings(path, what) + ([outside] if outside else [])


def cmd_evaluate(args: argparse.Namespace) -> int:
    from ..io import align_to_grid, read_label
    from ..io import json_compatible
    from ..outputs import check_destination, ground_truth_metrics

    geometry = load_geometry(args.geometry) if args.geometry else None
    if args.json:
        check_destination(Path(args.json).parent, [Path(args.json).name], args.overwrite)
    prediction, prediction_grid = read_label(args.prediction, grid=geometry.volume if geometry else None,
                                             threshold=args.threshold, what="prediction")
    if args.threshold is not None and not prediction.any():
        print(f"warning: no voxel of {args.prediction} reaches --threshold {args.threshold:g}: the prediction is empty and "
              "every overlap metric is 0 (occupancy.nrrd holds values in [0, 1]; its segmentation's level is 0.5)",
              file=sys.stderr)
    label, label_grid = read_label(args.label, grid=geometry.volume if geometry else prediction_grid, what="label")
    warnings = label_warnings(args.prediction, prediction_grid, "prediction") + label_warnings(args.label, label_grid)
    for warning in warnings:
        print(f"warning: {warning}", file=sys.stderr)
    prediction = align_to_grid(prediction, prediction_grid, label_grid, what="prediction")
    metrics = ground_truth_metrics(prediction, label, label_grid, geometry.views if geometry else None)
    print_metrics(metrics)
    if args.json:
        out = {"prediction_file": absolute_path(args.prediction), "label_file": absolute_path(args.label),
               "geometry_file": absolute_path(args.geometry),
               "grid": label_grid.to_dict(), "metrics": metrics, "warnings": warnings}
        write_text_atomically(Path(args.json), json.dumps(json_compatible(out), indent=2, allow_nan=False) + "\n")
        print(f"wrote {args.json}")
    return EXIT_OK


def cmd_geometry_template(args: argparse.Namespace) -> int:
    from ..geometry import CArmView, Geometry, standard_geometry

    if args.views and args.view_pair:
        raise ValueError("give either --view-pair or the views' angles with --view PRIMARY SECONDARY (repeated), not both")
    if args.views is not None and len(args.views) < 2:
        raise ValueError(f"--view was given {len(args.views)} time; a reconstruction needs at least two views: repeat "
                         "--view PRIMARY SECONDARY once per view")
    protocol = args.view_pair or "lao30-rao30"
    geometry = standard_geometry(protocol, volume_shape=args.shape, spacing_mm=args.spacing_mm,
                                 center_mm=args.center_mm, detector_shape=args.detector_shape,
                                 detector_spacing_mm=args.detector_spacing_mm)
    if args.views:
        spacing = (args.detector_spacing_mm, args.detector_spacing_mm)
        sid_mm = DEFAULT_SID_MM if args.sid_mm is None else args.sid_mm
        sod_mm = DEFAULT_SOD_MM if args.sod_mm is None else args.sod_mm
        geometry = Geometry(geometry.volume, tuple(
            CArmView(primary, secondary, sid_mm, sod_mm, spacing, tuple(args.detector_shape))
            for primary, secondary in args.views))
        protocol = f"{len(args.views)} views given with --view"
    elif args.sid_mm is not None or args.sod_mm is not None:
        # the protocol's own distances, replaced where the user gave one
        geometry = Geometry(geometry.volume, tuple(
            dataclasses.replace(view, sid_mm=view.sid_mm if args.sid_mm is None else args.sid_mm,
                                sod_mm=view.sod_mm if args.sod_mm is None else args.sod_mm)
            for view in geometry.views))
    data = {"description": f"SDFCAR geometry template ({protocol}); replace the angles, "
                           "distances and detector with those of your acquisition (DICOM tags PositionerPrimaryAngle, "
                           "PositionerSecondaryAngle, DistanceSourceToDetector, DistanceSourceToPatient, ImagerPixelSpacing)",
            **geometry.to_dict()}
    text = json.dumps(data, indent=2) + "\n"
    from ..consistency import view_separation_warnings

    for warning in view_separation_warnings(geometry):
        print(f"warning: {warning}", file=sys.stderr)
    if not args.out:
        sys.stdout.write(text)
        return EXIT_OK
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ValueError(f"{out} already exists; choose another file or pass --overwrite")
    write_text_atomically(out, text)
    print(f"wrote {out} ({', '.join(v.describe() for v in geometry.views)})", file=sys.stderr)
    return EXIT_OK
