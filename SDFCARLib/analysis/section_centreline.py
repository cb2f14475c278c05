"""The centreline moved onto the centroids of its own cross-sections: the bends the smoothing cut, given back.

Why
    ``extract_centrelines`` smooths the thinned voxel path along its arc (Gaussian σ, 1 mm) to take the voxel
    staircase out. On a bend of radius R that pulls the curve towards the bend's centre by about σ² / (2R) and
    shortens it by a share of about σ² / (2R²): on tortuous vessels (bends of 3–5 mm radius) a lesion's segment
    comes out 2–3 % short and its foreshortening up to 2 points off (bench/RESULTS.md §72). The lumen's
    cross-section perpendicular to the curve shows where its centre is.

Method (``centre_on_sections``)
    At each point p, the centroid c of its cross-section (``diameter.cross_sections``, which casts its rays
    again from the centroid it finds). The shift c − p counts where the section is the branch's own lumen
    (outside ``diameter.junction_zones``: a side branch's start inside its parent, a side branch's mouth on
    the parent, a free end's cap), where a section was found and where |c − p| is within the point's
    inscribed radius. The other points take the shift interpolated along the arc (the nearest counted shift
    beyond the ends); a side branch's first point takes its parent's shift at the junction, so it stays on
    the parent's moved junction point. The shift is smoothed along the arc (Gaussian, ``smoothing_mm``) and
    added: the shift varies as slowly as the curvature does, so smoothing it keeps the bend that smoothing
    the points cuts. A branch with fewer than ``min_measured`` counted points moves with its junction (a
    root stays). Only the points move: their number, the branch ids and the junction indices stay, so the
    sections still belong to the same points.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Dict, List, Mapping, Tuple

import numpy as np

from .centreline import CentrelineBranch, CentrelineTree, shift_along_arc
from .diameter import CrossSections, junction_zones

SMOOTHING_MM = 1.0


@dataclass(frozen=True)
class SectionPlacement:
    branch_id: int
    measured_share: float  # of the branch's points whose section set the shift
    mean_shift_mm: float  # |shift| after smoothing, mean over the branch

    def to_dict(self) -> Dict[str, float]:
        return {"branch_id": self.branch_id, "measured_share": round(self.measured_share, 3),
                "mean_shift_mm": round(self.mean_shift_mm, 3)}


def centre_on_sections(tree: CentrelineTree, sections: Mapping[int, CrossSections], smoothing_mm: float = SMOOTHING_MM,
                       min_measured: int = 5) -> Tuple[CentrelineTree, List[SectionPlacement]]:
    """The tree with every branch moved onto its sections' centroids (module docstring), and how far."""
    moved: Dict[int, CentrelineBranch] = {}
    report: List[SectionPlacement] = []
    for branch in sorted(tree.branches, key=lambda b: b.branch_id):  # parents first: ids grow with the generation
        points = branch.points_mm
        section = sections.get(branch.branch_id)
        parent = moved.get(branch.parent_id) if branch.parent_id is not None else None
        junction_shift = (parent.points_mm[branch.parent_index] - tree.branch(branch.parent_id).points_mm[branch.parent_index]
                          if parent is not None else None)
        if section is None or section.centres_mm is None or len(points) < 2:
            counted = np.zeros(len(points), bool)
            shift = np.zeros_like(points)
        else:
            shift = section.centres_mm - points
            radius = np.nan_to_num(branch.inscribed_radius_mm)
            counted = (np.isfinite(section.area_mm2) & (section.area_mm2 > 0) & np.isfinite(shift).all(axis=1)
                       & ~junction_zones(tree, branch))
            counted[counted] = np.linalg.norm(shift[counted], axis=1) <= radius[counted]
        delta = shift_along_arc(branch.arc_length_mm, counted, shift, junction_shift, smoothing_mm, min_measured)
        moved[branch.branch_id] = replace(branch, points_mm=points + delta)
        report.append(SectionPlacement(branch.branch_id, float(counted.mean()) if len(points) else 0.0,
                                       float(np.linalg.norm(delta, axis=1).mean()) if len(points) else 0.0))
    return CentrelineTree([moved[b.branch_id] for b in tree.branches]), report
