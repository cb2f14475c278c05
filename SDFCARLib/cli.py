"""Command line: ``python -m SDFCARLib <command>`` (also installed as ``sdfcar``).

Commands
    reconstruct        two views' masks (or line integrals) + GEOM.json → result folder
    simulate           a label volume or centreline + GEOM.json → masks and line integrals
    evaluate           a prediction against a label: every metric, and the visual-hull baseline
    demo               reconstruct the bundled sample case and compare with its ground truth
    geometry-template  write a GEOM.json for a standard view pair, as a starting point
    geometry           two XA DICOM runs → GEOM.json, every value with its source tag
    segment            one XA DICOM frame (or a plain image) → vessel mask, frame and overlay PNGs
    analyse            a result folder → 3D-QCA: centrelines, diameters, lesions, best view
    benchmark          many simulated cases × modes → results.csv, summary.md (the paper's tables)

Exit status: 0 success; 2 bad input (one line ``error: …`` on stderr, no traceback unless
``--verbose``); 130 cancelled with Ctrl-C (nothing written); 1 an unexpected failure.
This interface is a contract other tools drive: add options, do not change existing ones.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from . import __version__
from .cli_types import one_line as _one_line
from .cli_types import positive_int as _positive_int
from .dicom import add_dicom_arguments, cli_geometry_from_args, write_geometry_json
from .geometry import VIEW_PAIRS
from .io import write_text_atomically
from .settings import (DEFAULT_MODE, GROUND_TRUTH_METRICS, MASK_THRESHOLD_MM, METRICS, MODES, PAPER_DETECTOR_SPACING_MM,
                       make_settings, parse_setting_overrides, setting_help)

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_CANCELLED = 0, 1, 2, 130

METRIC_ROWS = [(key, METRICS[key].title + (f" ({METRICS[key].unit})" if METRICS[key].unit else ""))
               for key in GROUND_TRUTH_METRICS]


# --- progress and cancellation ------------------------------------------------------------------
class ProgressBar:
    """Turns ``reconstruct(progress=…)`` reports into a tqdm bar on stderr (step, loss, ETA)."""

    def __init__(self, enabled: bool = True, stream=None) -> None:
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.bar = None

    def __call__(self, info: Dict[str, Any]) -> None:
        if not self.enabled:
            return
        phase = info.get("phase")
        if phase == "setup":
            print("preparing the reconstruction (visual hull, projectors)…", file=self.stream)
        elif phase == "optimise":
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=int(info["total"]), desc="optimising", unit="step", file=self.stream,
                                dynamic_ncols=True, mininterval=0.5)
            self.bar.set_postfix(loss=f"{info.get('loss', float('nan')):.4f}", refresh=False)
            self.bar.update(int(info["step"]) - self.bar.n)
        elif phase == "output":
            self.close()
            print("evaluating the field on the grid…", file=self.stream)
        elif phase == "prune":
            print("pruning the branches that no mask pixel needs…", file=self.stream)
        elif phase == "warning":
            print(f"warning: {info.get('message', '')}", file=self.stream)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class CancelOnInterrupt:
    """While active, Ctrl-C asks the reconstruction to stop at its next step (a second one aborts)."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None

    def __call__(self) -> bool:
        return self.requested

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print("\ncancelling… (press Ctrl-C again to abort at once)", file=sys.stderr)

    def __enter__(self) -> "CancelOnInterrupt":
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc_info) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None


def _run_reconstruction(geometry, targets, settings, target_kind: str, show_progress: bool):
    from .optimiser import reconstruct

    bar = ProgressBar(show_progress)
    try:
        with CancelOnInterrupt() as cancel:
            return reconstruct(geometry, targets, settings, target_kind=target_kind, progress=bar, cancel=cancel)
    finally:
        bar.close()


# --- printing -----------------------------------------------------------------------------------
def _fmt(value: Any) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    if isinstance(value, (list, tuple)):
        return " / ".join(_fmt(v) for v in value)
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return f"{float(value):.3f}"


