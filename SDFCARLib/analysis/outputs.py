"""Files of a 3D-QCA: analysis.json, centrelines.vtk, per-branch CSV profiles and figures.

``analyse_result_dir`` reads a reconstruction's result folder (``outputs.py`` of the package:
occupancy.nrrd or segmentation.seg.nrrd, report.json with the geometry and the threshold),
runs ``pipeline.analyse_volume`` and writes, all at once or not at all (``staged_directory``):

    analysis.json           every number (``pipeline.summary``), LPS mm, degrees, percent
    centrelines.vtk         legacy ASCII polydata, one polyline per branch, ``SPACE=LPS`` in the
                            header line (as surface.vtk); point arrays Radius (3D equivalent
                            radius, the inscribed radius where a section could not be measured),
                            Diameter3D, DiameterMasks, EpipolarAngle (degrees to the acquired
                            views' epipolar planes; −1 where not measured or under two views), ArcLength
                            (a FIELD beside the Radius scalars: every reader loads them);
                            cell array BranchId. Written as text whether or not vtk is installed,
                            so the file is the same everywhere; vtk and Slicer read it.
    profile_branchNN.csv    arc length, 3D diameter, area, min/max diameter, mask diameter and
                            per-view widths, reference, excluded flag, epipolar angle, centreline point
    diameter_profiles.png   diameter against arc length per branch, lesions shaded (matplotlib);
                            lesions where the reconstruction is broken hatched grey
    view_map.png            foreshortening + overlap over the C-arm angles, best view marked
"""

from __future__ import annotations

import csv
import io as _io
import json
import numbers
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np

from ..evidence import is_binary_image, unreadable_intensity
from ..geometry import Geometry
from ..io import InputError, read_image, read_label, read_mask, read_volume, write_json
from ..lumen_profile import MAX_PSF_SIGMA_MM
from ..outputs import check_destination, staged_directory
from .pipeline import (FOUND_ON_FRAMES, FOUND_ON_MASKS, GRADED_ON_3D, MISSED_IN_3D_PHRASE, PSF_BY_FRAMES, QCAResult,
                       SegmentError, analyse_volume, lesion_grade, summary, unseen_on)

PathLike = Union[str, Path]
ANALYSIS_FILES = ("analysis.json", "centrelines.vtk", "diameter_profiles.png", "view_map.png")


def centrelines_vtk_text(result: QCAResult) -> str:
    """Legacy VTK polydata of the centreline tree (module docstring)."""
    pts, lines, arrays = [], [], {"Radius": [], "Diameter3D": [], "DiameterMasks": [], "EpipolarAngle": [], "ArcLength": []}
    ids = []
    for p in result.profiles:
        b = p.branch
        start = sum(len(x) for x in pts)
        pts.append(b.points_mm)
        lines.append(list(range(start, start + len(b.points_mm))))
        d3 = p.diameter_mm
        arrays["Radius"].append(np.where(np.isfinite(d3), d3 / 2, np.nan_to_num(b.inscribed_radius_mm)))
        arrays["Diameter3D"].append(np.where(np.isfinite(d3), d3, -1.0))
        dm = p.mask_diameter_mm if p.mask_diameter_mm is not None else np.full(len(d3), np.nan)
        arrays["DiameterMasks"].append(np.where(np.isfinite(dm), dm, -1.0))
        angle = result.epipolar_deg.get(b.branch_id, np.full(len(d3), np.nan))
        arrays["EpipolarAngle"].append(np.where(np.isfinite(angle), angle, -1.0))
        arrays["ArcLength"].append(b.arc_length_mm)
        ids.append(b.branch_id)
    points = np.concatenate(pts)
    out = _io.StringIO()
    out.write("# vtk DataFile Version 3.0\nSDFCAR centrelines SPACE=LPS\nASCII\nDATASET POLYDATA\n")
    out.write(f"POINTS {len(points)} float\n")
    np.savetxt(out, points, fmt="%.5f")
    out.write(f"LINES {len(lines)} {sum(len(l) + 1 for l in lines)}\n")
    for l in lines:
        out.write(" ".join(map(str, [len(l)] + l)) + "\n")
    out.write(f"CELL_DATA {len(lines)}\nSCALARS BranchId int 1\nLOOKUP_TABLE default\n")
    out.write("\n".join(map(str, ids)) + "\n")
    # Radius as the scalars a viewer colours by; the others as a FIELD, which readers (vtkPolyDataReader,
    # Slicer) load whole: of several SCALARS blocks a reader keeps only the first unless told ReadAllScalarsOn.
    out.write(f"POINT_DATA {len(points)}\nSCALARS Radius float 1\nLOOKUP_TABLE default\n")
    np.savetxt(out, np.concatenate(arrays.pop("Radius")), fmt="%.5f")
    out.write(f"FIELD PointArrays {len(arrays)}\n")
    for name, values in arrays.items():
        out.write(f"{name} 1 {len(points)} float\n")
        np.savetxt(out, np.concatenate(values), fmt="%.5f")
    return out.getvalue()


