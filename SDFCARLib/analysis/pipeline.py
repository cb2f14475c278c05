"""The whole 3D-QCA of one vessel volume: centrelines → diameters → lesions → angles → best view.

``analyse_volume`` runs every measure of the package on a volume (occupancy, probability or
label on its grid) and, when given, the acquisition views and their masks; ``summary`` turns the
result into the JSON-ready dictionary written as analysis.json.

Resolution
    A narrowing is reported as a lesion only when its reference diameter and its length both span
    ``RESOLVABLE_VOXELS`` voxels of the grid; the others are counted per branch
    (``narrowings_below_resolution``). A lesion whose minimal lumen on the 3D sections spans fewer
    (``mld_below_resolution``) is reported, but where it is graded on those sections a warning
    names it: the reconstruction's walls sit a fraction of a voxel off, a large share of so thin a
    throat, and its %DS with them (RESULTS §28b: +12.5 points on a 0.75 mm throat at 0.4 mm).

Side strands (``strands_within_parents``)
    A rough reconstruction (masks segmented from images) thins into a main path plus strands that
    run beside it inside its own lumen; each strand makes a junction zone on the main branch, which
    then leaves most of its sections out of the reference and misses its lesions (RESULTS §22).
    A side branch that stays within ``STRAND_MAX_REACH_DIAMETERS`` of its parent's median diameter
    from the parent's centreline and runs along it (mean |cos| of the angle between their tangents
    above ``STRAND_MIN_ALIGNMENT``) is such a strand: it is dropped from the analysed tree with
    everything below it (a real side branch leaves its parent). ``settings["strands_dropped"]``.

Broken reconstructions (``fragments``)
    Only the pieces of the lumen above ``fragments.MIN_COMPONENT_SHARE`` of the main tree are
    analysed. A lesion on a piece cut off from the main tree, beside another piece, or on a gap
    that reconnection bridged is flagged "unreliable: the reconstruction is broken here" and kept
    apart (``BranchProfile.unreliable``, analysis.json ``unreliable_lesions``) with its reasons; it
    is not the target of the best-view map.

Grade of a lesion (``lesion_grade``)
    Lesions are found on the 3D sections: they say where a lesion is on the tree. Where the frames
    are given, each lesion is graded on them, as 2D-QCA grades on its edges: the same lesion on the
    frames' density profile, else on their fitted edges, else (frames that show no narrowing there,
    or none given) on the 3D sections. The frames are far sharper than a reconstruction from
    segmented masks (RESULTS §21–22); a lesion the 3D sections find but the frames do not show is
    reported with ``seen_on_frames`` false and a warning. With masks, ``seen_on_masks`` says whether
    their widths (the two-view diameter or either view's) narrow there too; without frames, a lesion
    no mask shows gets the same warning: a rough reconstruction's bumps read as stenoses (README's
    sample case), and the masks are then the only images to check it on.

Lesions of the frames (``frames_lesions``)
    Where the frames are given they are searched too (density, else edges): a lesion they show that is
    none of the 3D sections' (``lesion.is_same_lesion``) is reported with ``found_on`` "frames" and a
    warning, its 3D measures being the sections' over the frames' extent: a 1.5 mm vessel reconstructed
    from segmented masks reads 0.7 mm too wide and its 50 % lesion below what the grid resolves, which
    the frames show (RESULTS §38b, §43). Several 3D lesions graded as the same lesion of the frames
    (bumps of a rough reconstruction along one long lesion) are reported once, as the one that narrows
    most in 3D. A lesion of the frames alone is reported only where the 3D sections, their free-end caps
    left out, narrow over its extent by ``FRAMES_LESION_MIN_3D_SHARE`` of ``min_stenosis_pct``: the
    reconstruction is fitted to the same views and smooths a true lesion under the threshold without
    erasing it, while where a branch crosses or runs beside another the frames' profile narrows alone
    (RESULTS §45); and where it is at least ``LESION_2D_MIN_LENGTH_DIAMETERS`` reference diameters long,
    as on the masks: at a branch's root its parent's lumen narrows the frames' profile over a millimetre
    or two; and where at its throat another vessel does not lie in every view's window (below): there
    no view measures it (RESULTS §47). The others are counted per branch (``narrowings_2d_unconfirmed``,
    with the masks' unconfirmed narrowings where no frames are given).

The frames' measures beside other vessels
    A view's density reads another vessel's iodine where that vessel's projection comes into the window
    across the measured one (in its integral, or in the background fitted beside it): on the exact trees
    with segmented masks a view's density erred by 0.28–0.53 mm (median) there and 0.05–0.09 mm
    elsewhere (RESULTS §47). The tree itself says where: another branch's projected edge nearer than
    the window's half width less its outermost millimetre (``views.other_vessel_clearance``) crowds
    that view at that point (``BranchProfile.frame_views_crowded``). The density is then the median area
    of the views no other vessel crowds, or of all where every view is crowded (leaving those points
    out lengthened lesions by up to 13 mm, §47); each view's attenuation is calibrated on its
    uncrowded healthy points only. The edges' diameter leaves a crowded view's width out the same way
    (§47b). The profile CSV names the views each point's density comes from (``density_views``) and
    the crowded ones (``crowded_views``). A side branch's own first millimetres touch the vessel in 3D
    and are not "other" vessels, yet where they run back beside it they lie in every view's window:
    there the frames read the lumen wider than the 3D sections do. ``FRAMES_MAX_OVER_3D`` (off) leaves
    both frames' diameters out (unmeasured: a lesion's flanks are walked across the gap) where they
    exceed that many times the 3D section's: it mends such a lesion's length on the exact trees, but on
    reconstructions the sections read thin in places and it takes healthy frames out there (RESULTS §54b).

Lesions of the masks (``masks_lesions``)
    Where no frames are given, the masks' two-view diameter is searched the same way, and a lesion it
    shows that the 3D sections did not report is reported with ``found_on`` "masks", graded on that
    diameter (``GRADED_ON_MASKS``), with a warning. A thin vessel's 3D reference can fall below what
    the grid resolves, so its narrowing is not reported from the sections although they show it (the
    1.5 mm tube's 50 % lesion from segmented masks, RESULTS §43). Three conditions keep the masks' own
    artefacts out (where a branch overlaps another or a ghost spur lies inside its parent's shadow the
    widths narrow too): the 3D sections narrow over the same extent by ``min_stenosis_pct`` as well;
    the masks narrow by at least ``MASKS_LESION_MIN_SCATTERS`` times their own scatter about the
    reference on that branch (``lesion.relative_scatter``; the reference fit's own outlier rule); and
    the narrowing is at least ``LESION_2D_MIN_LENGTH_DIAMETERS`` reference diameters long.

Target segment of the best-view map
    The worst lesion (highest graded %DS over all branches) padded by ``TARGET_PAD_MM`` of reference
    vessel on each side, as a clinician frames a lesion; without a lesion, the first
    ``TARGET_DEFAULT_MM`` of the main branch after the ostium. Or the segment a user marks by two
    points (``segment_between``): the stretch of the one branch whose centreline passes within
    ``MARK_MAX_DISTANCE_MM`` of both, between the centreline points nearest to them; its 3D length is
    what a validation against marked phantom lengths measures (between two landmarks the length is
    within 2 % where the whole tube's, with its free ends, is not: RESULTS §40a).

Depth from two views (``views.epipolar_angles_deg``)
    Every branch's angle to the acquired views' epipolar planes (analysis.json per branch and for the
    target, the profiles' ``epipolar_angle_deg``). Where the target segment runs along those planes (median
    under ``views.EPIPOLAR_WEAK_DEG``) a warning says its depth, and so its 3D length and foreshortening, rest
    on little, and names the third view that would cross it (``views.depth_view``): on realistic two-view
    reconstructions the centreline lies about twice as far off under 10° as over 45° (RESULTS §102a).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Union

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import CArmView, VolumeGrid
from ..lumen_profile import PSF_BY_FRAMES
from ..masks import binarise_mask
from .centreline import CentrelineBranch, CentrelineTree, bifurcation_angles, extract_centrelines, fill_lumen_cavities
from .diameter import (CrossSections, branch_cross_sections, ellipse_diameter, junction_zones, mask_diameters,
                       views_to_use)
from .frame_contrast import check_vessels_dark, frame_contrast_warning
from .frame_density import attenuation_per_mm, densities, density_diameter, density_views
from .frame_widths import DEFAULT_PSF_SIGMA_MM, estimate_psf_sigma_mm, frame_widths
from .fragments import MIN_COMPONENT_SHARE, UNRELIABLE, Fragments, find_fragments, lesion_reasons
from .lesion import (Lesion, ReferenceFit, find_lesions, is_same_lesion, lesion_within, minimal_lumen, reference_fit,
                     relative_scatter, same_lesion_on)
from .mask_centreline import place_on_masks
from .mask_order import MIN_SHARE_ON_MASK, better_order, mask_order_warning, shares_on_masks
from .root_check import narrow_root, narrow_root_warning, through_vessel_root, through_vessel_root_warning
from .section_centreline import centre_on_sections as centre_on_sections_of
from .views import (EPIPOLAR_WEAK_DEG, ViewMap, chord_tangents, depth_view, epipolar_angles_deg, foreshortening,
                    other_vessel_clearance, overlap_fraction, view_label, view_map)

TARGET_PAD_MM = 2.5
MARK_MAX_DISTANCE_MM = 5.0  # a marked point farther than this from a branch's centreline is not on it
TARGET_DEFAULT_MM = 20.0
OTHERS_STEP_MM = 1.0  # tree samples kept for the overlap test: finer adds time, not accuracy
RESOLVABLE_VOXELS = 2.5  # a lesion's reference diameter and length must span this many voxels
STRAND_MAX_REACH_DIAMETERS = 1.0  # a strand stays this close to its parent's centreline (× parent diameter)
STRAND_MIN_ALIGNMENT = 0.75  # … and runs along it: mean |cos| between the two tangents
FRAMES_LESION_MIN_3D_SHARE = 0.5  # a lesion found on the frames only narrows the 3D sections by this share of the threshold
MASKS_LESION_MIN_SCATTERS = 2.5  # a lesion found on the masks only narrows them by this many times their scatter
LESION_2D_MIN_LENGTH_DIAMETERS = 1.0  # a lesion found on the frames or masks only is this long (× its reference diameter)
FRAMES_MAX_OVER_3D: Optional[float] = None  # off; e.g. 1.4: a frames' diameter above this × the 3D section's is left out (RESULTS §54b)


@dataclass
class UnreliableLesion:
    """A lesion measured where the reconstruction is broken, and why (``fragments.lesion_reasons``)."""

    lesion: Lesion
    reasons: List[str]


@dataclass
class BranchProfile:
    branch: CentrelineBranch
    sections: CrossSections
    excluded: np.ndarray  # bool: junction or end zone (not used for the reference)
    mask_diameter_mm: Optional[np.ndarray] = None
    view_widths_mm: Optional[np.ndarray] = None  # (views, N)
    frame_diameter_mm: Optional[np.ndarray] = None  # from the frames' intensity profiles (frame_widths.py)
    frame_view_widths_mm: Optional[np.ndarray] = None  # (views, N)
    frame_density_diameter_mm: Optional[np.ndarray] = None  # lumen area from the frames' absorbance (frame_density.py)
    frame_views_crowded: Optional[np.ndarray] = None  # (views, N) bool: another branch in the view's window there
    frame_density_views: Optional[np.ndarray] = None  # (views, N) bool: the views whose median area the density takes there
    # the centreline the 2D widths are measured across: the volume's (through the lumen, lesions too),
    # where ``branch`` was re-placed on the masks' midlines; the same points, one for one
    width_branch: Optional[CentrelineBranch] = None
    reference: Optional[ReferenceFit] = None
    lesions: List[Lesion] = field(default_factory=list)  # reliable: measured on an intact vessel
    frames_only: List[Lesion] = field(default_factory=list)  # of lesions/unreliable: found on the frames, not in 3D
    masks_only: List[Lesion] = field(default_factory=list)  # … without frames: found on the masks, not in 3D
    unreliable: List[UnreliableLesion] = field(default_factory=list)
    unresolved: int = 0  # narrowings found but below the grid's resolution (not reported as lesions)
    unconfirmed: int = 0  # narrowings of the frames' (without frames, the masks') profile not reported: unconfirmed in 3D
    warning: str = ""

    def __post_init__(self) -> None:
        if self.width_branch is None:
            self.width_branch = self.branch

    @property
    def diameter_mm(self) -> np.ndarray:
        return self.sections.equivalent_diameter_mm


@dataclass
class QCAResult:
    tree: CentrelineTree
    profiles: List[BranchProfile]
    bifurcations: List[Dict[str, Any]]
    views: Sequence[CArmView]
    view_foreshortening: Dict[int, List[float]]  # branch id → per acquisition view
    target: Dict[str, Any]
    view_map: Optional[ViewMap]
    settings: Dict[str, Any]
    fragments: Optional[Fragments] = None
    # branch id → per centreline point, the angle to the acquired views' epipolar planes (views.py); empty under 2 views
    epipolar_deg: Dict[int, np.ndarray] = field(default_factory=dict)

    def profile(self, branch_id: int) -> BranchProfile:
        for p in self.profiles:
            if p.branch.branch_id == branch_id:
                return p
        raise KeyError(branch_id)


def _segment(branch: CentrelineBranch, start_mm: float, end_mm: float) -> np.ndarray:
    s = branch.arc_length_mm
    keep = (s >= start_mm) & (s <= end_mm)
    return np.flatnonzero(keep)


def _choose_target(profiles: List[BranchProfile], min_stenosis_pct: float) -> Dict[str, Any]:
    worst = None
    for p in profiles:
        for lesion in p.lesions:
            graded = lesion_grade(p, lesion, min_stenosis_pct).measure.diameter_stenosis_pct
            if worst is None or graded > worst[2]:
                worst = (p, lesion, graded)
    if worst is not None:
        p, lesion, _ = worst
        return {"branch_id": p.branch.branch_id, "kind": "worst lesion",
                "start_mm": max(0.0, lesion.start_mm - TARGET_PAD_MM),
                "end_mm": min(p.branch.length_mm, lesion.end_mm + TARGET_PAD_MM)}
    main = profiles[0]
    s = main.branch.arc_length_mm
    first = float(s[np.argmax(~main.excluded)]) if (~main.excluded).any() else 0.0
    return {"branch_id": main.branch.branch_id, "kind": "proximal main branch (no lesion)",
            "start_mm": first, "end_mm": min(main.branch.length_mm, first + TARGET_DEFAULT_MM)}


OSTIUM_MAX_DISTANCE_MM = 10.0  # a given ostium this far from every lumen voxel is a mistake (RAS for LPS, a typo)
# a given ostium where the tree is under this share of its thickest end's width, that end farther than
# OSTIUM_THIN_MIN_DISTANCE_MM away, is warned of: the tree is ordered from it (a distal tip orders it backwards)
OSTIUM_THIN_SHARE = 0.6
OSTIUM_THIN_MIN_DISTANCE_MM = 6.0


def check_ostium(lumen: np.ndarray, grid: VolumeGrid, ostium_mm: Optional[Sequence[float]]) -> None:
    """ValueError naming the distance where a given ostium lies farther than ``OSTIUM_MAX_DISTANCE_MM`` from the
    lumen: the tree would be ordered from whatever end lies nearest it."""
    if ostium_mm is None:
        return
    point = np.asarray(ostium_mm, float)
    if point.shape != (3,) or not np.isfinite(point).all():
        raise ValueError(f"the ostium is one point of three finite coordinates (LPS mm), got {np.asarray(ostium_mm).tolist()}")
    voxels = np.argwhere(lumen)
    if not len(voxels):
        return  # nothing to order; the empty result is reported as such
    distance = float(np.linalg.norm(grid.index_to_world(voxels) - point, axis=1).min())
    if distance > OSTIUM_MAX_DISTANCE_MM:
        raise ValueError(f"the ostium given, ({', '.join(f'{v:.1f}' for v in point)}) LPS mm, is {distance:.1f} mm from "
                         f"the nearest voxel of the vessel tree; give a point within {OSTIUM_MAX_DISTANCE_MM:g} mm of the "
                         "tree's root end in LPS (Slicer shows RAS: negate x and y), or leave the ostium out to start "
                         "from the thickest end")


class SegmentError(ValueError):
    """Two marked points that mark no segment of the tree (the message says why and what to do)."""


def segment_between(tree: CentrelineTree, first_mm: Sequence[float], second_mm: Sequence[float],
                    max_distance_mm: float = MARK_MAX_DISTANCE_MM) -> Dict[str, Any]:
    """The target segment between two marked points, LPS mm (module docstring); SegmentError naming what is
    wrong where no branch passes near both or they mark one place."""
    marks = np.asarray([first_mm, second_mm], float)
    if marks.shape != (2, 3) or not np.isfinite(marks).all():
        raise SegmentError(f"a segment is marked by two points of three finite coordinates (LPS mm), got {marks.tolist()}")
    reach = {}  # branch id → (each mark's distance to the branch's centreline, the index of its nearest point)
    for b in tree.branches:
        if len(b.points_mm) >= 2:
            distances = np.linalg.norm(b.points_mm[None, :, :] - marks[:, None, :], axis=2)  # (2 marks, points)
            index = distances.argmin(axis=1)
            reach[b.branch_id] = (distances[[0, 1], index], index)
    if not reach:
        raise SegmentError("the reconstruction has no centreline to mark a segment on")
    branch_id = min(reach, key=lambda k: reach[k][0].max())
    distances, index = reach[branch_id]
    if distances.max() > max_distance_mm:
        near = [min(reach, key=lambda k: reach[k][0][m]) for m in range(2)]  # each mark's nearest branch
        if all(reach[near[m]][0][m] <= max_distance_mm for m in range(2)):
            raise SegmentError(f"the two marked points lie on different branches ({near[0]} and {near[1]}): mark both "
                               "points on one branch (a branch runs from its junction, or the ostium, to its end)")
        far = [f"point {m + 1} is {reach[near[m]][0][m]:.1f} mm from the nearest centreline (branch {near[m]})"
               for m in range(2) if reach[near[m]][0][m] > max_distance_mm]
        raise SegmentError("; ".join(far) + f": mark points on the vessel, within {max_distance_mm:g} mm of its centreline")
    branch = tree.branch(branch_id)
    start_mm, end_mm = sorted(float(x) for x in branch.arc_length_mm[index])
    if end_mm - start_mm < 2 * float(np.median(np.diff(branch.arc_length_mm))):
        raise SegmentError(f"the two marked points fall on one place of branch {branch_id} ({start_mm:.1f} mm along it): "
                           "mark the segment's two ends")
    return {"branch_id": branch_id, "kind": "marked", "start_mm": start_mm, "end_mm": end_mm,
            "marked_mm": marks.tolist(), "marks_from_centreline_mm": [float(d) for d in distances]}


def analyse_volume(volume: np.ndarray, grid: VolumeGrid, level: float = 0.5, views: Sequence[CArmView] = (),
                   masks: Optional[Sequence[np.ndarray]] = None, ostium_mm: Optional[Sequence[float]] = None,
                   min_branch_mm: float = 3.0, min_stenosis_pct: float = 20.0, view_step_deg: float = 2.0,
                   target: Optional[Dict[str, Any]] = None, best_view: bool = True,
                   min_component_share: float = MIN_COMPONENT_SHARE,
                   bridges: Sequence[Dict[str, Any]] = (), frames: Optional[Sequence[np.ndarray]] = None,
                   psf_sigma_mm: Union[float, None, str] = PSF_BY_FRAMES,
                   centreline_on_masks: Optional[bool] = None,
                   segment_mm: Optional[Sequence[Sequence[float]]] = None, search_masks: bool = True,
                   centre_on_sections: bool = True, densitometry: Union[bool, Sequence[bool]] = True) -> QCAResult:
    """Every QCA measure of a vessel volume (module docstring); ``target`` overrides the chosen segment,
    as do two marked points ``segment_mm`` (LPS mm, ``segment_between``: SegmentError where they mark none).

    ``bridges``: the gaps reconnection filled (report.json ``reconnection.bridges``), LPS mm.
    ``frames`` (with ``masks``): the views' intensity images; the widths are then also fitted to
    their profiles (``frame_widths.py``, detector blur ``psf_sigma_mm``; None: estimated per view
    from the frames, the default where too few profiles allow it; ``PSF_BY_FRAMES``: ``DEFAULT_PSF_SIGMA_MM``
    on frames that keep the intensity, estimated on frames processed for display, ``densitometry`` False, whose
    sharpening is no detector blur — bench/RESULTS.md §80b), starting from the masks'.
    ``densitometry`` False: the frames were processed for display (or are LOG as stored), their widths are fitted
    on the grey level as a logarithm of the intensity and no lumen area is read from their absorbance
    (``evidence.unreadable_intensity``, ``frame_widths.profile_values``); one bool per view: so for those views
    only, the others read as they are (a LIN run beside a DISP one keeps its densitometry).
    ``centreline_on_masks``: the centreline is re-placed on the masks' midlines (``mask_centreline.py``)
    for the lengths, positions, angles, foreshortening and views, while the 3D sections and the 2D
    widths stay on the volume's own centreline (through the lumen, lesions too); None: where masks of
    two views or more are given (the lumen of a fit to segmented masks wanders about the axis: the
    comparison is in bench/RESULTS.md §35). ``centre_on_sections``: the volume's centreline is first moved onto
    its cross-sections' centroids (``section_centreline.py``: the smoothing cuts every bend; §72).
    ``search_masks``: without frames, the masks' two-view diameter is
    also searched for lesions the 3D sections missed (module docstring, "Lesions of the masks").
    """
    if frames is not None and (masks is None or len(frames) != len(views)):
        raise ValueError(f"{len(frames)} frames for {len(views)} views and {'no' if masks is None else len(masks)} masks: "
                         "frame widths need one frame and one mask per view, in the views' order")
    per_view_densitometry = ([bool(densitometry)] * len(views) if np.ndim(densitometry) == 0
                             else [bool(d) for d in densitometry])
    if frames is not None and len(per_view_densitometry) != len(views):
        raise ValueError(f"densitometry is one bool, or one per view: got {len(per_view_densitometry)} for {len(views)} views")
    if not 0.0 < float(min_stenosis_pct) < 100.0:  # NaN too: it would find lesions nowhere and store null
        raise ValueError(f"min_stenosis_pct is the least diameter stenosis reported as a lesion, a percentage above 0 and "
                         f"below 100 (default 20), got {min_stenosis_pct}")
    if masks is not None:
        if len(masks) != len(views):
            raise ValueError(f"{len(masks)} masks for {len(views)} views: the masks' diameters need the views they were "
                             "drawn in, one mask per view in the views' order (give views=)")
        # one reading of a mask everywhere (0/255 as 0/1: the edges are found at half the mask's value)
        masks = [binarise_mask(m, view.detector_shape, source=f"mask of view {n}")
                 for n, (m, view) in enumerate(zip(masks, views), start=1)]
    frame_contrasts = None
    if frames is not None:  # a frame with the vessels bright is refused before any work
        frame_contrasts = check_vessels_dark(frames, masks)
    volume = np.asarray(volume)
    if volume.shape != tuple(grid.shape):
        raise ValueError(f"the volume has shape {volume.shape} and its grid {tuple(grid.shape)}: give the grid the "
                         f"volume was reconstructed on")
    if volume.dtype != bool and not np.isfinite(volume).all():  # NaN is no lumen yet its sections read it: a broken tree
        raise ValueError(f"the volume holds {int((~np.isfinite(volume)).sum())} NaN or infinite values: give an occupancy "
                         f"(0 to 1) or a label volume, as reconstruct writes it")
    volume, cavities_filled = fill_lumen_cavities(volume, level)  # for the sections too, not only the skeleton
    lumen = volume if volume.dtype == bool else volume >= level
    check_ostium(lumen, grid, ostium_mm)
    fragments = find_fragments(lumen, grid, min_component_share, ostium_mm)
    pieces = volume
    if not fragments.analysed.all():
        # Pieces too small to analyse give no centrelines; the sections still read the whole volume,
        # whose values near a wall the trilinear interpolation needs.
        pieces = volume.copy()
        pieces[~fragments.analysed_mask()] = 0
    tree = extract_centrelines(pieces, grid, level=level, ostium_mm=ostium_mm, min_branch_mm=min_branch_mm)
    given_root = tree.given_root
    fvol = np.asarray(volume, np.float32)
    # Sections of the parents first, for the strand test; the strands dropped need none (a rough
    # reconstruction has most of its branches among them).
    parent_ids = {b.parent_id for b in tree.branches if b.parent_id is not None}
    known = {b.branch_id: branch_cross_sections(fvol, grid, b, level) for b in tree.branches if b.branch_id in parent_ids}
    strands = strands_within_parents(tree, {k: _median_diameter(v.equivalent_diameter_mm) for k, v in known.items()})
    if strands:
        tree = CentrelineTree([b for b in tree.branches if b.branch_id not in strands])
    sections_of = {b.branch_id: known[b.branch_id] if b.branch_id in known else branch_cross_sections(fvol, grid, b, level)
                   for b in tree.branches}
    section_placement = None
    if centre_on_sections:
        tree, section_placement = centre_on_sections_of(tree, sections_of)
    volume_tree, placement = tree, None
    mask_shares = order = None
    if masks is not None and len(views):  # before anything is read on the masks: do they belong to these views?
        points = np.concatenate([b.points_mm for b in tree.branches])
        shares = shares_on_masks(points, masks, views)
        mask_shares = [shares[n][n] for n in range(len(views))]
        if any(x is not None and x < MIN_SHARE_ON_MASK for x in mask_shares):
            order = better_order(shares)
    if centreline_on_masks is None:
        centreline_on_masks = masks is not None and len(views) >= 2
    if centreline_on_masks:
        if masks is None or len(views) < 2:
            raise ValueError("centreline_on_masks needs the masks of two views or more: give masks and views, "
                             "or leave centreline_on_masks off")
        tree, placement = place_on_masks(tree, masks, views)
    if segment_mm is not None:  # the tree is final: marks that mark no segment are refused before the frames' fit
        target = segment_between(tree, *segment_mm)
    profiles: List[BranchProfile] = []
    voxel = float(max(grid.spacing_mm))
    for branch in tree.branches:
        sections = sections_of[branch.branch_id]
        excluded = junction_zones(tree, branch)
        prof = BranchProfile(branch, sections, excluded, width_branch=volume_tree.branch(branch.branch_id))
        if masks is not None and len(views):
            md = mask_diameters(prof.width_branch.points_mm, prof.width_branch.tangents(), masks, views)
            prof.mask_diameter_mm, prof.view_widths_mm = md["equivalent_diameter_mm"], md["view_widths_mm"]
        s = branch.arc_length_mm
        try:
            prof.reference = reference_fit(s, sections.equivalent_diameter_mm, ~excluded)
            searchable = np.isfinite(sections.equivalent_diameter_mm) & ~_end_caps(branch)
            found = find_lesions(s, sections.equivalent_diameter_mm, prof.reference, searchable,
                                 sections.area_mm2, min_stenosis_pct=min_stenosis_pct)
            # Below RESOLVABLE_VOXELS voxels across (or along) a narrowing is voxel noise, not a lesion:
            # on the 0.8 mm sample grid, 1 mm branches showed 30–40 % "lesions" 1 mm long.
            resolved = [x for x in found if x.reference_diameter_mm >= RESOLVABLE_VOXELS * voxel
                        and x.length_mm >= RESOLVABLE_VOXELS * voxel]
            prof.unresolved = len(found) - len(resolved)
            for lesion in resolved:
                reasons = lesion_reasons(branch, lesion.start_mm, lesion.end_mm, prof.reference(s) / 2, fragments, bridges)
                if reasons:
                    prof.unreliable.append(UnreliableLesion(lesion, reasons))
                else:
                    prof.lesions.append(lesion)
        except ValueError as exc:
            prof.warning = str(exc)
        profiles.append(prof)
    fore = {b.branch_id: [foreshortening(b.points_mm, v) for v in views] for b in tree.branches if len(b.points_mm) > 1}
    epipolar = ({b.branch_id: epipolar_angles_deg(b.points_mm, chord_tangents(b.points_mm), [v.source_position for v in views])
                 for b in tree.branches} if len(views) >= 2 else {})
    blur: Dict[str, Any] = {}
    if frames is not None and profiles:  # before the target: the worst lesion is the worst graded one
        blur = _fit_frame_widths(profiles, frames, views, psf_sigma_mm, per_view_densitometry)
        for prof in profiles:
            frames_lesions(prof, min_stenosis_pct, fragments, bridges)
    elif search_masks:
        for prof in profiles:
            masks_lesions(prof, min_stenosis_pct, fragments, bridges)
    target = dict(target) if target else _choose_target(profiles, min_stenosis_pct)
    vm = None
    target_branch = tree.branch(int(target["branch_id"]))
    idx = _segment(target_branch, float(target["start_mm"]), float(target["end_mm"]))
    if len(idx) >= 2:
        seg = target_branch.points_mm[idx]
        seg_r = _radii(profiles, target_branch.branch_id)[idx]
        others, others_r = _others(tree, profiles, target_branch.branch_id, idx)
        target["length_mm"] = float(np.sum(np.linalg.norm(np.diff(seg, axis=0), axis=1)))
        target["acquisition_views"] = [
            {"label": view_label(v.primary_deg, v.secondary_deg), "primary_deg": v.primary_deg,
             "secondary_deg": v.secondary_deg, "foreshortening": foreshortening(seg, v),
             "overlap": overlap_fraction(seg, seg_r, others, others_r, v.primary_deg, v.secondary_deg)} for v in views]
        if epipolar:
            target["epipolar_angle_deg"] = epipolar_stats(epipolar[target_branch.branch_id][idx])
            if (target["epipolar_angle_deg"] or {}).get("median_deg", 90.0) < EPIPOLAR_WEAK_DEG:
                target["depth_view"] = depth_view(seg, views, step_deg=view_step_deg)
        if best_view:
            vm = view_map(seg, seg_r, others, others_r, step_deg=view_step_deg)
    # with no ostium given the root is the thickest end, which a guiding catheter or a blob on a vessel's side
    # can be (root_check.py)
    main_profile = next((p for p in profiles if p.branch.branch_id == 0), None)
    root_found = None
    through_root = through_vessel_root(tree) if ostium_mm is None else None
    if ostium_mm is None and main_profile is not None:
        root_found = narrow_root(main_profile.branch.arc_length_mm, main_profile.sections.equivalent_diameter_mm)
        if root_found:
            root_found["root_mm"] = [float(v) for v in main_profile.branch.points_mm[0]]
    settings = {"level": level, "min_branch_mm": min_branch_mm, "min_stenosis_pct": min_stenosis_pct, **blur,
                **({} if frame_contrasts is None else {"frame_vessel_contrast": frame_contrasts}),
                "view_step_deg": view_step_deg, "ostium_mm": None if ostium_mm is None else list(map(float, ostium_mm)),
                "min_component_share": min_component_share, "bridges_checked": len(bridges),
                "strands_dropped": len(strands), "given_root": given_root, "narrow_root": root_found,
                "through_vessel_root": through_root, "voxel_mm": voxel,
                "lumen_cavities_filled": cavities_filled,
                "centreline_share_on_masks": mask_shares, "masks_better_order": order, "centreline_on_masks": centreline_on_masks,
                "centreline_placement": None if placement is None else [p.to_dict() for p in placement],
                "centred_on_sections": None if section_placement is None else [p.to_dict() for p in section_placement]}
    return QCAResult(tree, profiles, bifurcation_angles(tree), list(views), fore, target, vm, settings, fragments,
                     epipolar_deg=epipolar)


def epipolar_stats(angles_deg: np.ndarray) -> Optional[Dict[str, float]]:
    """Median, least and the share under ``EPIPOLAR_WEAK_DEG`` of a stretch's epipolar angles; None where none is known."""
    known = np.asarray(angles_deg, float)
    known = known[np.isfinite(known)]
    if not len(known):
        return None
    return {"median_deg": float(np.median(known)), "min_deg": float(known.min()),
            "share_under_weak": float(np.mean(known < EPIPOLAR_WEAK_DEG)), "weak_below_deg": EPIPOLAR_WEAK_DEG}


