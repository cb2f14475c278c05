"""MRML bridge against the real MRML of the slicer-core package (headless).

What a Slicer user relies on: results and C-arm set-ups sit at the right RAS place (LPS x, y
flipped), provenance travels with the nodes, scenes survive .mrml/.mrb save and reload, frames and
masks are read from volumes, segmentations and sequences pixel-exactly, and a failing add leaves
the scene exactly as it was.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

slicer = pytest.importorskip("slicer", reason="the MRML bridge tests need the slicer-core package (pip install slicer-core)")

from SDFCARLib import mrml  # noqa: E402
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid  # noqa: E402
from SDFCARLib.masks import MaskError  # noqa: E402
from SDFCARLib.optimiser import Reconstruction  # noqa: E402
from SDFCARLib.settings import make_settings  # noqa: E402


# --- fixtures ---------------------------------------------------------------------------------------
def small_geometry() -> Geometry:
    # Off-centre grid with unequal spacing and shape: a swapped axis or a missing flip shows.
    grid = VolumeGrid((12, 14, 16), (1.0, 1.25, 1.5), (6.0, -9.0, 4.0))
    views = (
        CArmView(30.0, 0.0, 1000.0, 750.0, (2.0, 2.0), (64, 80)),
        CArmView(-20.0, 25.0, 1000.0, 750.0, (2.0, 2.0), (64, 80)),
    )
    return Geometry(grid, views)


BLOB_CENTRE = (4, 9, 5)  # voxel index of the blob's centre


def blob_result(geometry: Geometry, report=None) -> Reconstruction:
    grid = geometry.volume
    seg = np.zeros(grid.shape, dtype=bool)
    i, j, k = BLOB_CENTRE
    seg[i - 1:i + 2, j - 1:j + 2, k - 1:k + 2] = True
    occupancy = np.where(seg, 0.9, 0.05).astype(np.float32)
    settings = make_settings("fast", steps=7, seed=3)
    report = report if report is not None else {
        "settings": settings.to_dict(), "seed": 3, "method": "SDF-CAR",
        "final_losses": {"loss": 0.125, "l_occ": 0.25, "l_geo": 0.0625},
        "versions": {"sdfcar": "test", "torch": "x"}, "geometry_digest": geometry.digest(),
        "geometry": geometry.to_dict(), "reprojection_dice": [0.5, 0.75],
    }
    return Reconstruction(geometry, settings, occupancy, occupancy * 2 - 1, seg, None, report)


def snapshot(scene):
    """Everything a user could see of a scene's node list."""
    return [(n.GetID(), n.GetClassName(), n.GetName()) for n in (scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes()))]


@pytest.fixture()
def scene():
    return mrml.new_scene()


# --- coordinates -----------------------------------------------------------------------------------
def test_lps_to_ras_flips_x_and_y_only():
    np.testing.assert_array_equal(mrml.lps_to_ras([1.0, 2.0, 3.0]), [-1.0, -2.0, 3.0])
    pts = np.arange(12.0).reshape(2, 2, 3)
    np.testing.assert_array_equal(mrml.ras_to_lps(mrml.lps_to_ras(pts)), pts)
    with pytest.raises(mrml.MRMLBridgeError, match="3 coordinates"):
        mrml.lps_to_ras([1.0, 2.0])


def test_ijk_to_ras_matrix_maps_voxel_centres():
    grid = small_geometry().volume
    m = mrml.ijk_to_ras_matrix(grid)
    ijk = np.array([[0, 0, 0], [11, 13, 15], [3, 7, 2]], float)
    ras = ijk @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(ras, mrml.lps_to_ras(grid.index_to_world(ijk)))


