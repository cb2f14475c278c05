"""The thin vessels' weights in L_occ (``thin_weights.py``) against two straight tubes of known width."""

import numpy as np
import pytest
import torch

from SDFCARLib.losses import occupancy_loss
from SDFCARLib.settings import ReconstructionError, make_settings
from SDFCARLib.thin_weights import thin_vessel_weights


def two_tubes(thick_half_width=6, thin_half_width=1):
    """A horizontal band 2·6 px wide and one 2·1 px wide, 50 px long: radii 6 and 1 at their centrelines."""
    mask = np.zeros((60, 60), bool)
    mask[16 - thick_half_width:16 + thick_half_width, 5:55] = True
    mask[40 - thin_half_width:40 + thin_half_width, 5:55] = True
    return mask


def test_weights_follow_the_radius_ratio_and_keep_the_masks_mean():
    mask = two_tubes()
    for power in (0.5, 1.0, 2.0):
        weights = thin_vessel_weights(mask, power)
        assert weights.dtype == np.float32 and weights.shape == mask.shape
        assert weights[mask].mean() == pytest.approx(1.0, rel=1e-5)
        assert np.all(weights[~mask] == 1.0)
        # the middle of each tube, and the thick tube's border reads the thick tube's radius
        thick_mid, thick_border, thin = weights[16, 30], weights[10, 30], weights[40, 30]
        assert thick_border == pytest.approx(thick_mid)
        assert thin / thick_mid == pytest.approx(6.0 ** power, rel=0.05)


def test_power_zero_and_an_empty_mask_weigh_every_pixel_alike():
    assert np.all(thin_vessel_weights(two_tubes(), 0.0) == 1.0)
    assert np.all(thin_vessel_weights(np.zeros((8, 8), bool), 1.0) == 1.0)


def test_bad_input_is_refused_with_the_reason():
    with pytest.raises(ValueError, match="2D"):
        thin_vessel_weights(np.zeros((2, 8, 8), bool), 1.0)
    with pytest.raises(ValueError, match="power"):
        thin_vessel_weights(two_tubes(), -1.0)
    with pytest.raises(ValueError, match="min_radius_px"):
        thin_vessel_weights(two_tubes(), 1.0, min_radius_px=0.0)
    with pytest.raises(ReconstructionError, match="thin_vessel_weight_power"):
        make_settings("fast", thin_vessel_weight_power=-0.5)


def test_occupancy_loss_weighs_each_pixels_squared_difference():
    target = torch.tensor([[1.0, 1.0], [0.0, 0.0]])
    image = torch.tensor([[0.5, 0.0], [0.0, 0.5]])
    weight = torch.tensor([[2.0, 1.0], [1.0, 4.0]])
    assert float(occupancy_loss(image, target, weight)) == pytest.approx((2 * 0.25 + 1.0 + 0 + 4 * 0.25) / 4)
    assert float(occupancy_loss(image, target)) == pytest.approx((0.25 + 1.0 + 0.25) / 4)


def test_the_fit_weighs_l_occ_by_the_masks_thin_vessels_only_when_asked(tiny_case):
    from SDFCARLib.optimiser import build_problem

    masks = [m.astype(np.uint8) * 255 for m in tiny_case.masks]
    plain = build_problem(tiny_case.geometry, masks, make_settings("fast", device="cpu"), "mask")
    assert all(t.pixel_weight is None for t in plain.view_targets)
    weighed = build_problem(tiny_case.geometry, masks, make_settings("fast", device="cpu", thin_vessel_weight_power=1.0),
                            "mask")
    for target, mask in zip(weighed.view_targets, tiny_case.masks):
        weight = target.pixel_weight.cpu().numpy()
        np.testing.assert_allclose(weight, thin_vessel_weights(mask, 1.0))
        assert weight[mask].mean() == pytest.approx(1.0, rel=1e-5) and weight[mask].max() > 1.5
