"""Filling in what every view shows and the result leaves out (SDFCARLib.unexplained_fill, optimiser.fill_unexplained),
on tubes whose masks and voxels are known exactly."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from SDFCARLib.analysis.phantoms import grid_around, render_mask, straight_tube, voxelize_exact
from SDFCARLib.connectivity import field_values
from SDFCARLib.geometry import Geometry, standard_geometry
from SDFCARLib.metrics import component_counts
from SDFCARLib.optimiser import fill_unexplained, fit_field, reprojected_masks
from SDFCARLib.phantoms import Branch, CentrelineTree
from SDFCARLib.settings import make_settings
from SDFCARLib.unexplained_fill import MIN_BLOB_MM2, unexplained_fill, unexplained_pixels

VIEWS = standard_geometry("lao30-rao30").views  # LAO 30 / RAO 30, 512² at 0.278 mm
SPACING_MM = 0.4


def _branch(start_mm, direction, length_mm, diameter_mm):
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    points = np.asarray(start_mm, float) + np.linspace(0.0, length_mm, int(length_mm) + 1)[:, None] * direction
    return Branch(points, np.full(len(points), diameter_mm / 2))


# a 3 mm parent along the patient and a 2 mm side branch leaving it at 65°, both steep to the views' epipolar planes
# (which hold the line between the sources, along x): a vessel along them is placed in depth by neither view
PARENT = _branch((0.0, 0.0, -12.0), (-0.5, 0.2, 1.0), 24.0, 3.0)
SIDE = _branch(PARENT.points[12], (0.8, 0.1, 1.0), 12.0, 2.0)


def _within(a, b, voxels):
    """Share of ``a``'s voxels within ``voxels`` voxels of ``b``."""
    return float((ndimage.distance_transform_edt(~b)[a] <= voxels).mean())


def _side_branch_case(extra=()):
    tree = CentrelineTree([PARENT, SIDE, *extra])
    grid = grid_around(tree, SPACING_MM)
    geometry = Geometry(grid, VIEWS)
    masks = [render_mask(tree, v) for v in VIEWS]
    parent = voxelize_exact(CentrelineTree([PARENT]), grid)
    side = voxelize_exact(CentrelineTree([SIDE]), grid) & ~parent
    return geometry, masks, parent, side


def test_a_side_branch_the_result_left_out_is_filled_in_from_both_views_unexplained_pixels():
    geometry, masks, parent, side = _side_branch_case()
    explained = reprojected_masks(parent, geometry)
    left = [unexplained_pixels(m, e, v) for m, e, v in zip(masks, explained, VIEWS)]
    assert all(p.any() and not (p & e).any() for p, e in zip(left, explained))  # the side branch's pixels only
    fill, info = unexplained_fill(parent, masks, explained, geometry)
    assert not (fill & parent).any() and info["fill_voxels"] == fill.sum() > 0
    assert _within(side, fill, 1.5) > 0.75  # most of the branch, bar where it leaves the parent's shadow
    # and nothing else: two views' hull of a tube is a rhombic prism around it, whose edges reach a radius (1 mm)
    # beyond the wall at 60° between the views
    assert _within(fill, side, 1.0 / SPACING_MM + 0.5) > 0.95
    # the result already holds it: nothing left to fill
    nothing, info = unexplained_fill(parent | side, masks, reprojected_masks(parent | side, geometry), geometry)
    assert not nothing.any() and info["candidate_voxels"] == 0


def test_a_crossing_of_two_different_vessels_left_unexplained_is_not_filled():
    """Each view shows a vessel the result does not explain, a 3 mm one in view 1 and a 1.5 mm one in view 2: their
    rays cross in a tube no view sees at one width. The width check leaves it out."""
    true_tube = straight_tube(24.0, 2.5, direction=(0.2, 0.3, 1.0), center_mm=(-8.0, 0.0, 0.0))
    def unexplained_tube(diameter_mm):
        return straight_tube(24.0, diameter_mm, direction=(0.2, 0.3, 1.0), center_mm=(8.0, 0.0, 0.0))
    grid = grid_around(CentrelineTree(true_tube.tree.branches + unexplained_tube(3.0).tree.branches), SPACING_MM)
    geometry = Geometry(grid, VIEWS)
    masks = [render_mask(true_tube.tree, v) | render_mask(unexplained_tube(d).tree, v) for v, d in zip(VIEWS, (3.0, 1.5))]
    result = voxelize_exact(true_tube.tree, grid)
    fill, info = unexplained_fill(result, masks, reprojected_masks(result, geometry), geometry)
    assert info["candidate_voxels"] > 0 and info["width_dropped_voxels"] == info["candidate_voxels"]
    assert not fill.any()
    # the same tube seen at one width in both views is a vessel: filled
    masks = [render_mask(true_tube.tree, v) | render_mask(unexplained_tube(2.0).tree, v) for v in VIEWS]
    fill, _ = unexplained_fill(result, masks, reprojected_masks(result, geometry), geometry)
    assert _within(voxelize_exact(unexplained_tube(2.0).tree, grid), fill, 1.5) > 0.9