# --- results ---------------------------------------------------------------------------------------
def test_result_segmentation_and_model_are_at_ras_of_lps(scene):
    geometry = small_geometry()
    grid = geometry.volume
    nodes = mrml.add_reconstruction_to_scene(scene, blob_result(geometry), "Case A", include_occupancy=True)
    assert nodes.segmentation.IsA("vtkMRMLSegmentationNode") and nodes.segmentation.GetName() == "Case A"
    assert nodes.model.IsA("vtkMRMLModelNode") and nodes.model.GetName() == "Case A surface"
    assert nodes.occupancy.IsA("vtkMRMLScalarVolumeNode") and nodes.occupancy.GetName() == "Case A occupancy"
    segmentation = nodes.segmentation.GetSegmentation()
    assert segmentation.GetNumberOfSegments() == 1
    assert segmentation.GetSegment(nodes.segment_id).GetName() == "Coronary tree"
    assert segmentation.GetSourceRepresentationName() == "Binary labelmap"
    assert segmentation.ContainsRepresentation("Closed surface")

    x, y, z = grid.index_to_world(BLOB_CENTRE)
    # The voxel at LPS (x, y, z) is in the segment at RAS (-x, -y, z) ...
    ras_to_ijk = np.linalg.inv(mrml._segment_labelmap(nodes.segmentation, None)[1])
    ijk = ras_to_ijk[:3, :3] @ np.array([-x, -y, z]) + ras_to_ijk[:3, 3]
    np.testing.assert_allclose(ijk, BLOB_CENTRE, atol=1e-9)
    assert mrml.segment_contains_lps(nodes.segmentation, [[x, y, z]]).all()
    # ... and a point 3 voxels away along x is not (a sign error would put the blob there).
    assert not mrml.segment_contains_lps(nodes.segmentation, [[x + 3 * grid.spacing_mm[0], y, z]]).any()
    np.testing.assert_array_equal(mrml.segmentation_mask_lps(nodes.segmentation, grid), blob_result(geometry).segmentation)

    # The surface model encloses the blob around RAS (-x, -y, z).
    from vtk.util.numpy_support import vtk_to_numpy
    points = vtk_to_numpy(nodes.model.GetPolyData().GetPoints().GetData())
    assert len(points) > 20
    np.testing.assert_allclose(points.mean(axis=0), [-x, -y, z], atol=0.3)
    half = 1.5 * np.asarray(grid.spacing_mm)
    assert np.all(points.min(axis=0) >= np.array([-x, -y, z]) - half - 0.3)
    assert np.all(points.max(axis=0) <= np.array([-x, -y, z]) + half + 0.3)

    # Occupancy: same IJK->RAS as the grid, values at [i, j, k].
    import vtk
    matrix = vtk.vtkMatrix4x4()
    nodes.occupancy.GetIJKToRASMatrix(matrix)
    np.testing.assert_allclose(mrml._numpy_matrix(matrix), mrml.ijk_to_ras_matrix(grid))
    from vtk.util.numpy_support import vtk_to_numpy as v2n
    kji = v2n(nodes.occupancy.GetImageData().GetPointData().GetScalars()).reshape(grid.shape[::-1])
    assert kji[BLOB_CENTRE[2], BLOB_CENTRE[1], BLOB_CENTRE[0]] == pytest.approx(0.9)
    assert kji[0, 0, 0] == pytest.approx(0.05)


def test_result_provenance_attributes(scene):
    geometry = small_geometry()
    nodes = mrml.add_reconstruction_to_scene(scene, blob_result(geometry), "Case A", attributes={"input": "run 7"})
    for node in nodes.nodes:
        p = mrml.node_provenance(node)
        assert p["preset"] == "fast" and p["mode"] == "sdfcar"
        assert p["seed"] == "3" and p["steps"] == "7"
        assert float(p["finalLoss"]) == 0.125 and float(p["finalLossOcc"]) == 0.25 and float(p["finalLossGeo"]) == 0.0625
        assert json.loads(p["versions"]) == {"sdfcar": "test", "torch": "x"}
        assert p["geometryDigest"] == geometry.digest()
        assert Geometry.from_dict(json.loads(p["geometry"])) == geometry
        assert p["input"] == "run 7"
        assert "keptFitSeed" not in p  # one fit
    assert mrml.node_provenance(nodes.segmentation)["role"] == "segmentation"
    chosen = blob_result(geometry)
    chosen.report["ensemble_choice"] = {"combine": "best_reprojection", "seeds": [3, 4, 5], "chosen_fit": 1, "chosen_seed": 4,
                                        "reprojection_dice": [[0.9, 0.9], [0.95, 0.94], [0.8, 0.9]]}
    nodes = mrml.add_reconstruction_to_scene(scene, chosen, "Case B")
    assert mrml.node_provenance(nodes.segmentation)["keptFitSeed"] == "4"
    assert mrml.node_provenance(nodes.segmentation)["seed"] == "3"  # the run's, which reproduces it
    assert mrml.node_provenance(nodes.model)["role"] == "surface"


def test_failing_add_leaves_scene_exactly_as_before(scene, monkeypatch):
    geometry = small_geometry()
    mrml.add_reconstruction_to_scene(scene, blob_result(geometry), "earlier result")
    before = snapshot(scene)

    # Fails after the segmentation node exists: it must go again.
    def broken(*args, **kwargs):
        raise RuntimeError("surface extraction failed")
    monkeypatch.setattr(mrml.results, "segmentation_surface", broken)  # where add_reconstruction_to_scene looks it up
    with pytest.raises(RuntimeError, match="surface extraction failed"):
        mrml.add_reconstruction_to_scene(scene, blob_result(geometry), "Case B", include_occupancy=True)
    assert snapshot(scene) == before
    monkeypatch.undo()

    # An empty result is refused with a clear message, nothing added.
    empty = blob_result(geometry)
    empty.segmentation[:] = False
    with pytest.raises(mrml.MRMLBridgeError, match="no voxel"):
        mrml.add_reconstruction_to_scene(scene, empty, "Case C")
    assert snapshot(scene) == before

    # A C-arm display with a wrong image count adds nothing either.
    with pytest.raises(mrml.MRMLBridgeError, match="one per view"):
        mrml.add_carm_geometry_to_scene(scene, geometry, images=[None])
    assert snapshot(scene) == before


