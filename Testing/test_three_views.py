"""A third view removes the ghost two views cannot rule out (issue: more than two views)."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.hull import support_mask
from SDFCARLib.metrics import mask_dice
from SDFCARLib.optimiser import reconstruct
from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize
from SDFCARLib.settings import make_settings

GRID = VolumeGrid((32, 32, 32), (1.0, 1.0, 1.0))
AP, LAO90, LAO45 = (CArmView(a, 0.0, 1000.0, 750.0, (0.5, 0.5), (96, 96)) for a in (0.0, 90.0, 45.0))


def _tube(x, y):
    branch = Branch(np.array([[x, y, -12.0], [x, y, 12.0]], float), np.array([1.5, 1.5]))
    return voxelize(CentrelineTree([branch]), GRID)


@pytest.fixture(scope="module")
def crossing_case():
    # AP sees x, LAO 90 sees y: vessels at (0, −8) and (8, 0) cast the same shadows as vessels at
    # (0, 0) and (8, −8), so two views cannot tell the true pair from that ghost pair. LAO 45 sees
    # (x + y)/√2: the true vessels at ∓5.7 mm, the ghosts both at 0, where it shows no vessel.
    truth = _tube(0.0, -8.0) | _tube(8.0, 0.0)
    ghost = (_tube(0.0, 0.0) | _tube(8.0, -8.0)) & ~truth
    _, masks = simulate_views(truth, GRID, (AP, LAO90, LAO45))
    return truth, ghost, masks


def test_the_two_view_hull_holds_the_ghost_and_the_third_view_excludes_it(crossing_case):
    truth, ghost, masks = crossing_case
    hull2 = support_mask(masks[:2], (AP, LAO90), GRID, margin_mm=0.0)
    hull3 = support_mask(masks, (AP, LAO90, LAO45), GRID, margin_mm=0.0)
    assert np.all(hull2[truth]) and np.all(hull3[truth])
    assert hull2[ghost].mean() > 0.9
    assert hull3[ghost].mean() < 0.05


def test_three_views_reconstruct_without_the_ghost_two_views_keep(crossing_case):
    truth, ghost, masks = crossing_case
    results = {}
    for views in ((AP, LAO90), (AP, LAO90, LAO45)):
        settings = make_settings("fast", steps=100, prune=False, reconnect=False, seed=1, threads=1)
        targets = [m.astype(np.float32) for m in masks[:len(views)]]
        segmentation = reconstruct(Geometry(GRID, views), targets, settings, "mask").segmentation
        results[len(views)] = (mask_dice(segmentation, truth), int((segmentation & ghost).sum()))
    (dice2, ghost2), (dice3, ghost3) = results[2], results[3]
    assert ghost3 < 0.05 * ghost.sum() < ghost2  # the ghost stays with two views, goes with three
    assert dice3 > 0.8 and dice3 > dice2 + 0.1
