"""Per-patient self-supervised optimisation: modes, presets and the training loop.

Modes (the paper's method and its ablations, Tables 1–4)
    ``sdfcar``        SDF field, λ1·L_geo + λ2·L_occ   (SDF-CAR)
    ``neca``          occupancy field, L_occ            (NeCA baseline)
    ``occ-combined``  occupancy field, λ1·L_geo + λ2·L_occ
    ``sdf-occ``       SDF field, L_occ

Presets
    ``paper``  the published recipe: the field on every voxel of the grid, 16-level hash grid
               (2^19 table, 2 features), 8 × 256 residual MLP, α = 50, λ = (1, 0.25), Adam at
               lr 1e-4 for 5000 steps, L_geo at full detector resolution every step.
    ``fast``   the same losses and representation, sized for a CPU: the field is evaluated only
               on the visual hull of the masks widened by 0.5 mm (elsewhere the occupancy is 0,
               which any mask already demands), an 8 × 64 MLP and an 8-level 2^17 hash table, 400
               steps with the hash table at lr 1e-2 and the MLP at 1e-3 after a 20-step warm-up,
               L_geo on a 2× max-pooled image (8× until the distance cascade was truncated; 2×
               measured better: bench/RESULTS.md), and the skeleton pieces that no mask pixel
               needs pruned afterwards (``pruning.py``: ghost branches that two views cannot
               rule out). ``bench/`` compares it with ``paper``.

Learning rates
    Adam moves every weight by about lr per step. The SDF's occupancy logit is −α·s, so a step of
    the SDF network's output layer moves the logit α = 50 times further than the same step of the
    occupancy network's: at lr 1e-2 the SDF modes saturate σ(−α·s) within a few steps and their
    gradient dies (measured: empty results), while the occupancy network needs about 1e-2 to
    converge in a few hundred steps. ``fast`` therefore trains the hash table (where the spatial
    detail lives, as in Instant-NGP) at 1e-2 and the MLP at 1e-3, the same for every mode, so the
    ablations stay like-for-like as in the paper (which uses one learning rate for all).

The loop calls ``progress(dict)`` with step, total, losses, elapsed and ETA, and stops with
``ReconstructionCancelled`` as soon as ``cancel()`` returns true (checked every step).
"""

from __future__ import annotations

import dataclasses
import math
import platform
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from . import __version__
from .field import FieldConfig, ImplicitField
from .geometry import Geometry
from .hull import support_mask
from .losses import DistanceSettings, GeometricLoss, ViewTarget, make_target, occupancy_loss
from .phantoms import DEFAULT_MASK_THRESHOLD_MM
from .projector import ConeBeamProjector
from .pruning import PruneSettings, drop_small_components, prune_redundant_branches, removal_zone

MODES: Dict[str, Dict[str, Any]] = {
    "sdfcar": {"field": "sdf", "geometric": True, "title": "SDF-CAR (SDF rep. + combined loss)"},
    "neca": {"field": "occupancy", "geometric": False, "title": "NeCA (occupancy rep. + occupancy loss)"},
    "occ-combined": {"field": "occupancy", "geometric": True, "title": "Occ. rep. + combined loss"},
    "sdf-occ": {"field": "sdf", "geometric": False, "title": "SDF rep. + occupancy loss"},
}

TARGET_KINDS = ("mask", "line_integral")
MASK_MODELS = ("silhouette", "width")


class ReconstructionError(ValueError):
    """The inputs cannot be reconstructed; the message names the problem and the fix."""


class ReconstructionCancelled(RuntimeError):
    """The user cancelled the reconstruction."""


