"""The epipolar consistency check: a correct pair agrees, a sign-flipped angle does not."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.morphology import skeletonize

from SDFCARLib.consistency import (ConsistencyOptions, agreement_warnings, consistency_warnings, view_agreement,
                                     view_consistency)
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.phantoms import lad_tree, simulate_views, voxelize


@pytest.fixture(scope="module")
def case():
    grid = VolumeGrid((64, 64, 64), (1.5, 1.5, 1.5))
    views = (CArmView(50.0, 25.0, 1000.0, 757.0, (0.6, 0.6), (256, 256)),
             CArmView(-50.0, 25.0, 1000.0, 757.0, (0.6, 0.6), (256, 256)))
    label = voxelize(lad_tree(1), grid)
    _, masks = simulate_views(label, grid, views)
    return Geometry(grid, views), masks


def _with_view2(geometry, **changes):
    v = geometry.views[1]
    values = dict(primary_deg=v.primary_deg, secondary_deg=v.secondary_deg, sid_mm=v.sid_mm, sod_mm=v.sod_mm,
                  pixel_spacing_mm=v.pixel_spacing_mm, detector_shape=v.detector_shape)
    values.update(changes)
    return Geometry(geometry.volume, (geometry.views[0], CArmView(**values)))


def test_a_correct_pair_is_consistent_and_not_flagged(case):
    geometry, masks = case
    consistency = view_consistency(geometry, masks)
    assert len(consistency) == 2 and min(consistency) > 0.95
    assert consistency_warnings(consistency) == []


def test_a_sign_flipped_primary_angle_is_flagged(case):
    geometry, masks = case
    consistency = view_consistency(_with_view2(geometry, primary_deg=50.0), masks)
    assert max(consistency) < 0.5
    warnings = consistency_warnings(consistency)
    assert len(warnings) == 2 and "view 2" in warnings[1] and "angle signs" in warnings[1]


def test_a_sign_flipped_secondary_angle_lowers_the_consistency(case):
    geometry, masks = case
    correct = np.mean(view_consistency(geometry, masks))
    flipped = np.mean(view_consistency(_with_view2(geometry, secondary_deg=-25.0), masks))
    assert flipped < correct - 0.05


def test_options_and_bad_input(case):
    geometry, masks = case
    assert consistency_warnings([0.9, 0.7], ConsistencyOptions(warn_below=0.8))[0].startswith("view 2")
    assert view_consistency(geometry, [masks[0], np.zeros_like(masks[1])])[1] == 0.0
    with pytest.raises(ValueError, match="1 masks for 2 views"):
        view_consistency(geometry, masks[:1])


def test_reconstruct_reports_consistency_and_warns_before_the_loop(case):
    from SDFCARLib.optimiser import reconstruct
    from SDFCARLib.settings import make_settings

    geometry, masks = case
    settings = make_settings("fast", steps=2, levels=4, log2_table_size=12, width=16, depth=2, prune=False,
                             reconnect=False)
    report = reconstruct(geometry, masks, settings).report
    assert len(report["view_consistency"]) == 2 and min(report["view_consistency"]) > 0.95
    assert not any("partner" in w for w in report["warnings"])
    events = []
    flipped = _with_view2(geometry, primary_deg=50.0)
    try:
        report = reconstruct(flipped, masks, settings, progress=events.append).report
    except ValueError as exc:  # the flipped views may not meet at all: refused, which is fine too
        assert "do not intersect" in str(exc)
    else:
        assert any("angle signs" in w for w in report["warnings"])
    warned = [e for e in events if e.get("phase") == "warning" and "partner" in e["message"]]
    assert warned and all(e["step"] == 0 for e in warned)  # before the optimisation


def test_three_views_a_wrong_third_view_is_flagged(case):
    geometry, _ = case
    views = geometry.views + (CArmView(0.0, 30.0, 1000.0, 757.0, (0.6, 0.6), (256, 256)),)
    _, masks = simulate_views(voxelize(lad_tree(1), geometry.volume), geometry.volume, views)
    consistency = view_consistency(Geometry(geometry.volume, views), masks)
    assert len(consistency) == 3 and min(consistency) > 0.95 and consistency_warnings(consistency) == []
    # View 3 recorded as LAO 40 instead of AP: each view's rays must meet both others' vessels, so the
    # check drops for every view (a pair alone is lenient: views 2 and 3 still agree at 0.98).
    wrong = Geometry(geometry.volume, views[:2] + (CArmView(40.0, 30.0, 1000.0, 757.0, (0.6, 0.6), (256, 256)),))
    consistency = view_consistency(wrong, masks)
    assert max(consistency) < 0.6
    assert [w.split(":")[0] for w in consistency_warnings(consistency)] == ["view 1", "view 2", "view 3"]


def _behind_a_shutter(case, columns=90):
    """The case with view 1 behind a shutter over its first ``columns`` columns: its mask shows nothing there."""
    geometry, masks = case
    unseen = np.zeros(masks[0].shape, bool)
    unseen[:, :columns] = True
    return geometry, [masks[0] & ~unseen, masks[1]], unseen


def test_a_vessel_behind_one_views_shutter_is_named_and_not_blamed_on_the_geometry(case):
    geometry, masks, unseen = _behind_a_shutter(case)
    blind = view_agreement(geometry, masks)  # without the frame's field: the old reading
    assert blind[1].consistency < ConsistencyOptions().warn_below and blind[1].one_view_share == 0.0
    assert blind[1].visible_consistency == blind[1].consistency and blind[1].hidden_by == ()

    seen = view_agreement(geometry, masks, [unseen, None])
    assert seen[1].consistency == pytest.approx(blind[1].consistency)  # the same rays, the same partners
    assert seen[1].one_view_share > 0.02 and seen[1].hidden_by == (1,)
    assert seen[1].visible_consistency >= ConsistencyOptions().warn_below
    assert seen[1].visible_consistency == pytest.approx(seen[1].consistency + seen[1].one_view_share, abs=0.02)
    assert seen[0].one_view_share == 0.0  # view 1 shows nothing view 2 cannot
    # the pixels themselves, for the QA overlay: view 2's centreline, as many as the share says, none for view 1
    found = seen[1].one_view_image(masks[1].shape)
    assert found.sum() == round(seen[1].one_view_share * skeletonize(masks[1]).sum())
    assert not (found & ~skeletonize(masks[1])).any() and not seen[0].one_view_image(masks[0].shape).any()
    assert not blind[1].one_view_image(masks[1].shape).any()
    (message,) = agreement_warnings(seen)  # what is missing, why, and what would make it a wrong geometry
    assert message.startswith(f"view 2: {100 * (1 - seen[1].consistency):.0f} % of its vessel centreline has no partner")
    assert "where view 1 cannot show them (behind a collimator" in message and "angle signs" in message
    (blind_message,) = agreement_warnings(blind)
    assert blind_message == consistency_warnings([a.consistency for a in blind])[0] and "cannot show it" not in blind_message
    # a share seen by one view only without a low consistency is named alone
    lenient = ConsistencyOptions(warn_below=0.5)
    (alone,) = agreement_warnings(seen, lenient)
    assert alone.startswith(f"view 2: {100 * seen[1].one_view_share:.0f} % of its vessel centreline runs on where view 1")
    assert "angle signs" not in alone


def test_a_shutter_does_not_hide_a_wrong_angle(case):
    geometry, masks, unseen = _behind_a_shutter(case)
    flipped = view_agreement(_with_view2(geometry, secondary_deg=-25.0), masks, [unseen, None])
    # every view whose consistency is low is told to check the geometry, explained or not
    low = [n for n, a in enumerate(flipped, start=1) if a.consistency < ConsistencyOptions().warn_below]
    warnings = agreement_warnings(flipped)
    assert low and [w.split(":")[0] for w in warnings if "angle signs" in w] == [f"view {n}" for n in low]


def test_vessels_off_one_views_detector_are_named_without_any_frame():
    grid = VolumeGrid((64, 64, 64), (1.5, 1.5, 1.5))
    views = (CArmView(50.0, 25.0, 1000.0, 757.0, (0.6, 0.6), (256, 120)),  # a narrow detector: part of the tree is off it
             CArmView(-50.0, 25.0, 1000.0, 757.0, (0.6, 0.6), (256, 256)))
    _, masks = simulate_views(voxelize(lad_tree(1), grid), grid, views)
    agreements = view_agreement(Geometry(grid, views), masks)
    assert agreements[1].one_view_share > 0.02 and agreements[1].hidden_by == (1,)
    assert agreements[1].visible_consistency >= ConsistencyOptions().warn_below > agreements[1].consistency
    assert "off the detector" in agreement_warnings(agreements)[0]


def test_agreement_input_is_checked(case):
    geometry, masks = case
    with pytest.raises(ValueError, match="1 unseen images for 2 views"):
        view_agreement(geometry, masks, [None])
    assert agreement_warnings(view_agreement(geometry, masks)) == []  # nothing hidden, nothing named