def metrics_table(columns: Dict[str, Dict[str, Any]]) -> str:
    """A plain-text table: one row per metric, one column per method."""
    names = list(columns)
    rows = [("metric", *names)]
    for key, title in METRIC_ROWS + [("reprojection_dice", "reprojection Dice"), ("voxels_predicted", "voxels")]:
        if any(key in columns[n] for n in names):
            rows.append((title, *(_fmt(columns[n].get(key)) for n in names)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths)))
                     for r in rows)


def _print_metrics(metrics: Dict[str, Dict[str, Any]], stream=None) -> None:
    columns = {"reconstruction" if "visual_hull" in metrics else "prediction": metrics["prediction"]}
    if "visual_hull" in metrics:
        columns["visual hull (baseline)"] = metrics["visual_hull"]
    print(metrics_table(columns), file=stream or sys.stdout)


# --- commands -----------------------------------------------------------------------------------
def _settings(args: argparse.Namespace):
    named = {"mode": args.mode, "device": args.device, "seed": args.seed, "steps": args.steps, "threads": args.threads}
    reserved = {key: f"use --{key}" for key in named}
    reserved["preset"] = "use --preset"
    return make_settings(args.preset, **{**parse_setting_overrides(args.overrides, reserved), **named})


def _read_targets(args: argparse.Namespace, geometry) -> Tuple[List[np.ndarray], str, List[np.ndarray]]:
    """The per-view targets, their kind, and the views' masks (for the visual-hull baseline)."""
    from .io import read_line_integral, read_mask

    masks_given = [args.mask1, args.mask2]
    lineints_given = [args.lineint1, args.lineint2]
    kind = args.target_kind
    if kind is None:
        kind = "line_integral" if any(lineints_given) and not any(masks_given) else "mask"
    chosen, flag = (masks_given, "--mask") if kind == "mask" else (lineints_given, "--lineint")
    other, other_flag = (lineints_given, "--lineint") if kind == "mask" else (masks_given, "--mask")
    if any(other):
        raise ValueError(f"--target-kind {kind} uses {flag}1/{flag}2; remove {other_flag}1/{other_flag}2 "
                         "(give either masks or line integrals)")
    missing = [f"{flag}{n}" for n, path in enumerate(chosen, start=1) if not path]
    if missing:
        raise ValueError(f"missing {' and '.join(missing)}: give one {'mask' if kind == 'mask' else 'line-integral image'} per view")
    if len(geometry.views) != 2:
        raise ValueError(f"{args.geometry or 'the geometry'} describes {len(geometry.views)} view(s) but reconstruct takes two "
                         f"({flag}1 and {flag}2); list exactly two views in GEOM.json")
    if kind == "mask":
        targets = [read_mask(path, view.detector_shape, what=f"view {n} mask")
                   for n, (path, view) in enumerate(zip(chosen, geometry.views), start=1)]
        return targets, kind, targets
    targets = [read_line_integral(path, view.detector_shape) for path, view in zip(chosen, geometry.views)]
    return targets, kind, [t > MASK_THRESHOLD_MM for t in targets]


def _absolute(path: Optional[str]) -> Optional[str]:
    return str(Path(path).absolute()) if path else None


def _load_geometry(path: str):
    from .geometry import Geometry

    return Geometry.load(path)


def _geometry_for_reconstruct(args: argparse.Namespace):
    """GEOM.json, or the geometry read from the two DICOM files' tags (with its provenance), and
    the request to place the grid on the masks (``region.AutoVolume``) or None."""
    from .region import AutoVolume, read_geometry

    if args.dicom1 or args.dicom2:
        if args.geometry:
            raise ValueError("give either --geometry or --dicom1/--dicom2, not both")
        geometry, provenance = cli_geometry_from_args(args)
        _print_provenance(provenance)
        return geometry, provenance, _dicom_volume_request(args)
    if not args.geometry:
        raise ValueError("missing --geometry: give a GEOM.json, or the two XA DICOM files with --dicom1 and --dicom2")
    geometry, request = read_geometry(args.geometry)
    if request is None and args.auto_volume:
        request = AutoVolume(tuple(geometry.volume.spacing_mm))  # keep the user's voxel size
    return geometry, None, request


