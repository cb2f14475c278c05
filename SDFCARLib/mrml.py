"""MRML bridge: SDFCAR results, C-arm set-ups and input frames as 3D Slicer scene content.

Every function takes the scene as an argument, so the same code serves Slicer's
``slicer.mrmlScene`` and a bare ``vtkMRMLScene`` of the ``slicer-core`` package (headless tests,
scripts). ``slicer`` and ``vtk`` are imported inside the functions only: importing this module
needs neither.

Coordinates
    SDFCAR computes in patient LPS (``geometry.py``); MRML nodes hold RAS. The conversion happens
    here and nowhere else: RAS = diag(−1, −1, 1) · LPS (``lps_to_ras``). A voxel ``[i, j, k]`` of a
    result grid sits at LPS ``grid.index_to_world([i, j, k])`` and at RAS ``lps_to_ras`` of that
    in its volume or segmentation node.

2D frames in volume nodes
    An X-ray frame in Slicer is a volume with one slice (a PNG/TIFF read by ITK, one frame of an
    XA cine run loaded by the DICOM module as a sequence). Its array ``[k, j, i]`` has ``j`` along
    image rows (top to bottom, as stored in the file) and ``i`` along columns, so pixel
    ``(row, col)`` is ``array[0, row, col]`` whatever the node's IJK→RAS matrix.

Provenance
    Result nodes carry node attributes named ``SDFCAR.<key>`` (``provenance_attributes``); they are
    saved with the scene (.mrml and .mrb) and restored on load.
"""

from __future__ import annotations

import json
import math
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import CArmView, Geometry, VolumeGrid

PathLike = Union[str, Path]

#: Prefix of every node attribute SDFCAR writes.
ATTRIBUTE_PREFIX = "SDFCAR."
#: Name of the single segment of a result segmentation.
SEGMENT_NAME = "Coronary tree"
SEGMENT_COLOR = (0.86, 0.24, 0.2)
#: Colours of the C-arm views in 3D (view 1, view 2, ...).
VIEW_COLORS = ((1.0, 0.8, 0.1), (0.2, 0.8, 1.0), (0.6, 1.0, 0.4), (1.0, 0.5, 1.0))
#: Output file names written by ``outputs.write_reconstruction`` (looked up in a result folder).
RESULT_FILES = {
    "segmentation": "segmentation.seg.nrrd",
    "surface": "surface.vtk",
    "occupancy": "occupancy.nrrd",
    "report": "report.json",
}

#: Version written into scene files made headless. A bare slicer-core scene says "slicer-core
#: 4.0.0 0", which Slicer reports as a scene "saved with another application" that "may not load
#: correctly"; the files hold nothing newer than Slicer 5.0 reads (revision > 0: not a legacy scene).
SCENE_FILE_VERSION = "Slicer 5.0.0 1"

#: Matrix that maps homogeneous LPS coordinates to RAS (and back: it is its own inverse).
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


class MRMLBridgeError(ValueError):
    """Scene content cannot be used as asked; the message names the node, the problem and the fix."""


# --- coordinates ----------------------------------------------------------------------------------
def lps_to_ras(points: Any) -> np.ndarray:
    """RAS coordinates of LPS points (..., 3): the signs of x and y flip."""
    out = np.array(points, dtype=np.float64, copy=True)
    if out.shape[-1:] != (3,):
        raise MRMLBridgeError(f"points must have 3 coordinates in their last axis, got shape {out.shape}")
    out[..., :2] *= -1.0
    return out


def ras_to_lps(points: Any) -> np.ndarray:
    """LPS coordinates of RAS points (..., 3) (the same sign flip as ``lps_to_ras``)."""
    return lps_to_ras(points)


def ijk_to_ras_matrix(grid: VolumeGrid) -> np.ndarray:
    """4×4 IJK→RAS matrix of a volume grid (for the volume node's ``SetIJKToRASMatrix``)."""
    return LPS_TO_RAS @ grid.ijk_to_lps_matrix()


def _vtk_matrix(array: np.ndarray):
    import vtk

    matrix = vtk.vtkMatrix4x4()
    for r in range(4):
        for c in range(4):
            matrix.SetElement(r, c, float(array[r, c]))
    return matrix


def _numpy_matrix(vtk_matrix) -> np.ndarray:
    return np.array([[vtk_matrix.GetElement(r, c) for c in range(4)] for r in range(4)])


# --- scene set-up -------------------------------------------------------------------------------------
def _slicer():
    try:
        import slicer
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError(
            "SDFCARLib.mrml needs 3D Slicer's Python or the 'slicer-core' package (pip install slicer-core)"
        ) from exc
    if not hasattr(slicer, "vtkMRMLScene"):  # pragma: no cover - a foreign package named slicer
        raise ImportError("the imported 'slicer' module has no MRML classes; install 'slicer-core' or run inside 3D Slicer")
    return slicer


# Classes a bare slicer-core scene lacks but SDFCAR content needs; Slicer's module logics register
# them in the application, so this is a no-op there.
_EXTRA_NODE_CLASSES = ("vtkMRMLMarkupsJsonStorageNode", "vtkMRMLSequenceBrowserNode")
_CONVERTER_RULES = (
    "vtkBinaryLabelmapToClosedSurfaceConversionRule",
    "vtkClosedSurfaceToBinaryLabelmapConversionRule",
)


def prepare_scene(scene):
    """Make a scene ready for SDFCAR content and return it.

    Registers the segmentation conversion rules and the node classes that Slicer's module logics
    provide in the application but a bare ``slicer-core`` scene lacks. Safe to call repeatedly.
    """
    slicer = _slicer()
    for class_name in _EXTRA_NODE_CLASSES:
        if not scene.IsNodeClassRegistered(class_name) and hasattr(slicer, class_name):
            scene.RegisterNodeClass(getattr(slicer, class_name)())
    factory = slicer.vtkSegmentationConverterFactory.GetInstance()
    rules = factory.GetConverterRules()
    present = {rules[i].GetClassName() for i in range(len(rules))} if rules is not None else set()
    for class_name in _CONVERTER_RULES:
        if class_name not in present:
            factory.RegisterConverterRule(getattr(slicer, class_name)())
    return scene


def new_scene():
    """A fresh ``vtkMRMLScene`` prepared for SDFCAR content (headless use).

    It holds a selection node, as Slicer's scene does (markups look up their length unit there).
    """
    slicer = _slicer()
    scene = prepare_scene(slicer.vtkMRMLScene())
    scene.AddNode(slicer.vtkMRMLSelectionNode())
    return scene


def _node_ids(scene) -> List[str]:
    return [scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())]


