"""Metrics on volumes whose answers are known by construction."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from SDFCARLib.io import json_compatible
from scipy.spatial import cKDTree

from SDFCARLib.geometry import CArmView, VolumeGrid
from SDFCARLib.settings import GROUND_TRUTH_METRICS
from SDFCARLib.metrics import (
    chamfer_l2_mm,
    cldice,
    depth_aligned_metrics,
    dice,
    evaluate,
    iou,
    reprojection_metrics,
    shift_volume,
    skeleton,
    skeleton_dice,
    surface_voxels,
    topology_precision_sensitivity,
    volume_metrics,
)

SHAPE = (24, 24, 32)


def tube(centre_xy, radius, k_range=(4, 28), shape=SHAPE) -> np.ndarray:
    """A straight tube along k with a round cross-section (voxel units)."""
    i, j = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    disc = (i - centre_xy[0]) ** 2 + (j - centre_xy[1]) ** 2 <= radius**2
    volume = np.zeros(shape, bool)
    volume[:, :, k_range[0] : k_range[1]] = disc[:, :, None]
    return volume


def box(lo, hi, shape=SHAPE) -> np.ndarray:
    volume = np.zeros(shape, bool)
    volume[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = True
    return volume


# --- overlap metrics ------------------------------------------------------------------------------------
def test_identical_volumes():
    a = tube((10, 10), 3)
    m = volume_metrics(a, a.copy(), (0.8, 0.8, 0.8))
    assert m["dice"] == 1.0 and m["iou"] == 1.0
    assert m["cldice"] == 1.0 and m["skeleton_dice"] == 1.0
    assert m["tprec"] == 1.0 and m["tsens"] == 1.0
    assert m["chamfer_l2_mm"] == 0.0
    assert m["voxels_predicted"] == m["voxels_label"] == int(a.sum())


def test_disjoint_volumes():
    a, b = box((2, 2, 2), (8, 8, 8)), box((12, 12, 12), (18, 18, 18))
    assert dice(a, b) == 0.0 and iou(a, b) == 0.0
    assert cldice(tube((5, 5), 2), tube((16, 16), 2)) == 0.0


def test_half_overlap_by_hand():
    # A = [0, 4)³, B = A shifted by 2 along i: |A ∩ B| = 2·4·4 = 32, |A| = |B| = 64, |A ∪ B| = 96.
    a, b = box((0, 0, 0), (4, 4, 4)), box((2, 0, 0), (6, 4, 4))
    assert dice(a, b) == pytest.approx(2 * 32 / 128)
    assert iou(a, b) == pytest.approx(32 / 96)
    # and the identity Dice = 2·IoU / (1 + IoU) for any pair
    c = tube((10, 11), 4)
    d = tube((12, 9), 3)
    assert dice(c, d) == pytest.approx(2 * iou(c, d) / (1 + iou(c, d)))


def test_empty_pair_counts_as_perfect_and_nonbinary_input_is_read_as_mask():
    empty = np.zeros(SHAPE)
    assert dice(empty, empty) == 1.0 and iou(empty, empty) == 1.0
    a = box((0, 0, 0), (4, 4, 4)).astype(np.float32) * 0.7  # any non-zero value is foreground
    assert dice(a, a > 0) == 1.0


# --- clDice and skeleton-Dice ------------------------------------------------------------------------------
def test_skeleton_of_a_tube_is_its_axis():
    a = tube((10, 10), 3)
    s = skeleton(a)
    ii, jj, kk = np.nonzero(s)
    assert s.sum() >= 20  # most of the 24-voxel length survives
    assert np.all(ii == 10) and np.all(jj == 10)


def test_cldice_thin_tube_inside_thick_tube_is_perfect():
    # B (radius 2, axis offset 1) lies inside A (radius 3): the skeleton of each lies inside the
    # other (A's axis is 1 voxel from B's), so Tprec = Tsens = 1 although the volumes differ.
    a, b = tube((10, 10), 3), tube((11, 10), 2)
    assert np.all(a[b])  # B ⊂ A
    t = topology_precision_sensitivity(b, a)
    assert t["tprec"] == 1.0 and t["tsens"] == 1.0
    assert cldice(b, a) == 1.0
    assert dice(b, a) < 0.7


def test_cldice_tube_with_axis_outside_the_other():
    # A thin (radius 2), B thick (radius 4) 3 voxels away: A's axis lies inside B (Tsens = 1),
    # B's axis does not lie inside A (Tprec = 0): clDice = 0 despite the large overlap.
    a, b = tube((10, 10), 2), tube((13, 10), 4)
    t = topology_precision_sensitivity(b, a)
    assert t["tsens"] == 1.0 and t["tprec"] == 0.0
    assert cldice(b, a) == 0.0
    assert dice(b, a) > 0.3


def test_cldice_half_length_tube():
    # Prediction = the first half of the label tube: Tprec = 1, Tsens ≈ 1/2, clDice ≈ 2/3.
    label = tube((10, 10), 3, k_range=(4, 28))
    pred = tube((10, 10), 3, k_range=(4, 16))
    t = topology_precision_sensitivity(pred, label)
    assert t["tprec"] == 1.0
    assert t["tsens"] == pytest.approx(0.5, abs=0.08)  # skeleton ends shorten by a voxel or two
    assert cldice(pred, label) == pytest.approx(2 * t["tprec"] * t["tsens"] / (t["tprec"] + t["tsens"]))
    assert cldice(pred, label) == pytest.approx(2 / 3, abs=0.06)


def test_one_voxel_shift_skeleton_dice_much_lower_than_cldice():
    a, b = tube((10, 10), 3), tube((11, 10), 3)
    assert cldice(b, a) == 1.0  # each axis lies inside the other tube
    assert skeleton_dice(b, a) < 0.1  # the two axes share no voxel
    assert skeleton_dice(a, a) == 1.0


def test_cldice_and_skeleton_dice_are_symmetric():
    a, b = tube((10, 10), 2, k_range=(2, 30)), tube((12, 10), 4, k_range=(8, 24))
    assert cldice(a, b) == pytest.approx(cldice(b, a))
    assert skeleton_dice(a, b) == pytest.approx(skeleton_dice(b, a))


def test_empty_prediction_scores_zero():
    label = tube((10, 10), 3)
    empty = np.zeros(SHAPE, bool)
    m = volume_metrics(empty, label, (1.0, 1.0, 1.0))
    assert m["dice"] == 0.0 and m["cldice"] == 0.0 and m["iou"] == 0.0 and m["skeleton_dice"] == 0.0
    assert math.isnan(m["chamfer_l2_mm"])


# --- Chamfer distance -------------------------------------------------------------------------------------------
def test_surface_voxels_of_a_box():
    cube = box((2, 2, 2), (8, 8, 8))
    surface = surface_voxels(cube)
    assert surface.sum() == 6**3 - 4**3  # all but the 4³ interior
    assert not surface[3:7, 3:7, 3:7].any()


@pytest.mark.parametrize("k", [1, 3])
@pytest.mark.parametrize("axis, spacing", [(0, (0.5, 1.0, 2.0)), (2, (0.5, 1.0, 2.0)), (1, (0.8, 0.8, 0.8))])
def test_chamfer_of_parallel_plates_is_the_shift(k, axis, spacing):
    # One-voxel-thick plates: every voxel is a surface voxel, and its nearest neighbour in the
    # shifted plate is the same voxel k steps along the normal: Chamfer = k · spacing exactly.
    lo, hi = [4, 4, 4], [20, 20, 20]
    lo[axis], hi[axis] = 6, 7
    a = box(lo, hi)
    lo[axis], hi[axis] = 6 + k, 7 + k
    b = box(lo, hi)
    assert chamfer_l2_mm(a, b, spacing) == pytest.approx(k * spacing[axis])
    assert chamfer_l2_mm(b, a, spacing) == pytest.approx(k * spacing[axis])


@pytest.mark.parametrize("shift", [(2, 0, 0), (1, 2, 3)])
def test_chamfer_of_shifted_cube_against_brute_force(shift):
    spacing = (0.5, 1.0, 2.0)
    a = box((4, 4, 4), (12, 12, 12))
    b = box(tuple(4 + s for s in shift), tuple(12 + s for s in shift))
    # independent computation: nearest-neighbour distances between surface point clouds
    pa = np.argwhere(surface_voxels(a)) * spacing
    pb = np.argwhere(surface_voxels(b)) * spacing
    expected = 0.5 * (cKDTree(pb).query(pa)[0].mean() + cKDTree(pa).query(pb)[0].mean())
    assert chamfer_l2_mm(a, b, spacing) == pytest.approx(expected, rel=1e-9)
    assert 0 < expected <= np.linalg.norm(np.multiply(shift, spacing))


def test_chamfer_of_concentric_spheres():
    # surfaces of radius 6 and 9 voxels (1 mm): every surface point is ≈ 3 mm from the other
    shape = (32, 32, 32)
    grid = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), axis=-1)
    r = np.linalg.norm(grid - 15.5, axis=-1)
    assert chamfer_l2_mm(r <= 6, r <= 9, (1.0, 1.0, 1.0)) == pytest.approx(3.0, abs=0.5)


# --- projection metrics --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def projection_case():
    grid = VolumeGrid((16, 16, 16), (1.0, 1.0, 1.0))
    views = [CArmView(a, 0.0, 1000.0, 750.0, (1.0, 1.0), (32, 32)) for a in (30.0, -30.0)]
    label = np.zeros(grid.shape, bool)
    label[4:12, 7:9, 6:10] = True
    return grid, views, label


def test_reprojection_of_label_against_itself(projection_case):
    grid, views, label = projection_case
    m = reprojection_metrics(label, label, grid, views)
    assert m["re_error"] == 0.0 and m["re_mse"] == 0.0
    assert m["reprojection_dice"] == [1.0, 1.0]


def test_reprojection_of_empty_prediction(projection_case):
    # ||0 − L|| / ||L|| = 1 exactly; reMSE = mean((L / max L)²); no mask pixel is reproduced.
    grid, views, label = projection_case
    from SDFCARLib.projector import project_volume

    m = reprojection_metrics(np.zeros_like(label), label, grid, views)
    assert m["re_error"] == pytest.approx(1.0)
    expected = np.mean([np.mean((p / p.max()) ** 2) for p in (project_volume(label, v, grid) for v in views)])
    assert m["re_mse"] == pytest.approx(expected, rel=1e-5)
    assert m["reprojection_dice"] == [0.0, 0.0]


def test_reprojection_dice_against_given_masks(projection_case):
    grid, views, label = projection_case
    masks = [np.zeros(v.detector_shape, bool) for v in views]
    m = reprojection_metrics(label, None, grid, views, masks=masks)
    assert set(m) == {"reprojection_dice"} and m["reprojection_dice"] == [0.0, 0.0]
    with pytest.raises(ValueError, match=r"the mask of view 2 has shape \(10, 10\), not the detector shape"):
        reprojection_metrics(label, None, grid, views, masks=[masks[0], np.zeros((10, 10), bool)])
    with pytest.raises(ValueError, match="1 mask\\(s\\) for 2 view\\(s\\)"):
        reprojection_metrics(label, None, grid, views, masks=masks[:1])


def test_evaluate_reports_every_metric_as_strict_json(projection_case):
    grid, views, label = projection_case
    result = evaluate(np.zeros_like(label), label, grid, views)
    assert set(GROUND_TRUTH_METRICS) <= set(result)
    text = json.dumps(json_compatible(result), allow_nan=False)  # NaN (empty Chamfer) → null
    assert json.loads(text)["chamfer_l2_mm"] is None
    assert json_compatible({"a": [np.float32(1.5), float("inf")], "b": np.int64(3)}) == {"a": [1.5, None], "b": 3}


# --- bad input ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("metric", [dice, iou, cldice, skeleton_dice])
def test_mismatched_shapes_are_rejected(metric):
    with pytest.raises(ValueError, match="shape"):
        metric(np.zeros((4, 4, 4)), np.zeros((4, 4, 5)))


def test_mismatched_shapes_are_rejected_by_chamfer_and_summary():
    with pytest.raises(ValueError, match="resample"):
        chamfer_l2_mm(np.zeros((4, 4, 4)), np.zeros((5, 4, 4)), (1, 1, 1))
    with pytest.raises(ValueError, match="shape"):
        volume_metrics(np.zeros((4, 4, 4)), np.zeros((5, 4, 4)), (1, 1, 1))


# --- depth-aligned metrics ------------------------------------------------------------------------------
def test_depth_aligned_metrics_find_a_whole_tree_shifted_along_the_axis():
    """A thin tube moved 1.5 mm along an oblique axis scores low as it is and perfectly once moved back."""
    grid = VolumeGrid((40, 40, 40), (0.5, 0.5, 0.5), (0.0, 0.0, 0.0))
    label = np.zeros(grid.shape, bool)
    label[:, 18:21, 19:21] = True  # a tube along i, 1–1.5 mm across
    axis = np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0)  # across the tube, oblique to the grid
    moved = shift_volume(label, grid, 1.5 * axis)
    assert cldice(moved, label) < 0.2
    out = depth_aligned_metrics(moved, label, grid, axis)
    assert out["depth_offset_mm"] == pytest.approx(-1.5, abs=0.26)
    assert out["dice_depth_aligned"] > 0.9 and out["cldice_depth_aligned"] > 0.9


def test_depth_aligned_metrics_of_an_aligned_result_shift_nothing():
    grid = VolumeGrid(SHAPE, (0.8, 0.8, 0.8), (0.0, 0.0, 0.0))
    label = tube((12, 12), 2)
    out = depth_aligned_metrics(label, label, grid, (1.0, 0.0, 0.0))
    assert out == {"depth_offset_mm": 0.0, "dice_depth_aligned": 1.0, "cldice_depth_aligned": 1.0}


@pytest.mark.parametrize("axis, search, step, words", [((0, 0, 0), 3.0, 0.25, "non-zero"),
                                                        ((1, 0, 0), 3.0, 0.0, "step"),
                                                        ((1, 0, 0), 0.1, 0.25, "step")])
def test_depth_aligned_metrics_reject_a_bad_search(axis, search, step, words):
    grid = VolumeGrid(SHAPE, (0.8, 0.8, 0.8), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=words):
        depth_aligned_metrics(tube((12, 12), 2), tube((12, 12), 2), grid, axis, search, step)


# --- pieces scikit-image's skeletonize erases, and volumes that are no masks -------------------------------------
@pytest.mark.parametrize("width", [1, 2, 3, 4])
def test_a_tube_of_any_width_is_in_its_skeleton_and_scores_itself_perfectly(width):
    tube_ = np.zeros(SHAPE, bool)
    tube_[4:28, 10:10 + width, 10:10 + width] = True  # skimage's skeletonize erases the even widths whole
    assert skeleton(tube_).sum() >= 18  # its axis, less a voxel or two at the ends
    assert cldice(tube_, tube_) == 1.0


def test_an_erased_ghost_costs_precision():
    label = tube((6, 6), 3)
    ghost = np.zeros(SHAPE, bool)
    ghost[4:28, 16:18, 16:18] = True  # two voxels across, away from the label
    t = volume_metrics(label | ghost, label, (1.0, 1.0, 1.0))
    assert t["tprec"] < 0.6 and t["tsens"] == 1.0  # the ghost's axis counts (it counted for nothing before)
    everything = np.ones((10, 10, 10), bool)
    assert cldice(everything, everything) == 1.0
    empty = np.zeros(SHAPE, bool)
    assert cldice(empty, empty) == 1.0 == dice(empty, empty)  # one convention for an empty pair


@pytest.mark.parametrize("volume, words", [
    (lambda l: l * 0.3 + 0.01, "must be binary"),
    (lambda l: np.where(l, np.nan, 0.0), "NaN or infinite"),
    (lambda l: -l.astype(float), "must be binary"),
    (lambda l: l.astype(str), "must hold numbers"),
])
def test_a_volume_that_is_no_mask_is_refused(volume, words):
    label = tube((10, 10), 3)
    with pytest.raises(ValueError, match=words):
        dice(volume(label), label)
    with pytest.raises(ValueError, match=words):
        volume_metrics(volume(label), label, (1.0, 1.0, 1.0))


def test_the_volume_metrics_name_a_2d_input_and_a_bad_spacing():
    label = tube((10, 10), 3)
    with pytest.raises(ValueError, match="score 3-D volumes"):
        volume_metrics(label[:, :, 10], label[:, :, 10], (1.0, 1.0))
    for spacing in ((0.0, 0.0, 0.0), (-1.0, 1.0, 1.0), (1.0, 1.0)):
        with pytest.raises(ValueError, match="spacing_mm must be 3 positive numbers"):
            chamfer_l2_mm(label, label, spacing)