def _dicom_volume_request(args: argparse.Namespace):
    """Without --volume-shape and --volume-center the grid is placed on the masks (at --volume-spacing)."""
    from .region import AutoVolume
    from .settings import PAPER_SPACING_MM

    if (args.volume_shape is None and args.volume_center is None) or getattr(args, "auto_volume", False):
        return AutoVolume((float(args.volume_spacing or PAPER_SPACING_MM),) * 3)
    return None


def _place_grid(geometry, masks, request, provenance: Optional[Dict[str, Any]]):
    """The geometry on the grid placed on the masks' region, and the placement's record."""
    from .geometry import Geometry
    from .region import locate_region

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


def _grid_record(geometry, masks, source: str, placement=None) -> Tuple[Dict[str, Any], List[str]]:
    """report.json's ``grid`` entry (where the grid came from, how much of each mask its hull
    explains) and the warnings for views it explains poorly; the warnings are printed at once."""
    from .region import mask_coverage

    coverage = mask_coverage(masks, geometry.views, geometry.volume)
    warnings = [f"the grid's visual hull explains only {100 * c:.0f} % of view {n}'s mask pixels: the grid cuts the tree "
                "(place it on the masks with --auto-volume, or move/enlarge the volume) or the geometry does not align "
                "the views (check the angles, distances and pixel spacing)"
                for n, c in enumerate(coverage, start=1) if c < 0.9]
    for message in warnings:
        print(f"warning: {message}", file=sys.stderr)
    record = {"source": source, "mask_coverage": coverage, "placement": placement.to_dict() if placement else None}
    return record, warnings


def _print_provenance(provenance: Dict[str, Any]) -> None:
    """Every geometry value read from DICOM and where it came from, so a clinician can check it."""
    for n, view in enumerate(provenance.get("views", []), start=1):
        frame = view.get("frame", {})
        print(f"view {n}: {view.get('file')} frame {frame.get('index')} ({frame.get('reason', '')})", file=sys.stderr)
        for name, entry in view.get("fields", {}).items():
            print(f"  {name} = {_fmt(entry.get('value'))}  [{entry.get('source', '?')}]", file=sys.stderr)
        for note in view.get("notes", []):
            print(f"  note: {note}", file=sys.stderr)
    volume = provenance.get("volume")
    if volume:
        print(f"volume: {volume.get('value')}  [{volume.get('source')}]", file=sys.stderr)


def cmd_geometry(args: argparse.Namespace) -> int:
    from .io import read_mask

    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ValueError(f"{out} exists; choose another --out or add --overwrite")
    if bool(args.mask1) != bool(args.mask2):
        raise ValueError("give both --mask1 and --mask2 (one vessel mask per view) to place the grid, or neither")
    geometry, provenance = cli_geometry_from_args(args)
    _print_provenance(provenance)
    request = _dicom_volume_request(args)
    if args.mask1:
        masks = [read_mask(path, view.detector_shape, what=f"view {n} mask")
                 for n, (path, view) in enumerate(zip([args.mask1, args.mask2], geometry.views), start=1)]
        source = provenance["volume"]["source"]
        if request is not None:
            geometry, _, source = _place_grid(geometry, masks, request, provenance)
        record, _ = _grid_record(geometry, masks, source)
        provenance["volume"]["mask_coverage"] = record["mask_coverage"]
    elif request is not None:
        provenance["volume"]["source"] += ("; no masks were given, so the grid could not be placed on the vessels: "
                                           "give --mask1/--mask2 here, or run reconstruct --auto-volume")
        print(f"note: {provenance['volume']['source']}", file=sys.stderr)
    write_geometry_json(out, geometry, provenance)
    print(f"wrote {out}")
    return EXIT_OK


