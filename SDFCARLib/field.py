"""Neural fields: multiresolution hash encoding + residual MLP.

``HashEncoding`` is the Instant-NGP encoding (Müller et al. 2022) in plain torch: L levels whose
resolutions grow geometrically from ``base_resolution`` to ``max_resolution``
(N_l = floor(N_min · b^l), b = exp((ln N_max − ln N_min) / (L − 1))); each level stores F features
per grid vertex, directly indexed while the level's (N_l + 1)³ vertices fit the table and
spatially hashed (x·1 ⊕ y·2654435761 ⊕ z·805459861 mod T) beyond; features are trilinearly
interpolated and concatenated. Table entries start uniform in ±1e-4 as in Instant-NGP.

``ResidualMLP`` has ``depth`` linear layers of ``width`` units: an input layer, ``depth − 2``
residual layers h ← h + ReLU(W h + b), and a linear output layer.

``ImplicitField`` maps normalised coordinates in [0, 1]³ to

* ``kind="sdf"``: an unbounded signed-distance-like value s (negative inside); occupancy is
  σ(−α·s) (SDF-CAR);
* ``kind="occupancy"``: a logit z; occupancy is σ(z) (NeCA).

Both start from the same near-empty occupancy ``initial_occupancy`` everywhere (the SDF of an
empty scene is a positive constant), so the two representations are compared fairly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from .sparse import SparseOperator

_PRIMES = (1, 2654435761, 805459861)
_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.int64)


@dataclass(frozen=True)
class FieldConfig:
    levels: int = 16
    features_per_level: int = 2
    log2_table_size: int = 19
    base_resolution: int = 16
    max_resolution: int = 256
    width: int = 256
    depth: int = 8
    kind: str = "sdf"  # "sdf" | "occupancy"
    alpha: float = 50.0
    initial_occupancy: float = 0.01
    # the α of the first step when the fit raises it (``ImplicitField.alpha``); None: ``alpha`` throughout
    initial_alpha: Optional[float] = None


class HashEncoding(nn.Module):
    """Multiresolution hash encoding of points in [0, 1]³: (N, 3) → (N, levels · features)."""

    def __init__(self, levels: int = 16, features_per_level: int = 2, log2_table_size: int = 19,
                 base_resolution: int = 16, max_resolution: int = 256) -> None:
        super().__init__()
        if levels < 1 or features_per_level < 1:
            raise ValueError("levels and features_per_level must be positive")
        if max_resolution < base_resolution:
            raise ValueError("max_resolution must be at least base_resolution")
        growth = 1.0 if levels == 1 else math.exp((math.log(max_resolution) - math.log(base_resolution)) / (levels - 1))
        table_size = 2**log2_table_size
        resolutions: List[int] = []
        sizes: List[int] = []
        hashed: List[bool] = []
        for level in range(levels):
            n = int(math.floor(base_resolution * growth**level + 1e-9))
            dense = (n + 1) ** 3
            resolutions.append(n)
            sizes.append(min(dense, table_size))
            hashed.append(dense > table_size)
        offsets = [0]
        for s in sizes:
            offsets.append(offsets[-1] + s)
        self.levels = levels
        self.features_per_level = features_per_level
        self.output_dim = levels * features_per_level
        self.growth = growth
        self.resolutions = resolutions
        self.register_buffer("_resolution", torch.tensor(resolutions, dtype=torch.int64), persistent=False)
        self.register_buffer("_size", torch.tensor(sizes, dtype=torch.int64), persistent=False)
        self.register_buffer("_offset", torch.tensor(offsets[:-1], dtype=torch.int64), persistent=False)
        self.register_buffer("_hashed", torch.tensor(hashed), persistent=False)
        self.register_buffer("_corners", _CORNERS.clone(), persistent=False)
        self.register_buffer("_primes", torch.tensor(_PRIMES, dtype=torch.int64), persistent=False)
        self.table = nn.Parameter(torch.empty(offsets[-1], features_per_level).uniform_(-1e-4, 1e-4))
        self.level_weights = None  # (levels,) in [0, 1], or None: every level at full weight

    def fade_in_levels(self, active_levels: float) -> None:
        """Weigh level l by clamp(active_levels − l, 0, 1): the first ``active_levels`` levels fully, the
        next partly, the finer ones not at all (coarse-to-fine fitting); ``levels`` or more: all, unweighted."""
        if active_levels >= self.levels:
            self.level_weights = None
            return
        level = torch.arange(self.levels, dtype=self.table.dtype, device=self.table.device)
        self.level_weights = (active_levels - level).clamp(0.0, 1.0)

    def _weighed(self, features: torch.Tensor) -> torch.Tensor:
        if self.level_weights is None:
            return features
        n = features.shape[0]
        return (features.reshape(n, self.levels, self.features_per_level) * self.level_weights[None, :, None]).reshape(n, -1)

    def vertex_indices(self, x: torch.Tensor):
        """Table rows (N, L, 8) and trilinear weights (N, L, 8) of points ``x`` (N, 3) in [0, 1]."""
        res = self._resolution.to(x.dtype)
        pos = x[:, None, :] * res[None, :, None]  # (N, L, 3)
        base = torch.floor(pos)
        frac = pos - base
        base = base.long()
        corner = base[:, :, None, :] + self._corners[None, None]  # (N, L, 8, 3)
        corner = torch.minimum(corner, self._resolution[None, :, None, None])
        n1 = (self._resolution + 1)[None, :, None]
        dense = (corner[..., 0] * n1 + corner[..., 1]) * n1 + corner[..., 2]
        hashed = (corner[..., 0] * self._primes[0]) ^ (corner[..., 1] * self._primes[1]) ^ (corner[..., 2] * self._primes[2])
        index = torch.where(self._hashed[None, :, None], hashed, dense) % self._size[None, :, None]
        index = index + self._offset[None, :, None]
        c = self._corners.to(x.dtype)  # (8, 3)
        w = torch.where(c[None, None] > 0, frac[:, :, None, :], 1 - frac[:, :, None, :]).prod(dim=-1)
        return index, w

    def prepare(self, x: torch.Tensor) -> "EncodedPoints":
        """Encoding of fixed points (voxel centres) as a sparse linear map of the table.

        Row ``n * L + l`` holds the 8 trilinear weights of point n at level l, so the features are
        one sparse product with the table, forward and backward.
        """
        with torch.no_grad():
            index, weight = self.vertex_indices(x)
            n = index.shape[0]
            rows = torch.arange(n * self.levels, device=x.device).repeat_interleave(8)
            operator = SparseOperator(rows, index.reshape(-1), weight.reshape(-1).to(self.table.dtype),
                                      (n * self.levels, self.table.shape[0]), coalesce=True)
        return EncodedPoints(operator, n)

    def forward(self, x) -> torch.Tensor:
        """Encode points (N, 3) in [0, 1], or ``EncodedPoints`` from ``prepare``."""
        if isinstance(x, EncodedPoints):
            return self._weighed(x.operator(self.table).reshape(x.count, self.output_dim))
        index, weight = self.vertex_indices(x)
        features = self.table[index]  # (N, L, 8, F)
        return self._weighed((features * weight[..., None]).sum(dim=2).reshape(x.shape[0], self.output_dim))


@dataclass
class EncodedPoints:
    """A fixed set of points, encoded once (``HashEncoding.prepare``)."""

    operator: SparseOperator
    count: int

    def __len__(self) -> int:
        return self.count


#: on CPU the MLP runs over this many points at a time: each layer's activations then stay in the
#: cache, which makes a step's forward and backward a quarter faster (bench/RESULTS.md §36); one
#: launch per layer serves a GPU better
CPU_CHUNK_ROWS = 8192


class ResidualMLP(nn.Module):
    def __init__(self, in_dim: int, width: int = 256, depth: int = 8, out_dim: int = 1) -> None:
        super().__init__()
        if depth < 2:
            raise ValueError("depth must be at least 2 (input and output layers)")
        self.input = nn.Linear(in_dim, width)
        self.hidden = nn.ModuleList(nn.Linear(width, width) for _ in range(depth - 2))
        self.output = nn.Linear(width, out_dim)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        if h.device.type == "cpu" and h.shape[0] > CPU_CHUNK_ROWS:
            return torch.cat([self._layers(h[i:i + CPU_CHUNK_ROWS]) for i in range(0, h.shape[0], CPU_CHUNK_ROWS)])
        return self._layers(h)

    def _layers(self, h: torch.Tensor) -> torch.Tensor:
        # in place on each layer's fresh output: the same values and gradients, one allocation fewer
        h = torch.relu_(self.input(h))
        for layer in self.hidden:
            h = h + torch.relu_(layer(h))
        return self.output(h)


class ImplicitField(nn.Module):
    """Hash encoding + residual MLP, read as an SDF or as occupancy logits (module docstring)."""

    def __init__(self, config: FieldConfig) -> None:
        super().__init__()
        if config.kind not in ("sdf", "occupancy"):
            raise ValueError(f"field kind must be 'sdf' or 'occupancy', got {config.kind!r}")
        if not 0.0 < config.initial_occupancy < 0.5:
            raise ValueError("initial_occupancy must lie in (0, 0.5)")
        self.config = config
        self.encoding = HashEncoding(config.levels, config.features_per_level, config.log2_table_size,
                                     config.base_resolution, config.max_resolution)
        self.mlp = ResidualMLP(self.encoding.output_dim, config.width, config.depth, 1)
        # σ(−α·s)'s α now: a fit may raise it from ``initial_alpha`` to ``alpha`` (coarse to sharp)
        self.alpha = float(config.initial_alpha or config.alpha)
        logit = math.log(config.initial_occupancy / (1 - config.initial_occupancy))
        with torch.no_grad():
            # Start empty: a small output layer plus a bias that gives initial_occupancy. The SDF's
            # logit is −α·s, so its layer is scaled by 1/α for both kinds to start equally close.
            self.mlp.output.weight.mul_(0.01 / self.alpha if config.kind == "sdf" else 0.01)
            self.mlp.output.bias.fill_(-logit / self.alpha if config.kind == "sdf" else logit)

    def prepare(self, x: torch.Tensor) -> EncodedPoints:
        return self.encoding.prepare(x)

    def raw(self, x, checkpoint_points: int = 0) -> torch.Tensor:
        """The network's scalar output (N,): s for an SDF field, the logit for occupancy.

        ``x``: points (N, 3) in [0, 1]³, or ``EncodedPoints`` from ``prepare``. With
        ``checkpoint_points`` > 0 the MLP runs in chunks of that many points whose activations are
        recomputed in the backward pass: the paper's 8 × 256 MLP on every voxel of a 128³ grid
        would otherwise keep tens of GB of activations.
        """
        features = self.encoding(x)
        n = features.shape[0]
        if checkpoint_points and n > checkpoint_points and torch.is_grad_enabled():

            out = torch.cat([checkpoint(self.mlp, features[i:i + checkpoint_points], use_reentrant=False)
                             for i in range(0, n, checkpoint_points)])
        else:
            out = self.mlp(features)
        return out.squeeze(-1)

    def logit_from_raw(self, raw: torch.Tensor) -> torch.Tensor:
        """The occupancy's logit: −α·s for an SDF field, the raw output itself for occupancy."""
        return -self.alpha * raw if self.config.kind == "sdf" else raw

    def occupancy_from_raw(self, raw: torch.Tensor, logit_offset: Optional[torch.Tensor] = None) -> torch.Tensor:
        """σ(logit), with ``logit_offset`` added per point where given (``revival.py``)."""
        logit = self.logit_from_raw(raw)
        return torch.sigmoid(logit if logit_offset is None else logit + logit_offset)

    def forward(self, x, checkpoint_points: int = 0) -> torch.Tensor:
        return self.occupancy_from_raw(self.raw(x, checkpoint_points))