@dataclass
class Settings:
    preset: str = "fast"
    mode: str = "sdfcar"
    steps: int = 400
    learning_rate: float = 1e-3
    table_learning_rate: Optional[float] = None  # hash table; None: learning_rate
    warmup_steps: int = 0
    lambda_geo: float = 1.0
    lambda_occ: float = 0.25
    alpha: float = 50.0
    silhouette_length_mm: float = 0.3
    support: str = "hull"  # "hull" | "full"
    support_margin_mm: float = 0.5
    dt_downsample: int = 8
    dt_threshold: float = 0.5
    dt_truncation_mm: float = 5.0
    dt_kernel_size: int = 3
    levels: int = 16
    features_per_level: int = 2
    log2_table_size: int = 19
    base_resolution: int = 16
    max_resolution: int = 256
    width: int = 256
    depth: int = 8
    initial_occupancy: float = 0.01
    mask_model: str = "silhouette"  # "silhouette" | "width" (losses.py)
    checkpoint_points: int = 0  # >0: MLP in checkpointed chunks of this many points (memory)
    threshold: float = 0.5
    prune: bool = False  # remove skeleton pieces no mask pixel needs (pruning.py)
    prune_piece_mm: float = 6.0
    prune_tolerance: float = 0.02
    # after pruning, drop components smaller than this fraction of the largest (0: keep all); off:
    # it cost the RCA suite ~5 clDice points (bench/RESULTS.md 1c)
    prune_min_component_fraction: float = 0.0
    seed: int = 0
    device: str = "auto"
    memory_check: bool = True  # refuse CPU runs whose estimated peak exceeds the available memory
    threads: Optional[int] = None

    def validate(self) -> None:
        if self.mode not in MODES:
            raise ReconstructionError(f"unknown mode {self.mode!r}; choose one of {', '.join(MODES)}")
        if self.support not in ("hull", "full"):
            raise ReconstructionError(f"support must be 'hull' or 'full', got {self.support!r}")
        if self.steps < 1:
            raise ReconstructionError(f"steps must be at least 1, got {self.steps}")
        for name in ("learning_rate", "alpha", "silhouette_length_mm"):
            if not getattr(self, name) > 0:
                raise ReconstructionError(f"{name} must be positive, got {getattr(self, name)}")
        if self.dt_downsample < 1:
            raise ReconstructionError("dt_downsample must be at least 1")
        if self.mask_model not in MASK_MODELS:
            raise ReconstructionError(f"mask_model must be one of {', '.join(MASK_MODELS)}, got {self.mask_model!r}")
        if self.warmup_steps < 0 or self.checkpoint_points < 0:
            raise ReconstructionError("warmup_steps and checkpoint_points must not be negative")
        if not self.prune_piece_mm > 0 or not 0 <= self.prune_tolerance < 1 or not 0 <= self.prune_min_component_fraction <= 1:
            raise ReconstructionError("prune_piece_mm must be positive, prune_tolerance in [0, 1) and "
                                      "prune_min_component_fraction in [0, 1]")
        if self.device not in ("auto", "cpu", "cuda") and not str(self.device).startswith("cuda:"):
            raise ReconstructionError(f"device must be auto, cpu or cuda, got {self.device!r}")

    def field_config(self) -> FieldConfig:
        return FieldConfig(
            levels=self.levels, features_per_level=self.features_per_level, log2_table_size=self.log2_table_size,
            base_resolution=self.base_resolution, max_resolution=self.max_resolution, width=self.width,
            depth=self.depth, kind=MODES[self.mode]["field"], alpha=self.alpha, initial_occupancy=self.initial_occupancy,
        )

    def to_dict(self) -> Dict[str, Any]:
        return dataclasses.asdict(self)


PRESETS: Dict[str, Dict[str, Any]] = {
    "paper": dict(
        steps=5000, learning_rate=1e-4, table_learning_rate=None, warmup_steps=0, support="full", dt_downsample=1,
        levels=16, log2_table_size=19, features_per_level=2, base_resolution=16, max_resolution=256, width=256,
        depth=8, checkpoint_points=262144,
    ),
    "fast": dict(
        steps=400, learning_rate=1e-3, table_learning_rate=1e-2, warmup_steps=20, support="hull",
        support_margin_mm=0.5, dt_downsample=2, levels=8, log2_table_size=17, features_per_level=2,
        base_resolution=16, max_resolution=256, width=64, depth=8, prune=True,
    ),
}


