"""Redundant-branch pruning: a ghost that two views cannot rule out is removed, true vessels stay."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.metrics import component_labels, mask_dice
from SDFCARLib.settings import make_settings
from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize
from SDFCARLib.projector import project_volume
from SDFCARLib.hull import visual_hull
from SDFCARLib.optimiser import exclusion_schedule, fit_field
from SDFCARLib.pruning import (PruneSettings, parts_of_pieces, piece_adjacency, prune_redundant_branches, removal_zone,
                               skeleton_pieces, unconfirmed_fragments)

GRID = VolumeGrid((40, 40, 40), (1.0, 1.0, 1.0))
# AP sees (x, z), LAO 90 sees (y, z): two vertical vessels make two lines in each view.
VIEWS = [CArmView(0.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 128)),
         CArmView(90.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 128))]


def _tube(x, y, z0, z1, radius):
    return voxelize(CentrelineTree([Branch(np.array([[x, y, z0], [x, y, z1]], float), np.array([radius, radius]))]), GRID)


@pytest.fixture(scope="module")
def ghost_case():
    vessel_a = _tube(0.0, -8.0, -15.0, 15.0, 1.5)
    vessel_b = _tube(8.0, 0.0, -15.0, 15.0, 1.5)
    truth = vessel_a | vessel_b
    _, masks = simulate_views(truth, GRID, VIEWS)
    # At (0, 0) a shorter, thinner tube hides behind vessel A in AP and behind vessel B in LAO 90:
    # both masks are explained without it, so it is exactly the ghost two views cannot exclude.
    ghost = _tube(0.0, 0.0, -6.0, 6.0, 1.0) & ~truth
    return Geometry(GRID, VIEWS), truth, ghost, masks


def test_ghost_really_is_invisible(ghost_case):
    geometry, truth, ghost, masks = ghost_case
    for view, mask in zip(VIEWS, masks):
        ghost_shadow = project_volume(ghost.astype(np.float32), view, GRID) > 0.2
        assert ghost_shadow.any() and not np.any(ghost_shadow & ~mask)


def test_prune_removes_the_ghost_and_keeps_the_vessels(ghost_case):
    geometry, truth, ghost, masks = ghost_case
    segmentation = truth | ghost
    kept, info = prune_redundant_branches(segmentation, masks, geometry)
    assert kept.shape == segmentation.shape and kept.dtype == bool
    assert not np.any(kept & ghost)
    np.testing.assert_array_equal(kept, truth)
    assert info["removed_voxels"] == int(ghost.sum()) and info["removed_pieces"] >= 1
    assert info["pieces"] >= 3 and info["seconds"] >= 0
    for view, mask in zip(VIEWS, masks):  # the reprojection is as good as before
        before = mask_dice(project_volume(segmentation.astype(np.float32), view, GRID) > 0.2, mask)
        after = mask_dice(project_volume(kept.astype(np.float32), view, GRID) > 0.2, mask)
        assert after >= before - 0.01 and after > 0.9


def test_the_reconstructions_own_projectors_give_the_same_pruning_and_reprojection(ghost_case):
    from SDFCARLib.optimiser import reprojected_masks
    from SDFCARLib.projector import ConeBeamProjector

    geometry, truth, ghost, masks = ghost_case
    segmentation = truth | ghost
    support = np.flatnonzero(ndimage.binary_dilation(segmentation, iterations=2).reshape(-1))  # a support holding it
    own = [ConeBeamProjector(view, GRID, voxels=support) for view in VIEWS]
    fresh, fresh_info = prune_redundant_branches(segmentation, masks, geometry)
    reused, reused_info = prune_redundant_branches(segmentation, masks, geometry, projectors=own)
    np.testing.assert_array_equal(reused, fresh)
    assert reused_info["removed_pieces"] == fresh_info["removed_pieces"] >= 1
    for a, b in zip(reprojected_masks(segmentation, geometry, projectors=own), reprojected_masks(segmentation, geometry)):
        assert a.shape == b.shape and a.dtype == bool and a.any()
        np.testing.assert_array_equal(a, b)
    # projectors that do not hold every segmented voxel are not used: the segmentation is traced afresh
    narrow = [ConeBeamProjector(view, GRID, voxels=np.flatnonzero(truth.reshape(-1))) for view in VIEWS]
    np.testing.assert_array_equal(prune_redundant_branches(segmentation, masks, geometry, projectors=narrow)[0], fresh)
    for a, b in zip(reprojected_masks(segmentation, geometry, projectors=narrow), reprojected_masks(segmentation, geometry)):
        np.testing.assert_array_equal(a, b)


def test_prune_keeps_a_true_tree_whole():
    tree = CentrelineTree([
        Branch(np.array([[-14.0, -4.0, -13.0], [0.0, 3.0, 0.0], [13.0, -2.0, 14.0]]), np.array([2.0, 1.6, 1.2])),
        Branch(np.array([[0.0, 3.0, 0.0], [9.0, 9.0, -11.0]]), np.array([1.4, 1.0])),
    ])
    label = voxelize(tree, GRID)
    views = [CArmView(30.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 128)),
             CArmView(-30.0, 20.0, 1000.0, 750.0, (0.5, 0.5), (128, 128))]
    _, masks = simulate_views(label, GRID, views)
    kept, info = prune_redundant_branches(label, masks, Geometry(GRID, views))
    assert info["removed_pieces"] == 0
    np.testing.assert_array_equal(kept, label)


@pytest.mark.parametrize("centre", [0.5, 0.0], ids=["3-voxels-thick", "2-voxels-thick"])
def test_pieces_partition_the_segmentation_and_respect_the_length(centre):
    # A tube on voxel centres is 3 voxels thick; between them 2 voxels thick, which skimage's
    # thinning deletes entirely, so that case exercises the principal-axis fallback.
    tube = _tube(centre, centre, -12.0, 12.0, 1.5)
    pieces, count = skeleton_pieces(tube, GRID.spacing_mm, max_piece_mm=6.0)
    assert np.array_equal(pieces > 0, tube)
    assert set(np.unique(pieces[tube])) == set(range(1, count + 1))
    assert count in (4, 5)  # a 24–27 mm tube (with its rounded ends) in pieces of at most 6 mm
    z = GRID.voxel_centers(np.flatnonzero(tube))[:, 2]
    for label in range(1, count + 1):  # each piece is one stretch along the tube
        assert np.ptp(z[pieces[tube] == label]) <= 6.0 + 1.0
    _, one = skeleton_pieces(tube, GRID.spacing_mm, max_piece_mm=100.0)
    assert one == 1


def test_empty_and_single_piece_segmentations_are_returned_unchanged(ghost_case):
    geometry, truth, _, masks = ghost_case
    empty = np.zeros(GRID.shape, bool)
    kept, info = prune_redundant_branches(empty, masks, geometry)
    assert not kept.any() and info["pieces"] == 0 and info["removed_voxels"] == 0
    single = _tube(0.0, -8.0, -3.0, 3.0, 1.5)
    kept, info = prune_redundant_branches(single, masks, geometry, PruneSettings(max_piece_mm=50.0))
    np.testing.assert_array_equal(kept, single)


def test_prune_rejects_masks_that_do_not_match_the_views(ghost_case):
    geometry, truth, _, masks = ghost_case
    with pytest.raises(ValueError, match="1 mask"):
        prune_redundant_branches(truth, masks[:1], geometry)
    with pytest.raises(ValueError, match="mask 2 has shape"):
        prune_redundant_branches(truth, [masks[0], masks[1][:64]], geometry)


def test_removal_zone_covers_the_removed_voxels_and_spares_the_kept(ghost_case):
    _, truth, ghost, _ = ghost_case
    zone = removal_zone(truth | ghost, truth, GRID.spacing_mm)
    assert np.all(zone[ghost]) and not np.any(zone & truth)
    assert zone.sum() > ghost.sum()  # with the shell of partial occupancy around the ghost
    assert not removal_zone(truth, truth, GRID.spacing_mm).any()


@pytest.mark.parametrize("spacing_mm", [(0.8, 0.8, 0.8), (0.5, 0.7, 1.6)])
def test_removal_zone_is_the_shell_nearer_the_removed_by_centre_distances(spacing_mm):
    # against the definition by whole-grid distance transforms: the removed voxels and every other voxel not kept that
    # lies within a voxel diagonal of them and nearer to them than to anything kept
    rng = np.random.default_rng(5)
    segmentation = ndimage.binary_dilation(rng.random((24, 20, 18)) < 0.02, iterations=1)
    kept = segmentation & (rng.random(segmentation.shape) < 0.6)
    spacing = np.asarray(spacing_mm)
    to_removed = ndimage.distance_transform_edt(~(segmentation & ~kept), sampling=spacing)
    to_kept = ndimage.distance_transform_edt(~kept, sampling=spacing)
    expected = (segmentation & ~kept) | ((to_removed <= np.linalg.norm(spacing) + 1e-6) & (to_removed < to_kept) & ~kept)
    zone = removal_zone(segmentation, kept, spacing_mm)
    np.testing.assert_array_equal(zone, expected)
    assert zone.sum() > (segmentation & ~kept).sum()
    # nothing kept at all: the whole shell goes; a removed voxel on the grid's edge is no error
    edge = np.zeros((6, 6, 6), bool)
    edge[0, 0, :3] = True
    np.testing.assert_array_equal(removal_zone(edge, np.zeros_like(edge), spacing_mm),
                                  ndimage.distance_transform_edt(~edge, sampling=spacing) <= np.linalg.norm(spacing) + 1e-6)


def test_presets_prune_only_in_fast():
    assert make_settings("fast").region.prune is True
    assert make_settings("paper").region.prune is False  # the published recipe has no post-processing


def _segment(start, end, radius):
    return voxelize(CentrelineTree([Branch(np.array([start, end], float), np.array([radius, radius]))]), GRID)


@pytest.fixture(scope="module")
def missed_vessel_case():
    """Vessel B crosses the volume obliquely at z = 5; view 2's mask (LAO 90, sees (y, z)) misses it.

    AP's rays through B (along y) meet view 2's mask only on vertical vessel A's shadow (y = −8), so
    the only voxels that can explain B's AP pixels form a rod at y = −8, z = 5 under B's x-range:
    detached from A (x = 8) and from B, and in view 2 inside A's shadow — the ghost.
    """
    vessel_a = _segment([8.0, -8.0, -15.0], [8.0, -8.0, 15.0], 1.5)
    vessel_b = _segment([-15.0, 2.0, 5.0], [-3.0, 14.0, 5.0], 1.5)
    _, (ap_mask, _) = simulate_views(vessel_a | vessel_b, GRID, VIEWS)
    _, (_, lao_mask) = simulate_views(vessel_a, GRID, VIEWS)
    masks = [ap_mask, lao_mask]
    # the part of that rod the masks allow (cone-beam magnification differs along it)
    ghost = _segment([-15.0, -8.0, 5.0], [-3.0, -8.0, 5.0], 1.5) & visual_hull(masks, VIEWS, GRID) & ~vessel_a
    return Geometry(GRID, VIEWS), vessel_a, vessel_b, ghost, masks


def test_unconfirmed_fragments_removes_the_ghost_of_a_missed_vessel(missed_vessel_case):
    geometry, vessel_a, _, ghost, masks = missed_vessel_case
    # the ghost explains B's pixels in AP; in LAO 90 every mask pixel it covers, A covers too
    covered = [project_volume(v.astype(np.float32), VIEWS[1], GRID) > 0.1 for v in (ghost, vessel_a)]
    assert ghost.sum() >= 20 and np.any(covered[0] & masks[1]) and not np.any(covered[0] & masks[1] & ~covered[1])
    removed, info = unconfirmed_fragments(vessel_a | ghost, masks, geometry)
    np.testing.assert_array_equal(removed, ghost)
    assert info["fragments"] == 1 and info["removed_fragments"] == 1 and info["removed_voxels"] == int(ghost.sum())


def test_unconfirmed_fragments_keeps_a_fragment_that_both_views_see_alone(missed_vessel_case):
    geometry, vessel_a, vessel_b, _, _ = missed_vessel_case
    _, masks = simulate_views(vessel_a | vessel_b, GRID, VIEWS)
    removed, info = unconfirmed_fragments(vessel_a | vessel_b, masks, geometry)
    assert not removed.any() and info["fragments"] == 1 and info["removed_fragments"] == 0


def test_unconfirmed_fragments_does_not_count_a_view_that_cannot_see_the_fragment():
    # View 2's detector is 48 columns wide: it sees y in about [−9, 9] mm, not the fragment at y = 15.
    views = [VIEWS[0], CArmView(90.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 48))]
    vessel = _segment([8.0, -4.0, -15.0], [8.0, -4.0, 15.0], 1.5)
    fragment = _segment([-8.0, 15.0, -5.0], [-8.0, 15.0, 5.0], 1.5)
    masks = [m for m in simulate_views(vessel | fragment, GRID, views)[1]]
    assert not np.any(project_volume(fragment.astype(np.float32), views[1], GRID) > 0)
    removed, info = unconfirmed_fragments(vessel | fragment, masks, Geometry(GRID, views))
    assert not removed.any() and info["fragments"] == 1


def test_unconfirmed_fragments_does_not_count_a_view_that_could_not_see_the_fragment():
    # View 2 (LAO 90, its columns along y) is collimated over y > 10 mm: the fragment at y = 15 lies behind the blade
    vessel = _segment([8.0, -4.0, -15.0], [8.0, -4.0, 15.0], 1.5)
    fragment = _segment([-8.0, 15.0, -5.0], [-8.0, 15.0, 5.0], 1.5)
    _, masks = simulate_views(vessel | fragment, GRID, VIEWS)
    shadow = project_volume(fragment.astype(np.float32), VIEWS[1], GRID) > 0
    assert shadow.any()
    blade = np.zeros(VIEWS[1].detector_shape, bool)
    blade[:, np.flatnonzero(shadow.any(axis=0)).min() - 2:] = True
    masks = [masks[0], masks[1] & ~blade]
    removed, _ = unconfirmed_fragments(vessel | fragment, masks, Geometry(GRID, VIEWS))
    np.testing.assert_array_equal(removed, fragment)  # without the blade known, view 2 rejects it
    removed, info = unconfirmed_fragments(vessel | fragment, masks, Geometry(GRID, VIEWS), unknown=[None, blade & ~masks[1]])
    assert not removed.any() and info["fragments"] == 1
    with pytest.raises(ValueError, match="unknown-pixel images"):
        unconfirmed_fragments(vessel | fragment, masks, Geometry(GRID, VIEWS), unknown=[None])


def test_unconfirmed_fragments_of_one_piece_and_bad_masks(missed_vessel_case):
    geometry, vessel_a, _, _, masks = missed_vessel_case
    removed, info = unconfirmed_fragments(vessel_a, masks, geometry)
    assert not removed.any() and info["fragments"] == 0
    removed, info = unconfirmed_fragments(np.zeros(GRID.shape, bool), masks, geometry)
    assert not removed.any() and info["fragments"] == 0
    with pytest.raises(ValueError, match="1 mask"):
        unconfirmed_fragments(vessel_a, masks[:1], geometry)
    with pytest.raises(ValueError, match="mask shape"):
        unconfirmed_fragments(vessel_a | _segment([-8.0, 0.0, 0.0], [-8.0, 0.0, 9.0], 1.5), [masks[0], masks[1][:64]], geometry)


def test_a_vessel_missing_from_one_mask_is_not_replaced_by_a_ghost(missed_vessel_case):
    """End to end: the reconstruction places the ghost rod when fragments are kept, not when dropped."""
    geometry, vessel_a, vessel_b, ghost, masks = missed_vessel_case
    ghost_zone = ndimage.binary_dilation(ghost, iterations=2) & ~ndimage.binary_dilation(vessel_a | vessel_b, iterations=3)
    def settings(drop, width_ratio):  # the width check off: each step alone
        return make_settings("fast", steps=250, seed=0, device="cpu", threads=1, drop_unconfirmed_fragments=drop,
                             width_agreement_min_ratio=width_ratio)

    fitted = fit_field(geometry, [m.astype(np.float32) for m in masks], settings(False, 0.0))  # both steps come after the fit
    kept, dropped, width_checked = (fitted.finished(settings(drop, width_ratio))
                                    for drop, width_ratio in ((False, 0.0), (True, 0.0), (False, 0.7)))
    assert (kept.segmentation & ghost_zone).sum() >= 10  # the case does make a ghost
    # the two views read different widths along the ghost (B's shadow in AP, A's in LAO 90; median agreement 0.56)
    assert not np.any(width_checked.segmentation & ghost_zone)
    assert width_checked.report["width_agreement"]["removed_voxels"] >= 10
    assert not np.any(dropped.segmentation & ghost_zone)
    assert kept.report["unconfirmed_fragments"] is None
    info = dropped.report["unconfirmed_fragments"]
    assert info["removed_fragments"] >= 1 and info["removed_voxels"] >= 10
    # vessel A, which both views see, is still there, and its surroundings unchanged
    recall = (dropped.segmentation & vessel_a).sum() / vessel_a.sum()
    assert recall > 0.9
    near_a = ndimage.binary_dilation(vessel_a, iterations=3)
    np.testing.assert_array_equal(dropped.segmentation & near_a, kept.segmentation & near_a)


def test_pieces_the_views_widths_disagree_on_are_taken_out_of_the_fit(missed_vessel_case):
    """width_exclusion_fraction: part way through, the width check's pieces leave the field for good."""
    geometry, vessel_a, vessel_b, ghost, masks = missed_vessel_case
    ghost_zone = ndimage.binary_dilation(ghost, iterations=2) & ~ndimage.binary_dilation(vessel_a | vessel_b, iterations=3)
    settings = make_settings("fast", steps=250, seed=0, device="cpu", threads=1, width_exclusion_fraction=0.6)
    fitted = fit_field(geometry, [m.astype(np.float32) for m in masks], settings)
    excluded = fitted.problem.excluded
    (exclusion,) = fitted.problem.exclusion["exclusions"]
    assert exclusion["step"] == 150 and exclusion["removed_pieces"] >= 1 and exclusion["removed_voxels"] >= 10
    assert np.any(excluded & ghost_zone) and not np.any(excluded & vessel_a)  # the ghost went, vessel A stayed
    result = fitted.finished()
    assert result.report["width_exclusion"]["excluded_voxels"] == int(excluded.sum())
    assert not np.any(result.occupancy[excluded]) and not np.any(result.segmentation & ghost_zone)
    assert (result.segmentation & vessel_a).sum() / vessel_a.sum() > 0.9
    assert fitted.history[-1]["step"] == 250  # the fit went on after the exclusion


