"""The commands that reconstruct: ``reconstruct``, ``geometry`` (from DICOM), ``demo`` and ``analyse``."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from ..dicom import cli_geometry_from_args, dicom_runs_from_args, write_geometry_json
from ..settings import MASK_THRESHOLD_MM
from .common import (EXIT_OK, CancelOnInterrupt, PartlyWritten, Terminated, absolute_path, print_provenance, print_summary,
                     run_reconstruction, settings_from_args)

def _given(args: argparse.Namespace, flag: str) -> List[Optional[str]]:
    """The paths of ``--mask M1 M2 …`` (any number of views), or of ``--mask1/--mask2`` (two); [] if none."""
    listed, first, second = (getattr(args, f"{flag}s", None), getattr(args, f"{flag}1", None),
                             getattr(args, f"{flag}2", None))
    if listed and (first or second):
        raise ValueError(f"give the images either as --{flag} A B … or as --{flag}1/--{flag}2, not both")
    if listed:
        return list(listed)
    return [first, second] if (first or second) else []


def _views_named(args: argparse.Namespace, geometry) -> str:
    """What set the number of views, for the messages about a count of images that does not match it."""
    runs = getattr(args, "dicoms", None)
    if runs:
        return f"--dicom names {len(runs)} XA runs (one per view)"
    if getattr(args, "dicom1", None):
        return "--dicom1/--dicom2 name 2 XA runs (one per view)"
    return f"{getattr(args, 'geometry', None) or 'the geometry'} describes {len(geometry.views)} view(s)"


def _read_targets(args: argparse.Namespace, geometry) -> Tuple[List[np.ndarray], str, List[np.ndarray]]:
    """The per-view targets, their kind, and the views' masks (for the visual-hull baseline)."""
    from ..io import read_line_integral, read_mask

    masks_given = _given(args, "mask")
    lineints_given = _given(args, "lineint")
    kind = args.target_kind
    if kind is None:
        kind = "line_integral" if any(lineints_given) and not any(masks_given) else "mask"
    chosen, flag = (masks_given, "--mask") if kind == "mask" else (lineints_given, "--lineint")
    other, other_flag = (lineints_given, "--lineint") if kind == "mask" else (masks_given, "--mask")
    what = "mask" if kind == "mask" else "line-integral image"
    if any(other):
        raise ValueError(f"--target-kind {kind} uses {flag}; remove {other_flag} (give either masks or line integrals)")
    n_views = len(geometry.views)
    if not chosen:
        dicom = bool(getattr(args, "dicoms", None) or getattr(args, "dicom1", None))
        raise ValueError(f"no view images: give one {what} per view with {flag} "
                         f"{' '.join(f'V{n}' for n in range(1, n_views + 1))} ({n_views} views)"
                         + (", or --auto-masks to segment the DICOM frames" if dicom else ""))
    missing = [f"{flag}{n}" for n, path in enumerate(chosen, start=1) if not path]
    if missing:
        raise ValueError(f"missing {' and '.join(missing)}: give one {what} per view")
    if len(chosen) != n_views:
        raise ValueError(f"{_views_named(args, geometry)} but {len(chosen)} image(s) were given ({flag}); give one per "
                         f"view, in the same order ({flag} A B C … for any number of views)")
    if kind == "mask":
        targets = [read_mask(path, view.detector_shape, what=f"view {n} mask")
                   for n, (path, view) in enumerate(zip(chosen, geometry.views), start=1)]
        return targets, kind, targets
    targets = [read_line_integral(path, view.detector_shape) for path, view in zip(chosen, geometry.views)]
    return targets, kind, [t > MASK_THRESHOLD_MM for t in targets]