def _depth_warning(target: Dict[str, Any]) -> Optional[str]:
    angles = target.get("epipolar_angle_deg") or {}
    if angles.get("median_deg", 90.0) >= EPIPOLAR_WEAK_DEG:
        return None
    median = angles["median_deg"]
    gain = 1.0 / max(math.sin(math.radians(median)), 1e-3)
    text = (f"the target segment (branch {target['branch_id']}, {target['start_mm']:.1f}–{target['end_mm']:.1f} mm) runs at "
            f"{median:.0f}° (median) to the acquired views' epipolar planes, under {EPIPOLAR_WEAK_DEG:g}°: two views place it "
            f"in depth only weakly there (a mask's sideways error moves it about {gain:.0f}× as far in depth), so its 3D "
            f"course, length and foreshortening are less certain than where vessels cross those planes.")
    third = target.get("depth_view")
    if third:
        text += (f" A third view at {third['label']} would cross it at {third['epipolar_angle_median_deg']:.0f}° "
                 f"(foreshortening there {100 * third['foreshortening']:.1f}%).")
    return text


def _frames_profile(p: BranchProfile) -> Optional[np.ndarray]:
    """The frames' profile lesions are searched on: the density's, else the edges' (as they are graded)."""
    for values in (p.frame_density_diameter_mm, p.frame_diameter_mm):
        if values is not None and np.isfinite(values).sum() >= 3:
            return values
    return None