def test_exclusion_schedule_spaces_the_repeats_to_the_end():
    assert exclusion_schedule(make_settings("fast", steps=400, width_exclusion_fraction=0.0)) == []  # off
    assert exclusion_schedule(make_settings("fast", steps=400, width_exclusion_fraction=0.6)) == [240]
    # the width check off: nothing to take out
    assert exclusion_schedule(make_settings("fast", steps=400, width_exclusion_fraction=0.6, width_agreement_min_ratio=0.0)) == []
    assert exclusion_schedule(make_settings("fast", steps=400, width_exclusion_fraction=0.6, width_exclusion_repeats=2)) == [240, 320]
    assert exclusion_schedule(make_settings("fast", steps=100, width_exclusion_fraction=0.5, width_exclusion_repeats=4)) == [50, 62, 75, 88]


def test_presets_drop_unconfirmed_fragments_only_in_fast():
    assert make_settings("fast").region.drop_unconfirmed_fragments is True
    assert make_settings("paper").region.drop_unconfirmed_fragments is False


def test_unconfirmed_fragments_reads_the_reconstructions_own_projectors(missed_vessel_case):
    """Projectors of a larger voxel set (the support) give the same answer as ones of the segmentation;
    projectors that miss a segmented voxel are not used."""
    from SDFCARLib.projector import ConeBeamProjector

    geometry, vessel_a, _, ghost, masks = missed_vessel_case
    segmentation = vessel_a | ghost
    support = np.flatnonzero(ndimage.binary_dilation(segmentation, iterations=2).reshape(-1))
    removed, _ = unconfirmed_fragments(segmentation, masks, geometry,
                                       projectors=[ConeBeamProjector(v, GRID, voxels=support) for v in VIEWS])
    np.testing.assert_array_equal(removed, ghost)
    too_few = np.flatnonzero(vessel_a.reshape(-1))  # the ghost's voxels are missing: rebuilt, same answer
    removed, _ = unconfirmed_fragments(segmentation, masks, geometry,
                                       projectors=[ConeBeamProjector(v, GRID, voxels=too_few) for v in VIEWS])
    np.testing.assert_array_equal(removed, ghost)