def _geometry_for_reconstruct(args: argparse.Namespace):
    """GEOM.json, or the geometry read from the XA runs' tags (with its provenance), and
    the request to place the grid on the masks (``region.AutoVolume``) or None."""
    from ..region import AutoVolume, read_geometry

    if dicom_runs_from_args(args):
        if args.geometry:
            raise ValueError("give either --geometry or the XA runs (--dicom A B …, or --dicom1/--dicom2), not both")
        geometry, provenance = cli_geometry_from_args(args)
        request = _dicom_volume_request(args)
        print_provenance(provenance, warnings=False, volume=request is None)  # a placed grid is printed where placed
        return geometry, provenance, request
    if not args.geometry:
        raise ValueError("missing --geometry: give a GEOM.json, or the XA DICOM runs, one per view, with --dicom A B … "
                         "(or --dicom1 and --dicom2)")
    given = [flag for flag, value in (("--volume-shape", args.volume_shape), ("--volume-spacing", args.volume_spacing),
                                      ("--volume-center", args.volume_center)) if value is not None]
    if given:
        raise ValueError(f"{', '.join(given)} set the grid of a reconstruction from XA runs (--dicom); with --geometry the "
                         "grid is the GEOM.json's volume: edit its volume entry, or add --auto-volume to place the grid on "
                         "the masks at its voxel size")
    geometry, request = read_geometry(args.geometry)
    if request is None and args.auto_volume:
        request = AutoVolume(tuple(geometry.volume.spacing_mm))  # keep the user's voxel size
    return geometry, None, request


def _dicom_volume_request(args: argparse.Namespace):
    """Without --volume-shape and --volume-center the grid is placed on the masks (at --volume-spacing)."""
    from ..region import AutoVolume
    from ..settings import PAPER_SPACING_MM

    if (args.volume_shape is None and args.volume_center is None) or getattr(args, "auto_volume", False):
        return AutoVolume((float(args.volume_spacing or PAPER_SPACING_MM),) * 3)
    return None


def _place_grid(geometry, masks, request, provenance: Optional[Dict[str, Any]]):
    """The geometry on the grid placed on the masks' region, and the placement's record."""
    from ..geometry import Geometry
    from ..region import locate_region

    placement = locate_region(geometry.views, masks, request.spacing_mm, request.margin_mm)
    grid = placement.grid
    for note in placement.notes:
        print(f"warning: {note}", file=sys.stderr)
    source = (f"placed on the masks' region (SDFCARLib.region): where their back-projections meet, plus "
              f"{request.margin_mm:g} mm")
    print(f"volume: {list(grid.shape)} voxels of {'/'.join(f'{v:g}' for v in grid.spacing_mm)} mm centred at "
          f"{[round(c, 1) for c in grid.center_mm]} mm  [{source}]", file=sys.stderr)
    if provenance is not None:
        provenance["volume"] = {"value": grid.to_dict(), "source": source}
    return Geometry(volume=grid, views=geometry.views), placement, source


def grid_coverage_warnings(coverage: List[float], placed: bool) -> List[str]:
    """The warnings for the views whose mask the grid's visual hull explains poorly (under 90 %).

    ``placed``: the grid was placed on the masks' region, so it does not cut the tree: what the hull leaves
    unexplained are rays that meet no other view's mask — the views disagree there."""
    if placed:
        cause = ("the grid was placed on the masks, so the views disagree there: part of the vessels lies where another "
                 "view does not show it (a collimator's shutter, the detector's edge, a vessel its mask misses) or the "
                 "geometry does not align the views (check the angles, distances and pixel spacing; with the frames given, "
                 "the pose search may correct a shift: see the calibration lines after the run)")
    else:
        cause = ("the grid cuts the tree (place it on the masks with --auto-volume, or move/enlarge the volume) or the "
                 "geometry does not align the views (check the angles, distances and pixel spacing)")
    return [f"the grid's visual hull explains only {100 * c:.0f} % of view {n}'s mask pixels: {cause}"
            for n, c in enumerate(coverage, start=1) if c < 0.9]


def _grid_record(geometry, masks, source: str, placement=None, placed: Optional[bool] = None
                 ) -> Tuple[Dict[str, Any], List[str]]:
    """report.json's ``grid`` entry (where the grid came from, how much of each mask its hull
    explains) and the warnings for views it explains poorly; the warnings are printed at once.
    ``placed``: the grid was placed on the masks (default: a ``placement`` is given)."""
    from ..region import mask_coverage

    coverage = mask_coverage(masks, geometry.views, geometry.volume)
    warnings = grid_coverage_warnings(coverage, placement is not None if placed is None else placed)
    for message in warnings:
        print(f"warning: {message}", file=sys.stderr)
    record = {"source": source, "mask_coverage": coverage, "placement": placement.to_dict() if placement else None}
    return record, warnings


