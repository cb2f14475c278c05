"""The Slicer module's scene pieces against the real MRML of slicer-core (headless).

Views 3, 4, … in the module's parameter node (``mrml.parameter_views``), the reprojection-QA
overlays as volumes (``mrml.qa_overlays``), a result's folder found from its node, and the 3D-QCA
nodes grouped in one folder: what the module does in Slicer, on a real scene, saved and reloaded.
"""

from __future__ import annotations

import numpy as np
import pytest

slicer = pytest.importorskip("slicer", reason="the MRML tests need the slicer-core package (pip install slicer-core)")

from SDFCARLib import mrml  # noqa: E402
from SDFCARLib.mrml import parameter_views as pv  # noqa: E402


@pytest.fixture()
def scene():
    return mrml.new_scene()


def _module_node(scene, name="SDFCAR"):
    node = scene.AddNewNodeByClass("vtkMRMLScriptedModuleNode", name)
    node.SetModuleName("SDFCAR")
    return node


def _frame(scene, name, shape=(8, 10)):
    return mrml.add_frame_volume_node(scene, np.arange(np.prod(shape), dtype=np.float32).reshape(shape), name)


def _label(scene, name, shape=(8, 10)):
    mask = np.zeros(shape, np.uint8)
    mask[2:5, 3:7] = 1
    return mrml.add_frame_volume_node(scene, mask, name, class_name="vtkMRMLLabelMapVolumeNode")


# --- views 3, 4, … in the parameter node ---------------------------------------------------------------
def test_a_node_without_extra_views_has_two(scene):
    node = _module_node(scene)
    assert pv.view_count(node) == 2
    with pytest.raises(mrml.MRMLBridgeError, match="no view 3"):
        pv.get_view(node, 3)
    with pytest.raises(mrml.MRMLBridgeError, match="wrapper"):
        pv.get_view(node, 2)


def test_add_set_and_read_back_views(scene):
    node = _module_node(scene)
    frame, label = _frame(scene, "f3"), _label(scene, "m3")
    assert pv.add_view(node, {"frame": frame, "primaryAngle": 0.0, "secondaryAngle": 30.0}) == 3
    assert pv.add_view(node) == 4
    pv.set_view_value(node, 3, "mask", label)
    pv.set_view_value(node, 4, "sid", 1200)
    pv.set_view_value(node, 4, "frameIndex", 5)
    three, four = pv.get_view(node, 3), pv.get_view(node, 4)
    assert (three.frame, three.mask, three.secondaryAngle) == (frame, label, 30.0)
    assert (four.frame, four.mask, four.sid, four.frameIndex) == (None, None, 1200.0, 5)
    assert isinstance(four.frameIndex, int) and isinstance(four.sid, float)
    # The same names and text the wrapper uses for views 1 and 2.
    assert node.GetParameter("secondaryAngle3") == "30.0" and node.GetNodeReferenceID("mask3") == label.GetID()
    assert node.GetParameter("frame4Index") == "5" and pv.parameter_name("frameIndex", 1) == "frame1Index"
    assert pv.view_count(node) == 4


