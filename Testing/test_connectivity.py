"""Connected components in the reports and the reconnection of fragments (``connectivity.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.connectivity import ReconnectSettings, field_values, reconnect_fragments
from SDFCARLib.metrics import component_labels
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.metrics import component_counts, volume_metrics
from SDFCARLib.optimiser import reconstruct
from SDFCARLib.settings import ReconstructionError, make_settings, parse_setting_overrides

H = 0.5  # mm per voxel of the analytic volumes


def _tube(n: int = 48, radius_mm: float = 1.5) -> np.ndarray:
    """Occupancy of a straight tube along axis 0 through the centre of an n³ grid (soft wall)."""
    _, j, k = np.meshgrid(*[np.arange(n)] * 3, indexing="ij")
    r = np.hypot((j - n // 2) * H, (k - n // 2) * H)
    return (1.0 / (1.0 + np.exp((r - radius_mm) * 4.0))).astype(np.float32)


def _cut(occupancy: np.ndarray, start: int, stop: int, factor: float) -> np.ndarray:
    out = occupancy.copy()
    out[start:stop] *= factor
    return out


def test_component_counts_of_a_constructed_volume():
    v = np.zeros((20, 20, 20), bool)
    v[2:6, 2:6, 2:6] = True  # 64 voxels
    v[6, 6, 6] = True  # touches the cube only at a corner: the same 26-connected component
    v[12:14, 12:14, 12:14] = True  # 8 voxels
    v[18, 2, 2] = True  # 1 voxel
    assert component_counts(v) == {"components": 3, "largest_component_fraction": pytest.approx(65 / 74)}
    labels, sizes = component_labels(v)
    assert sorted(sizes.tolist()) == [1, 8, 65] and labels.max() == 3
    empty = component_counts(np.zeros((4, 4, 4)))
    assert empty["components"] == 0 and np.isnan(empty["largest_component_fraction"])
    m = volume_metrics(v, v[:, :, ::-1] & False | (np.arange(20) < 10)[:, None, None], (1.0, 1.0, 1.0))
    assert m["components"] == 3 and m["components_label"] == 1


def test_a_gap_with_a_ridge_of_occupancy_is_bridged():
    occupancy = _cut(_tube(), 22, 26, 0.3)  # 4 voxels = 2 mm where the field dips to 0.3
    segmentation = occupancy >= 0.5
    before = segmentation.copy()
    assert component_counts(segmentation)["components"] == 2
    joined, new_occupancy, changed, info = reconnect_fragments(segmentation, occupancy, (H, H, H))
    assert np.array_equal(segmentation, before)  # inputs untouched
    assert component_counts(joined)["components"] == 1
    assert component_counts(new_occupancy >= 0.5)["components"] == 1  # the surface at 0.5 includes the bridge
    assert info["components_before"] == 2 and info["components_after"] == 1 and info["joined"] == 1
    assert info["gap_mm"][0] == pytest.approx(2.5)  # between the two segmented voxels it joins
    bridge = info["bridges"][0]  # where the vessel was broken, for the 3D-QCA
    assert bridge["gap_mm"] == info["gap_mm"][0] and 0.5 * H <= bridge["radius_mm"] < 1.5
    assert sorted({ijk[0] for ijk in bridge["voxels_ijk"]}) == [22, 23, 24, 25]
    assert 0.2 < info["gap_occupancy"][0] < 0.35
    # The bridge has about the tube's cross-section, not a one-voxel thread and not a blob.
    assert 0.5 * before[10].sum() <= joined[24].sum() <= before[10].sum()
    assert changed.any() and not changed[:18].any() and not changed[30:].any()
    assert not (joined & ~before & ~changed).any()  # every added voxel got its occupancy raised


def test_the_bridge_respects_the_support():
    occupancy = _cut(_tube(), 22, 26, 0.3)
    support = np.ones(occupancy.shape, bool)
    support[22:26] = False  # the field was never evaluated in the gap
    joined, _, _, info = reconnect_fragments(occupancy >= 0.5, occupancy, (H, H, H), support)
    assert info["joined"] == 0 and component_counts(joined)["components"] == 2


@pytest.mark.parametrize("describe, factor, gap_voxels", [
    ("dark field across a short gap", 0.01, 4),
    ("a bright ridge but longer than max_gap_mm", 0.3, 12),
])
def test_unsupported_bridges_are_not_made(describe, factor, gap_voxels):
    occupancy = _cut(_tube(), 18, 18 + gap_voxels, factor)
    segmentation = occupancy >= 0.5
    joined, new_occupancy, changed, info = reconnect_fragments(
        segmentation, occupancy, (H, H, H), settings=ReconnectSettings(max_gap_mm=4.0, min_occupancy=0.1))
    assert info["joined"] == 0 and info["left_apart"] == 1, describe
    assert np.array_equal(joined, segmentation) and np.array_equal(new_occupancy, occupancy) and not changed.any()


def test_a_far_blob_behind_low_occupancy_stays_apart_unless_the_support_joins_it():
    occupancy = _tube()
    occupancy[:, :, :16] = 0.0
    i, j, k = np.meshgrid(*[np.arange(48)] * 3, indexing="ij")
    blob = np.hypot(np.hypot((i - 24) * H, (j - 24) * H), (k - 6) * H) <= 2.0  # 7.5 mm from the tube's wall
    occupancy[blob] = 0.9
    haze = (k > 8) & (k < 21) & (np.abs(j - 24) < 2) & (np.abs(i - 24) < 2)
    occupancy[haze] = 0.05  # a faint haze between
    segmentation = occupancy >= 0.5
    joined, _, _, info = reconnect_fragments(segmentation, occupancy, (H, H, H), settings=ReconnectSettings(4.0, 0.1))
    assert info["components_before"] == 2 and info["joined"] == 0
    assert np.array_equal(joined, segmentation)
    # the defaults ask no occupancy, only a gap of at most 8 mm inside the support
    support = (occupancy > 0.0) & ~haze
    joined, _, _, info = reconnect_fragments(segmentation, occupancy, (H, H, H), support)
    assert info["joined"] == 0 and np.array_equal(joined, segmentation)  # the haze is outside the support
    joined, _, _, info = reconnect_fragments(segmentation, occupancy, (H, H, H), support | haze)
    assert info["joined"] == 1 and 5.5 <= info["gap_mm"][0] <= 8.0  # wall to wall 5.5 mm, in voxel steps


def test_a_chain_of_fragments_is_joined_link_by_link():
    occupancy = _tube()
    for start in (12, 24, 36):
        occupancy[start:start + 3] *= 0.3
    joined, _, _, info = reconnect_fragments(occupancy >= 0.5, occupancy, (H, H, H))
    assert info["components_before"] == 4 and info["joined"] == 3 and component_counts(joined)["components"] == 1


def test_field_values_invert_the_occupancy():
    o = np.array([0.05, 0.5, 0.9], np.float32)
    s = field_values(o, "sdf", 50.0)
    np.testing.assert_allclose(1.0 / (1.0 + np.exp(50.0 * s)), o, rtol=1e-5)
    logit = field_values(o, "occupancy", 50.0)
    np.testing.assert_allclose(1.0 / (1.0 + np.exp(-logit)), o, rtol=1e-5)


@pytest.mark.parametrize("values, fragment", [
    ({"reconnect_max_gap_mm": 0.0}, "reconnect_max_gap_mm must be a positive length in mm (default 8), got 0.0"),
    ({"reconnect_min_occupancy": 1.5}, "reconnect_min_occupancy must be an occupancy in [0, 1)"),
    ({"reconnect_min_occupancy": -0.1}, "reconnect_min_occupancy must be an occupancy in [0, 1)"),
])
def test_reconnect_settings_are_validated(values, fragment):
    with pytest.raises(ReconstructionError) as info:
        make_settings("fast", **values)
    assert fragment in str(info.value)


def test_reconnect_settings_from_the_command_line():
    values = parse_setting_overrides(["reconnect=true", "reconnect_max_gap_mm=3", "reconnect_min_occupancy=0.2"])
    settings = make_settings("fast", **values)
    assert settings.region.reconnect is True
    assert settings.region.reconnect_max_gap_mm == 3.0 and settings.region.reconnect_min_occupancy == 0.2
    # on in the fast preset (measured in bench/RESULTS.md), off in the published recipe
    assert make_settings("fast").region.reconnect and not make_settings("paper").region.reconnect



def test_reconstruct_reports_components(small_tree_case):
    geometry, masks = small_tree_case
    grid = geometry.volume
    for reconnect in (False, True):
        result = reconstruct(geometry, masks, make_settings("fast", steps=60, reconnect=reconnect, device="cpu"))
        assert result.report["grown_voxels"] is not None  # fast grows by default
        assert result.segmentation.any()
        np.testing.assert_array_equal(result.segmentation, result.occupancy >= result.settings.region.threshold)
        counts = result.report["components"]
        assert counts == component_counts(result.segmentation)
        assert counts["components"] >= 1 and 0 < counts["largest_component_fraction"] <= 1
        reconnection = result.report["reconnection"]
        if reconnect:
            assert reconnection["components_after"] == counts["components"]
            assert len(reconnection["bridges"]) == reconnection["joined"]
            for bridge in reconnection["bridges"]:  # in LPS mm inside the grid
                lo, hi = grid.bounds()
                assert np.all((np.asarray(bridge["points_mm"]) >= lo) & (np.asarray(bridge["points_mm"]) <= hi))
            assert reconnection["components_before"] - reconnection["joined"] <= reconnection["components_after"]
        else:
            assert reconnection is None
    plain = reconstruct(geometry, masks, make_settings("fast", steps=60, grow_threshold=0, device="cpu"))
    assert plain.report["grown_voxels"] is None  # 0: off
    grown = reconstruct(geometry, masks, make_settings("fast", steps=60, grow_threshold=0.2, device="cpu"))
    added = grown.segmentation & ~plain.segmentation  # the same fit (same seed), grown
    assert grown.report["grown_voxels"] == int(added.sum()) > 0 and not (plain.segmentation & ~grown.segmentation).any()
    assert np.all(plain.occupancy[added] >= 0.2) and np.all(grown.occupancy[added] == 0.5)  # raised to the threshold
    np.testing.assert_array_equal(grown.segmentation, grown.occupancy >= 0.5)  # what the outputs read
    assert component_counts(grown.segmentation)["components"] <= component_counts(plain.segmentation)["components"]


def test_ground_truth_metrics_show_components_of_result_and_truth():
    from SDFCARLib.cli import metrics_table

    truth = np.zeros((12, 12, 12), bool)
    truth[2:10, 5:7, 5:7] = True
    result = truth.copy()
    result[5:7] = False  # cut in two
    m = volume_metrics(result, truth, (1.0, 1.0, 1.0))
    assert (m["components"], m["components_label"]) == (2, 1)
    table = metrics_table({"reconstruction": m})
    assert "connected components  " in table and "connected components of the truth" in table


def test_a_fragment_beside_a_gap_ends_up_in_the_tree_too():
    occupancy = _cut(_tube(), 20, 24, 0.3)  # the piece before the gap is the smaller one
    occupancy[22, 27, 24] = 0.9  # a one-voxel fragment 1.5 mm off the axis, inside the bridge to come
    segmentation = occupancy >= 0.5
    assert component_counts(segmentation)["components"] == 3
    joined, _, _, info = reconnect_fragments(segmentation, occupancy, (H, H, H))
    assert component_counts(joined)["components"] == 1 and info["components_after"] == 1


def test_growing_the_segmentation_takes_partial_occupancy_connected_to_it_and_nothing_apart():
    from SDFCARLib.optimiser import grown_segmentation
    from SDFCARLib.settings import RegionSettings

    occupancy = np.zeros((30, 9, 9), np.float32)
    occupancy[2:12, 4, 4] = 0.9  # a vessel ...
    occupancy[12:18, 4, 4] = 0.35  # ... thinner than a voxel for 6 voxels ...
    occupancy[18:28, 4, 4] = 0.9  # ... and on
    occupancy[5:9, 1, 1] = 0.35  # a faint blob beside it, not touching
    occupancy[12:18, 4, 5] = 0.15  # below the grow threshold, touching the thin part
    segmentation = occupancy >= 0.5
    assert component_counts(segmentation)["components"] == 2
    grown = grown_segmentation(segmentation, occupancy, RegionSettings(grow_threshold=0.3))
    assert grown[2:28, 4, 4].all() and component_counts(grown)["components"] == 1
    assert int(grown.sum()) == 26  # neither the blob apart nor the voxels below 0.3
    assert grown_segmentation(segmentation, occupancy, RegionSettings()) is segmentation  # 0: off
    # what was removed (occupancy zeroed) is not grown back, and an empty result stays empty
    assert not grown_segmentation(np.zeros_like(segmentation), occupancy, RegionSettings(grow_threshold=0.3)).any()


def test_joining_fragments_fills_the_occupancy_and_field_in_place_up_to_the_gap_asked():
    """optimiser.join_fragments, which reconnect and the final reconnection both call."""
    from SDFCARLib.optimiser import join_fragments

    occupancy = _cut(_tube(), 14, 34, 0.3)  # a 10 mm gap: beyond reconnect's 8 mm, within 12
    grid = VolumeGrid(occupancy.shape, (H, H, H))
    geometry = Geometry(grid, [CArmView(0.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (64, 64))])
    settings = make_settings("fast")
    for gap_mm, pieces in ((8.0, 2), (12.0, 1)):
        occ = occupancy.copy()
        field = field_values(occ, "sdf", settings.field.alpha)
        joined, info = join_fragments(occ >= 0.5, occ, field, geometry, None, settings, gap_mm)
        assert component_counts(joined)["components"] == pieces == info["components_after"]
        np.testing.assert_array_equal(joined, occ >= 0.5)  # the occupancy was raised along the bridge, in place
        np.testing.assert_allclose(field[joined], field_values(occ[joined], "sdf", settings.field.alpha), atol=1e-5)
        for bridge in info["bridges"]:  # in LPS mm, along the cut
            z = np.asarray(bridge["points_mm"])[:, 0]
            assert grid.index_to_world(np.array([[13.0, 0, 0]]))[0, 0] <= z.min() and z.max() <= grid.index_to_world(
                np.array([[34.0, 0, 0]]))[0, 0]


def test_the_final_reconnection_is_wired_into_the_finish_and_reported(small_tree_case):
    """final_reconnect_max_gap_mm: after the width check, the fragments still apart are joined once more."""
    from SDFCARLib.optimiser import fit_field

    geometry, masks = small_tree_case
    # the first reconnection off, so that what the fit leaves apart reaches the last step; one fit, finished both ways
    plain_settings = make_settings("fast", steps=60, reconnect=False, device="cpu")
    fitted = fit_field(geometry, masks, plain_settings)
    plain = fitted.finished()
    joined = fitted.finished(plain_settings.replace(final_reconnect_max_gap_mm=40.0))
    assert plain.report["final_reconnection"] is None  # 0: off
    info = joined.report["final_reconnection"]
    assert info["components_before"] == plain.report["components"]["components"]  # the same fit, finished alike
    assert info["components_after"] == joined.report["components"]["components"] <= info["components_before"]
    assert len(info["bridges"]) == info["joined"] == info["components_before"] - info["components_after"]
    assert info["max_gap_mm"] == 40.0
    assert not (plain.segmentation & ~joined.segmentation).any()  # it only adds
    np.testing.assert_array_equal(joined.segmentation, joined.occupancy >= 0.5)  # what the outputs read

    # the specks go first: a piece below min_fragment_volume_mm3 is removed, never bridged to (two in three are ghosts)
    assert plain.report["components"]["components"] >= 2  # the case has a detached piece to decide on
    cleaned = fitted.finished(plain_settings.replace(final_reconnect_max_gap_mm=40.0, min_fragment_volume_mm3=1e6))
    assert cleaned.report["small_fragments"]["removed_fragments"] == plain.report["components"]["components"] - 1
    assert cleaned.report["final_reconnection"]["components_before"] == 1
    assert cleaned.report["final_reconnection"]["joined"] == 0 and cleaned.report["components"]["components"] == 1


def test_small_fragments_are_the_detached_pieces_below_the_volume_and_never_the_largest():
    from SDFCARLib.pruning import small_fragments

    v = np.zeros((30, 30, 30), bool)
    v[2:28, 5, 5] = True  # the tree: 26 voxels of 0.125 mm³ = 3.25 mm³
    v[20, 20, 20] = True  # a speck: 0.125 mm³
    v[10:14, 20:22, 10:12] = True  # a second piece: 16 voxels = 2 mm³
    spacing = (H, H, H)
    removed, info = small_fragments(v, spacing, 1.0)
    assert removed.sum() == 1 and removed[20, 20, 20]
    assert info == {"fragments": 2, "removed_fragments": 1, "removed_voxels": 1, "min_volume_mm3": 1.0}
    removed, info = small_fragments(v, spacing, 2.5)  # the second piece too; the tree, though below 4 mm³, stays
    assert removed.sum() == 17 and not removed[2:28, 5, 5].any() and info["removed_fragments"] == 2
    assert not small_fragments(v, spacing, 0.0)[0].any()  # 0: off
    assert not small_fragments(v, spacing, 100.0)[0][2:28, 5, 5].any()
    assert small_fragments(np.zeros_like(v), spacing, 1.0)[1]["fragments"] == 0
    with pytest.raises(ValueError, match="min_volume_mm3"):
        small_fragments(v, spacing, -1.0)


def test_the_small_fragment_removal_is_wired_into_the_finish_and_reported(small_tree_case):
    """min_fragment_volume_mm3: last, the detached pieces below the volume are removed from the result and its outputs."""
    from SDFCARLib.optimiser import fit_field

    geometry, masks = small_tree_case
    # nothing joined, so that the fit's detached pieces reach the last step; one fit, finished both ways
    plain_settings = make_settings("fast", steps=60, reconnect=False, drop_unconfirmed_fragments=False,
                                   min_fragment_volume_mm3=0.0, device="cpu")
    fitted = fit_field(geometry, masks, plain_settings)
    plain = fitted.finished()
    cleaned = fitted.finished(plain_settings.replace(min_fragment_volume_mm3=1e9))  # every piece but the largest
    assert plain.report["small_fragments"] is None  # 0: off
    info = cleaned.report["small_fragments"]
    before = plain.report["components"]["components"]
    assert before >= 2  # the fit leaves detached pieces: the test means something
    assert info["fragments"] == before - 1 and info["removed_fragments"] == before - 1
    assert cleaned.report["components"]["components"] == 1
    assert not (cleaned.segmentation & ~plain.segmentation).any()  # it only removes ...
    _, sizes = component_labels(plain.segmentation)
    assert cleaned.segmentation.sum() == sizes.max()  # ... all but the largest piece
    np.testing.assert_array_equal(cleaned.segmentation, cleaned.occupancy >= 0.5)  # what the outputs read


def test_every_component_mends_a_second_tree_too_without_joining_the_two():
    n = 48
    _, j, k = np.meshgrid(*[np.arange(n)] * 3, indexing="ij")
    second = (1.0 / (1.0 + np.exp((np.hypot((j - n // 2 - 16) * H, (k - n // 2) * H) - 1.0) * 4.0))).astype(np.float32)
    # two separate vessels 8 mm apart (5–6 mm between their walls), each broken over 2 mm
    occupancy = np.maximum(_cut(_tube(), 22, 26, 0.3), _cut(second, 10, 14, 0.3))
    segmentation = occupancy >= 0.5
    assert component_counts(segmentation)["components"] == 4
    settings = ReconnectSettings(max_gap_mm=3.0)
    largest_only, _, _, info = reconnect_fragments(segmentation, occupancy, (H, H, H), settings=settings)
    assert info["components_after"] == 3 and info["joined"] == 1 and "trees_grown" not in info
    every = ReconnectSettings(max_gap_mm=3.0, every_component=True)
    joined, _, _, info = reconnect_fragments(segmentation, occupancy, (H, H, H), settings=every)
    assert info["components_after"] == 2 and info["joined"] == 2 and info["trees_grown"] == 2
    labels, sizes = component_labels(joined)
    assert labels[0, n // 2, n // 2] != labels[0, n // 2 + 16, n // 2]  # still two trees, each one piece
    added = joined & ~largest_only
    assert added.any() and not np.any(added & (j < n // 2 + 8))  # the bridge lies on the second vessel only