def write_result_files(tmp_path: Path, geometry: Geometry, result: Reconstruction):
    """A result folder as outputs.write_reconstruction writes it (seg.nrrd, LPS surface .vtk, report)."""
    from vtk.util.numpy_support import vtk_to_numpy

    work = mrml.new_scene()
    nodes = mrml.add_reconstruction_to_scene(work, result, "tmp", include_occupancy=True)
    seg_path = tmp_path / "segmentation.seg.nrrd"
    storage = slicer.vtkMRMLSegmentationStorageNode()
    storage.SetFileName(str(seg_path))
    assert storage.WriteData(nodes.segmentation)
    # Surface in LPS with Slicer's "SPACE=LPS" header, like io.write_surface_vtk.
    surface_path = tmp_path / "surface.vtk"
    model_storage = slicer.vtkMRMLModelStorageNode()
    model_storage.SetCoordinateSystem(slicer.vtkMRMLStorageNode.CoordinateSystemLPS)
    model_storage.SetFileName(str(surface_path))
    assert model_storage.WriteData(nodes.model)
    occupancy_path = tmp_path / "occupancy.nrrd"
    volume_storage = slicer.vtkMRMLVolumeArchetypeStorageNode()
    volume_storage.SetFileName(str(occupancy_path))
    assert volume_storage.WriteData(nodes.occupancy)
    (tmp_path / "report.json").write_text(json.dumps(result.report))
    assert "SPACE=LPS" in surface_path.read_bytes()[:300].decode("latin-1")
    ras_points = vtk_to_numpy(nodes.model.GetPolyData().GetPoints().GetData()).copy()
    return seg_path, surface_path, ras_points


def test_result_from_files_is_at_the_same_place(scene, tmp_path):
    geometry = small_geometry()
    result = blob_result(geometry)
    seg_path, surface_path, ras_points = write_result_files(tmp_path, geometry, result)
    nodes = mrml.add_reconstruction_to_scene(scene, tmp_path, "From files", include_occupancy=True)
    np.testing.assert_array_equal(mrml.segmentation_mask_lps(nodes.segmentation, geometry.volume), result.segmentation)
    from vtk.util.numpy_support import vtk_to_numpy
    np.testing.assert_allclose(vtk_to_numpy(nodes.model.GetPolyData().GetPoints().GetData()), ras_points, atol=1e-4)
    assert nodes.occupancy is not None
    assert mrml.node_provenance(nodes.model)["geometryDigest"] == geometry.digest()

    # A damaged surface file: the error names it and the scene is unchanged.
    before = snapshot(scene)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "segmentation.seg.nrrd").write_bytes(seg_path.read_bytes())
    (bad / "surface.vtk").write_text("not a vtk file\n")
    with pytest.raises(mrml.MRMLBridgeError, match="surface"):
        mrml.add_reconstruction_to_scene(scene, bad, "Broken", surface_from="file")
    assert snapshot(scene) == before
    with pytest.raises(mrml.MRMLBridgeError, match="does not exist"):
        mrml.add_reconstruction_to_scene(scene, tmp_path / "nothing-here", "x")
    (tmp_path / "empty").mkdir()
    with pytest.raises(mrml.MRMLBridgeError, match="segmentation.seg.nrrd"):
        mrml.add_reconstruction_to_scene(scene, tmp_path / "empty", "x")
    assert snapshot(scene) == before


