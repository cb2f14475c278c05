"""The C-arm set-up in 3D: per view the X-ray source, the detector (with its frame) and the beam.

``add_carm_geometry_to_scene`` draws a ``Geometry``'s views in RAS so that a user can check the
set-up against the result: source points as markups, detectors as model planes (the frame or
mask as point scalars or as a texture), beams as lines from the source to the detector.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Any, List, Optional, Sequence

import numpy as np

from ..geometry import CArmView, Geometry
from .inputs import frame_from_volume_node
from .results import add_model_node
from .scene import MRMLBridgeError, _image_data, _set_attributes, lps_to_ras, prepare_scene, scene_transaction

#: Colours of the C-arm views in 3D (view 1, view 2, ...).
VIEW_COLORS = ((1.0, 0.8, 0.1), (0.2, 0.8, 1.0), (0.6, 1.0, 0.4), (1.0, 0.5, 1.0))


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
    if not np.all(np.isfinite(image)):
        raise MRMLBridgeError(f"the image of view {view.describe()} has {int(np.count_nonzero(~np.isfinite(image)))} NaN or "
                              "infinite pixels; give the frame or mask with a number in every pixel")
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
    if (isinstance(max_points_per_side, bool) or not isinstance(max_points_per_side, numbers.Integral)
            or max_points_per_side < 2):
        raise MRMLBridgeError(f"max_points_per_side must be a whole number of 2 or more (points along a detector "
                              f"side), got {max_points_per_side!r}")
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
                if not hasattr(image, "GetImageData") and hasattr(image, "GetClassName"):
                    raise MRMLBridgeError(f"the image of view {n} is a {image.GetClassName()}; give the frame's volume node "
                                          "or a 2D array (None for none)")
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
