"""Is the reconstruction intact where a lesion is measured? Pieces, gaps and bridges.

Why
    A reconstruction from two views often falls apart into pieces (the bundled demo: 17, the
    largest with 61 % of the vessel voxels). Where a vessel is broken its reconstruction thins
    towards the gap, and where reconnection (``SDFCARLib/connectivity.py``) bridged a gap it laid
    a tube thinner than the vessel by construction; on a diameter profile both read as a
    stenosis. The 3D-QCA must neither report these as lesions of an intact vessel nor hide them:
    they are kept, flagged, with the reason.

Pieces analysed (``MIN_COMPONENT_SHARE``)
    The 26-connected components of the lumen (``metrics.component_labels``). The main tree is
    the largest, or the one nearest the ostium when it is given. A piece is analysed when it
    holds at least 10 % of the main tree's voxels. On the demo the two pieces on the true tree
    hold 100 % and 47 % of the largest's voxels, the two largest pieces off it (ghosts: no voxel
    within two voxels of the ground truth) 4.9 % and 3.5 %, every other piece at most 1.5 %:
    10 % keeps a factor of two from both. The others are counted, not analysed.

Reasons a lesion is flagged "unreliable: the reconstruction is broken here"
    fragment  it lies on a piece that is not connected to the main tree.
    gap       another piece comes within ``GAP_MM`` of the vessel's wall (its reference radius
              around the centreline) along the lesion: the vessel breaks there, or the break's
              debris lies beside it. ``GAP_MM`` (4 mm) is the breaks a reconstruction is known
              to leave in a vessel at a throat: a voxel or three of a coarse grid (RESULTS §5's
              accepted gaps were 2.6–3.6 mm). Reconnection reaches further (8 mm, inside the
              support), but a piece it could not join that far off is no sign of a broken throat.
    bridge    the lesion meets a tube that reconnection laid across a gap (report.json lists
              them): the vessel was broken there and the tube is as thin as the thinner end,
              less half a voxel.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
from scipy import ndimage

from ..geometry import VolumeGrid
from ..metrics import component_labels
from .centreline import CentrelineBranch

MIN_COMPONENT_SHARE = 0.10  # of the main tree's voxels (module docstring)
GAP_MM = 4.0  # mm from the vessel wall (module docstring)
UNRELIABLE = "unreliable: the reconstruction is broken here"


@dataclass
class Fragments:
    """The lumen's pieces: labels (0 background), voxels per label 1..n, the main tree's label and
    which labels are analysed."""

    labels: np.ndarray
    sizes: np.ndarray
    main: int
    analysed: np.ndarray  # bool per label 1..n
    min_share: float
    grid: VolumeGrid
    _distance: Dict[int, Any] = field(default_factory=dict, repr=False)

    @property
    def count(self) -> int:
        return int(self.sizes.size)

    def analysed_mask(self) -> np.ndarray:
        keep = np.concatenate([[False], self.analysed])
        return keep[self.labels]

    def label_of(self, points_mm: np.ndarray) -> int:
        """The piece most of the points lie in (0 if none)."""
        values = self.labels[_voxels(self.grid, points_mm, self.labels.shape)]
        values = values[values > 0]
        return int(np.bincount(values).argmax()) if values.size else 0

    def branch_record(self, branch: CentrelineBranch) -> Optional[Dict[str, Any]]:
        """The piece a branch lies on, for analysis.json."""
        own = self.label_of(branch.points_mm)
        if not own:
            return None
        return {"voxels": int(self.sizes[own - 1]), "share_of_main": float(self.sizes[own - 1] / self.sizes[self.main - 1]),
                "main": own == self.main}

    def distance_to_others_mm(self, own: int):
        """(distance in mm from every voxel to the nearest voxel of another piece, that voxel's label)."""
        if own not in self._distance:
            others = (self.labels > 0) & (self.labels != own)
            if not others.any():
                self._distance[own] = None
            else:
                distance, index = ndimage.distance_transform_edt(~others, sampling=self.grid.spacing_mm,
                                                                 return_indices=True)
                self._distance[own] = (distance, self.labels[tuple(index)])
        return self._distance[own]

    def summary(self) -> Dict[str, Any]:
        total = int(self.sizes.sum())
        left = ~self.analysed
        return {
            "components": self.count,
            "largest_component_share": float(self.sizes.max() / total) if total else None,
            "main_component_voxels": int(self.sizes[self.main - 1]) if self.main else 0,
            "min_component_share": self.min_share,
            "analysed_components": int(self.analysed.sum()),
            "not_analysed": {"components": int(left.sum()), "voxels": int(self.sizes[left].sum()),
                             "share_of_all_voxels": float(self.sizes[left].sum() / total) if total else 0.0},
            "gap_mm": GAP_MM,
        }

    def warning(self) -> Optional[str]:
        if self.count < 2:
            return None
        total = float(self.sizes.sum())
        left = ~self.analysed
        text = (f"the reconstruction is in {self.count} pieces; the largest holds {100 * self.sizes.max() / total:.0f} % "
                "of the vessel voxels")
        if left.any():
            text += (f"; {int(left.sum())} piece(s) under {100 * self.min_share:g} % of the main tree's size "
                     f"({100 * self.sizes[left].sum() / total:.0f} % of the voxels) were not analysed")
        return text + f". Lesions where the vessel is broken are flagged \"{UNRELIABLE}\" in analysis.json"


def _voxels(grid: VolumeGrid, points_mm: np.ndarray, shape: Sequence[int]):
    ijk = np.rint(grid.world_to_index(np.asarray(points_mm, float).reshape(-1, 3))).astype(int)
    return tuple(np.clip(ijk, 0, np.asarray(shape) - 1).T)


def find_fragments(lumen: np.ndarray, grid: VolumeGrid, min_share: float = MIN_COMPONENT_SHARE,
                   ostium_mm: Optional[Sequence[float]] = None) -> Fragments:
    """The pieces of a binary lumen and which are analysed (module docstring)."""
    if not 0 <= min_share <= 1:
        raise ValueError(f"the smallest piece analysed is a share of the main tree between 0 and 1 (default "
                         f"{MIN_COMPONENT_SHARE}), got {min_share}")
    labels, sizes = component_labels(lumen)
    if sizes.size == 0:
        return Fragments(labels, sizes, 0, np.zeros(0, bool), min_share, grid)
    main = int(np.argmax(sizes)) + 1
    if ostium_mm is not None:
        # The piece nearest the ostium the user gave is the tree being analysed.
        ijk = np.argwhere(labels > 0)
        nearest = ijk[int(np.argmin(np.linalg.norm(grid.index_to_world(ijk) - np.asarray(ostium_mm, float), axis=1)))]
        main = int(labels[tuple(nearest)])
    analysed = sizes >= min_share * sizes[main - 1]
    analysed[main - 1] = True
    return Fragments(labels, sizes, main, analysed, min_share, grid)


def lesion_reasons(branch: CentrelineBranch, start_mm: float, end_mm: float, reference_radius_mm: np.ndarray,
                   fragments: Fragments, bridges: Sequence[Dict[str, Any]] = ()) -> List[str]:
    """Why the lesion from ``start_mm`` to ``end_mm`` on ``branch`` is not measured on an intact vessel
    (module docstring); [] when it is. ``reference_radius_mm``: per centreline point."""
    s = branch.arc_length_mm
    inside = (s >= start_mm) & (s <= end_mm)
    if not inside.any():
        inside[int(np.argmin(np.abs(s - 0.5 * (start_mm + end_mm))))] = True
    points = branch.points_mm[inside]
    radius = np.nan_to_num(np.asarray(reference_radius_mm, float)[inside])
    reasons = []
    grid = fragments.grid
    own = fragments.label_of(branch.points_mm)
    if own and own != fragments.main:
        reasons.append(f"fragment: the vessel lies on a piece of {int(fragments.sizes[own - 1])} voxels "
                       f"({100 * fragments.sizes[own - 1] / fragments.sizes[fragments.main - 1]:.0f} % of the main "
                       "tree) that is not connected to the main tree")
    others = fragments.distance_to_others_mm(own) if own else None
    if others is not None:
        distance, nearest = others
        at = _voxels(grid, points, distance.shape)
        wall_gap = distance[at] - radius
        k = int(np.argmin(wall_gap))
        if wall_gap[k] <= GAP_MM:
            label = int(nearest[tuple(a[k] for a in at)])
            reasons.append(f"gap: another piece of the reconstruction ({int(fragments.sizes[label - 1])} voxels) lies "
                           f"{max(float(wall_gap[k]), 0.0):.1f} mm from the vessel wall at {float(s[inside][k]):.1f} mm: "
                           "the vessel is broken here")
    for bridge in bridges:
        bridge_points = np.asarray(bridge.get("points_mm") or [], float).reshape(-1, 3)
        if not bridge_points.size:
            continue
        d = np.linalg.norm(points[:, None, :] - bridge_points[None, :, :], axis=2).min(axis=1)
        # The bridge runs along the vessel's path across the gap: within the vessel's healthy lumen.
        k = int(np.argmin(d - np.maximum(radius, float(min(grid.spacing_mm)))))
        if d[k] <= max(radius[k], float(min(grid.spacing_mm))):
            reasons.append(f"bridge: reconnection filled a {float(bridge.get('gap_mm', float('nan'))):.1f} mm gap here "
                           f"at {float(s[inside][k]):.1f} mm with a tube of radius "
                           f"{float(bridge.get('radius_mm', float('nan'))):.2f} mm (thinner than the vessel by "
                           "construction)")
            break
    return reasons
