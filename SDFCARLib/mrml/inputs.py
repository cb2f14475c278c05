"""Inputs from a scene: X-ray frames and vessel masks from volume, segmentation and sequence nodes.

2D frames in volume nodes
    An X-ray frame in Slicer is a volume with one slice (a PNG/TIFF read by ITK, one frame of an
    XA cine run loaded by the DICOM module as a sequence). Its array ``[k, j, i]`` has ``j`` along
    image rows (top to bottom, as stored in the file) and ``i`` along columns, so pixel
    ``(row, col)`` is ``array[0, row, col]`` whatever the node's IJK→RAS matrix.

Masks
    A mask read from a volume node passes the library's one mask rule, ``masks.binarise_mask``
    (not empty, not everything, finite, ...), so the GUI accepts exactly what the command line does.

DICOM references
    ``dicom_frame_reference`` names the file and frame a shown frame came from (the SOP instance UID
    the DICOM module stores on the node), for reading the C-arm geometry from its header.

Grey levels
    What a frame's grey levels are (DICOM's Pixel Intensity Relationship) decides whether path lengths
    can be read off it. Where no DICOM file says, or to overrule it, the user says it on the frame node
    (``FRAME_INTENSITY_ATTRIBUTE``, saved with the scene): ``frame_intensity_said``, ``say_frame_intensity``.
"""

from __future__ import annotations

import numbers
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from ..evidence import DISPLAY_INTENSITY, LINEAR_INTENSITY
from ..masks import MaskError, binarise_mask
from .results import _segment_ids, _segment_mask_at_ras
from .scene import (ATTRIBUTE_PREFIX, MRMLBridgeError, _image_data, _local_to_world_matrix, _numpy_matrix, _slicer, _vtk_matrix,
                    nodes_by_class, prepare_scene, scene_transaction)


