"""Every reconstruction metric SDFCAR reports, defined once.

Volume metrics (binary prediction P and label L on the same grid):

* ``dice``  = 2|P∩L| / (|P| + |L|);  ``iou`` = |P∩L| / |P∪L|.
* ``cldice`` — centreline Dice of Shit et al. (CVPR 2021): with S(·) the skeleton
  (``skimage.morphology.skeletonize``, plus the connected pieces it erases whole — even widths, solid
  blocks — thinned again: ``skeleton``; the public code takes skimage's alone), topology precision
  Tprec = |S(P)∩L| / |S(P)|, topology sensitivity Tsens = |S(L)∩P| / |S(L)|,
  clDice = 2·Tprec·Tsens / (Tprec + Tsens); 1 for two empty volumes, as Dice.
* ``skeleton_dice`` — Dice of the two skeletons, 2|S(P)∩S(L)| / (|S(P)| + |S(L)|): what the public
  NeCA/SDF-CAR evaluation code reports under the name "clDice" (with skimage's skeleton alone); much
  stricter, as skeletons of slightly shifted tubes rarely share voxels.
* ``components`` — the number of 26-connected components, and ``largest_component_fraction`` the
  share of the voxels in the largest one (1 for a single piece; a coronary tree is one piece per
  ostium); ``components_label`` is the same count for the label.
* ``chamfer_l2_mm`` — symmetric Chamfer distance between the surface voxels (voxels of the shape
  with a 6-neighbour outside it) of P and L: the mean Euclidean distance (mm) from each surface
  voxel of one to the nearest surface voxel of the other, averaged over both directions.

Depth-aligned metrics (``depth_aligned_metrics``, for views with motion between them): P moved by linear
interpolation (threshold 0.5) along view 1's axis by the shift within ±3 mm, 0.25 mm apart, that maximises its Dice
with L (the smallest such shift on ties): ``depth_offset_mm`` (P + offset·axis lies on L), and ``cldice_depth_aligned``,
``dice_depth_aligned`` at that shift. When the heart moves between the acquisitions, the whole tree's depth along view
1's axis is seen only through view 1's magnification, and a shift of a millimetre halves the clDice of a thin tree
against itself: these say what the shape is worth apart from that one number.

Projection metrics (line-integral images of P and L for each view, ``projector.py``):

* ``re_error`` — relative reprojection error ||proj(P) − proj(L)||₂ / ||proj(L)||₂, averaged over views.
* ``re_mse`` — mean over views and pixels of ((proj(P) − proj(L)) / max proj(L))².
* ``reprojection_dice`` — per view, Dice of the projected prediction's mask (line integral >
  threshold) against the view's vessel mask.

Undefined values (for example Chamfer distance of an empty prediction) are NaN, written as null in JSON.
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage

from .geometry import CArmView, VolumeGrid
from .masks import binary_values_problem
from .settings import MASK_THRESHOLD_MM

NAN = float("nan")


def _bool(a: np.ndarray) -> np.ndarray:
    """A binary volume or mask as booleans: 0 is background, one other value vessel. A probability map, an image
    with NaN or negative values would have every non-zero voxel scored as vessel: refused, naming the fix."""
    a = np.asarray(a)
    if a.dtype == bool:
        return a
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"a volume to score must hold numbers (0 and one vessel value), got data type {a.dtype}")
    problem = binary_values_problem(a)
    if problem:
        raise ValueError(f"a volume to score {problem}: it must be binary (0 and one vessel value); threshold or fix "
                         "it first (e.g. occupancy >= 0.5)")
    return a != 0


def _check_same_shape(pred: np.ndarray, label: np.ndarray) -> None:
    if np.shape(pred) != np.shape(label):
        raise ValueError(f"prediction shape {np.shape(pred)} differs from label shape {np.shape(label)}; resample one onto the other's grid first")


def dice(pred: np.ndarray, label: np.ndarray) -> float:
    _check_same_shape(pred, label)
    p, l = _bool(pred), _bool(label)
    denominator = p.sum() + l.sum()
    return 1.0 if denominator == 0 else float(2.0 * np.logical_and(p, l).sum() / denominator)


def iou(pred: np.ndarray, label: np.ndarray) -> float:
    _check_same_shape(pred, label)
    p, l = _bool(pred), _bool(label)
    union = np.logical_or(p, l).sum()
    return 1.0 if union == 0 else float(np.logical_and(p, l).sum() / union)


def _without_upper_faces(piece: np.ndarray) -> np.ndarray:
    """``piece`` less its voxels whose +1 neighbour along some axis is background: one layer off one side, so
    that an even width becomes odd."""
    out = piece.copy()
    for axis in range(piece.ndim):
        ahead = np.zeros_like(piece)
        ahead[(slice(None),) * axis + (slice(0, -1),)] = piece[(slice(None),) * axis + (slice(1, None),)]
        out &= ahead
    return out


def skeleton(volume: np.ndarray) -> np.ndarray:
    """The medial skeleton (scikit-image's ``skeletonize``), every connected piece of ``volume`` in it.

    ``skeletonize`` erases some pieces whole: a tube two (or four) voxels across, a solid block, anything filling
    the array. Such a piece would count for nothing in clDice (a ghost of that width raised the precision). It is
    thinned again after one layer off one side (an even width made odd); a piece left empty still keeps its most
    interior voxel, so every piece is in the skeleton."""
    from skimage.morphology import skeletonize

    v = _bool(volume)
    if not v.any():
        return v
    skel = skeletonize(v).astype(bool)
    labels, _ = ndimage.label(v, structure=np.ones((3,) * v.ndim))
    kept = np.zeros(labels.max() + 1, bool)
    kept[labels[skel]] = True
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        if kept[k]:
            continue
        box = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        piece = labels[box] == k
        thin = skeletonize(_without_upper_faces(np.pad(piece, 1))).astype(bool)[(slice(1, -1),) * v.ndim] & piece
        if not thin.any():
            depth = ndimage.distance_transform_edt(np.pad(piece, 1))[(slice(1, -1),) * v.ndim]
            thin = np.zeros_like(piece)
            thin[np.unravel_index(int(np.argmax(np.where(piece, depth, -1.0))), piece.shape)] = True
        skel[box] |= thin
    return skel


def topology_precision_sensitivity(pred: np.ndarray, label: np.ndarray) -> Dict[str, float]:
    _check_same_shape(pred, label)
    p, l = _bool(pred), _bool(label)
    if not p.any() and not l.any():
        return {"tprec": 1.0, "tsens": 1.0}  # nothing predicted where there is nothing: agreement, as Dice says
    sp, sl = skeleton(p), skeleton(l)
    tprec = float(np.logical_and(sp, l).sum() / sp.sum()) if sp.any() else 0.0
    tsens = float(np.logical_and(sl, p).sum() / sl.sum()) if sl.any() else 0.0
    return {"tprec": tprec, "tsens": tsens}


def cldice(pred: np.ndarray, label: np.ndarray) -> float:
    t = topology_precision_sensitivity(pred, label)
    s = t["tprec"] + t["tsens"]
    return 0.0 if s == 0 else 2.0 * t["tprec"] * t["tsens"] / s


def skeleton_dice(pred: np.ndarray, label: np.ndarray) -> float:
    _check_same_shape(pred, label)
    sp, sl = skeleton(pred), skeleton(label)
    denominator = sp.sum() + sl.sum()
    return 1.0 if denominator == 0 else float(2.0 * np.logical_and(sp, sl).sum() / denominator)


def component_labels(volume: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """26-connected component labels (0 background) and the voxel count of each label 1..n.

    26-connectivity: diagonal voxel contacts along a thin oblique vessel are still one vessel."""
    labels, count = ndimage.label(_bool(volume), structure=np.ones((3, 3, 3), dtype=bool))
    return labels, np.bincount(labels.reshape(-1), minlength=count + 1)[1:]


def component_counts(volume: np.ndarray) -> Dict[str, float]:
    """Number of 26-connected components of ``volume`` and the share of its voxels in the largest (NaN if empty)."""
    _, sizes = component_labels(volume)
    count = sizes.size
    if count == 0:
        return {"components": 0, "largest_component_fraction": NAN}
    return {"components": int(count), "largest_component_fraction": float(sizes.max() / sizes.sum())}


def surface_voxels(volume: np.ndarray) -> np.ndarray:
    v = _bool(volume)
    return v & ~ndimage.binary_erosion(v, structure=ndimage.generate_binary_structure(3, 1), border_value=0)


def chamfer_l2_mm(pred: np.ndarray, label: np.ndarray, spacing_mm: Sequence[float]) -> float:
    _check_same_shape(pred, label)
    spacing = np.asarray(spacing_mm, dtype=float).reshape(-1)
    if spacing.size != np.ndim(pred) or not np.all(np.isfinite(spacing) & (spacing > 0)):
        raise ValueError(f"spacing_mm must be {np.ndim(pred)} positive numbers (one per axis, mm), got {spacing_mm!r}")
    sp, sl = surface_voxels(pred), surface_voxels(label)
    if not sp.any() or not sl.any():
        return NAN
    to_label = ndimage.distance_transform_edt(~sl, sampling=spacing_mm)
    to_pred = ndimage.distance_transform_edt(~sp, sampling=spacing_mm)
    return float(0.5 * (to_label[sp].mean() + to_pred[sl].mean()))


def volume_metrics(pred: np.ndarray, label: np.ndarray, spacing_mm: Sequence[float]) -> Dict[str, float]:
    _check_same_shape(pred, label)
    pred, label = _bool(pred), _bool(label)  # checked once: every measure below takes the booleans
    if pred.ndim != 3:
        raise ValueError(f"the volume metrics score 3-D volumes, got shape {pred.shape}; for one view's masks use dice "
                         "and cldice")
    t = topology_precision_sensitivity(pred, label)
    s = t["tprec"] + t["tsens"]
    return {
        "cldice": 0.0 if s == 0 else 2.0 * t["tprec"] * t["tsens"] / s,
        "tprec": t["tprec"],
        "tsens": t["tsens"],
        "skeleton_dice": skeleton_dice(pred, label),
        "dice": dice(pred, label),
        "iou": iou(pred, label),
        "chamfer_l2_mm": chamfer_l2_mm(pred, label, spacing_mm),
        **component_counts(pred),
        "components_label": component_counts(label)["components"],
        "voxels_predicted": int(_bool(pred).sum()),
        "voxels_label": int(_bool(label).sum()),
    }


DEPTH_SEARCH_MM = 3.0
DEPTH_STEP_MM = 0.25


def shift_volume(volume: np.ndarray, grid: VolumeGrid, shift_mm: Sequence[float]) -> np.ndarray:
    """A binary volume moved by ``shift_mm`` (world, LPS) on its grid (linear interpolation, threshold 0.5)."""
    to_index = np.linalg.inv(np.asarray(grid.ijk_to_lps_matrix(), float)[:3, :3])
    moved = ndimage.shift(_bool(volume).astype(np.float32), to_index @ np.asarray(shift_mm, float), order=1)
    return moved >= 0.5


def depth_aligned_metrics(pred: np.ndarray, label: np.ndarray, grid: VolumeGrid, axis: Sequence[float],
                          search_mm: float = DEPTH_SEARCH_MM, step_mm: float = DEPTH_STEP_MM) -> Dict[str, float]:
    """``depth_offset_mm``, ``cldice_depth_aligned`` and ``dice_depth_aligned`` (module docstring) along ``axis``."""
    _check_same_shape(pred, label)
    axis = np.asarray(axis, float)
    norm = float(np.linalg.norm(axis)) if axis.shape == (3,) else 0.0
    if not (math.isfinite(norm) and norm > 0):
        raise ValueError(f"the depth axis must be a finite non-zero 3-vector, got {axis.tolist()}")
    if not (search_mm > 0 and step_mm > 0 and step_mm <= search_mm):
        raise ValueError(f"the depth search needs 0 < step_mm <= search_mm, got step {step_mm} and search {search_mm}")
    axis = axis / norm
    steps = int(math.floor(search_mm / step_mm + 1e-9))
    shifts = sorted((k * step_mm for k in range(-steps, steps + 1)), key=lambda t: (abs(t), t))
    best_dice, best_shift, best_volume = -1.0, 0.0, _bool(pred)
    for t in shifts:
        moved = shift_volume(pred, grid, t * axis) if t else _bool(pred)
        d = dice(moved, label)
        if d > best_dice:
            best_dice, best_shift, best_volume = d, t, moved
    return {"depth_offset_mm": float(best_shift), "dice_depth_aligned": float(best_dice),
            "cldice_depth_aligned": float(cldice(best_volume, label))}


def mask_dice(a: np.ndarray, b: np.ndarray) -> float:
    return dice(a, b)


def reprojection_metrics(
    pred: np.ndarray,
    label: Optional[np.ndarray],
    grid: VolumeGrid,
    views: Sequence[CArmView],
    masks: Optional[Sequence[np.ndarray]] = None,
    mask_threshold_mm: float = MASK_THRESHOLD_MM,
) -> Dict[str, object]:
    """Projection metrics of ``pred`` against ``label`` (re_error, re_mse) and ``masks`` (Dice per view).

    With ``label`` None only the reprojection Dice against ``masks`` is computed; with ``masks``
    None the label's own simulated masks are used.
    """
    from .projector import project_volume

    pred_f = _bool(pred).astype(np.float32)
    pred_proj = [project_volume(pred_f, v, grid) if pred_f.any() else np.zeros(v.detector_shape, np.float32) for v in views]
    out: Dict[str, object] = {}
    if label is not None:
        label_f = _bool(label).astype(np.float32)
        label_proj = [project_volume(label_f, v, grid) for v in views]
        errors, mses = [], []
        for p, l in zip(pred_proj, label_proj):
            norm = float(np.linalg.norm(l))
            errors.append(float(np.linalg.norm(p - l) / norm) if norm > 0 else NAN)
            peak = float(l.max())
            mses.append(float(np.mean(((p - l) / peak) ** 2)) if peak > 0 else NAN)
        out["re_error"] = float(np.mean(errors))
        out["re_mse"] = float(np.mean(mses))
        if masks is None:
            masks = [l > mask_threshold_mm for l in label_proj]
    if masks is not None:
        if len(masks) != len(views):
            raise ValueError(f"{len(masks)} mask(s) for {len(views)} view(s); give one per view")
        for n, (m, view) in enumerate(zip(masks, views), start=1):
            if np.shape(m) != tuple(view.detector_shape):
                raise ValueError(f"the mask of view {n} has shape {np.shape(m)}, not the detector shape "
                                 f"{tuple(view.detector_shape)} of that view; give the mask drawn on that view's frame")
        out["reprojection_dice"] = [mask_dice(p > mask_threshold_mm, m) for p, m in zip(pred_proj, masks)]
    return out


def evaluate(
    pred: np.ndarray,
    label: np.ndarray,
    grid: VolumeGrid,
    views: Optional[Sequence[CArmView]] = None,
    masks: Optional[Sequence[np.ndarray]] = None,
) -> Dict[str, object]:
    """All volume metrics, plus projection metrics when ``views`` are given."""
    result: Dict[str, object] = dict(volume_metrics(pred, label, grid.spacing_mm))
    if views:
        result.update(reprojection_metrics(pred, label, grid, views, masks))
    return result

