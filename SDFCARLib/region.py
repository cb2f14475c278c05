"""Where the reconstruction grid goes: on the region where the views see vessel.

The grid used to be a fixed 102 mm box (128³ × 0.8 mm) centred on the isocenter whenever the
geometry came from DICOM tags. The isocenter is where the C-arm rotates, not where the heart is:
on real runs the tree lies off-centre and the box cuts it. ``place_volume`` puts the grid on the
masks instead, keeping the voxel size the user or the protocol asked for.

Method (``locate_region``)
    1. A coarse search grid: a cube of ``search_mm`` (400 mm: larger than a chest, and than the
       depth over which two views' ghosts can meet — 240 mm on the real phantom pair of
       bench/RESULTS.md) centred on the isocenter at ``search_spacing_mm`` (3.125 mm: 128³ voxels,
       about a second).
    2. The strict visual hull there (``hull.visual_hull``, ``fov_aware=False``: every view sees
       the voxel and its centre falls on every mask), with each mask widened by ``dilate_mm``
       plus a coarse voxel's half diagonal (both referred to the isocenter), so that thin vessels
       that the acquisition misaligns by a millimetre or two still meet.
    3. Pieces of that hull holding less than ``min_piece_fraction`` of its voxels are dropped:
       chance meetings of noise specks, not the tree.
    4. The bounding box of what remains, plus ``margin_mm`` on every side (the coarse voxels'
       rounding, and the vessel ends that one view sees beyond where the masks meet), at the
       requested voxel size: ``shape = ceil(extent / spacing)``, centred on the box.
    5. A box of more than ``max_voxels`` (256³) voxels is refused with a ``RegionError`` that
       says why it happens (inconsistent views, noisy masks) and what to do (clean the masks,
       a larger voxel, or give the volume).

``mask_coverage`` says how much of each mask a grid can explain: the share of the mask's
pixels whose ray meets the grid's strict hull (within a voxel's shadow of a hull voxel's
projection). On a grid that cuts the tree, or with views the geometry misaligns, it falls below 1;
the command line records it in report.json for every run.

A GEOM.json may say ``"volume": "auto"`` (or omit the volume, or give
``{"auto": true, "spacing_mm": 0.5}``): ``read_geometry`` returns the geometry with a stand-in
grid and the ``AutoVolume`` request, which ``reconstruct`` resolves once the masks are known.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
from scipy import ndimage

from .geometry import CArmView, Geometry, GeometryError, VolumeGrid
from .hull import visual_hull
from .metrics import component_labels
from .projector import footprint_radius_px
from .settings import PAPER_SPACING_MM, PAPER_VOLUME_SHAPE, ReconstructionError

SEARCH_MM = 400.0
SEARCH_SPACING_MM = 3.125
DILATE_MM = 2.0
MARGIN_MM = 10.0
MAX_VOXELS = 256**3  # 16.8 M voxels: 67 MB per float volume; beyond it, something is wrong with the input
MIN_PIECE_FRACTION = 0.01

Spacing = Union[float, Sequence[float]]


class RegionError(ReconstructionError):
    """The grid cannot be placed on the masks; the message says why and what to do."""


@dataclass(frozen=True)
class Placement:
    """A placed grid and how it was found (for report.json)."""

    grid: VolumeGrid
    region_low_mm: Tuple[float, float, float]  # where the masks meet (before the margin), LPS
    region_high_mm: Tuple[float, float, float]
    margin_mm: float
    search_mm: float
    search_spacing_mm: float
    dilate_mm: float
    dropped_pieces: int
    notes: Tuple[str, ...] = ()

    def to_dict(self) -> Dict[str, Any]:
        return {
            "method": "bounding box of the strict visual hull of the widened masks on a coarse search grid, plus a "
                      "margin (SDFCARLib.region)",
            "grid": self.grid.to_dict(),
            "region_low_mm": [round(v, 2) for v in self.region_low_mm],
            "region_high_mm": [round(v, 2) for v in self.region_high_mm],
            "margin_mm": self.margin_mm, "search_mm": self.search_mm, "search_spacing_mm": self.search_spacing_mm,
            "dilate_mm": self.dilate_mm, "dropped_pieces": self.dropped_pieces, "notes": list(self.notes),
        }


def _cube(count: int) -> str:
    side = round(count ** (1 / 3))
    return f"{side}³" if side**3 == count else str(count)


def _spacing3(spacing_mm: Spacing) -> Tuple[float, float, float]:
    values = [float(spacing_mm)] * 3 if np.ndim(spacing_mm) == 0 else [float(v) for v in spacing_mm]
    if len(values) != 3 or not all(math.isfinite(v) and v > 0 for v in values):
        raise RegionError(f"the voxel size must be one positive number or three, got {spacing_mm!r}")
    return (values[0], values[1], values[2])


def locate_region(
    views: Sequence[CArmView],
    masks: Sequence[np.ndarray],
    spacing_mm: Spacing = PAPER_SPACING_MM,
    margin_mm: float = MARGIN_MM,
    max_voxels: int = MAX_VOXELS,
    search_mm: float = SEARCH_MM,
    search_spacing_mm: float = SEARCH_SPACING_MM,
    dilate_mm: float = DILATE_MM,
    min_piece_fraction: float = MIN_PIECE_FRACTION,
) -> Placement:
    """The grid on the region where the masks' back-projections meet (see the module docstring)."""
    spacing = _spacing3(spacing_mm)
    if len(views) != len(masks) or len(views) < 2:
        raise RegionError(f"placing the grid needs one mask per view and at least two views, got {len(masks)} "
                          f"mask(s) for {len(views)} view(s)")
    bool_masks = [np.asarray(m).astype(bool) for m in masks]
    n = int(round(search_mm / search_spacing_mm))
    search = VolumeGrid((n, n, n), (search_spacing_mm,) * 3)
    # The widening and a coarse voxel's half diagonal, referred to the isocenter (the projector's
    # footprint bound assumes the magnification of the search box's corner nearest the source,
    # twice the isocenter's at 320 mm, and would merge ghosts).
    reach_mm = dilate_mm + 0.5 * math.sqrt(3.0) * search_spacing_mm
    widen = [reach_mm * v.magnification / min(v.pixel_spacing_mm) for v in views]
    hull = visual_hull(bool_masks, views, search, margin_px=widen)
    if not hull.any():
        raise RegionError(
            "the masks' back-projections do not meet anywhere within "
            f"{search_mm:g} mm of the isocenter: the views are inconsistent with the masks; check that each mask "
            "belongs to its view (in the geometry's order), the views' angles (LAO/RAO, CRA/CAU signs) and that the images are not "
            "mirrored, or give the volume explicitly")
    labels, sizes = component_labels(hull)
    keep = sizes >= max(1.0, min_piece_fraction * sizes.sum())
    kept = np.concatenate([[False], keep])[labels]
    ijk = np.argwhere(kept)
    half = np.asarray(search.spacing_mm) / 2
    low = search.index_to_world(ijk.min(axis=0)) - half
    high = search.index_to_world(ijk.max(axis=0)) + half
    notes: List[str] = []
    edge = np.any(ijk.min(axis=0) == 0) or np.any(ijk.max(axis=0) == np.asarray(search.shape) - 1)
    if edge:
        notes.append(f"the masks meet up to the edge of the {search_mm:g} mm search box: the region may reach further "
                     "(inconsistent views or noisy masks are the likely cause)")
    centre = (low + high) / 2
    extent = (high - low) + 2 * float(margin_mm)
    shape = tuple(int(math.ceil(e / s - 1e-6)) for e, s in zip(extent, spacing))
    if int(np.prod(shape)) > max_voxels:
        raise RegionError(
            f"the masks meet in a region of {' × '.join(f'{e:.0f}' for e in extent)} mm (margin included), which "
            f"at {'/'.join(f'{s:g}' for s in spacing)} mm voxels needs {' × '.join(map(str, shape))} voxels, more than "
            f"{_cube(max_voxels)}: implausibly large for a coronary tree. Usual causes: masks full of noise or a "
            "segmented collimator edge (see the mask warnings), or views whose geometry does not match the images "
            "(wrong angles, swapped masks). Clean the masks, check the geometry, or give the volume explicitly "
            "(--volume-shape/--volume-center, or GEOM.json's volume) or a larger voxel size")
    grid = VolumeGrid(shape, spacing, tuple(float(c) for c in centre))
    return Placement(grid, tuple(float(v) for v in low), tuple(float(v) for v in high), float(margin_mm),
                     float(search_mm), float(search_spacing_mm), float(dilate_mm), int((~keep).sum()), tuple(notes))