@contextmanager
def scene_transaction(scene) -> Iterator[None]:
    """Remove every node added inside the block when the block raises: the scene is left as it was."""
    before = set(_node_ids(scene))
    try:
        yield
    except BaseException:
        remove_nodes_added_since(scene, before)
        raise


def remove_nodes_added_since(scene, node_ids: Sequence[str]) -> None:
    """Remove the nodes whose IDs are not in ``node_ids`` (newest first)."""
    keep = set(node_ids)
    for node_id in reversed(_node_ids(scene)):
        if node_id not in keep:
            node = scene.GetNodeByID(node_id)
            if node is not None:
                scene.RemoveNode(node)


# --- provenance -------------------------------------------------------------------------------------
def _attribute_text(value: Any) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else "nan"
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(value, sort_keys=True)
    return str(value)


def provenance_attributes(report: Mapping[str, Any]) -> Dict[str, str]:
    """``SDFCAR.*`` node attributes from a reconstruction report (``Reconstruction.report``/report.json)."""
    settings = report.get("settings", {}) or {}
    losses = report.get("final_losses", {}) or {}
    out: Dict[str, Any] = {
        "preset": settings.get("preset"),
        "mode": settings.get("mode"),
        "seed": report.get("seed", settings.get("seed")),
        "steps": settings.get("steps"),
        "threshold": settings.get("threshold"),
        "method": report.get("method"),
        "device": report.get("device"),
        "targetKind": report.get("target_kind"),
        "finalLoss": losses.get("loss"),
        "finalLossOcc": losses.get("l_occ"),
        "finalLossGeo": losses.get("l_geo"),
        "reprojectionDice": report.get("reprojection_dice"),
        "segmentedVoxels": report.get("segmented_voxels"),
        "versions": report.get("versions"),
        "sdfcarVersion": (report.get("versions") or {}).get("sdfcar"),
        "geometryDigest": report.get("geometry_digest"),
        "geometry": report.get("geometry"),
        "settings": settings or None,
    }
    return {ATTRIBUTE_PREFIX + k: _attribute_text(v) for k, v in out.items() if v is not None}


def node_provenance(node) -> Dict[str, str]:
    """The ``SDFCAR.*`` attributes of a node, without the prefix."""
    names = node.GetAttributeNames() or ()
    return {n[len(ATTRIBUTE_PREFIX):]: node.GetAttribute(n) for n in names if n.startswith(ATTRIBUTE_PREFIX)}


def _set_attributes(node, attributes: Mapping[str, Any]) -> None:
    for key, value in attributes.items():
        name = key if key.startswith(ATTRIBUTE_PREFIX) else ATTRIBUTE_PREFIX + key
        node.SetAttribute(name, _attribute_text(value))


# --- volumes and segmentations from arrays ------------------------------------------------------------
def _image_data(array_ijk: np.ndarray, vtk_type: Optional[int] = None):
    """vtkImageData of an ``[i, j, k]`` array (VTK stores i fastest, i.e. numpy order [k, j, i])."""
    import vtk
    from vtk.util import numpy_support

    array_ijk = np.asarray(array_ijk)
    image = vtk.vtkImageData()
    image.SetDimensions(*array_ijk.shape)
    flat = np.ascontiguousarray(np.transpose(array_ijk, (2, 1, 0))).reshape(-1)
    scalars = numpy_support.numpy_to_vtk(flat, deep=True, array_type=vtk_type)
    scalars.SetName("ImageScalars")
    image.GetPointData().SetScalars(scalars)
    return image


def add_volume_node(scene, array_ijk: np.ndarray, grid: VolumeGrid, name: str,
                    class_name: str = "vtkMRMLScalarVolumeNode"):
    """A scalar (or labelmap) volume node holding an ``[i, j, k]`` array on an LPS grid."""
    array_ijk = np.asarray(array_ijk)
    if array_ijk.shape != tuple(grid.shape):
        raise MRMLBridgeError(f"volume {name!r}: array shape {array_ijk.shape} differs from the grid shape {tuple(grid.shape)}")
    if array_ijk.dtype == bool:
        array_ijk = array_ijk.astype(np.uint8)
    node = scene.AddNewNodeByClass(class_name, name)
    node.SetAndObserveImageData(_image_data(array_ijk))
    node.SetIJKToRASMatrix(_vtk_matrix(ijk_to_ras_matrix(grid)))
    node.CreateDefaultDisplayNodes()
    return node


def _oriented_labelmap(mask_ijk: np.ndarray, grid: VolumeGrid):
    import vtk

    slicer = _slicer()
    image = slicer.vtkOrientedImageData()
    image.ShallowCopy(_image_data(np.asarray(mask_ijk).astype(np.uint8), vtk.VTK_UNSIGNED_CHAR))
    image.SetImageToWorldMatrix(_vtk_matrix(ijk_to_ras_matrix(grid)))
    return image


def add_segmentation_node(scene, mask_ijk: np.ndarray, grid: VolumeGrid, name: str,
                          segment_name: str = SEGMENT_NAME, color: Sequence[float] = SEGMENT_COLOR,
                          closed_surface: bool = True):
    """A segmentation node with one segment from a boolean ``[i, j, k]`` mask on an LPS grid.

    Binary labelmap is the source representation; the reference geometry is the grid, and the
    closed surface is created with Slicer's conversion rules (``closed_surface``).
    """
    slicer = _slicer()
    mask_ijk = np.asarray(mask_ijk)
    if mask_ijk.shape != tuple(grid.shape):
        raise MRMLBridgeError(f"segmentation {name!r}: mask shape {mask_ijk.shape} differs from the grid shape {tuple(grid.shape)}")
    if not mask_ijk.any():
        raise MRMLBridgeError(
            f"segmentation {name!r}: the mask has no voxel, there is nothing to show; "
            "run more optimisation steps or lower the threshold")
    prepare_scene(scene)
    labelmap = _oriented_labelmap(mask_ijk != 0, grid)
    node = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    node.CreateDefaultDisplayNodes()
    segmentation = node.GetSegmentation()
    segmentation.SetSourceRepresentationName(slicer.vtkSegmentationConverter.GetSegmentationBinaryLabelmapRepresentationName())
    segmentation.SetConversionParameter(
        slicer.vtkSegmentationConverter.GetReferenceImageGeometryParameterName(),
        slicer.vtkSegmentationConverter.SerializeImageGeometry(labelmap))
    segment_id = node.AddSegmentFromBinaryLabelmapRepresentation(labelmap, segment_name, [float(c) for c in color])
    if not segment_id:
        raise MRMLBridgeError(f"segmentation {name!r}: Slicer could not add the segment {segment_name!r}")
    if closed_surface and not node.CreateClosedSurfaceRepresentation():
        raise MRMLBridgeError(f"segmentation {name!r}: Slicer could not create the closed surface representation")
    return node