def test_values_are_checked_like_the_wrapper_fields(scene):
    node = _module_node(scene)
    pv.add_view(node)
    with pytest.raises(mrml.MRMLBridgeError, match="sid 0 mm is outside 1 mm to 5000 mm"):
        pv.set_view_value(node, 3, "sid", 0)
    with pytest.raises(mrml.MRMLBridgeError, match="whole number"):
        pv.set_view_value(node, 3, "frameIndex", 1.5)
    with pytest.raises(mrml.MRMLBridgeError, match="vtkMRMLSegmentationNode or a vtkMRMLLabelMapVolumeNode"):
        pv.set_view_value(node, 3, "mask", _frame(scene, "grey"))
    with pytest.raises(mrml.MRMLBridgeError, match="no field 'angle'"):
        pv.set_view_value(node, 3, "angle", 1.0)
    outside = slicer.vtkMRMLScalarVolumeNode()
    outside.SetName("not added")
    with pytest.raises(mrml.MRMLBridgeError, match="not in the parameter node.s scene"):
        pv.set_view_value(node, 3, "frame", outside)
    # a node of another scene has an ID that names another node here
    other_scene = mrml.new_scene()
    foreign = _frame(other_scene, "foreign")
    with pytest.raises(mrml.MRMLBridgeError, match="'foreign' is not in the parameter node.s scene"):
        pv.set_view_value(node, 3, "frame", foreign)
    # numpy's numbers are numbers (a value read off an array), a view number is whole
    pv.set_view_value(node, 3, "frameIndex", np.int64(2))
    pv.set_view_value(node, 3, "sid", np.float32(1100.0))
    assert pv.get_view(node, 3).frameIndex == 2 and pv.get_view(node, 3).sid == 1100.0
    with pytest.raises(mrml.MRMLBridgeError, match="a view number is a whole number"):
        pv.get_view(node, 3.7)
    # A failed add leaves the node as it was.
    before = pv.view_count(node)
    with pytest.raises(mrml.MRMLBridgeError):
        pv.add_view(node, {"sod": -1.0})
    assert pv.view_count(node) == before and not node.HasParameter("sod4")


def test_removing_a_middle_view_moves_the_later_ones_up(scene):
    node = _module_node(scene)
    frames = [_frame(scene, f"f{n}") for n in (3, 4, 5)]
    for n, frame in enumerate(frames, start=3):
        pv.add_view(node, {"frame": frame, "primaryAngle": float(n)})
    pv.remove_view(node, 3)
    assert pv.view_count(node) == 4
    assert [pv.get_view(node, n).frame for n in (3, 4)] == frames[1:]
    assert [pv.get_view(node, n).primaryAngle for n in (3, 4)] == [4.0, 5.0]
    assert not node.HasParameter("primaryAngle5") and node.GetNodeReference("frame5") is None
    # The user's frame nodes stay in the scene: only the parameters moved.
    assert all(scene.GetNodeByID(f.GetID()) is f for f in frames)
    pv.set_view_count(node, 2)
    assert pv.view_count(node) == 2 and not node.HasParameter("viewCount")


def test_deleting_a_frame_node_clears_its_reference(scene):
    node = _module_node(scene)
    frame = _frame(scene, "f3")
    pv.add_view(node, {"frame": frame})
    scene.RemoveNode(frame)
    assert pv.get_view(node, 3).frame is None


@pytest.mark.parametrize("suffix", [".mrml", ".mrb"])
def test_extra_views_survive_save_and_reload(scene, tmp_path, suffix):
    node = _module_node(scene)
    # Views 1 and 2 as the wrapper stores them, next to the stored views.
    node.SetParameter("primaryAngle1", "30.0")
    frame, label = _frame(scene, "view 3"), _label(scene, "view 3 mask")
    pv.add_view(node, {"frame": frame, "mask": label, "primaryAngle": -5.5, "secondaryAngle": 31.0, "sid": 1100.0,
                       "sod": 760.0, "pixelSpacingRow": 0.3, "pixelSpacingCol": 0.35, "frameIndex": 2})
    pv.add_view(node, {"primaryAngle": 90.0})
    path = mrml.save_scene(scene, tmp_path / f"scene{suffix}")
    loaded = mrml.load_scene(mrml.new_scene(), path)
    again = loaded.GetFirstNodeByName("SDFCAR")
    assert pv.view_count(again) == 4 and again.GetParameter("primaryAngle1") == "30.0"
    three = pv.get_view(again, 3)
    assert three.frame.GetName() == "view 3" and three.mask.GetName() == "view 3 mask"
    assert three.mask.IsA("vtkMRMLLabelMapVolumeNode")
    assert (three.primaryAngle, three.secondaryAngle, three.sid, three.sod) == (-5.5, 31.0, 1100.0, 760.0)
    assert (three.pixelSpacingRow, three.pixelSpacingCol, three.frameIndex) == (0.3, 0.35, 2)
    assert pv.get_view(again, 4).primaryAngle == 90.0 and pv.get_view(again, 4).frame is None


def test_a_damaged_view_count_is_named(scene):
    node = _module_node(scene)
    node.SetParameter("viewCount", "three")
    with pytest.raises(mrml.MRMLBridgeError, match="viewCount is 'three'"):
        pv.view_count(node)


