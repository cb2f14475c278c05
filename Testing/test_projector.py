"""Cone-beam projector: line integrals against closed forms, linearity, support and gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from SDFCARLib.geometry import CArmView, VolumeGrid
from SDFCARLib.projector import ConeBeamProjector, project_volume


def ray_geometry(view: CArmView):
    rows, cols = view.pixel_grid()
    return view.rays(rows, cols)


def distance_to_rays(view: CArmView, point) -> np.ndarray:
    """Distance (mm) from ``point`` to every pixel's ray."""
    origin, direction = ray_geometry(view)
    w = np.asarray(point, float) - origin
    along = direction @ w
    return np.linalg.norm(w - along[..., None] * direction, axis=-1)


def box_chords(view: CArmView, grid: VolumeGrid) -> np.ndarray:
    """Exact length (mm) of every pixel's ray inside the grid's bounding box (slab method)."""
    origin, direction = ray_geometry(view)
    lo, hi = grid.bounds()
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / direction
        t2 = (hi - origin) / direction
    t_in = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_out = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.clip(t_out - t_in, 0.0, None)


def render(volume: np.ndarray, view: CArmView, grid: VolumeGrid) -> np.ndarray:
    projector = ConeBeamProjector(view, grid, dtype=torch.float64)
    with torch.no_grad():
        return projector.render(torch.as_tensor(volume.reshape(-1), dtype=torch.float64)).numpy()


# --- forward values -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "angles, spacing, centre",
    [
        ((0.0, 0.0), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)),
        ((90.0, 0.0), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)),
        ((-30.0, 25.0), (1.0, 0.8, 1.2), (3.0, -2.0, 1.0)),  # anisotropic voxels, grid off the isocenter
    ],
)
def test_gaussian_blob_line_integrals(angles, spacing, centre):
    # f(x) = exp(−|x − c|² / 2σ²) integrates along a line at distance d from c to σ√(2π)·exp(−d²/2σ²).
    # σ = 4 voxels keeps the blur of linear interpolation (≈ h²/6 of variance) below 1.5 %.
    sigma = 4.0
    grid = VolumeGrid((32, 32, 32), spacing, centre)
    view = CArmView(angles[0], angles[1], 1000.0, 750.0, (1.0, 1.0), (48, 48))
    c = np.asarray(centre) + np.array([2.0, -1.0, 3.0])
    volume = np.exp(-np.sum((grid.voxel_centers() - c) ** 2, axis=-1) / (2 * sigma**2)).reshape(grid.shape)
    image = render(volume, view, grid)
    expected = sigma * np.sqrt(2 * np.pi) * np.exp(-distance_to_rays(view, c) ** 2 / (2 * sigma**2))
    assert image.shape == (48, 48)
    core = expected > 0.2 * expected.max()
    assert core.sum() > 50
    np.testing.assert_allclose(image[core], expected[core], rtol=0.02)
    assert np.abs(image - expected).max() < 0.02 * expected.max()


@pytest.mark.parametrize("angles", [(-30.0, 25.0), (45.0, -40.0), (120.0, 35.0)])
def test_all_ones_volume_gives_box_chord_lengths(angles):
    grid = VolumeGrid((20, 16, 24), (1.0, 1.25, 0.8), (2.0, -3.0, 1.0))
    view = CArmView(angles[0], angles[1], 1000.0, 750.0, (1.0, 1.0), (48, 48))
    image = render(np.ones(grid.shape), view, grid)
    chord = box_chords(view, grid)
    hit = chord > 0
    assert hit.sum() > 300 and (~hit).sum() > 100  # the box's shadow lies inside the detector
    error = np.abs(image - chord)
    voxel = min(grid.spacing_mm)
    assert error[hit].mean() < 0.1 * voxel
    assert np.percentile(error[hit], 95) < 0.5 * voxel
    assert error[~hit].max() < voxel  # only the half-voxel interpolation rim reaches outside


def test_all_ones_volume_is_exact_for_rays_through_opposite_faces():
    # AP rays near the centre enter and leave through the y faces of the box: Joseph's method
    # then samples the value 1 in every slice and the integral is the chord to rounding error.
    grid = VolumeGrid((16, 20, 16), (1.0, 1.0, 1.0))
    view = CArmView(0.0, 0.0, 1000.0, 750.0, (1.0, 1.0), (32, 32))
    image = render(np.ones(grid.shape), view, grid)
    chord = box_chords(view, grid)
    central = np.zeros(view.detector_shape, bool)
    central[8:24, 8:24] = True  # within ±6 mm of the axis at the isocenter: ≥ 2 voxels from x, z faces
    np.testing.assert_allclose(image[central], chord[central], rtol=1e-9)
    assert chord[central].min() == pytest.approx(20.0, rel=1e-3)