# --- scene file of a written result --------------------------------------------------------------------
def test_write_result_scene_opens_at_the_right_place(tmp_path):
    geometry = small_geometry()
    result = blob_result(geometry)
    seg_path, surface_path, ras_points = write_result_files(tmp_path, geometry, result)
    path = mrml.write_result_scene(tmp_path, "Patient 1", geometry, seg_path.name, surface_path,
                                   {"preset": "fast", "finalLoss": 0.5})
    assert path == (tmp_path / "scene.mrml").resolve() and path.is_file()
    # Data files are referenced relative to the scene, so the folder can be moved.
    root = ET.parse(path).getroot()
    names = [e.get("fileName") for e in root.iter() if e.get("fileName")]
    assert sorted(names) == ["segmentation.seg.nrrd", "surface.vtk"]
    # Slicer warns about scenes "saved with another application": the file must say Slicer.
    assert root.get("version").startswith("Slicer ")

    moved = tmp_path.parent / (tmp_path.name + "-moved")
    tmp_path.rename(moved)
    loaded = mrml.load_scene(mrml.new_scene(), moved / "scene.mrml")
    seg = loaded.GetFirstNodeByName("Patient 1")
    model = loaded.GetFirstNodeByName("Patient 1 surface")
    assert seg.IsA("vtkMRMLSegmentationNode") and model.IsA("vtkMRMLModelNode")
    for node in (seg, model):
        p = mrml.node_provenance(node)
        assert p["preset"] == "fast" and float(p["finalLoss"]) == 0.5 and p["geometryDigest"] == geometry.digest()
    np.testing.assert_array_equal(mrml.segmentation_mask_lps(seg, geometry.volume), result.segmentation)
    from vtk.util.numpy_support import vtk_to_numpy
    np.testing.assert_allclose(vtk_to_numpy(model.GetPolyData().GetPoints().GetData()), ras_points, atol=1e-4)


def test_write_result_scene_refuses_missing_files(tmp_path):
    with pytest.raises(mrml.MRMLBridgeError, match="does not exist"):
        mrml.write_result_scene(tmp_path, "x", small_geometry(), "segmentation.seg.nrrd", None, {})
    assert list(tmp_path.iterdir()) == []


# --- save and reload -----------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".mrml", ".mrb"])
def test_scene_survives_save_and_reload(scene, tmp_path, suffix):
    geometry = small_geometry()
    result = blob_result(geometry)
    nodes = mrml.add_reconstruction_to_scene(scene, result, "Saved case", include_occupancy=True)
    frame = np.zeros((64, 80), np.float32)
    frame[10, 20] = 5.0
    carm = mrml.add_carm_geometry_to_scene(scene, geometry, images=[frame, None])
    expected = {}
    for node in nodes.nodes + carm.nodes:
        expected[node.GetName()] = (node.GetClassName(), mrml.node_provenance(node))
    model_points = nodes.model.GetPolyData().GetNumberOfPoints()
    detector_points = carm.detectors[0].GetPolyData().GetNumberOfPoints()

    path = mrml.save_scene(scene, tmp_path / ("saved" + suffix))
    loaded = mrml.load_scene(mrml.new_scene(), path)
    for name, (class_name, attributes) in expected.items():
        node = loaded.GetFirstNodeByName(name)
        assert node is not None, name
        assert node.GetClassName() == class_name
        assert mrml.node_provenance(node) == attributes
    seg = loaded.GetFirstNodeByName("Saved case")
    assert seg.GetSegmentation().GetNthSegment(0).GetName() == "Coronary tree"
    back = mrml.segmentation_mask_lps(seg, geometry.volume)
    assert back.sum() == result.segmentation.sum() == 27
    np.testing.assert_array_equal(back, result.segmentation)
    assert loaded.GetFirstNodeByName("Saved case surface").GetPolyData().GetNumberOfPoints() == model_points
    detector = loaded.GetFirstNodeByName("C-arm view 1 detector").GetPolyData()
    assert detector.GetNumberOfPoints() == detector_points
    assert detector.GetPointData().GetArray("frame").GetRange() == (0.0, 5.0)
    sources = loaded.GetFirstNodeByName("C-arm sources")
    np.testing.assert_allclose(sources.GetNthControlPointPosition(1), mrml.lps_to_ras(geometry.views[1].source_position), atol=1e-6)


def test_save_scene_refuses_other_formats(scene, tmp_path):
    with pytest.raises(mrml.MRMLBridgeError, match=".mrml or .mrb"):
        mrml.save_scene(scene, tmp_path / "scene.json")
    with pytest.raises(mrml.MRMLBridgeError, match="does not exist"):
        mrml.save_scene(scene, tmp_path / "missing" / "scene.mrml")


