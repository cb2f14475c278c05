"""Revival (revival.py): which voxels lie under mask pixels no view's rendering explains, the logit offsets that
lift them, and the fit that gets its gradient back."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from SDFCARLib.geometry import CArmView, VolumeGrid
from SDFCARLib.optimiser import reconstruct, revive_step
from SDFCARLib.revival import EXPLAINED_PATH_MM, revival_offsets, unexplained_in_every_view
from SDFCARLib.settings import ReconstructionError, make_settings

GRID = VolumeGrid((9, 9, 9), (2.0, 2.0, 2.0))
VIEWS = [CArmView(a, 0.0, 1000.0, 750.0, (1.0, 1.0), (64, 64)) for a in (0.0, 90.0)]
CENTRE = np.ravel_multi_index((4, 4, 4), GRID.shape)  # the voxel at the isocenter: the principal point in each view


def _principal_pixel(view):
    r, c, _ = view.project(np.zeros((1, 3)))
    return int(np.rint(r[0])), int(np.rint(c[0]))


def test_a_voxel_is_unexplained_only_where_every_view_leaves_its_mask_pixel_without_path():
    voxels = np.arange(GRID.num_voxels)
    masks = [np.ones((64, 64), bool) for _ in VIEWS]
    empty = [np.zeros((64, 64), np.float32) for _ in VIEWS]
    assert unexplained_in_every_view(empty, masks, VIEWS, GRID, voxels).all()  # nothing rendered: all unexplained

    rendered = [np.zeros((64, 64), np.float32) for _ in VIEWS]
    rendered[1][_principal_pixel(VIEWS[1])] = 2 * EXPLAINED_PATH_MM  # view 2 explains the isocenter's pixel
    found = unexplained_in_every_view(rendered, masks, VIEWS, GRID, voxels)
    assert not found[CENTRE] and found.sum() < GRID.num_voxels
    # the other voxels on view 2's central ray are explained there too; the voxels beside it are not
    r, c, _ = VIEWS[1].project(GRID.voxel_centers(voxels))
    on_ray = (np.rint(r) == _principal_pixel(VIEWS[1])[0]) & (np.rint(c) == _principal_pixel(VIEWS[1])[1])
    np.testing.assert_array_equal(found, ~on_ray)

    no_mask = [m.copy() for m in masks]
    no_mask[0][_principal_pixel(VIEWS[0])] = False  # off view 1's mask: no vessel asked for there
    assert not unexplained_in_every_view(empty, no_mask, VIEWS, GRID, voxels)[CENTRE]


def test_a_view_that_does_not_see_a_voxel_does_not_decide_for_it():
    narrow = CArmView(90.0, 0.0, 1000.0, 750.0, (1.0, 1.0), (4, 4))  # sees only the middle of the grid
    views = [VIEWS[0], narrow]
    masks = [np.ones((64, 64), bool), np.ones((4, 4), bool)]
    rendered = [np.zeros((64, 64), np.float32), np.full((4, 4), 1.0, np.float32)]  # the narrow view explains all it sees
    found = unexplained_in_every_view(rendered, masks, views, GRID, np.arange(GRID.num_voxels))
    r, c, _ = narrow.project(GRID.voxel_centers(np.arange(GRID.num_voxels)))
    seen = (np.rint(r) >= 0) & (np.rint(r) < 4) & (np.rint(c) >= 0) & (np.rint(c) < 4)
    np.testing.assert_array_equal(found, ~seen)


def test_unexplained_rejects_mismatched_inputs():
    masks = [np.ones((64, 64), bool) for _ in VIEWS]
    with pytest.raises(ValueError, match="renderings"):
        unexplained_in_every_view([np.zeros((64, 64))], masks, VIEWS, GRID, np.arange(3))
    with pytest.raises(ValueError, match="detector's shape"):
        unexplained_in_every_view([np.zeros((32, 32))] * 2, masks, VIEWS, GRID, np.arange(3))


def test_offsets_lift_the_chosen_saturated_logits_to_the_revived_occupancy_and_leave_the_rest():
    logits = torch.tensor([-12.0, -2.0, -12.0, -30.0])
    offsets = revival_offsets(logits, np.array([True, True, False, True]), 0.01)
    target = math.log(0.01 / 0.99)
    np.testing.assert_allclose(offsets.numpy(), [target + 12.0, 0.0, 0.0, target + 30.0], rtol=1e-6)
    np.testing.assert_allclose(torch.sigmoid(logits + offsets).numpy()[[0, 3]], [0.01, 0.01], rtol=1e-5)
    with pytest.raises(ValueError, match=r"\(0, 0.5\)"):
        revival_offsets(logits, np.ones(4, bool), 0.5)


@pytest.mark.parametrize("bad, message", [(dict(revive_fraction=1.0), "revive_fraction is the share"),
                                          (dict(revive_fraction=-0.1), "revive_fraction"),
                                          (dict(revive_occupancy=0.0), "revive_occupancy is the occupancy"),
                                          (dict(revive_occupancy=0.5), "revive_occupancy")])
def test_bad_revival_settings_are_refused(bad, message):
    with pytest.raises(ReconstructionError, match=message):
        make_settings("fast", **bad)


def test_the_revival_step():
    assert revive_step(make_settings("fast", steps=400)) is None  # off unless asked
    assert revive_step(make_settings("fast", steps=400, revive_fraction=0.6)) == 240


def test_a_saturated_fit_gets_its_gradient_back_where_the_masks_are_unexplained(tiny_case):
    """A field started saturated (occupancy 10⁻⁶ everywhere) barely moves in its first steps; revived at step 4,
    the same fit explains its masks within a few steps. The written field stays the one whose σ(−α·s) is the
    occupancy, and report.json says what was revived."""
    masks = [m.astype(np.uint8) * 255 for m in tiny_case.masks]

    def fit(fraction):
        return reconstruct(tiny_case.geometry, masks, make_settings("fast", steps=40, seed=3, device="cpu",
                                                                     initial_occupancy=1e-6, revive_fraction=fraction))

    plain, revived = fit(0.0), fit(0.1)
    assert plain.report["revival"] is None
    record = revived.report["revival"]["revivals"]
    assert len(record) == 1 and record[0]["step"] == 4 and record[0]["revived_voxels"] > 100
    assert record[0]["occupancy"] == 0.01
    assert revived.history[9]["loss"] < 0.3 * plain.history[9]["loss"]
    alpha = revived.settings.field.alpha
    np.testing.assert_allclose(revived.occupancy, 1.0 / (1.0 + np.exp(alpha * revived.field.astype(np.float64))), atol=1e-5)


def test_an_ensemble_reports_each_fits_revival_apart(tiny_case):
    """With ensemble_fits each fit revives at its own step; report.json lists the fits' records one per fit
    (as the width exclusion's), not pooled into one list that hides which fit revived what."""
    masks = [m.astype(np.uint8) * 255 for m in tiny_case.masks]
    result = reconstruct(tiny_case.geometry, masks, make_settings("fast", steps=40, seed=3, device="cpu", ensemble_fits=2,
                                                                   initial_occupancy=1e-6, revive_fraction=0.1))
    fits = result.report["revival"]["fits"]
    assert len(fits) == 2
    for record in fits:
        assert [revival["step"] for revival in record["revivals"]] == [4]
        assert record["revivals"][0]["revived_voxels"] > 100