def place_volume(
    views: Sequence[CArmView],
    masks: Sequence[np.ndarray],
    spacing_mm: Spacing = PAPER_SPACING_MM,
    margin_mm: float = MARGIN_MM,
    max_voxels: int = MAX_VOXELS,
) -> VolumeGrid:
    """The reconstruction grid on the masks' region, at ``spacing_mm`` voxels (see ``locate_region``)."""
    return locate_region(views, masks, spacing_mm, margin_mm, max_voxels).grid


def mask_coverage(masks: Sequence[np.ndarray], views: Sequence[CArmView], grid: VolumeGrid) -> List[float]:
    """Per view, the share of the mask's pixels that the grid's strict visual hull explains.

    A pixel is explained when it lies within one voxel's shadow radius (``footprint_radius_px``)
    of the projection of a hull voxel's centre, i.e. when its ray can meet the hull.
    """
    bool_masks = [np.asarray(m).astype(bool) for m in masks]
    hull = visual_hull(bool_masks, views, grid)
    centres = grid.voxel_centers(np.flatnonzero(hull.reshape(-1)))
    out = []
    for mask, view in zip(bool_masks, views):
        total = int(mask.sum())
        if total == 0:
            out.append(float("nan"))
            continue
        rows, cols = mask.shape
        hit = np.zeros(mask.shape, dtype=bool)
        if len(centres):
            r, c, _ = view.project(centres)
            r, c = np.rint(r), np.rint(c)
            inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
            hit[r[inside].astype(np.int64), c[inside].astype(np.int64)] = True
        if not hit.any():
            out.append(0.0)
            continue
        near = ndimage.distance_transform_edt(~hit) <= footprint_radius_px(view, grid)
        out.append(float((mask & near).sum()) / total)
    return out