def _view_numbers(per_view: Optional[np.ndarray], i: int) -> str:
    """The views (from 1) flagged at point ``i``, as "1+2"; empty where none or unknown."""
    return "" if per_view is None else "+".join(str(v + 1) for v in np.flatnonzero(per_view[:, i]))


def profile_csv_text(result: QCAResult, branch_id: int) -> str:
    p = result.profile(branch_id)
    b = p.branch
    n_views = 0 if p.view_widths_mm is None else len(p.view_widths_mm)
    n_frames = 0 if p.frame_view_widths_mm is None else len(p.frame_view_widths_mm)
    header = ["arc_mm", "diameter_3d_mm", "area_mm2", "min_diameter_mm", "max_diameter_mm", "diameter_masks_mm"]
    header += [f"width_view{v + 1}_mm" for v in range(n_views)]
    header += (["diameter_frames_mm"] + [f"frame_width_view{v + 1}_mm" for v in range(n_frames)]
               + ["diameter_frames_density_mm", "density_views", "crowded_views"]) if n_frames else []
    header += ["reference_mm", "excluded", "epipolar_angle_deg", "x_mm", "y_mm", "z_mm"]
    epipolar = result.epipolar_deg.get(branch_id)
    ref = p.reference(b.arc_length_mm) if p.reference is not None else np.full(len(b.points_mm), np.nan)
    out = _io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(header)

    def f(v):
        return "" if v is None or not np.isfinite(v) else f"{float(v):.4f}"

    for i in range(len(b.points_mm)):
        row = [f(b.arc_length_mm[i]), f(p.diameter_mm[i]), f(p.sections.area_mm2[i]), f(p.sections.min_diameter_mm[i]),
               f(p.sections.max_diameter_mm[i]), f(None if p.mask_diameter_mm is None else p.mask_diameter_mm[i])]
        row += [f(p.view_widths_mm[v, i]) for v in range(n_views)]
        if n_frames:
            row += [f(p.frame_diameter_mm[i])] + [f(p.frame_view_widths_mm[v, i]) for v in range(n_frames)]
            row += [f(None if p.frame_density_diameter_mm is None else p.frame_density_diameter_mm[i]),
                    _view_numbers(p.frame_density_views, i), _view_numbers(p.frame_views_crowded, i)]
        row += [f(ref[i]), int(p.excluded[i]), f(None if epipolar is None else epipolar[i])] + [f(c) for c in b.points_mm[i]]
        w.writerow(row)
    return out.getvalue()


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def plot_profiles(path: PathLike, result: QCAResult, max_branches: int = 6) -> bool:
    """Diameter-profile figure (branches with lesions first, then the longest); False without matplotlib."""
    plt = _pyplot()
    if plt is None:
        return False
    ranked = sorted(result.profiles, key=lambda p: (-len(p.lesions), -len(p.unreliable),
                                                    -p.branch.length_mm))[:max_branches]
    fig, axes = plt.subplots(len(ranked), 1, figsize=(8, 2.3 * len(ranked)), squeeze=False)
    min_stenosis = float(result.settings.get("min_stenosis_pct", 20.0))
    for ax, p in zip(axes[:, 0], ranked):
        s = p.branch.arc_length_mm
        ax.plot(s, p.diameter_mm, color="C0", lw=1.5, label="3D cross-section")
        if p.mask_diameter_mm is not None:
            ax.plot(s, p.mask_diameter_mm, color="C2", lw=1, alpha=0.8, label="two-view masks (ellipse)")
        if p.frame_diameter_mm is not None:
            ax.plot(s, p.frame_diameter_mm, color="C3", lw=1, alpha=0.8, label="two-view frames (fitted edges)")
        if p.frame_density_diameter_mm is not None:
            ax.plot(s, p.frame_density_diameter_mm, color="C4", lw=1, alpha=0.8, label="two-view frames (density: area)")
        if p.reference is not None:
            ax.plot(s, p.reference(s), color="k", ls="--", lw=1, label="reference")
        ex = np.where(p.excluded, p.diameter_mm, np.nan)
        ax.plot(s, ex, color="0.6", lw=3, alpha=0.5, label="junction / end (not in reference)")
        for lesion in p.lesions:
            grade = lesion_grade(p, lesion, min_stenosis)
            m = grade.measure
            ax.axvspan(lesion.start_mm, lesion.end_mm, color="C3", alpha=0.15)
            ax.plot([m.mld_position_mm], [m.mld_mm], "v", color="C3")
            images = unseen_on(grade.seen_on_frames, grade.seen_on_masks)
            unseen = f", not seen on the {images}" if images else ""
            ax.annotate(f"MLD {m.mld_mm:.2f} mm, DS {m.diameter_stenosis_pct:.0f}%, L {m.length_mm:.1f} mm "
                        f"({grade.source}{unseen})", (m.mld_position_mm, m.mld_mm),
                        textcoords="offset points", xytext=(6, -12), fontsize=8, color="C3")
        for flagged in p.unreliable:
            lesion = flagged.lesion
            ax.axvspan(lesion.start_mm, lesion.end_mm, facecolor="none", edgecolor="0.5", hatch="//", lw=0)
            ax.annotate(f"unreliable (broken reconstruction): DS {lesion.diameter_stenosis_pct:.0f}%",
                        (lesion.mld_position_mm, lesion.mld_mm), textcoords="offset points", xytext=(6, -12),
                        fontsize=8, color="0.4")
        parent = "" if p.branch.parent_id is None else f" (from branch {p.branch.parent_id})"
        ax.set_title(f"branch {p.branch.branch_id}{parent}: {p.branch.length_mm:.1f} mm", fontsize=9)
        ax.set_ylabel("diameter (mm)")
        ax.set_ylim(0, np.nanmax(np.r_[p.diameter_mm[~p.excluded] if (~p.excluded).any() else p.diameter_mm, 1.0]) * 1.3)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("arc length from the proximal end (mm)")
    fig.tight_layout()
    fig.savefig(str(path), dpi=110)
    plt.close(fig)
    return True