def _segment_ids(segmentation_node) -> List[str]:
    segmentation = segmentation_node.GetSegmentation()
    return [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]


def add_model_node(scene, polydata, name: str, color: Sequence[float] = SEGMENT_COLOR, opacity: float = 1.0):
    node = scene.AddNewNodeByClass("vtkMRMLModelNode", name)
    node.SetAndObservePolyData(polydata)
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    display.SetColor(*[float(c) for c in color])
    display.SetOpacity(float(opacity))
    return node


def segmentation_surface(segmentation_node, segment_id: Optional[str] = None):
    """The closed surface (vtkPolyData, RAS) of a segment, created if needed."""
    import vtk

    slicer = _slicer()
    segment_id = segment_id or _segment_ids(segmentation_node)[0]
    polydata = vtk.vtkPolyData()
    if not slicer.vtkSlicerSegmentationsModuleLogic.GetSegmentClosedSurfaceRepresentation(segmentation_node, segment_id, polydata, True):
        raise MRMLBridgeError(f"segmentation {segmentation_node.GetName()!r}: no closed surface could be made of segment {segment_id!r}")
    return polydata


# --- results ---------------------------------------------------------------------------------------------
@dataclass
class ResultNodes:
    """Nodes ``add_reconstruction_to_scene`` created."""

    segmentation: Any
    model: Any
    occupancy: Any = None
    segment_id: str = ""
    attributes: Dict[str, str] = field(default_factory=dict)

    @property
    def nodes(self) -> List[Any]:
        return [n for n in (self.segmentation, self.model, self.occupancy) if n is not None]


def _result_files(source: Union[PathLike, Mapping[str, PathLike]]) -> Dict[str, Path]:
    if isinstance(source, Mapping):
        files = {k: Path(v) for k, v in source.items() if v is not None and k in RESULT_FILES}
        base = None
    else:
        base = Path(source)
        if not base.is_dir():
            raise MRMLBridgeError(f"result folder {base} does not exist; give the output folder of a reconstruction")
        files = {k: base / v for k, v in RESULT_FILES.items() if (base / v).exists()}
    missing = [k for k in ("segmentation",) if k not in files]
    if missing:
        where = f" in {base}" if base else ""
        raise MRMLBridgeError(f"no {RESULT_FILES['segmentation']} file{where}; a result needs at least its segmentation")
    for key, path in files.items():
        if not path.is_file():
            raise MRMLBridgeError(f"{key} file {path} does not exist; check the reconstruction's output folder")
    return files


def _read_into(scene, node, storage_class: str, path: Path, what: str) -> None:
    storage = scene.AddNewNodeByClass(storage_class)
    storage.SetFileName(str(path))
    node.SetAndObserveStorageNodeID(storage.GetID())
    if not storage.ReadData(node):
        raise MRMLBridgeError(f"Slicer could not read the {what} file {path}; it may be damaged or not a {what} file")


def add_reconstruction_to_scene(
    scene,
    result: Any,
    name: str = "SDFCAR",
    include_occupancy: bool = False,
    surface_from: str = "auto",
    attributes: Optional[Mapping[str, Any]] = None,
) -> ResultNodes:
    """Add a reconstruction to a scene: segmentation, surface model and optionally the occupancy.

    ``result`` is a ``Reconstruction`` (``optimiser.reconstruct``), a folder written by
    ``outputs.write_reconstruction``, or a mapping of its files (keys ``segmentation``, ``surface``,
    ``occupancy``, ``report``). Nodes are named after ``name`` ("<name>", "<name> surface",
    "<name> occupancy"); the segmentation has one segment "Coronary tree" (binary labelmap source,
    closed surface created). ``surface_from``: "segmentation" builds the model from the segment's
    closed surface, "file" reads ``surface`` (LPS .vtk), "auto" reads the file when given.
    Provenance from the report (and ``attributes``) goes on every node as ``SDFCAR.*`` attributes.

    On any error every node added so far is removed again and the error is raised.
    """
    if surface_from not in ("auto", "segmentation", "file"):
        raise MRMLBridgeError(f"surface_from must be 'auto', 'segmentation' or 'file', got {surface_from!r}")
    if not name or not str(name).strip():
        raise MRMLBridgeError("name must be a non-empty text; it names the result nodes")
    prepare_scene(scene)
    with scene_transaction(scene):
        if hasattr(result, "segmentation") and hasattr(result, "geometry"):
            nodes = _add_result_arrays(scene, result, name, include_occupancy, surface_from)
            report = dict(getattr(result, "report", {}) or {})
        else:
            nodes, report = _add_result_files(scene, _result_files(result), name, include_occupancy, surface_from)
        provenance = provenance_attributes(report)
        provenance.update({(k if k.startswith(ATTRIBUTE_PREFIX) else ATTRIBUTE_PREFIX + k): _attribute_text(v)
                           for k, v in (attributes or {}).items()})
        for node, role in ((nodes.segmentation, "segmentation"), (nodes.model, "surface"), (nodes.occupancy, "occupancy")):
            if node is not None:
                _set_attributes(node, dict(provenance, role=role))
        nodes.attributes = provenance
    return nodes


def _add_result_arrays(scene, result, name: str, include_occupancy: bool, surface_from: str) -> ResultNodes:
    if surface_from == "file":
        raise MRMLBridgeError("surface_from='file' needs result files; a Reconstruction object has no surface file")
    grid = result.geometry.volume
    segmentation = add_segmentation_node(scene, np.asarray(result.segmentation, dtype=bool), grid, name)
    segment_id = _segment_ids(segmentation)[0]
    model = add_model_node(scene, segmentation_surface(segmentation, segment_id), f"{name} surface")
    occupancy = None
    if include_occupancy:
        occupancy = add_volume_node(scene, np.asarray(result.occupancy, dtype=np.float32), grid, f"{name} occupancy")
    return ResultNodes(segmentation, model, occupancy, segment_id)


