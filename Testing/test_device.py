"""Device choice and the memory estimate: honest about what a run needs before it starts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import SDFCARLib.optimiser as optimiser
from SDFCARLib.device import check_host_memory, choose_device, estimate_memory_bytes
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize
from SDFCARLib.settings import ReconstructionError, make_settings


def test_choose_device():
    assert choose_device("cpu")[0] == torch.device("cpu")
    device, reason = choose_device("auto")
    assert device.type == ("cuda" if torch.cuda.is_available() else "cpu") and reason.startswith("auto")
    if torch.cuda.is_available():
        assert choose_device("cuda")[0].type == "cuda"
    else:
        with pytest.raises(ReconstructionError, match="no CUDA"):
            choose_device("cuda")


def test_memory_estimate_tracks_measured_runs():
    # 721A at 128³ / 0.8 mm, two 512² views at 0.35 mm (bench/RESULTS.md): the fast preset on its
    # 23 452 hull voxels peaked at 1.4 GiB resident; the paper preset on the full grid was killed by
    # the OOM killer above 23 GiB.
    grid = VolumeGrid((128, 128, 128), (0.8, 0.8, 0.8))
    geometry = Geometry(grid, [CArmView(a, 0.0, 1000.0, 757.0, (0.35, 0.35), (512, 512)) for a in (30.0, -30.0)])
    fast = estimate_memory_bytes(make_settings("fast"), geometry, 23452)
    paper_full = estimate_memory_bytes(make_settings("paper"), geometry, grid.num_voxels)
    assert 0.5 * 2**30 < fast < 2 * 2**30
    assert paper_full > 23 * 2**30
    # More points, larger MLP, finer distance maps: never less memory.
    assert estimate_memory_bytes(make_settings("fast"), geometry, 60000) > fast
    assert estimate_memory_bytes(make_settings("fast", width=256), geometry, 23452) > fast
    assert estimate_memory_bytes(make_settings("fast", dt_downsample=1), geometry, 23452) > fast
    assert estimate_memory_bytes(make_settings("fast", mode="neca"), geometry, 23452) < fast  # no L_geo


def test_host_memory_check_refuses_with_the_ways_out(monkeypatch):
    check_host_memory(2 * 2**30, 4 * 2**30)
    check_host_memory(2 * 2**30, None)  # unknown (not Linux): no check
    with pytest.raises(ReconstructionError, match=r"needs about 30\.0 GiB .* only 8\.0 GiB .*'fast' preset.*memory_check"):
        check_host_memory(30 * 2**30, 8 * 2**30)
    # In a reconstruction the check comes before any work and can be switched off.
    grid = VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0))
    views = [CArmView(a, 0.0, 1000.0, 750.0, (1.0, 1.0), (64, 64)) for a in (30.0, -30.0)]
    tree = CentrelineTree([Branch(np.array([[-12.0, -6.0, -10.0], [12.0, 6.0, 10.0]]), np.array([3.0, 2.0]))])
    _, masks = simulate_views(voxelize(tree, grid), grid, views)
    geometry = Geometry(grid, views)
    monkeypatch.setattr(optimiser, "available_memory_bytes", lambda: 1024)
    calls = []
    with pytest.raises(ReconstructionError, match="memory"):
        optimiser.reconstruct(geometry, masks, make_settings("fast", steps=2, device="cpu"), progress=calls.append)
    assert [c["phase"] for c in calls] == ["setup"]
    result = optimiser.reconstruct(geometry, masks, make_settings("fast", steps=2, device="cpu", memory_check=False))
    assert result.report["memory_estimate_bytes"] > 1024
