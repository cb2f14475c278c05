"""The centreline re-placed on the masks' midlines (analysis/mask_centreline.py) against analytic tubes."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.analysis.centreline import CentrelineBranch, CentrelineTree
from SDFCARLib.analysis.mask_centreline import detector_jacobian, place_on_masks, runs_at_least
from SDFCARLib.analysis.phantoms import render_mask
from SDFCARLib.geometry import standard_geometry
from SDFCARLib.phantoms import Branch
from SDFCARLib.phantoms import CentrelineTree as PhantomTree

VIEWS = standard_geometry("lao30-rao30").views  # 512² at 0.278 mm, 60° apart
DIRECTION = np.array([1.0, 0.6, 0.3]) / np.linalg.norm([1.0, 0.6, 0.3])


def _perpendiculars(t):
    u = np.cross(t, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    return u, np.cross(t, u)


def _axis(length_mm=30.0, direction=DIRECTION, start=None, step_mm=0.25):
    s = np.arange(0.0, length_mm + 1e-9, step_mm)
    start = -0.5 * length_mm * direction if start is None else np.asarray(start, float)
    return start + s[:, None] * direction, s


def _masks(*axes, radius_mm=1.5):
    tree = PhantomTree([Branch(a, np.full(len(a), radius_mm), f"b{n}") for n, a in enumerate(axes)], "tubes")
    return [render_mask(tree, v) for v in VIEWS]


def _distance_to_line(points, start, direction):
    d = points - start
    return np.linalg.norm(d - (d @ direction)[:, None] * direction, axis=1)


def _wandering(axis, s, offset_mm=0.5, wander_mm=0.3, period_mm=8.0):
    """The axis moved as a segmented reconstruction's lumen is: a steady offset and a wander of a few mm."""
    u, w = _perpendiculars(DIRECTION)
    return axis + offset_mm * u + wander_mm * np.sin(2 * np.pi * s / period_mm)[:, None] * w


def test_the_jacobian_is_the_projection_s_derivative():
    p = np.array([[3.0, -2.0, 5.0]])
    jac = detector_jacobian(VIEWS[0], p)[0]
    step = np.array([0.01, -0.02, 0.015])
    r0, c0, _ = VIEWS[0].project(p)
    r1, c1, _ = VIEWS[0].project(p + step)
    moved_mm = np.array([(r1 - r0)[0], (c1 - c0)[0]]) * np.asarray(VIEWS[0].pixel_spacing_mm)
    np.testing.assert_allclose(jac @ step, moved_mm, rtol=1e-4, atol=1e-8)


def test_a_displaced_wandering_centreline_comes_back_onto_the_axis():
    axis, s = _axis()
    masks = _masks(axis)
    start = axis[0]
    off = _wandering(axis, s)
    tree = CentrelineTree([CentrelineBranch(0, off, np.full(len(s), 1.5))])
    placed, report = place_on_masks(tree, masks, VIEWS)
    inner = (s > 4.0) & (s < s[-1] - 4.0)  # the free-end caps keep the nearest measured shift
    before = _distance_to_line(off[inner], start, DIRECTION)
    after = _distance_to_line(placed.branches[0].points_mm[inner], start, DIRECTION)
    assert before.mean() > 0.5
    assert after.mean() < 0.06 and after.max() < 0.15, (after.mean(), after.max())
    # the wander's extra length is gone: the placed branch is as long as the axis it covers
    assert placed.branches[0].length_mm == pytest.approx(s[-1], rel=0.005)
    assert tree.branches[0].length_mm > 1.01 * s[-1]
    assert report[0].moved and report[0].measured_share > 0.6 and report[0].mean_shift_mm > 0.4


