"""Evaluation harness: the paper's Tables 1–4 measured on many simulated cases, locally or on Dask.

``python -m SDFCARLib benchmark --suite rca --modes sdfcar,neca --preset fast --cases 10 --out DIR``

For every case of a suite the harness simulates the protocol's two views of the ground-truth
label, computes the visual hull of the two masks (the baseline row ``hull``), reconstructs with
every requested mode and scores each result with ``metrics.evaluate`` against the label and the
masks. Cases run as Dask tasks (one task prepares a case, one task per mode reconstructs it) on a
``LocalCluster`` or on an existing cluster given by ``--scheduler``.

Suites
    ``rca``, ``lad``   procedural trees ``phantoms.rca_tree`` / ``lad_tree``, seeds seed … seed+N−1.
    ``721a``           the 721A centreline (``--centreline``), centred on the isocenter; N cases
                       are N optimiser seeds on that one anatomy.
    ``folder:PATH``    label volumes (NRRD/NIfTI, e.g. ImageCAS) with the DeepCA/NeCA preprocessing
                       (``preprocess_label_volume``): each file gives two cases, ``<stem>-lad`` and
                       ``<stem>-rca``.

Protocols
    ``paper``          line-integral targets, the NeCA views (``VIEW_PAIRS["paper"]``), 512² detector
                       at 0.278 mm, 128³ grid at 0.8 mm (1 mm for folder suites).
    ``clinical-…``     binary-mask targets with the named clinical pair, same detector and grid.

Files in ``--out``
    ``results.csv``    one row per case × mode (and the hull), appended as each task finishes, so
                       nothing finished is lost; a re-run of the same command skips rows already
                       there (failed ones too, unless ``--retry-failed``).
    ``summary.md``     mean ± std tables laid out like the paper's, the sdfcar-vs-neca ordering,
                       the command, seeds, versions, machine and date.
    ``run.json``       every invocation's configuration, cases, seeds, versions, machine, cluster.
    ``errors/``        the traceback of every failed case × mode.
    ``figures/``       per-metric box plots per mode, and overlay MIPs (green overlap, red predicted
                       only, blue missed) of the first ``--overlays`` cases.

Rows are keyed by (suite, case, mode, config): ``config`` is a short hash of everything besides
the case and mode that changes a result (protocol, preset, steps, ``--set`` overrides, grid and
detector overrides, base seed), so variants can share one folder without mixing; ``summary.md``
covers the rows of the command that wrote it.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import hashlib
import json
import math
import os
import platform
import re
import shlex
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import Geometry, VolumeGrid, standard_geometry
from .io import json_compatible, write_text_atomically

PathLike = Union[str, Path]

# Bump when a change to this harness changes what a row means; it enters the config hash.
HARNESS_VERSION = 1

HULL = "hull"
DEFAULT_MODES = ("sdfcar", "neca", "occ-combined", "sdf-occ")
PROCEDURAL_SUITES = ("rca", "lad")
SUITE_HELP = "rca, lad (procedural trees), 721a (the 721A centreline) or folder:PATH (label volumes)"

#: protocol name → (VIEW_PAIRS key, target kind)
PROTOCOLS: Dict[str, Tuple[str, str]] = {
    "paper": ("paper", "line_integral"),
    "clinical-lao30-rao30": ("lao30-rao30", "mask"),
    "clinical-lao50cra25-rao50cra25": ("lao50cra25-rao50cra25", "mask"),
}
PAPER_VOLUME_SHAPE = (128, 128, 128)
PAPER_SPACING_MM = 0.8
FOLDER_SPACING_MM = 1.0  # DeepCA/NeCA resample ImageCAS labels to 1 mm
PAPER_DETECTOR_SHAPE = (512, 512)
PAPER_DETECTOR_SPACING_MM = 0.278

VOLUME_SUFFIXES = (".nii.gz", ".seg.nrrd", ".nrrd", ".nhdr", ".nii")

# Short row names as in the paper's tables; a mode the optimiser adds later falls back to its title.
MODE_NAMES = {
    HULL: "Visual hull (masks only)",
    "neca": "NeCA",
    "occ-combined": "Occ. Rep. + Combined Loss",
    "sdf-occ": "SDF Rep. + Occ. Loss",
    "sdfcar": "SDF-CAR",
}

#: (column, header, scale, decimals, higher is better) — the paper's six metrics, then ours.
TABLE_METRICS: List[Tuple[str, str, float, int, bool]] = [
    ("cldice", "clDice (%)", 100.0, 2, True),
    ("dice", "Dice (%)", 100.0, 2, True),
    ("iou", "IoU (%)", 100.0, 2, True),
    ("re_error", "reError", 1.0, 3, False),
    ("chamfer_l2_mm", "CD-ℓ2 (mm)", 1.0, 2, False),
    ("re_mse", "reMSE (×1e-4)", 1e4, 2, False),
    ("skeleton_dice", "skeleton-Dice (%)", 100.0, 2, True),
    ("wall_s", "wall time (s)", 1.0, 1, False),
]
PAPER_METRICS = ("cldice", "dice", "iou", "re_error", "chamfer_l2_mm", "re_mse")

IDENTITY_COLUMNS = ["suite", "tree", "case", "seed", "protocol", "target_kind", "mode", "preset", "steps",
                    "overrides", "config"]
METRIC_COLUMNS = ["cldice", "tprec", "tsens", "skeleton_dice", "dice", "iou", "chamfer_l2_mm", "re_error", "re_mse",
                  "reprojection_dice_view1", "reprojection_dice_view2", "voxels_predicted", "voxels_label"]
COLUMNS = IDENTITY_COLUMNS + ["status", "error", "traceback_file"] + METRIC_COLUMNS + [
    "wall_s", "eval_s", "prepare_s", "device", "worker", "finished_at"]

# Settings the harness sets itself; --set must not fight them.
_RESERVED_SETTINGS = {
    "mode": "choose modes with --modes",
    "seed": "seeds are fixed per case; choose the first with --seed",
    "steps": "use --steps",
    "preset": "use --preset",
    "threads": "use --threads-per-worker",
}


class BenchmarkError(ValueError):
    """Bad benchmark input; the message names the problem and the fix."""


# --- configuration -------------------------------------------------------------------------------
@dataclass(frozen=True)
class GridOptions:
    """Overrides of the protocol's grid and detector (None: the protocol's), e.g. for quick runs."""

    volume_shape: Optional[Tuple[int, int, int]] = None
    spacing_mm: Optional[float] = None
    detector_shape: Optional[Tuple[int, int]] = None
    detector_spacing_mm: Optional[float] = None

    def to_dict(self) -> Dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


@dataclass(frozen=True)
class CaseSpec:
    """One case: everything a worker needs to rebuild its label (small, picklable)."""

    suite: str
    name: str
    tree: str  # "rca" or "lad"
    seed: int
    index: int
    source: str = ""  # centreline or label file
    component: str = ""  # folder suites: which tree of the file ("lad" or "rca")


@dataclass
class BenchmarkConfig:
    suite: str
    out: Path
    modes: Tuple[str, ...] = DEFAULT_MODES
    preset: str = "fast"
    protocol: str = "paper"
    cases: Optional[int] = None  # None: 10 procedural, 1 for 721a, every file of a folder
    seed: int = 0
    steps: Optional[int] = None
    overrides: Dict[str, Any] = field(default_factory=dict)
    grid: GridOptions = field(default_factory=GridOptions)
    centreline: Optional[Path] = None
    scheduler: Optional[str] = None
    workers: Optional[int] = None
    threads_per_worker: int = 1
    overlays: int = 3
    retry_failed: bool = False
    progress: bool = True

    def identity(self) -> Dict[str, Any]:
        """What, besides the case and mode, determines a row's numbers.

        The preset is resolved into its settings, so that retuned preset values make new rows
        instead of resuming from rows computed with the old ones.
        """
        from . import __version__
        from .optimiser import make_settings

        settings = make_settings(self.preset, steps=self.steps, **self.overrides).to_dict()
        for name in ("mode", "seed", "threads"):  # per row, or not affecting the numbers
            settings.pop(name, None)
        return {"harness": HARNESS_VERSION, "sdfcar": __version__, "protocol": self.protocol, "preset": self.preset,
                "steps": self.steps, "overrides": dict(sorted(self.overrides.items())), "grid": self.grid.to_dict(),
                "seed": self.seed, "settings": settings}

    def config_id(self) -> str:
        text = json.dumps(self.identity(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:10]

    def command_line(self) -> str:
        """The full command (defaults spelled out) that reproduces this run."""
        parts = ["python", "-m", "SDFCARLib", "benchmark", "--suite", self.suite, "--modes", ",".join(self.modes),
                 "--preset", self.preset, "--protocol", self.protocol, "--seed", str(self.seed), "--out", str(self.out)]
        if self.cases is not None:
            parts += ["--cases", str(self.cases)]
        if self.steps is not None:
            parts += ["--steps", str(self.steps)]
        for key, value in sorted(self.overrides.items()):
            parts += ["--set", f"{key}={json.dumps(value)}"]
        g = self.grid
        if g.volume_shape:
            parts += ["--volume-shape", *map(str, g.volume_shape)]
        if g.spacing_mm:
            parts += ["--spacing-mm", repr(g.spacing_mm)]
        if g.detector_shape:
            parts += ["--detector-shape", *map(str, g.detector_shape)]
        if g.detector_spacing_mm:
            parts += ["--detector-spacing-mm", repr(g.detector_spacing_mm)]
        if self.centreline is not None and self.suite == "721a":
            parts += ["--centreline", str(self.centreline)]
        return " ".join(shlex.quote(p) for p in parts)


def parse_overrides(items: Optional[Iterable[str]]) -> Dict[str, Any]:
    """``["learning_rate=1e-3", "device=cuda"]`` → typed optimiser overrides, checked against ``Settings``."""
    from .optimiser import ReconstructionError, parse_setting_overrides

    try:
        return parse_setting_overrides(items, reserved=_RESERVED_SETTINGS)
    except ReconstructionError as error:
        raise BenchmarkError(str(error)) from None


def parse_suite(suite: str) -> Tuple[str, Optional[Path]]:
    """``"rca"`` → ("rca", None); ``"folder:PATH"`` → ("folder", PATH)."""
    text = str(suite).strip()
    if text.lower() in PROCEDURAL_SUITES + ("721a",):
        return text.lower(), None
    if text.lower().startswith("folder:"):
        path = Path(text[len("folder:"):]).expanduser()
        if not str(path) or str(path) == ".":
            raise BenchmarkError("--suite folder:PATH needs the folder of label volumes after 'folder:'")
        return "folder", path
    raise BenchmarkError(f"unknown suite {suite!r}; choose {SUITE_HELP}")


def default_centreline() -> Path:
    """``../shared/data/721A_Centreline.vtk`` beside the repository holding SDFCARLib."""
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "721A_Centreline.vtk"


def _volume_files(folder: Path) -> List[Path]:
    if not folder.is_dir():
        raise BenchmarkError(f"--suite folder:{folder}: no such folder; give the folder holding the label volumes")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.name.lower().endswith(VOLUME_SUFFIXES))
    if not files:
        raise BenchmarkError(f"--suite folder:{folder}: the folder holds no label volume "
                             f"({', '.join(VOLUME_SUFFIXES)}); put the labels (e.g. ImageCAS *.label.nii.gz) there")
    return files


def _stem(path: Path) -> str:
    name = path.name
    for suffix in VOLUME_SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return path.stem


def build_cases(config: BenchmarkConfig) -> List[CaseSpec]:
    """The suite's cases in a fixed order, with their seeds."""
    kind, folder = parse_suite(config.suite)
    n = config.cases
    if n is not None and n < 1:
        raise BenchmarkError(f"--cases must be at least 1, got {n}")
    if kind in PROCEDURAL_SUITES:
        count = 10 if n is None else n
        prefix = kind.upper()
        return [CaseSpec(kind, f"{prefix}-{config.seed + i}", kind, config.seed + i, i) for i in range(count)]
    if kind == "721a":
        path = Path(config.centreline) if config.centreline else default_centreline()
        if not path.is_file():
            raise BenchmarkError(f"the 721a suite needs the 721A centreline (legacy VTK with radii); it is not at {path}: "
                                 "give its path with --centreline")
        count = 1 if n is None else n
        return [CaseSpec("721a", f"721A-s{config.seed + i}", "lad", config.seed + i, i, str(path.resolve())) for i in range(count)]
    cases: List[CaseSpec] = []
    for path in _volume_files(folder):
        for tree in ("lad", "rca"):
            index = len(cases)
            cases.append(CaseSpec(config.suite, f"{_stem(path)}-{tree}", tree, config.seed + index, index,
                                  str(path.resolve()), tree))
    return cases if n is None else cases[:n]


