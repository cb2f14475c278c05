"""Visual hull: contains the object, is close to it for a sphere, and lies inside the support."""

from __future__ import annotations

import math

import numpy as np
import pytest

from SDFCARLib.geometry import CArmView, VolumeGrid
from SDFCARLib.hull import support_mask, visual_hull
from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize


@pytest.fixture(scope="module")
def tube_case():
    grid = VolumeGrid((32, 32, 32), (1.0, 1.0, 1.0))
    views = [CArmView(30.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (96, 96)),
             CArmView(-30.0, 15.0, 1000.0, 750.0, (0.5, 0.5), (96, 96))]
    tree = CentrelineTree([
        Branch(np.array([[-12.0, -4.0, -11.0], [0.0, 3.0, 0.0], [11.0, -2.0, 12.0]]), np.array([2.0, 1.5, 1.0])),
        Branch(np.array([[0.0, 3.0, 0.0], [8.0, 8.0, -9.0]]), np.array([1.2, 0.7])),
    ])
    label = voxelize(tree, grid)
    _, masks = simulate_views(label, grid, views)
    return grid, views, label, masks


def test_hull_contains_the_label(tube_case):
    grid, views, label, masks = tube_case
    hull = visual_hull(masks, views, grid)
    assert hull.shape == grid.shape and hull.dtype == bool
    assert not np.any(label & ~hull)
    assert hull.sum() > label.sum()  # two views cannot pin the tree down exactly


def test_hull_of_one_view_contains_hull_of_two(tube_case):
    grid, views, _, masks = tube_case
    both = visual_hull(masks, views, grid)
    for mask, view in zip(masks, views):
        single = visual_hull([mask], [view], grid)
        assert not np.any(both & ~single)
        assert single.sum() > both.sum()


def test_hull_voxels_project_into_every_mask(tube_case):
    grid, views, _, masks = tube_case
    hull = visual_hull(masks, views, grid)
    centres = grid.voxel_centers(np.flatnonzero(hull))
    for mask, view in zip(masks, views):
        row, col, _ = view.project(centres)
        assert mask[np.rint(row).astype(int), np.rint(col).astype(int)].all()


def test_support_contains_the_hull(tube_case):
    grid, views, label, masks = tube_case
    hull = visual_hull(masks, views, grid)
    for margin in (0.0, 0.5, 2.0):
        support = support_mask(masks, views, grid, margin_mm=margin)
        assert not np.any(hull & ~support)
        assert not np.any(label & ~support)
    wide, narrow = support_mask(masks, views, grid, 2.0), support_mask(masks, views, grid, 0.0)
    assert not np.any(narrow & ~wide) and wide.sum() > narrow.sum()


def test_hull_of_a_sphere_from_orthogonal_views():
    # Seen from AP and LAO 90 (nearly parallel rays), a sphere's hull is the intersection of two
    # perpendicular cylinders of the sphere's radius, the Steinmetz solid of volume 16/3·R³, whose
    # farthest points are R·√2 from the centre.
    radius, h = 7.0, 0.5
    grid = VolumeGrid((40, 40, 40), (h, h, h))
    centres = grid.voxel_centers()
    sphere = (np.linalg.norm(centres, axis=-1) <= radius).reshape(grid.shape)
    views = [CArmView(a, 0.0, 1000.0, 750.0, (0.25, 0.25), (96, 96)) for a in (0.0, 90.0)]
    steinmetz = 16 / 3 * radius**3
    distance = np.linalg.norm(centres, axis=-1).reshape(grid.shape)

    # exact silhouettes (pixels whose ray passes within R of the centre): the hull's own geometry
    exact = []
    for view in views:
        origin, direction = view.rays(*view.pixel_grid())
        w = -origin
        exact.append(np.linalg.norm(w - (direction @ w)[..., None] * direction, axis=-1) <= radius)
    hull = visual_hull(exact, views, grid)
    assert hull.sum() * h**3 == pytest.approx(steinmetz, rel=0.02)
    assert distance[hull].max() <= radius * math.sqrt(2) + h

    # simulated masks (line integral > 0.2 mm): a superset of the sphere, close to the solid
    _, masks = simulate_views(sphere, grid, views)
    hull = visual_hull(masks, views, grid)
    assert not np.any(sphere & ~hull)
    assert steinmetz <= hull.sum() * h**3 <= 1.1 * steinmetz
    assert distance[hull].max() <= radius * math.sqrt(2) + 2 * h


def test_margin_widens_the_hull(tube_case):
    grid, views, _, masks = tube_case
    plain = visual_hull(masks, views, grid)
    wider = visual_hull(masks, views, grid, margin_px=3.0)
    footprint = visual_hull(masks, views, grid, include_footprint=True)
    assert not np.any(plain & ~wider) and wider.sum() > plain.sum()
    assert not np.any(plain & ~footprint) and footprint.sum() > plain.sum()


def test_hull_errors(tube_case):
    grid, views, _, masks = tube_case
    with pytest.raises(ValueError, match="2 masks for 1 views"):
        visual_hull(masks, views[:1], grid)
    with pytest.raises(ValueError, match="detector shape"):
        visual_hull([masks[0][:50], masks[1]], views, grid)


def test_empty_mask_gives_empty_hull(tube_case):
    grid, views, _, masks = tube_case
    hull = visual_hull([np.zeros_like(masks[0]), masks[1]], views, grid)
    assert not hull.any()


