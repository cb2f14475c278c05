"""The scene itself: coordinates, VTK helpers, set-up, transactions, node look-up, provenance, files.

Coordinates
    SDFCAR computes in patient LPS (``geometry.py``); MRML nodes hold RAS. The conversion is
    written here once: RAS = diag(−1, −1, 1) · LPS (``lps_to_ras``, ``LPS_TO_RAS``). A voxel
    ``[i, j, k]`` of a result grid sits at LPS ``grid.index_to_world([i, j, k])`` and at RAS
    ``lps_to_ras`` of that in its volume or segmentation node.

Provenance
    Result nodes carry node attributes named ``SDFCAR.<key>`` (``provenance_attributes``); they are
    saved with the scene (.mrml and .mrb) and restored on load.

Node look-up
    ``vtkMRMLScene.GetNodesByClass`` returns a new ``vtkCollection`` that the caller owns; Python's
    wrapper adds its own reference and never drops the C++ one, so every call leaks the collection
    and keeps its nodes alive. ``nodes_by_class`` walks the scene by index instead.
"""

from __future__ import annotations

import json
import math
import tempfile
import xml.etree.ElementTree as ET
import zipfile
import zlib
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Union

import numpy as np

from ..geometry import VolumeGrid

PathLike = Union[str, Path]

#: Prefix of every node attribute SDFCAR writes.
ATTRIBUTE_PREFIX = "SDFCAR."

#: Version written into scene files made headless. A bare slicer-core scene says "slicer-core
#: 4.0.0 0", which Slicer reports as a scene "saved with another application" that "may not load
#: correctly"; the files hold nothing newer than Slicer 5.0 reads (revision > 0: not a legacy scene).
SCENE_FILE_VERSION = "Slicer 5.0.0 1"

# The one statement of the LPS <-> RAS relation: x and y change sign, z stays.
_LPS_RAS_SIGNS = np.array([-1.0, -1.0, 1.0])
#: Matrix that maps homogeneous LPS coordinates to RAS (and back: it is its own inverse).
LPS_TO_RAS = np.diag([*_LPS_RAS_SIGNS, 1.0])


class MRMLBridgeError(ValueError):
    """Scene content cannot be used as asked; the message names the node, the problem and the fix."""


# --- coordinates ----------------------------------------------------------------------------------
def lps_to_ras(points: Any) -> np.ndarray:
    """RAS coordinates of LPS points (..., 3): the signs of x and y flip."""
    out = np.array(points, dtype=np.float64, copy=True)
    if out.shape[-1:] != (3,):
        raise MRMLBridgeError(f"points must have 3 coordinates in their last axis, got shape {out.shape}")
    out *= _LPS_RAS_SIGNS
    return out


def ras_to_lps(points: Any) -> np.ndarray:
    """LPS coordinates of RAS points (..., 3) (the same sign flip as ``lps_to_ras``)."""
    return lps_to_ras(points)


def ijk_to_ras_matrix(grid: VolumeGrid) -> np.ndarray:
    """4×4 IJK→RAS matrix of a volume grid (for the volume node's ``SetIJKToRASMatrix``)."""
    return LPS_TO_RAS @ grid.ijk_to_lps_matrix()


# --- VTK helpers --------------------------------------------------------------------------------------
def _vtk_matrix(array: np.ndarray):
    import vtk

    matrix = vtk.vtkMatrix4x4()
    for r in range(4):
        for c in range(4):
            matrix.SetElement(r, c, float(array[r, c]))
    return matrix


def _numpy_matrix(vtk_matrix) -> np.ndarray:
    return np.array([[vtk_matrix.GetElement(r, c) for c in range(4)] for r in range(4)])


def _local_to_world_matrix(node) -> np.ndarray:
    """4×4 from a transformable node's own RAS coordinates (where its IJK→RAS or its points lie) to the
    scene's world RAS: its parent transforms applied. A non-linear transform is refused, naming the fix."""
    import vtk

    parent = node.GetParentTransformNode() if node is not None else None
    if parent is None:
        return np.eye(4)
    if not parent.IsTransformToWorldLinear():
        raise MRMLBridgeError(f"{node.GetName()!r} is under the non-linear transform {parent.GetName()!r}; harden the "
                              "transform on it (Data module: Harden transform) or remove it")
    matrix = vtk.vtkMatrix4x4()
    parent.GetMatrixTransformToWorld(matrix)
    return _numpy_matrix(matrix)


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


