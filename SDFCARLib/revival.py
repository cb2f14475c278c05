"""Revival: voxels under vessels that no view's rendering explains get a usable gradient back.

Why
    The field's occupancy is σ(z), z = −α·s (α = 50) for the SDF modes. Where the fit has driven a voxel
    far outside (occupancy ≲ 10⁻⁴), σ'(z) is thousands of times smaller than at the surface: the fit places a
    vessel there slowly, if at all, even where every view's mask and the frames ask for one. On the
    realistic suites about half of the true vessel a result misses lies on rays that are empty in every view
    at the end of the fit, inside the support and never excluded (bench/RESULTS.md §64a); those stretches
    saturate early and grow back only in the last steps (§64g). Off in every preset: on the realistic suites
    it measured level (§64c).

Method
    Once, part way through the fit (``revive_fraction`` of the steps; after the width check's exclusion when
    both fall on the same step):
    1. the current occupancy is rendered in every view; a mask pixel whose rendered path length is below
       ``EXPLAINED_PATH_MM`` is unexplained;
    2. a support voxel still in the fit (not excluded) whose centre projects onto an unexplained mask pixel
       (nearest pixel) in every view that sees it, at least one, and whose occupancy is below
       ``revive_occupancy``, is revived;
    3. a fixed offset is added to each revived voxel's logit for the rest of the fit, so that it starts again
       at ``revive_occupancy``; the field's own parameters then move it up or down with σ' about
       ``revive_occupancy`` instead of 10⁻⁴. The offset stays part of the field's value there (the raw field
       written out is s − offset / α).

Units: mm for path lengths; occupancies and logits are unitless.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from .geometry import CArmView, VolumeGrid

EXPLAINED_PATH_MM = 0.1  # a rendered path length below this leaves a mask pixel unexplained (a mask switches on near 0.2 mm)


def unexplained_in_every_view(line_integrals_mm: Sequence[np.ndarray], masks: Sequence[np.ndarray],
                              views: Sequence[CArmView], grid: VolumeGrid, voxels: np.ndarray) -> np.ndarray:
    """Per voxel of ``voxels`` (flat grid indices): True where every view that sees its centre sees it on a mask
    pixel whose rendered path length is below ``EXPLAINED_PATH_MM``, and at least one view sees it."""
    if not (len(line_integrals_mm) == len(masks) == len(views)):
        raise ValueError(f"{len(line_integrals_mm)} renderings and {len(masks)} masks for {len(views)} views")
    centres = grid.voxel_centers(voxels)
    every = np.ones(len(voxels), dtype=bool)
    seen_by_any = np.zeros(len(voxels), dtype=bool)
    for rendered, mask, view in zip(line_integrals_mm, masks, views):
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != tuple(view.detector_shape) or np.shape(rendered) != mask.shape:
            raise ValueError(f"mask {mask.shape} and rendering {np.shape(rendered)} must have the detector's shape "
                             f"{tuple(view.detector_shape)}")
        unexplained = mask & (np.asarray(rendered) < EXPLAINED_PATH_MM)
        r, c, _ = view.project(centres)
        ri, ci = np.rint(r), np.rint(c)
        seen = (ri >= 0) & (ri < mask.shape[0]) & (ci >= 0) & (ci < mask.shape[1])  # NaN (behind the source): unseen
        on_unexplained = np.zeros(len(voxels), dtype=bool)
        on_unexplained[seen] = unexplained[ri[seen].astype(np.int64), ci[seen].astype(np.int64)]
        every &= on_unexplained | ~seen
        seen_by_any |= seen
    return every & seen_by_any


def revival_offsets(logits: torch.Tensor, revive: np.ndarray, occupancy: float) -> torch.Tensor:
    """Per voxel, the offset that brings a revived voxel's logit up to ``occupancy``'s (0 elsewhere, and where
    the voxel already lies above it)."""
    if not 0.0 < occupancy < 0.5:
        raise ValueError(f"the revived occupancy must lie in (0, 0.5), got {occupancy}")
    target = math.log(occupancy / (1.0 - occupancy))
    chosen = torch.as_tensor(np.asarray(revive, dtype=bool), device=logits.device) & (logits < target)
    offsets = torch.zeros_like(logits)
    offsets[chosen] = target - logits[chosen]
    return offsets