def _post_process(segmentation, masks, geometry, support=None, **overrides):
    """finish's fragment steps on a constructed result: occupancy 1 inside, 0.2 (dim field) outside."""
    from SDFCARLib.optimiser import drop_then_join_fragments

    settings = make_settings("fast", **overrides)
    occupancy = np.where(segmentation, 1.0, 0.2).astype(np.float32)
    field = np.where(segmentation, -0.05, 0.05).astype(np.float32)
    result, unconfirmed, reconnection = drop_then_join_fragments(segmentation, occupancy, field, masks, geometry,
                                                                 support, settings)
    np.testing.assert_array_equal(result, occupancy >= settings.region.threshold)  # the volumes follow the result
    np.testing.assert_array_equal(field[result] < 0, True)
    return result, unconfirmed, reconnection


def test_a_ghost_is_dropped_before_joining_could_attach_it(missed_vessel_case):
    """The ghost rod lies about 9 mm from vessel A: a 12 mm bridge would make it part of the tree, which
    the confirmation step never judges. Dropped first, nothing is left to join."""
    geometry, vessel_a, _, ghost, masks = missed_vessel_case
    result, unconfirmed, reconnection = _post_process(vessel_a | ghost, masks, geometry, reconnect_max_gap_mm=12.0)
    np.testing.assert_array_equal(result, vessel_a)
    assert unconfirmed["removed_fragments"] == 1 and reconnection["joined"] == 0
    # the other order, by hand: joined first, the ghost is on the tree and the confirmation keeps it
    from SDFCARLib.connectivity import ReconnectSettings, reconnect_fragments

    joined, _, _, info = reconnect_fragments(vessel_a | ghost, np.where(vessel_a | ghost, 1.0, 0.2), GRID.spacing_mm,
                                             None, ReconnectSettings(12.0, 0.1, 0.5))
    assert info["joined"] == 1 and not unconfirmed_fragments(joined, masks, geometry)[0].any()