def _auto_masks(args: argparse.Namespace, geometry, provenance) -> List[Tuple[Dict[str, Any], np.ndarray, Any]]:
    """--auto-masks: the segment pipeline on the frame of each DICOM view the geometry was read from."""
    from .dicom import load_xa
    from .masks import segment_angiogram

    if not (args.dicom1 and args.dicom2):
        raise ValueError("--auto-masks segments the frames of --dicom1 and --dicom2; give both (or give --mask1/--mask2)")
    if any([args.mask1, args.mask2, args.lineint1, args.lineint2]):
        raise ValueError("--auto-masks makes the masks itself; remove --mask1/--mask2 (or --lineint1/--lineint2)")
    auto = []
    for n, (view, info) in enumerate(zip(geometry.views, provenance["views"]), start=1):
        frame_info = info["frame"]
        frame = load_xa(getattr(args, f"dicom{n}")).frames[int(frame_info["index"])]
        auto.append((frame_info, frame, segment_angiogram(frame, view.pixel_spacing_mm, view.sid_mm / view.sod_mm)))
        p = auto[-1][2].parameters
        print(f"view {n}: auto mask of frame {frame_info['index']}: {p['components']} component(s), "
              f"{100 * p['vessel_fraction']:.1f}% of the frame", file=sys.stderr)
    return auto


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from .io import align_to_grid, read_label
    from .outputs import RESULT_FILES, check_destination, write_reconstruction

    geometry, provenance, request = _geometry_for_reconstruct(args)
    auto = _auto_masks(args, geometry, provenance) if args.auto_masks else None
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
    settings = _settings(args)
    check_destination(args.out, list(RESULT_FILES.values()), args.overwrite)  # before minutes of work
    result = _run_reconstruction(geometry, targets, settings, kind, not args.no_progress)
    result.report["warnings"] = grid_warnings + list(result.report.get("warnings", []))
    inputs = {"geometry": _absolute(args.geometry), "label": _absolute(args.label),
              "dicom": [_absolute(args.dicom1), _absolute(args.dicom2)] if args.dicom1 else None,
              "geometry_provenance": provenance,
              "targets": [_absolute(p) for p in ([args.mask1, args.mask2] if kind == "mask" else [args.lineint1, args.lineint2])]}
    if auto:
        inputs["targets"] = [f"auto_mask{n}.png" for n in (1, 2)]
        inputs["auto_masks"] = [dict(a.parameters, frame=f) for f, _, a in auto]
    files = write_reconstruction(result, args.out, name=args.name, label=label, masks=masks, overwrite=args.overwrite,
                                 extra={"inputs": inputs, "grid": grid_record})
    if auto:
        from .masks import write_segmentation

        for n, (f, frame, a) in enumerate(auto, start=1):
            write_segmentation(Path(args.out) / f"auto_mask{n}.png", frame, a,
                               {"dicom": _absolute(getattr(args, f"dicom{n}")), "frame": f}, overwrite=True)
        print(f"masks made by the segment pipeline (--auto-masks): {args.out}/auto_mask1.png, auto_mask2.png "
              "(overlays beside them; check them by eye)")
    _summarise(files)
    if args.analyse:
        _print_analysis(args.out, None, args.overwrite)
    return EXIT_OK