def parse_setting_overrides(items: Optional[Sequence[str]], reserved: Optional[Dict[str, str]] = None) -> Dict[str, Any]:
    """``["learning_rate=1e-3", "memory_check=false"]`` (command-line ``--set``) → typed ``Settings`` overrides.

    ``reserved`` maps settings that the caller sets itself to the option to use instead.
    """
    reserved = reserved or {}
    fields = {f.name: str(f.type) for f in dataclasses.fields(Settings)}
    out: Dict[str, Any] = {}
    for item in items or ():
        key, sep, text = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise ReconstructionError(f"--set {item!r}: write KEY=VALUE, e.g. --set learning_rate=1e-3")
        if key in reserved:
            raise ReconstructionError(f"--set {key}=…: {key} is set by this command; {reserved[key]}")
        if key not in fields:
            known = ", ".join(sorted(set(fields) - set(reserved) - {"preset"}))
            raise ReconstructionError(f"--set {key}=…: unknown optimiser setting {key!r}; known: {known}")
        out[key] = typed_setting_value(key, text.strip(), fields[key])
    return out


def typed_setting_value(key: str, text: str, type_name: str) -> Any:
    """The text of ``--set key=text`` as the type its ``Settings`` annotation names."""
    lowered = text.lower()
    if lowered in ("none", "null"):
        if "Optional" in type_name:
            return None
        raise ReconstructionError(f"--set {key}={text}: {key} needs a value ({type_name})")
    if "bool" in type_name:
        if lowered in ("true", "1", "yes", "on"):
            return True
        if lowered in ("false", "0", "no", "off"):
            return False
        raise ReconstructionError(f"--set {key}={text}: {key} takes true or false")
    if "int" in type_name:
        try:
            number = float(text)
        except ValueError:
            number = math.nan
        if not (math.isfinite(number) and number == int(number)):
            raise ReconstructionError(f"--set {key}={text}: {key} takes a whole number")
        return int(number)
    if "float" in type_name:
        try:
            number = float(text)
        except ValueError:
            raise ReconstructionError(f"--set {key}={text}: {key} takes a number, e.g. 1e-3") from None
        if not math.isfinite(number):
            raise ReconstructionError(f"--set {key}={text}: {key} must be finite")
        return number
    return text.strip("'\"")