def plot_view_map(path: PathLike, result: QCAResult) -> bool:
    """View-map figure: foreshortening (%) with the overlap hatched; False without matplotlib or a map."""
    plt = _pyplot()
    vm = result.view_map
    if plt is None or vm is None:
        return False
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    extent = [vm.primary_deg[0], vm.primary_deg[-1], vm.secondary_deg[0], vm.secondary_deg[-1]]
    for ax, data, title in ((axes[0], 100 * vm.foreshortening, "foreshortening (%)"),
                            (axes[1], 100 * vm.score, "score: foreshortening + overlap (%)")):
        im = ax.imshow(data, origin="lower", extent=extent, aspect="auto", cmap="viridis_r", vmin=0,
                       vmax=max(float(np.nanmax(data)), 1.0))
        fig.colorbar(im, ax=ax)
        if vm.overlap.any():
            ax.contour(vm.primary_deg, vm.secondary_deg, vm.overlap, levels=[0.05], colors="w", linewidths=1)
        ax.plot(vm.best_primary_deg, vm.best_secondary_deg, "r*", ms=14, label="suggested")
        for k, v in enumerate(result.views):
            ax.plot(v.primary_deg, v.secondary_deg, "o", mfc="none", mec="orange", ms=9,
                    label="acquired" if k == 0 else None)
        ax.set_xlabel("primary angle (° LAO +, RAO −)")
        ax.set_ylabel("secondary angle (° CRA +, CAU −)")
        ax.set_title(title, fontsize=9)
    best = vm.best()
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"branch {result.target['branch_id']} {result.target['start_mm']:.0f}–{result.target['end_mm']:.0f} mm: "
                 f"suggested {best['label']} (foreshortening {100 * best['foreshortening']:.1f}%, "
                 f"overlap {100 * best['overlap']:.0f}%); white line: overlap > 5%", fontsize=9)
    fig.tight_layout()
    fig.savefig(str(path), dpi=110)
    plt.close(fig)
    return True


