"""The module's logic (SDFCAR/SDFCAR.py) on a real MRML scene of slicer-core, headless.

``slicer_fakes.install(real_mrml=True)`` keeps Qt and the parameter-node wrapper fakes but gives
the logic slicer-core's scene and classes: a finished three-view job's files go into the scene as
the module loads them (segmentation, C-arm, one QA overlay per view on its frame), the Results
section's text and QA overlay come from them, and Analyse runs the real worker process and adds the
3D-QCA nodes; the suggested view turns a real camera node.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("slicer", reason="needs the slicer-core package (pip install slicer-core)")

import slicer_fakes  # noqa: E402


@pytest.fixture(scope="module")
def three_view_result(tmp_path_factory):
    """A three-view result folder as a finished job leaves it (job folder with its masks, output/)."""
    from conftest import tiny_tree

    from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
    from SDFCARLib.jobs import prepare_job
    from SDFCARLib.optimiser import Reconstruction
    from SDFCARLib.outputs import write_reconstruction
    from SDFCARLib.phantoms import beer_lambert_counts, make_case
    from SDFCARLib.qa import qa_warnings, reprojection_qa
    from SDFCARLib.settings import make_settings

    views = tuple(CArmView(a, b, 1000.0, 750.0, (1.0, 1.0), (96, 96)) for a, b in ((30.0, 0.0), (-30.0, 0.0), (0.0, 30.0)))
    geometry = Geometry(VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0)), views)
    case = make_case(tiny_tree(), geometry, name="three")
    label = np.asarray(case.label, bool)
    qa_masks = []
    for n, mask in enumerate(case.masks):
        projected = mask.astype(bool).copy()
        if n == 1:
            projected[5:15, 5:40] = True  # a ghost in view 2
        qa_masks.append((projected, mask.astype(bool)))
    qa = [reprojection_qa(p, m, v) for (p, m), v in zip(qa_masks, views)]
    settings = make_settings("fast", steps=1)
    report = {"settings": settings.to_dict(), "method": "test", "geometry": geometry.to_dict(),
              "geometry_digest": geometry.digest(), "reprojection_qa": qa, "warnings": qa_warnings(qa), "target_kind": "mask",
              "components": {"components": 3, "largest_component_fraction": 0.9}}
    result = Reconstruction(geometry, settings, label.astype(np.float32), label.astype(np.float32) * 2 - 1, label, None,
                            report, qa_masks=qa_masks)
    job = tmp_path_factory.mktemp("job") / "Tree-20260101-000000"
    frames = [beer_lambert_counts(li, 0.25, 3000.0, 12) for li in case.line_integrals]  # the frames the masks came from
    prepare_job(job, geometry, case.masks, {"preset": "fast", "steps": 1}, name="Tree", frames=frames)
    files = write_reconstruction(result, job / "output", name="Tree")
    return {k: str(v) for k, v in files.items()}, job, geometry, case


@pytest.fixture
def module(monkeypatch):
    return slicer_fakes.install(monkeypatch, real_mrml=True)


def _add_results(module, three_view_result):
    from SDFCARLib import mrml

    files, job, geometry, case = three_view_result
    frames = [mrml.add_frame_volume_node(module.scene, m.astype(np.float32), f"frame {n}", (1.0, 1.0))
              for n, m in enumerate(case.masks, start=1)]
    context = {"name": "Tree", "geometry": geometry, "frames": [f.astype(np.float32) for f in case.masks],
               "frameNodes": frames, "jobDir": str(job), "includeOccupancy": False, "showCArm": True}
    return module.SDFCARLogic().addResults(files, context), frames


def test_a_three_view_result_loads_with_its_qa_overlays(module, three_view_result, monkeypatch):
    from SDFCARLib import mrml

    files, job, geometry, case = three_view_result
    nodes, frames = _add_results(module, three_view_result)
    scene = module.scene
    segmentation = nodes.segmentation
    assert segmentation.GetScene() is scene and segmentation.GetAttribute("SDFCAR.resultFolder") == str(job / "output")
    assert mrml.result_folder_of(segmentation) == job / "output"
    overlays = mrml.qa_overlay_nodes(scene, job / "output")
    assert sorted(overlays) == [1, 2, 3]
    for n, frame in enumerate(frames, start=1):  # each overlay lies on its frame
        a, b = mrml.scene._vtk_matrix(np.eye(4)), mrml.scene._vtk_matrix(np.eye(4))
        overlays[n].GetIJKToRASMatrix(a)
        frame.GetIJKToRASMatrix(b)
        assert np.allclose(mrml.scene._numpy_matrix(a), mrml.scene._numpy_matrix(b))
    assert scene.GetFirstNodeByName("Tree C-arm view 3 detector") is not None
    text, views = module.SDFCARLogic().resultQAText(segmentation)
    assert views == 3 and text.startswith("View 1: Dice 1.000") and "View 3" in text and "warning(s):" in text
    assert "\nThe result is in 3 pieces (26-connected voxels); the largest holds 90 % of them." in text
    assert "Kept the fit" not in text  # one fit
    report = mrml.read_report(job / "output")
    report["ensemble_choice"] = {"combine": "best_reprojection", "seeds": [3, 4], "chosen_fit": 1, "chosen_seed": 4,
                                 "reprojection_dice": [[0.9, 0.8, 0.7], [1.0, 0.9, 0.8]]}
    monkeypatch.setattr(mrml, "read_report", lambda folder: report)
    text, views = module.SDFCARLogic().resultQAText(segmentation)
    assert views == 3 and "\nKept the fit of seed 4 of 2 (seeds 3, 4): the highest mean reprojection Dice (0.8000, 0.9000)." in text


def test_show_qa_overlay_reloads_what_the_user_deleted(module, three_view_result):
    from SDFCARLib import mrml

    files, job, geometry, case = three_view_result
    nodes, _ = _add_results(module, three_view_result)
    logic = module.SDFCARLogic()
    shown = logic.showQAOverlay(nodes.segmentation, 2)
    assert module.recorder.sliceLayers[-1] == {"background": shown, "fit": True}
    for node in mrml.qa_overlay_nodes(module.scene, job / "output").values():
        module.scene.RemoveNode(node)
    again = logic.showQAOverlay(nodes.segmentation, 3)
    assert again.GetName() == "Tree QA view 3" and again.GetScene() is module.scene
    with pytest.raises(ValueError, match="no QA overlay of view 4"):
        logic.showQAOverlay(nodes.segmentation, 4)


def test_analyse_adds_the_qca_and_the_suggested_view_turns_the_camera(module, three_view_result):
    files, job, geometry, case = three_view_result
    nodes, _ = _add_results(module, three_view_result)
    logic = module.SDFCARLogic()
    with pytest.raises(ValueError, match="press Analyse"):
        logic.showSuggestedView(nodes.segmentation)
    # The real worker process (this Python: PythonSlicer is not on the PATH here), as Analyse starts it.
    job_handle, context = logic.startAnalysis(nodes.segmentation, options={"view_step_deg": 20.0})
    assert job_handle.wait(300) == "finished", (job_handle.job_dir / "worker.log").read_text()
    manifest = json.loads((job_handle.job_dir / "analysis_job.json").read_text())
    assert len(manifest["masks"]) == 3  # the job's masks give the 2D diameters
    assert [Path(f).name for f in manifest["options"]["frames"]] == ["frame1.npy", "frame2.npy", "frame3.npy"]  # and its frames
    qca = logic.addAnalysis(job_handle.result(), context)
    folder = job / "output" / "analysis"
    assert nodes.segmentation.GetAttribute("SDFCAR.analysisFolder") == str(folder)
    assert qca["curves"] and qca["chart"].GetScene() is module.scene
    assert logic.analysisText(nodes.segmentation).startswith("3D-QCA:")
    best = logic.showSuggestedView(nodes.segmentation)
    camera = module.layoutManager.camera
    bounds = [0.0] * 6
    nodes.segmentation.GetRASBounds(bounds)
    assert np.allclose(camera.GetFocalPoint(), [(bounds[0] + bounds[1]) / 2, (bounds[2] + bounds[3]) / 2, (bounds[4] + bounds[5]) / 2])
    from SDFCARLib.analysis.mrml_nodes import camera_for_angles
    from SDFCARLib.mrml import ras_to_lps

    expected = camera_for_angles(best["primary_deg"], best["secondary_deg"], 500.0, ras_to_lps(np.array(camera.GetFocalPoint())))
    assert np.allclose(camera.GetPosition(), expected["position"], atol=1e-6)
    # A second analysis goes beside the first; the first one's nodes and files stay. (Without the frames, which the
    # first one read: their intensity fits are two thirds of an analysis' time here and add nothing to this check.)
    second, context2 = logic.startAnalysis(nodes.segmentation, options={"view_step_deg": 30.0, "frames": None})
    assert second.wait(300) == "finished"
    logic.addAnalysis(second.result(), context2)
    assert (job / "output" / "analysis-2" / "analysis.json").is_file() and (folder / "analysis.json").is_file()
    assert qca["table"].GetScene() is module.scene
    # The analysis' warnings reach the module's summary as they reach the command line's stderr.
    data = json.loads((folder / "analysis.json").read_text())
    data["warnings"] = ["1 lesion(s) of the 3D sections not seen on the frames: branch 0 at 12.0 mm (3D DS 40%)."]
    (folder / "analysis.json").write_text(json.dumps(data))
    nodes.segmentation.SetAttribute("SDFCAR.analysisFolder", str(folder))
    text = logic.analysisText(nodes.segmentation)
    assert text.startswith("3D-QCA:") and text.endswith("1 warning(s):\n• " + data["warnings"][0])


def test_a_point_list_of_two_points_marks_the_segment_in_lps(module):
    logic = module.SDFCARLogic()
    points = module.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "ends")
    points.AddControlPointWorld(10.0, -20.0, 30.0)
    assert logic.segmentFromPoints(None) is None  # none chosen: the analysis frames the worst lesion
    with pytest.raises(ValueError, match="'ends' has 1 point"):
        logic.segmentFromPoints(points)
    points.AddControlPointWorld(-4.0, 5.0, -6.0)
    assert logic.segmentFromPoints(points) == [[-10.0, 20.0, 30.0], [4.0, -5.0, -6.0]]  # RAS → LPS


def test_a_point_list_of_one_point_gives_the_ostium_in_lps(module):
    from SDFCARLib.analysis.mrml_nodes import _add_point

    logic = module.SDFCARLogic()
    point = module.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "ostium")
    assert logic.ostiumFromPoint(None) is None  # none chosen: the tree's thickest end
    with pytest.raises(ValueError, match="'ostium' has 0 point"):
        logic.ostiumFromPoint(point)
    point.AddControlPointWorld(10.0, -20.0, 30.0)
    assert logic.ostiumFromPoint(point) == [-10.0, 20.0, 30.0]  # RAS → LPS
    point.AddControlPointWorld(1.0, 2.0, 3.0)
    with pytest.raises(ValueError, match="has 2 point.*exactly one"):
        logic.ostiumFromPoint(point)
    suggested = _add_point(module.scene, "likeliest ostium", [10.0, -20.0, 30.0])  # as an analysis adds it, LPS
    assert logic.ostiumFromPoint(suggested) == [10.0, -20.0, 30.0]