def _checked_index(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise MRMLBridgeError(f"{what} must be a whole number (0-based), got {value!r}")
    return int(value)


def frame_from_volume_node(node, slice_index: Optional[int] = None) -> np.ndarray:
    """The 2D frame (rows, cols), float32, of a volume node holding an X-ray image.

    The node must hold one slice (or give ``slice_index`` for a multi-frame volume); pixel
    (row, col) is ``array[slice, row, col]`` (see the module docstring). RGB frames become grey.
    """
    from vtk.util import numpy_support

    if node is None or not hasattr(node, "GetImageData"):
        raise MRMLBridgeError("no volume node given; choose the volume that holds the X-ray frame")
    if slice_index is not None:
        slice_index = _checked_index(slice_index, f"the slice index of volume {node.GetName()!r}")
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


def _ijk_to_ras(node) -> np.ndarray:
    vtk_matrix = _vtk_matrix(np.eye(4))
    node.GetIJKToRASMatrix(vtk_matrix)
    return _numpy_matrix(vtk_matrix)


def _pixel_centres(volume_node, slice_index: Optional[int], into_node=None) -> Tuple[int, int, np.ndarray]:
    """(rows, cols, points (rows·cols, 3)): the centres of a frame's pixels, row by row, in ``into_node``'s own
    RAS coordinates (world RAS when None), parent transforms of both nodes applied."""
    rows, cols = frame_from_volume_node(volume_node, slice_index).shape
    k = 0 if volume_node.GetImageData().GetDimensions()[2] == 1 else int(slice_index)
    ijk_to_target = _local_to_world_matrix(volume_node) @ _ijk_to_ras(volume_node)
    if into_node is not None:
        ijk_to_target = np.linalg.inv(_local_to_world_matrix(into_node)) @ ijk_to_target
    jj, ii = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    ijk = np.stack([ii.reshape(-1), jj.reshape(-1), np.full(rows * cols, k)], axis=-1).astype(np.float64)
    return rows, cols, ijk @ ijk_to_target[:3, :3].T + ijk_to_target[:3, 3]


def _mask_on_reference_pixels(node, slice_index: Optional[int], values: np.ndarray, reference, reference_slice_index):
    """A mask volume's values (rows, cols) on the pixels of the frame ``reference``.

    A mask of the frame's size is the frame's pixel for pixel, wherever its node lies (a mask image loaded
    from a file has a spacing of 1 and no origin). A mask of another size must lie on the frame's pixels
    (a labelmap exported cropped to the vessels): it is taken where it lies, or refused."""
    name, frame_name = node.GetName(), reference.GetName()
    if values.shape == frame_from_volume_node(reference, reference_slice_index).shape:
        return values  # before any geometry: a transform of either node (even a non-linear one) does not matter
    rows, cols, points = _pixel_centres(reference, reference_slice_index, into_node=node)
    ras_to_ijk = np.linalg.inv(_ijk_to_ras(node))
    ijk = points @ ras_to_ijk[:3, :3].T + ras_to_ijk[:3, 3]
    own_k = 0 if node.GetImageData().GetDimensions()[2] == 1 else int(slice_index)
    nearest = np.rint(ijk).astype(np.int64)
    if not (np.allclose(ijk, nearest, atol=1e-3) and (nearest[:, 2] == own_k).all()):
        raise MRMLBridgeError(
            f"mask volume {name!r} ({values.shape[0]} × {values.shape[1]} pixels) is not the size of frame "
            f"{frame_name!r} ({rows} × {cols}) and does not lie on its pixels; give the mask drawn on that frame, "
            "pixel for pixel")
    in_mask = ((nearest[:, 0] >= 0) & (nearest[:, 0] < values.shape[1]) & (nearest[:, 1] >= 0) & (nearest[:, 1] < values.shape[0]))
    sampled = np.zeros(rows * cols, dtype=values.dtype)
    sampled[in_mask] = values[nearest[in_mask, 1], nearest[in_mask, 0]]
    lost = int(np.count_nonzero(values)) - int(np.count_nonzero(sampled))
    if lost > 0:
        raise MRMLBridgeError(
            f"mask volume {name!r} reaches beyond frame {frame_name!r}: {lost} of its non-zero pixels lie outside the "
            "frame; give the mask drawn on that frame")
    return sampled.reshape(rows, cols)


def mask_from_volume_node(node, threshold: Optional[float] = None, slice_index: Optional[int] = None,
                          label: Optional[float] = None, reference_volume_node=None,
                          reference_slice_index: Optional[int] = None) -> np.ndarray:
    """A boolean vessel mask (rows, cols) from a labelmap or scalar volume node holding a 2D frame.

    Labelmaps and two-valued volumes give ``value != 0`` (``label``: only that value); other
    scalar volumes need ``threshold`` (vessel = value > threshold). The result must pass
    ``masks.binarise_mask``: a two-valued image whose background is not 0 is refused there.
    With ``reference_volume_node`` (the frame, slice ``reference_slice_index`` of a multi-frame volume) a
    mask of another size than the frame (a labelmap exported cropped) is placed on the frame's pixels.
    """
    if threshold is not None and label is not None:
        raise MRMLBridgeError("give a threshold (for a grey image) or a label (for a label image), not both")
    if threshold is not None and (isinstance(threshold, bool) or not isinstance(threshold, numbers.Real)
                                  or not np.isfinite(threshold)):
        raise MRMLBridgeError(f"the threshold must be a finite number, got {threshold!r}")
    frame = frame_from_volume_node(node, slice_index)
    bad = int(np.count_nonzero(~np.isfinite(frame)))
    if bad:
        raise MRMLBridgeError(f"volume {node.GetName()!r} has {bad} NaN or infinite pixels; fix the mask image")
    if reference_volume_node is not None:
        frame = _mask_on_reference_pixels(node, slice_index, frame, reference_volume_node, reference_slice_index)
    if threshold is not None:
        frame = frame > float(threshold)
    elif label is None and not node.IsA("vtkMRMLLabelMapVolumeNode"):
        # A grey X-ray frame chosen by mistake would pass as "every non-zero pixel is vessel".
        values = np.unique(frame)
        if values.size > 2:
            raise MRMLBridgeError(
                f"volume {node.GetName()!r} holds {values.size} different values, so it is an image, not a mask; "
                "give a labelmap or segmentation of the vessels, or a threshold")
    try:
        return binarise_mask(frame, label=label, source=f"volume {node.GetName()!r}")
    except MaskError as exc:
        raise MRMLBridgeError(str(exc)) from exc


def mask_from_segmentation_node(segmentation_node, reference_volume_node=None,
                                segments: Optional[Sequence[str]] = None, slice_index: Optional[int] = None) -> np.ndarray:
    """A boolean vessel mask (rows, cols) on a 2D frame from a segmentation node.

    The mask is the union of ``segments`` (IDs or names, or one of them; default: every segment) sampled at
    the pixel centres of ``reference_volume_node`` (default: the segmentation's reference geometry
    volume), which holds the frame (slice ``slice_index`` of a multi-frame volume); parent transforms of
    both nodes are applied. The mask must pass ``masks.binarise_mask``: an unpainted segment is refused.
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
    if isinstance(segments, str):
        segments = [segments]
    keys = list(segments) if segments is not None else all_ids
    if not keys:
        raise MRMLBridgeError(f"no segment of {segmentation_node.GetName()!r} was chosen; name the vessels' segments, "
                              "or give none to take every segment")
    segmentation = segmentation_node.GetSegmentation()
    chosen: List[str] = []
    for key in keys:
        if key in all_ids:
            chosen.append(key)
            continue
        by_name = segmentation.GetSegmentIdBySegmentName(key) if isinstance(key, str) else ""
        if not by_name:
            names = [segmentation.GetSegment(i).GetName() for i in all_ids]
            raise MRMLBridgeError(f"segmentation {segmentation_node.GetName()!r} has no segment {key!r} (segments: {', '.join(names)})")
        chosen.append(by_name)
    rows, cols, points = _pixel_centres(reference_volume_node, slice_index, into_node=segmentation_node)
    mask = np.zeros(rows * cols, dtype=bool)
    for segment_id in chosen:
        mask |= _segment_mask_at_ras(segmentation_node, segment_id, points)
    names = ", ".join(repr(segmentation.GetSegment(i).GetName()) for i in chosen)
    try:
        return binarise_mask(mask.reshape(rows, cols),
                             source=f"segmentation {segmentation_node.GetName()!r} (segment {names}) on frame "
                                    f"{reference_volume_node.GetName()!r}")
    except MaskError as exc:
        raise MRMLBridgeError(str(exc)) from exc


def _checked_frame_layout(frame: Any, name: str, pixel_spacing_mm: Sequence[float]) -> Tuple[np.ndarray, Tuple[float, float]]:
    frame = np.asarray(frame)
    if frame.ndim != 2 or frame.size == 0:
        raise MRMLBridgeError(f"frame {name!r} must be a non-empty 2D array (rows, cols), got shape {frame.shape}")
    if frame.dtype == bool:
        frame = frame.astype(np.uint8)
    if not (np.issubdtype(frame.dtype, np.integer) or np.issubdtype(frame.dtype, np.floating)):
        raise MRMLBridgeError(f"frame {name!r} must hold real numbers, got data type {frame.dtype}")
    try:
        spacing = tuple(float(v) for v in pixel_spacing_mm)
    except (TypeError, ValueError):
        spacing = ()
    if len(spacing) != 2 or not all(np.isfinite(v) and v > 0 for v in spacing):
        raise MRMLBridgeError(f"pixel_spacing_mm of frame {name!r} must be two positive numbers (row, column spacing "
                              f"in mm), got {pixel_spacing_mm!r}")
    return frame, spacing


def add_frame_volume_node(scene, frame: np.ndarray, name: str, pixel_spacing_mm: Sequence[float] = (1.0, 1.0),
                          class_name: str = "vtkMRMLScalarVolumeNode"):
    """A volume node with one slice holding a 2D frame (rows, cols), laid out as Slicer's DICOM
    module lays out XA frames (IJK→RAS = diag(−col spacing, −row spacing, 1)). Bad input adds no node."""
    frame, (row_spacing, col_spacing) = _checked_frame_layout(frame, name, pixel_spacing_mm)
    if class_name not in ("vtkMRMLScalarVolumeNode", "vtkMRMLLabelMapVolumeNode"):
        raise MRMLBridgeError(f"a frame is held by a vtkMRMLScalarVolumeNode or a vtkMRMLLabelMapVolumeNode, "
                              f"not {class_name!r}")
    with scene_transaction(scene):
        node = scene.AddNewNodeByClass(class_name, name)
        node.SetAndObserveImageData(_image_data(frame.T[:, :, None]))
        node.SetIJKToRASMatrix(_vtk_matrix(np.diag([-col_spacing, -row_spacing, 1.0, 1.0])))
        node.CreateDefaultDisplayNodes()
    return node


def _frame_labelmap(mask: np.ndarray, frame_node, segmentation_node):
    """vtkOrientedImageData of a 2D mask (rows, cols) laid on a frame volume node's pixels, in the
    segmentation node's own coordinates. The mask passes ``masks.binarise_mask``."""
    import vtk

    slicer = _slicer()
    frame = frame_from_volume_node(frame_node)
    try:
        mask = binarise_mask(mask, detector_shape=frame.shape, source=f"the mask for frame {frame_node.GetName()!r}")
    except MaskError as exc:
        raise MRMLBridgeError(str(exc)) from exc
    labelmap = slicer.vtkOrientedImageData()
    labelmap.ShallowCopy(_image_data(mask.T[:, :, None].astype(np.uint8), vtk.VTK_UNSIGNED_CHAR))
    image_to_segmentation = (np.linalg.inv(_local_to_world_matrix(segmentation_node))
                             @ _local_to_world_matrix(frame_node) @ _ijk_to_ras(frame_node))
    labelmap.SetImageToWorldMatrix(_vtk_matrix(image_to_segmentation))
    return labelmap


def set_segment_mask(segmentation_node, mask: np.ndarray, frame_node, segment_name: str = "Vessels",
                     color: Sequence[float] = (1.0, 0.3, 0.3)) -> str:
    """Replace (or add) the segment ``segment_name`` with a 2D mask (rows, cols) on a frame; return its ID.
    The mask must pass ``masks.binarise_mask`` (binary, finite, neither empty nor everything)."""
    slicer = _slicer()
    if segmentation_node.GetScene() is not None:
        prepare_scene(segmentation_node.GetScene())
    labelmap = _frame_labelmap(mask, frame_node, segmentation_node)
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
    for browser in nodes_by_class(scene, "vtkMRMLSequenceBrowserNode"):
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


#: the frame node's attribute that says how its grey levels were made (``FRAME_INTENSITY_VALUES``); it wins over
#: the DICOM file's tags, and over the rule that takes 8-bit frames nothing is known of as processed for display
FRAME_INTENSITY_ATTRIBUTE = ATTRIBUTE_PREFIX + "PixelIntensityRelationship"
#: what a user may say: linear in the detector's intensity (path lengths are read off it) or processed for display
FRAME_INTENSITY_VALUES = (LINEAR_INTENSITY, DISPLAY_INTENSITY)


def _intensity_value_problem(node, value) -> str:
    return (f"{node.GetName()}: its grey levels were said to be {value!r} ({FRAME_INTENSITY_ATTRIBUTE}); say "
            f"{' or '.join(FRAME_INTENSITY_VALUES)} (linear detector intensities, or processed for display), or "
            "nothing to use the DICOM file's tags")


def frame_intensity_said(node) -> Optional[str]:
    """What the user said of a frame node's grey levels: one of ``FRAME_INTENSITY_VALUES``, or None where
    nothing was said. Any other value is refused (MRMLBridgeError, a ValueError, naming the fix): a typo must not silently
    fall back to the file's tags."""
    said = node.GetAttribute(FRAME_INTENSITY_ATTRIBUTE) if node is not None else None
    if not said:
        return None
    value = said.strip().upper()
    if value not in FRAME_INTENSITY_VALUES:
        raise MRMLBridgeError(_intensity_value_problem(node, said))
    return value


def say_frame_intensity(node, relationship: Optional[str]) -> None:
    """Say what a frame node's grey levels are (one of ``FRAME_INTENSITY_VALUES``, any case), or nothing (None or
    ""): the DICOM file's tags decide again. A value of another kind is refused before the node is changed."""
    if node is None:
        raise MRMLBridgeError("no frame node: choose the view's frame first")
    value = str(relationship or "").strip().upper()
    if not value:
        node.RemoveAttribute(FRAME_INTENSITY_ATTRIBUTE)
        return
    if value not in FRAME_INTENSITY_VALUES:
        raise MRMLBridgeError(_intensity_value_problem(node, relationship))
    node.SetAttribute(FRAME_INTENSITY_ATTRIBUTE, value)