def _read_result_volume(result_dir: Path, report: Dict[str, Any]):
    occupancy = result_dir / "occupancy.nrrd"
    segmentation = result_dir / "segmentation.seg.nrrd"
    level = float((report.get("settings") or {}).get("threshold", 0.5))
    if occupancy.is_file():
        volume, grid = read_volume(occupancy, "occupancy")
        return volume.astype(np.float32), grid, level, occupancy.name
    if segmentation.is_file():
        label, grid = read_label(segmentation, what="segmentation")
        return label.astype(np.float32), grid, 0.5, segmentation.name
    raise InputError(f"{result_dir} holds neither occupancy.nrrd nor segmentation.seg.nrrd: give the folder that "
                     "`python -m SDFCARLib reconstruct --out …` wrote")


def _masks_for(report: Dict[str, Any], geometry: Optional[Geometry], masks: Optional[Sequence[PathLike]],
               result_dir: Path = Path(".")):
    if geometry is None:
        return None, "no geometry in report.json: mask diameters need the views"
    paths = list(masks) if masks else []
    if not paths and report.get("target_kind") == "mask":
        # a relative name is the result folder's own file (reconstruct --auto-masks writes auto_maskN.png there)
        paths = [result_dir / p for p in ((report.get("inputs") or {}).get("targets") or []) if p]
        if not all(Path(p).is_file() for p in paths):
            return None, "the masks named in report.json were not found; pass --masks to measure 2D diameters"
    if not paths:
        return None, "no view masks (line-integral input or none given): 2D diameters skipped"
    if len(paths) != len(geometry.views):
        raise InputError(f"{len(paths)} masks for {len(geometry.views)} views: give one mask per view, in the views' order")
    return [read_mask(p, geometry.views[i].detector_shape, f"mask of view {i + 1}") for i, p in enumerate(paths)], None


def _densitometry_per_view(report: Dict[str, Any], geometry: Optional[Geometry]) -> List[bool]:
    """Per view, whether its frame's absorbance can be read (report.json "frame_intensity", as the reconstruction's
    DICOM runs said; a view it does not name is read as it is)."""
    said = list(report.get("frame_intensity") or ())
    n_views = len(geometry.views) if geometry is not None else len(said)
    return [n >= len(said) or not unreadable_intensity(said[n]) for n in range(n_views)]


def _frames_for(geometry: Optional[Geometry], view_masks, frames: Optional[Sequence[PathLike]],
                psf_sigma_mm: Union[float, None, str]):
    if not frames:
        return None
    if psf_sigma_mm != PSF_BY_FRAMES and psf_sigma_mm is not None and not (
            isinstance(psf_sigma_mm, numbers.Real) and 0 <= psf_sigma_mm <= MAX_PSF_SIGMA_MM):
        raise InputError(f"--psf-sigma-mm must be a blur in mm at the detector (0 to {MAX_PSF_SIGMA_MM:g}; default 0.3, estimated on "
                         f"frames processed for display) or 'auto', got {psf_sigma_mm}")
    if geometry is None or view_masks is None:
        raise InputError("--frames needs the views' geometry and masks (report.json's or --masks): the masks' widths "
                         "start the fit of each frame's profile")
    if len(frames) != len(geometry.views):
        raise InputError(f"{len(frames)} frames for {len(geometry.views)} views: give one frame per view, in the views' order")
    images = []
    for n, (path, view) in enumerate(zip(frames, geometry.views), start=1):
        image = read_image(path, f"frame of view {n}")
        if image.shape != tuple(view.detector_shape):
            raise InputError(f"frame of view {n} ({path}) has shape {image.shape}, the view's detector is "
                             f"{tuple(view.detector_shape)}: give the frame the mask was drawn on")
        _check_frame_grey_levels(image, n, path)
        images.append(image)
    return images