def test_small_blobs_and_pixels_next_to_the_reprojection_stay_explained():
    view = VIEWS[0]
    mask = np.zeros(view.detector_shape, bool)
    explained = np.zeros_like(mask)
    mask[100:140, 100:110] = True  # a band; its reprojection one pixel narrower on each side: a border a pixel off
    explained[100:140, 101:109] = True
    mask[300:305, 300:305] = True  # 25 px: a speck, under MIN_BLOB_MM2 at 0.278 mm
    assert 25 * 0.278 ** 2 < MIN_BLOB_MM2
    mask[400:420, 200:210] = True  # 200 px nobody explains
    left = unexplained_pixels(mask, explained, view)
    assert left.sum() == 200 and left[400:420, 200:210].all()
    assert unexplained_pixels(mask, explained, view, unknown=mask).sum() == 0  # what a view cannot see says nothing
    with pytest.raises(ValueError, match="detector's shape"):
        unexplained_pixels(mask[:100], explained, view)
    with pytest.raises(ValueError, match="one of each per view"):
        unexplained_fill(np.zeros((4, 4, 4), bool), [mask], [explained, explained], Geometry(grid_around(
            CentrelineTree([PARENT]), SPACING_MM), VIEWS))


def test_the_fill_is_joined_to_the_tree_and_a_fill_that_stays_apart_is_dropped():
    """The branch is cut from the parent by a 2 mm gap the fill cannot reach (it lies in the parent's shadow in
    one view): the join bridges it. A 3 mm tube 20 mm away, unexplained in both views, joins nothing: dropped,
    so the result stays one piece."""
    far = _branch((20.0, 0.0, -10.0), (0.2, 0.3, 1.0), 20.0, 3.0)
    geometry, masks, parent, side = _side_branch_case(extra=(far,))
    occupancy = parent.astype(np.float32)
    settings = make_settings("fast", fill_unexplained=True, device="cpu")
    field = field_values(occupancy, settings.mode.field_kind, settings.field.alpha)
    before_far = occupancy.copy()
    kept, info = fill_unexplained(parent, occupancy, field, masks, geometry, None, settings)
    assert component_counts(kept)["components"] == 1 and (kept & parent).sum() == parent.sum()
    assert _within(side, kept, 1.5) > 0.9 and info["added_voxels"] == int((kept & ~parent).sum()) > 0
    far_voxels = voxelize_exact(CentrelineTree([far]), geometry.volume)
    assert not (kept & far_voxels).any() and info["apart_voxels"] > 0.5 * far_voxels.sum()
    added = kept & ~parent
    assert (occupancy[added] >= 0.5).all() and np.array_equal(occupancy[~added], before_far[~added])
    assert np.allclose(field[added], field_values(occupancy[added], settings.mode.field_kind, settings.field.alpha))
    assert all(len(b["points_mm"]) > 0 for b in info["bridges"])


def test_a_reconstruction_reports_the_fill_when_asked_and_not_otherwise(small_tree_case):
    geometry, masks = small_tree_case
    plain_settings = make_settings("fast", steps=40, device="cpu", fill_unexplained=False)
    fitted = fit_field(geometry, masks, plain_settings)  # one fit, finished both ways
    assert fitted.finished().report["unexplained_fill"] is None
    asked = fitted.finished(plain_settings.replace(fill_unexplained=True))
    report = asked.report["unexplained_fill"]
    assert asked.segmentation.any() and len(report["unexplained_pixels"]) == 2
    assert {"candidate_voxels", "width_dropped_voxels", "short_dropped_voxels", "fill_voxels", "added_voxels",
            "apart_voxels", "bridges", "seconds"} <= set(report)
    np.testing.assert_array_equal(asked.segmentation, asked.occupancy >= 0.5)  # what the outputs read