# --- field of view ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cropped_case():
    """A tube that runs out of view 2's small detector but stays on view 1's."""
    grid = VolumeGrid((24, 24, 40), (1.0, 1.0, 1.0))
    views = [CArmView(0.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 128)),
             CArmView(90.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (48, 128))]  # view 2 sees |z| ≲ 9 mm only
    tree = CentrelineTree([Branch(np.array([[-8.0, 0.0, -18.0], [0.0, 2.0, 0.0], [8.0, -2.0, 18.0]]),
                                  np.array([1.5, 1.5, 1.5]))])
    label = voxelize(tree, grid)
    _, masks = simulate_views(label, grid, views)
    return grid, views, label, masks


def test_a_vessel_leaving_one_detector_stays_in_the_support(cropped_case):
    grid, views, label, masks = cropped_case
    z = grid.voxel_centers()[:, 2].reshape(grid.shape)
    outside_view2 = label & (np.abs(z) > 12)
    assert outside_view2.sum() > 50  # the case does what it says
    strict = visual_hull(masks, views, grid, include_footprint=True, fov_aware=False)
    assert np.any(outside_view2 & ~strict)  # the old rule cut the tree at view 2's detector edge
    support = support_mask(masks, views, grid, margin_mm=0.5)
    assert not np.any(label & ~support)
    # where both views see, view 2 still constrains: the support is the strict hull there
    both_see = np.abs(z) < 6
    assert np.array_equal(support & both_see, visual_hull(masks, views, grid, margin_px=[
        0.5 * v.magnification / 0.5 for v in views], include_footprint=True, fov_aware=False) & both_see)
    # off view 2's detector the support is view 1's back-projection (its mask's cone), not the whole slab
    cone = visual_hull(masks[:1], views[:1], grid, margin_px=0.5 * views[0].magnification / 0.5, include_footprint=True)
    off = np.abs(z) > 12
    unbounded = support_mask(masks, views, grid, margin_mm=0.5, one_view_reach_mm=None)
    assert np.array_equal(unbounded & off, cone & off) and unbounded[off].mean() < 0.5
    assert not np.any(support & ~unbounded)


def test_a_collimated_border_does_not_constrain(cropped_case):
    grid, views, label, masks = cropped_case
    view1 = views[0]
    fov = np.ones(view1.detector_shape, dtype=bool)
    fov[:, :60] = False  # a collimator leaf over the left columns of view 1
    clipped = [masks[0] & fov, masks[1]]
    assert clipped[0].sum() < masks[0].sum()
    without = support_mask(clipped, views, grid)
    with_fov = support_mask(clipped, views, grid, fields_of_view=[fov, None])
    covered = label & (np.abs(grid.voxel_centers()[:, 2].reshape(grid.shape)) < 8)  # view 2 sees this part
    assert np.any(covered & ~without)
    assert not np.any(covered & ~with_fov)
    with pytest.raises(ValueError, match="field-of-view image shape"):
        support_mask(clipped, views, grid, fields_of_view=[fov[:10], None])


def test_of_three_views_two_place_what_the_third_could_not_see():
    grid = VolumeGrid((24, 24, 40), (1.0, 1.0, 1.0))
    views = [CArmView(a, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 128)) for a in (0.0, 90.0, 45.0)]
    tree = CentrelineTree([Branch(np.array([[-4.0, 2.0, -18.0], [0.0, 0.0, 0.0], [4.0, -2.0, 18.0]]),
                                  np.array([1.5, 1.5, 1.5]))])
    label = voxelize(tree, grid)
    _, masks = simulate_views(label, grid, views)
    fov = np.ones((128, 128), bool)
    fov[:40] = False  # view 3's collimator over the top rows: the head end, z ≳ 9 mm (rows run along −z)
    masks = [masks[0], masks[1], masks[2] & fov]
    upper = label & (grid.voxel_centers()[:, 2].reshape(grid.shape) > 12)
    assert upper.sum() > 40
    assert np.any(upper & ~support_mask(masks, views, grid))  # view 3's empty mask forbade the head end
    # views 1 and 2 see it and place it in depth: no reach from the part all three see bounds it
    kept = support_mask(masks, views, grid, fields_of_view=[None, None, fov], one_view_reach_mm=0.0)
    assert not np.any(upper & ~kept)


def test_voxels_no_view_sees_are_left_out():
    grid = VolumeGrid((20, 20, 20), (4.0, 4.0, 4.0))  # 80 mm: larger than either detector's view
    views = [CArmView(0.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (64, 64)),
             CArmView(90.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (64, 64))]
    masks = [np.ones((64, 64), bool), np.ones((64, 64), bool)]
    hull = visual_hull(masks, views, grid, fov_aware=True)
    centres = grid.voxel_centers()
    seen = np.zeros(grid.num_voxels, bool)
    for view in views:
        r, c, _ = view.project(centres)
        seen |= (np.rint(r) >= 0) & (np.rint(r) < 64) & (np.rint(c) >= 0) & (np.rint(c) < 64)
    assert np.array_equal(hull.reshape(-1), seen) and not seen.all()


def test_the_one_view_reach_bounds_the_support(cropped_case):
    grid, views, label, masks = cropped_case
    z = grid.voxel_centers()[:, 2].reshape(grid.shape)
    unbounded = support_mask(masks, views, grid, one_view_reach_mm=None)
    short = support_mask(masks, views, grid, one_view_reach_mm=4.0)
    assert not np.any(short & ~unbounded)
    # view 2 sees |z| ≲ 9 mm: with a 4 mm reach nothing beyond about 13 mm is left, unbounded it is
    assert not short[np.abs(z) > 15].any() and unbounded[np.abs(z) > 15].any()
    assert np.array_equal(short[np.abs(z) < 6], unbounded[np.abs(z) < 6])
