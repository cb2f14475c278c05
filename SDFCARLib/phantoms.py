"""Coronary phantoms: centreline trees with radii, their voxelisation, and simulated C-arm views.

Procedural trees
    ``rca_tree(seed)`` and ``lad_tree(seed)`` build right- and left-coronary-like trees on a
    heart-sized frame around the isocenter (LPS mm): a main vessel with anatomically placed
    branches (RCA: conus, RV, acute marginal, PDA, PLV; left tree: LM, LAD with diagonals and a
    septal, LCx with an obtuse marginal), radii tapering from about 2 mm proximally to about
    0.5–0.7 mm distally, and smooth random tortuosity. The seed varies the control points, the
    tortuosity, a small rotation and the scale; the same seed gives the same tree.

Voxelisation
    A voxel is vessel when its centre lies inside the union of the tubes swept along each
    centreline segment, with the radius interpolated linearly along the segment.

Simulation
    A view's line integral (mm) is the projection of the binary label with ``projector.py``; its
    binary mask is ``line integral > threshold`` (default 0.2 mm, below which a vessel's shadow is
    too faint to segment).

Beer–Lambert frames
    ``beer_lambert_counts`` turns line integrals into detector counts ``i0 · exp(−μ·L)`` (contrast-
    filled vessels dark), ``line_integrals_from_counts`` inverts it. The one X-ray image model of
    the package: the self-test, the DICOM fixtures and the simulated angiograms all use it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import CArmView, Geometry, VolumeGrid
from .projector import project_volume
from .settings import MASK_THRESHOLD_MM

PathLike = Union[str, Path]


@dataclass
class Branch:
    points: np.ndarray  # (N, 3) LPS mm
    radii: np.ndarray  # (N,) mm
    name: str = ""


@dataclass
class CentrelineTree:
    branches: List[Branch]
    name: str = "tree"

    def all_points(self) -> np.ndarray:
        return np.concatenate([b.points for b in self.branches])

    def bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        """Bounding box of the tubes (centrelines widened by their radii)."""
        lo = np.min([np.min(b.points - b.radii[:, None], axis=0) for b in self.branches], axis=0)
        hi = np.max([np.max(b.points + b.radii[:, None], axis=0) for b in self.branches], axis=0)
        return lo, hi

    def translated(self, offset: Sequence[float]) -> "CentrelineTree":
        off = np.asarray(offset, float)
        return CentrelineTree([Branch(b.points + off, b.radii.copy(), b.name) for b in self.branches], self.name)

    def centered(self) -> "CentrelineTree":
        """The tree moved so that its bounding box is centred on the isocenter."""
        lo, hi = self.bounds()
        return self.translated(-(lo + hi) / 2)

    def total_length_mm(self) -> float:
        return float(sum(np.linalg.norm(np.diff(b.points, axis=0), axis=1).sum() for b in self.branches))

    def length_outside_mm(self, low_mm: Sequence[float], high_mm: Sequence[float]) -> float:
        """Centreline length outside the box [low_mm, high_mm] (LPS), each segment clipped to the box exactly."""
        lo, hi = np.asarray(low_mm, float), np.asarray(high_mm, float)
        outside = 0.0
        for b in self.branches:
            start, step = b.points[:-1], np.diff(b.points, axis=0)
            with np.errstate(divide="ignore", invalid="ignore"):  # a segment parallel to a face: that slab is all or nothing
                t_lo, t_hi = (lo - start) / step, (hi - start) / step
            parallel = step == 0
            inside_slab = (start >= lo) & (start <= hi)
            t_enter = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t_lo, t_hi))
            t_leave = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t_lo, t_hi))
            inside_share = np.clip(np.min(t_leave, axis=1), 0, 1) - np.clip(np.max(t_enter, axis=1), 0, 1)
            outside += float((np.linalg.norm(step, axis=1) * (1 - np.maximum(inside_share, 0))).sum())
        return outside


# --- voxelisation --------------------------------------------------------------------------------
def voxelize(tree: CentrelineTree, grid: VolumeGrid) -> np.ndarray:
    """Boolean label ``[i, j, k]`` of the tree's tubes on ``grid`` (voxel-centre test)."""
    label = np.zeros(grid.shape, dtype=bool)
    spacing = np.asarray(grid.spacing_mm, float)
    shape = np.asarray(grid.shape)
    for branch in tree.branches:
        pts, rad = np.asarray(branch.points, float), np.asarray(branch.radii, float)
        if len(pts) == 1:
            pts, rad = np.vstack([pts, pts]), np.concatenate([rad, rad])
        for p0, p1, r0, r1 in zip(pts[:-1], pts[1:], rad[:-1], rad[1:]):
            rmax = max(r0, r1)
            lo = np.floor(grid.world_to_index(np.minimum(p0, p1) - rmax)).astype(int)
            hi = np.ceil(grid.world_to_index(np.maximum(p0, p1) + rmax)).astype(int)
            lo, hi = np.clip(lo, 0, shape - 1), np.clip(hi, 0, shape - 1)
            if np.any(hi < lo):
                continue
            ii, jj, kk = np.meshgrid(*(np.arange(lo[a], hi[a] + 1) for a in range(3)), indexing="ij")
            x = grid.origin + np.stack([ii, jj, kk], axis=-1) * spacing
            seg = p1 - p0
            length2 = float(seg @ seg)
            t = np.zeros(ii.shape) if length2 == 0 else np.clip(((x - p0) @ seg) / length2, 0.0, 1.0)
            closest = p0 + t[..., None] * seg
            inside = np.linalg.norm(x - closest, axis=-1) <= r0 + t * (r1 - r0)
            label[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1] |= inside
    return label