def test_a_confirmed_piece_of_a_broken_vessel_is_joined_through_the_support():
    """A vertical vessel broken at z in (0, 4) mm: both views see the upper piece alone, so it is kept and
    bridged inside the support (the masks' hull, where both views show the vessel across the gap)."""
    vessel = _segment([0.0, 0.0, -15.0], [0.0, 0.0, 15.0], 1.5)
    _, masks = simulate_views(vessel, GRID, VIEWS)
    z = GRID.index_to_world(np.argwhere(vessel))[:, 2]
    broken = vessel.copy()
    broken[tuple(np.argwhere(vessel)[(z > 0.0) & (z < 4.0)].T)] = False
    assert np.unique(ndimage.label(broken, np.ones((3, 3, 3)))[0]).size == 3  # two pieces and the background
    support = visual_hull(masks, VIEWS, GRID)
    result, unconfirmed, reconnection = _post_process(broken, masks, Geometry(GRID, VIEWS), support,
                                                      reconnect_max_gap_mm=8.0)
    assert unconfirmed["removed_fragments"] == 0 and reconnection["joined"] == 1
    assert reconnection["components_after"] == 1 and (result & ~support).sum() == 0
    assert 3.0 <= reconnection["gap_mm"][0] <= 6.0
    # a support with the gap cut out of it (one view's mask misses the vessel there): nothing crosses
    cut = support & ~((np.abs(GRID.index_to_world(np.indices(GRID.shape).reshape(3, -1).T)[:, 2]) < 5.0)
                      .reshape(GRID.shape) & ~broken)
    _, _, reconnection = _post_process(broken, masks, Geometry(GRID, VIEWS), cut, reconnect_max_gap_mm=8.0)
    assert reconnection["joined"] == 0 and reconnection["components_after"] == 2