# --- geometry and cases -----------------------------------------------------------------------------
def protocol_geometry(protocol: str, suite_kind: str, grid: Optional[GridOptions] = None) -> Geometry:
    """The protocol's views and grid, with ``grid``'s overrides."""
    if protocol not in PROTOCOLS:
        raise BenchmarkError(f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")
    grid = grid or GridOptions()
    pair, _ = PROTOCOLS[protocol]
    spacing = grid.spacing_mm or (FOLDER_SPACING_MM if suite_kind == "folder" else PAPER_SPACING_MM)
    return standard_geometry(
        pair, volume_shape=grid.volume_shape or PAPER_VOLUME_SHAPE, spacing_mm=spacing,
        detector_shape=grid.detector_shape or PAPER_DETECTOR_SHAPE,
        detector_spacing_mm=grid.detector_spacing_mm or PAPER_DETECTOR_SPACING_MM)


def _connected_components(label: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    from scipy import ndimage

    # 26-connectivity: diagonal voxel contacts along a thin oblique vessel are still one vessel.
    components, count = ndimage.label(label, structure=np.ones((3, 3, 3), dtype=bool))
    sizes = np.bincount(components.reshape(-1), minlength=count + 1)[1:]
    return components, sizes


def _resample_nearest(mask: np.ndarray, spacing_in: Sequence[float], spacing_out: float) -> np.ndarray:
    """``mask`` (its voxels' faces spanning the array) resampled by nearest neighbour to ``spacing_out``.

    The output covers the same box: its first voxel's low faces coincide with the input's.
    """
    from scipy import ndimage

    spacing_in = np.asarray(spacing_in, float)
    ratio = spacing_out / spacing_in
    shape = np.maximum(1, np.ceil(np.asarray(mask.shape) * spacing_in / spacing_out - 1e-6).astype(int))
    # Output voxel m's centre lies at input index (m + 0.5) · ratio − 0.5.
    return ndimage.affine_transform(mask.astype(np.uint8), ratio, offset=0.5 * ratio - 0.5, output_shape=tuple(shape),
                                    order=0, mode="constant", cval=0).astype(bool)


def _centre_in(mask: np.ndarray, shape: Sequence[int]) -> Tuple[np.ndarray, int]:
    """``mask``'s bounding box centred in an array of ``shape``; also the vessel voxels cut off."""
    out = np.zeros(tuple(shape), dtype=bool)
    nz = np.argwhere(mask)
    lo, hi = nz.min(axis=0), nz.max(axis=0) + 1
    src, dst = [], []
    for a in range(3):
        size, n = hi[a] - lo[a], int(shape[a])
        if size <= n:
            start = (n - size) // 2
            src.append(slice(lo[a], hi[a]))
            dst.append(slice(start, start + size))
        else:  # too large: keep the middle
            cut = (size - n) // 2
            src.append(slice(lo[a] + cut, lo[a] + cut + n))
            dst.append(slice(0, n))
    out[tuple(dst)] = mask[tuple(src)]
    return out, int(mask.sum() - out.sum())


def preprocess_label_volume(label: np.ndarray, grid: VolumeGrid, spacing_mm: float = FOLDER_SPACING_MM,
                            shape: Sequence[int] = PAPER_VOLUME_SHAPE,
                            name: str = "label") -> Dict[str, Tuple[np.ndarray, VolumeGrid, Dict[str, Any]]]:
    """Split a coronary label into its two trees, each resampled to ``spacing_mm`` and centred in ``shape``.

    The DeepCA/NeCA preprocessing: the two largest connected components (26-connectivity,
    found at the label's own resolution, where thin vessels are still connected) are the two
    trees; the one whose centroid lies further to the patient's left (larger LPS x) is the left
    tree ("lad"), the other the right coronary artery ("rca"). Each is resampled by nearest
    neighbour to ``spacing_mm`` and its bounding box centred in a ``shape`` grid centred on the
    isocenter. Smaller components (fragments) are dropped and counted in the returned info.

    Returns ``{"lad": (mask, grid, info), "rca": (mask, grid, info)}``.
    """
    label = np.asarray(label).astype(bool)
    if label.ndim != 3 or label.shape != tuple(grid.shape):
        raise BenchmarkError(f"{name}: label shape {label.shape} does not match its grid {tuple(grid.shape)}")
    components, sizes = _connected_components(label)
    if sizes.size < 2:
        raise BenchmarkError(
            f"{name}: the label has {sizes.size} connected component(s); the folder suite needs the left and right "
            "coronary trees as two separate components (an ImageCAS-style label of both trees)")
    order = np.argsort(sizes)[::-1][:2] + 1
    centroids_x = [float(grid.index_to_world(np.argwhere(components == c).mean(axis=0))[0]) for c in order]
    left, right = (order[0], order[1]) if centroids_x[0] >= centroids_x[1] else (order[1], order[0])
    out_grid = VolumeGrid(tuple(int(s) for s in shape), (float(spacing_mm),) * 3)
    dropped = int(label.sum() - sizes[order - 1].sum())
    result: Dict[str, Tuple[np.ndarray, VolumeGrid, Dict[str, Any]]] = {}
    for tree, component in (("lad", left), ("rca", right)):
        mask = components == component
        nz = np.argwhere(mask)
        lo, hi = nz.min(axis=0), nz.max(axis=0) + 1
        cropped = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        resampled = _resample_nearest(cropped, grid.spacing_mm, float(spacing_mm))
        if not resampled.any():
            raise BenchmarkError(f"{name}: the {tree} tree vanishes when resampled to {spacing_mm} mm; use a finer spacing")
        centred, cut = _centre_in(resampled, shape)
        info = {"source_voxels": int(mask.sum()), "source_spacing_mm": [float(s) for s in grid.spacing_mm],
                "source_centroid_x_mm": centroids_x[list(order).index(component)], "voxels": int(centred.sum()),
                "voxels_cut_off": cut, "fragment_voxels_dropped": dropped}
        result[tree] = (centred, out_grid, info)
    return result


def preprocess_label_file(path: PathLike, spacing_mm: float = FOLDER_SPACING_MM,
                          shape: Sequence[int] = PAPER_VOLUME_SHAPE) -> Dict[str, Tuple[np.ndarray, VolumeGrid, Dict[str, Any]]]:
    """``preprocess_label_volume`` of a label file (NRRD/NIfTI; non-zero = vessel)."""
    from .io import read_label

    label, grid = read_label(path, what="label volume")
    return preprocess_label_volume(label, grid, spacing_mm, shape, name=str(path))


@dataclass
class PreparedCase:
    """A case's ground truth and simulated views on its protocol's geometry."""

    geometry: Geometry
    label: np.ndarray  # bool [i, j, k]
    masks: List[np.ndarray]  # bool per view
    targets: List[np.ndarray]  # what the reconstruction sees: line integrals or masks
    target_kind: str
    info: Dict[str, Any] = field(default_factory=dict)
    prepare_s: float = 0.0


def prepare_case(spec: CaseSpec, protocol: str, grid: Optional[GridOptions] = None) -> PreparedCase:
    """Build the case's label on its geometry and simulate the two views."""
    from .phantoms import DEFAULT_MASK_THRESHOLD_MM, lad_tree, load_centerline_vtk, rca_tree, simulate_views, voxelize

    t0 = time.perf_counter()
    kind, _ = parse_suite(spec.suite)
    geometry = protocol_geometry(protocol, kind, grid)
    info: Dict[str, Any] = {}
    if kind in PROCEDURAL_SUITES:
        tree = (rca_tree if kind == "rca" else lad_tree)(spec.seed)
        label = voxelize(tree, geometry.volume)
    elif kind == "721a":
        tree = load_centerline_vtk(spec.source, name="721A").centered()
        label = voxelize(tree, geometry.volume)
    else:
        trees = preprocess_label_file(spec.source, geometry.volume.spacing_mm[0], geometry.volume.shape)
        label, _, info = trees[spec.component]
    if not label.any():
        raise BenchmarkError(f"case {spec.name}: the vessel tree does not reach the volume grid")
    line_integrals, masks = simulate_views(label, geometry.volume, geometry.views, DEFAULT_MASK_THRESHOLD_MM)
    for n, (mask, view) in enumerate(zip(masks, geometry.views), start=1):
        if not mask.any() or mask.all():
            raise BenchmarkError(f"case {spec.name}: view {n} ({view.describe()}) sees {'no' if not mask.any() else 'only'} "
                                 "vessel; check the grid and detector overrides")
    target_kind = PROTOCOLS[protocol][1]
    targets = line_integrals if target_kind == "line_integral" else [m.astype(np.float32) for m in masks]
    info["label_voxels"] = int(label.sum())
    return PreparedCase(geometry, label, masks, targets, target_kind, info, time.perf_counter() - t0)


# --- one task: a case × mode ------------------------------------------------------------------------
def _reconstruct(geometry, targets, settings, target_kind):
    """The optimiser call (a seam: tests replace it to inject failures)."""
    from .optimiser import reconstruct

    return reconstruct(geometry, targets, settings, target_kind=target_kind)


def _pack(mask: np.ndarray) -> Tuple[bytes, Tuple[int, ...]]:
    return np.packbits(np.asarray(mask, bool).reshape(-1)).tobytes(), tuple(mask.shape)


def _unpack(packed: Tuple[bytes, Tuple[int, ...]]) -> np.ndarray:
    data, shape = packed
    n = int(np.prod(shape))
    return np.unpackbits(np.frombuffer(data, np.uint8), count=n).astype(bool).reshape(shape)


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except Exception:  # not inside a Dask worker
        return "local"


def _base_row(spec: CaseSpec, mode: str, task: Dict[str, Any]) -> Dict[str, Any]:
    return {"suite": spec.suite, "tree": spec.tree, "case": spec.name, "seed": spec.seed, "protocol": task["protocol"],
            "target_kind": PROTOCOLS[task["protocol"]][1], "mode": mode, "preset": task["preset"],
            "steps": task.get("steps_effective", ""), "overrides": task["overrides_text"], "config": task["config"]}


def prepare_task(spec: CaseSpec, protocol: str, grid: GridOptions) -> Dict[str, Any]:
    """Dask task: the prepared case, or the error that stopped it (so dependents record it)."""
    try:
        return {"case": prepare_case(spec, protocol, grid)}
    except Exception as exc:
        return {"error": f"case preparation failed: {_one_line(exc)}", "traceback": traceback.format_exc()}


def run_task(prepared: Dict[str, Any], spec: CaseSpec, mode: str, task: Dict[str, Any]) -> Dict[str, Any]:
    """Dask task: reconstruct one case with one mode (or the hull) and score it. Never raises."""
    import torch

    row = _base_row(spec, mode, task)
    row.update(worker=_worker_name(), status="failed")
    if "error" in prepared:
        row["error"] = prepared["error"]
        return {"row": row, "traceback": prepared["traceback"]}
    case: PreparedCase = prepared["case"]
    row["prepare_s"] = case.prepare_s
    threads = task.get("torch_threads")
    previous_threads = torch.get_num_threads()
    try:
        if threads:
            torch.set_num_threads(int(threads))  # this worker's share of the cores
        grid, views = case.geometry.volume, case.geometry.views
        t0 = time.perf_counter()
        if mode == HULL:
            from .hull import visual_hull

            prediction = visual_hull(case.masks, views, grid)
            row["device"] = "cpu (numpy)"
            row["wall_s"] = time.perf_counter() - t0
        else:
            from .optimiser import make_settings

            settings = make_settings(task["preset"], mode=mode, seed=spec.seed, steps=task["steps"], **task["overrides"])
            row["steps"] = settings.optimisation.steps
            result = _reconstruct(case.geometry, case.targets, settings, case.target_kind)
            prediction = result.segmentation
            row["device"] = result.report.get("device", "")
            row["wall_s"] = float(result.report.get("timings_s", {}).get("total", time.perf_counter() - t0))
        t1 = time.perf_counter()
        from .metrics import evaluate

        metrics = evaluate(prediction, case.label, grid, views, case.masks)
        row["eval_s"] = time.perf_counter() - t1
        for key in METRIC_COLUMNS:
            if key in metrics:
                row[key] = metrics[key]
        for n, value in enumerate(metrics.get("reprojection_dice", []), start=1):
            row[f"reprojection_dice_view{n}"] = value
        row["status"], row["error"] = "ok", ""
        out: Dict[str, Any] = {"row": row}
        if task.get("overlay"):
            out["overlay"] = (_pack(prediction), _pack(case.label))
        return out
    except Exception as exc:
        row["error"] = _one_line(exc)
        return {"row": row, "traceback": traceback.format_exc()}
    finally:
        torch.set_num_threads(previous_threads)


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}" if str(exc).strip() else type(exc).__name__


# --- results.csv ----------------------------------------------------------------------------------
def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return repr(v) if math.isfinite(v) else "nan"
    return str(value)


class ResultsFile:
    """``results.csv``: rows appended and flushed one by one, so an interrupted run loses nothing."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.columns = list(COLUMNS)
        if self.path.exists() and self.path.stat().st_size > 0:
            with self.path.open(newline="", encoding="utf-8") as stream:
                header = next(csv.reader(stream), None)
            if not header or "case" not in header or "mode" not in header:
                raise BenchmarkError(f"{self.path} is not a benchmark results file (its header is {header!r}); "
                                     "choose another --out")
            # A file from another harness version keeps its own columns: rows stay aligned with its header.
            self.columns = header

    def rows(self) -> List[Dict[str, str]]:
        if not self.path.exists():
            return []
        with self.path.open(newline="", encoding="utf-8") as stream:
            reader = csv.DictReader(stream)
            # A row cut short by a crash mid-write has missing cells (None): not a finished row.
            return [r for r in reader if None not in r.values() and r.get("status") in ("ok", "failed")]

    def append(self, row: Dict[str, Any]) -> None:
        new = not self.path.exists() or self.path.stat().st_size == 0
        if not new:
            with self.path.open("rb") as stream:
                stream.seek(-1, os.SEEK_END)
                needs_newline = stream.read(1) not in (b"\n", b"\r")
        with self.path.open("a", newline="", encoding="utf-8") as stream:
            if not new and needs_newline:
                stream.write("\r\n")  # finish a line a crash left open, so this row starts afresh
            writer = csv.DictWriter(stream, fieldnames=self.columns, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow({c: _cell(row.get(c)) for c in self.columns})
            stream.flush()
            os.fsync(stream.fileno())


def _row_key(row: Dict[str, Any]) -> Tuple[str, str, str, str]:
    return (str(row.get("suite")), str(row.get("case")), str(row.get("mode")), str(row.get("config")))


def latest_rows(rows: Iterable[Dict[str, str]]) -> Dict[Tuple[str, str, str, str], Dict[str, str]]:
    """The last row written for each (suite, case, mode, config)."""
    out: Dict[Tuple[str, str, str, str], Dict[str, str]] = {}
    for row in rows:
        out[_row_key(row)] = row
    return out


# --- summary ------------------------------------------------------------------------------------
def _float(text: Any) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def _mean_std(values: Sequence[float]) -> Tuple[float, float, int]:
    finite = np.asarray([v for v in values if math.isfinite(v)], float)
    if finite.size == 0:
        return math.nan, math.nan, 0
    std = float(finite.std(ddof=1)) if finite.size > 1 else 0.0
    return float(finite.mean()), std, int(finite.size)


def mode_title(mode: str) -> str:
    if mode in MODE_NAMES:
        return MODE_NAMES[mode]
    try:
        from .optimiser import MODES

        return MODES[mode].title
    except Exception:
        return mode


def _group_title(suite: str, tree: str) -> str:
    kind = suite.split(":", 1)[0]
    names = {"rca": "RCA (procedural trees)", "lad": "LAD (procedural left trees)", "721a": "721A centreline (LAD)"}
    if kind == "folder":
        return f"{'Left coronary tree (LAD)' if tree == 'lad' else 'Right coronary artery (RCA)'} — {suite}"
    return names.get(kind, suite)


def summary_tables(rows: Sequence[Dict[str, str]], modes: Sequence[str]) -> List[Dict[str, Any]]:
    """Per (suite, tree): per method the mean ± std of every table metric, over finished cases."""
    groups: Dict[Tuple[str, str], List[Dict[str, str]]] = {}
    for row in rows:
        groups.setdefault((row["suite"], row["tree"]), []).append(row)
    tables = []
    for (suite, tree), group in groups.items():
        methods = []
        for mode in [HULL] + [m for m in modes if m != HULL]:
            mode_rows = [r for r in group if r["mode"] == mode]
            ok = [r for r in mode_rows if r["status"] == "ok"]
            stats = {key: _mean_std([_float(r.get(key)) * scale for r in ok]) for key, _, scale, _, _ in TABLE_METRICS}
            methods.append({"mode": mode, "ok": len(ok), "failed": len(mode_rows) - len(ok), "stats": stats,
                            "per_case": {r["case"]: r for r in ok}})
        tables.append({"suite": suite, "tree": tree, "title": _group_title(suite, tree), "methods": methods,
                       "cases": sorted({r["case"] for r in group})})
    return tables


def _table_markdown(table: Dict[str, Any]) -> str:
    headers = ["Method"] + [h for _, h, _, _, _ in TABLE_METRICS] + ["cases (ok/failed)"]
    best: Dict[str, float] = {}
    for key, _, _, _, higher in TABLE_METRICS:
        means = [m["stats"][key][0] for m in table["methods"] if math.isfinite(m["stats"][key][0])]
        if means:
            best[key] = max(means) if higher else min(means)
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join(["---"] + ["---:"] * (len(headers) - 1)) + "|"]
    for method in table["methods"]:
        cells = [f"{mode_title(method['mode'])} (`{method['mode']}`)"]
        for key, _, _, decimals, _ in TABLE_METRICS:
            mean, std, n = method["stats"][key]
            if not math.isfinite(mean):
                cells.append("n/a")
                continue
            text = f"{mean:.{decimals}f} ± {std:.{decimals}f}"
            if n < method["ok"]:
                text += f" (n={n})"  # some cases undefined, e.g. Chamfer distance of an empty prediction
            is_best = key in best and round(mean, decimals) == round(best[key], decimals)
            cells.append(f"**{text}**" if is_best else text)
        cells.append(f"{method['ok']}/{method['failed']}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def ordering_lines(table: Dict[str, Any], first: str = "sdfcar", second: str = "neca") -> List[str]:
    """Per paper metric: which of two modes is better on average and case by case."""
    methods = {m["mode"]: m for m in table["methods"]}
    if first not in methods or second not in methods or not methods[first]["ok"] or not methods[second]["ok"]:
        return [f"Ordering {first} vs {second}: not available (both modes need finished cases)."]
    a, b = methods[first], methods[second]
    parts, agree, compared = [], 0, 0
    for key, header, scale, decimals, higher in TABLE_METRICS:
        if key not in PAPER_METRICS:
            continue
        ma, mb = a["stats"][key][0], b["stats"][key][0]
        if not (math.isfinite(ma) and math.isfinite(mb)):
            parts.append(f"{header}: n/a")
            continue
        compared += 1
        better = (ma > mb) if higher else (ma < mb)
        tie = round(ma, decimals) == round(mb, decimals)
        agree += int(better and not tie)
        paired = [(_float(a["per_case"][c].get(key)), _float(b["per_case"][c].get(key)))
                  for c in a["per_case"] if c in b["per_case"]]
        paired = [(x, y) for x, y in paired if math.isfinite(x) and math.isfinite(y)]
        wins = sum(1 for x, y in paired if (x > y if higher else x < y))
        verdict = "tie" if tie else (f"{first} better" if better else f"{second} better")
        parts.append(f"{header}: {verdict} ({ma:.{decimals}f} vs {mb:.{decimals}f}; {first} better in {wins}/{len(paired)} cases)")
    lines = [f"Ordering {first} vs {second} per metric (the paper has {first} better on all six):"]
    lines += [f"- {p}" for p in parts]
    lines.append(f"- The paper's ordering reproduces on {agree} of {compared} metrics" +
                 (" — it reproduces." if compared and agree == compared else " — it does not fully reproduce."))
    return lines


def machine_info() -> Dict[str, Any]:
    """CPU model, cores, RAM and GPU of this process's machine."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as stream:
            for line in stream:
                if line.lower().startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (AttributeError, ValueError, OSError):
        ram = math.nan
    gpus: List[str] = []
    try:
        import torch

        if torch.cuda.is_available():
            gpus = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
    except Exception:
        pass
    return {"host": platform.node(), "system": f"{platform.system()} {platform.release()}", "cpu": cpu,
            "cores": os.cpu_count(), "ram_gib": round(ram, 1) if math.isfinite(ram) else None, "gpus": gpus}


def all_versions() -> Dict[str, str]:
    from .optimiser import versions

    out = dict(versions())
    for name in ("dask", "distributed", "matplotlib"):
        try:
            out[name] = __import__(name).__version__
        except Exception:
            out[name] = "not installed"
    return out


def write_summary(out: Path, config: BenchmarkConfig, rows: Sequence[Dict[str, str]], record: Dict[str, Any]) -> Path:
    tables = summary_tables(rows, config.modes)
    machine = record.get("machine", {})
    versions = record.get("versions", {})
    lines = [
        f"# SDFCAR benchmark — suite `{config.suite}`, protocol `{config.protocol}`, preset `{config.preset}`",
        "",
        "Mean ± sample standard deviation over the finished cases (failed runs excluded and listed below); "
        "best value per column in **bold**. clDice is Shit et al.'s centreline Dice, skeleton-Dice the Dice of the "
        "two skeletons (what the public NeCA/SDF-CAR code reports as clDice); see `SDFCARLib/metrics.py`.",
        "",
    ]
    if not tables:
        lines += ["No finished rows yet.", ""]
    for table in tables:
        lines += [f"## {table['title']}", "", f"{len(table['cases'])} cases.", "", _table_markdown(table), ""]
        lines += ordering_lines(table) + [""]
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        lines += ["## Failed runs", ""]
        lines += [f"- `{r['case']}` × `{r['mode']}`: {r['error']} (traceback: `{r.get('traceback_file', '')}`)" for r in failed]
        lines.append("")
    seeds = record.get("seeds", [])
    gpu = ", ".join(machine.get("gpus") or []) or "none"
    identity = config.identity()
    lines += [
        "## Reproduce", "", "```", config.command_line(), "```", "",
        f"- configuration `{config.config_id()}`: " + json.dumps({k: v for k, v in identity.items() if k != "settings"}, sort_keys=True),
        "- optimiser settings (besides mode and seed): " + ", ".join(f"{k}={v}" for k, v in identity["settings"].items()),
        f"- seeds (per case, tree and optimiser): {', '.join(map(str, seeds))}",
        "- versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()),
        f"- machine (this process): {machine.get('cpu')}, {machine.get('cores')} cores, {machine.get('ram_gib')} GiB RAM, GPU: {gpu}",
        f"- cluster: {record.get('cluster', {}).get('description', 'n/a')}",
        "- devices that ran the reconstructions: " + (", ".join(sorted({r.get('device', '') for r in rows if r.get('device')})) or "n/a"),
        f"- date: {record.get('finished') or record.get('started')}",
        "",
    ]
    path = out / "summary.md"
    write_text_atomically(path, "\n".join(lines))
    return path


def write_box_plots(out: Path, rows: Sequence[Dict[str, str]], modes: Sequence[str]) -> List[Path]:
    """One PNG per (suite tree, metric): a box per method over the finished cases."""
    # The Agg canvas directly, not pyplot: no global backend switch in the caller's process (Slicer).
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    folder = out / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for table in summary_tables(rows, modes):
        group = _safe_name(table["tree"] if table["suite"].split(":")[0] != "721a" else "721a")
        for key, header, scale, _, _ in TABLE_METRICS:
            data, labels = [], []
            for method in table["methods"]:
                values = [_float(r.get(key)) * scale for r in method["per_case"].values()]
                values = [v for v in values if math.isfinite(v)]
                if values:
                    data.append(values)
                    labels.append(method["mode"])
            if not data:
                continue
            figure = Figure(figsize=(1.2 + 1.1 * len(data), 3.2))
            FigureCanvasAgg(figure)
            axes = figure.add_subplot()
            axes.boxplot(data)
            axes.set_xticks(range(1, len(labels) + 1))
            axes.set_xticklabels(labels, rotation=20)
            axes.set_ylabel(header)
            axes.set_title(f"{table['title']}: {header}", fontsize=9)
            figure.tight_layout()
            path = folder / f"box_{group}_{key}.png"
            figure.savefig(path, dpi=100)
            written.append(path)
    return written


def save_overlay_figure(path: Path, prediction: np.ndarray, label: np.ndarray, min_panel_px: int = 256) -> Path:
    """The paper's overlay (green overlap, red predicted only, blue missed) as MIPs along the three
    axes, enlarged by whole pixels so that a 128³ case is readable."""
    import imageio.v3 as iio

    from .figures import overlay_mip

    panels = [overlay_mip(prediction, label, axis) for axis in (1, 0, 2)]
    factor = max(1, int(math.ceil(min_panel_px / max(max(p.shape[:2]) for p in panels))))
    panels = [np.repeat(np.repeat(p, factor, axis=0), factor, axis=1) for p in panels]
    height = max(p.shape[0] for p in panels)
    padded = [np.pad(p, ((0, height - p.shape[0]), (0, 6), (0, 0)), constant_values=255) for p in panels]
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(str(path), np.concatenate(padded, axis=1))
    return path


# --- files ----------------------------------------------------------------------------------------
def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(text)).strip("_") or "case"