# --- C-arm set-up ----------------------------------------------------------------------------------------
def test_carm_geometry_places_source_detector_and_image(scene):
    from vtk.util.numpy_support import vtk_to_numpy

    geometry = small_geometry()
    image = np.zeros((64, 80), np.float32)
    image[5, 70] = 1.0  # top right: a flipped row or column axis moves it
    carm = mrml.add_carm_geometry_to_scene(scene, geometry, images=[image, None], name="Set-up")
    assert carm.sources.GetNumberOfControlPoints() == 2
    for n, view in enumerate(geometry.views):
        np.testing.assert_allclose(carm.sources.GetNthControlPointPosition(n), mrml.lps_to_ras(view.source_position), atol=1e-9)
        assert view.describe() in carm.sources.GetNthControlPointLabel(n)
    # Plain detector: its corners are the detector's outer corners.
    view = geometry.views[1]
    corners = vtk_to_numpy(carm.detectors[1].GetPolyData().GetPoints().GetData())
    rows, cols = view.detector_shape
    expected = view.pixel_to_world(np.array([-0.5, -0.5, rows - 0.5, rows - 0.5]), np.array([-0.5, cols - 0.5, cols - 0.5, -0.5]))
    np.testing.assert_allclose(corners, mrml.lps_to_ras(expected), atol=1e-9)
    # Image plane: the bright pixel's point is at the pixel's world position.
    poly = carm.detectors[0].GetPolyData()
    values = vtk_to_numpy(poly.GetPointData().GetArray("frame"))
    points = vtk_to_numpy(poly.GetPoints().GetData())
    np.testing.assert_allclose(points[np.argmax(values)], mrml.lps_to_ras(geometry.views[0].pixel_to_world(5, 70)), atol=1e-9)
    assert carm.detectors[0].GetDisplayNode().GetScalarVisibility()
    # Beams start at the source.
    beam = vtk_to_numpy(carm.beams[0].GetPolyData().GetPoints().GetData())
    np.testing.assert_allclose(beam[0], mrml.lps_to_ras(geometry.views[0].source_position))
    np.testing.assert_allclose(beam[-1], mrml.lps_to_ras(geometry.views[0].detector_center))


def test_carm_texture_uses_the_frame_volume(scene):
    geometry = small_geometry()
    frame = np.arange(64 * 80, dtype=np.float32).reshape(64, 80)
    node = mrml.add_frame_volume_node(scene, frame, "frame 1")
    carm = mrml.add_carm_geometry_to_scene(scene, geometry, images=[node, frame], image_display="texture")
    display = carm.detectors[0].GetDisplayNode()
    assert display.GetTextureImageDataConnection() is not None
    assert display.GetTextureImageDataConnection().GetProducer() is node.GetImageDataConnection().GetProducer()
    assert not display.GetScalarVisibility()
    assert carm.detectors[1].GetDisplayNode().GetTextureImageDataConnection() is not None
    with pytest.raises(mrml.MRMLBridgeError, match="image_display"):
        mrml.add_carm_geometry_to_scene(scene, geometry, image_display="photo")


# --- inputs -----------------------------------------------------------------------------------------------
def test_frame_and_mask_from_volume_nodes(scene):
    frame = np.arange(30 * 40, dtype=np.float32).reshape(30, 40)
    node = mrml.add_frame_volume_node(scene, frame, "frame", pixel_spacing_mm=(0.3, 0.2))
    np.testing.assert_array_equal(mrml.frame_from_volume_node(node), frame)
    assert node.GetSpacing() == pytest.approx((0.2, 0.3, 1.0))
    mask = np.zeros((30, 40), bool)
    mask[3:7, 30:35] = True
    label = mrml.add_frame_volume_node(scene, mask, "mask", class_name="vtkMRMLLabelMapVolumeNode")
    np.testing.assert_array_equal(mrml.mask_from_volume_node(label), mask)
    two_valued = mrml.add_frame_volume_node(scene, mask * 255.0, "mask as image")
    np.testing.assert_array_equal(mrml.mask_from_volume_node(two_valued), mask)
    np.testing.assert_array_equal(mrml.mask_from_volume_node(node, threshold=600), frame > 600)
    with pytest.raises(mrml.MRMLBridgeError, match="not a mask"):
        mrml.mask_from_volume_node(node)


def test_masks_from_volume_nodes_follow_the_one_mask_rule(scene):
    # masks.binarise_mask decides, as for mask files: 0 is background, and the mask is neither
    # empty nor everything. A two-valued image with a non-zero background used to pass (the larger
    # value taken as vessel); it is refused with binarise_mask's message now.
    mask = np.zeros((30, 40), bool)
    mask[3:7, 30:35] = True
    grey_background = mrml.add_frame_volume_node(scene, np.where(mask, 200.0, 50.0), "mask on grey")
    with pytest.raises(mrml.MRMLBridgeError, match=r"not binary \(values 50, 200\)") as caught:
        mrml.mask_from_volume_node(grey_background)
    assert isinstance(caught.value.__cause__, MaskError)
    assert "'mask on grey'" in str(caught.value)
    # ... and the fix the message names works: the vessel label.
    np.testing.assert_array_equal(mrml.mask_from_volume_node(grey_background, label=200), mask)
    empty = mrml.add_frame_volume_node(scene, np.zeros((30, 40), bool), "empty", class_name="vtkMRMLLabelMapVolumeNode")
    with pytest.raises(mrml.MRMLBridgeError, match="empty"):
        mrml.mask_from_volume_node(empty)
    labels = mrml.add_frame_volume_node(scene, mask * 2 + np.eye(30, 40, dtype=np.uint8), "labels",
                                        class_name="vtkMRMLLabelMapVolumeNode")
    np.testing.assert_array_equal(mrml.mask_from_volume_node(labels, label=2), mask)
    with pytest.raises(mrml.MRMLBridgeError, match="label 7 does not occur"):
        mrml.mask_from_volume_node(labels, label=7)
    # A threshold makes the mask of a grey image; the result is checked like any mask.
    frame = mrml.add_frame_volume_node(scene, np.arange(30 * 40, dtype=np.float32).reshape(30, 40), "frame")
    with pytest.raises(mrml.MRMLBridgeError, match="empty"):
        mrml.mask_from_volume_node(frame, threshold=5000)