def _print_analysis(result_dir: str, out: Optional[str], overwrite: bool, **options: Any) -> None:
    from .analysis.outputs import analyse_result_dir

    files = analyse_result_dir(result_dir, out, overwrite=overwrite, **options)
    data = json.loads(files["analysis.json"].read_text(encoding="utf-8"))
    print(f"3D-QCA: {data['tree']['branches']} branches, {data['tree']['total_length_mm']:.1f} mm of centreline")
    for lesion in data["lesions"]:
        print(f"  branch {lesion['branch_id']}: MLD {lesion['mld_mm']:.2f} mm, reference {lesion['reference_diameter_mm']:.2f} mm, "
              f"DS {lesion['diameter_stenosis_pct']:.0f}%, AS {lesion['area_stenosis_pct']:.0f}%, length {lesion['length_mm']:.1f} mm")
    if data.get("best_view"):
        best = data["best_view"]
        print(f"  suggested view: {best['label']} (foreshortening {100 * best['foreshortening']:.1f}%, "
              f"overlap {100 * best['overlap']:.0f}%)")
    print(f"wrote {len(files)} files to {files['analysis.json'].parent}")


def cmd_analyse(args: argparse.Namespace) -> int:
    _print_analysis(args.result_dir, args.out, args.overwrite, masks=args.masks, ostium_mm=args.ostium,
                    view_step_deg=args.view_step_deg)
    return EXIT_OK


def cmd_segment(args: argparse.Namespace) -> int:
    from .masks import AngioMaskSettings, segment_angiogram, segmentation_paths, write_segmentation

    spacing, magnification = args.pixel_spacing, args.magnification
    if bool(args.dicom) == bool(args.image):
        raise ValueError("give one input: --dicom RUN.dcm (with --frame N) or --image FRAME.png")
    segmentation_paths(args.out)  # a wrong --out fails before the work
    if args.dicom:
        from .dicom import DicomInputError, choose_frame, load_xa, view_from_dicom

        run = load_xa(args.dicom)
        choice = choose_frame(run, args.frame)
        frame = run.frames[choice.index]
        source = {"dicom": _absolute(args.dicom), "frame": choice.to_dict()}
        try:
            view, _ = view_from_dicom(run, choice.index)
            spacing = spacing or list(view.pixel_spacing_mm)
            magnification = magnification or view.sid_mm / view.sod_mm
            source["geometry"] = "pixel spacing and SID/SOD from the DICOM tags unless given"
        except DicomInputError as exc:
            source["geometry"] = f"not read from the tags ({exc})"
        print(f"frame {choice.index} (0-based): {choice.reason}", file=sys.stderr)
    else:
        if args.frame is not None:
            raise ValueError("--frame picks a frame of a --dicom run; an --image is one frame")
        from .io import read_image

        frame = read_image(args.image, what="frame")
        source = {"image": _absolute(args.image)}
    settings = AngioMaskSettings(**({"method": args.method} if args.method else {}),
                                 **({"vessel_radius_mm": tuple(args.vessel_radius_mm)} if args.vessel_radius_mm else {}))
    result = segment_angiogram(frame, spacing, magnification, settings)
    paths = write_segmentation(args.out, frame, result, source, overwrite=args.overwrite)
    p = result.parameters
    print(f"mask: {p['components']} component(s), {100 * p['vessel_fraction']:.1f}% of the frame, border "
          f"{100 * p['border_fraction']:.0f}% excluded, σ {p['sigmas_px']} px at {p['isocenter_pixel_mm']:.3f} mm/px "
          f"(pixel spacing {p['pixel_spacing_source']}, magnification {p['magnification_source']}), {p['seconds']:.1f} s")
    for path in paths.values():
        print(f"wrote {path}")
    return EXIT_OK


def _summarise(files: Dict[str, Path]) -> None:
    report = json.loads(files["report"].read_text(encoding="utf-8"))
    timings = report.get("timings_s", {})
    total = timings.get("total")
    print(f"{report.get('method', 'reconstruction')}: {report.get('segmented_voxels', 0)} voxels segmented in "
          f"{total if total is None else round(float(total), 1)} s on {report.get('device', '?')}")
    print(f"reprojection Dice per view: {_fmt(report.get('reprojection_dice'))}")
    if "metrics" in report:
        _print_metrics(report["metrics"])
    for message in report.get("warnings", []):
        print(f"warning: {message}", file=sys.stderr)
    print(f"results in {files['report'].parent}: {', '.join(sorted(p.name for p in files.values()))}")