def frames_lesions(p: BranchProfile, min_stenosis_pct: float, fragments: Optional[Fragments] = None,
                   bridges: Sequence[Dict[str, Any]] = ()) -> None:
    """One lesion per lesion of the frames on ``p``, and the frames' lesions the 3D sections missed (module
    docstring, "Lesions of the frames"); changes ``p.lesions``, ``p.unreliable`` and ``p.frames_only``."""
    values = _frames_profile(p)
    if values is None or p.reference is None:
        return
    worst_of: Dict[Any, Lesion] = {}  # the frames' lesion (source, MLD position) → the 3D lesion kept for it
    for lesion in p.lesions:
        grade = lesion_grade(p, lesion, min_stenosis_pct)
        key = id(lesion) if grade.source == GRADED_ON_3D else (grade.source, grade.measure.mld_position_mm)
        kept = worst_of.get(key)
        if kept is None or lesion.diameter_stenosis_pct > kept.diameter_stenosis_pct:
            worst_of[key] = lesion
    p.lesions = [x for x in p.lesions if any(x is y for y in worst_of.values())]

    def confirmed(on_frames: Lesion, in_3d: Lesion, fit: ReferenceFit) -> bool:
        # the 3D sections without the free-end caps, where a vessel's rounded end narrows but is no lesion
        sections = np.where(_end_caps(p.branch), np.nan, p.diameter_mm)
        there = lesion_within(p.branch.arc_length_mm, sections, p.reference, on_frames.start_mm, on_frames.end_mm)
        return (there is not None and there.diameter_stenosis_pct >= FRAMES_LESION_MIN_3D_SHARE * min_stenosis_pct
                and on_frames.length_mm >= LESION_2D_MIN_LENGTH_DIAMETERS * on_frames.reference_diameter_mm
                and not _crowded_in_every_view(p, on_frames.mld_position_mm))

    p.frames_only += _lesions_missed_in_3d(p, values, min_stenosis_pct, fragments, bridges, confirmed)


