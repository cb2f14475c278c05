"""Image model and losses: silhouette, L_occ, and a geometric loss L_geo that has a gradient."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from SDFCARLib.field import FieldConfig, ImplicitField
from SDFCARLib.geometry import CArmView, VolumeGrid
from SDFCARLib.losses import (
    DistanceSettings,
    GeometricLoss,
    cascaded_distance,
    excess_path_loss,
    gaussian_blur,
    make_target,
    occupancy_loss,
    partial_occupancy_loss,
    signed_distance,
    silhouette,
)
from SDFCARLib.phantoms import Branch, CentrelineTree, voxelize
from SDFCARLib.projector import ConeBeamProjector, project_volume

TAU = 0.3


# --- silhouette and L_occ -------------------------------------------------------------------------------
def test_silhouette_zero_monotone_saturating():
    lengths = torch.linspace(0.0, 10.0, 201, dtype=torch.float64)
    s = silhouette(lengths, TAU)
    assert s[0] == 0.0
    assert torch.all(s[1:] > s[:-1])  # strictly increasing
    assert float(s[-1]) > 0.9999 and float(s.max()) <= 1.0
    assert float(silhouette(torch.tensor(TAU), TAU)) == pytest.approx(1 - math.exp(-1))
    # a gradient also where nothing is crossed yet: dS/dL = 1/τ at L = 0
    zero = torch.zeros(1, requires_grad=True)
    silhouette(zero, TAU).sum().backward()
    assert float(zero.grad) == pytest.approx(1 / TAU)


def test_occupancy_loss_is_mean_squared_difference():
    image = torch.tensor([[0.0, 0.5], [1.0, 0.25]])
    target = torch.tensor([[0.0, 1.0], [1.0, 0.0]])
    assert float(occupancy_loss(image, target)) == pytest.approx((0.25 + 0.0625) / 4)
    assert float(occupancy_loss(target, target)) == 0.0


def test_excess_path_loss_charges_only_what_a_ray_crosses_beyond_its_allowance():
    target = torch.tensor([[0.0, 1.0], [2.0, 1.0]])
    # allowance 1.5·target + 0.2: 0.2, 1.7, 3.2, 1.7
    rendered = torch.tensor([[0.5, 1.0], [3.0, 2.7]], requires_grad=True)
    loss = excess_path_loss(rendered, target, 1.5, 0.2)
    assert float(loss.detach()) == pytest.approx((0.3 ** 2 + 1.0 ** 2) / 4)  # a ghost on empty sky, one over its cap
    loss.backward()
    # less than the frame shows (the lumen's shape) costs nothing and is not pushed either way
    assert rendered.grad[0, 1] == 0 and rendered.grad[1, 0] == 0
    assert float(rendered.grad[0, 0]) == pytest.approx(2 * 0.3 / 4) and float(rendered.grad[1, 1]) == pytest.approx(2 * 1.0 / 4)
    assert float(excess_path_loss(target, target, 1.0, 0.0)) == 0.0


def test_unknown_pixels_add_nothing_to_the_occupancy_terms():
    target = make_target(torch.tensor([[0.0, 1.0], [0.0, 0.0]]), "mask", TAU)
    rendered = torch.tensor([[0.5, 1.0], [1.0, 0.0]], requires_grad=True)  # a ghost on each empty pixel of the first column
    known = torch.tensor([[1.0, 1.0], [0.0, 1.0]])  # the bottom left pixel the view could not see
    hidden = dataclasses.replace(target, known=known)
    assert float(occupancy_loss(rendered, target.image, hidden.occupancy_weight()).detach()) == pytest.approx(0.25 / 4)
    assert float(occupancy_loss(rendered, target.image, target.occupancy_weight()).detach()) == pytest.approx(1.25 / 4)
    weighted = dataclasses.replace(hidden, pixel_weight=torch.full((2, 2), 2.0))
    assert torch.equal(weighted.occupancy_weight(), 2.0 * known)  # the thin-vessel weights on the known pixels only
    loss = excess_path_loss(rendered, target.image, 1.0, 0.0, known)
    loss.backward()
    assert float(loss.detach()) == pytest.approx(0.25 / 4) and rendered.grad[1, 0] == 0


def test_partial_occupancy_loss_is_the_mass_weighted_mean_of_one_minus_occupancy():
    assert float(partial_occupancy_loss(torch.tensor([0.0, 1.0, 1.0, 0.0]))) == 0.0  # binary: nothing partial
    assert float(partial_occupancy_loss(torch.zeros(5))) == 0.0  # no mass: no division by zero
    # 0.5 and 0.1 of mass 2 and 0.2: (2·0.5·0.5 + 2·0.1·0.9) / (2·0.5 + 2·0.1)
    o = torch.tensor([0.5, 0.5, 0.1, 0.1], requires_grad=True)
    assert float(partial_occupancy_loss(o).detach()) == pytest.approx((0.5 + 0.18) / 1.2)
    # the same mass spread four times thinner along a ray costs more than held in one full voxel
    assert float(partial_occupancy_loss(torch.full((8,), 0.25))) > float(partial_occupancy_loss(torch.tensor([1.0, 1.0])))
    # its gradient (mass held fixed) moves a faint voxel's mass to the strong one
    partial_occupancy_loss(o).backward()
    assert float(o.grad[0]) < 0 < float(o.grad[2])


def test_make_target():
    data = torch.tensor([[0.0, 3.0], [0.0, 255.0]])
    mask = make_target(data, "mask", TAU)
    assert mask.kind == "mask" and mask.reference_mm == 1.0
    torch.testing.assert_close(mask.image, torch.tensor([[0.0, 1.0], [0.0, 1.0]]))
    torch.testing.assert_close(mask.rendered(torch.tensor([TAU])), torch.tensor([1 - math.exp(-1)]))
    lengths = torch.tensor([[0.0, 1.0], [0.5, 4.0]])
    li = make_target(lengths, "line_integral", TAU)
    assert li.reference_mm == 4.0
    torch.testing.assert_close(li.image, lengths / 4.0)
    torch.testing.assert_close(li.silhouette, silhouette(lengths, TAU))
    torch.testing.assert_close(li.rendered(torch.tensor([2.0])), torch.tensor([0.5]))
    with pytest.raises(ValueError, match="all zero"):
        make_target(torch.zeros(3, 3), "line_integral", TAU)
    with pytest.raises(ValueError, match="kind"):
        make_target(data, "probability", TAU)


def test_gaussian_blur_of_a_line_is_a_normalised_gaussian_across_it():
    image = torch.zeros(41, 33)
    image[20, :] = 1.0  # a line along the columns: blurring along them changes nothing away from the ends
    blurred = gaussian_blur(image, (2.0, 1.5))
    across = blurred[:, 16]
    x = torch.arange(41.0) - 20
    expected = torch.exp(-0.5 * (x / 2.0) ** 2)
    expected[x.abs() > 6] = 0.0  # cut at 3σ
    torch.testing.assert_close(across, expected / expected.sum())
    assert float(across.sum()) == pytest.approx(1.0, abs=1e-6)  # the mass is kept (the line's path length)
    assert float((x ** 2 * across).sum()) == pytest.approx(4.0, rel=0.03)  # variance σ² (3σ cut: 2.7 % low)
    assert torch.equal(gaussian_blur(image, (0.0, 0.0)), image)
    # along the columns only: the line stays a line, its ends soften
    along = gaussian_blur(image, (0.0, 1.5))
    assert torch.equal(along[19], image[19]) and float(along[20, 16]) == pytest.approx(1.0)
    assert 0.4 < float(along[20, 0]) < 0.7


# --- signed distance ---------------------------------------------------------------------------------------
def soft_vessel_images(seed: int, size=(2, 1, 48, 56)) -> torch.Tensor:
    """Blurred random blobs in [0, 1]: sources of every strength, like a rendered silhouette."""
    rng = np.random.default_rng(seed)
    noise = ndimage.gaussian_filter(rng.random(size), sigma=(0, 0, 3, 3))
    images = np.clip((noise - np.quantile(noise, 0.92)) * 60, 0, 1)  # sparse, soft-edged blobs
    return torch.as_tensor(images, dtype=torch.float32)


@pytest.mark.parametrize("kernel_size", [3, 5])
def test_cascaded_distance_equals_kornia_values_and_gradients(kernel_size):
    from kornia.contrib import distance_transform

    images = soft_vessel_images(0)
    assert 0.02 < float((images > 0).float().mean()) < 0.2 and float(((images > 0) & (images < 1)).float().mean()) > 0.01
    # The full cascade is kornia's transform.
    ours = cascaded_distance(images, kernel_size)
    torch.testing.assert_close(ours, distance_transform(images, kernel_size=kernel_size), rtol=1e-5, atol=1e-5)
    # Stopped early: the same below the limit, +inf (never a wrong finite value) beyond it, and the
    # same gradient of anything computed from the clipped distances.
    limit = 7.0
    x_ours = images.clone().requires_grad_(True)
    x_ref = images.clone().requires_grad_(True)
    truncated = cascaded_distance(x_ours, kernel_size, max_distance_px=limit)
    reference = distance_transform(x_ref, kernel_size=kernel_size)
    below = reference < limit
    assert float((reference >= limit).float().mean()) > 0.05  # the limit matters in this image
    torch.testing.assert_close(truncated[below], reference[below], rtol=1e-5, atol=1e-5)
    assert torch.all(truncated[~below] >= limit)
    weights = torch.rand(images.shape, generator=torch.Generator().manual_seed(1))
    (weights * truncated.clamp(max=limit)).sum().backward()
    (weights * reference.clamp(max=limit)).sum().backward()
    assert float(x_ref.grad.abs().sum()) > 0
    torch.testing.assert_close(x_ours.grad, x_ref.grad, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("kernel_size", [3, 5])
def test_symmetric_filter_equals_the_convolution_and_its_gradient(kernel_size):
    from SDFCARLib.losses import _SymmetricFilter

    half = kernel_size // 2
    offsets = torch.arange(-half, half + 1, dtype=torch.float64)
    kernel = torch.exp(-torch.sqrt(offsets[:, None] ** 2 + offsets[None, :] ** 2) / 0.35)[None, None]
    padded = torch.rand(2, 1, 7 + 2 * half, 9 + 2 * half, dtype=torch.float64, requires_grad=True)
    out = _SymmetricFilter.apply(padded, kernel)
    assert out.shape == (2, 1, 7, 9)
    torch.testing.assert_close(out, torch.nn.functional.conv2d(padded, kernel))
    assert torch.autograd.gradcheck(lambda x: _SymmetricFilter.apply(x, kernel), (padded,))


def test_cascaded_distance_on_simple_cases_and_bad_shapes():
    image = torch.zeros(1, 1, 9, 9)
    image[0, 0, 4, 4] = 1.0
    d = cascaded_distance(image, 3)
    assert float(d[0, 0, 4, 4]) == 0.0
    assert float(d[0, 0, 4, 7]) == pytest.approx(3.0, abs=0.2)  # the soft minimum is ~0.17 px short
    assert torch.all(cascaded_distance(torch.zeros(1, 1, 5, 5)).isinf())  # no source anywhere: far
    assert torch.all(cascaded_distance(image, 3, max_distance_px=1.5)[0, 0, 4, 8:].isinf())
    with pytest.raises(ValueError, match="shape"):
        cascaded_distance(torch.zeros(9, 9))
    with pytest.raises(ValueError, match="odd"):
        cascaded_distance(image, 4)


def test_signed_distance_memory_does_not_grow_with_the_image_beyond_the_truncation():
    # kornia's own cascade runs max(H, W) rounds and keeps all of them for the gradient (22 GB for
    # four 512² images); the truncated cascade runs truncation / pixel + 1 rounds at any size.
    from SDFCARLib import losses

    rounds = []
    original = losses._correlate

    def counting_correlate(*args, **kwargs):
        rounds.append(1)
        return original(*args, **kwargs)

    settings = DistanceSettings(truncation_mm=5.0)
    for size in (64, 256):
        rounds.clear()
        losses._correlate = counting_correlate
        try:
            signed_distance(torch.rand(1, 1, size, size), torch.tensor([1.0]), settings)
        finally:
            losses._correlate = original
        assert len(rounds) == 6  # ceil(5 mm / 1 mm) + 1


def test_signed_distance_of_a_band_against_exact_distances():
    # A vertical band: every distance is horizontal, where kornia's transform is accurate
    # (it is documented as up to 0.17 px short beside a straight edge).
    h, w, step, truncation = 24, 40, 0.5, 5.0
    band = np.zeros((h, w), bool)
    band[:, 18:22] = True
    outside = ndimage.distance_transform_edt(~band)  # pixels to the nearest vessel pixel
    inside = ndimage.distance_transform_edt(band)  # pixels to the nearest background pixel
    expected = np.clip((outside - inside) * step / truncation, -1, 1)
    settings = DistanceSettings(truncation_mm=truncation)
    result = signed_distance(torch.as_tensor(band, dtype=torch.float32)[None, None], torch.tensor([step]), settings)
    assert result.shape == (1, 1, h, w)
    np.testing.assert_allclose(result[0, 0].numpy(), expected, atol=0.25 * step / truncation)
    assert torch.all(result[0, 0][:, 18:22] < 0) and torch.all(result[0, 0][:, :18] > 0)


def test_signed_distance_without_any_vessel_is_far():
    settings = DistanceSettings()
    empty = signed_distance(torch.zeros(1, 1, 8, 8), torch.tensor([0.5]), settings)
    assert torch.all(empty == 1.0)  # "far from any vessel", not kornia's 0 for a sourceless image
    full = signed_distance(torch.ones(1, 1, 8, 8), torch.tensor([0.5]), settings)
    assert torch.all(full == -1.0)


# --- L_geo on images ------------------------------------------------------------------------------------------
def band_image(h=40, w=40, col=18, width=4):
    image = torch.zeros(h, w)
    image[5:35, col : col + width] = 1.0
    return image


def test_geometric_loss_zero_for_perfect_rendering_and_grows_with_shift():
    target = band_image()
    loss = GeometricLoss([target], [0.5], [None], DistanceSettings())
    assert float(loss([target.clone()])) == 0.0
    shifted = [float(loss([band_image(col=18 + k)])) for k in (1, 2, 4, 8)]
    assert 0.0 < shifted[0] < shifted[1] < shifted[2] < shifted[3]
    empty = float(loss([torch.zeros_like(target)]))
    assert empty > shifted[-1]  # an empty rendering is worse than any rendering near the vessel
    assert empty > 0.1  # large: kornia alone would give a sourceless image the distance 0


def test_geometric_loss_tolerance_ignores_border_shifts_below_it():
    target = band_image()
    plain = GeometricLoss([target], [0.5], [None], DistanceSettings())
    one_pixel = band_image(col=19)  # the band moved by one pixel (0.5 mm)
    # a tolerance beyond the shift (the cascade's soft distances move by up to 0.83 mm where the band's
    # ends move diagonally): the rendering costs nothing; one below it: less than without
    assert float(GeometricLoss([target], [0.5], [None], DistanceSettings(tolerance_mm=1.0))([one_pixel])) == 0.0
    half = float(GeometricLoss([target], [0.5], [None], DistanceSettings(tolerance_mm=0.25))([one_pixel]))
    assert 0.0 < half < float(plain([one_pixel]))
    # a rendering many pixels off still costs, less the tolerance
    far = band_image(col=26)
    tolerant = GeometricLoss([target], [0.5], [None], DistanceSettings(tolerance_mm=1.0))
    assert 0.0 < float(tolerant([far])) < float(plain([far]))


def test_geometric_loss_gradient_points_towards_the_target():
    target = band_image(col=18)
    loss = GeometricLoss([target], [0.5], [None], DistanceSettings())
    rendering = band_image(col=20).clamp(0.02, 0.98).requires_grad_(True)  # shifted 2 px right
    value = loss([rendering])
    value.backward()
    grad = rendering.grad
    assert torch.isfinite(grad).all()
    rows = slice(8, 32)
    # target pixels the rendering misses (cols 18, 19, and its own left border) want more vessel ...
    assert float(grad[rows, 18:21].sum()) < 0
    # ... and the rendered border beyond the target wants less
    assert float(grad[rows, 23:25].sum()) > 0
    # far from both borders nothing changes
    assert float(grad[rows, :12].abs().sum()) == 0.0


def test_geometric_loss_ignores_what_the_view_could_not_see():
    target = band_image(col=18)
    known = torch.ones_like(target)
    known[:, 28:] = 0.0  # a collimator blade over the right columns
    ghost = target.clone()
    ghost[8:32, 32:36] = 1.0  # a vessel behind the blade, which the mask could not show
    for downsample in (1, 2):
        settings = DistanceSettings(downsample=downsample)
        blind = GeometricLoss([target], [0.5], [None], settings, known_pixels=[known])
        assert float(GeometricLoss([target], [0.5], [None], settings)([ghost])) > 0.0
        assert float(blind([ghost])) == 0.0
        # where the view could see, the loss is the one without unknown pixels
        shifted = band_image(col=16)
        assert float(blind([shifted])) > 0.0
    rendering = ghost.clamp(0.02, 0.98).requires_grad_(True)
    blind([rendering]).backward()
    assert float(rendering.grad[:, 30:].abs().sum()) == 0.0


def test_geometric_loss_averages_views_and_handles_different_sizes():
    a, b = band_image(40, 40), band_image(40, 56, col=30)
    loss = GeometricLoss([a, b], [0.5, 0.4], [None, None], DistanceSettings())
    assert float(loss([a, b])) == 0.0
    only_a = GeometricLoss([a], [0.5], [None], DistanceSettings())
    only_b = GeometricLoss([b], [0.4], [None], DistanceSettings())
    wrong_a, wrong_b = band_image(40, 40, col=22), band_image(40, 56, col=26)
    expected = (float(only_a([wrong_a])) + float(only_b([wrong_b]))) / 2
    assert float(loss([wrong_a, wrong_b])) == pytest.approx(expected, rel=1e-5)


def test_geometric_loss_downsampled_keeps_thin_vessels():
    target = torch.zeros(64, 64)
    target[10:50, 31] = 1.0  # one pixel wide
    loss = GeometricLoss([target], [0.25], [None], DistanceSettings(downsample=4))
    assert float(loss([target])) == 0.0
    assert float(loss([torch.zeros_like(target)])) > 0.05


# --- L_geo through the whole pipeline: field → projector → silhouette → L_geo ------------------------------
@pytest.fixture(scope="module")
def tiny_problem():
    grid = VolumeGrid((16, 16, 16), (1.0, 1.0, 1.0))
    view = CArmView(20.0, 10.0, 1000.0, 750.0, (1.0, 1.0), (24, 24))
    tree = CentrelineTree([Branch(np.array([[-5.0, -2.0, -4.0], [5.0, 2.0, 4.0]]), np.array([1.5, 1.5]))])
    label = voxelize(tree, grid)
    mask = torch.as_tensor(project_volume(label.astype(np.float32), view, grid) > 0.2, dtype=torch.float32)
    assert 0 < float(mask.sum()) < 0.5 * mask.numel()
    ijk = np.stack(np.unravel_index(np.arange(grid.num_voxels), grid.shape), axis=-1)
    points = torch.as_tensor((ijk + 0.5) / np.asarray(grid.shape), dtype=torch.float32)
    projector = ConeBeamProjector(view, grid)
    loss = GeometricLoss([mask], [view.isocenter_pixel_spacing_mm[0]], [None], DistanceSettings())
    return points, projector, loss, mask


@pytest.mark.parametrize("kind", ["sdf", "occupancy"])
def test_geometric_loss_has_a_gradient_wrt_field_parameters(tiny_problem, kind):
    # Guard against the public SDF-CAR code, whose L_geo thresholds the rendering and so has no
    # gradient at all. A field whose rendering crosses the mask threshold in places (any state
    # past the first steps) must receive a finite, non-zero gradient from L_geo alone.
    points, projector, loss, _ = tiny_problem
    torch.manual_seed(0)
    # initial occupancy 0.05: long rays through the 16 mm cube render above the 0.5 threshold
    field = ImplicitField(FieldConfig(kind=kind, levels=4, log2_table_size=12, base_resolution=4,
                                      max_resolution=16, width=16, depth=4, initial_occupancy=0.05))
    sil = silhouette(projector.render(field(points)), TAU)
    assert float(sil.detach().max()) > 0.5 > float(sil.detach().min())
    value = loss([sil])
    assert torch.isfinite(value) and float(value.detach()) > 0
    value.backward()
    table_grad = field.encoding.table.grad
    assert table_grad is not None and torch.isfinite(table_grad).all() and table_grad.abs().sum() > 0
    for name, parameter in field.mlp.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
    assert sum(float(p.grad.abs().sum()) for p in field.mlp.parameters()) > 0


def test_geometric_loss_descent_moves_a_shifted_rendering_onto_the_target():
    # The gradient is useful, not merely non-zero: Adam on L_geo alone, acting on per-pixel
    # logits, moves a rendering shifted by 3 px towards the target and keeps it non-empty.
    def band(col):
        image = torch.zeros(32, 32)
        image[4:28, col : col + 4] = 1.0
        return image

    target = band(14)
    loss = GeometricLoss([target], [0.5], [None], DistanceSettings())
    logits = (band(17) * 4.0 - 2.0).requires_grad_(True)
    optimiser = torch.optim.Adam([logits], lr=1.0)
    values = []
    for _ in range(20):
        optimiser.zero_grad()
        value = loss([torch.sigmoid(logits)])
        value.backward()
        optimiser.step()
        values.append(float(value.detach()))
    rendered = torch.sigmoid(logits.detach()) > 0.5

    def dice(a, b):
        return float(2 * (a & b).sum() / (a.sum() + b.sum()))

    assert values[-1] < 0.5 * values[0]
    assert rendered.any()
    assert dice(rendered, target > 0) > dice(band(17) > 0, target > 0) + 0.1