@pytest.mark.parametrize("prune, drop_unconfirmed, removed_by", [
    (True, True, "pruned_voxels"), (False, True, "unconfirmed_voxels"), (False, False, None)])
def test_the_exclusion_can_take_what_pruning_and_the_fragment_check_would_remove(ghost_case, prune, drop_unconfirmed,
                                                                                  removed_by):
    """exclusion_takes_finishing_removals: the mid-fit exclusion reads finish's removals on the fit so far."""
    from SDFCARLib.optimiser import finishing_removals

    geometry, truth, ghost, masks = ghost_case
    region = make_settings("fast", prune=prune, drop_unconfirmed_fragments=drop_unconfirmed).region
    kept, counts = finishing_removals(truth | ghost, masks, geometry, region, projectors=None)
    if removed_by is None:  # neither step asked: nothing goes
        np.testing.assert_array_equal(kept, truth | ghost)
        assert counts == {}
    else:  # the hidden ghost goes, whichever step takes it, and the vessels stay whole
        np.testing.assert_array_equal(kept, truth)
        assert counts[removed_by] == int(ghost.sum())


def test_keeping_the_tree_whole_leaves_a_tube_whose_middle_other_vessels_cover_in_both_views():
    # A tube T along z; its middle is hidden behind a short tube A in AP and behind another, B, in LAO 90,
    # while T's ends and A and B are each seen on their own somewhere: set cover alone cuts T's middle out.
    tube = _tube(0.0, 0.0, -15.0, 15.0, 1.5)
    behind_in_ap, behind_in_lao = _tube(0.0, 8.0, -5.0, 5.0, 1.5), _tube(8.0, 0.0, -5.0, 5.0, 1.5)
    truth = tube | behind_in_ap | behind_in_lao
    _, masks = simulate_views(truth, GRID, VIEWS)
    geometry = Geometry(GRID, VIEWS)
    cut, cut_info = prune_redundant_branches(truth, masks, geometry)
    assert (tube & ~cut).sum() > 0 and component_labels(tube & cut)[1].size == 2
    assert "kept_whole_pieces" not in cut_info
    whole, info = prune_redundant_branches(truth, masks, geometry, PruneSettings(keep_connected=True))
    np.testing.assert_array_equal(whole, truth)
    assert info["removed_pieces"] == 0 and info["kept_whole_pieces"] >= 1