def _crowded_in_every_view(p: BranchProfile, position_mm: float) -> bool:
    """Whether another vessel lies in the frames' window of every view at ``position_mm`` on ``p``."""
    if p.frame_views_crowded is None:
        return False
    return bool(p.frame_views_crowded[:, int(np.argmin(np.abs(p.branch.arc_length_mm - position_mm)))].all())


def masks_lesions(p: BranchProfile, min_stenosis_pct: float, fragments: Optional[Fragments] = None,
                  bridges: Sequence[Dict[str, Any]] = ()) -> None:
    """Where no frames are given: the lesions the masks' two-view diameter shows that the 3D sections missed
    (module docstring, "Lesions of the masks"); changes ``p.lesions``, ``p.unreliable`` and ``p.masks_only``."""
    if p.mask_diameter_mm is None or p.reference is None:
        return
    s = p.branch.arc_length_mm

    def confirmed(on_masks: Lesion, in_3d: Lesion, fit: ReferenceFit) -> bool:
        scatter_pct = 100 * relative_scatter(s, p.mask_diameter_mm, fit)
        return (in_3d.diameter_stenosis_pct >= min_stenosis_pct
                and on_masks.diameter_stenosis_pct >= MASKS_LESION_MIN_SCATTERS * scatter_pct
                and on_masks.length_mm >= LESION_2D_MIN_LENGTH_DIAMETERS * on_masks.reference_diameter_mm)

    p.masks_only += _lesions_missed_in_3d(p, p.mask_diameter_mm, min_stenosis_pct, fragments, bridges, confirmed)


