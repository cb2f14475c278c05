"""3D-QCA benchmark: SDFCARLib.analysis against phantoms with known lesions.

Suites
    tubes   stenosed tubes (30/50/70 % over 5/10/15 mm, diameters 1.5/2.5/4 mm, concentric straight
            or eccentric on a 40 mm bend, random orientation), voxelised exactly at --spacing mm;
            clean masks rendered analytically in LAO 30 / RAO 30 (512² at 0.278 mm, 60° apart)
    trees   procedural LAD/RCA trees with a 50 or 70 % lesion on the main branch (--spacing)
    recon   stenosed tubes (10 cases) reconstructed by SDF-CAR (``fast`` preset, clinical LAO 30 / RAO 30
            binary masks, 128³ at 0.4 mm), then analysed like the others; ``--masks segmented`` takes
            the input a user would have instead: masks segmented by SDFCAR's own pipeline from
            simulated angiograms of the tube (the realistic protocol without motion, ``realistic.py``),
            the angiograms given to the reconstruction as the DICOM path gives them (frame evidence,
            calibration from the frames); ``--masks segmented-moving`` the same with the object moved
            up to 3 mm / 2° between the two acquisitions (the realistic protocol). The analysis uses
            the poses the reconstruction ends with (corrected where the calibration found a motion).

For every case: healthy-diameter error (3D sections and two-view masks), %DS, MLD and lesion
length errors (lesion nearest the true one), 3D length error, foreshortening of the lesion segment
in each acquisition view against the truth centreline's, and the truth's foreshortening in the
suggested view. Prints a Markdown table of case rows and a summary; ``--csv`` keeps the rows.

    python bench/qca.py --suite tubes --csv bench/qca_tubes.csv
    python bench/qca.py --suite recon --cases 4
    python bench/qca.py --suite recon --cases 10 --masks segmented --save runs/recon   # keep the reconstructions
    python bench/qca.py --suite recon --cases 10 --masks segmented --load runs/recon   # analyse them again
    python bench/qca.py --suite recon --cases 10 --masks segmented --grow 0 0.3       # finishing rules, same fits
    python bench/qca.py --suite recon --cases 10 --masks segmented --views lao30-rao30-cra30   # a third view, same tubes

The "graded" line is what analysis.json reports as each lesion's grade (``pipeline.lesion_grade``).
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Union

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from SDFCARLib.analysis.centreline import CentrelineError, CentrelineTree  # noqa: E402
from SDFCARLib.analysis.phantoms import (branch_arc_length_mm, grid_around, lesion_weight, render_mask,  # noqa: E402
                                         stenosed_tree, stenosed_tube, voxelize_exact)
from SDFCARLib.analysis.pipeline import (SegmentError, analyse_volume, lesion_grade, lesion_on_2d_profile,  # noqa: E402
                                        masks_stenosis_pct, segment_between)
from SDFCARLib.analysis.views import EPIPOLAR_WEAK_DEG, foreshortening, foreshortening_map  # noqa: E402
from SDFCARLib.angiogram import AngiogramSettings  # noqa: E402
from SDFCARLib.geometry import Geometry, VolumeGrid, standard_geometry  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree  # noqa: E402
from SDFCARLib.settings import parse_setting_overrides  # noqa: E402
from SDFCARLib.lumen_profile import PSF_BY_FRAMES  # noqa: E402

VIEW_SETS = ("lao30-rao30", "lao30-rao30-cra30")  # --views: the acquisitions (standard_geometry's names)
VIEWS = list(standard_geometry(VIEW_SETS[0]).views)  # filled in place by --views, so score's default follows
INNER_MARK_MM = 5.0  # the inner landmarks of the 3D length: this far from either true end


def _truth_samples(phantom):
    """Dense truth centreline samples: points, diameter, lesion weight (0 = healthy), branch name, arc."""
    pts, dia, w, names, arcs = [], [], [], [], []
    t = phantom.truth
    for b in phantom.tree.branches:
        s = branch_arc_length_mm(b)
        pts.append(b.points)
        dia.append(2 * b.radii)
        on = b.name == t.get("branch", b.name)
        # (for an eccentric tube the arc runs along the lumen centres, a fraction of a mm longer than the
        # axis over the lesion: the healthy/lesion split is what matters here)
        w.append(lesion_weight(s - t["lesion_start_mm"], t["lesion_length_mm"]) if on else np.zeros(len(s)))
        names += [b.name] * len(s)
        arcs.append(s)
    return np.concatenate(pts), np.concatenate(dia), np.concatenate(w), np.asarray(names), np.concatenate(arcs)


def _truth_span(segment_mm, truth_points, truth_names, kd, min_run=3):
    """The truth centreline over the span of a measured segment, following it across truth branches: a
    tree's reconstructed main branch runs on from the truth's main vessel into one of its distal branches,
    and the samples of all branches are concatenated, so a span between the samples nearest the segment's
    two ends would run across unrelated branches. Per run of segment points nearest one truth branch, that
    branch's samples between the run's first and last nearest (runs of fewer than ``min_run`` points, the
    other child at a junction, are skipped)."""
    _, nearest = kd.query(segment_mm)
    names = truth_names[nearest]
    cuts = np.flatnonzero(names[1:] != names[:-1]) + 1
    runs = np.split(nearest, cuts)
    kept = [run for run in runs if len(run) >= min_run] or [max(runs, key=len)]
    pieces = [truth_points[int(r[0]):int(r[-1]) + 1] if r[0] <= r[-1] else truth_points[int(r[-1]):int(r[0]) + 1][::-1]
              for r in kept]
    return np.concatenate(pieces)


def _truth_path_to(tree, end_point_mm, attach_tol_mm=0.2):
    """The truth centreline from the tree's ostium (its first branch's first point) to the end of the branch
    nearest ``end_point_mm``: that branch, preceded by each ancestor up to where the child leaves it. A
    phantom's side branch starts on a point of its parent (within ``attach_tol_mm`` after resampling)."""
    branches = tree.branches
    distance = [float(np.min(np.linalg.norm(b.points - end_point_mm, axis=1))) for b in branches]
    chain = [branches[int(np.argmin(distance))].points]
    current = chain[0]
    for _ in branches:
        if current is branches[0].points:
            return np.concatenate(chain)
        start = current[0]
        parent, index = None, 0
        for b in branches:  # the branch that passes through the start (a sibling leaving there begins at it)
            gap = np.linalg.norm(b.points - start, axis=1)
            if b.points is not current and gap.min() <= attach_tol_mm and (int(np.argmin(gap)) > 0 or b is branches[0]):
                parent, index = b, int(np.argmin(gap))
                break
        if parent is None:
            break
        chain.insert(0, parent.points[:index])  # the child's first point stands for the parent's point there
        current = parent.points
    raise ValueError("a truth branch starts on no other branch: the tree's chain to its ostium is broken")


