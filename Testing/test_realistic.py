"""Realistic benchmark input: masks segmented from simulated angiograms, with motion between views."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.metrics import mask_dice
from SDFCARLib.phantoms import lad_tree, simulate_views, voxelize
from SDFCARLib.realistic import RealisticOptions, realistic_input
from SDFCARLib.settings import PROTOCOLS, REALISTIC_PROTOCOLS


@pytest.fixture(scope="module")
def case():
    grid = VolumeGrid((48, 48, 48), (2.0, 2.0, 2.0))
    views = tuple(CArmView(a, 0.0, 1000.0, 757.0, (0.6, 0.6), (200, 200)) for a in (30.0, -30.0))
    geometry = Geometry(grid, views)
    return geometry, voxelize(lad_tree(2), grid)


def test_masks_come_from_images_and_the_heart_moves_within_bounds(case):
    geometry, label = case
    result = realistic_input(label, geometry, seed=4)
    _, nominal = simulate_views(label, geometry.volume, geometry.views)
    assert len(result.masks) == 2 and all(m.dtype == bool and m.shape == (200, 200) for m in result.masks)
    assert all(f.dtype == np.uint16 for f in result.frames)
    # segmented, not copied from the truth: close to the moved silhouette but not equal to it
    for mask, truth in zip(result.masks, result.true_masks):
        assert 0.6 < mask_dice(mask, truth) < 1.0
    motion = result.info["motion"]
    assert motion[0] == {"rotation_deg": [0.0] * 3, "translation_mm": [0.0] * 3}
    assert 0.5 * 3.0 <= np.linalg.norm(motion[1]["translation_mm"]) <= 3.0 + 1e-6
    assert 0.5 * 2.0 <= np.linalg.norm(motion[1]["rotation_deg"]) <= 2.0 + 1e-6
    assert result.true_views[1].has_object_motion and not result.geometry.views[1].has_object_motion
    assert not np.array_equal(result.true_masks[1], nominal[1])  # view 2 saw the moved heart
    assert {"mask_dice", "mask_cldice", "mask_components"} <= set(result.info["views"][0])


def test_same_seed_same_input_and_static_has_no_motion(case):
    geometry, label = case
    a, b = realistic_input(label, geometry, seed=1), realistic_input(label, geometry, seed=1)
    assert all(np.array_equal(x, y) for x, y in zip(a.masks, b.masks))
    static = realistic_input(label, geometry, seed=1, options=RealisticOptions(0.0, 0.0))
    assert not static.true_views[1].has_object_motion
    for options, words in ((RealisticOptions(-1.0), "max_shift_mm must be a finite number, 0 or more, got -1.0"),
                           (RealisticOptions(float("nan")), "max_shift_mm must be a finite number"),
                           (RealisticOptions(max_rotation_deg=float("inf")), "max_rotation_deg must be a finite number"),
                           (RealisticOptions(snr=float("inf")), "snr must be a positive finite number"),
                           (RealisticOptions(collimator_fraction=0.5), "collimator_fraction is the share of each side"),
                           (RealisticOptions(collimator_fraction=float("nan")), "collimator_fraction")):
        with pytest.raises(ValueError, match=words):
            options.check()
    for seed in (-1, 1.7, None):
        with pytest.raises(ValueError, match="seed must be a whole number, 0 or more"):
            realistic_input(label, geometry, seed=seed)


def test_realistic_protocols_are_registered():
    assert set(REALISTIC_PROTOCOLS) <= set(PROTOCOLS)
    assert all(PROTOCOLS[p][1] == "mask" for p in REALISTIC_PROTOCOLS)


def test_display_frames_are_the_linear_frames_processed_and_say_disp(case):
    from SDFCARLib.display_processing import display_processed

    geometry, label = case
    linear = realistic_input(label, geometry, seed=3, options=RealisticOptions(0.0, 0.0))
    shown = realistic_input(label, geometry, seed=3, options=RealisticOptions(0.0, 0.0, display=True))
    assert linear.frame_intensity is None and shown.frame_intensity == ["DISP", "DISP"]
    assert shown.info["display"] is True and linear.info["display"] is False
    for lin, disp, view in zip(linear.frames, shown.frames, geometry.views):
        # the same scene and noise (no draw for the processing), stored for display
        assert disp.dtype == np.uint8 and np.array_equal(disp, display_processed(lin, view.pixel_spacing_mm))
    # the masks are segmented on the processed frames, and still find the vessels
    for mask, truth in zip(shown.masks, shown.true_masks):
        assert 0.5 < mask_dice(mask, truth) < 1.0
    assert REALISTIC_PROTOCOLS["realistic-static-display-lao30-rao30"]["display"] is True


def test_collimated_frames_hide_what_the_shutter_covers_from_the_masks(case):
    geometry, label = case
    open_field = realistic_input(label, geometry, seed=5, options=RealisticOptions(0.0, 0.0))
    options = RealisticOptions(0.0, 0.0, collimator_fraction=0.12)
    collimated = realistic_input(label, geometry, seed=5, options=options)
    assert collimated.info["collimator_fraction"] == 0.12 and open_field.info["collimator_fraction"] == 0.0
    edge = int(0.12 * 200)  # the shutters cover 12 % of each side: 24 pixels
    for shut, open_mask, truth in zip(collimated.masks, open_field.masks, collimated.true_masks):
        outer = np.zeros((200, 200), bool)
        outer[:edge], outer[-edge:], outer[:, :edge], outer[:, -edge:] = True, True, True, True
        assert truth[outer].any() and not shut[outer].any()  # vessels are there, the mask cannot show them
        inner = ~ndimage.binary_dilation(outer, iterations=12)
        assert mask_dice(shut[inner], open_mask[inner]) > 0.8  # in the open field the masks are alike
    registered = REALISTIC_PROTOCOLS["realistic-static-collimated-lao30-rao30"]
    assert registered["collimator_fraction"] > 0 and registered["max_shift_mm"] == 0.0