def test_keeping_the_tree_whole_still_removes_a_detached_ghost_piece_by_piece(ghost_case):
    geometry, truth, ghost, masks = ghost_case
    pieces, _ = skeleton_pieces(truth | ghost, GRID.spacing_mm, PruneSettings().max_piece_mm)
    assert np.unique(pieces[ghost]).size >= 2  # the ghost is more than one piece: they go one after another
    kept, info = prune_redundant_branches(truth | ghost, masks, geometry, PruneSettings(keep_connected=True))
    np.testing.assert_array_equal(kept, truth)
    assert info["removed_voxels"] == int(ghost.sum()) and info["kept_whole_pieces"] == 0


def test_piece_adjacency_links_the_touching_pieces_only():
    pieces = np.zeros((6, 6, 6), np.int64)
    pieces[0:2, 0, 0], pieces[2, 1, 1], pieces[4:, 4, 4] = 1, 2, 3  # 1 and 2 touch diagonally; 3 is apart
    adjacency = piece_adjacency(pieces, 3).toarray()
    np.testing.assert_array_equal(adjacency, [[False, True, False], [True, False, False], [False, False, False]])
    assert piece_adjacency(np.zeros((3, 3, 3), np.int64), 0).shape == (0, 0)


def test_prune_last_removes_a_ghost_that_growing_attached_after_the_first_pruning(ghost_case):
    """The hidden tube is left at partial occupancy (0.4), joined to vessel A by a partial-occupancy path: the first
    pruning never sees it (below the threshold), growing takes it in (≥ grow_threshold 0.3), and only pruning once
    more at the end (``prune_last``) removes it; the two vessels stay (bar a stray voxel of a split piece)."""
    import dataclasses

    from SDFCARLib.connectivity import field_values

    geometry, truth, ghost, masks = ghost_case
    settings = make_settings("fast", steps=10, device="cpu", width_agreement_min_ratio=0.0, fill_unexplained=False,
                             prune_last=False)
    fitted = fit_field(geometry, masks, settings)
    # along y at x = z = 0, from vessel A's wall (y = −6.5 mm) to the ghost's (y = −1 mm)
    (i, j_a, k), (_, j_g, _) = np.round(GRID.world_to_index(np.array([[0.0, -6.5, 0.0], [0.0, -1.0, 0.0]]))).astype(int)
    path = np.zeros_like(truth)
    path[i, min(j_a, j_g):max(j_a, j_g) + 1, k] = True
    occupancy = np.where(truth, 1.0, np.where(ghost | path, 0.4, 0.0)).astype(np.float32)
    volumes = (occupancy, field_values(occupancy, settings.mode.field_kind, settings.field.alpha))
    with_ghost = dataclasses.replace(fitted, volumes=volumes).finished(settings)
    assert (with_ghost.segmentation & ghost).sum() > 0.9 * ghost.sum()  # grown in and kept
    assert with_ghost.report["last_pruning"] is None
    pruned = dataclasses.replace(fitted, volumes=volumes).finished(settings.replace(prune_last=True,
                                                                                 prune_last_only_without_motion=False))
    assert (pruned.segmentation & ghost).sum() < 0.1 * ghost.sum()
    assert (pruned.segmentation & truth).sum() >= 0.99 * truth.sum()  # a stray voxel of a split piece may go
    assert pruned.report["last_pruning"]["removed_voxels"] > 0
    assert pruned.report["components"]["components"] == with_ghost.report["components"]["components"] == 2  # A, B
    np.testing.assert_array_equal(pruned.segmentation, pruned.occupancy >= 0.5)  # what the outputs read


