"""Width agreement of the views (SDFCARLib.width_agreement) on tubes whose projected widths are known."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from SDFCARLib.analysis.phantoms import grid_around, render_mask, straight_tube, voxelize_exact
from SDFCARLib.geometry import Geometry, standard_geometry
from SDFCARLib.metrics import component_counts
from SDFCARLib.phantoms import Branch, CentrelineTree
from SDFCARLib.settings import ReconstructionError, make_settings
from SDFCARLib.width_agreement import (centreline_half_width_px, disagreeing_pieces, half_widths_mm,
                                       local_thickness_px, open_ends_half_width_px, width_agreement)

VIEWS = standard_geometry("lao30-rao30").views  # LAO 30 / RAO 30, 512² at 0.278 mm
AXIS = (0.2, 0.3, 1.0)  # along the patient, little foreshortened in either view


def _tube(diameter_mm, x_mm=0.0):
    return straight_tube(24.0, diameter_mm, direction=AXIS, center_mm=(x_mm, 0.0, 0.0))


def _interior(tube, trim=4):
    return tube.tree.branches[0].points[trim:-trim]


def test_half_width_map_of_a_band_is_its_half_width_everywhere_near_it():
    mask = np.zeros((60, 80), bool)
    mask[20:31, 5:75] = True  # 11 pixels across: the centre row is 6 pixels from the outside
    half = centreline_half_width_px(mask)
    assert half[25, 40] == pytest.approx(6.0)
    assert half[21, 40] == pytest.approx(6.0)  # read at the nearest centreline pixel, not where it stands
    assert half[50, 40] == pytest.approx(6.0)  # outside too: the nearest vessel's width
    assert not centreline_half_width_px(np.zeros((10, 10), bool)).any()


def test_local_thickness_reads_a_bands_half_width_up_to_its_free_end():
    mask = np.zeros((60, 80), bool)
    mask[20:31, 5:75] = True
    thickness = local_thickness_px(mask)
    assert thickness[25, 40] == pytest.approx(6.0) and thickness[21, 40] == pytest.approx(6.0)
    assert thickness[50, 40] == pytest.approx(6.0)  # outside: the nearest covered pixel's
    # the band's end: its cap lies in the disks of the band behind it; the skeleton's last pixels read less
    assert thickness[20:31, 5].min() == pytest.approx(6.0)
    assert centreline_half_width_px(mask)[20:31, 5].max() < 6.0
    assert not local_thickness_px(np.zeros((10, 10), bool)).any()


def test_local_thickness_of_a_disk_is_its_radius_and_of_two_bands_each_ones():
    rows, cols = np.mgrid[0:81, 0:81]
    disk = (rows - 40) ** 2 + (cols - 40) ** 2 <= 15 ** 2
    assert np.abs(local_thickness_px(disk)[disk] - 16.0).max() <= 1.0  # 15 px to the edge: 16 to the first pixel out
    bands = np.zeros((80, 80), bool)
    bands[10:31, 5:75] = True  # 21 px across: 11
    bands[50:55, 5:75] = True  # 5 px across: 3
    thickness = local_thickness_px(bands)
    assert thickness[20, 40] == pytest.approx(11.0) and thickness[52, 40] == pytest.approx(3.0)


def test_open_ends_leave_a_tapered_tips_cap_unread_and_read_the_rest():
    rows, cols = np.mgrid[0:60, 0:100]
    half_px = np.where(cols < 60, 6.0, 6.0 * (90 - cols) / 30.0)  # a band narrowing to a point over 30 px
    mask = (np.abs(rows - 30) <= half_px) & (cols >= 5) & (cols <= 90)
    plain, open_ends = centreline_half_width_px(mask), open_ends_half_width_px(mask)
    assert open_ends[30, 30] == pytest.approx(plain[30, 30]) == pytest.approx(7.0)
    tip = mask & (cols >= 85)
    assert plain[tip].max() < 0.75 * 7.0 and np.isnan(open_ends[tip]).all()  # the thin tip: no width of its own
    assert np.isfinite(open_ends[mask & (cols <= 60)]).mean() > 0.9


def test_the_half_width_measure_is_checked():
    tube = _tube(3.0)
    with pytest.raises(ValueError, match="half-width measure"):
        width_agreement([render_mask(tube.tree, v) for v in VIEWS], Geometry(grid_around(tube.tree, 0.4), VIEWS),
                        _interior(tube), measure="edges")
    with pytest.raises(ReconstructionError, match="width_agreement_measure"):
        make_settings("fast", width_agreement_measure="edges")


@pytest.mark.parametrize("diameter_mm", [1.5, 3.0])
def test_each_view_reads_a_tubes_radius_at_its_depth(diameter_mm):
    tube = _tube(diameter_mm)
    points = _interior(tube)
    for view, half_width_px in itertools.product(VIEWS, (centreline_half_width_px, local_thickness_px)):
        half = half_widths_mm(half_width_px(render_mask(tube.tree, view)), view, points)
        pixel_at_depth_mm = view.pixel_spacing_mm[0] * view.sod_mm / view.sid_mm
        # the distance map counts whole pixels from the centre pixel: within a pixel of the radius
        assert np.abs(half - diameter_mm / 2).max() <= pixel_at_depth_mm + 1e-6
    for measure in ("centreline", "thickness", "open_ends", "axis"):
        agreement = width_agreement([render_mask(tube.tree, v) for v in VIEWS],
                                    Geometry(grid_around(tube.tree, 0.4), VIEWS), points, measure)
        assert np.nanmedian(agreement) >= 0.8 and np.isfinite(agreement).mean() >= 0.8


def test_a_piece_seen_with_different_widths_is_removed_and_a_true_one_kept():
    true_tube, ghost = _tube(2.5, x_mm=-8.0), _tube(2.5, x_mm=8.0)
    both = CentrelineTree(true_tube.tree.branches + ghost.tree.branches)
    grid = grid_around(both, 0.4)
    segmentation = voxelize_exact(both, grid)
    # view 1 shows the ghost's place as a 3 mm vessel, view 2 as a 1.5 mm one: agreement 0.5 there
    masks = [render_mask(true_tube.tree, v) | render_mask(_tube(width, x_mm=8.0).tree, v) for v, width in zip(VIEWS, (3.0, 1.5))]
    geometry = Geometry(grid, VIEWS)
    truth_only = voxelize_exact(true_tube.tree, grid)

    kept, info = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7)
    assert info["removed_pieces"] >= 1 and info["removed_voxels"] == int((segmentation & ~kept).sum())
    assert not (kept & ~truth_only).any()  # nothing of the ghost's tube left
    assert (kept & truth_only).sum() == truth_only.sum()  # the true tube whole
    assert min(info["median_agreement"]) == pytest.approx(0.5, abs=0.1)

    unchanged, loose = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.4)
    assert loose["removed_voxels"] == 0 and np.array_equal(unchanged, segmentation)


def test_a_piece_a_view_could_not_see_is_not_judged_by_it():
    true_tube, hidden = _tube(1.2, x_mm=-8.0), _tube(2.5, x_mm=8.0)
    both = CentrelineTree(true_tube.tree.branches + hidden.tree.branches)
    grid = grid_around(both, 0.4)
    segmentation = voxelize_exact(both, grid)
    geometry = Geometry(grid, VIEWS)
    # view 2's collimator covers the second tube: its mask is empty there, and that says nothing (read as it is,
    # the nearest centreline there is the thin tube's, and the hidden tube looks a ghost of widths 1.2 and 2.5 mm)
    behind_blade = render_mask(_tube(6.0, x_mm=8.0).tree, VIEWS[1])
    masks = [render_mask(both, VIEWS[0]), render_mask(both, VIEWS[1]) & ~behind_blade]
    unknown = [None, behind_blade & ~masks[1]]
    cut, _ = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7)
    assert (segmentation & ~cut).sum() > 0.5 * voxelize_exact(hidden.tree, grid).sum()  # taken as a ghost
    kept, info = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7, unknown=unknown)
    assert np.array_equal(kept, segmentation) and info["removed_pieces"] == 0
    agreement = width_agreement(masks, geometry, _interior(hidden), unknown=unknown)
    assert np.isnan(agreement).mean() > 0.9  # unread where view 2 did not look
    with pytest.raises(ValueError, match="unknown-pixel images"):
        width_agreement(masks, geometry, _interior(hidden), unknown=unknown[:1])


def test_with_three_views_a_vessel_widened_in_one_view_by_a_crossing_is_kept_and_a_ghost_still_goes():
    """``views="best_pair"``: a true tube whose shadow in the third view is widened (a vessel running across it there)
    agrees in the other two views and is kept; a ghost the three views see at three different widths is removed;
    with two views the choice changes nothing."""
    import dataclasses

    views = VIEWS + (dataclasses.replace(VIEWS[0], primary_deg=0.0, secondary_deg=30.0),)  # AP cranial 30
    true_tube, ghost = _tube(2.5, x_mm=-8.0), _tube(2.5, x_mm=8.0)
    both = CentrelineTree(true_tube.tree.branches + ghost.tree.branches)
    grid = grid_around(both, 0.4)
    segmentation = voxelize_exact(both, grid)
    truth_only = voxelize_exact(true_tube.tree, grid)
    geometry = Geometry(grid, views)
    # the true tube: 2.5 mm in views 1 and 2, 5 mm wide in view 3; the ghost's place: 3, 1.5 and 0.8 mm
    masks = [render_mask(_tube(true_width, x_mm=-8.0).tree, v) | render_mask(_tube(ghost_width, x_mm=8.0).tree, v)
             for v, true_width, ghost_width in zip(views, (2.5, 2.5, 5.0), (3.0, 1.5, 0.8))]

    every_view, _ = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7)
    assert (every_view & truth_only).sum() < 0.5 * truth_only.sum()  # every view's: the true tube read as a ghost
    kept, info = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7, views="best_pair")
    assert info["views"] == "best_pair"
    assert (kept & truth_only).sum() == truth_only.sum()  # the true tube whole
    assert not (kept & ~truth_only).any()  # the ghost gone: no two views agree on its width
    agreement = width_agreement(masks, geometry, _interior(true_tube), views="best_pair")
    assert np.median(agreement) >= 0.8 and np.median(width_agreement(masks, geometry, _interior(true_tube))) < 0.6

    pair = Geometry(grid, views[:2])
    assert np.array_equal(width_agreement(masks[:2], pair, _interior(ghost), views="best_pair"),
                          width_agreement(masks[:2], pair, _interior(ghost)))
    with pytest.raises(ValueError, match="choose one of all, best_pair"):
        width_agreement(masks, geometry, _interior(ghost), views="median")
    with pytest.raises(ReconstructionError, match="width_agreement_views"):
        make_settings("fast", width_agreement_views="median")


def test_the_axis_measure_keeps_a_vessel_merged_with_a_neighbour_in_one_view_and_removes_a_ghost():
    """``measure="axis"``: two parallel tubes that view 2 sees as one wide band (each 2.5 mm, the band 4.7 mm) read
    the band's half-width at the nearest 2D centreline, and both go as ghosts; read at their own axes' projections
    they agree and stay. A ghost seen at 3 and 1.5 mm still goes."""
    first = np.array([-6.0, 0.0, 0.0])
    # behind the first along view 2's rays, 2.2 mm to its side
    second = first + 16.0 * VIEWS[1].detector_direction + 2.2 * VIEWS[1].column_direction
    tubes = [straight_tube(24.0, 2.5, direction=AXIS, center_mm=tuple(c)) for c in (first, second)]
    both = CentrelineTree(tubes[0].tree.branches + tubes[1].tree.branches)
    grid = grid_around(both, 0.4)
    segmentation = voxelize_exact(both, grid)
    masks = [render_mask(both, v) for v in VIEWS]
    assert [component_counts(m[None])["components"] for m in masks] == [2, 1]  # apart in view 1, one band in view 2
    geometry = Geometry(grid, VIEWS)

    read_at_centreline, _ = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7)
    assert read_at_centreline.sum() < 0.5 * segmentation.sum()
    kept, info = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7, measure="axis")
    assert np.array_equal(kept, segmentation) and info["measure"] == "axis" and min(info["median_agreement"]) >= 0.7
    on_axis = width_agreement(masks, geometry, _interior(tubes[1]), measure="axis")
    assert np.median(on_axis) >= 0.8 and np.median(width_agreement(masks, geometry, _interior(tubes[1]))) < 0.6

    true_tube, ghost = _tube(2.5, x_mm=-8.0), _tube(2.5, x_mm=8.0)
    pair = CentrelineTree(true_tube.tree.branches + ghost.tree.branches)
    grid = grid_around(pair, 0.4)
    masks = [render_mask(true_tube.tree, v) | render_mask(_tube(width, x_mm=8.0).tree, v) for v, width in zip(VIEWS, (3.0, 1.5))]
    truth_only = voxelize_exact(true_tube.tree, grid)
    kept, _ = disagreeing_pieces(voxelize_exact(pair, grid), masks, Geometry(grid, VIEWS), min_ratio=0.7, measure="axis")
    assert np.array_equal(kept, truth_only)
    with pytest.raises(ReconstructionError, match="'open_ends' or 'axis'"):
        make_settings("fast", width_agreement_measure="edges")


def _segment(start_mm, end_mm, diameter_mm):
    points = np.linspace(start_mm, end_mm, 13)
    return Branch(points, np.full(len(points), diameter_mm / 2))


def test_keep_connected_keeps_a_ghost_bridge_and_peels_a_ghost_spur():
    left = _segment((-8.0, 0.0, -12.0), (-8.0, 0.0, 12.0), 2.5)
    right = _segment((8.0, 0.0, -12.0), (8.0, 0.0, 12.0), 2.5)
    bridge = _segment((-8.0, 0.0, 0.0), (8.0, 0.0, 0.0), 2.5)  # joins the two vessels: the only path between them
    spur = _segment((-8.0, 0.0, 8.0), (-8.0, 12.0, 8.0), 2.5)  # hangs from the left vessel, along the depth
    grid = grid_around(CentrelineTree([left, right, spur]), 0.5)
    true_vessels = voxelize_exact(CentrelineTree([left, right]), grid)
    segmentation = voxelize_exact(CentrelineTree([left, right, bridge, spur]), grid)
    # the views see the two true vessels alike, the bridge and the spur at 3 mm in one and 1.5 mm in the other
    masks = [render_mask(CentrelineTree([left, right]), v)
             | render_mask(CentrelineTree([_segment(b.points[0], b.points[-1], w) for b in (bridge, spur)]), v)
             for v, w in zip(VIEWS, (3.0, 1.5))]
    geometry = Geometry(grid, VIEWS)

    cut, _ = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7)
    joined, info = disagreeing_pieces(segmentation, masks, geometry, min_ratio=0.7, keep_connected=True)
    assert component_counts(segmentation)["components"] == 1
    assert component_counts(cut)["components"] >= 2  # the bridge gone: the tree in parts
    assert component_counts(joined)["components"] == 1  # the bridge kept ...
    assert (joined & true_vessels).sum() >= 0.99 * true_vessels.sum()  # (the junction's voxels nearest the spur go with it)
    spur_only = voxelize_exact(CentrelineTree([spur]), grid) & ~true_vessels
    bridge_only = voxelize_exact(CentrelineTree([bridge]), grid) & ~true_vessels
    assert (joined & bridge_only).sum() >= 0.9 * bridge_only.sum()
    assert (joined & spur_only).sum() <= 0.1 * spur_only.sum()  # ... and the spur peeled off, tip first
    assert info["removed_pieces"] >= 2


def test_bad_input_is_refused_with_the_fix():
    tube = _tube(2.0)
    grid = grid_around(tube.tree, 0.5)
    segmentation = voxelize_exact(tube.tree, grid)
    masks = [render_mask(tube.tree, v) for v in VIEWS]
    with pytest.raises(ValueError, match="1 masks for 2 views"):
        disagreeing_pieces(segmentation, masks[:1], Geometry(grid, VIEWS), min_ratio=0.5)
    with pytest.raises(ValueError, match="from 0 .* to 1"):
        disagreeing_pieces(segmentation, masks, Geometry(grid, VIEWS), min_ratio=1.5)
    empty, info = disagreeing_pieces(np.zeros(grid.shape, bool), masks, Geometry(grid, VIEWS), min_ratio=0.5)
    assert not empty.any() and info["pieces"] == 0


def test_reconstruction_finished_with_the_width_check_removes_only_what_the_check_names():
    from SDFCARLib.geometry import CArmView, VolumeGrid
    from SDFCARLib.optimiser import fit_field
    from SDFCARLib.phantoms import simulate_views, voxelize
    from SDFCARLib.settings import make_settings

    grid = VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0))
    views = [CArmView(a, 0.0, 1000.0, 750.0, (1.0, 1.0), (64, 64)) for a in (30.0, -30.0)]
    tree = CentrelineTree([Branch(np.array([[-12.0, -6.0, -10.0], [0.0, 2.0, 0.0], [12.0, 6.0, 10.0]]),
                                  np.array([3.0, 2.5, 2.0]))])
    _, masks = simulate_views(voxelize(tree, grid), grid, views)
    # the fill off: it comes after the width check and would fill back what a check at 0.99 leaves unexplained
    base = dict(steps=60, device="cpu", fill_unexplained=False)
    settings = make_settings("fast", **base, width_agreement_min_ratio=0.0)
    fitted = fit_field(Geometry(grid, views), masks, settings)
    plain = fitted.finished()
    assert plain.report["width_agreement"] is None  # off
    checked = fitted.finished(make_settings("fast", **base, width_agreement_min_ratio=0.99))
    info = checked.report["width_agreement"]
    removed = plain.segmentation & ~checked.segmentation
    assert info["removed_voxels"] == int(removed.sum()) and info["pieces"] >= 1
    assert info["measure"] == "centreline"  # report.json says how the widths were read
    thickness = fitted.finished(make_settings("fast", **base, width_agreement_min_ratio=0.99,
                                              width_agreement_measure="thickness"))
    assert thickness.report["width_agreement"]["measure"] == "thickness"
    assert not (checked.segmentation & ~plain.segmentation).any()  # only ever removes
    np.testing.assert_array_equal(checked.segmentation, checked.occupancy >= 0.5)  # what the outputs read
    assert len(info["median_agreement"]) == info["pieces"]
    assert info["removed_pieces"] <= sum(m < 0.99 for m in info["median_agreement"])
    # a piece goes only where its component stays in one part: never more pieces than before
    assert component_counts(checked.segmentation)["components"] <= component_counts(plain.segmentation)["components"]


def test_fast_checks_the_views_widths_at_0_7_and_takes_them_out_of_the_fit_at_60_percent():
    from SDFCARLib.optimiser import exclusion_schedule
    from SDFCARLib.settings import make_settings

    assert make_settings("fast").region.width_agreement_min_ratio == 0.7
    assert make_settings("fast").region.width_agreement_views == "best_pair"  # three views or more: the best pair's
    assert make_settings("paper").region.width_agreement_views == "all"
    assert make_settings("fast").region.width_exclusion_fraction == 0.6
    assert exclusion_schedule(make_settings("fast")) == [240]  # of 400 steps
    assert make_settings("paper").region.width_agreement_min_ratio == 0.0  # the published recipe has no such step
    assert exclusion_schedule(make_settings("paper")) == []


def test_the_voxel_graph_tells_a_split_as_relabelling_the_voxels_does():
    # random blobs cut into random pieces: for every piece, removed alone and after others, the graph's answer is
    # whether the rest of the piece's component(s) falls into more than one 26-connected part
    from scipy import ndimage

    from SDFCARLib.metrics import component_labels
    from SDFCARLib.width_agreement import _VoxelGraph

    rng = np.random.default_rng(3)
    segmentation = ndimage.binary_dilation(rng.random((20, 18, 16)) < 0.03, iterations=1)
    pieces = np.where(segmentation, rng.integers(1, 40, segmentation.shape), 0)
    labels = component_labels(segmentation)[0]
    graph = _VoxelGraph(segmentation, labels, pieces)
    kept = segmentation.copy()
    answers = []
    for k in range(1, 40):
        piece = pieces == k
        own = np.unique(labels[piece & kept])
        rest = np.isin(labels, own[own > 0]) & kept & ~piece
        expected = bool(rest.any()) and component_labels(rest)[1].size > 1
        assert graph.splits_its_component(k) == expected, k
        answers.append(expected)
        if k % 3 == 0:  # remove some whatever they split: the graph follows what is still alive
            graph.remove(k)
            kept &= ~piece
    assert any(answers) and not all(answers)
