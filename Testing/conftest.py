"""Shared fixtures: a tiny geometry and a tiny simulated case, small enough for 2 CPU cores.

The tiny case is a three-branch tube tree (radii 2.5–4 mm) on a 32³ grid at 2 mm, seen in an
LAO 30 / RAO 30 pair on a 96² detector at 1 mm: every view sees it, and simulation takes seconds.
"""

from __future__ import annotations

import os

# Under pytest-xdist each worker would run torch and BLAS on every core, so `make test`'s two workers ran four threads
# on two cores; one thread per worker instead (read by torch and OpenBLAS when they load, hence before the imports).
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    os.environ.setdefault("OMP_NUM_THREADS", "1")

import json
from pathlib import Path
from typing import Any, Dict

import numpy as np
import pytest

from SDFCARLib.geometry import Geometry, standard_geometry

TINY_SHAPE = (32, 32, 32)
TINY_SPACING_MM = 2.0
TINY_DETECTOR = (96, 96)
TINY_DETECTOR_SPACING_MM = 1.0


def tiny_geometry_dict() -> Dict[str, Any]:
    """The tiny geometry as GEOM.json content (a fresh dict each call, free to corrupt)."""
    return standard_geometry("lao30-rao30", volume_shape=TINY_SHAPE, spacing_mm=TINY_SPACING_MM,
                             detector_shape=TINY_DETECTOR, detector_spacing_mm=TINY_DETECTOR_SPACING_MM).to_dict()


def write_json(path: Path, data: Any) -> Path:
    path.write_text(json.dumps(data, indent=2), encoding="utf-8")
    return path


def tiny_tree():
    from SDFCARLib.phantoms import Branch, CentrelineTree

    return CentrelineTree([
        Branch(np.array([[-20.0, -5.0, 20.0], [0.0, 0.0, 0.0], [5.0, 5.0, -20.0]]), np.array([4.0, 3.5, 3.0]), "main"),
        Branch(np.array([[0.0, 0.0, 0.0], [20.0, -5.0, -10.0]]), np.array([3.0, 2.5]), "side"),
    ], "tiny")


@pytest.fixture(scope="session")
def tiny_geometry() -> Geometry:
    return Geometry.from_dict(tiny_geometry_dict())


@pytest.fixture(scope="session")
def tiny_case(tiny_geometry):
    """Label, line integrals and masks of the tiny tree (simulated once per test session)."""
    from SDFCARLib.phantoms import make_case

    return make_case(tiny_tree(), tiny_geometry, name="tiny")


@pytest.fixture(scope="session")
def small_tree_case():
    """A two-view case small enough to reconstruct in seconds: (geometry, masks) of one tapering tube, 24³ at 2 mm,
    LAO 30 / RAO 30 on 64² at 1 mm."""
    from SDFCARLib.geometry import CArmView, VolumeGrid
    from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize

    grid = VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0))
    views = [CArmView(a, 0.0, 1000.0, 750.0, (1.0, 1.0), (64, 64)) for a in (30.0, -30.0)]
    tree = CentrelineTree([Branch(np.array([[-12.0, -6.0, -10.0], [0.0, 2.0, 0.0], [12.0, 6.0, 10.0]]),
                                  np.array([3.0, 2.5, 2.0]))])
    _, masks = simulate_views(voxelize(tree, grid), grid, views)
    return Geometry(grid, views), masks


@pytest.fixture
def geometry_file(tmp_path) -> Path:
    return write_json(tmp_path / "geometry.json", tiny_geometry_dict())


@pytest.fixture
def mask_files(tmp_path, tiny_case):
    """The tiny case's two masks as 0/255 PNGs."""
    from SDFCARLib.io import write_mask_png

    return [write_mask_png(tmp_path / f"view{n}_mask.png", m) for n, m in enumerate(tiny_case.masks, start=1)]


@pytest.fixture(scope="session")
def tube_frames():
    """A 2 mm tube both views of LAO 30 / RAO 30 see almost side-on, its simulated angiograms and the masks
    segmented from them (``realistic.RealisticInput``), and centreline points and tangents clear of its ends."""
    from SDFCARLib.analysis.phantoms import grid_around, straight_tube, voxelize_exact
    from SDFCARLib.realistic import RealisticOptions, realistic_input

    tube = straight_tube(30.0, 2.0, (0.2, 0.25, 1.0))
    grid = grid_around(tube.tree, 0.2)
    realistic = realistic_input(voxelize_exact(tube.tree, grid), Geometry(grid, standard_geometry("lao30-rao30").views), 3,
                                RealisticOptions(max_shift_mm=0.0, max_rotation_deg=0.0))
    direction = np.asarray(tube.truth["direction"])
    s = np.linspace(-11.0, 11.0, 23)  # clear of the flat ends
    return realistic, s[:, None] * direction[None, :], np.repeat(direction[None], len(s), axis=0)