# --- centreline files ------------------------------------------------------------------------------
RADIUS_ARRAY_NAMES = ("radii", "radius", "Radius", "MaximumInscribedSphereRadius", "RADIUS")
#: the range a coronary tree's median radius lies in (mm): a file's outside it is in other units
CORONARY_RADIUS_MM = (0.2, 5.0)


def load_centreline_vtk(path: PathLike, name: Optional[str] = None) -> CentrelineTree:
    """Read a centreline tree from VTK polydata (.vtk legacy or .vtp) with a point radius array."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"centreline file not found: {path}")
    try:
        import vtk  # noqa: F401  (Slicer ships vtk; headless installs get it with slicer-core)
        from vtk.util.numpy_support import vtk_to_numpy
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("reading VTK centrelines needs the 'vtk' package: pip install 'SDFCARLib[headless]'") from exc
    if path.suffix.lower() == ".vtp":
        reader = vtk.vtkXMLPolyDataReader()
    else:
        reader = vtk.vtkPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    if poly is None or poly.GetNumberOfPoints() == 0:
        raise ValueError(f"{path} holds no polydata points; expected a centreline polydata file")
    points = vtk_to_numpy(poly.GetPoints().GetData()).astype(float)
    header = reader.GetHeader() if hasattr(reader, "GetHeader") else ""
    if "SPACE=RAS" in str(header or "").upper():  # Slicer's marker (write_surface_vtk writes SPACE=LPS): SDFCAR is LPS
        points = points * np.array([-1.0, -1.0, 1.0])
    pd = poly.GetPointData()
    radius = None
    for array_name in RADIUS_ARRAY_NAMES:
        array = pd.GetArray(array_name)
        if array is not None:
            if array.GetNumberOfComponents() != 1:
                raise ValueError(f"{path}: its radius array {array_name!r} has {array.GetNumberOfComponents()} components "
                                 "per point; a radius is one number per point")
            radius = vtk_to_numpy(array).astype(float).reshape(-1)
            break
    if radius is None:
        names = [pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())]
        raise ValueError(f"{path} has no radius point array (looked for {', '.join(RADIUS_ARRAY_NAMES)}; found {names or 'none'})")
    bad = ~(np.isfinite(radius) & (radius > 0))
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} of its {radius.size} radii are not positive numbers (the first at "
                         f"point {int(np.flatnonzero(bad)[0])}: {float(radius[bad][0])!r}); give every centreline point its radius in mm")
    median = float(np.median(radius))
    if not CORONARY_RADIUS_MM[0] <= median <= CORONARY_RADIUS_MM[1]:
        raise ValueError(f"{path}: its median radius is {median:g}, outside the {CORONARY_RADIUS_MM[0]:g}–"
                         f"{CORONARY_RADIUS_MM[1]:g} mm of coronary arteries: are the radii (and points) in cm or µm? "
                         "SDFCAR reads centrelines in mm")
    branches = []
    lines = poly.GetLines()
    lines.InitTraversal()
    ids = vtk.vtkIdList()
    n = 0
    while lines.GetNextCell(ids):
        index = [ids.GetId(i) for i in range(ids.GetNumberOfIds())]
        branches.append(Branch(points[index], radius[index], f"branch{n}"))
        n += 1
    if not branches:
        raise ValueError(f"{path} has no polylines; a centreline needs its points connected by lines")
    return CentrelineTree(branches, name or path.stem)


# --- procedural trees --------------------------------------------------------------------------------
def _smooth_path(control: np.ndarray, step_mm: float = 0.5) -> np.ndarray:
    from scipy.interpolate import CubicSpline

    control = np.asarray(control, float)
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(control, axis=0), axis=1))])
    spline = CubicSpline(chord, control, bc_type="natural")
    s = np.arange(0.0, chord[-1], step_mm)
    return spline(np.append(s, chord[-1]))


def _add_tortuosity(path: np.ndarray, rng: np.random.Generator, amplitude_mm: float) -> np.ndarray:
    """Smooth random displacement orthogonal to the path, zero at its start (stays attached)."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True) + 1e-12
    # Parallel transport of one normal: the frame turns with the tangent and never flips, so the
    # displacement stays continuous.
    helper = np.array([0.0, 0.0, 1.0]) if abs(tangent[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n1 = np.empty_like(path)
    n1[0] = np.cross(tangent[0], helper)
    n1[0] /= np.linalg.norm(n1[0])
    for i in range(1, len(path)):
        n = n1[i - 1] - (n1[i - 1] @ tangent[i]) * tangent[i]
        n1[i] = n / np.linalg.norm(n)
    n2 = np.cross(tangent, n1)
    ramp = np.clip(s / 8.0, 0.0, 1.0)
    offset = np.zeros_like(path)
    for normal in (n1, n2):
        for _ in range(3):
            wavelength = rng.uniform(12.0, 35.0)
            phase = rng.uniform(0, 2 * np.pi)
            amp = amplitude_mm * rng.uniform(0.3, 1.0)
            offset += (amp * ramp * np.sin(2 * np.pi * s / wavelength + phase))[:, None] * normal
    return path + offset


def _taper(n: int, r_start: float, r_end: float) -> np.ndarray:
    # Geometric taper: vessels lose a similar fraction of calibre per unit length.
    return r_start * (r_end / r_start) ** np.linspace(0.0, 1.0, n)


def _rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    angles = np.radians(rng.uniform(-max_deg, max_deg, 3))
    cx, cy, cz = np.cos(angles)
    sx, sy, sz = np.sin(angles)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


# Branch templates: name, parent (or None), attachment fraction along the parent, control
# points (LPS mm, first point replaced by the attachment point for side branches), radii.
_Template = Tuple[str, Optional[str], float, List[Tuple[float, float, float]], Tuple[float, float]]

_RCA: List[_Template] = [
    ("RCA", None, 0.0, [(-8, -22, 30), (-22, -31, 24), (-36, -25, 12), (-42, -10, 0), (-40, 8, -10), (-30, 24, -18), (-14, 32, -22), (-2, 34, -24)], (2.0, 1.2)),
    ("conus", "RCA", 0.06, [(0, 0, 0), (-12, -36, 22), (-4, -39, 14)], (0.8, 0.5)),
    ("RV", "RCA", 0.28, [(0, 0, 0), (-28, -35, 3), (-18, -39, -8)], (0.9, 0.55)),
    ("AM", "RCA", 0.45, [(0, 0, 0), (-38, -17, -14), (-30, -21, -28)], (1.0, 0.6)),
    ("PDA", "RCA", 0.88, [(0, 0, 0), (0, 30, -32), (8, 24, -41)], (1.1, 0.6)),
    ("PLV", "RCA", 1.0, [(0, 0, 0), (10, 34, -22), (20, 30, -27)], (1.0, 0.6)),
]

_LAD: List[_Template] = [
    ("LM-LAD", None, 0.0, [(4, -20, 34), (10, -26, 30), (14, -34, 18), (16, -38, 4), (18, -38, -10), (20, -34, -24), (22, -26, -36), (22, -16, -44)], (2.1, 0.7)),
    ("LCx", "LM-LAD", 0.07, [(0, 0, 0), (22, -18, 30), (34, -4, 26), (40, 10, 18), (38, 22, 8)], (1.6, 0.8)),
    ("OM", "LCx", 0.6, [(0, 0, 0), (44, 6, 6), (44, -2, -8)], (1.0, 0.6)),
    ("D1", "LM-LAD", 0.28, [(0, 0, 0), (24, -33, 10), (32, -27, 0), (38, -21, -10)], (1.1, 0.6)),
    ("D2", "LM-LAD", 0.5, [(0, 0, 0), (26, -35, -10), (32, -29, -22)], (0.95, 0.55)),
    ("S1", "LM-LAD", 0.22, [(0, 0, 0), (8, -27, 12), (4, -21, 5)], (0.7, 0.5)),
]


def _procedural_tree(templates: List[_Template], name: str, seed: int, grid_half_extent_mm: float = 48.0) -> CentrelineTree:
    rng = np.random.default_rng(seed)
    rotation = _rotation(rng, 10.0)
    scale = rng.uniform(0.9, 1.08)
    tortuosity = rng.uniform(0.8, 2.0)
    built: Dict[str, Branch] = {}
    for branch_name, parent, fraction, control, (r0, r1) in templates:
        control = np.asarray(control, float) + rng.normal(0.0, 2.0, (len(control), 3))
        if parent is not None:
            parent_branch = built[parent]
            index = int(round(fraction * (len(parent_branch.points) - 1)))
            control[0] = parent_branch.points[index]
            r0 = min(r0, 0.85 * float(parent_branch.radii[index]))
            r1 = min(r1, r0)
        path = _smooth_path(control)
        path = _add_tortuosity(path, rng, tortuosity * (0.6 if parent else 1.0))
        built[branch_name] = Branch(path, _taper(len(path), r0, r1), branch_name)
    branches = []
    for b in built.values():
        branches.append(Branch((b.points @ rotation.T) * scale, b.radii, b.name))
    tree = CentrelineTree(branches, name).centered()
    lo, hi = tree.bounds()
    half = float(np.max(np.maximum(np.abs(lo), np.abs(hi))))
    if half > grid_half_extent_mm:
        tree = CentrelineTree([Branch(b.points * grid_half_extent_mm / half, b.radii, b.name) for b in tree.branches], name)
    return tree


def rca_tree(seed: int = 0) -> CentrelineTree:
    """Right-coronary-like procedural tree (see module docstring)."""
    return _procedural_tree(_RCA, f"RCA-{seed}", seed)


def lad_tree(seed: int = 0) -> CentrelineTree:
    """Left-coronary (LM/LAD/LCx)-like procedural tree (see module docstring)."""
    return _procedural_tree(_LAD, f"LAD-{seed}", seed)


# --- simulation -------------------------------------------------------------------------------------
@dataclass
class SimulatedCase:
    """A ground-truth label and its simulated views on a geometry."""

    geometry: Geometry
    label: np.ndarray  # bool [i, j, k] on geometry.volume
    line_integrals: List[np.ndarray]  # mm, one per view
    masks: List[np.ndarray]  # bool, one per view
    name: str = "case"
    meta: Dict[str, object] = field(default_factory=dict)


def simulate_views(
    label: np.ndarray,
    label_grid: VolumeGrid,
    views: Sequence[CArmView],
    mask_threshold_mm: float = MASK_THRESHOLD_MM,
    device: str = "cpu",
) -> Tuple[List[np.ndarray], List[np.ndarray]]:
    """Line-integral images (mm) and binary masks of a label volume for each view."""
    label = np.asarray(label)
    if label.shape != tuple(label_grid.shape):
        raise ValueError(f"label shape {label.shape} does not match its grid {tuple(label_grid.shape)}")
    if not np.any(label):
        raise ValueError("the label volume is empty: nothing to project")
    line_integrals = [project_volume((label > 0).astype(np.float32), view, label_grid, device=device) for view in views]
    masks = [li > mask_threshold_mm for li in line_integrals]
    return line_integrals, masks


def make_case(
    tree: CentrelineTree,
    geometry: Geometry,
    mask_threshold_mm: float = MASK_THRESHOLD_MM,
    name: Optional[str] = None,
) -> SimulatedCase:
    """Voxelise ``tree`` on the geometry's grid and simulate every view."""
    label = voxelize(tree, geometry.volume)
    if not label.any():
        raise ValueError(f"the tree {tree.name!r} does not intersect the volume grid")
    line_integrals, masks = simulate_views(label, geometry.volume, geometry.views, mask_threshold_mm)
    return SimulatedCase(geometry, label, line_integrals, masks, name or tree.name, {"mask_threshold_mm": mask_threshold_mm})


# --- Beer–Lambert frames ------------------------------------------------------------------------------
def beer_lambert_counts(
    line_integrals_mm: np.ndarray,
    mu_per_mm: float = 0.25,
    i0: Optional[float] = None,
    bits_stored: int = 12,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Detector counts ``round(i0 · exp(−μ·L) + noise)`` of line-integral image(s), as uint8/uint16.

    ``i0`` defaults to 90% of the largest stored value; contrast-filled vessels come out dark.
    """
    if bits_stored not in (8, 10, 12, 14, 16):
        raise ValueError(f"bits_stored must be 8, 10, 12, 14 or 16, got {bits_stored}")
    top = 2**bits_stored - 1
    i0 = 0.9 * top if i0 is None else float(i0)
    counts = i0 * np.exp(-float(mu_per_mm) * np.asarray(line_integrals_mm, dtype=np.float64))
    if noise_sigma > 0:
        counts = counts + np.random.default_rng(seed).normal(0.0, noise_sigma, counts.shape)
    return np.clip(np.rint(counts), 0, top).astype(np.uint8 if bits_stored == 8 else np.uint16)


def line_integrals_from_counts(counts: np.ndarray, i0: float, mu_per_mm: float = 0.25) -> np.ndarray:
    """Inverse of ``beer_lambert_counts``: −ln(I / i0) / μ (mm), clipped at 0."""
    intensity = np.maximum(np.asarray(counts, dtype=np.float64), 0.5)
    return np.maximum(-np.log(intensity / float(i0)) / float(mu_per_mm), 0.0)