def _check_frame_grey_levels(image: np.ndarray, n: int, path: PathLike) -> None:
    """Refuse a frame whose grey levels cannot be the detector's: the widths are fitted on −log of them."""
    if not np.isfinite(image).all():
        raise InputError(f"frame of view {n} ({path}) holds NaN or infinite values: give the frame as acquired")
    if is_binary_image(image):
        raise InputError(f"frame of view {n} ({path}) has two grey levels or fewer: it looks like a mask, not an "
                         f"angiogram frame; give masks with --masks and the frames they were drawn on with --frames")
    if float(image.max()) <= 1.0:
        raise InputError(f"frame of view {n} ({path}) has no grey level above 1 (largest {float(image.max()):.3g}): the "
                         f"frames are read as intensities, −log of them the path through contrast, and a frame scaled to "
                         f"[0, 1] or stored as −log keeps none of that; give the frame's grey levels as stored")


def _depth_phrase(angles: Optional[Dict[str, Any]]) -> str:
    if not angles:
        return ""
    weak = " (weak: see the warning)" if angles["median_deg"] < angles.get("weak_below_deg", 15.0) else ""
    return f"; crosses the views' epipolar planes at {angles['median_deg']:.0f}° (median){weak}"


def analysis_summary_lines(data: Dict[str, Any]) -> List[str]:
    """The headline of an analysis.json: the tree, each lesion, the suggested view (the command line
    prints these lines; the Slicer module shows them)."""
    tree = data.get("tree") or {}
    lines = [f"3D-QCA: {tree.get('branches', 0)} branches, {float(tree.get('total_length_mm', 0.0)):.1f} mm of centreline"]
    if tree.get("strands_dropped"):
        lines[0] += f" ({tree['strands_dropped']} strand(s) inside a parent's lumen dropped: the reconstruction is rough there)"

    def lesion_line(lesion: Dict[str, Any]) -> str:
        grade = lesion.get("grade") or dict(lesion, source=GRADED_ON_3D)  # (analysis.json written before grades)
        line = (f"  branch {lesion['branch_id']}: DS {grade['diameter_stenosis_pct']:.0f}%, AS {grade['area_stenosis_pct']:.0f}%, "
                f"MLD {grade['mld_mm']:.2f} mm, reference {grade['reference_diameter_mm']:.2f} mm, "
                f"length {grade['length_mm']:.1f} mm (graded on the {grade['source']})")
        frames = lesion.get("frames") or {}
        others = [(GRADED_ON_3D, lesion)] + [(f"frames ({name})", frames.get(name)) for name in ("density", "edges")]
        seen = [f"{name} DS {m['diameter_stenosis_pct']:.0f}%, MLD {m['mld_mm']:.2f} mm"
                for name, m in others if m and name != grade["source"]]
        if lesion.get("masks_diameter_stenosis_pct") is not None:  # what the drawn masks show there, beside it
            seen.append(f"masks DS {lesion['masks_diameter_stenosis_pct']:.0f}%")
        if seen:
            line += "; " + "; ".join(seen)
        if lesion.get("found_on") in (FOUND_ON_FRAMES, FOUND_ON_MASKS):
            why = MISSED_IN_3D_PHRASE.get(lesion.get("missed_in_3d"), "the 3D sections did not report it")
            line += f"; found on the {lesion['found_on']} only ({why})"
        images = unseen_on(lesion.get("seen_on_frames"), lesion.get("seen_on_masks"))
        if images == "frames":
            line += "; NOT seen on the frames: check it there"
        elif images == "masks":
            line += "; NOT seen on the masks: check it on the angiograms"
        return line

    lines += [lesion_line(lesion) for lesion in data.get("lesions") or []]
    unreliable = data.get("unreliable_lesions") or []
    if unreliable:
        lines.append(f"  {len(unreliable)} more narrowing(s) flagged \"{unreliable[0]['flag']}\" (in analysis.json, not lesions):")
        lines += ["  " + lesion_line(lesion) + f" — {'; '.join(lesion['reasons'])}" for lesion in unreliable]
    target = data.get("target_segment") or {}
    if target.get("length_mm") is not None:
        seen = ", ".join(f"{v['label']} {100 * v['foreshortening']:.1f}%" for v in target.get("acquisition_views") or [])
        lines.append(f"  target segment ({target.get('kind', 'chosen')}): branch {target['branch_id']}, "
                     f"{target['start_mm']:.1f}–{target['end_mm']:.1f} mm, 3D length {target['length_mm']:.1f} mm"
                     + (f"; foreshortened in the acquired views {seen}" if seen else "")
                     + _depth_phrase(target.get("epipolar_angle_deg")))
    best = data.get("best_view")
    if best:
        lines.append(f"  suggested view: {best['label']} (foreshortening {100 * best['foreshortening']:.1f}%, "
                     f"overlap {100 * best['overlap']:.0f}%)")
    return lines