def _add_result_files(scene, files: Dict[str, Path], name: str, include_occupancy: bool, surface_from: str):
    report: Dict[str, Any] = {}
    if "report" in files:
        try:
            report = json.loads(files["report"].read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise MRMLBridgeError(f"cannot read the report {files['report']}: {exc}") from exc
    segmentation = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    _read_into(scene, segmentation, "vtkMRMLSegmentationStorageNode", files["segmentation"], "segmentation")
    segmentation.CreateDefaultDisplayNodes()
    ids = _segment_ids(segmentation)
    if not ids:
        raise MRMLBridgeError(f"the segmentation file {files['segmentation']} holds no segment")
    segment_id = ids[0]
    if not _segment_labelmap(segmentation, segment_id)[0].any():
        raise MRMLBridgeError(
            f"the segmentation {files['segmentation']} has no voxel, there is nothing to show; "
            "run more optimisation steps or lower the threshold (the report says more)")
    if len(ids) == 1:
        # Result segments are "Coronary tree" in the scene whatever the file calls them.
        segmentation.GetSegmentation().GetSegment(segment_id).SetName(SEGMENT_NAME)
    segmentation.CreateClosedSurfaceRepresentation()
    if surface_from == "file" and "surface" not in files:
        raise MRMLBridgeError("surface_from='file' but the result has no surface file")
    if surface_from != "segmentation" and "surface" in files:
        model = scene.AddNewNodeByClass("vtkMRMLModelNode", f"{name} surface")
        _read_into(scene, model, "vtkMRMLModelStorageNode", files["surface"], "surface model")
        model.CreateDefaultDisplayNodes()
        model.GetDisplayNode().SetColor(*SEGMENT_COLOR)
    else:
        model = add_model_node(scene, segmentation_surface(segmentation, segment_id), f"{name} surface")
    occupancy = None
    if include_occupancy and "occupancy" in files:
        occupancy = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", f"{name} occupancy")
        _read_into(scene, occupancy, "vtkMRMLVolumeArchetypeStorageNode", files["occupancy"], "occupancy volume")
        occupancy.CreateDefaultDisplayNodes()
    return ResultNodes(segmentation, model, occupancy, segment_id), report


def segmentation_mask_lps(segmentation_node, grid: VolumeGrid, segment_id: Optional[str] = None) -> np.ndarray:
    """Boolean ``[i, j, k]`` mask of a segment sampled at the voxel centres of an LPS grid."""
    return _segment_mask_at_ras(segmentation_node, segment_id, lps_to_ras(grid.voxel_centers())).reshape(grid.shape)


def segment_contains_lps(segmentation_node, points_lps: Any, segment_id: Optional[str] = None) -> np.ndarray:
    """For LPS points (N, 3): whether each lies in a voxel of the segment (nearest voxel)."""
    return _segment_mask_at_ras(segmentation_node, segment_id, lps_to_ras(np.reshape(points_lps, (-1, 3))))


def _segment_labelmap(segmentation_node, segment_id: Optional[str]) -> Tuple[np.ndarray, np.ndarray, Tuple[int, ...]]:
    """(boolean array [k, j, i] over the extent, IJK→RAS matrix, extent) of one segment."""
    from vtk.util import numpy_support

    slicer = _slicer()
    ids = _segment_ids(segmentation_node)
    if not ids:
        raise MRMLBridgeError(f"segmentation {segmentation_node.GetName()!r} has no segment")
    segment_id = segment_id or ids[0]
    segment = segmentation_node.GetSegmentation().GetSegment(segment_id)
    if segment is None:
        raise MRMLBridgeError(f"segmentation {segmentation_node.GetName()!r} has no segment with ID {segment_id!r}")
    image = slicer.vtkOrientedImageData()
    if not slicer.vtkSlicerSegmentationsModuleLogic.GetSegmentBinaryLabelmapRepresentation(segmentation_node, segment_id, image, True):
        raise MRMLBridgeError(f"segment {segment.GetName()!r} of {segmentation_node.GetName()!r} has no binary labelmap")
    extent = tuple(image.GetExtent())
    matrix = _vtk_matrix(np.eye(4))
    image.GetImageToWorldMatrix(matrix)
    dims = [extent[1] - extent[0] + 1, extent[3] - extent[2] + 1, extent[5] - extent[4] + 1]
    if min(dims) <= 0 or image.GetPointData().GetScalars() is None:
        return np.zeros((0, 0, 0), bool), _numpy_matrix(matrix), extent
    values = numpy_support.vtk_to_numpy(image.GetPointData().GetScalars()).reshape(dims[::-1])
    # A shared labelmap holds several segments, each with its own label value.
    return values == segment.GetLabelValue(), _numpy_matrix(matrix), extent


def _segment_mask_at_ras(segmentation_node, segment_id: Optional[str], points_ras: np.ndarray) -> np.ndarray:
    mask_kji, ijk_to_ras, extent = _segment_labelmap(segmentation_node, segment_id)
    out = np.zeros(len(points_ras), dtype=bool)
    if mask_kji.size == 0:
        return out
    ras_to_ijk = np.linalg.inv(ijk_to_ras)
    ijk = points_ras @ ras_to_ijk[:3, :3].T + ras_to_ijk[:3, 3]
    idx = np.rint(ijk).astype(np.int64) - np.array([extent[0], extent[2], extent[4]])
    shape_ijk = mask_kji.shape[::-1]
    inside = np.all((idx >= 0) & (idx < np.array(shape_ijk)), axis=1)
    out[inside] = mask_kji[idx[inside, 2], idx[inside, 1], idx[inside, 0]]
    return out


# --- result scene file ------------------------------------------------------------------------------------
def write_result_scene(
    directory: PathLike,
    name: str,
    geometry: Geometry,
    segmentation_file: PathLike,
    surface_file: Optional[PathLike] = None,
    attributes: Optional[Mapping[str, Any]] = None,
    scene_file: str = "scene.mrml",
) -> Path:
    """Write ``<directory>/scene.mrml`` that opens a written result in Slicer; return its path.

    The scene references the segmentation (.seg.nrrd) and the surface (.vtk in LPS, as
    ``io.write_surface_vtk`` writes it) by paths relative to ``directory``, so the folder can be
    moved. Both nodes are named after ``name`` and carry ``attributes`` (plus the geometry digest)
    as ``SDFCAR.*`` attributes. The data files are referenced, not read.
    """
    slicer = _slicer()
    directory = Path(directory)
    if not directory.is_dir():
        raise MRMLBridgeError(f"output folder {directory} does not exist; write the result files there first")
    files = {"segmentation": Path(segmentation_file)}
    if surface_file is not None:
        files["surface"] = Path(surface_file)
    for key, path in files.items():
        full = path if path.is_absolute() else directory / path
        if not full.is_file():
            raise MRMLBridgeError(f"the {key} file {full} does not exist; write it before the scene that references it")
        files[key] = full.resolve()
    scene = slicer.vtkMRMLScene()
    scene.SetVersion(SCENE_FILE_VERSION)
    target = directory.resolve() / scene_file
    scene.SetRootDirectory(str(target.parent))
    scene.SetURL(str(target))
    values = {"geometryDigest": geometry.digest(), "geometry": geometry.to_dict()}
    values.update(dict(attributes or {}))

    segmentation = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    display = scene.AddNewNodeByClass("vtkMRMLSegmentationDisplayNode")
    segmentation.SetAndObserveDisplayNodeID(display.GetID())
    storage = scene.AddNewNodeByClass("vtkMRMLSegmentationStorageNode")
    storage.SetFileName(str(files["segmentation"]))
    segmentation.SetAndObserveStorageNodeID(storage.GetID())
    _set_attributes(segmentation, dict(values, role="segmentation"))
    if "surface" in files:
        model = scene.AddNewNodeByClass("vtkMRMLModelNode", f"{name} surface")
        model_display = scene.AddNewNodeByClass("vtkMRMLModelDisplayNode")
        model_display.SetColor(*SEGMENT_COLOR)
        model.SetAndObserveDisplayNodeID(model_display.GetID())
        model_storage = scene.AddNewNodeByClass("vtkMRMLModelStorageNode")
        model_storage.SetFileName(str(files["surface"]))
        model_storage.SetCoordinateSystem(slicer.vtkMRMLStorageNode.CoordinateSystemLPS)
        model.SetAndObserveStorageNodeID(model_storage.GetID())
        _set_attributes(model, dict(values, role="surface"))
    # Write to a temporary name first so that a failed write leaves no half-written scene behind.
    partial = target.with_name(target.name + ".partial")
    if not scene.Commit(str(partial)):
        if partial.exists():
            partial.unlink()
        raise MRMLBridgeError(f"Slicer could not write the scene file {target}")
    partial.replace(target)
    return target


# --- saving and loading scenes ------------------------------------------------------------------------------
def save_scene(scene, path: PathLike) -> Path:
    """Save a scene as .mrml (data files next to it) or .mrb (one bundle file); return the path.

    For .mrml every storable node without a file gets one in the scene's folder, named after the
    node; data read from a file and not modified since are referenced where they are; modified data
    are written into the scene's folder (never over a file in another folder).
    """
    path = Path(path).resolve()
    suffix = path.suffix.lower()
    if suffix not in (".mrml", ".mrb"):
        raise MRMLBridgeError(f"cannot save a scene as {path.name}: use a .mrml or .mrb file name")
    if not path.parent.is_dir():
        raise MRMLBridgeError(f"folder {path.parent} does not exist; create it first")
    prepare_scene(scene)
    if (scene.GetVersion() or "").startswith("slicer-core"):
        scene.SetVersion(SCENE_FILE_VERSION)
    if suffix == ".mrb":
        if not scene.WriteToMRB(str(path)):
            raise MRMLBridgeError(f"Slicer could not write the scene bundle {path}")
        return path
    scene.SetRootDirectory(str(path.parent))
    taken = set()
    for i in range(scene.GetNumberOfNodes()):
        node = scene.GetNthNode(i)
        # Hidden nodes are written by Commit itself (into "<scene>_Private"), as Slicer does.
        if not node.IsA("vtkMRMLStorableNode") or node.GetHideFromEditors() or not node.GetSaveWithScene():
            continue
        storage = node.GetStorageNode()
        if storage is None:
            if not node.AddDefaultStorageNode():
                continue
            storage = node.GetStorageNode()
        current = storage.GetFileName()
        if current and Path(current).exists():
            if not node.GetModifiedSinceRead():
                continue  # referenced where it is
            # Modified data are written into the scene's folder: files elsewhere stay untouched.
            if Path(current).resolve().parent != path.parent:
                current = None
        if not current:
            extension = "." + storage.GetDefaultWriteFileExtension()
            base = _safe_file_name(node.GetName())
            candidate, n = base + extension, 0
            while candidate in taken or (path.parent / candidate).exists():
                n += 1
                candidate = f"{base}_{n}{extension}"
            taken.add(candidate)
            storage.SetFileName(str(path.parent / candidate))
        if not storage.WriteData(node):
            raise MRMLBridgeError(f"Slicer could not write the data of node {node.GetName()!r} to {storage.GetFileName()}")
    scene.SetURL(str(path))
    if not scene.Commit(str(path)):
        raise MRMLBridgeError(f"Slicer could not write the scene file {path}")
    return path


def _safe_file_name(name: str) -> str:
    keep = "".join(c if c.isalnum() or c in "-_." else "_" for c in (name or "node"))
    return keep.strip("._") or "node"


def load_scene(scene, path: PathLike, clear: bool = True):
    """Load a .mrml or .mrb file into ``scene`` (replacing its content when ``clear``); return the scene."""
    path = Path(path).resolve()
    if not path.is_file():
        raise MRMLBridgeError(f"scene file {path} does not exist")
    prepare_scene(scene)
    if path.suffix.lower() == ".mrb":
        io = scene.GetDataIOManager()
        cache = io.GetCacheManager() if io is not None else None
        if cache is not None and cache.GetRemoteCacheDirectory():
            ok = scene.ReadFromMRB(str(path), clear)
        else:
            # A bare slicer-core scene has no cache folder to unpack into: unpack here, as
            # ReadFromMRB does (the data are in memory once read, so the folder can go).
            import tempfile

            with tempfile.TemporaryDirectory(prefix="sdfcar-mrb-") as unpack_dir:
                mrml_file = scene.UnpackSlicerDataBundle(str(path), unpack_dir)
                if not mrml_file:
                    raise MRMLBridgeError(f"{path} is not a Slicer scene bundle (no .mrml inside)")
                scene.SetURL(mrml_file)
                ok = scene.Connect() if clear else scene.Import()
    else:
        scene.SetURL(str(path))
        ok = scene.Connect() if clear else scene.Import()
    if not ok:
        raise MRMLBridgeError(f"Slicer could not load the scene {path}")
    return scene


# --- C-arm set-up ------------------------------------------------------------------------------------------
@dataclass
class CArmNodes:
    """Nodes ``add_carm_geometry_to_scene`` created."""

    sources: Any
    detectors: List[Any] = field(default_factory=list)
    beams: List[Any] = field(default_factory=list)

    @property
    def nodes(self) -> List[Any]:
        return [self.sources, *self.detectors, *self.beams]


def _detector_corners_lps(view: CArmView) -> np.ndarray:
    rows, cols = view.detector_shape
    r = np.array([-0.5, -0.5, rows - 0.5, rows - 0.5])
    c = np.array([-0.5, cols - 0.5, cols - 0.5, -0.5])
    return view.pixel_to_world(r, c)


def _pooled(image: np.ndarray, factor: int) -> np.ndarray:
    if factor <= 1:
        return image
    rows, cols = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    return image[:rows, :cols].reshape(rows // factor, factor, cols // factor, factor).mean(axis=(1, 3))


def detector_image_polydata(view: CArmView, image: Optional[np.ndarray] = None, max_points_per_side: int = 512,
                            scalar_name: str = "frame"):
    """The detector of a view as a RAS plane; with ``image``, one point per pixel holding its value.

    Points sit at pixel centres (``view.pixel_to_world``), so the image lies on the detector as the
    projector sees it. Images larger than ``max_points_per_side`` are averaged over square blocks.
    Texture coordinates (u along columns, v along rows) are set for texturing as well.
    """
    import vtk
    from vtk.util import numpy_support

    rows, cols = view.detector_shape
    if image is None:
        corners = lps_to_ras(_detector_corners_lps(view))
        points = vtk.vtkPoints()
        for p in corners:
            points.InsertNextPoint(*p)
        polys = vtk.vtkCellArray()
        polys.InsertNextCell(4, [0, 1, 2, 3])
        poly = vtk.vtkPolyData()
        poly.SetPoints(points)
        poly.SetPolys(polys)
        tcoords = numpy_support.numpy_to_vtk(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32), deep=True)
        tcoords.SetName("TextureCoordinates")
        poly.GetPointData().SetTCoords(tcoords)
        return poly
    image = np.asarray(image, dtype=np.float32)
    if image.shape != (rows, cols):
        raise MRMLBridgeError(f"image shape {image.shape} differs from the detector shape {(rows, cols)} of the view")
    factor = max(1, int(math.ceil(max(rows, cols) / float(max_points_per_side))))
    pooled = _pooled(image, factor)
    n_r, n_c = pooled.shape
    rr, cc = np.meshgrid(np.arange(n_r) * factor + (factor - 1) / 2.0, np.arange(n_c) * factor + (factor - 1) / 2.0, indexing="ij")
    xyz = lps_to_ras(view.pixel_to_world(rr, cc)).reshape(-1, 3)
    points = vtk.vtkPoints()
    points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(xyz), deep=True))
    # Quads between neighbouring pixel centres.
    index = np.arange(n_r * n_c).reshape(n_r, n_c)
    quads = np.stack([index[:-1, :-1], index[:-1, 1:], index[1:, 1:], index[1:, :-1]], axis=-1).reshape(-1, 4)
    polys = vtk.vtkCellArray()
    polys.SetData(numpy_support.numpy_to_vtkIdTypeArray(np.arange(0, 4 * len(quads) + 1, 4, dtype=np.int64), deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(quads.astype(np.int64).reshape(-1), deep=True))
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetPolys(polys)
    scalars = numpy_support.numpy_to_vtk(np.ascontiguousarray(pooled.reshape(-1)), deep=True)
    scalars.SetName(scalar_name)
    poly.GetPointData().SetScalars(scalars)
    # Texture t runs along image rows: the texture image has row 0 first, like a frame volume node.
    tc = np.stack([(cc.reshape(-1) + 0.5) / cols, (rr.reshape(-1) + 0.5) / rows], axis=-1).astype(np.float32)
    tcoords = numpy_support.numpy_to_vtk(tc, deep=True)
    tcoords.SetName("TextureCoordinates")
    poly.GetPointData().SetTCoords(tcoords)
    return poly


def beam_polydata(view: CArmView):
    """Lines (RAS) from the X-ray source to the detector corners and centre: the view's beam."""
    import vtk

    source = lps_to_ras(view.source_position)
    ends = lps_to_ras(np.vstack([_detector_corners_lps(view), view.detector_center[None]]))
    points = vtk.vtkPoints()
    points.InsertNextPoint(*source)
    lines = vtk.vtkCellArray()
    for n, p in enumerate(ends, start=1):
        points.InsertNextPoint(*p)
        lines.InsertNextCell(2, [0, n])
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(lines)
    return poly


def add_carm_geometry_to_scene(
    scene,
    geometry: Geometry,
    images: Optional[Sequence[Any]] = None,
    name: str = "C-arm",
    image_display: str = "scalars",
    show_beams: bool = True,
    max_points_per_side: int = 512,
) -> CArmNodes:
    """Show the C-arm set-up: per view the source point, the detector and (optionally) its image.

    * sources: one markups fiducial node "<name> sources", one control point per view labelled
      with the view's angles;
    * detectors: a model per view, "<name> view N detector": the detector rectangle in RAS, or,
      when ``images[N-1]`` is given (a 2D array or a volume node holding the frame/mask), a plane
      with one point per pixel and the image as point scalars (grey scale);
    * beams (``show_beams``): lines from the source to the detector corners and centre.

    ``image_display`` "scalars" colours the plane by its point scalars (saved with the scene);
    "texture" additionally maps the image as a texture (``vtkMRMLModelDisplayNode``'s
    ``SetTextureImageDataConnection``) and hides the scalars. Slicer does not save texture
    connections with a scene: after reloading, switch the model's scalars back on to see the image.
    On error the scene is left as it was.
    """
    if image_display not in ("scalars", "texture"):
        raise MRMLBridgeError(f"image_display must be 'scalars' or 'texture', got {image_display!r}")
    views = list(geometry.views)
    images = list(images) if images is not None else [None] * len(views)
    if len(images) != len(views):
        raise MRMLBridgeError(f"{len(images)} image(s) for {len(views)} view(s); give one per view (None for none)")
    prepare_scene(scene)
    with scene_transaction(scene):
        sources = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", f"{name} sources")
        sources.CreateDefaultDisplayNodes()
        _set_attributes(sources, {"role": "carm-sources", "geometryDigest": geometry.digest(), "geometry": geometry.to_dict()})
        result = CArmNodes(sources)
        for n, (view, image) in enumerate(zip(views, images), start=1):
            color = VIEW_COLORS[(n - 1) % len(VIEW_COLORS)]
            p = lps_to_ras(view.source_position)
            sources.AddControlPoint(float(p[0]), float(p[1]), float(p[2]), f"view {n} ({view.describe()})")
            array = None
            texture_connection = None
            if image is not None:
                if hasattr(image, "GetImageData"):
                    array = frame_from_volume_node(image)
                    texture_connection = image.GetImageDataConnection() if hasattr(image, "GetImageDataConnection") else None
                else:
                    array = np.asarray(image, dtype=np.float32)
                    if array.ndim != 2:
                        raise MRMLBridgeError(f"image of view {n} must be a 2D array (rows, cols), got shape {array.shape}")
            detector = add_model_node(scene, detector_image_polydata(view, array, max_points_per_side),
                                      f"{name} view {n} detector", color=color if array is None else (1.0, 1.0, 1.0),
                                      opacity=0.5 if array is None else 1.0)
            display = detector.GetDisplayNode()
            display.SetBackfaceCulling(False)
            if array is not None:
                display.SetActiveScalarName("frame")
                display.SetScalarRangeFlag(display.UseDataScalarRange)
                grey = scene.GetNodeByID("vtkMRMLColorTableNodeGrey")
                if grey is not None:
                    display.SetAndObserveColorNodeID(grey.GetID())
                display.SetScalarVisibility(True)
                if image_display == "texture":
                    if texture_connection is None:
                        texture_connection = _texture_producer(array).GetOutputPort()
                    display.SetTextureImageDataConnection(texture_connection)
                    display.SetScalarVisibility(False)
            _set_attributes(detector, {"role": "carm-detector", "view": n, "view.description": view.describe(),
                                       "view.geometry": view.to_dict()})
            result.detectors.append(detector)
            if show_beams:
                beam = add_model_node(scene, beam_polydata(view), f"{name} view {n} beam", color=color, opacity=0.6)
                _set_attributes(beam, {"role": "carm-beam", "view": n})
                result.beams.append(beam)
    return result


# Texture producers must outlive the call (a display node keeps only the output port).
_TEXTURE_PRODUCERS: List[Any] = []


def _texture_producer(array: np.ndarray):
    import vtk

    a = np.asarray(array, dtype=np.float64)
    lo, hi = float(np.min(a)), float(np.max(a))
    scaled = np.zeros(a.shape, np.uint8) if hi <= lo else np.round((a - lo) / (hi - lo) * 255).astype(np.uint8)
    # Same layout as a frame volume node: i along columns, j along rows (row 0 first).
    image = _image_data(scaled.T[:, :, None], vtk.VTK_UNSIGNED_CHAR)
    producer = vtk.vtkTrivialProducer()
    producer.SetOutput(image)
    _TEXTURE_PRODUCERS.append(producer)
    return producer


# --- inputs from a scene --------------------------------------------------------------------------------------
def frame_from_volume_node(node, slice_index: Optional[int] = None) -> np.ndarray:
    """The 2D frame (rows, cols), float32, of a volume node holding an X-ray image.

    The node must hold one slice (or give ``slice_index`` for a multi-frame volume); pixel
    (row, col) is ``array[slice, row, col]`` (see the module docstring). RGB frames become grey.
    """
    from vtk.util import numpy_support

    if node is None or not hasattr(node, "GetImageData"):
        raise MRMLBridgeError("no volume node given; choose the volume that holds the X-ray frame")
    image = node.GetImageData()
    if image is None or image.GetPointData().GetScalars() is None:
        raise MRMLBridgeError(f"volume {node.GetName()!r} holds no image data; load the frame first")
    dims = image.GetDimensions()
    scalars = image.GetPointData().GetScalars()
    components = scalars.GetNumberOfComponents()
    array = numpy_support.vtk_to_numpy(scalars).reshape(dims[2], dims[1], dims[0], components)
    array = array.astype(np.float32)
    array = array[..., 0] if components == 1 else array[..., : min(components, 3)].mean(axis=-1)
    if dims[2] == 1:
        return array[0]
    if slice_index is None:
        raise MRMLBridgeError(
            f"volume {node.GetName()!r} has {dims[2]} slices; an X-ray frame has one. Choose the frame "
            "(slice index), or load the cine run as a sequence and pick its frame")
    if not 0 <= slice_index < dims[2]:
        raise MRMLBridgeError(f"slice index {slice_index} is out of range for volume {node.GetName()!r} with {dims[2]} slices")
    return array[slice_index]


def mask_from_volume_node(node, threshold: Optional[float] = None, slice_index: Optional[int] = None) -> np.ndarray:
    """A boolean vessel mask (rows, cols) from a labelmap or scalar volume node holding a 2D frame.

    Labelmaps and two-valued volumes give ``value != 0``; other scalar volumes need ``threshold``
    (vessel = value > threshold).
    """
    frame = frame_from_volume_node(node, slice_index)
    if threshold is not None:
        return frame > float(threshold)
    if node.IsA("vtkMRMLLabelMapVolumeNode"):
        return frame != 0
    values = np.unique(frame)
    if values.size <= 2:
        return frame != 0 if values.size == 1 or values[0] == 0 else frame == values.max()
    raise MRMLBridgeError(
        f"volume {node.GetName()!r} holds {values.size} different values, so it is an image, not a mask; "
        "give a labelmap or segmentation of the vessels, or a threshold")


def mask_from_segmentation_node(segmentation_node, reference_volume_node=None,
                                segments: Optional[Sequence[str]] = None, slice_index: Optional[int] = None) -> np.ndarray:
    """A boolean vessel mask (rows, cols) on a 2D frame from a segmentation node.

    The mask is the union of ``segments`` (IDs or names; default: every segment) sampled at the
    pixel centres of ``reference_volume_node`` (default: the segmentation's reference geometry
    volume), which holds the frame (slice ``slice_index`` of a multi-frame volume).
    """
    slicer = _slicer()
    if segmentation_node is None or not segmentation_node.IsA("vtkMRMLSegmentationNode"):
        raise MRMLBridgeError("no segmentation node given; choose the segmentation of the vessels")
    if reference_volume_node is None:
        role = slicer.vtkMRMLSegmentationNode.GetReferenceImageGeometryReferenceRole()
        reference_volume_node = segmentation_node.GetNodeReference(role)
        if reference_volume_node is None:
            raise MRMLBridgeError(
                f"segmentation {segmentation_node.GetName()!r} has no reference volume; give the frame's volume node")
    all_ids = _segment_ids(segmentation_node)
    if not all_ids:
        raise MRMLBridgeError(f"segmentation {segmentation_node.GetName()!r} has no segment; paint the vessels first")
    segmentation = segmentation_node.GetSegmentation()
    chosen: List[str] = []
    for key in (segments if segments is not None else all_ids):
        if key in all_ids:
            chosen.append(key)
            continue
        by_name = segmentation.GetSegmentIdBySegmentName(key)
        if not by_name:
            names = [segmentation.GetSegment(i).GetName() for i in all_ids]
            raise MRMLBridgeError(f"segmentation {segmentation_node.GetName()!r} has no segment {key!r} (segments: {', '.join(names)})")
        chosen.append(by_name)
    rows, cols = frame_from_volume_node(reference_volume_node, slice_index).shape
    vtk_matrix = _vtk_matrix(np.eye(4))
    reference_volume_node.GetIJKToRASMatrix(vtk_matrix)
    ijk_to_ras = _numpy_matrix(vtk_matrix)
    k = 0 if reference_volume_node.GetImageData().GetDimensions()[2] == 1 else int(slice_index)
    jj, ii = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    ijk = np.stack([ii.reshape(-1), jj.reshape(-1), np.full(rows * cols, k)], axis=-1).astype(np.float64)
    ras = ijk @ ijk_to_ras[:3, :3].T + ijk_to_ras[:3, 3]
    mask = np.zeros(rows * cols, dtype=bool)
    for segment_id in chosen:
        mask |= _segment_mask_at_ras(segmentation_node, segment_id, ras)
    return mask.reshape(rows, cols)


def add_frame_volume_node(scene, frame: np.ndarray, name: str, pixel_spacing_mm: Sequence[float] = (1.0, 1.0),
                          class_name: str = "vtkMRMLScalarVolumeNode"):
    """A volume node with one slice holding a 2D frame (rows, cols), laid out as Slicer's DICOM
    module lays out XA frames (IJK→RAS = diag(−col spacing, −row spacing, 1))."""
    frame = np.asarray(frame)
    if frame.ndim != 2:
        raise MRMLBridgeError(f"frame {name!r} must be 2D (rows, cols), got shape {frame.shape}")
    if frame.dtype == bool:
        frame = frame.astype(np.uint8)
    node = scene.AddNewNodeByClass(class_name, name)
    node.SetAndObserveImageData(_image_data(frame.T[:, :, None]))
    node.SetIJKToRASMatrix(_vtk_matrix(np.diag([-float(pixel_spacing_mm[1]), -float(pixel_spacing_mm[0]), 1.0, 1.0])))
    node.CreateDefaultDisplayNodes()
    return node


def _frame_labelmap(mask: np.ndarray, frame_node):
    """vtkOrientedImageData of a 2D mask (rows, cols) laid on a frame volume node's pixels."""
    import vtk

    slicer = _slicer()
    mask = np.asarray(mask, dtype=bool)
    frame = frame_from_volume_node(frame_node)
    if mask.shape != frame.shape:
        raise MRMLBridgeError(f"mask shape {mask.shape} differs from the frame shape {frame.shape} of {frame_node.GetName()!r}")
    labelmap = slicer.vtkOrientedImageData()
    labelmap.ShallowCopy(_image_data(mask.T[:, :, None].astype(np.uint8), vtk.VTK_UNSIGNED_CHAR))
    matrix = _vtk_matrix(np.eye(4))
    frame_node.GetIJKToRASMatrix(matrix)
    labelmap.SetImageToWorldMatrix(matrix)
    return labelmap


def set_segment_mask(segmentation_node, mask: np.ndarray, frame_node, segment_name: str = "Vessels",
                     color: Sequence[float] = (1.0, 0.3, 0.3)) -> str:
    """Replace (or add) the segment ``segment_name`` with a 2D mask (rows, cols) on a frame; return its ID."""
    slicer = _slicer()
    if segmentation_node.GetScene() is not None:
        prepare_scene(segmentation_node.GetScene())
    labelmap = _frame_labelmap(mask, frame_node)
    segmentation = segmentation_node.GetSegmentation()
    segment_id = segmentation.GetSegmentIdBySegmentName(segment_name)
    if segment_id:
        if not slicer.vtkSlicerSegmentationsModuleLogic.SetBinaryLabelmapToSegment(
                labelmap, segmentation_node, segment_id, slicer.vtkSlicerSegmentationsModuleLogic.MODE_REPLACE):
            raise MRMLBridgeError(f"Slicer could not write the mask into segment {segment_name!r} of {segmentation_node.GetName()!r}")
        return segment_id
    return segmentation_node.AddSegmentFromBinaryLabelmapRepresentation(labelmap, segment_name, [float(c) for c in color])


def add_mask_segmentation_node(scene, mask: np.ndarray, frame_node, name: str, segment_name: str = "Vessels"):
    """A segmentation node over a frame volume node holding a 2D mask (rows, cols) as one segment."""
    prepare_scene(scene)
    with scene_transaction(scene):
        node = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
        node.CreateDefaultDisplayNodes()
        node.SetReferenceImageGeometryParameterFromVolumeNode(frame_node)
        set_segment_mask(node, mask, frame_node, segment_name)
    return node


def sequence_of_proxy_node(scene, proxy_node) -> Tuple[Any, Any]:
    """(browser node, sequence node) that drive ``proxy_node``, or (None, None) if none does."""
    if proxy_node is None:
        return None, None
    browsers = scene.GetNodesByClass("vtkMRMLSequenceBrowserNode")
    for i in range(browsers.GetNumberOfItems()):
        browser = browsers.GetItemAsObject(i)
        if browser.IsProxyNodeID(proxy_node.GetID()):
            return browser, browser.GetSequenceNode(proxy_node)
    return None, None


def sequence_frame_node(sequence, index: int):
    """Data node of frame ``index`` (0-based) of a sequence node or of a browser's main sequence."""
    if sequence is not None and sequence.IsA("vtkMRMLSequenceBrowserNode"):
        browser = sequence
        sequence = browser.GetMasterSequenceNode()
        if sequence is None:
            raise MRMLBridgeError(f"sequence browser {browser.GetName()!r} has no sequence")
    if sequence is None or not sequence.IsA("vtkMRMLSequenceNode"):
        raise MRMLBridgeError("no sequence given; choose the cine run loaded by the DICOM module")
    count = sequence.GetNumberOfDataNodes()
    if not 0 <= int(index) < count:
        raise MRMLBridgeError(f"frame {index} is out of range: sequence {sequence.GetName()!r} has {count} frames (0 to {count - 1})")
    return sequence.GetNthDataNode(int(index))


def frame_from_sequence(sequence, index: int) -> np.ndarray:
    """Frame ``index`` (0-based) of a cine run loaded as a sequence: a (rows, cols) float32 array."""
    return frame_from_volume_node(sequence_frame_node(sequence, index))


def dicom_instance_uid(node) -> Optional[str]:
    """The SOP instance UID Slicer's DICOM module stored on a loaded volume (or frame), if any."""
    if node is None:
        return None
    value = node.GetAttribute("DICOM.instanceUIDs")
    return value.split()[0] if value else None


def dicom_frame_reference(scene, node, index: int = -1) -> Tuple[Optional[str], Optional[int]]:
    """(SOP instance UID, 0-based frame in that DICOM file) of the frame a volume node shows.

    For a sequence proxy node, ``index`` picks the sequence item (-1: the item on display); a
    multi-frame run loaded as one sequence shares one UID, so the item is the file's frame, while a
    run stored one file per frame has a UID per item and frame 0 in each. For another volume the
    frame is ``index`` (None when -1: let the DICOM reader choose).
    """
    browser, sequence = sequence_of_proxy_node(scene, node)
    if sequence is None:
        return dicom_instance_uid(node), (int(index) if index is not None and index >= 0 else None)
    item = int(index) if index is not None and index >= 0 else int(browser.GetSelectedItemNumber())
    data_node = sequence_frame_node(sequence, item)
    uid = dicom_instance_uid(data_node)
    uids = {dicom_instance_uid(sequence.GetNthDataNode(i)) for i in range(sequence.GetNumberOfDataNodes())}
    return uid, (item if len(uids) == 1 else 0)