def test_a_centreline_on_the_axis_stays_there():
    axis, s = _axis()
    tree = CentrelineTree([CentrelineBranch(0, axis.copy(), np.full(len(s), 1.5))])
    placed, _ = place_on_masks(tree, _masks(axis), VIEWS)
    moved = np.linalg.norm(placed.branches[0].points_mm - axis, axis=1)
    # the masks' edges are nearest-pixel (0.278 mm): what remains is that noise, smoothed
    assert moved.mean() < 0.06 and moved.max() < 0.15, (moved.mean(), moved.max())
    assert placed.branches[0].length_mm == pytest.approx(s[-1], rel=0.002)


def test_a_side_branch_keeps_its_junction_and_both_branches_are_placed():
    main, s_main = _axis(36.0)
    junction = len(s_main) // 2
    u, w = _perpendiculars(DIRECTION)
    side_direction = (u + w + 0.5 * DIRECTION) / np.linalg.norm(u + w + 0.5 * DIRECTION)  # 62° from the main in both views
    side, s_side = _axis(20.0, side_direction, start=main[junction])
    masks = _masks(main, side)
    shift = 0.4 * _perpendiculars(DIRECTION)[1]
    tree = CentrelineTree([CentrelineBranch(0, main + shift, np.full(len(s_main), 1.5)),
                           CentrelineBranch(1, side + shift, np.full(len(s_side), 1.5), parent_id=0, parent_index=junction)])
    placed, _ = place_on_masks(tree, masks, VIEWS)
    parent, child = placed.branch(0), placed.branch(1)
    np.testing.assert_array_equal(child.points_mm[0], parent.points_mm[junction])
    far = np.abs(s_main - s_main[junction]) > 6.0
    inner = far & (s_main > 4.0) & (s_main < s_main[-1] - 4.0)
    assert _distance_to_line(parent.points_mm[inner], main[0], DIRECTION).mean() < 0.08
    distal = (s_side > 8.0) & (s_side < s_side[-1] - 4.0)
    assert _distance_to_line(child.points_mm[distal], side[0], side_direction).mean() < 0.08
    assert len(parent.points_mm) == len(s_main) and len(child.points_mm) == len(s_side)