def nodes_by_class(scene, class_name: str) -> List[Any]:
    """The nodes of ``class_name`` (subclasses included) in scene order.

    Same nodes as ``scene.GetNodesByClass``, without the ``vtkCollection`` that call leaks (see the
    module docstring).
    """
    return [scene.GetNthNodeByClass(i, class_name) for i in range(scene.GetNumberOfNodesByClass(class_name))]


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
    """``SDFCAR.*`` node attributes from a reconstruction report (``Reconstruction.report``/report.json).

    A section of another kind than SDFCAR writes (a hand-edited or older report) is left out, not failed on."""
    if not isinstance(report, Mapping):
        raise MRMLBridgeError(f"the reconstruction report must be a JSON object, got {type(report).__name__}; give the "
                              "report.json SDFCAR wrote")

    def section(key: str) -> Mapping[str, Any]:
        value = report.get(key)
        return value if isinstance(value, Mapping) else {}

    settings = section("settings")
    losses = section("final_losses")
    out: Dict[str, Any] = {
        "preset": settings.get("preset"),
        "mode": settings.get("mode"),
        "seed": report.get("seed", settings.get("seed")),
        # of an ensemble kept whole (ensemble_combine "best_reprojection"): the seed of the fit that was kept
        "keptFitSeed": section("ensemble_choice").get("chosen_seed"),
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
        "sdfcarVersion": section("versions").get("sdfcar"),
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


#: what ``load_scene`` reads: a scene file and a scene bundle
SCENE_FILE_SUFFIXES = (".mrml", ".mrb")


def _scene_text_problem(text: bytes) -> Optional[str]:
    """Why ``text`` is not a MRML scene (None when it is one): checked before a scene is cleared for it."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        return f"it is not an XML file ({exc})"
    if root.tag != "MRML":
        return f"its XML root is <{root.tag}>, not <MRML>"
    return None


def _bundle_scene_problem(path: Path) -> Optional[str]:
    """Why the .mrb bundle ``path`` holds no loadable scene (None when it holds one)."""
    try:
        with zipfile.ZipFile(path) as bundle:
            inside = [name for name in bundle.namelist() if name.lower().endswith(".mrml")]
            if not inside:
                return "it holds no .mrml scene"
            return _scene_text_problem(bundle.read(inside[0]))
    except (zipfile.BadZipFile, OSError) as exc:
        return f"it is not a Slicer scene bundle (a zip file): {exc}"
    except (zlib.error, EOFError, RuntimeError, NotImplementedError) as exc:  # damaged, encrypted, unknown compression
        return f"the bundle is damaged: its scene cannot be unpacked ({exc})"


def load_scene(scene, path: PathLike, clear: bool = True):
    """Load a .mrml or .mrb file into ``scene`` (replacing its content when ``clear``); return the scene.

    The file is checked before the scene is touched: a wrong or damaged file leaves the scene as it was.
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise MRMLBridgeError(f"scene file {path} does not exist")
    if path.suffix.lower() not in SCENE_FILE_SUFFIXES:
        raise MRMLBridgeError(f"{path} is not a scene file: give a .mrml scene or a .mrb bundle (a result folder's "
                              "scene.mrml); load data files with add_reconstruction_to_scene or Slicer's Add Data")
    if path.suffix.lower() == ".mrb":
        problem = _bundle_scene_problem(path)
    else:
        try:
            problem = _scene_text_problem(path.read_bytes())
        except OSError as exc:
            problem = f"it cannot be read ({exc.strerror or exc})"
    if problem:
        raise MRMLBridgeError(f"{path} cannot be loaded as a scene: {problem}; nothing in the scene was changed")
    prepare_scene(scene)
    if path.suffix.lower() == ".mrb":
        io = scene.GetDataIOManager()
        cache = io.GetCacheManager() if io is not None else None
        if cache is not None and cache.GetRemoteCacheDirectory():
            ok = scene.ReadFromMRB(str(path), clear)
        else:
            # A bare slicer-core scene has no cache folder to unpack into: unpack here, as
            # ReadFromMRB does (the data are in memory once read, so the folder can go).
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