# --- QA overlays ------------------------------------------------------------------------------------------
def _qa_result(tmp_path, views=3):
    """A result folder as outputs.write_reconstruction leaves it: qa_view<n>.png and report.json."""
    import json

    from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
    from SDFCARLib.qa import qa_title, qa_warnings, reprojection_qa, write_qa_png

    shape = (40, 48)
    geometry = Geometry(VolumeGrid((8, 8, 8), (1.0, 1.0, 1.0)),
                        tuple(CArmView(30.0 * n, 0.0, 1000.0, 750.0, (0.5, 0.25), shape) for n in range(views)))
    folder = tmp_path / "result"
    folder.mkdir()
    qa, masks = [], []
    for n, view in enumerate(geometry.views, start=1):
        mask = np.zeros(shape, bool)
        mask[10:20, 5:30] = True
        projected = mask.copy()
        if n == 2:  # a ghost branch in view 2 only
            projected[25:35, 10:30] = True
        qa.append(reprojection_qa(projected, mask, view))
        masks.append((projected, mask))
    for n, (projected, mask) in enumerate(masks, start=1):
        write_qa_png(folder / f"qa_view{n}.png", None, projected, mask, qa_title(n, qa[n - 1]))
    report = {"reprojection_qa": qa, "warnings": ["view 1: the mask has 3 specks"] + qa_warnings(qa),
              "files": {f"qa_view{n}": f"qa_view{n}.png" for n in range(1, views + 1)}}
    (folder / "report.json").write_text(json.dumps(report), encoding="utf-8")
    return folder, geometry


def test_qa_summary_per_view_with_its_warnings(tmp_path):
    import json

    from SDFCARLib.qa import qa_summary, qa_summary_lines

    folder, _ = _qa_result(tmp_path)
    report = json.loads((folder / "report.json").read_text())
    rows = qa_summary(report)
    assert [r["view"] for r in rows] == [1, 2, 3]
    assert rows[0]["dice"] == pytest.approx(1.0) and rows[0]["warnings"] == ["view 1: the mask has 3 specks"]
    assert rows[1]["result_only_mm2"] == pytest.approx(200 * 0.5 * 0.25 * 750 / 1000 * 750 / 1000, rel=1e-6)
    assert rows[1]["warnings"] and all(w.startswith("view 2:") for w in rows[1]["warnings"])
    lines = qa_summary_lines(report)
    assert lines[0].startswith("View 1: Dice 1.000") and "warning(s)" in lines[1] and "warning" not in lines[2]
    assert qa_summary({}) == [] and qa_summary_lines({"reprojection_qa": [None]}) == []


def test_qa_overlays_become_colour_volumes_on_their_frames(scene, tmp_path):
    from vtk.util import numpy_support

    from SDFCARLib import qa

    folder, geometry = _qa_result(tmp_path)
    frame = mrml.add_frame_volume_node(scene, np.zeros((40, 48), np.float32), "frame 2", (0.5, 0.25))
    frame.SetOrigin(10.0, 20.0, 30.0)
    before = scene.GetNumberOfNodes()
    nodes = mrml.add_qa_overlays_to_scene(scene, folder, "Case", geometry, frame_nodes=[None, frame])
    assert [n.GetName() for n in nodes] == ["Case QA view 1", "Case QA view 2", "Case QA view 3"]
    two = nodes[1]
    assert two.IsA("vtkMRMLVectorVolumeNode") and two.GetImageData().GetNumberOfScalarComponents() == 3
    dims = two.GetImageData().GetDimensions()
    assert dims[1] == 40 + qa.LEGEND_HEIGHT_PX and dims[2] == 1
    rgb = numpy_support.vtk_to_numpy(two.GetImageData().GetPointData().GetScalars()).reshape(dims[1], dims[0], 3)
    # Detector pixel (row, col) is voxel (i=col, j=row): the ghost is vermillion, the mask green.
    assert tuple(rgb[30, 20]) == qa.RESULT_ONLY_RGB and tuple(rgb[15, 20]) == qa.AGREE_RGB
    # On the frame: same IJK→RAS as the frame node; without one, the view's pixel spacing.
    for node, reference in ((two, frame),):
        a, b = mrml.scene._vtk_matrix(np.eye(4)), mrml.scene._vtk_matrix(np.eye(4))
        node.GetIJKToRASMatrix(a)
        reference.GetIJKToRASMatrix(b)
        assert np.allclose(mrml.scene._numpy_matrix(a), mrml.scene._numpy_matrix(b))
    assert np.allclose(nodes[0].GetSpacing(), (0.25, 0.5, 1.0))
    assert nodes[1].GetAttribute("SDFCAR.role") == "qa-overlay" and nodes[1].GetAttribute("SDFCAR.view") == "2"
    assert float(nodes[0].GetAttribute("SDFCAR.qa.dice")) == pytest.approx(1.0)
    assert "view 2:" in nodes[1].GetAttribute("SDFCAR.qa.warnings")
    display = two.GetDisplayNode()
    assert display.IsA("vtkMRMLVectorVolumeDisplayNode") and (display.GetWindow(), display.GetLevel()) == (255.0, 127.5)
    # A second load adds new nodes and keeps the first ones.
    again = mrml.add_qa_overlays_to_scene(scene, folder, "Case", geometry)
    assert scene.GetNumberOfNodes() > before and all(scene.GetNodeByID(n.GetID()) is n for n in nodes + again)


