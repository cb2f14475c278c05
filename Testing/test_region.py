"""Grid placement on the masks' region, mask coverage, and GEOM.json's automatic volume."""

from __future__ import annotations

import json

import numpy as np
import pytest

from SDFCARLib.geometry import CArmView, GeometryError, VolumeGrid
from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize
from SDFCARLib.region import (STAND_IN_VOLUME, RegionError, locate_region, mask_coverage, place_volume,
                              read_geometry)

OFFSET = np.array([42.0, -25.0, 30.0])  # the heart is not at the isocenter


@pytest.fixture(scope="module")
def off_centre_case():
    views = [CArmView(a, b, 1000.0, 750.0, (1.0, 1.0), (224, 224)) for a, b in ((30.0, 0.0), (-30.0, 20.0))]
    tree = CentrelineTree([
        Branch(OFFSET + np.array([[-30.0, -5.0, 25.0], [0.0, 0.0, 0.0], [10.0, 5.0, -30.0]]), np.array([3.0, 2.5, 2.0])),
        Branch(OFFSET + np.array([[0.0, 0.0, 0.0], [28.0, -6.0, -12.0]]), np.array([2.5, 2.0])),
    ])
    truth_grid = VolumeGrid((80, 80, 80), (2.0, 2.0, 2.0))  # 160 mm around the isocenter holds the whole tree
    label = voxelize(tree, truth_grid)
    _, masks = simulate_views(label, truth_grid, views)
    return views, masks, tree, truth_grid, label


def _inside(grid: VolumeGrid, points: np.ndarray) -> np.ndarray:
    lo, hi = grid.bounds()
    return np.all((points >= lo) & (points <= hi), axis=-1)


def test_the_placed_grid_holds_an_off_centre_tree_the_default_box_cuts(off_centre_case):
    views, masks, tree, truth_grid, label = off_centre_case
    tube_voxels = truth_grid.voxel_centers(np.flatnonzero(label.reshape(-1)))
    default = VolumeGrid((64, 64, 64), (1.6, 1.6, 1.6))  # the 102 mm box at the isocenter
    assert not _inside(default, tube_voxels).all()
    placement = locate_region(views, masks, spacing_mm=1.6)
    grid = placement.grid
    assert grid.spacing_mm == (1.6, 1.6, 1.6)  # the voxel size is kept
    assert _inside(grid, tube_voxels).all()
    # placed on the tree and its ghosts (two views leave the depth loosely bound), not the search box
    assert max(grid.extent_mm) < 170, grid
    assert np.linalg.norm(np.asarray(grid.center_mm) - OFFSET) < 20
    low, high = mask_coverage(masks, views, default), mask_coverage(masks, views, grid)
    assert all(c > 0.97 for c in high), high
    assert min(low) < 0.9 and all(a < b for a, b in zip(low, high)), (low, high)
    assert placement.to_dict()["grid"] == grid.to_dict()


def test_voxel_size_is_kept_anisotropic_too(off_centre_case):
    views, masks, *_ = off_centre_case
    grid = place_volume(views, masks, spacing_mm=(0.8, 1.0, 1.2), margin_mm=5.0)
    assert grid.spacing_mm == (0.8, 1.0, 1.2)
    extent = np.asarray(grid.extent_mm)
    assert np.all(extent >= 10.0)  # at least the two margins
    assert extent[0] / grid.shape[0] == pytest.approx(0.8)


def test_noisy_masks_give_a_clear_error(off_centre_case):
    views, masks, *_ = off_centre_case
    rng = np.random.default_rng(0)
    noise = [m | (rng.random(m.shape) < 0.3) for m in masks]
    with pytest.raises(RegionError, match=r"more than 256³: implausibly large.*Clean the masks"):
        place_volume(views, noise, spacing_mm=0.8)


def test_masks_that_never_meet_give_a_clear_error():
    views = [CArmView(0.0, 0.0, 1000.0, 750.0, (1.0, 1.0), (128, 128)),
             CArmView(90.0, 0.0, 1000.0, 750.0, (1.0, 1.0), (128, 128))]
    top, bottom = np.zeros((128, 128), bool), np.zeros((128, 128), bool)
    top[5:15, 60:70] = True  # rows are z: view 1 sees the vessel high up, view 2 low down
    bottom[110:120, 60:70] = True
    with pytest.raises(RegionError, match="do not meet.*each mask belongs to its view"):
        place_volume(views, [top, bottom], spacing_mm=1.0)


def test_geometry_json_with_an_automatic_volume(tmp_path, tiny_geometry):
    data = tiny_geometry.to_dict()
    for volume, spacing in (("auto", 0.8), (None, 0.8), ({"auto": True, "spacing_mm": 0.5}, 0.5)):
        entry = dict(data)
        if volume is None:
            del entry["volume"]
        else:
            entry["volume"] = volume
        path = tmp_path / "geom.json"
        path.write_text(json.dumps(entry), encoding="utf-8")
        geometry, request = read_geometry(path)
        assert request is not None and request.spacing_mm == (spacing,) * 3
        assert geometry.volume == STAND_IN_VOLUME and geometry.views == tiny_geometry.views
    path.write_text(json.dumps(data), encoding="utf-8")
    geometry, request = read_geometry(path)
    assert request is None and geometry == tiny_geometry
    path.write_text(json.dumps({**data, "volume": {"auto": True, "shape": [8, 8, 8]}}), encoding="utf-8")
    with pytest.raises(GeometryError, match="unknown field.*shape"):
        read_geometry(path)
    path.write_text(json.dumps({**data, "volume": "automatic"}), encoding="utf-8")
    with pytest.raises(GeometryError, match='or "auto"'):
        read_geometry(path)
