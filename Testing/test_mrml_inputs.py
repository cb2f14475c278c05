"""What a Slicer-console user hands the MRML bridge by mistake, against the real MRML of slicer-core:
each is refused naming the problem, and the scene is left as it was; masks land where their frame lies."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

slicer = pytest.importorskip("slicer", reason="the MRML bridge tests need the slicer-core package (pip install slicer-core)")

from SDFCARLib import mrml  # noqa: E402


@pytest.fixture()
def scene():
    return mrml.new_scene()


def node_names(scene):
    return [scene.GetNthNode(i).GetName() for i in range(scene.GetNumberOfNodes())]


def l_mask(shape=(10, 12)):
    mask = np.zeros(shape, bool)
    mask[2:7, 3] = True
    mask[6, 3:9] = True
    return mask


# --- scene files --------------------------------------------------------------------------------------
def test_a_file_that_is_no_scene_is_refused_before_the_scene_is_cleared(scene, tmp_path):
    mrml.add_frame_volume_node(scene, np.ones((4, 4)), "my frame")
    before = node_names(scene)
    damaged = tmp_path / "damaged.mrml"
    damaged.write_text("<not xml")
    other_xml = tmp_path / "other.mrml"
    other_xml.write_text("<html><body/></html>")
    bundle = tmp_path / "empty.mrb"
    with zipfile.ZipFile(bundle, "w") as z:
        z.writestr("readme.txt", "no scene here")
    not_zip = tmp_path / "broken.mrb"
    not_zip.write_bytes(b"PK\x03\x04 broken")
    for path, expected in ((damaged, "not an XML file"), (other_xml, "root is <html>"), (bundle, "no .mrml scene"),
                           (not_zip, "not a Slicer scene bundle")):
        with pytest.raises(mrml.MRMLBridgeError, match=expected):
            mrml.load_scene(scene, path)
        assert node_names(scene) == before, path.name
    report = tmp_path / "report.json"
    report.write_text("{}")
    with pytest.raises(mrml.MRMLBridgeError, match=r"not a scene file: give a \.mrml scene or a \.mrb bundle"):
        mrml.load_scene(scene, report)
    assert node_names(scene) == before
    # a real scene still loads, replacing the content
    saved = mrml.save_scene(mrml.new_scene(), tmp_path / "saved.mrml")
    mrml.load_scene(scene, saved)
    assert "my frame" not in node_names(scene)


# --- masks from segmentations ---------------------------------------------------------------------------
def test_an_unpainted_segment_or_no_chosen_segment_is_refused_and_one_name_is_a_segment(scene):
    frame = mrml.add_frame_volume_node(scene, np.zeros((10, 12)), "frame", pixel_spacing_mm=(0.3, 0.2))
    seg = mrml.add_mask_segmentation_node(scene, l_mask(), frame, "vessels")
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg, frame, segments="Vessels"), l_mask())
    with pytest.raises(mrml.MRMLBridgeError, match="no segment of 'vessels' was chosen"):
        mrml.mask_from_segmentation_node(seg, frame, segments=[])
    seg.GetSegmentation().AddEmptySegment("Unpainted", "Unpainted", [0.0, 1.0, 0.0])  # what the module creates to paint in
    with pytest.raises(mrml.MRMLBridgeError, match=r"segment 'Unpainted'\) on frame 'frame': the mask is empty"):
        mrml.mask_from_segmentation_node(seg, frame, segments=["Unpainted"])
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg, frame), l_mask())  # the union


def test_a_mask_on_a_transformed_frame_lies_where_the_frame_lies(scene):
    frame = mrml.add_frame_volume_node(scene, np.zeros((10, 12)), "frame", pixel_spacing_mm=(0.5, 0.5))
    shift = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "table moved")
    shift.SetMatrixTransformToParent(mrml.scene._vtk_matrix(np.array(
        [[1, 0, 0, 3.0], [0, 1, 0, -2.0], [0, 0, 1, 5.0], [0, 0, 0, 1.0]])))
    frame.SetAndObserveTransformNodeID(shift.GetID())
    seg = mrml.add_mask_segmentation_node(scene, l_mask(), frame, "vessels")
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg, frame), l_mask())
    # pixel (row 6, col 8) at world RAS: the transform applied to IJK→RAS = diag(-0.5, -0.5, 1)
    world = np.array([-0.5 * 8 + 3.0, -0.5 * 6 - 2.0, 0.0 + 5.0])
    segment_id = seg.GetSegmentation().GetNthSegmentID(0)
    assert mrml.results._segment_mask_at_ras(seg, segment_id, world[None, :])[0]  # the segmentation has no transform
    assert not mrml.results._segment_mask_at_ras(seg, segment_id, np.array([[-4.0, -3.0, 0.0]]))[0]  # the untransformed place


def test_a_probability_map_or_a_nan_mask_is_no_segment(scene):
    frame = mrml.add_frame_volume_node(scene, np.zeros((10, 12)), "frame")
    probability = np.full((10, 12), 0.02)
    probability[2:5, 3:7] = 0.9
    before = node_names(scene)
    with pytest.raises(mrml.MRMLBridgeError, match=r"the mask for frame 'frame': the mask is not binary"):
        mrml.add_mask_segmentation_node(scene, probability, frame, "seg")
    with pytest.raises(mrml.MRMLBridgeError, match="NaN or infinite"):
        mrml.add_mask_segmentation_node(scene, np.where(probability > 0.5, 1.0, np.nan), frame, "seg")
    with pytest.raises(mrml.MRMLBridgeError, match="differs from the detector shape"):
        mrml.add_mask_segmentation_node(scene, l_mask((12, 10)), frame, "seg")
    assert node_names(scene) == before
    seg = mrml.add_mask_segmentation_node(scene, l_mask(), frame, "seg")
    with pytest.raises(mrml.MRMLBridgeError, match="the mask is empty"):
        mrml.set_segment_mask(seg, np.zeros((10, 12), bool), frame)
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg, frame), l_mask())  # the segment kept


# --- masks from volumes ---------------------------------------------------------------------------------
def test_a_labelmap_exported_cropped_is_placed_on_its_frame(scene):
    frame = mrml.add_frame_volume_node(scene, np.zeros((10, 12)), "frame", pixel_spacing_mm=(0.3, 0.2))
    seg = mrml.add_mask_segmentation_node(scene, l_mask(), frame, "seg")
    cropped = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "exported")
    assert slicer.vtkSlicerSegmentationsModuleLogic.ExportAllSegmentsToLabelmapNode(seg, cropped)
    assert cropped.GetImageData().GetDimensions()[:2] == (6, 5)  # cropped to the vessels: 5 rows × 6 columns
    np.testing.assert_array_equal(mrml.mask_from_volume_node(cropped, reference_volume_node=frame), l_mask())
    # a mask of the frame's size is the frame's pixel for pixel, whatever its spacing (an image file's is 1)
    from_file = mrml.add_frame_volume_node(scene, l_mask(), "mask.png", class_name="vtkMRMLLabelMapVolumeNode")
    np.testing.assert_array_equal(mrml.mask_from_volume_node(from_file, reference_volume_node=frame), l_mask())
    # another size on another grid is refused, naming both sizes
    other = mrml.add_frame_volume_node(scene, l_mask((8, 8)), "other", class_name="vtkMRMLLabelMapVolumeNode")
    with pytest.raises(mrml.MRMLBridgeError, match=r"'other' \(8 × 8 pixels\) is not the size of frame 'frame' \(10 × 12\)"):
        mrml.mask_from_volume_node(other, reference_volume_node=frame)
    # on the frame's grid but reaching beyond it
    larger = mrml.add_frame_volume_node(scene, l_mask((10, 14)) | np.eye(10, 14, 13, dtype=bool), "larger",
                                        pixel_spacing_mm=(0.3, 0.2), class_name="vtkMRMLLabelMapVolumeNode")
    with pytest.raises(mrml.MRMLBridgeError, match="1 of its non-zero pixels lie outside the frame"):
        mrml.mask_from_volume_node(larger, reference_volume_node=frame)


def test_nan_pixels_thresholds_and_slice_indices_of_the_wrong_kind_are_named(scene):
    image = np.where(l_mask(), 1.0, 0.0)
    image[0, 0] = np.nan
    node = mrml.add_frame_volume_node(scene, image, "nan mask")
    for threshold in (None, 0.5):
        with pytest.raises(mrml.MRMLBridgeError, match="'nan mask' has 1 NaN or infinite pixels"):
            mrml.mask_from_volume_node(node, threshold=threshold)
    grey = mrml.add_frame_volume_node(scene, np.arange(120.0).reshape(10, 12), "grey")
    for threshold in ("abc", float("nan"), True):
        with pytest.raises(mrml.MRMLBridgeError, match="threshold must be a finite number"):
            mrml.mask_from_volume_node(grey, threshold=threshold)
    with pytest.raises(mrml.MRMLBridgeError, match="not both"):
        mrml.mask_from_volume_node(grey, threshold=50, label=3)
    np.testing.assert_array_equal(mrml.mask_from_volume_node(grey, threshold=np.float32(100.0)),
                                  np.arange(120.0).reshape(10, 12) > 100)
    for index in (1.5, "2", True):
        with pytest.raises(mrml.MRMLBridgeError, match="slice index .* must be a whole number"):
            mrml.frame_from_volume_node(grey, index)


def test_a_frame_node_of_bad_input_is_not_added(scene):
    before = node_names(scene)
    for frame, spacing, class_name, expected in (
            (np.ones((4, 4)), (0.5,), "vtkMRMLScalarVolumeNode", "two positive numbers"),
            (np.ones((4, 4)), 0.3, "vtkMRMLScalarVolumeNode", "two positive numbers"),
            (np.ones((4, 4)), (0.0, 0.3), "vtkMRMLScalarVolumeNode", "two positive numbers"),
            (np.ones((0, 0)), (1.0, 1.0), "vtkMRMLScalarVolumeNode", "non-empty 2D array"),
            (np.ones((4, 4), complex), (1.0, 1.0), "vtkMRMLScalarVolumeNode", "real numbers, got data type complex128"),
            (np.ones((4, 4)), (1.0, 1.0), "vtkMRMLScalarVolumNode", "not 'vtkMRMLScalarVolumNode'")):
        with pytest.raises(mrml.MRMLBridgeError, match=expected):
            mrml.add_frame_volume_node(scene, frame, "f", pixel_spacing_mm=spacing, class_name=class_name)
    assert node_names(scene) == before


# --- results --------------------------------------------------------------------------------------------
def test_a_result_of_the_wrong_kind_is_refused_and_a_report_of_another_shape_read_as_far_as_it_goes(scene, tmp_path):
    import json

    from test_mrml import blob_result, small_geometry, snapshot, write_result_files

    geometry = small_geometry()
    before = snapshot(scene)
    for values in (np.where(blob_result(geometry).segmentation, 0.9, 0.02), np.where(blob_result(geometry).segmentation,
                                                                                      1.0, np.nan)):
        result = blob_result(geometry)
        result.segmentation = values
        with pytest.raises(mrml.MRMLBridgeError, match="the mask (is not binary|contains NaN)"):
            mrml.add_reconstruction_to_scene(scene, result, "Probabilities")
        assert snapshot(scene) == before
    listed = blob_result(geometry, report=[1, 2])
    with pytest.raises(mrml.MRMLBridgeError, match="report must be a JSON object, got list"):
        mrml.add_reconstruction_to_scene(scene, listed, "Listed")
    assert snapshot(scene) == before
    # a hand-edited report: the sections of another kind are left out, the rest kept
    edited = blob_result(geometry, report={"settings": "fast", "final_losses": [0.1], "ensemble_choice": "x",
                                           "versions": "1.0", "method": "SDF-CAR"})
    nodes = mrml.add_reconstruction_to_scene(scene, edited, "Edited")
    provenance = mrml.node_provenance(nodes.segmentation)
    assert provenance["method"] == "SDF-CAR" and "preset" not in provenance and "finalLoss" not in provenance
    # report.json in another encoding
    folder = tmp_path / "result"
    folder.mkdir()
    write_result_files(folder, geometry, blob_result(geometry))
    (folder / "report.json").write_text(json.dumps({"method": "SDF-CAR"}), encoding="utf-16")
    before = snapshot(scene)
    with pytest.raises(mrml.MRMLBridgeError, match="cannot read the report"):
        mrml.add_reconstruction_to_scene(scene, folder, "UTF-16")
    assert snapshot(scene) == before


def test_a_result_file_whose_first_segment_was_emptied_shows_the_segment_with_voxels(scene, tmp_path):
    from test_mrml import blob_result, small_geometry, write_result_files

    geometry = small_geometry()
    result = blob_result(geometry)
    folder = tmp_path / "result"
    folder.mkdir()
    seg_path, _, _ = write_result_files(folder, geometry, result)
    edit = mrml.new_scene()
    seg = mrml.add_reconstruction_to_scene(edit, folder, "edit").segmentation
    seg.GetSegmentation().AddEmptySegment("notes", "notes", [0.0, 1.0, 0.0])
    segmentation = seg.GetSegmentation()
    first = segmentation.GetNthSegmentID(0)
    # the tree moved to a second segment, the first left empty (as a user's edit in Slicer may leave it)
    copied = segmentation.GetNthSegmentID(1)
    labelmap = mrml.results._oriented_labelmap(result.segmentation, geometry.volume)
    assert slicer.vtkSlicerSegmentationsModuleLogic.SetBinaryLabelmapToSegment(
        labelmap, seg, copied, slicer.vtkSlicerSegmentationsModuleLogic.MODE_REPLACE)
    empty = mrml.results._oriented_labelmap(np.zeros(geometry.volume.shape, bool), geometry.volume)
    assert slicer.vtkSlicerSegmentationsModuleLogic.SetBinaryLabelmapToSegment(
        empty, seg, first, slicer.vtkSlicerSegmentationsModuleLogic.MODE_REPLACE)
    storage = slicer.vtkMRMLSegmentationStorageNode()
    storage.SetFileName(str(seg_path))
    assert storage.WriteData(seg)
    nodes = mrml.add_reconstruction_to_scene(scene, folder, "Edited")
    assert nodes.segment_id == copied
    np.testing.assert_array_equal(mrml.segmentation_mask_lps(nodes.segmentation, geometry.volume, nodes.segment_id),
                                  result.segmentation)


def test_result_sources_and_c_arm_options_of_the_wrong_kind_are_named(scene, tmp_path):
    from test_mrml import small_geometry, snapshot

    before = snapshot(scene)
    a_file = tmp_path / "segmentation.seg.nrrd"
    a_file.write_text("x")
    with pytest.raises(mrml.MRMLBridgeError, match="is a file; give the reconstruction's output folder"):
        mrml.add_reconstruction_to_scene(scene, a_file, "x")
    with pytest.raises(mrml.MRMLBridgeError, match="unknown result file key.*occupnacy"):
        mrml.add_reconstruction_to_scene(scene, {"segmentation": a_file, "occupnacy": a_file}, "x")
    with pytest.raises(mrml.MRMLBridgeError, match="no result given"):
        mrml.add_reconstruction_to_scene(scene, None, "x")
    geometry = small_geometry()
    for points in (0, 1, 2.5, True):
        with pytest.raises(mrml.MRMLBridgeError, match="max_points_per_side must be a whole number of 2 or more"):
            mrml.add_carm_geometry_to_scene(scene, geometry, max_points_per_side=points)
    frame = np.zeros((64, 80), np.float32)
    frame[3, 4] = np.nan
    with pytest.raises(mrml.MRMLBridgeError, match="1 NaN or infinite pixels"):
        mrml.add_carm_geometry_to_scene(scene, geometry, images=[frame, None], image_display="texture")
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "not an image")
    before_seg = snapshot(scene)
    with pytest.raises(mrml.MRMLBridgeError, match="the image of view 1 is a vtkMRMLSegmentationNode"):
        mrml.add_carm_geometry_to_scene(scene, geometry, images=[seg, None])
    assert snapshot(scene) == before_seg
    scene.RemoveNode(seg)
    assert snapshot(scene) == before
    with pytest.raises(mrml.MRMLBridgeError, match="grey levels were said to be 'linear'"):
        mrml.say_frame_intensity(mrml.add_frame_volume_node(scene, np.ones((4, 4)), "f"), "linear")


def test_an_occupancy_asked_of_a_folder_without_one_is_named(scene, tmp_path):
    from test_mrml import blob_result, small_geometry, snapshot, write_result_files

    geometry = small_geometry()
    write_result_files(tmp_path, geometry, blob_result(geometry))
    (tmp_path / "occupancy.nrrd").unlink()
    before = snapshot(scene)
    with pytest.raises(mrml.MRMLBridgeError, match="the occupancy was asked for but the result has no occupancy.nrrd"):
        mrml.add_reconstruction_to_scene(scene, tmp_path, "No occupancy", include_occupancy=True)
    assert snapshot(scene) == before
    assert mrml.add_reconstruction_to_scene(scene, tmp_path, "Without", include_occupancy=False).occupancy is None


def test_a_damaged_bundle_and_a_full_size_mask_on_a_warped_frame(scene, tmp_path):
    import vtk

    bundle = tmp_path / "bundle.mrb"
    with zipfile.ZipFile(bundle, "w", zipfile.ZIP_DEFLATED) as z:  # a deflated scene: damage is a zlib error
        z.writestr("bundle/bundle.mrml", '<MRML version="Slicer 5.0.0 1">' + '<Selection id="s"/>' * 200 + "</MRML>")
    data = bytearray(bundle.read_bytes())
    with zipfile.ZipFile(bundle) as z:
        info = z.infolist()[0]
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    for k in range(start, start + 20):  # the compressed scene's first bytes; the zip's directory kept
        data[k] ^= 0x5A
    damaged = tmp_path / "damaged.mrb"
    damaged.write_bytes(bytes(data))
    before = node_names(scene)
    with pytest.raises(mrml.MRMLBridgeError, match="the bundle is damaged: its scene cannot be unpacked"):
        mrml.load_scene(scene, damaged)
    assert node_names(scene) == before
    # a mask of the frame's size is the frame's pixel for pixel, whatever transform the frame is under
    frame = mrml.add_frame_volume_node(scene, np.zeros((10, 12)), "frame")
    warp = scene.AddNewNodeByClass("vtkMRMLTransformNode", "warp")
    spline = vtk.vtkThinPlateSplineTransform()
    source, target = vtk.vtkPoints(), vtk.vtkPoints()
    for p in ((0, 0, 0), (10, 0, 0), (0, 10, 0), (0, 0, 10)):
        source.InsertNextPoint(p)
        target.InsertNextPoint(p[0] + 1.0, p[1], p[2])
    spline.SetSourceLandmarks(source)
    spline.SetTargetLandmarks(target)
    spline.SetBasisToR()
    warp.SetAndObserveTransformToParent(spline)
    frame.SetAndObserveTransformNodeID(warp.GetID())
    label = mrml.add_frame_volume_node(scene, l_mask(), "mask", class_name="vtkMRMLLabelMapVolumeNode")
    np.testing.assert_array_equal(mrml.mask_from_volume_node(label, reference_volume_node=frame), l_mask())
    with pytest.raises(mrml.MRMLBridgeError, match="non-linear transform 'warp'.*Harden transform"):
        mrml.add_mask_segmentation_node(scene, l_mask(), frame, "seg")


def test_a_0_255_result_segmentation_is_a_segmentation(scene):
    from test_mrml import blob_result, small_geometry

    result = blob_result(small_geometry())
    result.segmentation = result.segmentation.astype(np.uint8) * 255
    nodes = mrml.add_reconstruction_to_scene(scene, result, "0-255")
    assert mrml.segmentation_mask_lps(nodes.segmentation, small_geometry().volume).sum() == 27
