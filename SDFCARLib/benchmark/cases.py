"""Cases: suites and their case specs, the protocol's geometry, the DeepCA/NeCA preprocessing of
label volumes (folder suites), and a prepared case (ground truth and simulated views).

Everything here is per case and runs in a Dask worker; the run's configuration is in ``config.py``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..geometry import Geometry, VolumeGrid, standard_geometry
from ..io import read_label
from ..settings import (MASK_THRESHOLD_MM, PAPER_DETECTOR_SHAPE, PAPER_DETECTOR_SPACING_MM, PAPER_SPACING_MM,
                        PAPER_VOLUME_SHAPE, PROTOCOLS, REALISTIC_PROTOCOLS)
from .errors import BenchmarkError


PathLike = Union[str, Path]

PROCEDURAL_SUITES = ("rca", "lad")
SUITE_HELP = "rca, lad (procedural trees), 721a (the 721A centreline) or folder:PATH (label volumes)"
FOLDER_SPACING_MM = 1.0  # DeepCA/NeCA resample ImageCAS labels to 1 mm
VOLUME_SUFFIXES = (".nii.gz", ".seg.nrrd", ".nrrd", ".nhdr", ".nii")


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
    return Path(__file__).resolve().parents[2].parent / "shared" / "data" / "721A_Centreline.vtk"


def label_volume_files(folder: Path) -> List[Path]:
    """The label volumes of a folder suite, sorted by name."""
    if not folder.is_dir():
        raise BenchmarkError(f"--suite folder:{folder}: no such folder; give the folder holding the label volumes")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.name.lower().endswith(VOLUME_SUFFIXES))
    if not files:
        raise BenchmarkError(f"--suite folder:{folder}: the folder holds no label volume "
                             f"({', '.join(VOLUME_SUFFIXES)}); put the labels (e.g. ImageCAS *.label.nii.gz) there")
    return files


def volume_stem(path: Path) -> str:
    """The file name without its volume suffix (``.nii.gz`` counts as one): the case name's stem."""
    name = path.name
    for suffix in VOLUME_SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return path.stem


# --- geometry ---------------------------------------------------------------------------------------
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


# --- folder suites: label volumes -------------------------------------------------------------------
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
    from ..metrics import component_labels  # scipy: kept out of the CLI's start

    components, sizes = component_labels(label)
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
    label, grid = read_label(path, what="label volume")
    return preprocess_label_volume(label, grid, spacing_mm, shape, name=str(path))


# --- a prepared case ----------------------------------------------------------------------------------
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
    frames: Optional[List[np.ndarray]] = None  # the simulated angiograms of the realistic protocols
    # their Pixel Intensity Relationship per view ("DISP" on the display protocols); None: linear counts
    frame_intensity: Optional[List[str]] = None


def prepare_case(spec: CaseSpec, protocol: str, grid: Optional[GridOptions] = None,
                 realistic_overrides: Optional[Dict[str, Any]] = None) -> PreparedCase:
    """Build the case's label on its geometry and simulate its views (``realistic_overrides``: fields of
    ``realistic.RealisticOptions`` over the realistic protocol's own)."""
    from ..phantoms import lad_tree, load_centreline_vtk, rca_tree, simulate_views, voxelize

    t0 = time.perf_counter()
    kind, _ = parse_suite(spec.suite)
    geometry = protocol_geometry(protocol, kind, grid)
    info: Dict[str, Any] = {}
    if kind in PROCEDURAL_SUITES:
        tree = (rca_tree if kind == "rca" else lad_tree)(spec.seed)
        label = voxelize(tree, geometry.volume)
    elif kind == "721a":
        tree = load_centreline_vtk(spec.source, name="721A").centered()
        label = voxelize(tree, geometry.volume)
    else:
        trees = preprocess_label_file(spec.source, geometry.volume.spacing_mm[0], geometry.volume.shape)
        label, _, info = trees[spec.component]
    if not label.any():
        raise BenchmarkError(f"case {spec.name}: the vessel tree does not reach the volume grid")
    if protocol in REALISTIC_PROTOCOLS:
        # The masks a user would have: segmented from simulated angiograms of a moving heart.
        from ..realistic import RealisticOptions, realistic_input

        options = RealisticOptions(**{**REALISTIC_PROTOCOLS[protocol], **(realistic_overrides or {})})
        realistic = realistic_input(label, geometry, spec.seed, options)
        line_integrals, masks, frames = [], realistic.masks, realistic.frames
        frame_intensity = realistic.frame_intensity
        info.update(realistic=realistic.info)
    else:
        line_integrals, masks = simulate_views(label, geometry.volume, geometry.views, MASK_THRESHOLD_MM)
        frames = frame_intensity = None
    for n, (mask, view) in enumerate(zip(masks, geometry.views), start=1):
        if not mask.any() or mask.all():
            raise BenchmarkError(f"case {spec.name}: view {n} ({view.describe()}) sees {'no' if not mask.any() else 'only'} "
                                 "vessel; check the grid and detector overrides")
    target_kind = PROTOCOLS[protocol][1]
    targets = line_integrals if target_kind == "line_integral" else [m.astype(np.float32) for m in masks]
    info["label_voxels"] = int(label.sum())
    return PreparedCase(geometry, label, masks, targets, target_kind, info, time.perf_counter() - t0, frames,
                        frame_intensity)
