"""A result's reprojection-QA overlays (``qa_view<n>.png``) as colour volumes in the scene.

Each overlay becomes a ``vtkMRMLVectorVolumeNode`` "<name> QA view <n>" (RGB, one slice) that the
slice views show in colour and that is saved with the scene. Image pixel (row, col) is detector
pixel (row, col) (``qa.qa_overlay_rgb``; the legend strip lies below the detector rows), so the
volume takes the IJK→RAS matrix of that view's frame node when one is given — the overlay then
lies exactly on the frame in a slice view — and otherwise the layout of
``inputs.add_frame_volume_node`` with the view's pixel spacing. The view's QA numbers from
report.json go on the node as ``SDFCAR.qa.*`` attributes.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import numpy as np

from ..geometry import Geometry, GeometryError
from ..qa import qa_summary
from .scene import (MRMLBridgeError, PathLike, _set_attributes, _vtk_matrix, nodes_by_class, prepare_scene,
                    scene_transaction)

_QA_KEY = re.compile(r"^qa_view(\d+)$")


def qa_overlay_files(result: Union[PathLike, Mapping[str, Any]]) -> Dict[int, Path]:
    """{view number: overlay file} of a result folder or of a job's output mapping (keys ``qa_view<n>``)."""
    if isinstance(result, Mapping):
        found = {}
        for key, value in result.items():
            match = _QA_KEY.match(str(key))
            if match and value:
                found[int(match.group(1))] = Path(value)
        return dict(sorted(found.items()))
    folder = Path(result)
    if not folder.is_dir():
        raise MRMLBridgeError(f"result folder {folder} does not exist; give the output folder of a reconstruction")
    found = {}
    for path in folder.glob("qa_view*.png"):
        match = _QA_KEY.match(path.stem)
        if match:
            found[int(match.group(1))] = path
    return dict(sorted(found.items()))


def read_report(result: Union[PathLike, Mapping[str, Any]]) -> Dict[str, Any]:
    """report.json of a result folder or job output mapping ({} when there is none)."""
    path = Path(result["report"]) if isinstance(result, Mapping) and result.get("report") else (
        None if isinstance(result, Mapping) else Path(result) / "report.json")
    if path is None or not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise MRMLBridgeError(f"cannot read the report {path}: {exc}; restore the file or re-run the reconstruction") from exc
    return data if isinstance(data, dict) else {}


def read_rgb_png(path: PathLike) -> np.ndarray:
    """An image file as uint8 RGB (rows, cols, 3)."""
    from PIL import Image  # bundled with Slicer; qa.py writes these files with it

    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"), dtype=np.uint8)
    except (OSError, ValueError) as exc:
        raise MRMLBridgeError(f"cannot read the QA overlay {path}: {exc}; re-run the reconstruction to write it again") from exc


def _rgb_image_data(rgb: np.ndarray):
    import vtk
    from vtk.util import numpy_support

    rows, cols, _ = rgb.shape
    image = vtk.vtkImageData()
    image.SetDimensions(cols, rows, 1)  # i along columns, j along rows (row 0 first), as a frame
    # numpy (rows, cols, 3) in C order is VTK's order: i fastest, the three components interleaved.
    scalars = numpy_support.numpy_to_vtk(np.ascontiguousarray(rgb).reshape(-1, 3), deep=True,
                                         array_type=vtk.VTK_UNSIGNED_CHAR)
    scalars.SetName("ImageScalars")
    image.GetPointData().SetScalars(scalars)
    return image


def _ijk_to_ras(view_number: int, geometry: Optional[Geometry], frame_node) -> np.ndarray:
    if frame_node is not None and hasattr(frame_node, "GetIJKToRASMatrix") and frame_node.GetImageData() is not None \
            and frame_node.GetImageData().GetDimensions()[2] == 1:
        matrix = _vtk_matrix(np.eye(4))
        frame_node.GetIJKToRASMatrix(matrix)
        return np.array([[matrix.GetElement(r, c) for c in range(4)] for r in range(4)])
    spacing = (1.0, 1.0)
    if geometry is not None and view_number <= len(geometry.views):
        spacing = tuple(float(s) for s in geometry.views[view_number - 1].pixel_spacing_mm)
    return np.diag([-spacing[1], -spacing[0], 1.0, 1.0])


def add_qa_overlays_to_scene(
    scene,
    result: Union[PathLike, Mapping[str, Any]],
    name: str = "SDFCAR",
    geometry: Optional[Geometry] = None,
    frame_nodes: Optional[Sequence[Any]] = None,
    attributes: Optional[Mapping[str, Any]] = None,
) -> List[Any]:
    """Add a result's QA overlays as RGB volume nodes, one per view (module docstring); return them.

    ``result``: a result folder or a job's output mapping; ``geometry``: the views (pixel spacing;
    default: the geometry in report.json); ``frame_nodes``: the views' frame volume nodes (None where unknown) to lay each overlay on its
    frame. A result without overlays (written before they existed) adds nothing. New nodes are
    added on every call; nodes already in the scene are never changed. On error the scene is left
    as it was.
    """
    files = qa_overlay_files(result)
    if not files:
        return []
    report = read_report(result)
    if geometry is None and isinstance(report.get("geometry"), dict):
        try:
            geometry = Geometry.from_dict(report["geometry"])
        except GeometryError:  # only the pixel spacing is taken from it; 1 mm without
            geometry = None
    summaries = {row["view"]: row for row in qa_summary(report)}
    frames = list(frame_nodes or [])
    prepare_scene(scene)
    nodes = []
    with scene_transaction(scene):
        for n, path in files.items():
            if not path.is_file():
                raise MRMLBridgeError(f"the QA overlay {path} of view {n} does not exist; check the result folder")
            rgb = read_rgb_png(path)
            node = scene.AddNewNodeByClass("vtkMRMLVectorVolumeNode", f"{name} QA view {n}")
            node.SetAndObserveImageData(_rgb_image_data(rgb))
            node.SetIJKToRASMatrix(_vtk_matrix(_ijk_to_ras(n, geometry, frames[n - 1] if n <= len(frames) else None)))
            node.CreateDefaultDisplayNodes()
            display = node.GetDisplayNode()
            if display is not None:
                # The colours are final 0–255 values: no automatic window/level stretch.
                display.SetAutoWindowLevel(0)
                display.SetWindowLevel(255.0, 127.5)
            values: Dict[str, Any] = {"role": "qa-overlay", "view": n, "qa.file": str(path)}
            row = summaries.get(n)
            if row is not None:
                values.update({f"qa.{key}": value for key, value in row.items()
                               if key not in ("view", "file") and value is not None})
            values.update(dict(attributes or {}))
            _set_attributes(node, values)
            nodes.append(node)
    return nodes


def qa_overlay_nodes(scene, result_folder: PathLike) -> Dict[int, Any]:
    """{view number: overlay node} of the QA overlays in ``scene`` made from ``result_folder``
    (``SDFCAR.resultFolder`` attribute); the latest added wins when a view was loaded twice."""
    folder = str(Path(result_folder))
    found: Dict[int, Any] = {}
    for node in nodes_by_class(scene, "vtkMRMLVectorVolumeNode"):
        if node.GetAttribute("SDFCAR.role") != "qa-overlay" or node.GetAttribute("SDFCAR.resultFolder") != folder:
            continue
        try:
            found[int(node.GetAttribute("SDFCAR.view"))] = node
        except (TypeError, ValueError):
            continue
    return dict(sorted(found.items()))


__all__ = ["qa_overlay_nodes", "add_qa_overlays_to_scene", "qa_overlay_files", "read_report", "read_rgb_png"]