def cmd_geometry(args: argparse.Namespace) -> int:
    from ..io import read_mask

    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ValueError(f"{out} exists; choose another --out or add --overwrite")
    given = _given(args, "mask")
    if given and not all(given):
        raise ValueError("give both --mask1 and --mask2 (one vessel mask per view) to place the grid, or neither")
    geometry, provenance = cli_geometry_from_args(args)
    if given and len(given) != len(geometry.views):
        raise ValueError(f"{_views_named(args, geometry)} but {len(given)} mask(s) were given (--mask); give one per "
                         "run, in the same order, to place the grid, or none")
    request = _dicom_volume_request(args)
    print_provenance(provenance, volume=not (given and request is not None))  # a placed grid is printed where placed
    if given:
        masks = [read_mask(path, view.detector_shape, what=f"view {n} mask")
                 for n, (path, view) in enumerate(zip(given, geometry.views), start=1)]
        source = provenance["volume"]["source"]
        if request is not None:
            geometry, _, source = _place_grid(geometry, masks, request, provenance)
        record, _ = _grid_record(geometry, masks, source, placed=request is not None)
        provenance["volume"]["mask_coverage"] = record["mask_coverage"]
    elif request is not None:
        provenance["volume"]["source"] += ("; no masks were given, so the grid could not be placed on the vessels: "
                                           "give the masks here (--mask A B …, one per run, or --mask1/--mask2), or run "
                                           "reconstruct --auto-volume")
        print(f"note: {provenance['volume']['source']}", file=sys.stderr)
    write_geometry_json(out, geometry, provenance)
    print(f"wrote {out}")
    return EXIT_OK


def _auto_masks(args: argparse.Namespace, geometry, provenance
                ) -> Tuple[List[Tuple[Dict[str, Any], np.ndarray, Any]], List[Optional[str]]]:
    """--auto-masks: the segment pipeline on the chosen frame of each XA run the geometry was read from, and each
    run's Pixel Intensity Relationship."""
    from ..masks import (BrightVesselsError, MaskError, frame_processed_for_display, mask_settings_for_intensity,
                         segment_angiogram)

    runs = dicom_runs_from_args(args)
    if not runs:
        raise ValueError("--auto-masks segments the frames of the XA runs; give them with --dicom A B … (or "
                         "--dicom1/--dicom2), or give the masks with --mask")
    given = [f"--{flag}{suffix}" for flag in ("mask", "lineint") for suffix in ("", "1", "2")
             if getattr(args, f"{flag}{suffix or 's'}", None)]
    if given:
        raise ValueError(f"--auto-masks makes the masks itself; remove {', '.join(given)}")
    auto = []
    frames, intensity = _dicom_frames(args, provenance, "mask")
    for n, (frame, view, info) in enumerate(zip(frames, geometry.views, provenance["views"]), start=1):
        frame_info = info["frame"]
        relationship = intensity[n - 1] if intensity else None
        try:
            segmented = segment_angiogram(frame, view.pixel_spacing_mm, view.sid_mm / view.sod_mm,
                                          mask_settings_for_intensity(relationship))
        except BrightVesselsError as exc:
            raise MaskError(f"view {n} ({runs[n - 1].path}): {exc}. --auto-masks segments the frames as they are: make "
                            f"this view's mask with `segment --dicom {shlex.quote(str(runs[n - 1].path))} --frame "
                            f"{frame_info['index']} --bright-vessels --out MASK.png`, the other views' with segment too, "
                            "and give every view's mask with --mask") from None
        except MaskError as exc:
            raise MaskError(f"view {n} ({runs[n - 1].path}): {exc}") from None
        auto.append((frame_info, frame, segmented))
        p = auto[-1][2].parameters
        print(f"view {n}: auto mask of frame {frame_info['index']}: {p['components']} component(s), "
              f"{100 * p['vessel_fraction']:.1f}% of the frame"
              + (f" (processed for display, {relationship}: the edge rule's trim off)" if frame_processed_for_display(relationship) else ""),
              file=sys.stderr)
        for warning in p.get("warnings", []):
            print(f"warning: view {n}: {warning}", file=sys.stderr)
    return auto, intensity