def score(phantom, volume, grid, level, masks, ostium, view_step_deg, frames=None, views=VIEWS,
          centreline_on_masks=False) -> Dict[str, float]:
    t0 = time.perf_counter()
    if ANALYSE_WITHOUT_FRAMES:  # as analyse does where the user gives masks only
        frames = None
    r = analyse_volume(volume, grid, level=level, views=views, masks=masks, ostium_mm=ostium, view_step_deg=view_step_deg,
                       frames=frames, psf_sigma_mm=PSF_SIGMA_MM[0], centreline_on_masks=centreline_on_masks,
                       search_masks=SEARCH_MASKS, densitometry=not DISPLAY_FRAMES)
    elapsed = time.perf_counter() - t0
    tp, td, tw, tnames, tarc = _truth_samples(phantom)
    kd = cKDTree(tp)
    truth = phantom.truth
    row: Dict[str, float] = {"seconds": elapsed, "branches": len(r.tree.branches)}
    err3, err2, errf, errd = [], [], [], []
    best = None  # (distance to the true lesion centre, lesion, profile, which)
    # The middle of the lesion's plateau, not its first point (np.argmax): a 15 mm lesion's plateau begins 2 mm
    # inside it, 5.5 mm before its middle, where a bump of a rough reconstruction was taken for it (RESULTS §38a)
    plateau = np.flatnonzero(tw == tw.max()) if tw.max() > 0 else None
    centre = None if plateau is None else tp[plateau[len(plateau) // 2]]
    # A tube is one vessel: its lesion is looked for on the main branch first, where one lies near enough; a
    # ghost spur leaving the tube beside the lesion has a narrowing at its root as near (RESULTS §38d)
    main = None  # a tube's main branch: the root nearest its ostium (the longest path)
    if "length_mm" in truth:
        ostium = np.asarray(truth["ostium_mm"], float)
        main = min((x for x in r.tree.branches if x.parent_id is None), key=lambda x: np.linalg.norm(x.points_mm[0] - ostium))
    best_on_main = None
    for p in r.profiles:
        b = p.branch
        dist, k = kd.query(b.points_mm)
        healthy = (tw[k] == 0) & ~p.excluded & (dist < td[k])
        err3.append(np.abs(p.diameter_mm - td[k])[healthy])
        if p.mask_diameter_mm is not None:
            err2.append(np.abs(p.mask_diameter_mm - td[k])[healthy])
        if p.frame_diameter_mm is not None:
            errf.append(np.abs(p.frame_diameter_mm - td[k])[healthy])
        if p.frame_density_diameter_mm is not None:
            errd.append(np.abs(p.frame_density_diameter_mm - td[k])[healthy])
        for lesion in p.lesions:
            pos = b.points_mm[np.argmin(np.abs(b.arc_length_mm - lesion.mld_position_mm))]
            d = np.linalg.norm(pos - centre)
            if best is None or d < best[0]:
                best = (d, lesion, p)
            if main is not None and b.branch_id == main.branch_id and (best_on_main is None or d < best_on_main[0]):
                best_on_main = (d, lesion, p)
    if best_on_main is not None and best_on_main[0] <= truth["lesion_length_mm"]:
        best = best_on_main
    e3, e2 = np.concatenate(err3), np.concatenate(err2) if err2 else np.array([np.nan])
    row.update({"healthy_mae_3d_mm": float(np.nanmean(e3)), "healthy_mae_masks_mm": float(np.nanmean(e2))})
    if errf:
        row["healthy_mae_frames_mm"] = float(np.nanmean(np.concatenate(errf)))
    if errd:
        density = np.concatenate(errd)  # all NaN where no healthy stretch had a density width
        row["healthy_mae_density_mm"] = float(np.nanmean(density)) if np.isfinite(density).any() else float("nan")
    # Lesions other than the true one (rough surfaces, bridges), and how many the masks do not show (the flag).
    others = [(q, x) for q in r.profiles for x in q.lesions
              if best is None or best[0] > truth["lesion_length_mm"] or x is not best[1]]
    # the lesions found on the masks only (no frames) or the frames only, each as T(rue)/F(alse):root or side
    # branch:branch mm:lesion mm:the 2D %DS:the 2D reference mm:the 3D sections' %DS over the same stretch:where
    # their narrowest section lies in that stretch (0 its start, 1 its end)
    for field in ("masks_only", "frames_only"):
        details = []
        for q in r.profiles:
            for x in getattr(q, field):
                pos = q.branch.points_mm[np.argmin(np.abs(q.branch.arc_length_mm - x.mld_position_mm))]
                true = centre is not None and np.linalg.norm(pos - centre) <= truth["lesion_length_mm"]
                g = lesion_grade(q, x)
                details.append(f"{'T' if true else 'F'}:{'root' if q.branch.parent_id is None else 'side'}:"
                               f"{q.branch.length_mm:.1f}:{g.measure.length_mm:.1f}:{g.measure.diameter_stenosis_pct:.1f}:"
                               f"{g.measure.reference_diameter_mm:.2f}:{x.diameter_stenosis_pct:.1f}:"
                               f"{(x.mld_position_mm - x.start_mm) / max(x.end_mm - x.start_mm, 1e-9):.2f}")
        row[field] = " ".join(details)
    row.update({"false_lesions": len(others),
                "false_lesions_unseen_on_masks": sum(lesion_grade(q, x).seen_on_masks is False for q, x in others),
                # each as "3D %DS / the masks' largest %DS there", to choose the masks' rule on
                "false_lesions_ds_3d_masks": " ".join(f"{x.diameter_stenosis_pct:.1f}/{masks_stenosis_pct(q, x) or 0.0:.1f}"
                                                      for q, x in others)})
    if best is None or best[0] > truth["lesion_length_mm"]:
        row.update({"found": 0})
        return row
    _, lesion, p = best
    row.update({"found": 1, "ds_true": truth["diameter_stenosis_pct"], "ds_3d": lesion.diameter_stenosis_pct,
                "ds_err_3d": lesion.diameter_stenosis_pct - truth["diameter_stenosis_pct"],
                "mld_err_3d_mm": lesion.mld_mm - truth["mld_mm"],
                "len_err_3d_mm": lesion.length_mm - truth["lesion_length_mm"]})
    # The same lesion on the two-view mask and frame profiles, as analyse reports it for the frames.
    both = None
    if p.frame_diameter_mm is not None and p.frame_density_diameter_mm is not None:
        with np.errstate(invalid="ignore"):  # the mean of the two frame measures, where both exist
            both = 0.5 * (p.frame_diameter_mm + p.frame_density_diameter_mm)
    for source, profile in (("masks", p.mask_diameter_mm), ("frames", p.frame_diameter_mm),
                            ("density", p.frame_density_diameter_mm), ("both", both)):
        same = lesion_on_2d_profile(p, profile, lesion)
        if same is not None:
            row.update({f"ds_err_{source}": same.diameter_stenosis_pct - truth["diameter_stenosis_pct"],
                        f"mld_err_{source}_mm": same.mld_mm - truth["mld_mm"],
                        f"len_err_{source}_mm": same.length_mm - truth["lesion_length_mm"]})
    grade = lesion_grade(p, lesion)  # what analysis.json reports as the lesion's grade
    if grade.seen_on_masks is not None:
        row["seen_on_masks"] = int(grade.seen_on_masks)
        row["masks_ds"] = masks_stenosis_pct(p, lesion)
    row.update({"graded_on": grade.source, "ds_err_grade": grade.measure.diameter_stenosis_pct - truth["diameter_stenosis_pct"],
                "mld_err_grade_mm": grade.measure.mld_mm - truth["mld_mm"],
                "len_err_grade_mm": grade.measure.length_mm - truth["lesion_length_mm"]})
    b = p.branch
    if "length_mm" in truth:  # a tube: its centreline against the main branch from the ostium (the longest path),
        # not the lesion's branch, which on a rough surface can be a parallel side strand (RESULTS §20)
        row["length_err_pct"] = 100 * (main.length_mm - truth["length_mm"]) / truth["length_mm"]
        # how far the main branch's centreline runs from the true one (3 mm from either end left out): its
        # wander lengthens the tube (RESULTS §32d)
        inner = (main.arc_length_mm >= 3.0) & (main.arc_length_mm <= main.arc_length_mm[-1] - 3.0)
        row["axis_offset_mm"] = float(kd.query(main.points_mm[inner])[0].mean()) if inner.any() else float("nan")
        # the length between two inner landmarks (the true axis 5 mm from either end), marked on the main branch
        # as a user marks a segment (analyse --segment); the rest of the error is the ends'
        true_arc = tarc[tnames == tnames[0]]
        marks = [tp[np.argmin(np.abs(true_arc - a))] for a in (INNER_MARK_MM, truth["length_mm"] - INNER_MARK_MM)]
        try:
            marked = segment_between(CentrelineTree([main]), *marks)
        except SegmentError:  # a landmark farther than the product allows from the centreline: no marked length
            marked = None
        if marked is not None:
            inner_truth = truth["length_mm"] - 2 * INNER_MARK_MM
            row["inner_length_err_pct"] = 100 * (marked["end_mm"] - marked["start_mm"] - inner_truth) / inner_truth
            row["start_excess_mm"] = marked["start_mm"] - INNER_MARK_MM  # beyond the true ostium end (+) or short (−)
            row["end_excess_mm"] = float(main.length_mm - marked["end_mm"] - INNER_MARK_MM)
        row["lesion_on_main_branch"] = int(b.branch_id == main.branch_id)
    else:  # a tree: its main path from the ostium (the root branch nearest it) against the truth's path to where
        # that branch ends, as for a tube. The total over all branches is kept beside it: where each side branch
        # is said to begin moves it (a branch leaving at a shallow angle shares its parent's lumen for millimetres
        # and its centreline starts where the lumens part; RESULTS §72c)
        ostium = phantom.tree.branches[0].points[0]
        root = min((x for x in r.tree.branches if x.parent_id is None), key=lambda x: np.linalg.norm(x.points_mm[0] - ostium))
        path = _truth_path_to(phantom.tree, root.points_mm[-1])
        path_mm = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
        row["length_err_pct"] = 100 * (root.length_mm - path_mm) / path_mm
        total = phantom.tree.total_length_mm()
        row["tree_total_length_err_pct"] = 100 * (r.tree.total_length_mm() - total) / total
    # Foreshortening of the target segment (measured centreline) vs the truth centreline over the same span.
    tg = r.target
    idx = np.flatnonzero((b.arc_length_mm >= tg["start_mm"]) & (b.arc_length_mm <= tg["end_mm"]))
    if tg["branch_id"] == b.branch_id and len(idx) > 2:
        seg = b.points_mm[idx]
        tseg = _truth_span(seg, tp, tnames, kd)
        fs_err = [foreshortening(seg, v) - foreshortening(tseg, v) for v in VIEWS]
        seg_mm = float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
        tseg_mm = float(np.linalg.norm(np.diff(tseg, axis=0), axis=1).sum())
        row["segment_length_err_pct"] = 100 * (seg_mm - tseg_mm) / tseg_mm  # the target segment's 3D length
        row["fs_err_pts"] = float(100 * np.max(np.abs(fs_err)))
        # the segment's median angle to the views' epipolar planes (analysis.json target_segment): where it is small
        # the two views place the segment in depth weakly (RESULTS §102a)
        row["target_epipolar_deg"] = (tg.get("epipolar_angle_deg") or {}).get("median_deg")
        if len(VIEWS) > 2:  # the pair's two views alone, to set beside the two-view rows
            row["fs_err_pair_pts"] = float(100 * np.max(np.abs(fs_err[:2])))
        if r.view_map is not None:
            bv = r.view_map.best()
            row["best_view"] = bv["label"]
            row["best_fs_truth_pct"] = float(100 * foreshortening_map(tseg, bv["primary_deg"], bv["secondary_deg"]))
            aa, bb = np.meshgrid(r.view_map.primary_deg, r.view_map.secondary_deg)
            row["least_fs_truth_pct"] = float(100 * foreshortening_map(tseg, aa, bb).min())  # what any view could do
    return row


def tube_cases(seed: int = 0):
    rng = np.random.default_rng(seed)
    for sev, length, diameter, ecc in itertools.product((30, 50, 70), (5, 10, 15), (1.5, 2.5, 4.0), (False, True)):
        direction = rng.normal(size=3)
        ph = stenosed_tube(length_mm=40.0, diameter_mm=diameter, stenosis_pct=sev, lesion_length_mm=length,
                           eccentric=ecc, direction=direction, curvature_radius_mm=40.0 if ecc else None)
        yield (f"{sev}%/{length}mm/{diameter}mm/{'ecc' if ecc else 'con'}", ph,
               {"axis_foreshortening_pct": [round(v, 1) for v in axis_foreshortening_pct(direction)]})


def tree_cases():
    for maker, branch, seed, sev in ((lad_tree, "LM-LAD", 0, 50), (lad_tree, "LM-LAD", 1, 70),
                                     (rca_tree, "RCA", 0, 50), (rca_tree, "RCA", 1, 70)):
        yield f"{maker.__name__}({seed}) {branch} {sev}%", stenosed_tree(maker(seed), branch, sev, 10.0), {}


def run_truth(cases, spacing, view_step_deg, mask_source="clean"):
    from SDFCARLib.masks import MaskError

    rows = []
    for n, (name, ph, extra) in enumerate(cases):
        grid = grid_around(ph.tree, spacing)
        label = voxelize_exact(ph.tree, grid)
        frames = None
        if mask_source == "segmented":
            try:
                masks, _, frames, _ = segmented_masks(ph.tree, n)
            except MaskError as exc:  # a tube seen almost end-on in one view: no elongated vessel there
                rows.append(dict(case=name, error=str(exc)))
                print(f"{name}: {exc}", flush=True)
                continue
        else:
            masks = [render_mask(ph.tree, v) for v in VIEWS]
        ostium = ph.truth.get("ostium_mm") or ph.tree.branches[0].points[0]
        for centreline in CENTRELINES:
            row = score(ph, label.astype(np.float32), grid, 0.5, masks, ostium, view_step_deg, frames,
                        centreline_on_masks=centreline == "masks")
            rows.append(dict(case=name, centreline=centreline, **extra, **row))
            print(f"{name}: " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in rows[-1].items()),
                  flush=True)
    return rows


#: realistic.RealisticOptions overrides for the segmented masks (``--mask-option``), e.g. the mask pipeline's edge rule
MASK_OPTIONS: Dict[str, Optional[float]] = {}


def segmented_masks(tree, seed, moving=False):
    """The views' masks segmented from simulated angiograms of ``tree``, their Dice against the true
    silhouettes, the angiograms and the motion of the object of the view moved most against view 1 (none
    unless ``moving``: then the realistic protocol's, up to 3 mm / 2°). With a third view the pair's are
    those without it."""
    from SDFCARLib.realistic import RealisticOptions, realistic_input
    from SDFCARLib.settings import REALISTIC_PROTOCOLS

    label_grid = grid_around(tree, 0.2)
    label = voxelize_exact(tree, label_grid)
    # the pair's protocol: its motion and noise settings are the three-view protocol's too
    protocol = "realistic-lao30-rao30" if moving else "realistic-static-lao30-rao30"
    options = RealisticOptions(**{**REALISTIC_PROTOCOLS[protocol], **MASK_OPTIONS, "display": DISPLAY_FRAMES})
    realistic = realistic_input(label, Geometry(label_grid, VIEWS[:2]), seed, options)
    masks, frames, info = list(realistic.masks), list(realistic.frames), realistic.info
    dice, motions = [v["mask_dice"] for v in info["views"]], list(info["motion"])
    if len(VIEWS) > 2:
        # The pair's frames exactly as without the third view (the rows compare tube by tube); the third
        # from a draw of all three, whose motions begin with the pair's (drawn before any frame)
        third = realistic_input(label, Geometry(label_grid, VIEWS), seed, options)
        assert third.info["motion"][:2] == motions, "the pair's motion differs with a third view"
        masks += third.masks[2:]
        frames += third.frames[2:]
        dice += [v["mask_dice"] for v in third.info["views"][2:]]
        motions += third.info["motion"][2:]
    # with three views, the view whose object moved most (each is moved against view 1's)
    moved = max(motions[1:], key=lambda m: float(np.linalg.norm(m["translation_mm"])))
    return masks, [round(d, 4) for d in dice], frames, moved


def axis_foreshortening_pct(direction) -> List[float]:
    """Foreshortening (%) of a straight segment along ``direction`` in each acquisition view."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    return [100.0 * (1.0 - float(np.sqrt(max(0.0, 1.0 - float(d @ v.detector_direction) ** 2)))) for v in VIEWS]


def tube_direction(seed: int, max_foreshortening_pct=None) -> np.ndarray:
    """The case's random tube axis; with a limit, the first draw of its stream that no view foreshortens
    more (as a clinician picks views that show the lesion) in the first two views."""
    rng = np.random.default_rng(seed)
    while True:
        direction = rng.normal(size=3)
        # the limit on the two views of the pair only, so a third view (--views) analyses the same tubes
        if max_foreshortening_pct is None or max(axis_foreshortening_pct(direction)[:2]) <= max_foreshortening_pct:
            return direction


#: --elevation-deg: every recon tube's axis (cos e, 0, sin e) instead of its random draw; near the isocentre LAO 30 / RAO
#: 30's epipolar planes are horizontal, so e is the axis' angle to them (RESULTS §102a)
ELEVATION_DEG: Optional[float] = None
CENTRELINES = ["volume"]  # the analysis' centreline: "volume", "masks" (main's --centreline)
ANALYSE_WITHOUT_FRAMES = False  # --no-frames: the analysis on the masks alone, as analyse without --frames
SEARCH_MASKS = True  # analyse_volume's search_masks (--no-masks-search: off, the analysis before RESULTS §43)
# --display: the segmented masks' angiograms processed for display (``display_processing.py``) before they are
# segmented and read, and analysed as ``analyse`` reads a DISP run (edges only, no densitometry)
DISPLAY_FRAMES = False
#: the detector blur the analysis assumes (--psf-sigma-mm): analyse's default (the simulation's own 0.3 mm on linear
#: frames, estimated on display ones); None estimates it from any frames
PSF_SIGMA_MM: List[Union[float, None, str]] = [PSF_BY_FRAMES]

RECON_TUBES = [  # the recon suite's ten tubes: name, stenosed_tube's parameters
    ("50%/10mm/3mm/con", dict(stenosis_pct=50, lesion_length_mm=10, diameter_mm=3.0, eccentric=False)),
    ("70%/10mm/3mm/ecc", dict(stenosis_pct=70, lesion_length_mm=10, diameter_mm=3.0, eccentric=True, curvature_radius_mm=40.0)),
    ("50%/15mm/2.5mm/ecc", dict(stenosis_pct=50, lesion_length_mm=15, diameter_mm=2.5, eccentric=True, curvature_radius_mm=40.0)),
    ("70%/5mm/4mm/con", dict(stenosis_pct=70, lesion_length_mm=5, diameter_mm=4.0, eccentric=False)),
    ("30%/10mm/2mm/con", dict(stenosis_pct=30, lesion_length_mm=10, diameter_mm=2.0, eccentric=False)),
    ("50%/10mm/1.5mm/con", dict(stenosis_pct=50, lesion_length_mm=10, diameter_mm=1.5, eccentric=False)),
    ("70%/15mm/2.5mm/con", dict(stenosis_pct=70, lesion_length_mm=15, diameter_mm=2.5, eccentric=False)),
    ("50%/5mm/3.5mm/ecc", dict(stenosis_pct=50, lesion_length_mm=5, diameter_mm=3.5, eccentric=True, curvature_radius_mm=40.0)),
    ("30%/15mm/3mm/ecc", dict(stenosis_pct=30, lesion_length_mm=15, diameter_mm=3.0, eccentric=True, curvature_radius_mm=40.0)),
    ("70%/10mm/2mm/ecc", dict(stenosis_pct=70, lesion_length_mm=10, diameter_mm=2.0, eccentric=True, curvature_radius_mm=40.0)),
]


def run_recon(n_cases, view_step_deg, steps=None, save_dir=None, first=0, mask_source="clean", max_foreshortening_pct=None,
              load_dir=None, grow_thresholds=None, overrides=None):
    """Reconstruct and analyse each case. ``grow_thresholds``: fit the field once per case and finish it once
    per grow threshold (``RegionSettings.grow_threshold``), so the rows of a case differ only in that rule;
    each row then carries its ``grow_threshold``. ``overrides``: settings that differ from ``fast`` (``--set``)."""
    from SDFCARLib.io import read_volume, write_volume_nrrd
    from SDFCARLib.masks import MaskError
    from SDFCARLib.optimiser import fit_field, make_settings, reconstruct

    rows = []
    for n, (name, kw) in list(enumerate(RECON_TUBES))[first:first + n_cases]:
        direction = (tube_direction(n, max_foreshortening_pct) if ELEVATION_DEG is None else
                     np.array([np.cos(np.radians(ELEVATION_DEG)), 0.0, np.sin(np.radians(ELEVATION_DEG))]))
        ph = stenosed_tube(length_mm=40.0, direction=direction, **kw)
        geometry = Geometry(VolumeGrid((128, 128, 128), (0.4, 0.4, 0.4)), VIEWS)
        extra = {"axis_foreshortening_pct": [round(v, 1) for v in axis_foreshortening_pct(direction)]}
        if mask_source in ("segmented", "segmented-moving"):
            try:
                masks, extra["input_mask_dice"], frames, motion = segmented_masks(ph.tree, n, mask_source == "segmented-moving")
                if mask_source == "segmented-moving":
                    extra["motion_mm"] = round(float(np.linalg.norm(motion["translation_mm"])), 2)
                    extra["motion_deg"] = round(float(np.linalg.norm(motion["rotation_deg"])), 2)
            except MaskError as exc:  # e.g. a tube seen almost end-on in one view: no elongated vessel there
                rows.append(dict(case=name, **extra, error=str(exc)))
                print(f"{name}: {extra} — {exc}", flush=True)
                continue
        else:
            masks, frames = [render_mask(ph.tree, v) for v in VIEWS], None
        settings = make_settings("fast", **({"steps": steps} if steps else {}), **(overrides or {}))
        # display-processed frames give no path lengths, as a DISP run's do not
        frame_intensity = ["DISP"] * len(frames) if DISPLAY_FRAMES and frames is not None else None

        def add_row(occupancy, views, threshold, reconstruct_s, **rule):
            for centreline in CENTRELINES:
                try:
                    row = score(ph, occupancy, geometry.volume, float(threshold), masks, ph.truth["ostium_mm"],
                                view_step_deg, frames, views, centreline_on_masks=centreline == "masks")
                except CentrelineError as exc:  # e.g. nothing above the level: a failed case, not a failed run
                    row = {"error": str(exc)}
                rows.append(dict(case=name, centreline=centreline, **rule, reconstruct_s=reconstruct_s, **extra, **row))
                print(f"{name}: " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                                              for k, v in rows[-1].items()), flush=True)

        if grow_thresholds:
            fitted = fit_field(geometry, masks, settings, "mask", frames=frames, frame_intensity=frame_intensity)
            t_fit = time.perf_counter() - fitted.t_start
            for grow in grow_thresholds:
                variant = settings.replace(grow_threshold=grow)
                result = fitted.finished(variant)
                add_row(result.occupancy, result.geometry.views, variant.region.threshold, t_fit, grow_threshold=grow)
            continue
        occupancy_name, geometry_name = f"recon{n}_occupancy.nrrd", f"recon{n}_geometry.json"
        t0 = time.perf_counter()
        if load_dir:  # a reconstruction --save kept (same case, same masks): the analysis alone is measured
            occupancy, _ = read_volume(Path(load_dir) / occupancy_name)
            views = Geometry.from_dict(json.loads((Path(load_dir) / geometry_name).read_text())).views
            t_rec = None
        else:
            rec = reconstruct(geometry, masks, settings, "mask", frames=frames, frame_intensity=frame_intensity)
            occupancy, views, t_rec = rec.occupancy, rec.geometry.views, time.perf_counter() - t0
        if save_dir:  # keep the reconstruction (occupancy on the 0.4 mm grid, LPS; the poses it ended with)
            Path(save_dir).mkdir(parents=True, exist_ok=True)
            write_volume_nrrd(Path(save_dir) / occupancy_name, occupancy, geometry.volume)
            (Path(save_dir) / geometry_name).write_text(json.dumps(Geometry(geometry.volume, views).to_dict()))
        add_row(occupancy, views, settings.region.threshold, t_rec)
    return rows


def summarise(rows: List[Dict]) -> str:
    def col(key, subset=None):
        v = np.array([r[key] for r in (rows if subset is None else subset) if key in r and r[key] is not None], float)
        return v[np.isfinite(v)]

    found = [r for r in rows if r.get("found")]
    sig = [r for r in found if r.get("ds_true", 0) >= 50]
    frames = bool(col("healthy_mae_frames_mm").size)
    lines = ["| measure | 3D sections | the views' masks |"
             + (" the views' frames (edges) | frames (density) | frames (mean of the two) |" if frames else "")
             + " target |", "|---|---|---|" + ("---|---|---|" if frames else "") + "---|"]

    def ms(v):
        return "n/a" if v.size == 0 else f"{v.mean():+.2f} ± {v.std():.2f} (max |·| {np.abs(v).max():.2f})"

    def mae(key):
        v = col(key)
        return "n/a" if v.size == 0 else f"{v.mean():.3f} (worst {v.max():.3f})"

    def extra(key, subset):
        return (f" {ms(col(key, subset))} | {ms(col(key.replace('frames', 'density'), subset))} |"
                f" {ms(col(key.replace('frames', 'both'), subset))} |") if frames else ""

    mild = [r for r in found if r["ds_true"] < 50]
    lines.append(f"| healthy diameter MAE (mm), mean of cases | {mae('healthy_mae_3d_mm')} | {mae('healthy_mae_masks_mm')} |"
                 + (f" {mae('healthy_mae_frames_mm')} | {mae('healthy_mae_density_mm')} | — |" if frames else "") + " ≤ 0.15 |")
    lines.append(f"| %DS error, 50–70 % lesions (points) | {ms(col('ds_err_3d', sig))} | {ms(col('ds_err_masks', sig))} |"
                 + extra("ds_err_frames", sig) + " within 8 |")
    lines.append(f"| %DS error, 30 % lesions (points) | {ms(col('ds_err_3d', mild))} | {ms(col('ds_err_masks', mild))} |"
                 + extra("ds_err_frames", mild) + " — |")
    lines.append(f"| MLD error (mm) | {ms(col('mld_err_3d_mm', found))} | {ms(col('mld_err_masks_mm', found))} |"
                 + extra("mld_err_frames_mm", found) + " (CAAS 0.01 ± 0.13) |")
    lines.append(f"| lesion length error (mm) | {ms(col('len_err_3d_mm', found))} | {ms(col('len_err_masks_mm', found))} |"
                 + extra("len_err_frames_mm", found) + " within 2 |")
    lines.append(f"| 3D length error, main branch from the ostium (%) | {ms(col('length_err_pct', found))} | — |{' — | — | — |' if frames else ''} within 2 % |")
    if col("tree_total_length_err_pct", found).size:
        lines.append(f"| trees: total length of all branches (%) | {ms(col('tree_total_length_err_pct', found))} | — |{' — | — | — |' if frames else ''} — |")
    lines.append(f"| the target segment's 3D length (%) | {ms(col('segment_length_err_pct', found))} | — |{' — | — | — |' if frames else ''} within 2 % |")
    lines.append(f"| 3D length between inner landmarks, 5 mm from each end (%) | {ms(col('inner_length_err_pct', found))} | — |{' — | — | — |' if frames else ''} within 2 % |")
    lines.append(f"| ostium end beyond the truth (mm) | {ms(col('start_excess_mm', found))} | — |{' — | — | — |' if frames else ''} — |")
    lines.append(f"| distal end beyond the truth (mm) | {ms(col('end_excess_mm', found))} | — |{' — | — | — |' if frames else ''} — |")
    lines.append(f"| main branch's centreline from the true axis (mm, mean) | {mae('axis_offset_mm')} | — |{' — | — | — |' if frames else ''} — |")
    lines.append(f"| foreshortening error, acquisition views (points, worst view) | {ms(col('fs_err_pts', found))} | — |{' — | — | — |' if frames else ''} within 1 |")
    if col("target_epipolar_deg", found).size:  # the same two errors where the views place the segment in depth weakly
        for name, weak in (("under", True), ("at or over", False)):
            part = [r for r in found if r.get("target_epipolar_deg") is not None
                    and (r["target_epipolar_deg"] < EPIPOLAR_WEAK_DEG) == weak]
            lines.append(f"| … target segments {name} {EPIPOLAR_WEAK_DEG:g}° to the epipolar planes ({len(part)}): "
                         f"foreshortening error; 3D length (%) | {ms(col('fs_err_pts', part))}; "
                         f"{ms(col('segment_length_err_pct', part))} | — |{' — | — | — |' if frames else ''} — |")
    if col("fs_err_pair_pts", found).size:  # --views with a third: the pair's two, as the two-view rows read
        lines.append(f"| foreshortening error, the pair's two views only (points, worst view) | {ms(col('fs_err_pair_pts', found))} | — |{' — | — | — |' if frames else ''} within 1 |")
    lines.append(f"| truth foreshortening in the suggested view (%) | {ms(col('best_fs_truth_pct', found))} | — |{' — | — | — |' if frames else ''} ≤ 5 |")
    lines.append(f"| least truth foreshortening over the range (%) | {ms(col('least_fs_truth_pct', found))} | — |{' — | — | — |' if frames else ''} (the bound) |")
    lines.append(f"\nlesions found: {len(found)} of {len(rows)} cases; |%DS err| ≤ 8 in {int(np.sum(np.abs(col('ds_err_3d', sig)) <= 8))} of {len(sig)} "
                 f"50–70 % cases (3D), |length err| ≤ 2 mm in {int(np.sum(np.abs(col('len_err_3d_mm', found)) <= 2))} of {len(found)}; "
                 f"suggested view ≤ 5 % in {int(np.sum(col('best_fs_truth_pct', found) <= 5))} of {len(col('best_fs_truth_pct', found))}"
                 + (f"; lesion on the main branch in {int(col('lesion_on_main_branch', found).sum())} of "
                    f"{col('lesion_on_main_branch', found).size}" if col('lesion_on_main_branch', found).size else ""))
    if frames:
        within = ", ".join(f"{name} {int(np.sum(np.abs(col('ds_err_' + key, sig)) <= 8))}"
                           for name, key in (("edges", "frames"), ("density", "density"), ("mean", "both")))
        lines.append(f"frames, |%DS err| ≤ 8 of the {len(sig)} 50–70 % lesions found in 3D: {within}")
    seen = col("seen_on_masks", found)
    if seen.size:
        false, unseen = col("false_lesions"), col("false_lesions_unseen_on_masks")
        lines.append(f"seen on the masks (pipeline.seen_on_masks): true lesions {int(seen.sum())} of {seen.size} "
                     f"({int(np.sum(col('seen_on_masks', mild)))} of {col('seen_on_masks', mild).size} 30 %); "
                     f"other lesions not seen on the masks (flagged) {int(unseen.sum())} of {int(false.sum())}")
        # the masks' largest %DS at a lesion over its 3D %DS: can a ratio tell true lesions from the others?
        true_ratio = np.array([r["masks_ds"] / r["ds_3d"] for r in found if r.get("masks_ds") is not None])
        other_ratio = np.array([float(m) / float(d) for r in rows for d, m in
                                (pair.split("/") for pair in str(r.get("false_lesions_ds_3d_masks") or "").split())
                                if float(d) > 0])  # (a lesion found on the masks only may not narrow in 3D)
        lines.append(f"masks' %DS / 3D %DS: true lesions min {true_ratio.min():.2f}, below 0.6 in {int(np.sum(true_ratio < 0.6))} "
                     f"of {true_ratio.size}; other lesions " + (f"max {other_ratio.max():.2f}, at or above 0.6 in "
                     f"{int(np.sum(other_ratio >= 0.6))} of {other_ratio.size}" if other_ratio.size else "none"))
    for field in ("frames_only", "masks_only"):  # T/F:… entries (score)
        entries = [e for r in rows for e in str(r.get(field) or "").split()]
        if entries:
            lines.append(f"found on the {field.split('_')[0]} only: {sum(e.startswith('T') for e in entries)} at the true "
                         f"lesion, {sum(e.startswith('F') for e in entries)} elsewhere")
    sources = {}
    for r in found:
        sources[r["graded_on"]] = sources.get(r["graded_on"], 0) + 1
    g = col("ds_err_grade", sig)
    lines.append(f"graded as analysis.json reports (frames' density, else edges, else 3D; {sources}): %DS error "
                 f"50–70 % {ms(g)}, within 8 in {int(np.sum(np.abs(g) <= 8))} of {len(sig)}; MLD error "
                 f"{ms(col('mld_err_grade_mm', found))} mm; lesion length error {ms(col('len_err_grade_mm', found))} mm")
    return "\n".join(lines)


NUMERIC_MASK_OPTIONS = ("mask_edge_fraction", "mask_edge_grow_mm", "snr")
OPTIONAL_MASK_OPTIONS = ("mask_edge_max_radius_mm", "mask_edge_taper_radius_mm")  # these also take none


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", choices=("tubes", "trees", "recon"), default="tubes")
    ap.add_argument("--spacing", type=float, default=0.25, help="voxel size of the voxelised truth (mm)")
    ap.add_argument("--cases", type=int, default=4, help="recon suite: number of cases (at most 10)")
    ap.add_argument("--steps", type=int, default=None, help="recon suite: optimiser steps (default: the preset's)")
    ap.add_argument("--first", type=int, default=0, help="recon suite: index of the first case (0–9)")
    ap.add_argument("--save", help="recon suite: write each reconstruction's occupancy and final poses here")
    ap.add_argument("--load", help="recon suite: analyse the reconstructions --save wrote here (same --masks, --first, "
                                   "--max-foreshortening-pct) instead of reconstructing")
    ap.add_argument("--max-foreshortening-pct", type=float, default=None,
                    help="recon suite: draw each tube's axis until no view foreshortens it more (default: the first draw)")
    ap.add_argument("--elevation-deg", type=float, default=None,
                    help="recon suite: every tube's axis (cos e, 0, sin e) instead of its draw: e is its angle to LAO 30 / "
                         "RAO 30's epipolar planes near the isocentre (where two views place it in depth weakly when small)")
    ap.add_argument("--masks", choices=("clean", "segmented", "segmented-moving"), default="clean",
                    help="clean masks rendered from the tubes, or masks segmented from their simulated angiograms (then the "
                         "two-view widths and areas are also read from those angiograms: the 'frames' columns); "
                         "segmented-moving (recon suite): the same with the object moved up to 3 mm / 2° between the views")
    ap.add_argument("--mask-option", action="append", default=[], metavar="KEY=VALUE",
                    help="segmented masks: a realistic.RealisticOptions field other than the protocol's, repeatable "
                         "(e.g. mask_edge_fraction=0: the mask pipeline without its edge rule)")
    ap.add_argument("--grow", type=float, nargs="+", default=None,
                    help="recon suite: fit each case once and analyse it finished with each of these grow thresholds "
                         "(0 = the threshold alone; the fast preset grows into 0.3), side by side")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="recon suite: a setting of the reconstructions other than fast's, repeatable")
    ap.add_argument("--centreline", choices=("volume", "masks"), nargs="+", default=["volume"],
                    help="analyse with the volume's centreline, or re-placed on the masks' midlines "
                         "(analyse_volume's centreline_on_masks), or both side by side on the same volumes")
    ap.add_argument("--no-frames", action="store_true",
                    help="with --masks segmented: analyse on the masks alone, as analyse does without --frames")
    ap.add_argument("--display", action="store_true",
                    help="with --masks segmented*: the angiograms processed for display (DISP) before they are segmented "
                         "and read; the frames then give edges only, as analyse reads a DISP run")
    ap.add_argument("--no-masks-search", action="store_true",
                    help="without frames, do not search the masks for lesions the 3D sections missed (as before RESULTS §43)")
    ap.add_argument("--frames-max-over-3d", type=float, default=None, metavar="RATIO",
                    help="the analysis's FRAMES_MAX_OVER_3D (0: off): the frames' diameter left out where it exceeds "
                         "this × the 3D section's")
    ap.add_argument("--end-probe-radii", type=float, default=None, metavar="RADII",
                    help="the analysis's END_PROBE_RADII (0: off): a free end's extension reads the lumen across a "
                         "disk of this many vessel radii about its line (RESULTS §63c)")
    ap.add_argument("--psf-sigma-mm", default=None, metavar="MM|auto",
                    help="the detector blur the analysis's frame widths assume (default: analyse's — the "
                         f"simulation's {AngiogramSettings().psf_sigma_mm} mm on linear frames, estimated on --display "
                         "ones); auto: estimated from any frames, as analyse --psf-sigma-mm auto")
    ap.add_argument("--view-step-deg", type=float, default=2.0)
    ap.add_argument("--views", choices=VIEW_SETS, default=VIEW_SETS[0],
                    help="the acquisitions: two views, or a third at AP cranial 30 (masks, frames, motion and the "
                         "foreshortening error in every one of them)")
    ap.add_argument("--csv", help="write the case rows here")
    args = ap.parse_args(argv)
    if args.grow and (args.suite != "recon" or args.save or args.load):
        ap.error("--grow compares finishing rules of fresh reconstructions: it needs --suite recon, without --save or --load")
    if args.set and (args.suite != "recon" or args.load):
        ap.error("--set changes the reconstructions' settings: it needs --suite recon, without --load")
    if args.masks == "segmented-moving" and args.suite != "recon":
        ap.error("--masks segmented-moving needs --suite recon (a motion between the views matters to a reconstruction)")
    CENTRELINES[:] = args.centreline
    VIEWS[:] = standard_geometry(args.views).views
    if args.views != VIEW_SETS[0]:
        print(f"# views {args.views}", flush=True)
    for item in args.mask_option:
        key, _, text = (part.strip() for part in item.partition("="))
        no_limit = key in OPTIONAL_MASK_OPTIONS and text.lower() == "none"
        try:
            value = None if no_limit else float(text)
        except ValueError:
            value = key = ""
        if args.masks == "clean" or key not in NUMERIC_MASK_OPTIONS + OPTIONAL_MASK_OPTIONS:
            ap.error(f"--mask-option {item!r}: give {', '.join(NUMERIC_MASK_OPTIONS + OPTIONAL_MASK_OPTIONS)}=NUMBER "
                     f"({' or '.join(OPTIONAL_MASK_OPTIONS)}=none: no radius limit / no taper), with segmented masks")
        MASK_OPTIONS[key] = value
    if MASK_OPTIONS:
        print(f"# segmented masks with {MASK_OPTIONS}", flush=True)
    if args.display and args.masks == "clean":
        ap.error("--display processes the simulated angiograms: it needs --masks segmented or segmented-moving")
    global ANALYSE_WITHOUT_FRAMES, SEARCH_MASKS, DISPLAY_FRAMES, ELEVATION_DEG
    ANALYSE_WITHOUT_FRAMES, SEARCH_MASKS, DISPLAY_FRAMES = args.no_frames, not args.no_masks_search, args.display
    ELEVATION_DEG = args.elevation_deg
    if ELEVATION_DEG is not None:
        if args.suite != "recon" or args.max_foreshortening_pct is not None:
            ap.error("--elevation-deg sets the recon suite's tube axes: it needs --suite recon and no --max-foreshortening-pct")
        print(f"# every tube's axis at {ELEVATION_DEG:g}° elevation, (cos e, 0, sin e)", flush=True)
    if DISPLAY_FRAMES:
        print("# frames processed for display (DISP): masks segmented on them, edges only", flush=True)
    if args.psf_sigma_mm is not None:
        try:
            PSF_SIGMA_MM[0] = None if args.psf_sigma_mm.lower() == "auto" else float(args.psf_sigma_mm)
        except ValueError:
            ap.error(f"--psf-sigma-mm {args.psf_sigma_mm!r}: give a blur in mm (0 or more) or auto")
        print(f"# psf_sigma_mm {PSF_SIGMA_MM[0] if PSF_SIGMA_MM[0] is not None else 'auto'}", flush=True)
    if args.end_probe_radii is not None:
        from SDFCARLib.analysis import centreline

        centreline.END_PROBE_RADII = args.end_probe_radii
        print(f"# END_PROBE_RADII {centreline.END_PROBE_RADII}", flush=True)
    if args.frames_max_over_3d is not None:
        import SDFCARLib.analysis.pipeline as pipeline
        pipeline.FRAMES_MAX_OVER_3D = args.frames_max_over_3d or None
        print(f"# FRAMES_MAX_OVER_3D {pipeline.FRAMES_MAX_OVER_3D}", flush=True)
    t0 = time.perf_counter()
    if args.suite == "tubes":
        rows = run_truth(tube_cases(), args.spacing, args.view_step_deg, args.masks)
    elif args.suite == "trees":
        rows = run_truth(tree_cases(), args.spacing, args.view_step_deg, args.masks)
    else:
        rows = run_recon(args.cases, args.view_step_deg, args.steps, args.save, args.first, args.masks,
                         args.max_foreshortening_pct, args.load, args.grow, parse_setting_overrides(args.set))
    print()
    for centreline in CENTRELINES:
        chosen = [r for r in rows if r.get("centreline", centreline) == centreline]
        if len(CENTRELINES) > 1:
            print(f"# centreline: {centreline}\n")
        if args.grow:
            for grow in args.grow:
                print(f"## grow_threshold {grow:g}\n")
                # a case whose masks could not be made has one row, without a rule: it counts under every rule
                print(summarise([r for r in chosen if r.get("grow_threshold", grow) == grow]) + "\n")
        else:
            print(summarise(chosen) + "\n")
    print(f"\n{len(rows)} cases in {time.perf_counter() - t0:.0f} s")
    if args.csv:
        keys = sorted({k for r in rows for k in r}, key=lambda k: (k != "case", k))
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, keys)
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
