"""Hash encoding and implicit field: Instant-NGP level layout, sparse encoding, occupancy maps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from SDFCARLib.field import FieldConfig, HashEncoding, ImplicitField, ResidualMLP


def expected_resolutions(n_min: int, n_max: int, levels: int):
    # Instant-NGP: b = exp((ln N_max − ln N_min) / (L − 1)), N_l = floor(N_min · b^l); the last
    # level is N_max by construction (the tiny epsilon only absorbs rounding of b^(L−1)).
    b = math.exp((math.log(n_max) - math.log(n_min)) / (levels - 1))
    return [int(math.floor(n_min * b**level * (1 + 1e-12))) for level in range(levels)]


@pytest.mark.parametrize("n_min, n_max, levels", [(16, 256, 16), (16, 256, 8), (4, 64, 5), (2, 3, 4)])
def test_level_resolutions_follow_geometric_growth(n_min, n_max, levels):
    enc = HashEncoding(levels=levels, features_per_level=2, log2_table_size=10,
                       base_resolution=n_min, max_resolution=n_max)
    assert enc.resolutions == expected_resolutions(n_min, n_max, levels)
    assert enc.resolutions[0] == n_min and enc.resolutions[-1] == n_max
    assert enc.growth == pytest.approx((n_max / n_min) ** (1 / (levels - 1)))


def test_paper_configuration():
    config = FieldConfig()
    assert (config.levels, config.log2_table_size, config.features_per_level) == (16, 19, 2)
    assert (config.width, config.depth, config.alpha, config.kind) == (256, 8, 50.0, "sdf")
    enc = HashEncoding(config.levels, config.features_per_level, config.log2_table_size,
                       config.base_resolution, config.max_resolution)
    assert enc.output_dim == 32
    assert enc(torch.rand(7, 3)).shape == (7, 32)
    # every level's table is at most 2^19 rows; levels that need more are hashed
    sizes = [(n + 1) ** 3 for n in enc.resolutions]
    assert enc.table.shape == (sum(min(s, 2**19) for s in sizes), 2)
    assert any(s > 2**19 for s in sizes) and any(s <= 2**19 for s in sizes)


def test_paper_mlp_has_eight_linear_layers_and_residual_hidden_layers():
    mlp = ResidualMLP(32, width=256, depth=8)
    linear = [m for m in mlp.modules() if isinstance(m, torch.nn.Linear)]
    assert len(linear) == 8
    assert linear[0].in_features == 32 and linear[-1].out_features == 1
    # residual: with a hidden layer's weights and bias zero, it passes its input through unchanged
    with torch.no_grad():
        for layer in mlp.hidden:
            layer.weight.zero_()
            layer.bias.zero_()
    h = torch.randn(5, 32)
    expected = mlp.output(torch.relu(mlp.input(h)))
    torch.testing.assert_close(mlp(h), expected)
    with pytest.raises(ValueError, match="depth"):
        ResidualMLP(32, width=8, depth=1)


def test_mlp_in_chunks_on_cpu_gives_the_whole_batch_values_and_gradients(monkeypatch):
    from SDFCARLib import field

    torch.manual_seed(0)
    mlp = ResidualMLP(8, width=16, depth=4)
    x = torch.randn(1000, 8, requires_grad=True)
    whole = mlp(x)
    grads_whole = torch.autograd.grad(whole.square().sum(), [x, mlp.input.weight])
    monkeypatch.setattr(field, "CPU_CHUNK_ROWS", 300)  # 4 chunks, the last one short
    chunked = mlp(x)
    grads_chunked = torch.autograd.grad(chunked.square().sum(), [x, mlp.input.weight])
    assert chunked.shape == (1000, 1)
    torch.testing.assert_close(chunked, whole)
    for a, b in zip(grads_chunked, grads_whole):
        torch.testing.assert_close(a, b)


def _all_vertices(n: int) -> torch.Tensor:
    k = torch.arange(n + 1, dtype=torch.float64) / n
    return torch.stack(torch.meshgrid(k, k, k, indexing="ij"), dim=-1).reshape(-1, 3)


def test_dense_levels_have_no_collisions_and_hashed_levels_stay_in_their_table():
    log2 = 12  # 4096 rows: levels with (N + 1)^3 <= 4096, i.e. N <= 15, are stored densely
    enc = HashEncoding(levels=4, features_per_level=2, log2_table_size=log2, base_resolution=4, max_resolution=32)
    assert enc.resolutions == [4, 8, 16, 32]
    offsets = np.cumsum([0] + [min((n + 1) ** 3, 2**log2) for n in enc.resolutions])
    for level, n in enumerate(enc.resolutions):
        points = _all_vertices(n)
        index, weight = enc.vertex_indices(points)
        # each point is a grid vertex: its weight is 1 at one corner; that corner's row is the vertex's
        corner = weight[:, level].argmax(dim=1)
        assert torch.allclose(weight[:, level].max(dim=1).values, torch.ones(len(points), dtype=torch.float64))
        rows = index[torch.arange(len(points)), level, corner]
        assert int(rows.min()) >= offsets[level] and int(rows.max()) < offsets[level + 1]
        distinct = torch.unique(rows).numel()
        if (n + 1) ** 3 <= 2**log2:
            assert distinct == (n + 1) ** 3  # dense: distinct vertices → distinct rows
        else:
            assert distinct < (n + 1) ** 3  # hashed: pigeonhole collisions, but inside the level's table


def test_encoding_is_trilinear_inside_a_cell():
    enc = HashEncoding(levels=1, features_per_level=1, log2_table_size=10, base_resolution=4, max_resolution=4)
    with torch.no_grad():
        enc.table.copy_(torch.randn_like(enc.table))
    # along an axis-parallel segment inside one cell the feature is linear in the coordinate
    t = torch.linspace(0.0, 1.0, 5, dtype=torch.float32)[:, None]
    a, b = torch.tensor([[0.26, 0.6, 0.8]]), torch.tensor([[0.49, 0.6, 0.8]])
    values = enc(a + t * (b - a)).squeeze(1)
    torch.testing.assert_close(values, values[0] + t.squeeze(1) * (values[-1] - values[0]), atol=1e-5, rtol=1e-5)
    # and at a vertex it equals that vertex's table entry: (1, 2, 3) / 4 is row (1·5 + 2)·5 + 3
    torch.testing.assert_close(enc(torch.tensor([[0.25, 0.5, 0.75]])), enc.table[(1 * 5 + 2) * 5 + 3][None])


def test_prepared_encoding_equals_direct_encoding_values_and_gradients():
    torch.manual_seed(0)
    enc = HashEncoding(levels=5, features_per_level=2, log2_table_size=11, base_resolution=4, max_resolution=40)
    assert any((n + 1) ** 3 > 2**11 for n in enc.resolutions)  # include hashed levels
    with torch.no_grad():
        enc.table.copy_(torch.randn_like(enc.table))
    points = torch.rand(300, 3)
    points[:5] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.5], [0.5, 0.5, 0.5], [0.999, 0.001, 1.0]])
    weights = torch.randn(300, enc.output_dim)

    direct = enc(points)
    (direct * weights).sum().backward()
    grad_direct = enc.table.grad.clone()
    enc.table.grad = None

    prepared = enc.prepare(points)
    assert len(prepared) == 300
    sparse = enc(prepared)
    (sparse * weights).sum().backward()
    torch.testing.assert_close(sparse, direct, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(enc.table.grad, grad_direct, atol=1e-5, rtol=1e-5)


def test_fading_in_levels_weighs_each_levels_features_and_no_gradient_reaches_the_faded_ones():
    torch.manual_seed(1)
    enc = HashEncoding(levels=5, features_per_level=2, log2_table_size=11, base_resolution=4, max_resolution=40)
    with torch.no_grad():
        enc.table.copy_(torch.randn_like(enc.table))
    points = torch.rand(200, 3)
    full = enc(points).detach().reshape(200, 5, 2)
    enc.fade_in_levels(2.25)  # levels 0 and 1 whole, level 2 at a quarter, 3 and 4 off
    torch.testing.assert_close(enc.level_weights, torch.tensor([1.0, 1.0, 0.25, 0.0, 0.0]))
    for x in (points, enc.prepare(points)):
        enc.table.grad = None
        faded = enc(x)
        torch.testing.assert_close(faded.detach().reshape(200, 5, 2), full * enc.level_weights[None, :, None],
                                   atol=1e-5, rtol=1e-5)
        faded.sum().backward()
        finest = slice(int(enc._offset[3]), None)  # the rows of levels 3 and 4
        assert not enc.table.grad[finest].any() and enc.table.grad[: int(enc._offset[1])].abs().sum() > 0
    enc.fade_in_levels(5.0)  # all levels: no weighting at all
    assert enc.level_weights is None
    torch.testing.assert_close(enc(points).detach().reshape(200, 5, 2), full)


def small_config(**overrides) -> FieldConfig:
    values = dict(levels=4, log2_table_size=12, base_resolution=4, max_resolution=32, width=32, depth=4)
    values.update(overrides)
    return FieldConfig(**values)


def test_sdf_occupancy_is_sigmoid_of_minus_alpha_s():
    field = ImplicitField(small_config(kind="sdf"))
    s = torch.tensor([-1.0, -0.05, -0.01, 0.0, 0.01, 0.05, 1.0])
    occupancy = field.occupancy_from_raw(s)
    torch.testing.assert_close(occupancy, 1.0 / (1.0 + torch.exp(50.0 * s)))
    assert occupancy[3] == 0.5  # the zero level set is the 0.5 iso-surface
    assert occupancy[0] > 0.999 and occupancy[-1] < 0.001  # negative inside
    points = torch.rand(50, 3)
    torch.testing.assert_close(field(points), torch.sigmoid(-50.0 * field.raw(points)))


def test_alpha_is_configurable():
    field = ImplicitField(small_config(kind="sdf", alpha=10.0))
    s = torch.tensor([0.1])
    torch.testing.assert_close(field.occupancy_from_raw(s), torch.sigmoid(torch.tensor([-1.0])))


def test_a_field_started_at_a_lower_alpha_starts_at_the_initial_occupancy_and_reads_with_its_current_alpha():
    points = torch.rand(300, 3)
    field = ImplicitField(small_config(kind="sdf", alpha=50.0, initial_alpha=10.0, initial_occupancy=0.01))
    assert field.alpha == 10.0 and field.config.alpha == 50.0
    with torch.no_grad():
        assert float(field(points).mean()) == pytest.approx(0.01, rel=0.1)  # the fair start at the first α
        s = field.raw(points)
        field.alpha = 50.0  # the same field, sharper: further from ½ on the same side
        torch.testing.assert_close(field(points), torch.sigmoid(-50.0 * s))
        assert float(field(points).max()) < 1e-3


def test_occupancy_field_is_sigmoid_of_logit():
    field = ImplicitField(small_config(kind="occupancy"))
    z = torch.tensor([-3.0, 0.0, 2.0])
    torch.testing.assert_close(field.occupancy_from_raw(z), torch.sigmoid(z))
    points = torch.rand(50, 3)
    torch.testing.assert_close(field(points), torch.sigmoid(field.raw(points)))


@pytest.mark.parametrize("kind", ["sdf", "occupancy"])
@pytest.mark.parametrize("width, initial", [(32, 0.05), (64, 0.01)])
def test_initial_occupancy_equals_configured_value(kind, width, initial):
    # The two representations must start from the same near-empty scene (fair ablations), for
    # any seed and MLP width (the fast preset's MLP is 64 × 8).
    points = torch.rand(300, 3)
    for seed in range(8):
        torch.manual_seed(seed)
        field = ImplicitField(small_config(kind=kind, width=width, depth=8, initial_occupancy=initial))
        with torch.no_grad():
            occupancy = field(points)
        assert float(occupancy.mean()) == pytest.approx(initial, rel=0.1), f"seed {seed}"
        assert float(occupancy.max()) < 2 * initial


def test_field_output_is_unbounded():
    field = ImplicitField(small_config(kind="sdf"))
    points = torch.rand(20, 3)
    with torch.no_grad():
        field.mlp.output.weight.zero_()
        field.mlp.output.bias.fill_(7.5)
    torch.testing.assert_close(field.raw(points), torch.full((20,), 7.5))
    with torch.no_grad():
        field.mlp.output.bias.fill_(-4.0)
    torch.testing.assert_close(field.raw(points), torch.full((20,), -4.0))
    # large weights give |s| > 1 without any squashing
    with torch.no_grad():
        field.mlp.output.weight.normal_(0.0, 100.0)
        field.mlp.output.bias.zero_()
    assert float(field.raw(points).detach().abs().max()) > 1.0


def test_field_gradients_reach_table_and_mlp_through_prepared_points():
    field = ImplicitField(small_config(kind="sdf", initial_occupancy=0.2))
    prepared = field.prepare(torch.rand(100, 3))
    occupancy = field(prepared)
    assert occupancy.shape == (100,)
    occupancy.sum().backward()
    for name, parameter in field.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
    assert field.encoding.table.grad.abs().sum() > 0
    assert field.mlp.output.weight.grad.abs().sum() > 0


def test_bad_configurations():
    with pytest.raises(ValueError, match="kind"):
        ImplicitField(small_config(kind="density"))
    with pytest.raises(ValueError, match="initial_occupancy"):
        ImplicitField(small_config(initial_occupancy=0.7))
    with pytest.raises(ValueError, match="initial_occupancy"):
        ImplicitField(small_config(initial_occupancy=0.0))
    with pytest.raises(ValueError, match="max_resolution"):
        HashEncoding(levels=4, base_resolution=32, max_resolution=16)
    with pytest.raises(ValueError, match="positive"):
        HashEncoding(levels=0)