def _lesions_missed_in_3d(p: BranchProfile, values: np.ndarray, min_stenosis_pct: float, fragments: Optional[Fragments],
                          bridges: Sequence[Dict[str, Any]],
                          confirmed: Optional[Callable[[Lesion, Lesion, ReferenceFit], bool]] = None) -> List[Lesion]:
    """The lesions of a two-view profile of ``p`` that are none of its lesions yet, each added (to ``p.lesions``,
    or ``p.unreliable`` where the reconstruction is broken there) as the 3D sections measure its extent;
    ``confirmed(on the profile, in 3D, the profile's reference)``: which to add (None: all)."""
    b = p.branch
    s = b.arc_length_mm
    usable = np.isfinite(values) & ~_end_caps(b)
    try:
        fit = reference_fit(s, values, usable)
    except ValueError:
        return []
    found = find_lesions(s, values, fit, usable, min_stenosis_pct=min_stenosis_pct)
    known = p.lesions + [u.lesion for u in p.unreliable]
    added: List[Lesion] = []
    for x in found:
        if any(is_same_lesion(lesion, x) for lesion in known):
            continue
        lesion = lesion_within(s, p.diameter_mm, p.reference, x.start_mm, x.end_mm, p.sections.area_mm2)
        if lesion is None or (confirmed is not None and not confirmed(x, lesion, fit)):
            p.unconfirmed += 1
            continue
        reasons = [] if fragments is None else lesion_reasons(b, lesion.start_mm, lesion.end_mm, p.reference(s) / 2,
                                                              fragments, bridges)
        if reasons:
            p.unreliable.append(UnreliableLesion(lesion, reasons))
        else:
            p.lesions.append(lesion)
        added.append(lesion)
        known.append(lesion)
    return added


def psf_for_frames(psf_sigma_mm: Union[float, None, str], densitometry: bool) -> Optional[float]:
    """The detector blur the frame widths assume: a given one (None: estimated), or for ``PSF_BY_FRAMES`` the
    default on frames that keep the intensity and an estimate on frames processed for display."""
    if isinstance(psf_sigma_mm, str):
        if psf_sigma_mm != PSF_BY_FRAMES:
            raise ValueError(f"psf_sigma_mm must be a blur in mm, None (estimated) or {PSF_BY_FRAMES!r}, got {psf_sigma_mm!r}")
        return DEFAULT_PSF_SIGMA_MM if densitometry else None
    return psf_sigma_mm


def _fit_frame_widths(profiles: List[BranchProfile], frames: Sequence[np.ndarray], views: Sequence[CArmView],
                      psf_sigma_mm: Union[float, None, str], densitometry: Sequence[bool]) -> Dict[str, Any]:
    """Each profile's widths fitted to the frames; the blur used per view (``psf_for_frames`` of each view:
    estimated when None). A view whose ``densitometry`` is False (its frame processed for display: its grey
    levels are no absorbance) gives no lumen areas and has its widths fitted on the grey level as a logarithm
    of the intensity (``frame_widths.profile_values``); the other views are read as they are."""
    log_grey = [not d for d in densitometry]
    sigmas, estimated = [], []
    for n, (frame, view) in enumerate(zip(frames, views)):
        sigma = psf_for_frames(psf_sigma_mm, densitometry[n])
        if sigma is None:
            sigma = estimate_psf_sigma_mm(np.concatenate([p.width_branch.points_mm for p in profiles]),
                                          np.concatenate([p.width_branch.tangents() for p in profiles]), frame, view,
                                          np.concatenate([p.view_widths_mm[n] for p in profiles]),
                                          grey_is_log_intensity=log_grey[n])
            estimated.append(sigma is not None)
        else:
            estimated.append(False)
        sigmas.append(float(DEFAULT_PSF_SIGMA_MM if sigma is None else sigma))
    per_profile = []
    for p in profiles:
        fitted = np.stack([frame_widths(p.width_branch.points_mm, p.width_branch.tangents(), f, v, w, sigma,
                                        grey_is_log_intensity=log)
                           for f, v, w, sigma, log in zip(frames, views, p.view_widths_mm, sigmas, log_grey)])
        p.frame_view_widths_mm = fitted
        if any(densitometry):
            unread = np.full(len(p.width_branch.points_mm), np.nan)
            per_profile.append(np.stack([densities(p.width_branch.points_mm, p.width_branch.tangents(), f, v, w, sigma)
                                         if lin else unread
                                         for f, v, w, sigma, lin in zip(frames, views, p.view_widths_mm, sigmas,
                                                                        densitometry)]))
    guessed = [sum(int(np.isfinite(p.view_widths_mm[n]).sum()) for p in profiles) for n in range(len(views))]
    fitted_points = [sum(int(np.isfinite(p.frame_view_widths_mm[n]).sum()) for p in profiles) for n in range(len(views))]
    measured = [f / g if g else None for f, g in zip(fitted_points, guessed)]
    crowded = [_crowded_views(p, profiles, views, sigmas) for p in profiles]
    for p, c in zip(profiles, crowded):
        p.frame_diameter_mm = left_out_beyond_sections(ellipse_diameter(_uncrowded_widths(p.frame_view_widths_mm, c)),
                                                       p.diameter_mm)
        p.frame_views_crowded = c
    if not any(densitometry):
        return {"psf_sigma_mm": sigmas, "psf_sigma_estimated": estimated, "frame_widths_measured": measured,
                "attenuation_per_mm": None, "densitometry": [False] * len(views)}
    # Each view's iodine attenuation from all branches' healthy points, where the vessel is round and
    # no other vessel lies in that view's window; none for a view processed for display.
    attenuations = [attenuation_per_mm(np.concatenate([d[n] for d in per_profile]),
                                       np.concatenate([p.frame_view_widths_mm[n] for p in profiles]),
                                       np.concatenate([~p.excluded & ~c[n] for p, c in zip(profiles, crowded)]))
                    if densitometry[n] else None for n in range(len(views))]
    for p, d, c in zip(profiles, per_profile, crowded):
        p.frame_density_diameter_mm = left_out_beyond_sections(density_diameter(d, attenuations, ~c), p.diameter_mm)
        p.frame_density_views = density_views(d, attenuations, ~c)
    # per view: the areas are read on the True ones
    return {"psf_sigma_mm": sigmas, "psf_sigma_estimated": estimated, "frame_widths_measured": measured,
            "attenuation_per_mm": attenuations, "densitometry": [bool(d) for d in densitometry]}