def test_multi_slice_volume_needs_a_slice_index(scene):
    volume = mrml.add_volume_node(scene, np.arange(4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3), VolumeGrid((4, 5, 3), (1, 1, 1)), "cine")
    with pytest.raises(mrml.MRMLBridgeError, match="3 slices"):
        mrml.frame_from_volume_node(volume)
    np.testing.assert_array_equal(mrml.frame_from_volume_node(volume, 2), np.arange(60, dtype=np.float32).reshape(4, 5, 3)[:, :, 2].T)
    with pytest.raises(mrml.MRMLBridgeError, match="no volume node"):
        mrml.frame_from_volume_node(None)


def test_mask_from_segmentation_node_on_its_frame(scene):
    frame = np.random.default_rng(0).random((30, 40)).astype(np.float32)
    node = mrml.add_frame_volume_node(scene, frame, "frame", pixel_spacing_mm=(0.3, 0.2))
    mask = np.zeros((30, 40), bool)
    mask[2:5, 31:38] = True
    mask[20:28, 4] = True
    seg = mrml.add_mask_segmentation_node(scene, mask, node, "vessels")
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg), mask)
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg, node, segments=["Vessels"]), mask)
    with pytest.raises(mrml.MRMLBridgeError, match="no segment 'LAD'"):
        mrml.mask_from_segmentation_node(seg, node, segments=["LAD"])
    with pytest.raises(mrml.MRMLBridgeError, match="segmentation"):
        mrml.mask_from_segmentation_node(None, node)


def test_nodes_by_class_finds_the_nodes_without_leaking(scene):
    volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "volume")
    label = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "label")
    scene.AddNewNodeByClass("vtkMRMLModelNode", "model")
    assert mrml.nodes_by_class(scene, "vtkMRMLScalarVolumeNode") == [volume, label]  # subclasses too, scene order
    assert mrml.nodes_by_class(scene, "vtkMRMLSequenceNode") == []
    # GetNodesByClass's collection kept a reference to every node it listed, for ever: each
    # look-up of a proxy's sequence added one to every browser's count.
    browser = scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode", "browser")
    references = browser.GetReferenceCount()
    for _ in range(3):
        assert mrml.sequence_of_proxy_node(scene, volume) == (None, None)
    assert browser.GetReferenceCount() == references


def test_the_bridge_never_calls_get_nodes_by_class():
    import ast

    package = Path(mrml.__file__).parent
    calls = [f"{path.name}:{node.lineno}" for path in sorted(package.parent.rglob("*.py"))
             for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
             if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "GetNodesByClass"]
    assert not calls, f"GetNodesByClass leaks its vtkCollection; use mrml.nodes_by_class: {calls}"


def test_frames_from_a_sequence_and_its_browser(scene):
    frames = [np.full((6, 8), float(n), np.float32) + np.arange(8) for n in range(3)]
    sequence = scene.AddNewNodeByClass("vtkMRMLSequenceNode", "XA run")
    template = mrml.add_frame_volume_node(scene, frames[0], "tmp")
    for n, frame in enumerate(frames):
        template.SetAndObserveImageData(mrml._image_data(frame.T[:, :, None]))
        template.SetAttribute("DICOM.instanceUIDs", f"1.2.3.{n}")
        sequence.SetDataNodeAtValue(template, str(n))
    np.testing.assert_array_equal(mrml.frame_from_sequence(sequence, 2), frames[2])
    assert mrml.dicom_instance_uid(mrml.sequence_frame_node(sequence, 1)) == "1.2.3.1"
    with pytest.raises(mrml.MRMLBridgeError, match="out of range"):
        mrml.frame_from_sequence(sequence, 3)
    browser = scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode", "XA run browser")
    browser.SetAndObserveMasterSequenceNodeID(sequence.GetID())
    proxy = browser.AddProxyNode(template, sequence)
    assert mrml.sequence_of_proxy_node(scene, proxy) == (browser, sequence)
    assert mrml.sequence_of_proxy_node(scene, template) == (None, None)
    np.testing.assert_array_equal(mrml.frame_from_sequence(browser, 1), frames[1])