def test_a_vessel_overlapping_in_one_view_does_not_pull_the_centreline():
    axis, s = _axis()
    masks = _masks(axis)
    # a wide vessel across the tube in view 1 only, centred 2 mm to one side: that view's midline moves
    row, col, _ = VIEWS[0].project(axis[len(s) // 2])
    rr, cc = np.mgrid[0:512, 0:512]
    overlap = np.hypot(rr - (row + 7.0), cc - col) < 14.0
    masks[0] = masks[0] | overlap
    tree = CentrelineTree([CentrelineBranch(0, axis.copy(), np.full(len(s), 1.5))])
    placed, report = place_on_masks(tree, masks, VIEWS)
    unguarded, _ = place_on_masks(tree, masks, VIEWS, max_width_change=np.inf)
    near = np.abs(s - s[len(s) // 2]) < 3.0
    assert _distance_to_line(unguarded.branches[0].points_mm[near], axis[0], DIRECTION).max() > 0.3  # the trap is real
    assert _distance_to_line(placed.branches[0].points_mm[near], axis[0], DIRECTION).max() < 0.1
    assert report[0].measured_share < 0.9


def _tube_with_neighbour_beside(neighbour_radius_in_tree_mm: float):
    """A 3 mm tube and, 10 mm away in depth, a 1.2 mm vessel that view 1 sees overlapping the tube's edge along
    its whole length; the masks of both, and the tree holding the neighbour at the radius given."""
    axis, s = _axis()
    ray = VIEWS[0].detector_direction
    beside = np.cross(DIRECTION, ray)
    beside /= np.linalg.norm(beside)
    neighbour = axis + 1.9 * beside + 10.0 * ray
    pair = PhantomTree([Branch(axis, np.full(len(s), 1.5), "tube"), Branch(neighbour, np.full(len(s), 0.6), "beside")], "pair")
    masks = [render_mask(pair, v) for v in VIEWS]
    tree = CentrelineTree([CentrelineBranch(0, axis.copy(), np.full(len(s), 1.5)),
                           CentrelineBranch(1, neighbour.copy(), np.full(len(s), neighbour_radius_in_tree_mm), tree_id=1)])
    return axis, s, masks, tree


def test_a_vessel_running_beside_in_one_view_does_not_pull_the_centreline():
    # Its mask merges with the tube's there and widens the running median with it, so the width rule cannot tell.
    axis, s, masks, tree = _tube_with_neighbour_beside(0.6)
    placed, _ = place_on_masks(tree, masks, VIEWS)
    unguarded, _ = place_on_masks(tree, masks, VIEWS, crowding_margin_mm=-np.inf)
    inner = (s > 4.0) & (s < s[-1] - 4.0)
    assert _distance_to_line(unguarded.branch(0).points_mm[inner], axis[0], DIRECTION).mean() > 0.5  # the trap is real
    after = _distance_to_line(placed.branch(0).points_mm[inner], axis[0], DIRECTION)
    assert after.max() < 0.15, after.max()


def test_a_neighbour_reconstructed_too_thin_still_guards_the_view():
    # As above, but the tree holds the neighbour at half its radius (a reconstruction's thin vessel comes out
    # thinner than its mask shows): the merged mask edge lies 0.5-1 mm (detector) outside the neighbour's
    # projected edge, so a margin of 0.5 mm lets that view pull the tube, and the default must not.
    axis, s, masks, tree = _tube_with_neighbour_beside(0.3)
    inner = (s > 4.0) & (s < s[-1] - 4.0)
    # (every measured point counted, however short its run: the margin's part alone)
    narrow, _ = place_on_masks(tree, masks, VIEWS, crowding_margin_mm=0.5, min_run_mm=0.0)
    assert _distance_to_line(narrow.branch(0).points_mm[inner], axis[0], DIRECTION).mean() > 0.5  # the trap is real
    placed, _ = place_on_masks(tree, masks, VIEWS)
    after = _distance_to_line(placed.branch(0).points_mm[inner], axis[0], DIRECTION)
    assert after.max() < 0.15, after.max()


def test_a_branch_seen_inside_the_vessel_leaves_the_view_measured():
    # A thin branch 8 mm behind the tube on view 1's rays (a reconstruction's ghost spur lies so): inside the
    # tube's edges in that view, it merges nothing, and the wandering centreline still comes back to the axis.
    axis, s = _axis()
    behind = axis + 8.0 * VIEWS[0].detector_direction
    off = _wandering(axis, s)
    tree = CentrelineTree([CentrelineBranch(0, off, np.full(len(s), 1.5)),
                           CentrelineBranch(1, behind, np.full(len(s), 0.3), tree_id=1)])
    placed, report = place_on_masks(tree, _masks(axis), VIEWS)
    inner = (s > 4.0) & (s < s[-1] - 4.0)
    after = _distance_to_line(placed.branch(0).points_mm[inner], axis[0], DIRECTION)
    assert after.mean() < 0.06 and after.max() < 0.15, (after.mean(), after.max())
    assert report[0].measured_share > 0.6


@pytest.mark.parametrize("foreshortening, measured", [(0.6, True), (0.8, False)])
def test_a_view_that_sees_the_vessel_end_on_does_not_measure_its_midline(foreshortening, measured):
    from SDFCARLib.analysis.mask_centreline import MAX_FORESHORTENING, midline_shifts, smooth_tangents

    ray, other_ray = VIEWS[0].detector_direction, VIEWS[1].detector_direction
    across = -(other_ray - (other_ray @ ray) * ray)  # turned away from view 2's ray: that view sees it nearly whole
    across /= np.linalg.norm(across)
    # a straight tube whose parallel-projection foreshortening in view 1 is 1 − √(1 − (t·d)²)
    along = np.sqrt(1.0 - (1.0 - foreshortening) ** 2)
    direction = along * ray + np.sqrt(1.0 - along ** 2) * across
    axis, s = _axis(20.0, direction)
    shifts = midline_shifts(axis, smooth_tangents(axis, 3.0), _masks(axis), VIEWS)
    inner = (s > 4.0) & (s < s[-1] - 4.0)
    assert (foreshortening < MAX_FORESHORTENING) == measured
    assert np.isfinite(shifts[inner]).all() if measured else np.isnan(shifts).all()


def test_bad_input_is_refused():
    axis, s = _axis()
    tree = CentrelineTree([CentrelineBranch(0, axis, np.full(len(s), 1.5))])
    masks = _masks(axis)
    with pytest.raises(ValueError, match="2 masks for 1 views"):
        place_on_masks(tree, masks, VIEWS[:1])
    with pytest.raises(ValueError, match="two views or more"):
        place_on_masks(tree, masks[:1], VIEWS[:1])


def test_analyse_volume_measures_on_the_masks_centreline_and_the_volume_s_sections():
    from SDFCARLib.analysis.phantoms import grid_around, straight_tube, voxelize_exact
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    true = straight_tube(30.0, 3.0, direction=DIRECTION)
    offset = 0.5 * _perpendiculars(DIRECTION)[0]
    # the volume's lumen lies 0.5 mm off the vessel the masks show, as a fit to segmented masks can
    shifted = straight_tube(30.0, 3.0, direction=DIRECTION, center_mm=offset)
    grid = grid_around(shifted.tree, 0.3, margin_mm=3.0)
    volume = voxelize_exact(shifted.tree, grid).astype(np.float32)
    masks = [render_mask(true.tree, v) for v in VIEWS]
    start = true.tree.branches[0].points[0]
    results = {on: analyse_volume(volume, grid, views=VIEWS, masks=masks, best_view=False, centreline_on_masks=on)
               for on in (False, True)}
    distance = {}
    for on, result in results.items():
        branch = result.tree.branches[0]
        inner = (branch.arc_length_mm > 5.0) & (branch.arc_length_mm < branch.length_mm - 5.0)
        distance[on] = _distance_to_line(branch.points_mm[inner], start, DIRECTION).mean()
        sections = result.profiles[0].sections.equivalent_diameter_mm[inner]
        assert np.nanmean(np.abs(sections - 3.0)) < 0.15  # the sections stay on the volume's own lumen
    assert distance[False] > 0.4 and distance[True] < 0.1, distance
    data = summary(results[True])
    assert data["settings"]["centreline_on_masks"] is True
    assert data["settings"]["centreline_placement"][0]["moved"]


def test_analyse_volume_refuses_the_masks_centreline_without_two_masks():
    from SDFCARLib.analysis.phantoms import grid_around, straight_tube, voxelize_exact
    from SDFCARLib.analysis.pipeline import analyse_volume

    tube = straight_tube(20.0, 3.0, direction=DIRECTION)
    grid = grid_around(tube.tree, 0.4)
    with pytest.raises(ValueError, match="needs the masks of two views or more"):
        analyse_volume(voxelize_exact(tube.tree, grid), grid, views=VIEWS, centreline_on_masks=True)


def test_a_lone_measured_point_inside_an_unmeasured_stretch_sets_no_shift():
    arc = np.arange(0.0, 10.0, 0.25)
    flags = np.zeros(len(arc), bool)
    flags[:8] = True  # 0–1.75 mm: a run of 1.75 mm
    flags[20] = True  # one point at 5 mm
    flags[30:34] = True  # 7.5–8.25 mm: 0.75 mm
    flags[-5:] = True  # 8.75–9.75 mm: exactly 1 mm
    kept = runs_at_least(flags, arc, 1.0)
    np.testing.assert_array_equal(np.flatnonzero(kept), np.r_[0:8, len(arc) - 5:len(arc)])
    np.testing.assert_array_equal(runs_at_least(flags, arc, 0.0), flags)