def _json_safe(value: Any) -> Any:
    return json_compatible(json.loads(json.dumps(value, default=str)))


def _update_run_record(out: Path, record: Dict[str, Any]) -> None:
    """``run.json``: the invocations in order, this one last (replaced as it progresses)."""
    path = out / "run.json"
    runs: List[Dict[str, Any]] = []
    if path.exists():
        try:
            runs = json.loads(path.read_text(encoding="utf-8")).get("runs", [])
        except (ValueError, AttributeError):
            # Keep the unreadable file for the user instead of overwriting it.
            os.replace(path, path.with_name(f"run.json.unreadable-{int(time.time())}"))
            runs = []
    runs = [r for r in runs if r.get("run_id") != record["run_id"]] + [record]
    write_text_atomically(path, json.dumps(_json_safe({"runs": runs}), indent=2, allow_nan=False) + "\n")


# --- the run --------------------------------------------------------------------------------------
@dataclass
class BenchmarkOutcome:
    out: Path
    rows_written: int
    failed: int
    skipped: int
    summary: Path
    figures: List[Path]


def check_config(config: BenchmarkConfig) -> List[CaseSpec]:
    """Validate everything before any work (bad input changes nothing on disk); the cases."""
    from .optimiser import MODES, make_settings

    if not config.modes:
        raise BenchmarkError(f"--modes is empty; choose from {', '.join(MODES)}")
    unknown = [m for m in config.modes if m not in MODES and m != HULL]
    if unknown:
        raise BenchmarkError(f"unknown mode(s) {', '.join(unknown)} in --modes; choose from {', '.join(MODES)} "
                             "(the visual hull baseline is always included)")
    if len(set(config.modes)) != len(config.modes):
        raise BenchmarkError(f"--modes lists a mode twice: {','.join(config.modes)}")
    if config.protocol not in PROTOCOLS:
        raise BenchmarkError(f"unknown protocol {config.protocol!r}; choose one of {', '.join(PROTOCOLS)}")
    if config.steps is not None and config.steps < 1:
        raise BenchmarkError(f"--steps must be at least 1, got {config.steps}")
    if config.workers is not None and config.workers < 1:
        raise BenchmarkError(f"--workers must be at least 1, got {config.workers}")
    if config.threads_per_worker < 1:
        raise BenchmarkError(f"--threads-per-worker must be at least 1, got {config.threads_per_worker}")
    if config.overlays < 0:
        raise BenchmarkError(f"--overlays must be 0 or more, got {config.overlays}")
    for mode in config.modes:
        if mode != HULL:
            try:
                make_settings(config.preset, mode=mode, steps=config.steps, **config.overrides)
            except (ValueError, TypeError) as exc:
                raise BenchmarkError(f"the optimiser settings are invalid: {exc}") from None
    kind, _ = parse_suite(config.suite)
    try:
        protocol_geometry(config.protocol, kind, config.grid)
    except ValueError as exc:
        raise BenchmarkError(f"the grid/detector overrides give an invalid geometry: {exc}") from None
    for extra in ("matplotlib", "distributed"):
        try:
            __import__(extra)
        except ImportError:
            raise BenchmarkError(f"the benchmark needs {extra}: pip install 'SDFCARLib[bench]' "
                                 "(dask[distributed] and matplotlib)") from None
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise BenchmarkError(f"--out {out} is a file; give a folder")
    return build_cases(config)