# --- GEOM.json with an automatic volume ------------------------------------------------------------------
@dataclass(frozen=True)
class AutoVolume:
    """A request to place the grid on the masks, at this voxel size."""

    spacing_mm: Tuple[float, float, float] = (PAPER_SPACING_MM,) * 3
    margin_mm: float = MARGIN_MM


#: The grid a geometry with an automatic volume holds until the masks are known (never reconstructed on).
STAND_IN_VOLUME = VolumeGrid(PAPER_VOLUME_SHAPE, (PAPER_SPACING_MM,) * 3)


def auto_volume_request(volume: Any, where: str = "volume") -> Optional[AutoVolume]:
    """The ``AutoVolume`` a GEOM.json volume entry asks for, or None for an explicit grid."""
    if volume is None or volume == "auto":
        return AutoVolume()
    if isinstance(volume, dict) and volume.get("auto") is not None:
        if volume.get("auto") is not True:
            raise GeometryError(f"{where}.auto must be true (or leave out 'auto' and give shape and spacing_mm), "
                                f"got {volume.get('auto')!r}")
        unknown = sorted(set(volume) - {"auto", "spacing_mm", "margin_mm"})
        if unknown:
            raise GeometryError(f"{where} has unknown field(s) {', '.join(unknown)} next to auto; allowed: spacing_mm, "
                                "margin_mm (the shape and centre come from the masks)")
        try:
            spacing = _spacing3(volume.get("spacing_mm", PAPER_SPACING_MM))
        except RegionError as exc:
            raise GeometryError(f"{where}.spacing_mm: {exc}") from None
        margin = volume.get("margin_mm", MARGIN_MM)
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not margin >= 0:
            raise GeometryError(f"{where}.margin_mm must be a number of mm, 0 or more, got {margin!r}")
        return AutoVolume(spacing, float(margin))
    if isinstance(volume, str):
        raise GeometryError(f"{where} must be an object (shape, spacing_mm, center_mm) or \"auto\", got {volume!r}")
    return None


def read_geometry(path: Union[str, Path]) -> Tuple[Geometry, Optional[AutoVolume]]:
    """GEOM.json → (geometry, automatic-volume request or None).

    With a request the geometry's volume is ``STAND_IN_VOLUME``: place the grid on the masks
    (``locate_region``) before reconstructing.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise GeometryError(f"cannot read geometry file {path}: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise GeometryError(f"{path} is not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from exc
    if not isinstance(data, dict):
        return Geometry.load(path), None  # Geometry.load says what is wrong
    try:
        request = auto_volume_request(data.get("volume"))
    except GeometryError as exc:
        raise GeometryError(f"{path}: {exc}") from None
    if request is None:
        return Geometry.load(path), None
    try:
        geometry = Geometry.from_dict({**data, "volume": STAND_IN_VOLUME.to_dict()})
    except GeometryError as exc:
        raise GeometryError(f"{path}: {exc}") from None
    return geometry, request