@pytest.mark.parametrize("angles", [(0.0, 0.0), (37.0, -21.0)])
def test_voxelised_sphere_chords(angles):
    radius = 8.0
    grid = VolumeGrid((40, 40, 40), (0.5, 0.5, 0.5))
    sphere = (np.linalg.norm(grid.voxel_centers(), axis=-1) <= radius).reshape(grid.shape)
    view = CArmView(angles[0], angles[1], 1000.0, 750.0, (0.5, 0.5), (33, 33))  # odd: a central pixel
    image = project_volume(sphere.astype(np.float32), view, grid)
    b = distance_to_rays(view, (0.0, 0.0, 0.0))
    expected = 2.0 * np.sqrt(np.clip(radius**2 - b**2, 0.0, None))
    assert b[16, 16] == pytest.approx(0.0, abs=1e-9)
    assert image[16, 16] == pytest.approx(2.0 * radius, rel=0.02)
    inner = b < 0.8 * radius
    error = np.abs(image - expected)[inner]
    # a staircase surface moves each end of a chord by at most about one voxel
    assert error.mean() < 0.5 * 0.5
    assert error.max() < 1.5 * 0.5


def test_line_integrals_scale_with_voxel_value_and_vanish_for_empty():
    grid = VolumeGrid((10, 10, 10), (1.0, 1.0, 1.0))
    view = CArmView(20.0, 10.0, 1000.0, 750.0, (1.0, 1.0), (20, 20))
    ones = render(np.ones(grid.shape), view, grid)
    np.testing.assert_allclose(render(np.full(grid.shape, 2.5), view, grid), 2.5 * ones, rtol=1e-12)
    assert not render(np.zeros(grid.shape), view, grid).any()
    assert not project_volume(np.zeros(grid.shape), view, grid).any()


# --- linear operator properties -------------------------------------------------------------------------
def small_problem(angles=(25.0, -15.0)):
    grid = VolumeGrid((12, 10, 14), (1.0, 1.2, 0.9), (1.0, 0.5, -1.0))
    view = CArmView(angles[0], angles[1], 1000.0, 750.0, (1.0, 1.0), (24, 20))
    return grid, view


def test_linearity():
    grid, view = small_problem()
    rng = np.random.default_rng(0)
    x, y = rng.random(grid.shape), rng.random(grid.shape)
    lhs = render(2.0 * x - 3.0 * y, view, grid)
    rhs = 2.0 * render(x, view, grid) - 3.0 * render(y, view, grid)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-10, atol=1e-10)


def test_restricted_projector_equals_full_on_supported_volume():
    grid, view = small_problem()
    rng = np.random.default_rng(1)
    centres = grid.voxel_centers()
    support = np.flatnonzero(np.linalg.norm(centres - [2.0, 0.0, -1.0], axis=-1) < 4.0)
    values = rng.random(support.size)
    dense = np.zeros(grid.num_voxels)
    dense[support] = values
    full = render(dense, view, grid)
    restricted = ConeBeamProjector(view, grid, voxels=support, dtype=torch.float64)
    assert restricted.num_inputs == support.size
    assert restricted.pixels.size < view.detector_shape[0] * view.detector_shape[1]  # rays were skipped
    with torch.no_grad():
        image = restricted.render(torch.as_tensor(values)).numpy()
    np.testing.assert_allclose(image, full, rtol=1e-10, atol=1e-12)
    # and project_volume (which restricts to the non-zero voxels itself) agrees
    np.testing.assert_allclose(project_volume(dense.reshape(grid.shape), view, grid), full, rtol=1e-5, atol=1e-6)