def _start_client(config: BenchmarkConfig, processes: bool):
    """A Dask client on ``--scheduler`` or on a new LocalCluster; (client, cluster or None, description)."""
    import logging

    from distributed import Client, LocalCluster

    if config.scheduler:
        try:
            client = Client(config.scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise BenchmarkError(f"cannot reach the Dask scheduler at {config.scheduler} ({exc}); start it "
                                 "(dask scheduler / dask worker) or leave out --scheduler for a local cluster") from None
        try:
            client.wait_for_workers(1, timeout=60)
        except TimeoutError:
            client.close()
            raise BenchmarkError(f"the Dask scheduler at {config.scheduler} has no worker after 60 s; start workers "
                                 f"(dask worker {config.scheduler}) and run the command again") from None
        slots = client.nthreads()
        description = f"scheduler {config.scheduler}: {len(slots)} worker(s), {sum(slots.values())} task slots"
        return client, None, description
    cores = os.cpu_count() or 1
    workers = config.workers or max(1, cores // config.threads_per_worker)
    # One task slot per worker; the worker's cores go to torch inside the task (threads_per_worker).
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=":0",
                           silence_logs=logging.ERROR)
    client = Client(cluster)
    description = (f"LocalCluster: {workers} {'process' if processes else 'thread'} worker(s), one case at a time each, "
                   f"{config.threads_per_worker} torch thread(s) per case")
    return client, cluster, description


def run_benchmark(config: BenchmarkConfig, processes: bool = True, argv: Optional[Sequence[str]] = None,
                  log: Callable[[str], None] = lambda text: print(text, file=sys.stderr)) -> BenchmarkOutcome:
    """Run (or resume) a benchmark and write results.csv, summary.md, run.json and figures in ``config.out``.

    ``processes`` False runs the LocalCluster's workers as threads of this process (tests).
    """
    cases = check_config(config)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    results = ResultsFile(out / "results.csv")
    config_id = config.config_id()
    all_modes = [HULL] + [m for m in config.modes if m != HULL]
    case_names = {c.name for c in cases}

    done = latest_rows(r for r in results.rows() if r.get("config") == config_id)
    todo: List[Tuple[CaseSpec, List[str]]] = []
    skipped = 0
    for spec in cases:
        modes = []
        for mode in all_modes:
            previous = done.get((spec.suite, spec.name, mode, config_id))
            if previous is not None and (previous["status"] == "ok" or not config.retry_failed):
                skipped += 1
            else:
                modes.append(mode)
        if modes:
            todo.append((spec, modes))

    run_id = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
    record: Dict[str, Any] = {
        "run_id": run_id, "command": config.command_line(), "argv": list(argv) if argv is not None else None,
        "config_id": config_id, "configuration": config.identity(), "suite": config.suite,
        "modes": list(config.modes), "cases": [c.name for c in cases], "seeds": [c.seed for c in cases],
        "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "versions": all_versions(), "machine": machine_info(),
        "cluster": {"description": "none (nothing to run)"}, "skipped_rows": skipped,
    }
    _update_run_record(out, record)
    n_tasks = sum(len(m) for _, m in todo)
    written = failed = 0
    overlay_figures: List[Path] = []
    if n_tasks:
        log(f"benchmark: {len(todo)} case(s), {n_tasks} run(s) to do ({skipped} already in {results.path.name}) → {out}")
        written, failed, overlay_figures = _execute(config, todo, results, record, processes, log)
    else:
        log(f"benchmark: all {skipped} run(s) already in {results.path} — nothing to run")

    rows = [r for key, r in latest_rows(results.rows()).items()
            if key[3] == config_id and key[1] in case_names and key[2] in all_modes]
    order = {c.name: c.index for c in cases}
    rows.sort(key=lambda r: (order[r["case"]], all_modes.index(r["mode"])))
    record.update(finished=datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                  rows_written=written, rows_failed=failed)
    _update_run_record(out, record)
    summary = write_summary(out, config, rows, record)
    figures = write_box_plots(out, rows, all_modes) + overlay_figures
    return BenchmarkOutcome(out, written, failed, skipped, summary, figures)


def _execute(config: BenchmarkConfig, todo: List[Tuple[CaseSpec, List[str]]], results: ResultsFile,
             record: Dict[str, Any], processes: bool, log: Callable[[str], None]) -> Tuple[int, int, List[Path]]:
    from distributed import as_completed

    client, cluster, description = _start_client(config, processes)
    record["cluster"] = {"description": description, "scheduler": config.scheduler,
                         "workers": _worker_machines(client)}
    _update_run_record(config.out, record)
    task = task_options(config)
    errors_dir = Path(config.out) / "errors"
    figures_dir = Path(config.out) / "figures"
    token = record["run_id"]
    futures = {}
    written = failed = 0
    overlays: List[Path] = []
    bar = None
    try:
        for spec, modes in todo:
            prepared = client.submit(prepare_task, spec, config.protocol, config.grid, key=f"sdfcar-prepare-{token}-{spec.index}",
                                     priority=-spec.index)
            for mode in modes:
                task_mode = dict(task, overlay=spec.index < config.overlays)
                future = client.submit(run_task, prepared, spec, mode, task_mode, key=f"sdfcar-run-{token}-{spec.index}-{mode}",
                                       priority=-spec.index)
                futures[future] = (spec, mode)
            del prepared  # held by its dependents, released with them
        from tqdm import tqdm

        bar = tqdm(total=len(futures), desc="benchmark", unit="run", disable=not config.progress, file=sys.stderr,
                   dynamic_ncols=True)
        for future in as_completed(list(futures)):
            spec, mode = futures.pop(future)
            if future.status == "finished":
                outcome = future.result()
            else:  # the task itself died (worker lost, unpicklable result…)
                exc = future.exception()
                tb = "".join(traceback.format_exception(type(exc), exc, future.traceback()))
                row = _base_row(spec, mode, task)
                row.update(status="failed", error=f"task failed: {_one_line(exc)}")
                outcome = {"row": row, "traceback": tb}
            future.release()
            row = outcome["row"]
            row["finished_at"] = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
            if row["status"] != "ok":
                failed += 1
                path = errors_dir / f"{_safe_name(spec.name)}__{_safe_name(mode)}.txt"
                write_text_atomically(path, f"case {spec.name}, mode {mode}\n{row.get('error', '')}\n\n{outcome.get('traceback', '')}")
                row["traceback_file"] = str(path.relative_to(config.out))
                bar.write(f"failed: {spec.name} × {mode}: {row.get('error', '')}", file=sys.stderr)
            results.append(row)
            written += 1
            if "overlay" in outcome:
                path = figures_dir / f"overlay_{_safe_name(spec.name)}_{_safe_name(mode)}.png"
                save_overlay_figure(path, _unpack(outcome["overlay"][0]), _unpack(outcome["overlay"][1]))
                overlays.append(path)
            bar.update(1)
    finally:
        if bar is not None:
            bar.close()
        for future in futures:
            future.cancel()
        client.close()
        if cluster is not None:
            cluster.close()
    return written, failed, overlays


def task_options(config: BenchmarkConfig) -> Dict[str, Any]:
    """What every ``run_task`` of a run shares (small, picklable)."""
    from .optimiser import make_settings

    modes = [m for m in config.modes if m != HULL]
    steps = make_settings(config.preset, mode=modes[0], steps=config.steps, **config.overrides).optimisation.steps if modes else ""
    return {"protocol": config.protocol, "preset": config.preset, "steps": config.steps, "steps_effective": steps,
            "overrides": dict(config.overrides),
            "overrides_text": json.dumps(config.overrides, sort_keys=True) if config.overrides else "",
            "config": config.config_id(), "torch_threads": config.threads_per_worker, "overlay": False}


def _worker_machines(client) -> Dict[str, Any]:
    try:
        return client.run(machine_info)
    except Exception as exc:  # informative only
        return {"error": _one_line(exc)}


# --- command line -------------------------------------------------------------------------------
def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def add_benchmark_command(commands, common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add ``benchmark`` to the CLI's sub-parsers (``commands``), with ``common``'s --verbose."""
    p = commands.add_parser(
        "benchmark", parents=[common], help="measure the modes on many simulated cases (the paper's tables)",
        description="For every case of a suite: simulate the protocol's two views, compute the visual-hull "
                    "baseline, reconstruct with each mode and score every metric. Writes results.csv (appended, "
                    "resumable), summary.md (tables like the paper's), run.json and figures/ in --out. Cases run in "
                    "parallel on a local Dask cluster or on --scheduler.")
    p.add_argument("--suite", required=True, help=SUITE_HELP)
    p.add_argument("--modes", default=",".join(DEFAULT_MODES),
                   help=f"comma-separated modes (default {','.join(DEFAULT_MODES)}); the visual hull is always added")
    p.add_argument("--preset", default="fast", help="optimiser preset (fast, paper, …)")
    p.add_argument("--protocol", default="paper", choices=sorted(PROTOCOLS),
                   help="paper: line integrals, the NeCA views; clinical-…: binary masks of a clinical pair (default paper)")
    p.add_argument("--cases", type=_positive_int, default=None,
                   help="number of cases (default: 10 procedural, 1 for 721a, every file of a folder ×2 trees)")
    p.add_argument("--out", required=True, help="results folder (created; rows already there are kept and skipped)")
    p.add_argument("--seed", type=int, default=0, help="first case seed (case i uses seed+i for its tree and optimiser)")
    p.add_argument("--steps", type=_positive_int, default=None, help="optimisation steps (default: the preset's)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="optimiser override, repeatable (e.g. --set learning_rate=1e-3 --set device=cuda)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="address of an existing Dask scheduler (e.g. tcp://host:8786); default: a local cluster")
    p.add_argument("--workers", type=_positive_int, default=None, help="local cluster workers (default: cores / threads per worker)")
    p.add_argument("--threads-per-worker", type=_positive_int, default=1, help="torch threads per case (default 1)")
    p.add_argument("--centreline", "--centerline", dest="centreline", default=None,
                   help="721a suite: the centreline file (default ../shared/data/721A_Centreline.vtk beside the repository)")
    p.add_argument("--volume-shape", type=_positive_int, nargs=3, default=None, metavar=("NI", "NJ", "NK"),
                   help="override the protocol's grid shape (default 128 128 128)")
    p.add_argument("--spacing-mm", type=_positive_float, default=None, help="override the grid spacing (default 0.8; folder 1)")
    p.add_argument("--detector-shape", type=_positive_int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                   help="override the detector shape (default 512 512)")
    p.add_argument("--detector-spacing-mm", type=_positive_float, default=None, help="override the detector pixel spacing (default 0.278)")
    p.add_argument("--overlays", type=int, default=3, help="overlay figures for the first N cases (default 3)")
    p.add_argument("--retry-failed", action="store_true", help="run failed rows again (default: keep them, skip)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_benchmark)
    return p


def config_from_args(args: argparse.Namespace) -> BenchmarkConfig:
    modes = tuple(m.strip() for m in str(args.modes).split(",") if m.strip())
    grid = GridOptions(
        volume_shape=tuple(args.volume_shape) if args.volume_shape else None, spacing_mm=args.spacing_mm,
        detector_shape=tuple(args.detector_shape) if args.detector_shape else None,
        detector_spacing_mm=args.detector_spacing_mm)
    return BenchmarkConfig(
        suite=args.suite, out=Path(args.out), modes=modes, preset=args.preset, protocol=args.protocol, cases=args.cases,
        seed=args.seed, steps=args.steps, overrides=parse_overrides(args.overrides), grid=grid,
        centreline=Path(args.centreline) if args.centreline else None, scheduler=args.scheduler, workers=args.workers,
        threads_per_worker=args.threads_per_worker, overlays=args.overlays, retry_failed=args.retry_failed,
        progress=not args.no_progress)


def cmd_benchmark(args: argparse.Namespace) -> int:
    """The ``benchmark`` command: 0 done (failed runs are recorded, not fatal), 2 bad input, 130 interrupted."""
    try:
        config = config_from_args(args)
        outcome = run_benchmark(config, argv=sys.argv)
    except BenchmarkError as exc:
        if getattr(args, "verbose", False):
            traceback.print_exc()
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"interrupted: finished runs are kept in {Path(args.out) / 'results.csv'}; run the same command to resume",
              file=sys.stderr)
        return 130
    print(outcome.summary.read_text(encoding="utf-8"))
    print(f"{outcome.rows_written} run(s) written, {outcome.skipped} skipped (already done), {outcome.failed} failed; "
          f"results in {outcome.out}", file=sys.stderr)
    if outcome.failed:
        print(f"warning: {outcome.failed} run(s) failed; their errors are in {outcome.out / 'errors'}", file=sys.stderr)
    return 0