@pytest.mark.parametrize("motion_found, min_views, pruned_last", [
    (False, 3, True), (True, 3, False), (None, 3, False), (True, 2, True), (None, 2, True), (True, 0, False)])
def test_prune_last_only_without_motion_prunes_where_the_pose_check_found_the_views_aligned(ghost_case, motion_found,
                                                                                          min_views, pruned_last):
    """``prune_last_only_without_motion``: the ghost growing attached goes only where the pose check found no motion;
    where it found one, or none ran, the last pruning is skipped and report.json says why — unless the case has
    ``prune_last_min_views_any_motion`` views or more (this case has two)."""
    import dataclasses

    from SDFCARLib.connectivity import field_values
    from SDFCARLib.optimiser import LAST_PRUNING_SKIPPED

    geometry, truth, ghost, masks = ghost_case
    settings = make_settings("fast", steps=10, device="cpu", width_agreement_min_ratio=0.0, fill_unexplained=False,
                             prune_last=True, prune_last_only_without_motion=True,
                             prune_last_min_views_any_motion=min_views)
    fitted = fit_field(geometry, masks, settings)
    assert fitted.problem.motion_found is None  # masks alone: no frames, no check
    (i, j_a, k), (_, j_g, _) = np.round(GRID.world_to_index(np.array([[0.0, -6.5, 0.0], [0.0, -1.0, 0.0]]))).astype(int)
    path = np.zeros_like(truth)
    path[i, min(j_a, j_g):max(j_a, j_g) + 1, k] = True
    occupancy = np.where(truth, 1.0, np.where(ghost | path, 0.4, 0.0)).astype(np.float32)
    volumes = (occupancy, field_values(occupancy, settings.mode.field_kind, settings.field.alpha))
    fitted.problem.motion_found = motion_found
    result = dataclasses.replace(fitted, volumes=volumes).finished(settings)
    assert result.report["motion_found"] is motion_found
    if pruned_last:
        assert (result.segmentation & ghost).sum() < 0.1 * ghost.sum()
        assert result.report["last_pruning"]["removed_voxels"] > 0
    else:
        assert (result.segmentation & ghost).sum() > 0.9 * ghost.sum()
        assert result.report["last_pruning"] == {"skipped": LAST_PRUNING_SKIPPED[motion_found]}