def test_group_integrals_of_a_support_projector_equal_fresh_projections_of_each_group():
    grid, view = small_problem()
    centres = grid.voxel_centers()
    support = np.flatnonzero(np.linalg.norm(centres - [2.0, 0.0, -1.0], axis=-1) < 4.5)
    projector = ConeBeamProjector(view, grid, voxels=support)
    groups = np.zeros(grid.num_voxels, np.int64)
    groups[support[::3]] = 1  # two interleaved groups inside the support, the rest in none
    groups[support[1::3]] = 2
    integrals, pixels, seen = projector.group_integrals(groups.reshape(grid.shape), 2)
    assert integrals.shape == (pixels.size, 2) and integrals.dtype == np.float64 and seen.tolist() == [True, True]
    for label in (1, 2):
        image = np.zeros(view.detector_shape[0] * view.detector_shape[1])
        image[pixels] = integrals[:, label - 1]
        fresh = project_volume((groups == label).reshape(grid.shape).astype(np.float64), view, grid)
        np.testing.assert_allclose(image.reshape(view.detector_shape), fresh, rtol=1e-6, atol=1e-6)
    assert projector.covers(support[::2]) and not projector.covers(np.array([0]))
    full = ConeBeamProjector(view, grid)  # every voxel an input: the labels are read as they are
    assert full.covers(np.array([0, grid.num_voxels - 1]))
    np.testing.assert_allclose(full.group_integrals(groups, 2)[0].sum(axis=0), integrals.sum(axis=0), rtol=1e-6)


def test_gradcheck_float64():
    grid = VolumeGrid((6, 5, 4), (1.0, 1.2, 0.9), (0.3, -0.2, 0.1))
    view = CArmView(20.0, 10.0, 1000.0, 750.0, (1.0, 1.0), (8, 8))
    projector = ConeBeamProjector(view, grid, dtype=torch.float64)
    assert projector.nnz > 0
    x = torch.rand(grid.num_voxels, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(projector.line_integrals, (x,), eps=1e-6, atol=1e-8)
    # render = the same line integrals scattered into the detector image (random-direction check)
    assert torch.autograd.gradcheck(projector.render, (x,), eps=1e-6, atol=1e-8, fast_mode=True)


def test_gradcheck_restricted_projector():
    grid = VolumeGrid((6, 5, 4), (1.0, 1.0, 1.0))
    view = CArmView(-35.0, 20.0, 1000.0, 750.0, (1.0, 1.0), (10, 10))
    voxels = np.arange(0, grid.num_voxels, 3)
    projector = ConeBeamProjector(view, grid, voxels=voxels, dtype=torch.float64)
    x = torch.rand(voxels.size, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(projector.line_integrals, (x,), eps=1e-6, atol=1e-8)


def test_batched_columns():
    grid, view = small_problem()
    projector = ConeBeamProjector(view, grid, dtype=torch.float64)
    x = torch.rand(grid.num_voxels, 3, dtype=torch.float64)
    batched = projector.operator(x)
    for k in range(3):
        np.testing.assert_allclose(batched[:, k].numpy(), projector.line_integrals(x[:, k]).numpy(), rtol=1e-12)


# --- bad input ------------------------------------------------------------------------------------------
def test_bad_input_errors():
    grid, view = small_problem()
    projector = ConeBeamProjector(view, grid, dtype=torch.float64)
    with pytest.raises(ValueError, match="expected values of shape"):
        projector.line_integrals(torch.zeros(grid.num_voxels + 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="does not match the grid shape"):
        project_volume(np.zeros((3, 3, 3)), view, grid)
    with pytest.raises(ValueError, match="sorted and unique"):
        ConeBeamProjector(view, grid, voxels=np.array([5, 3, 9]))
    with pytest.raises(ValueError, match="inside the grid"):
        ConeBeamProjector(view, grid, voxels=np.array([0, grid.num_voxels]))


# --- CUDA (the only allowed skip) -----------------------------------------------------------------------
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    grid, view = small_problem()
    rng = np.random.default_rng(2)
    volume = rng.random(grid.num_voxels)
    cpu = ConeBeamProjector(view, grid, dtype=torch.float64)
    gpu = ConeBeamProjector(view, grid, device="cuda", dtype=torch.float64)
    x_cpu = torch.tensor(volume, requires_grad=True)
    x_gpu = torch.tensor(volume, device="cuda", requires_grad=True)
    y_cpu, y_gpu = cpu.render(x_cpu), gpu.render(x_gpu)
    np.testing.assert_allclose(y_gpu.detach().cpu().numpy(), y_cpu.detach().numpy(), rtol=1e-9, atol=1e-9)
    weights = torch.as_tensor(rng.random(view.detector_shape))
    (y_cpu * weights).sum().backward()
    (y_gpu * weights.cuda()).sum().backward()
    np.testing.assert_allclose(x_gpu.grad.cpu().numpy(), x_cpu.grad.numpy(), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(project_volume(volume.reshape(grid.shape), view, grid, device="cuda"),
                               y_cpu.detach().numpy(), rtol=1e-5, atol=1e-5)
