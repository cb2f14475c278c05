"""Is the tree's root a coronary ostium? Checks for a root the vessel widens away from and for one on a vessel's side.

Where no ostium is given, the tree is rooted at its thickest end (``centreline.py``). Every clinical
angiogram shows the guiding catheter entering the ostium, and the masks take it for a vessel; in the
reconstruction it continues the tree beyond the ostium to where it leaves a view, and its free end
becomes the root: lengths are counted from it, and the step from the catheter (2 mm for 6 F) to the
wider vessel reads as a stenosis at the start of the main branch. On reconstructions from realistic masks the
thickest end is sometimes a distal end, where the proximal vessel's own end came out thin or joined to a
ghost: the tree is then read backwards.

A coronary artery narrows from its ostium. The check reads the main branch's 3D sections: the median
equivalent diameter over its first ``ROOT_SPAN_MM`` against the widest median over ``WINDOW_MM``
windows up to ``SEARCH_MM`` along it. Where the vessel widens by ``MIN_WIDENING`` or more, after a narrow
stretch (the smoothed diameter under ``NARROW_SHARE`` × the widest) of at least ``MIN_NARROW_STRETCH_MM``,
the root is not an ostium as measured: a catheter, a distal end, or a long ostial lesion.
Nothing is cut; the analysis says so and how to give the ostium. Measured in bench/RESULTS.md §103f.

A root can also sit on the side of a vessel: a thick blob on a vessel's middle (a ghost where vessels
cross in a view) is the thickest end, and the tree then leaves its root both ways along that vessel. An
ostium begins one vessel. Where the root branch and a side branch, both running on for
``THROUGH_MIN_LENGTH_MM`` or more, part ``THROUGH_MIN_ANGLE_DEG`` or more apart within
``THROUGH_JUNCTION_MM`` of the root (``through_vessel_root``), the root is likely no ostium, and the
thickest of the tree's other ends (by the root rule's own measure) the likeliest one. The junction's
nearness is what tells: a left main's bifurcation, about a centimetre from the ostium, can part its branches
as widely, while a blob's end lies within its own radius of the vessel it sits on. Measured in
bench/RESULTS.md §105b, §105e.
"""

from __future__ import annotations

from typing import Any, Dict, Optional

import numpy as np

from .centreline import ROOT_RADIUS_REACH_MM

ROOT_SPAN_MM = 5.0
WINDOW_MM = 3.0
SEARCH_MM = 60.0
#: trees measured 1.0–1.27 (the widest window at the first bifurcation), lone tubes ≤ 1.03, a tree with a catheter 2.0–2.5
MIN_WIDENING = 1.6
NARROW_SHARE = 0.8
MIN_NARROW_STRETCH_MM = 10.0
#: the middle of the gap between trees rooted at the ostium and roots on a vessel's side (bench/RESULTS.md §105e)
THROUGH_JUNCTION_MM = 5.0
THROUGH_MIN_LENGTH_MM = 30.0
THROUGH_MIN_ANGLE_DEG = 95.0
#: each branch's direction: from where it leaves the root to this far along it
THROUGH_DIRECTION_MM = 5.0


def narrow_root(arc_mm: np.ndarray, diameter_mm: np.ndarray) -> Optional[Dict[str, float]]:
    """Where the main branch (arc length and 3D section diameter per point, from the root) widens by
    ``MIN_WIDENING`` after a narrow stretch of ``MIN_NARROW_STRETCH_MM``: the root's and the wide part's
    diameters (mm), the widening and where the vessel reaches the wide part's ``NARROW_SHARE`` (mm from the
    root); None where it does not."""
    arc, diameter = np.asarray(arc_mm, float), np.asarray(diameter_mm, float)

    def median_over(start: float, span: float) -> float:
        inside = (arc >= start) & (arc <= start + span) & np.isfinite(diameter)
        return float(np.median(diameter[inside])) if inside.any() else float("nan")

    root = median_over(0.0, ROOT_SPAN_MM)
    if not root > 0:
        return None
    starts = np.arange(0.0, SEARCH_MM, 0.5)
    smoothed = np.array([median_over(s, WINDOW_MM) for s in starts])
    beyond = starts >= ROOT_SPAN_MM
    if not np.isfinite(smoothed[beyond]).any():
        return None
    wide = float(np.nanmax(smoothed[beyond]))
    if wide < MIN_WIDENING * root:
        return None
    reached = np.flatnonzero(np.isfinite(smoothed) & (smoothed >= NARROW_SHARE * wide))
    stretch = float(starts[reached[0]]) if reached.size else float("nan")
    if not stretch >= MIN_NARROW_STRETCH_MM:
        return None
    return {"root_diameter_mm": root, "wide_diameter_mm": wide, "widening": wide / root, "narrow_stretch_mm": stretch}


