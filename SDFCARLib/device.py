"""Where a reconstruction runs: its memory estimate, the CPU/GPU choice, and what the host can give.

``device="auto"`` takes the CUDA GPU only when it has room for the run's estimated peak (with a
20 % margin), so a run never starts on a GPU it would not fit; on the CPU a run whose estimate
exceeds the memory the system has available is refused before any work, with the ways out,
instead of being killed half-way through it.
"""

from __future__ import annotations

import math
import platform
from typing import Optional, Tuple

import numpy as np
import torch

from .geometry import Geometry
from .settings import MODES, ReconstructionError, Settings

#: resident memory of the interpreter with torch and the inputs before a reconstruction starts
BASELINE_BYTES = 400 * 2**20


def estimate_memory_bytes(settings: Settings, geometry: Geometry, active_voxels: int) -> int:
    """Peak memory of a reconstruction in bytes, to choose a device and to refuse runs that cannot fit.

    The terms, per run (the distance maps are taken as large as the detector, which
    over-estimates the paper preset; bench/RESULTS.md compares the estimate with peak RSS):

    * projectors: about 56 non-zeros per active voxel and view, kept as CSR plus transpose
      (24 B each); building one view briefly needs another ~60 B per non-zero;
    * hash encoding of the fixed points: 8 non-zeros per point and level, 24 B each, ~56 B while
      it is built (coalesced and sorted copies); tables with gradient and Adam's moments (16 B/entry);
    * MLP: ~16 B per unit and layer for the saved activations and their gradients, for every point
      or, with ``checkpoint_points``, for one chunk (plus the chunk inputs of every point);
    * L_geo: ~14 saved images per view and source kind per round of the truncated distance cascade;
    * the interpreter, torch and the inputs (``BASELINE_BYTES``).
    """
    f, o, loss = settings.field, settings.optimisation, settings.loss
    views = geometry.views
    points = int(active_voxels)
    projector_nnz = 56 * points
    encoding_nnz = 8 * f.levels * points
    stored = len(views) * projector_nnz * 24 + encoding_nnz * 24
    build_peak = max(projector_nnz * 60, encoding_nnz * 56)
    tables = (2 ** f.log2_table_size) * f.levels * f.features_per_level * 16
    mlp_points = min(points, o.checkpoint_points) if o.checkpoint_points else points
    mlp = 16 * f.width * f.depth * mlp_points
    if o.checkpoint_points:
        mlp += points * f.levels * f.features_per_level * 4 * 3
    distance = 0
    if MODES[settings.run.mode].geometric_loss:
        for view in views:
            pixel_mm = float(np.mean(view.isocenter_pixel_spacing_mm)) * loss.dt_downsample
            rounds = math.ceil(loss.dt_truncation_mm / pixel_mm / (loss.dt_kernel_size // 2)) + 1
            crop = math.prod(math.ceil(n / loss.dt_downsample) for n in view.detector_shape)
            distance += 14 * 2 * rounds * crop * 4
    images = sum(int(np.prod(v.detector_shape)) for v in views) * 4 * 16
    optimise = mlp + distance + images
    return int(BASELINE_BYTES + stored + tables + max(build_peak, optimise))


def available_memory_bytes() -> Optional[int]:
    """Memory the system can give this process now (Linux MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def check_host_memory(needed_bytes: int, available_bytes: Optional[int]) -> None:
    """Refuse a CPU run that would not fit in memory, instead of being killed half-way through it."""
    if available_bytes is None or needed_bytes <= available_bytes:
        return
    raise ReconstructionError(
        f"this reconstruction needs about {needed_bytes / 2**30:.1f} GiB of memory on the CPU but only "
        f"{available_bytes / 2**30:.1f} GiB is available: use the 'fast' preset or support 'hull' (the field only "
        f"inside the masks' visual hull), a smaller volume, a CUDA GPU (--device cuda), or set memory_check "
        f"to false to try anyway")


def choose_device(requested: str, needed_bytes: int = 0) -> Tuple[torch.device, str]:
    """The torch device to use and why. ``auto`` takes CUDA when present with room, else the CPU."""
    if requested == "auto":
        if not torch.cuda.is_available():
            return torch.device("cpu"), "auto: no CUDA GPU is available to torch, using the CPU"
        free, total = torch.cuda.mem_get_info()
        name = torch.cuda.get_device_name(0)
        if needed_bytes and free < 1.2 * needed_bytes:
            return torch.device("cpu"), (f"auto: {name} has {free / 2**30:.1f} GiB free, this run needs about "
                                         f"{needed_bytes / 2**30:.1f} GiB; using the CPU")
        return torch.device("cuda"), f"auto: {name} with {free / 2**30:.1f} GiB free (needs about {needed_bytes / 2**30:.1f} GiB)"
    if str(requested).startswith("cuda") and not torch.cuda.is_available():
        raise ReconstructionError("device 'cuda' was requested but no CUDA GPU is available to torch; use --device cpu or auto")
    return torch.device(requested), "requested"


def device_description(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"