def cmd_simulate(args: argparse.Namespace) -> int:
    from .io import read_label, write_image_nrrd, write_mask_png
    from .outputs import check_destination, staged_directory
    from .phantoms import simulate_views

    geometry = _load_geometry(args.geometry)
    if not args.mask_threshold_mm > 0:
        raise ValueError(f"--mask-threshold-mm must be positive, got {args.mask_threshold_mm}")
    names = [f"view{n}_{kind}" for n in range(1, len(geometry.views) + 1) for kind in ("mask.png", "lineint.nrrd")]
    check_destination(args.out, names, args.overwrite)
    label, label_grid = read_label(args.label, grid=geometry.volume, what="label")
    if not label.any():
        raise ValueError(f"{args.label}: the label is empty (no vessel voxel); nothing to project")
    _warn_outside(label, label_grid, geometry.volume)
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


def _warn_outside(label: np.ndarray, label_grid, grid) -> None:
    ijk = np.argwhere(label)
    lo, hi = grid.bounds()
    if np.any(label_grid.index_to_world(ijk.min(axis=0)) < lo) or np.any(label_grid.index_to_world(ijk.max(axis=0)) > hi):
        print("warning: part of the label lies outside the geometry's volume; a reconstruction on that volume "
              "cannot recover it (check volume.center_mm and volume.shape)", file=sys.stderr)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .io import align_to_grid, read_label
    from .io import json_compatible
    from .outputs import check_destination, ground_truth_metrics

    geometry = _load_geometry(args.geometry) if args.geometry else None
    if args.json:
        check_destination(Path(args.json).parent, [Path(args.json).name], args.overwrite)
    prediction, prediction_grid = read_label(args.prediction, grid=geometry.volume if geometry else None,
                                             threshold=args.threshold, what="prediction")
    label, label_grid = read_label(args.label, grid=geometry.volume if geometry else prediction_grid, what="label")
    prediction = align_to_grid(prediction, prediction_grid, label_grid, what="prediction")
    metrics = ground_truth_metrics(prediction, label, label_grid, geometry.views if geometry else None)
    _print_metrics(metrics)
    if args.json:
        out = {"prediction_file": _absolute(args.prediction), "label_file": _absolute(args.label),
               "geometry_file": _absolute(args.geometry),
               "grid": label_grid.to_dict(), "metrics": metrics}
        write_text_atomically(Path(args.json), json.dumps(json_compatible(out), indent=2, allow_nan=False) + "\n")
        print(f"wrote {args.json}")
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from .outputs import RESULT_FILES, check_destination, write_reconstruction
    from .sample_data import load_sample_case

    check_destination(args.out, list(RESULT_FILES.values()), args.overwrite)
    case = load_sample_case()
    settings = _settings(args)
    print(f"SDFCAR demo: bundled sample case ({case.directory}), {settings.run.preset} preset, mode {settings.run.mode}, "
          f"{settings.optimisation.steps} steps", file=sys.stderr)
    started = time.perf_counter()
    result = _run_reconstruction(case.geometry, case.masks, settings, "mask", not args.no_progress)
    files = write_reconstruction(result, args.out, name=args.name or "SDFCAR demo", label=case.label, masks=case.masks,
                                 overwrite=args.overwrite, extra={"inputs": {"sample_case": str(case.directory)}})
    _summarise(files)
    print(f"demo finished in {time.perf_counter() - started:.0f} s")
    return EXIT_OK