def analyse_result_dir(result_dir: PathLike, out_dir: Optional[PathLike] = None, overwrite: bool = False,
                       masks: Optional[Sequence[PathLike]] = None, ostium_mm: Optional[Sequence[float]] = None,
                       view_step_deg: float = 2.0, min_stenosis_pct: float = 20.0,
                       min_component_share: Optional[float] = None, frames: Optional[Sequence[PathLike]] = None,
                       psf_sigma_mm: Union[float, None, str] = PSF_BY_FRAMES, centreline_on_masks: Optional[bool] = None,
                       segment_mm: Optional[Sequence[Sequence[float]]] = None) -> Dict[str, Path]:
    """Analyse a reconstruction's result folder and write the QCA files (module docstring); return their paths.

    ``frames``: the views' intensity images (vessels dark), one per view: the widths are then also
    fitted to their profiles (``frame_widths.py``; needs the masks, which give the first guess) and the
    lumen area read from their absorbance (``frame_density.py``);
    ``psf_sigma_mm`` None estimates the detector blur from the frames (``pipeline.PSF_BY_FRAMES``, the default:
    0.3 mm, estimated where report.json says the frames were processed for display); ``centreline_on_masks``: see
    ``pipeline.analyse_volume`` (None: on where the masks of two views or more are found);
    ``segment_mm``: two points (LPS mm) marking the target segment (``pipeline.segment_between``)."""
    result_dir = Path(result_dir)
    if not result_dir.is_dir():
        raise InputError(f"{result_dir} is not a folder; give the result folder of `reconstruct`")
    for name, paths in (("masks", masks), ("frames", frames)):
        if isinstance(paths, (str, Path)):  # one path would be read as a list of its characters
            raise InputError(f"{name} is a list of paths, one per view in the views' order; got the one path {paths!r}")
    if isinstance(psf_sigma_mm, str) and psf_sigma_mm.strip().lower() == "auto":
        psf_sigma_mm = None  # the command line's 'auto': estimated from the frames
    for name, number in (("view_step_deg", view_step_deg), ("min_stenosis_pct", min_stenosis_pct)):
        if isinstance(number, bool) or not isinstance(number, numbers.Real):
            raise InputError(f"{name} must be a number, got {number!r}")
    if out_dir is not None and not str(out_dir).strip():
        raise InputError("the output folder is an empty name (an unset variable?): give a folder, or none for "
                         f"{result_dir / 'analysis'}")
    out = Path(out_dir) if out_dir is not None else result_dir / "analysis"
    check_destination(out, ANALYSIS_FILES, overwrite)  # before the analysis, not after it
    report_path = result_dir / "report.json"
    report: Dict[str, Any] = {}
    if report_path.is_file():
        try:
            report = json.loads(report_path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(f"{report_path} is not valid JSON ({exc.msg}); restore it or re-run reconstruct") from exc
    volume, grid, level, source = _read_result_volume(result_dir, report)
    geometry = Geometry.from_dict(report["geometry"]) if isinstance(report.get("geometry"), dict) else None
    view_masks, mask_note = _masks_for(report, geometry, masks, result_dir)
    view_frames = _frames_for(geometry, view_masks, frames, psf_sigma_mm)
    # the frames the reconstruction was given, as their DICOM runs said (report.json "frame_intensity")
    processed = [(n, why) for n, why in enumerate(map(unreadable_intensity, report.get("frame_intensity") or ()), start=1)
                 if why]
    if centreline_on_masks and (view_masks is None or len(view_masks) < 2):
        raise InputError(f"the centreline on the masks needs the masks of two views or more ({mask_note or 'one view'}); "
                         "give --masks, or analyse with the volume's centreline (--centreline volume)")
    reconnection = report.get("reconnection") or {}
    # both reconnections lay bridges (the last one when final_reconnect_max_gap_mm asks for it), and so does the join
    # of the unexplained vessels' fill (fill_unexplained)
    bridges = list(reconnection.get("bridges") or []) + [
        bridge for step in ("final_reconnection", "unexplained_fill") for bridge in (report.get(step) or {}).get("bridges") or []]
    try:
        result = analyse_volume(volume, grid, level=level, views=geometry.views if geometry else (), masks=view_masks,
                                ostium_mm=ostium_mm, view_step_deg=view_step_deg, min_stenosis_pct=min_stenosis_pct,
                                bridges=bridges, frames=view_frames, psf_sigma_mm=psf_sigma_mm,
                                centreline_on_masks=centreline_on_masks, segment_mm=segment_mm,
                                densitometry=_densitometry_per_view(report, geometry),
                                **({} if min_component_share is None
                                                    else {"min_component_share": min_component_share}))
    except SegmentError as exc:
        raise InputError(f"--segment: {exc}") from None
    data = summary(result)
    data["source"] = {"result_dir": str(result_dir.absolute()), "volume": source, "level": level,
                      "report": report_path.name if report else None}
    notes = [mask_note] if mask_note else []
    if view_frames is not None and processed:
        if len(processed) == len(view_frames):
            what = "the frames' widths are fitted to their edges, no lumen area is read from them"
        else:
            what = "the widths of those views' frames are fitted to their edges and no lumen area is read from them; "
            calibrated = [a for a in data["settings"].get("attenuation_per_mm") or () if a is not None]
            what += ("the areas come from the other views" if calibrated else
                     "the other views' attenuation could not be calibrated (too few healthy, uncrowded stretches), "
                     "so no lumen area is read at all")
        notes.append("; ".join(f"view {n}: {why}" for n, why in processed) + f" (the reconstruction's DICOM runs): {what} "
                     "(densitometry needs LIN frames)")
    if reconnection.get("joined") and not reconnection.get("bridges"):
        notes.append(f"report.json says reconnection bridged {reconnection['joined']} gap(s) but not where (a result "
                     "from before bridges were recorded): lesions on them cannot be flagged; reconstruct again to check")
    csv_names = [f"profile_branch{p.branch.branch_id:02d}.csv" for p in result.profiles]
    stale = [p.name for p in out.glob("profile_branch*.csv")] if out.is_dir() and overwrite else []
    names = list(ANALYSIS_FILES) + sorted(set(csv_names) | set(stale))
    with staged_directory(out, names, overwrite) as staging:
        (staging / "centrelines.vtk").write_text(centrelines_vtk_text(result), encoding="utf-8")
        for p, name in zip(result.profiles, csv_names):
            (staging / name).write_text(profile_csv_text(result, p.branch.branch_id), encoding="utf-8")
        figures = {"diameter_profiles": plot_profiles(staging / "diameter_profiles.png", result),
                   "view_map": plot_view_map(staging / "view_map.png", result)}
        if not all(figures.values()):
            notes.append("figures skipped: " + ", ".join(k for k, v in figures.items() if not v)
                         + " (matplotlib missing, or no view map)")
        data["files"] = {"centrelines": "centrelines.vtk", "profiles": csv_names,
                         **{k: f"{k}.png" for k, v in figures.items() if v}}
        data["notes"] = notes
        write_json(staging / "analysis.json", data)
        written = sorted(p.name for p in staging.iterdir())
    return {name: out / name for name in written}
