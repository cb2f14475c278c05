"""The 3D-QCA's scene content from the Slicer console (slicer-core, headless): an analysis folder that is
incomplete, edited or older, a wrong result node and odd camera angles are named, with the scene left as it was."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

slicer = pytest.importorskip("slicer", reason="the QCA scene nodes need the slicer-core package")

from SDFCARLib.analysis import mrml_nodes as qca  # noqa: E402
from SDFCARLib.mrml import new_scene  # noqa: E402


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    """A result folder with the analysis analyse wrote into it (a 50 % stenosis on a 3 mm tube)."""
    from test_analysis import _result_folder

    from SDFCARLib.analysis.outputs import analyse_result_dir

    folder, phantom = _result_folder(tmp_path_factory.mktemp("qca"))
    analyse_result_dir(folder, view_step_deg=10.0, ostium_mm=phantom.truth["ostium_mm"])
    return folder


def node_count(scene):
    return scene.GetNumberOfNodes()


def edited(analysed, tmp_path, edit=None, profile=None):
    """A copy of the analysis with analysis.json changed by ``edit(data)`` and/or profile_branch00.csv by ``profile``."""
    folder = tmp_path / "analysis"
    shutil.copytree(analysed / "analysis", folder)
    if edit is not None:
        data = json.loads((folder / "analysis.json").read_text())
        replaced = edit(data)  # an edit changes data in place, or returns what replaces it
        (folder / "analysis.json").write_text(json.dumps(data if replaced is None else replaced))
    if profile is not None:
        path = folder / "profile_branch00.csv"
        path.write_text(profile(path.read_text()))
    return folder


def test_the_result_folder_or_the_json_given_links_the_analysis_folder(analysed):
    scene = new_scene()
    result = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "result")
    qca.add_analysis_to_scene(scene, analysed, "case", result_node=result)  # the result folder, not its analysis/
    assert result.GetAttribute("SDFCAR.analysisFolder") == str(analysed / "analysis")
    assert set(qca.suggested_view_of(result)) >= {"primary_deg", "secondary_deg"}
    nodes = qca.add_analysis_nodes(scene, analysed / "analysis" / "analysis.json", "again")  # the file itself
    assert nodes["curves"]


def test_a_root_on_a_vessel_s_side_adds_the_likeliest_ostium_as_a_point_list_in_ras(analysed, tmp_path):
    finding = {"angle_deg": 150.0, "likeliest_ostium_mm": [10.0, -20.0, 30.0]}  # as root_check.through_vessel_root
    folder = edited(analysed, tmp_path, lambda d: d["settings"].update(through_vessel_root=finding))
    scene = new_scene()
    result = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "result")
    nodes = qca.add_analysis_to_scene(scene, folder, "case", result_node=result)
    point = nodes["likeliest_ostium"]
    assert point.IsA("vtkMRMLMarkupsFiducialNode") and point.GetName() == "case likeliest ostium"
    assert point.GetNumberOfControlPoints() == 1 and not point.GetLocked()  # to be checked and moved
    ras = [0.0, 0.0, 0.0]
    point.GetNthControlPointPosition(0, ras)
    np.testing.assert_allclose(ras, [-10.0, 20.0, 30.0])  # LPS → RAS
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)
    assert hierarchy.GetItemParent(hierarchy.GetItemByDataNode(point)) == nodes["folder"]
    assert point.GetAttribute("SDFCAR.analysisFolder") == str(folder)
    assert qca.add_analysis_nodes(new_scene(), analysed, "case")["likeliest_ostium"] is None  # a root not flagged


def test_a_result_node_that_is_no_segmentation_of_this_scene_is_refused_first(analysed):
    scene = new_scene()
    other = new_scene().AddNewNodeByClass("vtkMRMLSegmentationNode", "elsewhere")
    volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "a volume")
    before = node_count(scene)
    for wrong in ("vtkMRMLSegmentationNode1", volume, other):
        with pytest.raises(ValueError, match="is not a segmentation in this scene"):
            qca.add_analysis_to_scene(scene, analysed, "case", result_node=wrong)
        assert node_count(scene) == before


def _without(*keys):
    def edit(data):
        entry = data
        for key in keys[:-1]:
            entry = entry[key]
        del entry[keys[-1]]
    return edit


@pytest.mark.parametrize("edit, expected", [
    (_without("branches"), r"'branches' is missing or not a list"),
    (lambda d: [d], r"the file holds a list, not an object"),
    (lambda d: d["branches"][0].update(branch_id="0"), r"branches\[0\]\.branch_id is '0', not a whole number"),
    (_without("branches", 0, "parent_id"), r"branches\[0\]\.parent_id is missing"),
    (_without("branches", 0, "lesions", 0, "diameter_stenosis_pct"), r"lesions\[0\]\.diameter_stenosis_pct is missing"),
    (lambda d: d["branches"][0]["lesions"][0].update(length_mm="8"), r"lesions\[0\]\.length_mm is missing or not a number"),
    (lambda d: d["view_map"].update(overlap=[[0.0]]), r"'view_map' does not hold"),
    (lambda d: d["settings"].update(through_vessel_root={"likeliest_ostium_mm": [1.0, None, 3.0]}),
     r"settings\.through_vessel_root\.likeliest_ostium_mm is missing or not three numbers"),
])
def test_an_edited_analysis_is_named_before_any_node_is_made(analysed, tmp_path, edit, expected):
    folder = edited(analysed, tmp_path, edit)
    scene = new_scene()
    for add in (qca.add_analysis_nodes, qca.add_analysis_to_scene):
        before = node_count(scene)
        with pytest.raises(ValueError, match=expected + ".*re-run analyse"):
            add(scene, folder, "case")
        assert node_count(scene) == before


def test_a_damaged_profile_is_named_and_an_editors_bom_is_read(analysed, tmp_path):
    scene = new_scene()
    no_x = edited(analysed, tmp_path / "a", profile=lambda t: "\n".join(
        ",".join(c for i, c in enumerate(line.split(",")) if i != t.splitlines()[0].split(",").index("x_mm"))
        for line in t.splitlines()) + "\n")
    with pytest.raises(ValueError, match=r"profile_branch00.csv lacks the column\(s\) x_mm"):
        qca.add_analysis_nodes(scene, no_x, "case")
    cut = edited(analysed, tmp_path / "b", profile=lambda t: t[: len(t) // 2].rsplit(",", 1)[0] + "\n")
    with pytest.raises(ValueError, match=r"line \d+: [xyz]_mm is missing \(a cut or edited file\)"):
        qca.add_analysis_nodes(scene, cut, "case")
    def first_arc_not_a_number(text):
        lines = text.splitlines()
        lines[1] = "n/a" + lines[1][lines[1].index(","):]  # arc_mm is the first column
        return "\n".join(lines) + "\n"

    text = edited(analysed, tmp_path / "c", profile=first_arc_not_a_number)
    with pytest.raises(ValueError, match=r"line 2: arc_mm = 'n/a' is not a number"):
        qca.add_analysis_nodes(scene, text, "case")
    bom = edited(analysed, tmp_path / "d")
    (bom / "analysis.json").write_bytes(b"\xef\xbb\xbf" + (bom / "analysis.json").read_bytes())
    assert qca.add_analysis_nodes(scene, bom, "bom")["curves"]


def test_a_nan_grade_does_not_hide_the_worst_lesion(analysed, tmp_path):
    def add_unmeasured_lesion(data):
        lesions = data["branches"][0]["lesions"]
        unmeasured = json.loads(json.dumps(lesions[0]))
        unmeasured["diameter_stenosis_pct"] = float("nan")
        unmeasured.pop("grade", None)
        lesions.insert(0, unmeasured)

    folder = edited(analysed, tmp_path, add_unmeasured_lesion)
    table = qca.add_analysis_nodes(new_scene(), folder, "case")["table"].GetTable()
    assert table.GetColumnByName("diameter_stenosis_pct").GetValue(0) == pytest.approx(50.0, abs=8.0)


def test_camera_angles_of_the_wrong_kind_leave_the_camera_as_it_was(analysed, tmp_path):
    scene = new_scene()
    camera = scene.AddNewNodeByClass("vtkMRMLCameraNode")
    camera.SetPosition(0.0, 500.0, 0.0)
    before = camera.GetPosition()
    for args, expected in (((float("nan"), 0.0), "primary_deg must be a finite number"),
                           (("30", 0.0), "primary_deg must be a finite number"),
                           ((30.0, None), "secondary_deg must be a finite number"),
                           ((30.0, 0.0, 0.0), "distance_mm must be positive"),
                           ((30.0, 0.0, float("inf")), "distance_mm must be a finite number")):
        with pytest.raises(ValueError, match=expected):
            qca.set_camera_to_angles(camera, *args)
        assert camera.GetPosition() == before
    with pytest.raises(ValueError, match="no camera node"):
        qca.set_camera_to_angles(None, 30.0, 0.0)
    qca.set_camera_to_angles(camera, np.float32(90.0), np.int64(0))  # numpy's numbers are numbers
    assert np.allclose(camera.GetPosition(), (-500.0, 0.0, 0.0), atol=1e-3)
    camera.SetPosition(*camera.GetFocalPoint())  # a collapsed camera: a usable distance, not 1e-20
    qca.set_camera_to_angles(camera, 0.0, 0.0)
    assert np.linalg.norm(np.subtract(camera.GetPosition(), camera.GetFocalPoint())) == pytest.approx(800.0)
    folder = edited(analysed, tmp_path, lambda d: d["best_view"].update(primary_deg=float("nan")))
    with pytest.raises(ValueError, match="the suggested view .* is not a pair of angles"):
        qca.read_best_view(folder)
    with pytest.raises(ValueError, match="point_step_mm must be a positive number"):
        qca.add_analysis_nodes(scene, analysed, "case", point_step_mm=float("nan"))