def cmd_geometry_template(args: argparse.Namespace) -> int:
    from .geometry import standard_geometry

    geometry = standard_geometry(args.view_pair, volume_shape=args.shape, spacing_mm=args.spacing_mm,
                                 center_mm=args.center_mm, detector_shape=args.detector_shape,
                                 detector_spacing_mm=args.detector_spacing_mm)
    data = {"description": f"SDFCAR geometry template for the view pair {args.view_pair}; replace the angles, "
                           "distances and detector with those of your acquisition (DICOM tags PositionerPrimaryAngle, "
                           "PositionerSecondaryAngle, DistanceSourceToDetector, DistanceSourceToPatient, ImagerPixelSpacing)",
            **geometry.to_dict()}
    text = json.dumps(data, indent=2) + "\n"
    if not args.out:
        sys.stdout.write(text)
        return EXIT_OK
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ValueError(f"{out} already exists; choose another file or pass --overwrite")
    write_text_atomically(out, text)
    print(f"wrote {out} ({', '.join(v.describe() for v in geometry.views)})", file=sys.stderr)
    return EXIT_OK


# --- parser -------------------------------------------------------------------------------------
def _add_optimiser_options(p: argparse.ArgumentParser, preset_default: str = "fast") -> None:
    p.add_argument("--preset", default=preset_default,
                   help="fast: sized for a CPU (default); paper: the published recipe (5000 steps, needs a GPU)")
    p.add_argument("--mode", default=None,
                   help="; ".join(f"{key}: {mode.title}" for key, mode in MODES.items()) + f" (default {DEFAULT_MODE})")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="auto: CUDA when available")
    p.add_argument("--seed", type=int, default=None, help="random seed (repeatable on the same device)")
    p.add_argument("--steps", type=_positive_int, default=None, help="optimisation steps (default: the preset's)")
    p.add_argument("--threads", type=_positive_int, default=None, help="CPU threads for torch")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="any other setting, repeatable (e.g. --set support_margin_mm=1 --set memory_check=false); "
                        "the settings with the published recipe's values: " + setting_help().replace("%", "%%"))
    p.add_argument("--name", default=None, help="name of the result in Slicer (default: the output folder's name)")
    p.add_argument("--overwrite", action="store_true", help="replace result files the output folder already holds")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m SDFCARLib",
        description="SDF-CAR: 3D coronary artery reconstruction from two X-ray angiography views.",
        epilog="Exit status: 0 success, 2 bad input, 130 cancelled, 1 unexpected failure.")
    parser.add_argument("--version", action="version", version=f"SDFCARLib {__version__}")
    parser.add_argument("--verbose", action="store_true", help="show tracebacks of errors")
    # --verbose is accepted after the command too; SUPPRESS keeps the sub-parser from resetting it.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS, help="show tracebacks of errors")
    commands = parser.add_subparsers(dest="command", metavar="command")
    commands.required = True

    p = commands.add_parser("reconstruct", parents=[common], help="reconstruct the vessel tree from two views",
                            description="Reconstruct the 3D vessel tree seen in two views and write occupancy.nrrd, "
                                        "field.nrrd, segmentation.seg.nrrd, surface.vtk, report.json and scene.mrml.")
    p.add_argument("--geometry", help="GEOM.json with the volume grid and the two views (or give --dicom1/--dicom2)")
    add_dicom_arguments(p, required=False)
    p.add_argument("--mask1", help="vessel mask of view 1 (PNG/TIFF/NRRD, non-zero = vessel)")
    p.add_argument("--mask2", help="vessel mask of view 2")
    p.add_argument("--lineint1", help="line-integral image of view 1 (mm; NRRD/TIFF), instead of --mask1")
    p.add_argument("--lineint2", help="line-integral image of view 2, instead of --mask2")
    p.add_argument("--auto-masks", action="store_true",
                   help="with --dicom1/--dicom2: make the masks with the segment pipeline (written as auto_maskN*.png "
                        "in --out, their parameters in report.json) instead of --mask1/--mask2")
    p.add_argument("--target-kind", choices=("mask", "line_integral"), default=None,
                   help="what the view images are (default: from which options are given)")
    p.add_argument("--label", help="optional ground truth (volume, .seg.nrrd or centreline) for metrics in report.json")
    p.add_argument("--auto-volume", action="store_true",
                   help="place the grid on the region where the masks' back-projections meet (plus a margin), keeping "
                        "the geometry's voxel size; the default when GEOM.json's volume is \"auto\" or absent, or "
                        "when --dicom1/--dicom2 come without --volume-shape/--volume-center")
    p.add_argument("--out", required=True, help="output folder (created; existing results are kept unless --overwrite)")
    p.add_argument("--analyse", action="store_true", help="also run the 3D-QCA (`analyse`) into OUT/analysis")
    _add_optimiser_options(p)
    p.set_defaults(func=cmd_reconstruct)

    p = commands.add_parser("analyse", parents=[common], help="3D-QCA of a result folder: centrelines, diameters, lesions",
                            description="Centreline tree, diameter profiles (3D sections and, with the masks, two-view "
                                        "widths), lesions (MLD, %%DS, %%AS, length), bifurcation angles, foreshortening and "
                                        "the best-view map of a reconstruction: analysis.json, centrelines.vtk, "
                                        "profile_branchNN.csv, diameter_profiles.png, view_map.png.")
    p.add_argument("result_dir", help="folder written by reconstruct (occupancy.nrrd or segmentation.seg.nrrd, report.json)")
    p.add_argument("--out", help="output folder (default RESULT_DIR/analysis)")
    p.add_argument("--masks", nargs="+", help="view masks for the 2D diameters (default: the masks report.json names)")
    p.add_argument("--ostium", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="ostium in LPS mm (default: the thickest end of the tree)")
    p.add_argument("--view-step-deg", type=float, default=2.0, help="angle step of the best-view map (default 2)")
    p.add_argument("--overwrite", action="store_true", help="replace analysis files the output folder already holds")
    p.set_defaults(func=cmd_analyse)

    p = commands.add_parser("geometry", parents=[common], help="write GEOM.json from two XA DICOM files",
                            description="Read the C-arm geometry of two X-ray angiography DICOM runs from their tags and "
                                        "write GEOM.json, listing every value used and where it came from. Missing tags "
                                        "are errors that say which option supplies the value (e.g. --sod1).")
    add_dicom_arguments(p)
    p.add_argument("--mask1", help="vessel mask of view 1: with --mask2 and no --volume-shape/--volume-center, the grid "
                                   "is placed on where the masks' back-projections meet")
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

    p = commands.add_parser("geometry-template", parents=[common], help="write a GEOM.json for a standard view pair",
                            description="Write a GEOM.json for a standard view pair as a starting point.")
    p.add_argument("--view-pair", default="lao30-rao30", choices=sorted(VIEW_PAIRS),
                   help="paper: the SDF-CAR/NeCA simulation views; the others are clinical pairs (default lao30-rao30)")
    p.add_argument("--out", help="file to write (default: print to stdout)")
    p.add_argument("--shape", type=_positive_int, nargs=3, default=[128, 128, 128], metavar=("NI", "NJ", "NK"))
    p.add_argument("--spacing-mm", type=float, default=0.8)
    p.add_argument("--center-mm", type=float, nargs=3, default=[0.0, 0.0, 0.0], metavar=("X", "Y", "Z"),
                   help="volume centre in LPS mm (isocenter = 0 0 0)")
    p.add_argument("--detector-shape", type=_positive_int, nargs=2, default=[512, 512], metavar=("ROWS", "COLS"))
    p.add_argument("--detector-spacing-mm", type=float, default=PAPER_DETECTOR_SPACING_MM)
    p.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p.set_defaults(func=cmd_geometry_template)

    from .benchmark import add_benchmark_command

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
        from .optimiser import ReconstructionCancelled

        return args.func(args)
    except (KeyboardInterrupt, ReconstructionCancelled):
        print("cancelled: nothing was written", file=sys.stderr)
        return EXIT_CANCELLED
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


if __name__ == "__main__":
    sys.exit(main())
