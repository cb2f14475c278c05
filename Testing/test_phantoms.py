"""Phantoms: procedural coronary trees, the voxeliser, centreline files and view simulation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.phantoms import (
    Branch,
    CentrelineTree,
    lad_tree,
    load_centreline_vtk,
    make_case,
    rca_tree,
    simulate_views,
    voxelize,
)
from SDFCARLib.projector import project_volume

CENTRELINE_721A = Path("/work/shared/data/721A_Centreline.vtk")
TREES = {"rca": rca_tree, "lad": lad_tree}


@pytest.fixture(scope="module", params=[(name, seed) for name in TREES for seed in (0, 7)], ids=lambda p: f"{p[0]}-{p[1]}")
def tree(request):
    name, seed = request.param
    return TREES[name](seed)


# --- procedural trees -------------------------------------------------------------------------------------
@pytest.mark.parametrize("make", [rca_tree, lad_tree])
def test_trees_are_deterministic_per_seed(make):
    a, b, c = make(3), make(3), make(4)
    assert len(a.branches) == len(b.branches)
    for x, y in zip(a.branches, b.branches):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.radii, y.radii)
    assert not np.allclose(a.branches[0].points[:50], c.branches[0].points[:50])


def test_trees_have_branches(tree):
    assert len(tree.branches) >= 5
    assert all(len(b.points) == len(b.radii) >= 10 for b in tree.branches)
    assert tree.total_length_mm() > 150.0


def test_radii_are_realistic_and_taper(tree):
    for branch in tree.branches:
        assert branch.radii.min() >= 0.45 and branch.radii.max() <= 2.2, branch.name
        assert np.all(np.diff(branch.radii) <= 1e-12), f"{branch.name} widens distally"
        assert branch.radii[-1] < branch.radii[0], branch.name
    main = tree.branches[0]
    assert main.radii[0] >= 1.5  # a proximal main vessel is the widest


def test_branches_start_on_their_parent(tree):
    main, *side = tree.branches
    for branch in side:
        others = np.concatenate([b.points for b in tree.branches if b is not branch])
        distance = np.linalg.norm(others - branch.points[0], axis=1)
        assert distance.min() < 1e-6, f"{branch.name} floats {distance.min():.2f} mm from the tree"
        # and a side branch is not wider than the vessel it leaves
        parent = [b for b in tree.branches if b is not branch and np.linalg.norm(b.points - branch.points[0], axis=1).min() < 1e-6]
        parent_radius = min(float(p.radii[np.argmin(np.linalg.norm(p.points - branch.points[0], axis=1))]) for p in parent)
        assert branch.radii[0] <= parent_radius + 1e-9
    # the main vessel is the root: its first point lies on no other branch
    others = np.concatenate([b.points for b in side])
    assert np.linalg.norm(others - main.points[0], axis=1).min() > 1.0


def test_branches_are_tortuous(tree):
    for branch in tree.branches:
        length = np.linalg.norm(np.diff(branch.points, axis=0), axis=1).sum()
        chord = np.linalg.norm(branch.points[-1] - branch.points[0])
        assert length > 1.005 * chord, branch.name
    main = tree.branches[0]
    assert np.linalg.norm(np.diff(main.points, axis=0), axis=1).sum() > 1.3 * np.linalg.norm(main.points[-1] - main.points[0])


def test_centrelines_are_continuous(tree):
    # Sampled every ~0.5 mm: a step of more than 1 mm is a jump (a kink in the vessel), not a bend.
    for branch in tree.branches:
        steps = np.linalg.norm(np.diff(branch.points, axis=0), axis=1)
        worst = int(np.argmax(steps))
        assert steps[worst] < 1.0, f"{branch.name}: {steps[worst]:.2f} mm jump after point {worst}"


def test_tree_fits_the_paper_grid(tree):
    grid = VolumeGrid((128, 128, 128), (0.8, 0.8, 0.8))
    lo, hi = tree.bounds()
    glo, ghi = grid.bounds()
    assert np.all(lo > glo + 1.0) and np.all(hi < ghi - 1.0)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)  # centred on the isocenter
    assert np.max(hi - lo) > 50.0 and np.min(hi - lo) > 25.0  # heart-sized, not a speck


def test_voxelised_tree_is_connected_and_inside(tree):
    from scipy import ndimage

    grid = VolumeGrid((128, 128, 128), (0.8, 0.8, 0.8))  # the paper's grid
    label = voxelize(tree, grid)
    assert label.sum() > 500
    _, components = ndimage.label(label, structure=np.ones((3, 3, 3)))
    assert components == 1
    assert not (label[0].any() or label[-1].any() or label[:, 0].any() or label[:, :, -1].any())


# --- voxeliser ---------------------------------------------------------------------------------------------
def test_voxelised_cylinder_volume():
    # voxelize sweeps a sphere along each segment: a straight branch of radius r and length L is
    # a capsule, πr²L + 4/3·πr³ (for L ≫ r this is πr²L).
    r, length, h = 2.0, 10.0, 0.25
    grid = VolumeGrid((64, 24, 24), (h, h, h))
    tree = CentrelineTree([Branch(np.array([[-length / 2, 0.1, -0.05], [length / 2, 0.1, -0.05]]), np.array([r, r]))])
    label = voxelize(tree, grid)
    expected = (math.pi * r**2 * length + 4 / 3 * math.pi * r**3) / h**3
    assert label.sum() == pytest.approx(expected, rel=0.03)
    # the slab away from the caps is a disc of area πr² per slice
    middle = label[28:36].sum() / 8
    assert middle == pytest.approx(math.pi * r**2 / h**2, rel=0.05)


def test_voxelised_tapering_segment_volume():
    # radius linear along the segment: a frustum πL(r0² + r0·r1 + r1²)/3 plus hemispherical ends.
    r0, r1, length, h = 2.0, 1.0, 12.0, 0.25
    grid = VolumeGrid((72, 24, 24), (h, h, h))
    tree = CentrelineTree([Branch(np.array([[-length / 2, 0.0, 0.0], [length / 2, 0.0, 0.0]]), np.array([r0, r1]))])
    label = voxelize(tree, grid)
    expected = (math.pi * length * (r0**2 + r0 * r1 + r1**2) / 3 + 2 / 3 * math.pi * (r0**3 + r1**3)) / h**3
    assert label.sum() == pytest.approx(expected, rel=0.03)


def test_voxelize_uses_voxel_centres_in_lps():
    grid = VolumeGrid((10, 10, 10), (1.0, 1.0, 1.0), (20.0, 0.0, 0.0))  # grid centred at x = 20 mm
    point = grid.index_to_world([7, 2, 5])
    tree = CentrelineTree([Branch(np.array([point, point]), np.array([0.3, 0.3]))])
    label = voxelize(tree, grid)
    assert label.sum() == 1 and label[7, 2, 5]


# --- centreline files ------------------------------------------------------------------------------------------
@pytest.mark.skipif(not CENTRELINE_721A.is_file(), reason="the 721A centreline lives outside the repository (/work/shared/data) and is absent here")
def test_load_721a_centreline():
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    tree = load_centreline_vtk(CENTRELINE_721A)
    assert tree.name == "721A_Centreline"
    assert len(tree.branches) == 3
    points = tree.all_points()
    # 357 points; the two daughter branches share the bifurcation point with the parent polyline
    assert len(points) == 357 + 2
    assert len(np.unique(points, axis=0)) == 357
    radii = np.concatenate([b.radii for b in tree.branches])
    assert radii.min() == pytest.approx(0.5, abs=0.01) and radii.max() == pytest.approx(2.56, abs=0.01)
    np.testing.assert_allclose(tree.branches[1].points[0], tree.branches[0].points[-1])
    np.testing.assert_allclose(tree.branches[2].points[0], tree.branches[0].points[-1])
    lo, hi = tree.bounds()
    assert np.all((hi - lo) > 50) and np.all((hi - lo) < 75)
    centred = tree.centered()
    clo, chi = centred.bounds()
    np.testing.assert_allclose(clo + chi, 0.0, atol=1e-9)


VTK_HEADER = "# vtk DataFile Version 3.0\ntest\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n0 0 0 5 0 0 10 0 0\n"


def test_load_centreline_alternative_radius_name(tmp_path):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    path = tmp_path / "c.vtk"
    path.write_text(VTK_HEADER + "LINES 1 4\n3 0 1 2\nPOINT_DATA 3\nSCALARS Radius float 1\nLOOKUP_TABLE default\n1.5 1.2 1.0\n")
    tree = load_centreline_vtk(path)
    assert len(tree.branches) == 1
    np.testing.assert_allclose(tree.branches[0].radii, [1.5, 1.2, 1.0])
    np.testing.assert_allclose(tree.branches[0].points[2], [10, 0, 0])


def test_load_centreline_errors(tmp_path):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    with pytest.raises(FileNotFoundError, match="not found"):
        load_centreline_vtk(tmp_path / "missing.vtk")
    no_radius = tmp_path / "no_radius.vtk"
    no_radius.write_text(VTK_HEADER + "LINES 1 4\n3 0 1 2\n")
    with pytest.raises(ValueError, match="radius"):
        load_centreline_vtk(no_radius)
    no_lines = tmp_path / "no_lines.vtk"
    no_lines.write_text(VTK_HEADER + "POINT_DATA 3\nSCALARS radii float 1\nLOOKUP_TABLE default\n1 1 1\n")
    with pytest.raises(ValueError, match="polylines"):
        load_centreline_vtk(no_lines)
    garbage = tmp_path / "garbage.vtk"
    garbage.write_text("this is not a VTK file\n")
    with pytest.raises(ValueError):
        load_centreline_vtk(garbage)


# --- simulation ---------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_case():
    grid = VolumeGrid((32, 32, 32), (1.0, 1.0, 1.0))
    views = [CArmView(30.0, 0.0, 1000.0, 750.0, (1.0, 1.0), (48, 48)), CArmView(-30.0, 20.0, 1000.0, 750.0, (1.0, 1.0), (48, 48))]
    tree = CentrelineTree([Branch(np.array([[-12.0, -5.0, -10.0], [0.0, 3.0, 0.0], [10.0, 0.0, 12.0]]), np.array([2.0, 1.5, 1.0]))])
    return grid, views, tree


def test_simulated_masks_are_thresholded_line_integrals(small_case):
    grid, views, tree = small_case
    label = voxelize(tree, grid)
    line_integrals, masks = simulate_views(label, grid, views)
    for li, mask, view in zip(line_integrals, masks, views):
        assert li.shape == mask.shape == view.detector_shape
        np.testing.assert_array_equal(mask, li > 0.2)
        np.testing.assert_allclose(li, project_volume(label.astype(np.float32), view, grid), rtol=1e-6)
        assert 20 < mask.sum() < 0.5 * mask.size
        assert li.max() <= 2 * 2.0 + 2.0  # a ray crosses at most a diameter plus a voxel staircase
    _, strict = simulate_views(label, grid, views, mask_threshold_mm=1.0)
    for li, mask, loose in zip(line_integrals, strict, masks):
        np.testing.assert_array_equal(mask, li > 1.0)
        assert mask.sum() < loose.sum()


def test_make_case(small_case):
    grid, views, tree = small_case
    case = make_case(tree, Geometry(grid, views), name="tube")
    assert case.name == "tube" and case.label.dtype == bool and case.label.shape == grid.shape
    np.testing.assert_array_equal(case.label, voxelize(tree, grid))
    assert len(case.masks) == len(case.line_integrals) == 2
    assert case.meta["mask_threshold_mm"] == 0.2


def test_simulation_errors(small_case):
    grid, views, tree = small_case
    with pytest.raises(ValueError, match="empty"):
        simulate_views(np.zeros(grid.shape, bool), grid, views)
    with pytest.raises(ValueError, match="does not match"):
        simulate_views(np.ones((4, 4, 4), bool), grid, views)
    far_away = tree.translated((200.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="does not intersect"):
        make_case(far_away, Geometry(grid, views))


@pytest.mark.parametrize("radii, words", [
    ("1.5 nan 1.0", "of its 3 radii are not positive numbers"),  # VTK's ASCII reader reads what follows a nan as 0 or not
    ("1.5 -1.2 1.0", "1 of its 3 radii are not positive numbers"),
    ("0 0 0", "3 of its 3 radii are not positive numbers"),
    ("0.15 0.12 0.10", r"median radius is 0.12, outside the 0.2–5 mm of coronary arteries: are the radii .* in cm"),
    ("1500 1200 1000", r"median radius is 1200"),
])
def test_centreline_radii_that_are_no_coronary_radii_in_mm_are_named(tmp_path, radii, words):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    path = tmp_path / "c.vtk"
    path.write_text(VTK_HEADER + f"LINES 1 4\n3 0 1 2\nPOINT_DATA 3\nSCALARS radii float 1\nLOOKUP_TABLE default\n{radii}\n")
    with pytest.raises(ValueError, match=words):
        load_centreline_vtk(path)


def test_a_centreline_marked_ras_is_read_in_lps_and_a_vector_radius_refused(tmp_path):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    ras = tmp_path / "ras.vtk"
    ras.write_text(VTK_HEADER.replace("\ntest\n", "\nvtk output SPACE=RAS\n")
                   + "LINES 1 4\n3 0 1 2\nPOINT_DATA 3\nSCALARS radii float 1\nLOOKUP_TABLE default\n1.5 1.2 1.0\n")
    np.testing.assert_allclose(load_centreline_vtk(ras).branches[0].points[2], [-10, 0, 0])  # RAS x 10 = LPS x −10
    vector = tmp_path / "vector.vtk"
    vector.write_text(VTK_HEADER + "LINES 1 4\n3 0 1 2\nPOINT_DATA 3\nSCALARS radii float 3\nLOOKUP_TABLE default\n"
                      + "1 1 1 1 1 1 1 1 1\n")
    with pytest.raises(ValueError, match="has 3 components per point"):
        load_centreline_vtk(vector)


def test_length_outside_a_box_clips_each_segment_exactly():
    from SDFCARLib.phantoms import Branch, CentrelineTree

    box = (np.zeros(3), np.full(3, 10.0))
    diagonal = Branch(np.array([[5.0, 5.0, 5.0], [15.0, 15.0, 5.0]]), np.ones(2))  # leaves through the x and y faces at 10
    along_face = Branch(np.array([[0.0, 2.0, 2.0], [0.0, 8.0, 2.0]]), np.ones(2))  # on the x = 0 face: inside
    parallel_outside = Branch(np.array([[-1.0, 2.0, 2.0], [-1.0, 8.0, 2.0], [-1.0, 8.0, 9.0]]), np.ones(3))
    tree = CentrelineTree([diagonal, along_face, parallel_outside])
    assert tree.length_outside_mm(*box) == pytest.approx(5 * math.sqrt(2) + 6 + 7)
    assert CentrelineTree([along_face]).length_outside_mm(*box) == 0.0