# --- files as SDFCARLib.io writes them ------------------------------------------------------------------
def test_files_written_by_sdfcarlib_io_open_at_the_right_place(scene, tmp_path):
    from SDFCARLib import io

    geometry = small_geometry()
    result = blob_result(geometry)
    io.write_segmentation_nrrd(tmp_path / "segmentation.seg.nrrd", result.segmentation, geometry.volume, name="IO case")
    # A tetrahedron around the blob centre, in LPS: Slicer must show it at RAS (-x, -y, z).
    centre = geometry.volume.index_to_world(BLOB_CENTRE)
    vertices = centre + np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-1.0, -1.0, -1.0]])
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    io.write_surface_vtk(tmp_path / "surface.vtk", vertices, faces)
    path = mrml.write_result_scene(tmp_path, "IO case", geometry, "segmentation.seg.nrrd", "surface.vtk", {"SDFCAR.preset": "fast"})

    loaded = mrml.load_scene(mrml.new_scene(), path)
    seg = loaded.GetFirstNodeByName("IO case")
    np.testing.assert_array_equal(mrml.segmentation_mask_lps(seg, geometry.volume), result.segmentation)
    from vtk.util.numpy_support import vtk_to_numpy
    points = vtk_to_numpy(loaded.GetFirstNodeByName("IO case surface").GetPolyData().GetPoints().GetData())
    np.testing.assert_allclose(points, mrml.lps_to_ras(vertices), atol=1e-5)
    assert mrml.node_provenance(seg)["preset"] == "fast"

    # The same folder through add_reconstruction_to_scene (the GUI's path after a job).
    nodes = mrml.add_reconstruction_to_scene(scene, tmp_path, "IO case")
    assert nodes.segmentation.GetSegmentation().GetSegment(nodes.segment_id).GetName() == "Coronary tree"
    np.testing.assert_allclose(vtk_to_numpy(nodes.model.GetPolyData().GetPoints().GetData()), mrml.lps_to_ras(vertices), atol=1e-5)


def test_an_empty_result_folder_is_refused_and_the_scene_kept(scene, tmp_path):
    from SDFCARLib import io

    geometry = small_geometry()
    io.write_segmentation_nrrd(tmp_path / "segmentation.seg.nrrd", np.zeros(geometry.volume.shape, bool), geometry.volume)
    io.write_surface_vtk(tmp_path / "surface.vtk", np.zeros((0, 3)), np.zeros((0, 3), int))
    before = snapshot(scene)
    with pytest.raises(mrml.MRMLBridgeError, match="no voxel"):
        mrml.add_reconstruction_to_scene(scene, tmp_path, "Empty")
    assert snapshot(scene) == before


def test_segment_mask_replaces_and_dicom_frame_reference(scene):
    frame = np.zeros((10, 12), np.float32)
    node = mrml.add_frame_volume_node(scene, frame, "frame")
    first = np.zeros((10, 12), bool)
    first[1:3, 2:5] = True
    seg = mrml.add_mask_segmentation_node(scene, first, node, "vessels")
    second = np.zeros((10, 12), bool)
    second[6:9, 7] = True
    segment_id = mrml.set_segment_mask(seg, second, node, "Vessels")
    assert seg.GetSegmentation().GetNumberOfSegments() == 1 and seg.GetSegmentation().GetSegment(segment_id)
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg, node), second)

    node.SetAttribute("DICOM.instanceUIDs", "1.2.840.99")
    assert mrml.dicom_frame_reference(scene, node, -1) == ("1.2.840.99", None)
    assert mrml.dicom_frame_reference(scene, node, 4) == ("1.2.840.99", 4)
    # A multi-frame run as a sequence (one UID): item n is frame n of the file; one file per
    # frame (a UID per item): frame 0 of that item's file.
    for shared in (True, False):
        sequence = scene.AddNewNodeByClass("vtkMRMLSequenceNode")
        for n in range(3):
            node.SetAttribute("DICOM.instanceUIDs", "1.2.3" if shared else f"1.2.3.{n}")
            sequence.SetDataNodeAtValue(node, str(n))
        browser = scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode")
        browser.SetAndObserveMasterSequenceNodeID(sequence.GetID())
        proxy = browser.AddProxyNode(node, sequence)
        browser.SetSelectedItemNumber(1)
        assert mrml.dicom_frame_reference(scene, proxy, 2) == (("1.2.3", 2) if shared else ("1.2.3.2", 0))
        assert mrml.dicom_frame_reference(scene, proxy, -1) == (("1.2.3", 1) if shared else ("1.2.3.1", 0))