def narrow_root_warning(found: Optional[Dict[str, Any]]) -> Optional[str]:
    """The warning for ``narrow_root``'s finding (with ``root_mm``, the root's LPS position, added by the caller)."""
    if not found:
        return None
    where = ", ".join(f"{v:.1f}" for v in found["root_mm"])
    return (f"the tree's thickest end, taken as the ostium at ({where}) LPS mm, leads through "
            f"{found['narrow_stretch_mm']:.0f} mm of vessel {found['root_diameter_mm']:.1f} mm wide into one "
            f"{found['wide_diameter_mm']:.1f} mm wide ({found['widening']:.1f}×): a coronary artery narrows from its "
            "ostium, so this root is likely not the ostium — the guiding catheter, a distal end where the proximal "
            "vessel's own end came out thin, or a long ostial lesion. Lengths, positions and branch order are counted "
            "from it, and where it widens reads as a stenosis. Give the ostium where the artery begins (analyse --ostium "
            "X Y Z in LPS mm; in Slicer a one-point list as the Ostium; in Python analyse_result_dir(…, ostium_mm=…)); a "
            "catheter can also be erased from the masks before reconstructing.")


def _direction(points_mm: np.ndarray) -> np.ndarray:
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points_mm, axis=0), axis=1))])
    step = points_mm[min(int(np.searchsorted(arc, THROUGH_DIRECTION_MM)), len(points_mm) - 1)] - points_mm[0]
    return step / max(float(np.linalg.norm(step)), 1e-12)


def root_junctions(tree, reach_mm: float = THROUGH_JUNCTION_MM):
    """Each side branch leaving the root branch within ``reach_mm`` of the root, with what
    both ways measure there: (child, mm from the root, angle (degrees) between the root branch's direction
    beyond the junction and the child's, the shorter one's length beyond the junction in mm).
    ``tree``: a ``CentrelineTree`` whose branch 0 is the root branch."""
    try:
        root_branch = tree.branch(0)
    except KeyError:
        return []
    arc = root_branch.arc_length_mm
    out = []
    for child in tree.children(0):
        at = child.parent_index
        if at is None or arc[at] > reach_mm:
            continue
        # a side branch's points start at its junction
        cosine = float(_direction(root_branch.points_mm[at:]) @ _direction(child.points_mm))
        out.append((child, float(arc[at]), float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))),
                    min(child.length_mm, float(arc[-1] - arc[at]))))
    return out


def through_vessel_root(tree) -> Optional[Dict[str, Any]]:
    """Where the root branch and a side branch, both running on ``THROUGH_MIN_LENGTH_MM`` or more, part
    ``THROUGH_MIN_ANGLE_DEG`` or more apart within ``THROUGH_JUNCTION_MM`` of the root (``root_junctions``),
    the widest such: the angle, the junction's distance from the root, both branches' ids, lengths beyond
    the junction and far ends, the root, and the likeliest ostium: the end of the root's piece (the root
    aside) with the largest inscribed radius within ``ROOT_RADIUS_REACH_MM`` of it (LPS mm); None where none
    do."""
    found = [j for j in root_junctions(tree) if j[2] >= THROUGH_MIN_ANGLE_DEG and j[3] >= THROUGH_MIN_LENGTH_MM]
    if not found:
        return None
    child, junction_mm, angle, _ = max(found, key=lambda j: j[2])
    root_branch = tree.branch(0)
    likeliest = max((b for b in tree.branches if b.tree_id == root_branch.tree_id), key=lambda b: float(
        np.max(b.inscribed_radius_mm[b.arc_length_mm >= b.length_mm - ROOT_RADIUS_REACH_MM])))
    return {"angle_deg": angle, "junction_from_root_mm": junction_mm, "branch_ids": [0, child.branch_id],
            "lengths_mm": [float(root_branch.length_mm - junction_mm), child.length_mm],
            "far_ends_mm": [[float(v) for v in b.points_mm[-1]] for b in (root_branch, child)],
            "root_mm": [float(v) for v in root_branch.points_mm[0]],
            "likeliest_ostium_mm": [float(v) for v in likeliest.points_mm[-1]]}


def through_vessel_root_warning(found: Optional[Dict[str, Any]]) -> Optional[str]:
    """The warning for ``through_vessel_root``'s finding."""
    if not found:
        return None

    def at(point) -> str:
        return "(" + ", ".join(f"{v:.1f}" for v in point) + ")"

    lengths = " and ".join(f"{v:.0f}" for v in found["lengths_mm"])
    return (f"the tree's thickest end, taken as the ostium at {at(found['root_mm'])} LPS mm, lies on the side of a "
            f"vessel: branches of {lengths} mm leave it {found['angle_deg']:.0f}° apart, running both ways, where an "
            "ostium begins one vessel. The root is likely a ghost or a crossing on the vessel's middle. The thickest of "
            f"the tree's other ends, at {at(found['likeliest_ostium_mm'])} LPS mm, is the likeliest ostium: check it. "
            "Lengths, positions and branch order are counted from the root. Give the ostium where the artery begins "
            f"(there: analyse … --ostium {' '.join(f'{v:.1f}' for v in found['likeliest_ostium_mm'])}; in Slicer a "
            "one-point list as the Ostium; in Python analyse_result_dir(…, ostium_mm=…)).")