def _dicom_frames(args: argparse.Namespace, provenance, kind: str) -> Tuple[Optional[List[np.ndarray]], Optional[List[Optional[str]]]]:
    """The chosen frame of each XA run the geometry was read from (the frames the masks were drawn on) and the
    Pixel Intensity Relationship of those frames as read (LIN for LOG runs, ``dicom.intensity``: whether path
    lengths can be read off them), or (None, None)."""
    runs = dicom_runs_from_args(args)
    if not runs or kind != "mask" or provenance is None:
        return None, None
    from ..dicom import load_xa

    loaded = [load_xa(run.path) for run in runs]
    return ([xa.frames[int(info["frame"]["index"])] for xa, info in zip(loaded, provenance["views"])],
            [xa.frames_relationship for xa in loaded])


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from ..io import align_to_grid, read_label
    from ..outputs import check_destination, result_file_names
    from .data import label_warnings

    geometry, provenance, request = _geometry_for_reconstruct(args)
    auto, intensity = _auto_masks(args, geometry, provenance) if args.auto_masks else (None, None)
    targets, kind, masks = ([a.mask for _, _, a in auto], "mask", [a.mask for _, _, a in auto]) if auto \
        else _read_targets(args, geometry)
    placement = None
    if request is not None:
        geometry, placement, source = _place_grid(geometry, masks, request, provenance)
    elif provenance is not None:
        source = provenance["volume"]["source"]
    else:
        source = f"user: {args.geometry}"
    grid_record, grid_warnings = _grid_record(geometry, masks, source, placement)
    label = None
    if args.label:
        label, label_grid = read_label(args.label, grid=geometry.volume, what="ground-truth label")
        label = align_to_grid(label, label_grid, geometry.volume, what="ground-truth label")
        for warning in label_warnings(args.label, geometry.volume, what="ground-truth label"):
            print(f"warning: {warning}", file=sys.stderr)
            grid_warnings = grid_warnings + [warning]
    settings = settings_from_args(args)
    auto_mask_names = []
    if auto:
        from ..masks import segmentation_paths

        auto_mask_names = [path.name for n in range(1, len(auto) + 1)
                           for path in segmentation_paths(Path(args.out) / f"auto_mask{n}.png").values()]
    # before minutes of work
    check_destination(args.out, result_file_names(len(geometry.views)) + auto_mask_names, args.overwrite)
    if args.analyse:
        from ..analysis.outputs import ANALYSIS_FILES

        check_destination(Path(args.out) / "analysis", ANALYSIS_FILES, args.overwrite)
    # the frames the masks were made on: the path-length evidence of frame_evidence (on in fast)
    if auto:  # the very frames the masks were segmented on
        frames = [frame for _, frame, _ in auto]
    else:
        frames, intensity = _dicom_frames(args, provenance, kind)
    with CancelOnInterrupt() as cancel:  # over the fit and the writing: a Ctrl-C after the fit's last check counts too
        result = run_reconstruction(geometry, targets, settings, kind, not args.no_progress, frames=frames,
                                    frame_intensity=intensity, cancel=cancel)
        if cancel():
            from ..optimiser import ReconstructionCancelled

            raise ReconstructionCancelled("cancelled before writing the results")
        # no step to stop at while writing: a Ctrl-C stops at once, and the staging folder goes with it
        cancel.at_once = True
        files = _write_result(args, result, kind, grid_warnings, provenance, auto, label, masks, grid_record)
    pending = (["the auto masks"] if auto else []) + (["the analysis (--analyse)"] if args.analyse else [])
    try:
        if auto:
            _write_auto_masks(args, auto)
            pending.remove("the auto masks")
        print_summary(files)
        if args.analyse:
            _print_analysis(args.out, None, args.overwrite)
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (Terminated): the reconstruction itself is complete
        missing = f"; {' and '.join(pending)} {'was' if len(pending) == 1 else 'were'} not written" if pending else ""
        raise PartlyWritten(f"the reconstruction was written to {args.out}{missing}",
                            terminated=isinstance(exc, Terminated)) from None
    return EXIT_OK