def test_qa_overlays_from_a_job_mapping_and_scene_reload(scene, tmp_path):
    folder, geometry = _qa_result(tmp_path, views=2)
    files = {"report": str(folder / "report.json"), "qa_view1": str(folder / "qa_view1.png"),
             "qa_view2": str(folder / "qa_view2.png"), "segmentation": str(folder / "segmentation.seg.nrrd")}
    nodes = mrml.add_qa_overlays_to_scene(scene, files, "Job", geometry)
    assert len(nodes) == 2
    path = mrml.save_scene(scene, tmp_path / "qa.mrb")
    loaded = mrml.load_scene(mrml.new_scene(), path)
    node = loaded.GetFirstNodeByName("Job QA view 2")
    assert node is not None and node.GetImageData().GetNumberOfScalarComponents() == 3
    assert node.GetAttribute("SDFCAR.role") == "qa-overlay"


def test_qa_overlays_fail_cleanly(scene, tmp_path):
    folder, geometry = _qa_result(tmp_path, views=2)
    (folder / "qa_view2.png").write_bytes(b"not a png")
    before = [scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())]
    with pytest.raises(mrml.MRMLBridgeError, match="qa_view2.png"):
        mrml.add_qa_overlays_to_scene(scene, folder, "Broken", geometry)
    assert [scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())] == before
    empty = tmp_path / "old"
    empty.mkdir()
    assert mrml.add_qa_overlays_to_scene(scene, empty, "Old") == []
    with pytest.raises(mrml.MRMLBridgeError, match="does not exist"):
        mrml.add_qa_overlays_to_scene(scene, tmp_path / "missing", "Missing")


# --- a result's folder, its 3D-QCA in the scene ------------------------------------------------------------
def test_result_folder_of_a_node(scene, tmp_path):
    folder = tmp_path / "job" / "output"
    folder.mkdir(parents=True)
    (folder / "report.json").write_text("{}", encoding="utf-8")
    node = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "r")
    assert mrml.result_folder_of(node) is None and mrml.result_folder_of(None) is None
    node.SetAttribute("SDFCAR.jobFolder", str(tmp_path / "job"))  # results loaded by older versions
    assert mrml.result_folder_of(node) == folder
    node.SetAttribute("SDFCAR.resultFolder", str(tmp_path / "gone"))  # moved away: the next clue counts
    assert mrml.result_folder_of(node) == folder
    opened = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "from scene.mrml")
    storage = scene.AddNewNodeByClass("vtkMRMLSegmentationStorageNode")
    storage.SetFileName(str(folder / "segmentation.seg.nrrd"))
    opened.SetAndObserveStorageNodeID(storage.GetID())
    assert mrml.result_folder_of(opened) == folder