def left_out_beyond_sections(frames_diameter_mm: np.ndarray, sections_diameter_mm: np.ndarray,
                             max_ratio: Optional[float] = None) -> np.ndarray:
    """The frames' diameter, NaN (unmeasured) where it exceeds ``max_ratio`` (default ``FRAMES_MAX_OVER_3D``) × the
    3D section's equivalent diameter at the same point (module docstring, "The frames' measures beside other vessels")."""
    ratio = FRAMES_MAX_OVER_3D if max_ratio is None else max_ratio
    out = np.array(frames_diameter_mm, float)
    if ratio is None or not np.isfinite(ratio):
        return out
    with np.errstate(invalid="ignore"):
        out[out > ratio * np.asarray(sections_diameter_mm, float)] = np.nan
    return out


def _uncrowded_widths(view_widths_mm: np.ndarray, crowded: np.ndarray) -> np.ndarray:
    """The views' widths, a crowded view's left out (NaN) where an uncrowded view has a width."""
    has = np.isfinite(view_widths_mm) & (view_widths_mm > 0)
    return np.where(views_to_use(has, ~np.asarray(crowded, bool)), view_widths_mm, np.nan)


def crowded_in_view(points_mm: np.ndarray, radii_mm, others_mm: np.ndarray, others_radii_mm, view: CArmView,
                    guess_widths_mm: np.ndarray, psf_sigma_mm: float) -> np.ndarray:
    """Per point, whether another vessel's projected edge lies inside the frames' window across the vessel
    in ``view`` (``frame_widths.frame_profiles``, sized by ``guess_widths_mm``, the radii's diameter where
    NaN), short of the window's outermost millimetre."""
    radii = np.broadcast_to(np.asarray(radii_mm, float), (len(points_mm),))
    magnification = view.sid_mm / view.project(points_mm)[2]
    width = np.where(np.isfinite(guess_widths_mm), guess_widths_mm, 2 * radii)
    # The window reaches the guessed width + 4σ + 1 mm from the centre; on the exact trees a view's
    # density errs once another vessel's edge comes nearer than its outermost millimetre (RESULTS §47).
    window = width * magnification + 4.0 * psf_sigma_mm
    return other_vessel_clearance(points_mm, radii, others_mm, others_radii_mm, view) < window


def _crowded_views(p: BranchProfile, profiles: List[BranchProfile], views: Sequence[CArmView],
                   sigmas: Sequence[float]) -> np.ndarray:
    """(views, N) bool: ``crowded_in_view`` of ``p`` among the other branches, per view."""
    rest = [q for q in profiles if q is not p]
    others = np.concatenate([q.width_branch.points_mm for q in rest]) if rest else np.zeros((0, 3))
    others_r = np.concatenate([_profile_radii(q) for q in rest]) if rest else np.zeros(0)
    return np.stack([crowded_in_view(p.width_branch.points_mm, _profile_radii(p), others, others_r, view,
                                     p.view_widths_mm[n], sigma) for n, (view, sigma) in enumerate(zip(views, sigmas))])


def _median_diameter(diameter_mm: np.ndarray) -> float:
    return float(np.nanmedian(diameter_mm)) if np.isfinite(diameter_mm).any() else float("nan")


def strands_within_parents(tree: CentrelineTree, parent_diameter_mm: Dict[int, float]) -> set:
    """Ids of the side branches that are strands of their parent's lumen, and of everything below them
    (module docstring, "Side strands"); ``parent_diameter_mm``: each parent's median 3D equivalent diameter."""
    strands: set = set()
    for b in tree.branches:  # breadth first: a parent is judged before its children
        if b.parent_id is None:
            continue
        if b.parent_id in strands:
            strands.add(b.branch_id)
            continue
        parent = tree.branch(b.parent_id)
        width = parent_diameter_mm.get(parent.branch_id, float("nan"))
        if not np.isfinite(width) or len(b.points_mm) < 2:
            continue
        distance, nearest = cKDTree(parent.points_mm).query(b.points_mm)
        alignment = float(np.mean(np.abs(np.sum(b.tangents() * parent.tangents()[nearest], axis=1))))
        if distance.max() < STRAND_MAX_REACH_DIAMETERS * width and alignment > STRAND_MIN_ALIGNMENT:
            strands.add(b.branch_id)
    return strands


