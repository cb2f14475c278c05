"""Result nodes: a reconstruction (or its output folder) as segmentation, surface and occupancy nodes.

Also the read-back of a segmentation (its segment sampled on an LPS grid or at LPS points) and
``write_result_scene``, the ``scene.mrml`` that ``outputs.write_reconstruction`` writes next to the
result files. Arrays are ``[i, j, k]`` on an LPS ``VolumeGrid``; nodes hold RAS (``scene.py``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from ..geometry import Geometry, VolumeGrid
from ..masks import binary_values_problem
from ..outputs import RESULT_FILES
from .scene import (ATTRIBUTE_PREFIX, SCENE_FILE_VERSION, MRMLBridgeError, PathLike, _attribute_text, _image_data,
                    _numpy_matrix, _set_attributes, _slicer, _vtk_matrix, ijk_to_ras_matrix, lps_to_ras, prepare_scene,
                    provenance_attributes, scene_transaction)

#: Name of the single segment of a result segmentation.
SEGMENT_NAME = "Coronary tree"
SEGMENT_COLOR = (0.86, 0.24, 0.2)
# The files of an output folder (names from ``outputs.RESULT_FILES``) that the scene shows.
_RESULT_KEYS = ("segmentation", "surface", "occupancy", "report")


# --- volumes and segmentations from arrays ------------------------------------------------------------
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
    if mask_ijk.dtype != bool:
        problem = (binary_values_problem(mask_ijk) if np.issubdtype(mask_ijk.dtype, np.number)
                   else f"holds {mask_ijk.dtype} values, not numbers")
        if problem:
            raise MRMLBridgeError(f"segmentation {name!r}: the mask {problem}: it must be binary (0 and one vessel "
                                  "value); threshold an occupancy first (e.g. occupancy >= 0.5)")
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
        # the files a result folder holds (``write_reconstruction``'s keys, the QA overlays among them): a typo is named
        unknown = sorted(str(k) for k in source if k not in RESULT_FILES and not str(k).startswith("qa_view"))
        if unknown:
            raise MRMLBridgeError(f"unknown result file key(s) {', '.join(unknown)}; the keys are {', '.join(_RESULT_KEYS)}")
        files = {k: Path(v) for k, v in source.items() if v is not None and k in _RESULT_KEYS}
        base = None
    else:
        if source is None:
            raise MRMLBridgeError("no result given; give a Reconstruction, a result folder or a mapping of its files")
        base = Path(source)
        if base.is_file():
            raise MRMLBridgeError(f"{base} is a file; give the reconstruction's output folder (the one holding "
                                  f"{RESULT_FILES['segmentation']})")
        if not base.is_dir():
            raise MRMLBridgeError(f"result folder {base} does not exist; give the output folder of a reconstruction")
        files = {k: base / RESULT_FILES[k] for k in _RESULT_KEYS if (base / RESULT_FILES[k]).exists()}
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
            report = getattr(result, "report", None) or {}
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
    segmentation = add_segmentation_node(scene, result.segmentation, grid, name)
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
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MRMLBridgeError(f"cannot read the report {files['report']}: {exc}") from exc
    segmentation = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    _read_into(scene, segmentation, "vtkMRMLSegmentationStorageNode", files["segmentation"], "segmentation")
    segmentation.CreateDefaultDisplayNodes()
    ids = _segment_ids(segmentation)
    if not ids:
        raise MRMLBridgeError(f"the segmentation file {files['segmentation']} holds no segment")
    # a segment added or emptied by hand in Slicer: the result is the first segment with voxels
    segment_id = next((i for i in ids if _segment_labelmap(segmentation, i)[0].any()), ids[0])
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
    if include_occupancy and "occupancy" not in files:
        raise MRMLBridgeError(f"the occupancy was asked for but the result has no {RESULT_FILES['occupancy']} (every "
                              "reconstruction writes one: the folder is incomplete); load it without the occupancy")
    if include_occupancy:
        occupancy = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", f"{name} occupancy")
        _read_into(scene, occupancy, "vtkMRMLVolumeArchetypeStorageNode", files["occupancy"], "occupancy volume")
        occupancy.CreateDefaultDisplayNodes()
    return ResultNodes(segmentation, model, occupancy, segment_id), report


def result_folder_of(node) -> Optional[Path]:
    """The folder of the result files a result node came from, or None when it cannot be told.

    In order: the ``SDFCAR.resultFolder`` attribute (the Slicer module sets it), the ``output``
    folder of ``SDFCAR.jobFolder`` (results loaded before that attribute existed), the folder of the
    node's segmentation file when report.json lies beside it (a result's scene.mrml opened in
    Slicer). The folder is returned only if it still exists.
    """
    if node is None:
        return None
    candidates = []
    for attribute, sub in (("SDFCAR.resultFolder", ""), ("SDFCAR.jobFolder", "output")):
        value = node.GetAttribute(attribute)
        if value:
            candidates.append(Path(value) / sub if sub else Path(value))
    storage = node.GetStorageNode() if hasattr(node, "GetStorageNode") else None
    file_name = storage.GetFileName() if storage is not None else None
    if file_name:
        candidates.append(Path(file_name).parent)
    for folder in candidates:
        if folder.is_dir() and (folder / RESULT_FILES["report"]).is_file():
            return folder
    return None


# --- segmentation read-back ------------------------------------------------------------------------------
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