def _give_new_nodes_items(scene):
    """As Slicer's subject-hierarchy plugins do: every node added gets an item under the scene."""
    import vtk

    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)

    @vtk.calldata_type(vtk.VTK_OBJECT)
    def on_added(caller, event, node):
        if node.IsA("vtkMRMLStorableNode") or node.IsA("vtkMRMLPlotChartNode") or node.IsA("vtkMRMLPlotSeriesNode"):
            if node.GetHideFromEditors() == 0 and hierarchy.GetItemByDataNode(node) == hierarchy.GetInvalidItemID():
                hierarchy.CreateItem(hierarchy.GetSceneItemID(), node)

    return scene.AddObserver(slicer.vtkMRMLScene.NodeAddedEvent, on_added)


@pytest.mark.parametrize("items", ["bare scene", "items as in Slicer"])
def test_analysis_in_one_folder_linked_to_its_result(scene, tmp_path, items):
    from test_analysis import _result_folder

    from SDFCARLib.analysis.mrml_nodes import add_analysis_to_scene, set_camera_to_angles, suggested_view_of
    from SDFCARLib.analysis.outputs import analyse_result_dir

    folder, phantom = _result_folder(tmp_path)
    analyse_result_dir(folder, view_step_deg=10.0, ostium_mm=phantom.truth["ostium_mm"])
    if items != "bare scene":
        _give_new_nodes_items(scene)
    result = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "Case")
    with pytest.raises(ValueError, match="press Analyse"):
        suggested_view_of(result)
    nodes = add_analysis_to_scene(scene, folder / "analysis", "Case", result_node=result)
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)
    assert hierarchy.GetItemName(nodes["folder"]) == "Case QCA"
    grouped = [nodes["table"], nodes["chart"], nodes["view_map"], *nodes["curves"], *nodes["series"]]
    if items != "bare scene":
        assert hierarchy.GetItemParent(hierarchy.GetItemByDataNode(result)) == hierarchy.GetSceneItemID()
    assert all(hierarchy.GetItemParent(hierarchy.GetItemByDataNode(n)) == nodes["folder"] for n in grouped)
    # The plot: one series per branch, diameter against arc length from the branch's profile table.
    series = nodes["series"][0]
    table = scene.GetNodeByID(series.GetTableNodeID())
    assert (series.GetXColumnName(), series.GetYColumnName()) == ("arc_mm", "diameter_3d_mm")
    assert table.GetNumberOfRows() > 10 and nodes["chart"].GetNthPlotSeriesNodeID(0) == series.GetID()
    assert result.GetAttribute("SDFCAR.analysisFolder") == str((folder / "analysis").absolute())
    best = suggested_view_of(result)
    assert best == nodes["best_view"]
    camera = scene.AddNewNodeByClass("vtkMRMLCameraNode")
    camera.SetFocalPoint(1.0, 2.0, 3.0)
    camera.SetPosition(1.0, 502.0, 3.0)
    set_camera_to_angles(camera, best["primary_deg"], best["secondary_deg"])
    direction = np.subtract(camera.GetPosition(), camera.GetFocalPoint())
    assert np.linalg.norm(direction) == pytest.approx(500.0) and np.allclose(camera.GetFocalPoint(), (1, 2, 3))
    # A second analysis adds its own nodes beside the first.
    again = add_analysis_to_scene(scene, folder / "analysis", "Case", result_node=result)
    assert again["folder"] != nodes["folder"] and scene.GetNodeByID(nodes["table"].GetID()) is nodes["table"]


def test_a_missing_analysis_leaves_the_scene_unchanged(scene, tmp_path):
    from SDFCARLib.analysis.mrml_nodes import add_analysis_to_scene, suggested_view_of

    before = scene.GetNumberOfNodes()
    with pytest.raises(FileNotFoundError, match="analyse"):
        add_analysis_to_scene(scene, tmp_path, "Nothing")
    assert scene.GetNumberOfNodes() == before
    result = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "r")
    result.SetAttribute("SDFCAR.analysisFolder", str(tmp_path / "deleted"))
    with pytest.raises(FileNotFoundError, match="moved or deleted"):
        suggested_view_of(result)