def _write_result(args: argparse.Namespace, result, kind: str, grid_warnings: List[str], provenance, auto, label, masks,
                  grid_record: Dict[str, Any]) -> Dict[str, Path]:
    from ..outputs import write_reconstruction

    result.report["warnings"] = grid_warnings + list(result.report.get("warnings", []))
    inputs = {"geometry": absolute_path(args.geometry), "label": absolute_path(args.label),
              "dicom": [absolute_path(run.path) for run in dicom_runs_from_args(args)] or None,
              "geometry_provenance": provenance,
              "targets": [absolute_path(p) for p in _given(args, "mask" if kind == "mask" else "lineint")]}
    if auto:
        inputs["targets"] = [f"auto_mask{n}.png" for n in range(1, len(auto) + 1)]
        inputs["auto_masks"] = [dict(a.parameters, frame=f) for f, _, a in auto]
    return write_reconstruction(result, args.out, name=args.name, label=label, masks=masks, overwrite=args.overwrite,
                                extra={"inputs": inputs, "grid": grid_record})


def _write_auto_masks(args: argparse.Namespace, auto) -> None:
    from ..masks import write_segmentation

    names = []
    for n, (run, (f, frame, a)) in enumerate(zip(dicom_runs_from_args(args), auto), start=1):
        write_segmentation(Path(args.out) / f"auto_mask{n}.png", frame, a,
                           {"dicom": absolute_path(run.path), "frame": f}, overwrite=args.overwrite)
        names.append(f"auto_mask{n}.png")
    print(f"masks made by the segment pipeline (--auto-masks): {args.out}/{', '.join(names)} "
          "(overlays beside them; check them by eye)")


def _print_analysis(result_dir: str, out: Optional[str], overwrite: bool, **options: Any) -> None:
    from ..analysis.outputs import analyse_result_dir, analysis_summary_lines

    files = analyse_result_dir(result_dir, out, overwrite=overwrite, **options)
    data = json.loads(files["analysis.json"].read_text(encoding="utf-8"))
    for warning in data.get("warnings", []):
        print(f"warning: {warning}", file=sys.stderr)
    for note in data.get("notes", []):
        print(f"note: {note}", file=sys.stderr)
    for line in analysis_summary_lines(data):
        print(line)
    print(f"wrote {len(files)} files to {files['analysis.json'].parent}")


def cmd_analyse(args: argparse.Namespace) -> int:
    _print_analysis(args.result_dir, args.out, args.overwrite, masks=args.masks, ostium_mm=args.ostium,
                    view_step_deg=args.view_step_deg, min_component_share=args.min_component_share,
                    frames=args.frames, psf_sigma_mm=args.psf_sigma_mm,
                    centreline_on_masks={"auto": None, "masks": True, "volume": False}[args.centreline],
                    segment_mm=None if args.segment is None else [args.segment[:3], args.segment[3:]])
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from ..outputs import check_destination, result_file_names, write_reconstruction
    from ..sample_data import FILES, load_sample_case

    case = load_sample_case()
    check_destination(args.out, result_file_names(len(case.geometry.views)), args.overwrite)
    settings = settings_from_args(args)
    print(f"SDFCAR demo: bundled sample case ({case.directory}), {settings.run.preset} preset, mode {settings.run.mode}, "
          + (f"{settings.optimisation.ensemble_fits} fits of " if settings.optimisation.ensemble_fits > 1 else "")
          + f"{settings.optimisation.steps} steps", file=sys.stderr)
    started = time.perf_counter()
    result = run_reconstruction(case.geometry, case.masks, settings, "mask", not args.no_progress)
    files = write_reconstruction(result, args.out, name=args.name or "SDFCAR demo", label=case.label, masks=case.masks,
                                 overwrite=args.overwrite,
                                 # the masks named as reconstruct names its inputs: `analyse` then finds them
                                 extra={"inputs": {"sample_case": str(case.directory), "targets": [
                                     str(case.directory / FILES[f"mask{n + 1}"]) for n in range(len(case.masks))]}})
    print_summary(files)
    print(f"demo finished in {time.perf_counter() - started:.0f} s")
    return EXIT_OK