def test_saving_a_mrml_scene_never_overwrites_files_elsewhere(scene, tmp_path):
    geometry = small_geometry()
    result_dir = tmp_path / "result"
    result_dir.mkdir()
    write_result_files(result_dir, geometry, blob_result(geometry))
    original = (result_dir / "segmentation.seg.nrrd").read_bytes()
    nodes = mrml.add_reconstruction_to_scene(scene, result_dir, "Loaded")
    # The user edits the segmentation, then saves the scene in another folder.
    grown = blob_result(geometry).segmentation.copy()
    grown[0:2, 0:2, 0:2] = True
    labelmap = mrml._oriented_labelmap(grown, geometry.volume)
    assert slicer.vtkSlicerSegmentationsModuleLogic.SetBinaryLabelmapToSegment(labelmap, nodes.segmentation, nodes.segment_id)
    (tmp_path / "saved").mkdir()
    path = mrml.save_scene(scene, tmp_path / "saved" / "scene.mrml")
    assert (result_dir / "segmentation.seg.nrrd").read_bytes() == original
    loaded = mrml.load_scene(mrml.new_scene(), path)
    np.testing.assert_array_equal(mrml.segmentation_mask_lps(loaded.GetFirstNodeByName("Loaded"), geometry.volume), grown)
    # The unmodified surface is referenced where it is.
    names = [e.get("fileName") for e in ET.parse(path).getroot().iter() if e.get("fileName")]
    assert "../result/surface.vtk" in names


def test_mask_from_a_segmentation_on_one_slice_of_a_multi_frame_volume(scene):
    # A cine run loaded as a 3D volume: i = column, j = row, k = frame.
    grid = VolumeGrid((8, 6, 3), (1.0, 1.0, 1.0))
    run = mrml.add_volume_node(scene, np.zeros((8, 6, 3), np.float32), grid, "run")
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "painted")
    seg.SetReferenceImageGeometryParameterFromVolumeNode(run)
    painted = np.zeros((8, 6, 3), bool)
    painted[2:4, 1, 2] = True  # on frame 2 only
    labelmap = mrml._oriented_labelmap(painted, grid)
    seg.AddSegmentFromBinaryLabelmapRepresentation(labelmap, "Vessels", [1.0, 0.0, 0.0])
    expected = painted[:, :, 2].T  # (rows, cols) = (j, i)
    np.testing.assert_array_equal(mrml.mask_from_segmentation_node(seg, run, slice_index=2), expected)
    with pytest.raises(mrml.MRMLBridgeError, match="the mask is empty"):  # nothing painted on frame 0
        mrml.mask_from_segmentation_node(seg, run, slice_index=0)
    with pytest.raises(mrml.MRMLBridgeError, match="3 slices"):
        mrml.mask_from_segmentation_node(seg, run)


def test_what_a_user_says_of_a_frames_grey_levels_is_kept_on_the_node_and_saved_with_the_scene(scene, tmp_path):
    """The Slicer module's "Grey levels" box: LIN or DISP (any case) on the frame node, nothing said removes it;
    anything else is refused before the node changes; the scene file keeps it."""
    frame = mrml.add_frame_volume_node(scene, np.zeros((4, 6), np.float32), "frame 1")
    assert mrml.frame_intensity_said(frame) is None and mrml.frame_intensity_said(None) is None
    mrml.say_frame_intensity(frame, "disp")
    assert frame.GetAttribute(mrml.FRAME_INTENSITY_ATTRIBUTE) == "DISP" and mrml.frame_intensity_said(frame) == "DISP"
    with pytest.raises(ValueError, match="frame 1.*'LOG'.*say LIN or DISP"):
        mrml.say_frame_intensity(frame, "LOG")
    assert mrml.frame_intensity_said(frame) == "DISP"  # unchanged by the refused value
    mrml.say_frame_intensity(frame, "lin")
    loaded = mrml.load_scene(mrml.new_scene(), mrml.save_scene(scene, tmp_path / "scene.mrml"))
    (again,) = [n for n in mrml.nodes_by_class(loaded, "vtkMRMLScalarVolumeNode") if n.GetName() == "frame 1"]
    assert mrml.frame_intensity_said(again) == "LIN"
    mrml.say_frame_intensity(frame, "")
    assert frame.GetAttribute(mrml.FRAME_INTENSITY_ATTRIBUTE) is None and mrml.frame_intensity_said(frame) is None
    frame.SetAttribute(mrml.FRAME_INTENSITY_ATTRIBUTE, "raw")  # set by hand from the console: a typo is not ignored
    with pytest.raises(ValueError, match="'raw'"):
        mrml.frame_intensity_said(frame)
    with pytest.raises(mrml.MRMLBridgeError, match="choose the view's frame"):
        mrml.say_frame_intensity(None, "LIN")
