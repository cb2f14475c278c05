"""MRML bridge: SDFCAR results, C-arm set-ups and input frames as 3D Slicer scene content.

Every function takes the scene as an argument, so the same code serves Slicer's
``slicer.mrmlScene`` and a bare ``vtkMRMLScene`` of the ``slicer-core`` package (headless tests,
scripts). ``slicer`` and ``vtk`` are imported inside the functions only: importing this package
needs neither.

Modules (every public name is re-exported here, so ``mrml.X`` works for all of them)
    ``scene``    LPS↔RAS coordinates, VTK matrix/image helpers, scene set-up, transactions, node
                 look-up, ``SDFCAR.*`` provenance attributes, saving and loading scenes
    ``results``  result nodes (segmentation, surface, occupancy), ``add_reconstruction_to_scene``,
                 ``write_result_scene``, reading a segment back on an LPS grid
    ``inputs``   frames and masks from volume, segmentation and sequence nodes; DICOM references
    ``carm``     the C-arm set-up drawn in 3D (sources, detectors with their frames, beams)
    ``parameter_views``  the Slicer module's views 3, 4, … in its parameter node
    ``qa_overlays``  a result's reprojection-QA overlays (qa_view<n>.png) as colour volumes
"""

from __future__ import annotations

from ..outputs import RESULT_FILES
from .carm import (VIEW_COLORS, CArmNodes, add_carm_geometry_to_scene, beam_polydata,
                   detector_image_polydata)
from .inputs import (FRAME_INTENSITY_ATTRIBUTE, FRAME_INTENSITY_VALUES, add_frame_volume_node,
                     add_mask_segmentation_node, dicom_frame_reference, dicom_instance_uid, frame_from_sequence,
                     frame_from_volume_node, frame_intensity_said, mask_from_segmentation_node, mask_from_volume_node,
                     say_frame_intensity, sequence_frame_node, sequence_of_proxy_node, set_segment_mask)
from .parameter_views import (FIRST_STORED_VIEW, MAX_VIEWS, VIEW_FIELDS, VIEW_NODE_FIELDS, VIEW_VALUE_FIELDS,
                              ViewParameters, add_view, get_view, get_view_value, remove_view, set_view_count,
                              set_view_value, view_count)
from .qa_overlays import add_qa_overlays_to_scene, qa_overlay_files, qa_overlay_nodes, read_report, read_rgb_png
from .results import (SEGMENT_COLOR, SEGMENT_NAME, ResultNodes, _oriented_labelmap, _segment_labelmap,
                      add_model_node, add_reconstruction_to_scene, add_segmentation_node, add_volume_node, result_folder_of,
                      segment_contains_lps, segmentation_mask_lps, segmentation_surface, write_result_scene)
from .scene import (ATTRIBUTE_PREFIX, LPS_TO_RAS, SCENE_FILE_VERSION, MRMLBridgeError, PathLike, _image_data,
                    _numpy_matrix, _slicer, _vtk_matrix, ijk_to_ras_matrix, load_scene, lps_to_ras, new_scene,
                    node_provenance, nodes_by_class, prepare_scene, provenance_attributes, ras_to_lps,
                    remove_nodes_added_since, save_scene, scene_transaction)

__all__ = [
    # scene
    "ATTRIBUTE_PREFIX", "LPS_TO_RAS", "SCENE_FILE_VERSION", "MRMLBridgeError", "PathLike", "ijk_to_ras_matrix",
    "load_scene", "lps_to_ras", "new_scene", "node_provenance", "nodes_by_class", "prepare_scene",
    "provenance_attributes", "ras_to_lps", "remove_nodes_added_since", "save_scene", "scene_transaction",
    # results
    "RESULT_FILES", "SEGMENT_COLOR", "SEGMENT_NAME", "ResultNodes", "add_model_node", "add_reconstruction_to_scene",
    "add_segmentation_node", "add_volume_node", "segment_contains_lps", "segmentation_mask_lps",
    "result_folder_of", "segmentation_surface", "write_result_scene",
    # inputs
    "FRAME_INTENSITY_ATTRIBUTE", "FRAME_INTENSITY_VALUES", "frame_intensity_said", "say_frame_intensity",
    "add_frame_volume_node", "add_mask_segmentation_node", "dicom_frame_reference", "dicom_instance_uid",
    "frame_from_sequence", "frame_from_volume_node", "mask_from_segmentation_node", "mask_from_volume_node",
    "sequence_frame_node", "sequence_of_proxy_node", "set_segment_mask",
    # carm
    "VIEW_COLORS", "CArmNodes", "add_carm_geometry_to_scene", "beam_polydata", "detector_image_polydata",
    # parameter_views
    "FIRST_STORED_VIEW", "MAX_VIEWS", "VIEW_FIELDS", "VIEW_NODE_FIELDS", "VIEW_VALUE_FIELDS", "ViewParameters",
    "add_view", "get_view", "get_view_value", "remove_view", "set_view_count", "set_view_value", "view_count",
    # qa_overlays
    "add_qa_overlays_to_scene", "qa_overlay_files", "qa_overlay_nodes", "read_report", "read_rgb_png",
]