def _end_caps(branch: CentrelineBranch) -> np.ndarray:
    """Free-end caps: a lesion may sit at a junction, but the rounded or cut end of a vessel is not one."""
    s = branch.arc_length_mm
    r = np.nan_to_num(branch.inscribed_radius_mm)
    n = max(1, len(r) // 10)
    cap = s > s[-1] - 2.0 * float(np.max(r[-n:]))
    if branch.parent_id is None:
        cap |= s < 2.0 * float(np.max(r[:n]))
    return cap


def _profile_radii(p: BranchProfile) -> np.ndarray:
    """The 3D sections' radius per point, the centreline's inscribed radius where no section was measured."""
    r = p.diameter_mm / 2
    return np.where(np.isfinite(r), r, p.branch.inscribed_radius_mm)


def _radii(profiles: List[BranchProfile], branch_id: int) -> np.ndarray:
    for p in profiles:
        if p.branch.branch_id == branch_id:
            return _profile_radii(p)
    raise KeyError(branch_id)


def _others(tree: CentrelineTree, profiles: List[BranchProfile], branch_id: int, idx: np.ndarray):
    pts, rad = [], []
    for b in tree.branches:
        r = _radii(profiles, b.branch_id)
        keep = np.ones(len(b.points_mm), bool)
        if b.branch_id == branch_id:
            keep[idx] = False
        step = max(1, int(round(OTHERS_STEP_MM / max(np.median(np.diff(b.arc_length_mm)), 1e-6))))
        sel = np.flatnonzero(keep)[::step]
        pts.append(b.points_mm[sel])
        rad.append(r[sel])
    return np.concatenate(pts), np.concatenate(rad)


def _stats(values: Optional[np.ndarray], use: np.ndarray) -> Optional[Dict[str, float]]:
    if values is None:
        return None
    v = values[use & np.isfinite(values)]
    if v.size == 0:
        return None
    return {"mean_mm": float(v.mean()), "min_mm": float(v.min()), "max_mm": float(v.max())}


def lesion_on_2d_profile(p: BranchProfile, values: Optional[np.ndarray], lesion: Lesion,
                         min_stenosis_pct: float = 20.0) -> Optional[Lesion]:
    """``lesion`` (found on the 3D sections of ``p``) as a two-view profile of the same centreline measures
    it (``lesion.same_lesion_on``). Only the free-end caps are left out, not the junction zones: those
    keep side-branch mouths out of 3D sections, but on a rough reconstruction its side strands cover
    most of a branch, and a reference fitted to what is left runs through the lesion (RESULTS §21c)."""
    if values is None:
        return None
    return same_lesion_on(p.branch.arc_length_mm, values, np.isfinite(values) & ~_end_caps(p.branch), lesion,
                          min_stenosis_pct)


GRADED_ON_DENSITY, GRADED_ON_EDGES, GRADED_ON_3D = "frames (density)", "frames (edges)", "3D sections"
GRADED_ON_MASKS = "masks (two-view diameter)"
FOUND_ON_FRAMES, FOUND_ON_MASKS = "frames", "masks"  # analysis.json ``found_on``: "3D sections" (GRADED_ON_3D) or these


@dataclass
class LesionGrade:
    """How a lesion found on the 3D sections is graded (module docstring, "Grade of a lesion")."""

    source: str  # GRADED_ON_DENSITY, GRADED_ON_EDGES, GRADED_ON_MASKS (lesions found on the masks only) or GRADED_ON_3D
    measure: Lesion  # the lesion as that source measures it
    seen_on_frames: Optional[bool]  # None: no frames given
    on_frames: Optional[Dict[str, Optional[Lesion]]] = None  # "edges", "density": the same lesion there, or None
    seen_on_masks: Optional[bool] = None  # None: no masks given

    def to_dict(self) -> Dict[str, Any]:
        return dict(self.measure.to_dict(), source=self.source)


def _mask_profiles(p: BranchProfile) -> List[np.ndarray]:
    """The masks' profiles a lesion is read on: their two-view diameter and each view's width."""
    return [p.mask_diameter_mm] + list(p.view_widths_mm)


def masks_stenosis_pct(p: BranchProfile, lesion: Lesion) -> Optional[float]:
    """The largest % diameter stenosis the masks show at ``lesion`` (found on ``p``'s 3D sections): on their
    two-view diameter or either view's width; 0 where none narrows there, None without masks."""
    if p.view_widths_mm is None:
        return None
    found = [lesion_on_2d_profile(p, values, lesion, min_stenosis_pct=1.0) for values in _mask_profiles(p)]
    return max([x.diameter_stenosis_pct for x in found if x is not None], default=0.0)


def seen_on_masks(p: BranchProfile, lesion: Lesion, min_stenosis_pct: float = 20.0) -> Optional[bool]:
    """Whether the masks show ``lesion`` (found on ``p``'s 3D sections): their two-view diameter or one view's
    width narrows by ``min_stenosis_pct`` there (an eccentric throat may narrow in one view only; an overlap
    widens one view, not both). None without masks."""
    if p.view_widths_mm is None:
        return None
    return any(lesion_on_2d_profile(p, values, lesion, min_stenosis_pct) is not None for values in _mask_profiles(p))


def lesion_grade(p: BranchProfile, lesion: Lesion, min_stenosis_pct: float = 20.0) -> LesionGrade:
    """The grade of ``lesion`` (found on ``p``'s 3D sections): the frames' density, else their edges,
    else the 3D sections (module docstring); with both frame measures of it, and whether the masks show it."""
    on_masks = seen_on_masks(p, lesion, min_stenosis_pct)
    if p.frame_diameter_mm is None:
        if any(lesion is x for x in p.masks_only):  # found on the masks only: graded on them
            measure = lesion_on_2d_profile(p, p.mask_diameter_mm, lesion, min_stenosis_pct)
            if measure is not None:
                return LesionGrade(GRADED_ON_MASKS, measure, None, seen_on_masks=True)
        return LesionGrade(GRADED_ON_3D, lesion, None, seen_on_masks=on_masks)
    on_frames = {name: lesion_on_2d_profile(p, values, lesion, min_stenosis_pct)
                 for name, values in (("edges", p.frame_diameter_mm), ("density", p.frame_density_diameter_mm))}
    for source, name in ((GRADED_ON_DENSITY, "density"), (GRADED_ON_EDGES, "edges")):
        if on_frames[name] is not None:
            return LesionGrade(source, on_frames[name], True, on_frames, on_masks)
    return LesionGrade(GRADED_ON_3D, lesion, False, on_frames, on_masks)


def unseen_on(seen_on_frames: Optional[bool], seen_on_masks: Optional[bool]) -> Optional[str]:
    """Which images a lesion of the 3D sections is not seen on, to warn about: "frames" where they were
    given and do not show it; without frames, "masks" where no mask shows it; else None."""
    if seen_on_frames is False:
        return "frames"
    if seen_on_frames is None and seen_on_masks is False:
        return "masks"
    return None


def _lesion_entry(p: BranchProfile, lesion: Lesion, min_stenosis_pct: float, voxel_mm: float, **extra) -> Dict[str, Any]:
    """A lesion of analysis.json: its 3D-section measures (top level), its grade, the frames' measures
    (``frames``: None without frames, else each measure's lesion or None where it shows none), whether
    its 3D minimal lumen is thinner than the grid resolves (module docstring, "Resolution")."""
    grade = lesion_grade(p, lesion, min_stenosis_pct)
    frames = None if grade.on_frames is None else {k: None if v is None else v.to_dict() for k, v in grade.on_frames.items()}
    found_on = (FOUND_ON_FRAMES if any(lesion is x for x in p.frames_only)
                else FOUND_ON_MASKS if any(lesion is x for x in p.masks_only) else GRADED_ON_3D)
    return dict(lesion.to_dict(), branch_id=p.branch.branch_id, grade=grade.to_dict(), found_on=found_on,
                missed_in_3d=None if found_on == GRADED_ON_3D else _why_missed_in_3d(lesion, min_stenosis_pct, voxel_mm),
                mld_below_resolution=bool(lesion.mld_mm < RESOLVABLE_VOXELS * voxel_mm),
                seen_on_frames=grade.seen_on_frames, frames=frames, seen_on_masks=grade.seen_on_masks,
                masks_diameter_stenosis_pct=masks_stenosis_pct(p, lesion), **extra)


# Why the 3D sections report no lesion where the frames or masks found one (analysis.json ``missed_in_3d``),
# and how the messages say it: the 3D measures printed beside them are the sections' over the found extent.
MISSED_NARROWS_LESS = "narrows less"
MISSED_UNRESOLVED = "unresolved"
MISSED_OTHER = "free end or beside another lesion"
MISSED_IN_3D_PHRASE = {
    MISSED_NARROWS_LESS: "the 3D sections narrow there less than a lesion",
    MISSED_UNRESOLVED: (f"the 3D sections narrow there too, but over a vessel or a length under {RESOLVABLE_VOXELS:g} "
                        f"voxels, which they do not report"),
    MISSED_OTHER: ("the 3D sections narrow there too, but report no lesion of their own there (at a branch's free end, "
                   "or beside another lesion they report)"),
}


def _why_missed_in_3d(lesion: Lesion, min_stenosis_pct: float, voxel_mm: float) -> str:
    """Which of ``MISSED_IN_3D_PHRASE`` holds for a lesion found on the frames or masks only, its 3D measure
    ``lesion`` (the sections over the found extent)."""
    if lesion.diameter_stenosis_pct < min_stenosis_pct:
        return MISSED_NARROWS_LESS
    resolvable_mm = RESOLVABLE_VOXELS * voxel_mm
    if lesion.reference_diameter_mm < resolvable_mm or lesion.length_mm < resolvable_mm:
        return MISSED_UNRESOLVED
    return MISSED_OTHER


def _unseen_warning(lesions: List[Dict[str, Any]], images: str, check_on: str) -> Optional[str]:
    unseen = [d for d in lesions if unseen_on(d["seen_on_frames"], d["seen_on_masks"]) == images]
    if not unseen:
        return None
    where = ", ".join(f"branch {d['branch_id']} at {d['mld_position_mm']:.1f} mm (3D DS {d['diameter_stenosis_pct']:.0f}%)"
                      for d in unseen)
    return (f"{len(unseen)} lesion(s) of the 3D sections not seen on the {images}: {where}. The reconstruction may be "
            f"rough or flattened there; check the {check_on} before acting on these (they are graded on the 3D sections).")


def _found_only_warning(lesions: List[Dict[str, Any]], images: str) -> Optional[str]:
    """The warning for the lesions found on ``images`` (FOUND_ON_FRAMES or FOUND_ON_MASKS) only."""
    only = [d for d in lesions if d["found_on"] == images]
    if not only:
        return None
    where = ", ".join(f"branch {d['branch_id']} at {d['grade']['mld_position_mm']:.1f} mm ({images} DS "
                      f"{d['grade']['diameter_stenosis_pct']:.0f}%, 3D sections {d['diameter_stenosis_pct']:.0f}%: "
                      f"{MISSED_IN_3D_PHRASE[d['missed_in_3d']]})" for d in only)
    reasons = {d["missed_in_3d"] for d in only}
    why = []
    if MISSED_NARROWS_LESS in reasons:
        why.append("Where the 3D sections narrow less, the reconstruction is too coarse or too rough for this vessel, or "
                   f"a vessel crossing this one in a view narrows the {images}' profile (check the angiograms).")
    if MISSED_UNRESOLVED in reasons:
        why.append("Where the grid does not resolve it, a reconstruction on a finer grid measures it in 3D.")
    if images == FOUND_ON_FRAMES:
        why.append("The grade is the frames'")
    else:
        why.append("The grade is the masks' two-view diameter, which reads an eccentric throat up to 20 points off; "
                   "grade it on the frames (analyse --frames)")
    return (f"{len(only)} lesion(s) found on the {images} only: {where}. {' '.join(why)}; the 3D measures are the "
            f"sections' over the {images}' extent.")


def _given_root_warning(given_root: Optional[Dict[str, Any]]) -> Optional[str]:
    """A warning where the ostium given roots the tree far thinner than its thickest end (``OSTIUM_THIN_SHARE``)."""
    if not given_root:
        return None
    given, best = 2 * given_root["given_radius_mm"], 2 * given_root["thickest_end_radius_mm"]
    if given >= OSTIUM_THIN_SHARE * best or given_root["distance_to_thickest_end_mm"] <= OSTIUM_THIN_MIN_DISTANCE_MM:
        return None
    where = ", ".join(f"{v:.1f}" for v in given_root["thickest_end_mm"])
    return (f"the ostium given roots the tree where the vessel is {given:.1f} mm wide, but its thickest end, at ({where}) "
            f"LPS mm, is {best:.1f} mm wide: every branch is ordered from the ostium, so a point at a distal tip reads the "
            f"tree backwards (lengths from the wrong end, side branches as the main vessel). If the ostium is not where you "
            f"put it, give the root end (Slicer shows RAS: negate x and y) or leave --ostium out (in Slicer: no Ostium point "
            f"list) to start from the thickest end.")


def _thin_throat_warning(lesions: List[Dict[str, Any]], voxel_mm: float) -> Optional[str]:
    thin = [d for d in lesions if d["mld_below_resolution"] and d["grade"]["source"] == GRADED_ON_3D]
    if not thin:
        return None
    where = ", ".join(f"branch {d['branch_id']} at {d['mld_position_mm']:.1f} mm (3D MLD {d['mld_mm']:.2f} mm, "
                      f"DS {d['diameter_stenosis_pct']:.0f}%)" for d in thin)
    return (f"{len(thin)} lesion(s) graded on the 3D sections have a minimal lumen under {RESOLVABLE_VOXELS:g} voxels "
            f"({RESOLVABLE_VOXELS * voxel_mm:.2f} mm on this {voxel_mm:g} mm grid): {where}. So thin a throat is read a "
            f"fraction of a voxel off and its %DS may be 10 points or more off; grade it on the frames (analyse --frames) "
            f"or reconstruct on a finer grid.")


def summary(result: QCAResult) -> Dict[str, Any]:
    """JSON-ready description of a QCA result (lengths mm, angles degrees, stenoses %)."""
    branches = []
    min_stenosis = float(result.settings.get("min_stenosis_pct", 20.0))
    voxel_mm = float(result.settings["voxel_mm"])
    all_lesions: List[Dict[str, Any]] = []
    unreliable: List[Dict[str, Any]] = []
    for p in result.profiles:
        b = p.branch
        healthy = ~p.excluded
        mld = minimal_lumen(b.arc_length_mm, p.diameter_mm, healthy)
        entry = {
            "branch_id": b.branch_id, "parent_id": b.parent_id, "tree_id": b.tree_id,
            "parent_arc_mm": None if b.parent_id is None else float(result.tree.branch(b.parent_id).arc_length_mm[b.parent_index]),
            "length_mm": b.length_mm, "points": len(b.points_mm),
            "start_mm": b.points_mm[0].tolist(), "end_mm": b.points_mm[-1].tolist(),
            "diameter_3d": _stats(p.diameter_mm, healthy),
            "diameter_masks": _stats(p.mask_diameter_mm, healthy),
            "diameter_frames": _stats(p.frame_diameter_mm, healthy),
            "diameter_frames_density": _stats(p.frame_density_diameter_mm, healthy),
            "reference": None if p.reference is None else {"intercept_mm": p.reference.intercept_mm,
                                                           "slope_mm_per_mm": p.reference.slope_mm_per_mm},
            "minimal_lumen": mld,
            "component": None if result.fragments is None else result.fragments.branch_record(b),
            "lesions": [_lesion_entry(p, lesion, min_stenosis, voxel_mm, reliable=True) for lesion in p.lesions],
            "unreliable_lesions": [_lesion_entry(p, u.lesion, min_stenosis, voxel_mm, reliable=False, flag=UNRELIABLE,
                                                 reasons=list(u.reasons)) for u in p.unreliable],
            "narrowings_below_resolution": p.unresolved,
            "narrowings_2d_unconfirmed": p.unconfirmed,
            "foreshortening_per_view": result.view_foreshortening.get(b.branch_id, []),
            "epipolar_angle_deg": epipolar_stats(result.epipolar_deg[b.branch_id]) if b.branch_id in result.epipolar_deg else None,
            "warning": p.warning or None,
        }
        branches.append(entry)
        all_lesions.extend(entry["lesions"])
        unreliable.extend(entry["unreliable_lesions"])
    all_lesions.sort(key=lambda d: -d["grade"]["diameter_stenosis_pct"])
    unreliable.sort(key=lambda d: -d["grade"]["diameter_stenosis_pct"])
    out: Dict[str, Any] = {
        "coordinate_system": "LPS", "units": {"length": "mm", "angle": "degrees", "stenosis": "percent"},
        "settings": result.settings,
        "views": [{"label": view_label(v.primary_deg, v.secondary_deg), "primary_deg": v.primary_deg,
                   "secondary_deg": v.secondary_deg} for v in result.views],
        "tree": {"branches": len(result.tree.branches), "total_length_mm": result.tree.total_length_mm(),
                 "strands_dropped": int(result.settings.get("strands_dropped", 0))},
        "branches": branches, "lesions": all_lesions, "unreliable_lesions": unreliable,
        "bifurcations": result.bifurcations, "target_segment": result.target,
        "connectivity": result.fragments.summary() if result.fragments is not None else None,
        "warnings": [w for w in [result.fragments.warning() if result.fragments is not None else None,
                                 _unseen_warning(all_lesions, "frames", "frames"),
                                 _unseen_warning(all_lesions, "masks", "angiograms"),
                                 _found_only_warning(all_lesions, FOUND_ON_FRAMES),
                                 _found_only_warning(all_lesions, FOUND_ON_MASKS),
                                 _thin_throat_warning(all_lesions, voxel_mm),
                                 _depth_warning(result.target),
                                 _given_root_warning(result.settings.get("given_root")),
                                 narrow_root_warning(result.settings.get("narrow_root")),
                                 through_vessel_root_warning(result.settings.get("through_vessel_root")),
                                 mask_order_warning(result.settings.get("centreline_share_on_masks") or (),
                                                    result.settings.get("masks_better_order")),
                                 frame_contrast_warning(result.settings.get("frame_vessel_contrast") or (),
                                                        result.settings.get("frame_widths_measured") or ())] if w],
    }
    if result.view_map is not None:
        best = result.view_map.best()
        out["best_view"] = dict(best, overlap_weight=1.0, primary_range_deg=[float(result.view_map.primary_deg[0]),
                                                                          float(result.view_map.primary_deg[-1])],
                                secondary_range_deg=[float(result.view_map.secondary_deg[0]),
                                                     float(result.view_map.secondary_deg[-1])])
        vm = result.view_map
        # The maps themselves (rows = secondary angle), for viewers that draw their own (Slicer's image).
        out["view_map"] = {"primary_deg": vm.primary_deg.tolist(), "secondary_deg": vm.secondary_deg.tolist(),
                           "foreshortening": np.round(vm.foreshortening, 4).tolist(),
                           "overlap": np.round(vm.overlap, 4).tolist()}
    return out