def test_parts_of_pieces_gives_each_part_of_a_piece_its_own_label():
    pieces = np.zeros((10, 10, 10), np.int64)
    pieces[1, 1:4, 1] = 1
    pieces[1, 6:9, 1] = 1  # piece 1 in two parts
    pieces[1, 4:6, 1] = 2  # piece 2 between them
    pieces[7, 7, 7:9] = 3
    parts, count = parts_of_pieces(pieces, 3)
    assert count == 4
    np.testing.assert_array_equal(parts > 0, pieces > 0)  # the same voxels
    assert len({parts[1, 1, 1], parts[1, 7, 1], parts[1, 4, 1], parts[7, 7, 7]}) == 4
    assert set(np.unique(parts)) == {0, 1, 2, 3, 4}
    for label in range(1, count + 1):  # each label within one piece
        assert np.unique(pieces[parts == label]).size == 1


def test_split_pieces_keep_a_tree_whole_where_a_piece_in_two_parts_joins_it():
    """A rod of pieces 1, 2, 3; piece 1 has a second part, a voxel beside piece 3 only. Unsplit, the graph links 1 and 3
    directly, so removing piece 2 seems to leave the rod whole; split, piece 1's first part hangs on piece 2 alone."""
    from SDFCARLib.pruning import _splits_pieces

    pieces = np.zeros((12, 12, 12), np.int64)
    pieces[1, 1:4, 1] = 1
    pieces[1, 4:7, 1] = 2
    pieces[1, 7:10, 1] = 3
    pieces[2, 9, 1] = 1  # piece 1's second part, beside piece 3 only
    unsplit = piece_adjacency(pieces, 3)
    assert not _splits_pieces(unsplit, np.ones(3, bool), 1)  # the graph says 1 and 3 stay joined without 2
    parts, count = parts_of_pieces(pieces, 3)
    assert count == 4
    middle = int(parts[1, 5, 1]) - 1
    assert _splits_pieces(piece_adjacency(parts, count), np.ones(count, bool), middle)


def test_the_first_pruning_splits_pieces_only_when_asked():
    from SDFCARLib.optimiser import prune_settings

    assert prune_settings(make_settings("fast", prune_split_pieces=True).region).split_disconnected_pieces is True
    assert prune_settings(make_settings("fast", prune_split_pieces=False).region).split_disconnected_pieces is False
