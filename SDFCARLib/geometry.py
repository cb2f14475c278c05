"""C-arm view geometry and the reconstruction grid.

Every geometric convention of SDFCAR is defined here, once.

World frame
    Patient LPS (x → patient's Left, y → Posterior, z → Superior), millimetres, isocenter at the
    origin. Slicer's RAS is converted to and from at the MRML boundary only (``mrml.py``).

C-arm view (primary angle α: LAO +, RAO −; secondary angle β: CRA +, CAU −)
    d = (sin α cos β, −cos α cos β, sin β)   unit vector isocenter → detector
    source          S = −SOD · d
    detector centre C = (SID − SOD) · d
    u = (cos α, sin α, 0)                     image columns (left → right)
    v = u × d                                  image rows (top → bottom)
    At AP (0°, 0°) the detector is anterior, the patient's left is on the image's right and the
    head at the top.

Object motion between acquisitions (optional, per view)
    Views are acquired seconds apart and table, patient and heart move in between. A view may
    carry the rigid motion of the object at its acquisition relative to the reference frame (the
    first view's): a reference point x sits at R·x + t when this view is acquired, R the rotation
    by the vector ``object_rotation_deg`` (axis × angle, degrees, LPS), t ``object_translation_mm``.
    The view's frame is then expressed in the reference frame — source R⁻¹(S − t), detector centre
    R⁻¹(C − t), directions R⁻¹d, R⁻¹u, R⁻¹v — so every projection and ray of SDFCAR sees the
    object where this view saw it. Zero motion (the default) is the nominal C-arm pose.

Pixel coordinates
    (row, col), continuous; the centre of pixel (0, 0) — the top-left pixel — is at (0.0, 0.0).
    The principal point (foot of the perpendicular from the source onto the detector) defaults
    to the image centre ((rows − 1) / 2, (cols − 1) / 2).

Volume grid
    An axis-aligned voxel grid in LPS. Arrays are indexed ``[i, j, k]`` with i along x (L),
    j along y (P), k along z (S). ``center_mm`` is the centre of the grid's bounding box; voxel
    centres sit at ``origin + index * spacing`` with ``origin`` the centre of voxel (0, 0, 0).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from .settings import PAPER_DETECTOR_SHAPE, PAPER_DETECTOR_SPACING_MM, PAPER_SPACING_MM, PAPER_VOLUME_SHAPE

PathLike = Union[str, Path]


class GeometryError(ValueError):
    """A geometry description is invalid; the message names the field and the fix."""


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise GeometryError(message)


def _finite_number(value: Any, where: str) -> float:
    _require(
        isinstance(value, (int, float)) and not isinstance(value, bool),
        f"{where} must be a number, got {value!r}",
    )
    _require(math.isfinite(value), f"{where} must be finite, got {value!r}")
    return float(value)


def _number_list(value: Any, length: int, where: str) -> Tuple[float, ...]:
    _require(
        isinstance(value, (list, tuple)) and len(value) == length,
        f"{where} must be a list of {length} numbers, got {value!r}",
    )
    return tuple(_finite_number(v, f"{where}[{i}]") for i, v in enumerate(value))


def _int_list(value: Any, length: int, where: str) -> Tuple[int, ...]:
    _require(
        isinstance(value, (list, tuple)) and len(value) == length,
        f"{where} must be a list of {length} positive integers, got {value!r}",
    )
    out = []
    for i, v in enumerate(value):
        _require(
            isinstance(v, int) and not isinstance(v, bool) and v > 0,
            f"{where}[{i}] must be a positive integer, got {v!r}",
        )
        out.append(int(v))
    return tuple(out)


def rotation_matrix(rotation_deg: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis × angle, degrees): Rodrigues' formula."""
    vector = np.radians(np.asarray(rotation_deg, dtype=np.float64))
    angle = float(np.linalg.norm(vector))
    if angle == 0.0:
        return np.eye(3)
    k = vector / angle
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross


@dataclass(frozen=True)
class CArmView:
    """One C-arm acquisition: angles, distances and detector (see module docstring)."""

    primary_deg: float
    secondary_deg: float
    sid_mm: float
    sod_mm: float
    pixel_spacing_mm: Tuple[float, float]  # (row, col)
    detector_shape: Tuple[int, int]  # (rows, cols)
    principal_point_px: Optional[Tuple[float, float]] = None  # (row, col)
    object_rotation_deg: Tuple[float, float, float] = (0.0, 0.0, 0.0)  # see "Object motion" above
    object_translation_mm: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    # where the values came from (GEOM.json's optional per-view "provenance"): kept for the reader and written back by
    # ``Geometry.save``, but no part of the geometry: not compared, not in ``to_dict`` or the digest
    provenance: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        self.validate("view")

    def validate(self, where: str = "view") -> None:
        a = _finite_number(self.primary_deg, f"{where}.primary_deg")
        b = _finite_number(self.secondary_deg, f"{where}.secondary_deg")
        _require(
            -180.0 <= a <= 180.0,
            f"{where}.primary_deg = {a} is out of range: the primary angle must lie in [-180, 180] "
            "degrees (LAO positive, RAO negative)",
        )
        _require(
            -90.0 <= b <= 90.0,
            f"{where}.secondary_deg = {b} is out of range: the secondary angle must lie in [-90, 90] "
            "degrees (CRA positive, CAU negative)",
        )
        sid = _finite_number(self.sid_mm, f"{where}.sid_mm")
        sod = _finite_number(self.sod_mm, f"{where}.sod_mm")
        _require(sid > 0, f"{where}.sid_mm (source to detector) must be positive, got {sid}")
        _require(sod > 0, f"{where}.sod_mm must be positive, got {sod}")
        _require(
            sod < sid,
            f"{where}.sod_mm = {sod} must be smaller than {where}.sid_mm = {sid} (the source-to-isocenter "
            "distance lies inside the source-to-detector distance); check that the two values are not swapped",
        )
        ps = _number_list(self.pixel_spacing_mm, 2, f"{where}.pixel_spacing_mm")
        _require(all(p > 0 for p in ps), f"{where}.pixel_spacing_mm must be positive, got {list(ps)}")
        _int_list(self.detector_shape, 2, f"{where}.detector_shape")
        if self.principal_point_px is not None:
            _number_list(self.principal_point_px, 2, f"{where}.principal_point_px")
        _number_list(self.object_rotation_deg, 3, f"{where}.object_rotation_deg")
        _number_list(self.object_translation_mm, 3, f"{where}.object_translation_mm")

    # --- frame -------------------------------------------------------------------------------
    @property
    def has_object_motion(self) -> bool:
        return any(float(v) != 0.0 for v in (*self.object_rotation_deg, *self.object_translation_mm))

    def _nominal_detector_direction(self) -> np.ndarray:
        a, b = math.radians(self.primary_deg), math.radians(self.secondary_deg)
        return np.array([math.sin(a) * math.cos(b), -math.cos(a) * math.cos(b), math.sin(b)])

    def _to_reference(self, vector: np.ndarray, point: bool) -> np.ndarray:
        """A nominal C-arm vector (or point) in the reference frame: R⁻¹v (or R⁻¹(p − t))."""
        if not self.has_object_motion:
            return vector
        if point:
            vector = vector - np.asarray(self.object_translation_mm, dtype=np.float64)
        return rotation_matrix(self.object_rotation_deg).T @ vector

    @property
    def detector_direction(self) -> np.ndarray:
        """Unit vector d from the isocenter towards the detector."""
        return self._to_reference(self._nominal_detector_direction(), False)

    @property
    def column_direction(self) -> np.ndarray:
        """Unit vector u along increasing image columns."""
        a = math.radians(self.primary_deg)
        return self._to_reference(np.array([math.cos(a), math.sin(a), 0.0]), False)

    @property
    def row_direction(self) -> np.ndarray:
        """Unit vector v = u × d along increasing image rows (downwards)."""
        return np.cross(self.column_direction, self.detector_direction)

    @property
    def source_position(self) -> np.ndarray:
        return self._to_reference(-self.sod_mm * self._nominal_detector_direction(), True)

    @property
    def detector_center(self) -> np.ndarray:
        return self._to_reference((self.sid_mm - self.sod_mm) * self._nominal_detector_direction(), True)

    def with_object_motion(self, rotation_deg: Sequence[float], translation_mm: Sequence[float]) -> "CArmView":
        """This view with the object's motion at its acquisition set (replacing any before)."""
        return dataclasses.replace(self, object_rotation_deg=tuple(float(v) for v in rotation_deg),
                                   object_translation_mm=tuple(float(v) for v in translation_mm))

    @property
    def principal_point(self) -> Tuple[float, float]:
        if self.principal_point_px is not None:
            return (float(self.principal_point_px[0]), float(self.principal_point_px[1]))
        rows, cols = self.detector_shape
        return ((rows - 1) / 2.0, (cols - 1) / 2.0)

    @property
    def magnification(self) -> float:
        """Magnification of an object at the isocenter."""
        return self.sid_mm / self.sod_mm

    @property
    def isocenter_pixel_spacing_mm(self) -> Tuple[float, float]:
        """Pixel spacing (row, col) referred to the isocenter plane."""
        m = self.magnification
        return (self.pixel_spacing_mm[0] / m, self.pixel_spacing_mm[1] / m)

    # --- mappings ----------------------------------------------------------------------------
    def project(self, points_mm: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project world points (..., 3) to pixel coordinates.

        Returns (row, col, depth_mm) where depth is the distance from the source along the
        central ray; points with depth <= 0 lie behind the source and get NaN pixel coordinates.
        """
        w = np.asarray(points_mm, dtype=np.float64) - self.source_position
        depth = w @ self.detector_direction
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(depth > 0, self.sid_mm / depth, np.nan)
        r0, c0 = self.principal_point
        row = r0 + scale * (w @ self.row_direction) / self.pixel_spacing_mm[0]
        col = c0 + scale * (w @ self.column_direction) / self.pixel_spacing_mm[1]
        return row, col, depth

    def pixel_to_world(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """World position (..., 3) of detector pixel coordinates (row, col)."""
        r0, c0 = self.principal_point
        row = np.asarray(row, dtype=np.float64)[..., None]
        col = np.asarray(col, dtype=np.float64)[..., None]
        return (
            self.detector_center
            + (row - r0) * self.pixel_spacing_mm[0] * self.row_direction
            + (col - c0) * self.pixel_spacing_mm[1] * self.column_direction
        )

    def rays(self, row: np.ndarray, col: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Rays from the source through pixel coordinates: (origin (3,), unit directions (..., 3))."""
        target = self.pixel_to_world(row, col)
        direction = target - self.source_position
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        return self.source_position.copy(), direction

    def pixel_grid(self) -> Tuple[np.ndarray, np.ndarray]:
        """Row and column coordinates of every pixel centre, each of detector_shape."""
        rows, cols = self.detector_shape
        return np.meshgrid(np.arange(rows, dtype=np.float64), np.arange(cols, dtype=np.float64), indexing="ij")

    # --- serialisation -----------------------------------------------------------------------
    def to_dict(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {
            "primary_deg": float(self.primary_deg),
            "secondary_deg": float(self.secondary_deg),
            "sid_mm": float(self.sid_mm),
            "sod_mm": float(self.sod_mm),
            "pixel_spacing_mm": [float(v) for v in self.pixel_spacing_mm],
            "detector_shape": [int(v) for v in self.detector_shape],
        }
        if self.principal_point_px is not None:
            out["principal_point_px"] = [float(v) for v in self.principal_point_px]
        if self.has_object_motion:  # absent when zero, so nominal geometries keep their digest
            out["object_rotation_deg"] = [float(v) for v in self.object_rotation_deg]
            out["object_translation_mm"] = [float(v) for v in self.object_translation_mm]
        return out

    @classmethod
    def from_dict(cls, data: Any, where: str = "view") -> "CArmView":
        _require(isinstance(data, dict), f"{where} must be an object, got {type(data).__name__}")
        required = ["primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_spacing_mm", "detector_shape"]
        missing = [k for k in required if k not in data]
        _require(not missing, f"{where} is missing required field(s): {', '.join(missing)}")
        known = set(required) | {"principal_point_px", "object_rotation_deg", "object_translation_mm", "provenance"}
        unknown = sorted(set(data) - known)
        _require(not unknown, f"{where} has unknown field(s): {', '.join(unknown)} (allowed: {', '.join(sorted(known))})")
        pp = data.get("principal_point_px")
        try:
            return cls(
                primary_deg=_finite_number(data["primary_deg"], f"{where}.primary_deg"),
                secondary_deg=_finite_number(data["secondary_deg"], f"{where}.secondary_deg"),
                sid_mm=_finite_number(data["sid_mm"], f"{where}.sid_mm"),
                sod_mm=_finite_number(data["sod_mm"], f"{where}.sod_mm"),
                pixel_spacing_mm=_number_list(data["pixel_spacing_mm"], 2, f"{where}.pixel_spacing_mm"),
                detector_shape=_int_list(data["detector_shape"], 2, f"{where}.detector_shape"),
                principal_point_px=None if pp is None else _number_list(pp, 2, f"{where}.principal_point_px"),
                object_rotation_deg=_number_list(data.get("object_rotation_deg", (0.0, 0.0, 0.0)), 3,
                                                 f"{where}.object_rotation_deg"),
                object_translation_mm=_number_list(data.get("object_translation_mm", (0.0, 0.0, 0.0)), 3,
                                                   f"{where}.object_translation_mm"),
                provenance=data.get("provenance"),
            )
        except GeometryError as exc:
            # Range checks in validate() speak of "view"; give the caller's field path instead.
            message = str(exc)
            if message.startswith(("view.", "view:")):
                message = where + message[len("view"):]
            raise GeometryError(message) from None

    def describe(self) -> str:
        a, b = self.primary_deg, self.secondary_deg
        lr = "LAO" if a > 0 else ("RAO" if a < 0 else "AP")
        cc = "CRA" if b > 0 else ("CAU" if b < 0 else "")
        text = f"{lr} {abs(a):g}" if lr != "AP" else "AP"
        if cc:
            text += f" {cc} {abs(b):g}"
        return text


@dataclass(frozen=True)
class VolumeGrid:
    """Axis-aligned voxel grid in LPS (see module docstring)."""

    shape: Tuple[int, int, int]
    spacing_mm: Tuple[float, float, float]
    center_mm: Tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        self.validate("volume")

    def validate(self, where: str = "volume") -> None:
        _int_list(self.shape, 3, f"{where}.shape")
        sp = _number_list(self.spacing_mm, 3, f"{where}.spacing_mm")
        _require(all(s > 0 for s in sp), f"{where}.spacing_mm must be positive, got {list(sp)}")
        _number_list(self.center_mm, 3, f"{where}.center_mm")

    @property
    def origin(self) -> np.ndarray:
        """Centre of voxel (0, 0, 0) in LPS mm."""
        return np.asarray(self.center_mm, float) - (np.asarray(self.shape, float) - 1) / 2.0 * np.asarray(self.spacing_mm, float)

    @property
    def extent_mm(self) -> np.ndarray:
        return np.asarray(self.shape, float) * np.asarray(self.spacing_mm, float)

    @property
    def num_voxels(self) -> int:
        return int(np.prod(self.shape))

    def bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        """(low, high) corners of the grid's bounding box (voxel faces), LPS mm."""
        half = np.asarray(self.spacing_mm, float) / 2
        return self.origin - half, self.origin + (np.asarray(self.shape) - 1) * np.asarray(self.spacing_mm) + half

    def grown_to_hold(self, low_mm: Sequence[float], high_mm: Sequence[float]) -> "VolumeGrid":
        """This grid grown, on its own voxel lattice, until its voxel centres span [low_mm, high_mm] (LPS) as well."""
        first = np.minimum(np.floor(self.world_to_index(low_mm)), 0).astype(int)
        last = np.maximum(np.ceil(self.world_to_index(high_mm)), np.asarray(self.shape) - 1).astype(int)
        if np.all(first == 0) and np.all(last == np.asarray(self.shape) - 1):
            return self
        centre = self.index_to_world((first + last) / 2.0)
        return VolumeGrid(tuple(int(n) for n in last - first + 1), tuple(self.spacing_mm), tuple(float(c) for c in centre))

    def corners(self) -> np.ndarray:
        lo, hi = self.bounds()
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        return self.origin + np.asarray(ijk, float) * np.asarray(self.spacing_mm, float)

    def world_to_index(self, xyz: np.ndarray) -> np.ndarray:
        return (np.asarray(xyz, float) - self.origin) / np.asarray(self.spacing_mm, float)

    def voxel_centers(self, flat_indices: Optional[np.ndarray] = None) -> np.ndarray:
        """World coordinates (N, 3) of voxel centres, in C order of ``[i, j, k]`` or of ``flat_indices``."""
        if flat_indices is None:
            flat_indices = np.arange(self.num_voxels)
        ijk = np.stack(np.unravel_index(np.asarray(flat_indices), self.shape), axis=-1)
        return self.index_to_world(ijk)

    def ijk_to_lps_matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = np.diag(self.spacing_mm)
        m[:3, 3] = self.origin
        return m

    def to_dict(self) -> Dict[str, Any]:
        return {
            "shape": [int(v) for v in self.shape],
            "spacing_mm": [float(v) for v in self.spacing_mm],
            "center_mm": [float(v) for v in self.center_mm],
        }

    @classmethod
    def from_dict(cls, data: Any, where: str = "volume") -> "VolumeGrid":
        _require(isinstance(data, dict), f"{where} must be an object, got {type(data).__name__}")
        missing = [k for k in ("shape", "spacing_mm") if k not in data]
        _require(not missing, f"{where} is missing required field(s): {', '.join(missing)}")
        unknown = sorted(set(data) - {"shape", "spacing_mm", "center_mm"})
        _require(not unknown, f"{where} has unknown field(s): {', '.join(unknown)} (allowed: center_mm, shape, spacing_mm)")
        shape = _int_list(data["shape"], 3, f"{where}.shape")
        spacing = _number_list(data["spacing_mm"], 3, f"{where}.spacing_mm")
        center = _number_list(data.get("center_mm", [0.0, 0.0, 0.0]), 3, f"{where}.center_mm")
        return cls(shape=shape, spacing_mm=spacing, center_mm=center)


#: GEOM.json's optional top-level keys for the reader (``Geometry.annotations``)
ANNOTATION_KEYS = ("description", "provenance")


@dataclass(frozen=True)
class Geometry:
    """A reconstruction problem's geometry: the volume grid and the C-arm views (GEOM.json)."""

    volume: VolumeGrid
    views: Tuple[CArmView, ...] = field(default_factory=tuple)
    # GEOM.json's optional top-level "description" and "provenance", kept for the reader and written back by ``save``;
    # like a view's provenance, no part of the geometry (not compared, not in ``to_dict`` or the digest)
    annotations: Dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "views", tuple(self.views))
        self.validate()

    def validate(self) -> None:
        _require(len(self.views) >= 1, "views must list at least one C-arm view")
        lo, hi = self.volume.bounds()
        radius = float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi))))
        for n, view in enumerate(self.views):
            where = f"views[{n}]"
            _require(
                view.sod_mm > radius,
                f"{where}: the X-ray source (sod_mm = {view.sod_mm} mm from the isocenter) can lie inside "
                f"the volume, which reaches {radius:.1f} mm from the isocenter; make the volume smaller "
                "or check sod_mm",
            )
            row, col, _ = view.project(self.volume.corners())
            rows, cols = view.detector_shape
            hits_detector = (row.max() >= -0.5 and row.min() <= rows - 0.5 and col.max() >= -0.5 and col.min() <= cols - 0.5)
            _require(
                hits_detector,
                f"{where} ({view.describe()}): the volume (centre {list(self.volume.center_mm)} mm, extent "
                f"{list(np.round(self.volume.extent_mm, 1))} mm) does not project onto the detector; "
                "check volume.center_mm and the view's angles and principal point",
            )

    def to_dict(self) -> Dict[str, Any]:
        return {"volume": self.volume.to_dict(), "views": [v.to_dict() for v in self.views]}

    @classmethod
    def from_dict(cls, data: Any) -> "Geometry":
        _require(isinstance(data, dict), f"the geometry must be a JSON object, got {type(data).__name__}")
        given = data.get("volume")
        asks_for_automatic_volume = given is None or given == "auto" or (isinstance(given, dict) and given.get("auto") is not None)
        _require("views" not in data or not asks_for_automatic_volume,
                 "the geometry asks for an automatic volume (no grid given): read it with "
                 "SDFCARLib.region.read_geometry, which returns the geometry and the request, or give the volume's "
                 "shape and spacing_mm")
        missing = [k for k in ("volume", "views") if k not in data]
        _require(not missing, f"the geometry is missing required field(s): {', '.join(missing)}")
        unknown = sorted(set(data) - {"volume", "views", *ANNOTATION_KEYS})
        _require(not unknown, f"the geometry has unknown field(s): {', '.join(unknown)}")
        volume = VolumeGrid.from_dict(data["volume"])
        _require(isinstance(data["views"], list) and len(data["views"]) >= 1, "views must be a non-empty list")
        views = tuple(CArmView.from_dict(v, f"views[{n}]") for n, v in enumerate(data["views"]))
        return cls(volume=volume, views=views, annotations={k: data[k] for k in ANNOTATION_KEYS if k in data})

    @classmethod
    def load(cls, path: PathLike) -> "Geometry":
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise GeometryError(f"cannot read geometry file {path}: {exc.strerror or exc}") from exc
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise GeometryError(f"{path} is not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from exc
        try:
            return cls.from_dict(data)
        except GeometryError as exc:
            raise GeometryError(f"{path}: {exc}") from exc

    def save(self, path: PathLike) -> None:
        """GEOM.json: the geometry, with the description and provenance it was loaded with."""
        data = self.to_dict()
        for entry, view in zip(data["views"], self.views):
            if view.provenance is not None:
                entry["provenance"] = view.provenance
        data.update(self.annotations)
        Path(path).write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")

    def digest(self) -> str:
        """Short stable hash of the geometry, for provenance."""
        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

# --- standard acquisition protocols -------------------------------------------------------------

#: Named view sets (pairs, and a triple): (primary, secondary, SID, SOD) per view. "paper" is the NeCA/SDF-CAR
#: simulation protocol; the others are clinically typical coronary pairs.
VIEW_PAIRS: Dict[str, List[Tuple[float, float, float, float]]] = {
    "paper": [(29.7, 0.1, 993.0, 757.06), (2.0, 29.0, 1055.0, 756.99)],
    "lao30-rao30": [(30.0, 0.0, 1000.0, 757.0), (-30.0, 0.0, 1000.0, 757.0)],
    "lao50cra25-rao50cra25": [(50.0, 25.0, 1000.0, 757.0), (-50.0, 25.0, 1000.0, 757.0)],
    # the pair above plus an AP cranial view: a third view rules out ghosts two views allow
    "lao30-rao30-cra30": [(30.0, 0.0, 1000.0, 757.0), (-30.0, 0.0, 1000.0, 757.0), (0.0, 30.0, 1000.0, 757.0)],
}


def standard_geometry(
    view_pair: str = "paper",
    volume_shape: Sequence[int] = PAPER_VOLUME_SHAPE,
    spacing_mm: float = PAPER_SPACING_MM,
    center_mm: Sequence[float] = (0.0, 0.0, 0.0),
    detector_shape: Sequence[int] = PAPER_DETECTOR_SHAPE,
    detector_spacing_mm: float = PAPER_DETECTOR_SPACING_MM,
) -> Geometry:
    """Geometry of a named protocol (``VIEW_PAIRS``) with the paper's default grid and detector."""
    if view_pair not in VIEW_PAIRS:
        raise GeometryError(f"unknown view pair {view_pair!r}; choose one of {', '.join(VIEW_PAIRS)}")
    views = tuple(
        CArmView(a, b, sid, sod, (detector_spacing_mm, detector_spacing_mm), tuple(detector_shape))
        for a, b, sid, sod in VIEW_PAIRS[view_pair]
    )
    grid = VolumeGrid(tuple(int(s) for s in volume_shape), (spacing_mm,) * 3, tuple(float(c) for c in center_mm))
    return Geometry(volume=grid, views=views)