def make_settings(preset: str = "fast", **overrides: Any) -> Settings:
    """Settings of a preset, with any field overridden (None values are ignored)."""
    if preset not in PRESETS:
        raise ReconstructionError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    values = dict(PRESETS[preset])
    values.update({k: v for k, v in overrides.items() if v is not None})
    known = {f.name for f in dataclasses.fields(Settings)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ReconstructionError(f"unknown setting(s): {', '.join(unknown)}")
    settings = Settings(preset=preset, **values)
    settings.validate()
    return settings


#: resident memory of the interpreter with torch and the inputs before a reconstruction starts
BASELINE_BYTES = 400 * 2**20


def estimate_memory_bytes(settings: Settings, geometry: Geometry, active_voxels: int) -> int:
    """Peak memory of a reconstruction in bytes, to choose a device and to refuse runs that cannot fit.

    The terms, per run (against peak RSS measured in bench/RESULTS.md: 0.6–2.1× of it; the
    distance maps are taken as large as the detector, which over-estimates the paper preset):

    * projectors: about 56 non-zeros per active voxel and view, kept as CSR plus transpose
      (24 B each); building one view briefly needs another ~60 B per non-zero;
    * hash encoding of the fixed points: 8 non-zeros per point and level, 24 B each, ~56 B while
      it is built (coalesced and sorted copies); tables with gradient and Adam's moments (16 B/entry);
    * MLP: ~16 B per unit and layer for the saved activations and their gradients, for every point
      or, with ``checkpoint_points``, for one chunk (plus the chunk inputs of every point);
    * L_geo: ~14 saved images per view and source kind per round of the truncated distance cascade;
    * the interpreter, torch and the inputs (``BASELINE_BYTES``).
    """
    views = geometry.views
    points = int(active_voxels)
    projector_nnz = 56 * points
    encoding_nnz = 8 * settings.levels * points
    stored = len(views) * projector_nnz * 24 + encoding_nnz * 24
    build_peak = max(projector_nnz * 60, encoding_nnz * 56)
    tables = (2 ** settings.log2_table_size) * settings.levels * settings.features_per_level * 16
    mlp_points = min(points, settings.checkpoint_points) if settings.checkpoint_points else points
    mlp = 16 * settings.width * settings.depth * mlp_points
    if settings.checkpoint_points:
        mlp += points * settings.levels * settings.features_per_level * 4 * 3
    distance = 0
    if MODES[settings.mode]["geometric"]:
        for view in views:
            pixel_mm = float(np.mean(view.isocenter_pixel_spacing_mm)) * settings.dt_downsample
            rounds = math.ceil(settings.dt_truncation_mm / pixel_mm / (settings.dt_kernel_size // 2)) + 1
            crop = math.prod(math.ceil(n / settings.dt_downsample) for n in view.detector_shape)
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
    if str(requested).startswith("cuda"):
        if not torch.cuda.is_available():
            raise ReconstructionError("device 'cuda' was requested but no CUDA GPU is available to torch; use --device cpu or auto")
        return torch.device(requested), "requested"
    return torch.device(requested), "requested"


def resolve_device(requested: str) -> torch.device:
    return choose_device(requested)[0]


def validate_targets(targets: Sequence[np.ndarray], geometry: Geometry, kind: str) -> List[np.ndarray]:
    """Check the per-view targets and return them as float32 arrays (masks as 0/1)."""
    if kind not in TARGET_KINDS:
        raise ReconstructionError(f"target kind must be one of {TARGET_KINDS}, got {kind!r}")
    if len(targets) != len(geometry.views):
        raise ReconstructionError(f"{len(targets)} target image(s) for {len(geometry.views)} view(s) in the geometry; give one per view")
    out = []
    for n, (target, view) in enumerate(zip(targets, geometry.views), start=1):
        a = np.asarray(target)
        if a.shape != tuple(view.detector_shape):
            raise ReconstructionError(
                f"view {n}: image shape {a.shape} differs from the detector shape {tuple(view.detector_shape)} "
                "in the geometry; use the mask of that view or fix detector_shape")
        if not np.issubdtype(a.dtype, np.number) and a.dtype != bool:
            raise ReconstructionError(f"view {n}: image data type {a.dtype} is not numeric")
        a = a.astype(np.float32)
        if not np.all(np.isfinite(a)):
            raise ReconstructionError(f"view {n}: the image contains NaN or infinite values; fix the input image")
        if kind == "mask":
            values = np.unique(a)
            if values.size > 2 or (values.size == 2 and values[0] != 0):
                raise ReconstructionError(
                    f"view {n}: the mask is not binary (values {values[:6].tolist()}{'…' if values.size > 6 else ''}); "
                    "give a mask with 0 for background and one non-zero value for vessel")
            a = (a != 0).astype(np.float32)
            if not a.any():
                raise ReconstructionError(f"view {n}: the mask is empty (no vessel pixel); segment the vessels of this view first")
            if a.all():
                raise ReconstructionError(f"view {n}: the mask covers the whole image; it is not a vessel segmentation")
        else:
            if a.min() < 0:
                raise ReconstructionError(f"view {n}: line integrals must be non-negative (min {a.min():.3g})")
            if not a.any():
                raise ReconstructionError(f"view {n}: the line-integral image is all zero; there is no vessel to reconstruct")
        out.append(a)
    return out


@dataclass
class Reconstruction:
    """Result of ``reconstruct``: volumes on ``geometry.volume`` (arrays ``[i, j, k]``) and a report."""

    geometry: Geometry
    settings: Settings
    occupancy: np.ndarray  # float32 in [0, 1]
    field: np.ndarray  # float32: s (sdf modes, mm-free units) or logit (occupancy modes)
    segmentation: np.ndarray  # bool, occupancy >= threshold
    support: Optional[np.ndarray]  # bool voxels the field was evaluated on (None: all)
    report: Dict[str, Any] = field(default_factory=dict)
    history: List[Dict[str, float]] = field(default_factory=list)


def _normalised_points(geometry: Geometry, flat: np.ndarray, device: torch.device) -> torch.Tensor:
    shape = np.asarray(geometry.volume.shape)
    ijk = np.stack(np.unravel_index(flat, tuple(shape)), axis=-1)
    return torch.as_tensor((ijk + 0.5) / shape, dtype=torch.float32, device=device)


def _is_cancelled(cancel: Optional[Callable[[], bool]]) -> bool:
    return bool(cancel is not None and cancel())


def versions() -> Dict[str, str]:
    import scipy
    import skimage

    return {
        "sdfcar": __version__, "python": platform.python_version(), "torch": torch.__version__,
        "numpy": np.__version__, "scipy": scipy.__version__, "scikit-image": skimage.__version__,
    }


def device_description(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


def reconstruct(
    geometry: Geometry,
    targets: Sequence[np.ndarray],
    settings: Optional[Settings] = None,
    target_kind: str = "mask",
    progress: Optional[Callable[[Dict[str, Any]], None]] = None,
    cancel: Optional[Callable[[], bool]] = None,
    progress_interval_s: float = 0.5,
    snapshot: Optional[Callable[[int, np.ndarray], None]] = None,
    snapshot_every: int = 0,
) -> Reconstruction:
    """Reconstruct the vessel tree seen in ``targets`` (one image per view of ``geometry``).

    ``snapshot(step, occupancy)`` — for benchmarks of time to accuracy — receives the occupancy
    volume every ``snapshot_every`` steps (its time is excluded from the optimisation timings).
    """
    settings = settings or make_settings("fast")
    settings.validate()
    t_start = time.perf_counter()
    arrays = validate_targets(targets, geometry, target_kind)
    if settings.threads:
        torch.set_num_threads(int(settings.threads))
    torch.manual_seed(settings.seed)
    np.random.seed(settings.seed % (2**32))
    mode = MODES[settings.mode]
    grid = geometry.volume

    def report_progress(**info: Any) -> None:
        if progress is not None:
            progress(info)

    report_progress(phase="setup", step=0, total=settings.steps, elapsed_s=0.0, eta_s=None, device=settings.device)

    # Support: where the field is evaluated.
    if settings.support == "hull":
        # Line integrals have faint interpolation tails; a vessel pixel is one above the mask
        # threshold, and the voxel footprint plus the margin cover the tails.
        floor = 0.0 if target_kind == "mask" else DEFAULT_MASK_THRESHOLD_MM
        support = support_mask([a > floor for a in arrays], geometry.views, grid, settings.support_margin_mm)
        voxels = np.flatnonzero(support.reshape(-1))
        if voxels.size == 0:
            raise ReconstructionError(
                "the masks' back-projections do not intersect inside the volume: check the view angles, "
                "that mask 1 and mask 2 belong to views 1 and 2, and the volume centre")
    else:
        support, voxels = None, np.arange(grid.num_voxels)
    needed_bytes = estimate_memory_bytes(settings, geometry, int(voxels.size))
    device, device_reason = choose_device(settings.device, needed_bytes)
    if device.type == "cpu" and settings.memory_check:
        check_host_memory(needed_bytes, available_memory_bytes())
    points = _normalised_points(geometry, voxels, device)
    projectors = [
        ConeBeamProjector(view, grid, voxels=None if support is None else voxels, device=str(device))
        for view in geometry.views
    ]
    view_targets: List[ViewTarget] = [
        make_target(torch.as_tensor(array, device=device), target_kind, settings.silhouette_length_mm,
                    settings.mask_model, float(np.mean(view.isocenter_pixel_spacing_mm)))
        for array, view in zip(arrays, geometry.views)
    ]
    geometric: Optional[GeometricLoss] = None
    if mode["geometric"]:
        geometric = GeometricLoss(
            [t.silhouette for t in view_targets],
            [float(np.mean(v.isocenter_pixel_spacing_mm)) for v in geometry.views],
            [None if support is None else p.pixels for p in projectors],
            DistanceSettings(settings.dt_downsample, settings.dt_threshold, settings.dt_truncation_mm, settings.dt_kernel_size),
        )
    if _is_cancelled(cancel):
        raise ReconstructionCancelled("cancelled before the optimisation started")

    model = ImplicitField(settings.field_config()).to(device)
    encoded = model.prepare(points)
    table_lr = settings.table_learning_rate or settings.learning_rate
    optimiser = torch.optim.Adam([
        {"params": [model.encoding.table], "lr": table_lr},
        {"params": list(model.mlp.parameters()), "lr": settings.learning_rate},
    ])
    # A linear warm-up keeps Adam's first, sign-like steps from saturating σ(−α·s).
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimiser, lambda n: min(1.0, (n + 1) / settings.warmup_steps) if settings.warmup_steps > 0 else 1.0)
    setup_s = time.perf_counter() - t_start

    history: List[Dict[str, float]] = []
    t_loop = time.perf_counter()
    last_report = -math.inf
    losses: Dict[str, float] = {}
    for step in range(1, settings.steps + 1):
        if _is_cancelled(cancel):
            raise ReconstructionCancelled(f"cancelled at step {step - 1} of {settings.steps}")
        optimiser.zero_grad(set_to_none=True)
        occupancy = model(encoded, checkpoint_points=settings.checkpoint_points)
        line_integrals = [projector.render(occupancy) for projector in projectors]
        l_occ = sum(occupancy_loss(t.rendered(li), t.image) for li, t in zip(line_integrals, view_targets)) / len(projectors)
        loss = settings.lambda_occ * l_occ
        l_geo = torch.zeros((), device=device)
        if geometric is not None:
            l_geo = geometric([t.silhouette_of(li) for li, t in zip(line_integrals, view_targets)])
            loss = loss + settings.lambda_geo * l_geo
        loss.backward()
        optimiser.step()
        scheduler.step()
        losses = {"loss": float(loss.detach()), "l_occ": float(l_occ.detach()), "l_geo": float(l_geo.detach())}
        history.append({"step": step, **losses})
        if snapshot is not None and snapshot_every > 0 and step % snapshot_every == 0:
            paused = time.perf_counter()
            snapshot(step, _evaluate_volume(model, geometry, voxels, support is None, device)[0])
            t_loop += time.perf_counter() - paused
        now = time.perf_counter()
        if now - last_report >= progress_interval_s or step == settings.steps:
            elapsed = now - t_loop
            report_progress(phase="optimise", step=step, total=settings.steps, elapsed_s=elapsed,
                            eta_s=elapsed / step * (settings.steps - step), device=str(device), **losses)
            last_report = now
    optimise_s = time.perf_counter() - t_loop

    report_progress(phase="output", step=settings.steps, total=settings.steps, elapsed_s=time.perf_counter() - t_loop, eta_s=0.0, device=str(device))
    t_out = time.perf_counter()
    occupancy_volume, field_volume = _evaluate_volume(model, geometry, voxels, support is None, device)
    segmentation = occupancy_volume >= settings.threshold
    pruning: Optional[Dict[str, Any]] = None
    if settings.prune and segmentation.any():
        if _is_cancelled(cancel):
            raise ReconstructionCancelled("cancelled before pruning")
        report_progress(phase="prune", step=settings.steps, total=settings.steps,
                        elapsed_s=time.perf_counter() - t_loop, eta_s=None, device=str(device))
        floor = 0.0 if target_kind == "mask" else DEFAULT_MASK_THRESHOLD_MM
        kept, pruning = prune_redundant_branches(
            segmentation, [a > floor for a in arrays], geometry,
            PruneSettings(max_piece_mm=settings.prune_piece_mm, tolerance=settings.prune_tolerance))
        if settings.prune_min_component_fraction > 0:
            before = int(kept.sum())
            kept = drop_small_components(kept, settings.prune_min_component_fraction)
            pruning["small_component_voxels"] = before - int(kept.sum())
        zone = removal_zone(segmentation, kept, grid.spacing_mm)
        occupancy_volume[zone] = 0.0
        field_volume[zone] = float(field_volume.max()) if MODES[settings.mode]["field"] == "sdf" else float(field_volume.min())
        segmentation = occupancy_volume >= settings.threshold
    reprojection = _reprojection_dice(segmentation, geometry, arrays, target_kind)
    output_s = time.perf_counter() - t_out

    report: Dict[str, Any] = {
        "method": MODES[settings.mode]["title"],
        "settings": settings.to_dict(),
        "target_kind": target_kind,
        "seed": settings.seed,
        "device": device_description(device),
        "device_reason": device_reason,
        "memory_estimate_bytes": needed_bytes,
        "versions": versions(),
        "geometry": geometry.to_dict(),
        "geometry_digest": geometry.digest(),
        "support_voxels": int(voxels.size),
        "segmented_voxels": int(segmentation.sum()),
        "pruning": pruning,
        "projector_nonzeros": [p.nnz for p in projectors],
        "final_losses": losses,
        "reprojection_dice": reprojection,
        "timings_s": {"setup": setup_s, "optimise": optimise_s, "output": output_s,
                      "total": time.perf_counter() - t_start, "per_step": optimise_s / settings.steps},
    }
    return Reconstruction(geometry, settings, occupancy_volume, field_volume, segmentation, support, report, history)


@torch.no_grad()
def _evaluate_volume(model: ImplicitField, geometry: Geometry, voxels: np.ndarray, dense: bool,
                     device: torch.device, chunk: int = 262144):
    grid = geometry.volume
    raw_values = []
    for start in range(0, voxels.size, chunk):
        raw_values.append(model.raw(_normalised_points(geometry, voxels[start:start + chunk], device)).float().cpu())
    raw = torch.cat(raw_values) if raw_values else torch.zeros(0)
    occupancy = model.occupancy_from_raw(raw).numpy()
    occ_volume = np.zeros(grid.num_voxels, dtype=np.float32)
    occ_volume[voxels] = occupancy
    # Outside the support the field was never evaluated: record it as clearly outside.
    if model.config.kind == "sdf":
        outside = max(float(raw.max()) if raw.numel() else 1.0, 1.0)
    else:
        outside = min(float(raw.min()) if raw.numel() else -10.0, -10.0)
    field_volume = np.full(grid.num_voxels, outside, dtype=np.float32)
    field_volume[voxels] = raw.numpy()
    return occ_volume.reshape(grid.shape), field_volume.reshape(grid.shape)


def _reprojection_dice(segmentation: np.ndarray, geometry: Geometry, targets: Sequence[np.ndarray], kind: str,
                       mask_threshold_mm: float = 0.2) -> List[float]:
    from .metrics import mask_dice
    from .projector import project_volume

    out = []
    for view, target in zip(geometry.views, targets):
        if segmentation.any():
            projected = project_volume(segmentation.astype(np.float32), view, geometry.volume) > mask_threshold_mm
        else:
            projected = np.zeros(view.detector_shape, dtype=bool)
        reference = target > 0 if kind == "mask" else target > mask_threshold_mm
        out.append(mask_dice(projected, reference))
    return out
