"""SDFCAR/SDFCAR.py driven headless against the Slicer behaviour it must survive (slicer_fakes.py).

Each test names the defect it guards against; the fakes copy Slicer 5.4–5.8 where it differs
from later versions (see slicer_fakes' docstring for the tag and file).
"""

from __future__ import annotations

import importlib.util
import inspect
import os
import sys
import types
import unittest

import pytest

import slicer_fakes

# the module imports vtk, which Slicer ships; here the 'headless' extra (slicer-core) brings it
pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")


@pytest.fixture
def sdfcar(monkeypatch):
    return slicer_fakes.install(monkeypatch)


def _widget(sdfcar):
    widget = sdfcar.SDFCARWidget()
    widget.ui = slicer_fakes.module_ui(sdfcar)
    widget.logic = sdfcar.SDFCARLogic()
    widget.parent = types.SimpleNamespace(isEntered=True)
    widget.connectWidgets()  # what setup() connects after loading the .ui
    return widget


# --- the choices survive leaving and entering the module (Slicer 5.4–5.8) --------------------------------
def test_the_fake_reproduces_the_combo_box_reset_of_connectGui(sdfcar):
    """Guard for the fake itself: with connectGui (no tag before 5.10) the preset comes back as the first choice."""
    node = sdfcar.SDFCARLogic().getParameterNode()
    node.preset = "paper"
    ui = slicer_fakes.module_ui(sdfcar)
    first = sdfcar.SDFCARLogic().getParameterNode()
    first.disconnectGui(first.connectGui(ui))  # disconnectGui(None): the connectors stay live
    sdfcar.SDFCARLogic().getParameterNode().connectGui(ui)
    assert node.preset == "fast"


def test_reentering_the_module_keeps_preset_mode_and_device(sdfcar):
    node = sdfcar.SDFCARLogic().getParameterNode()
    node.preset, node.mode, node.device = "paper", "neca", "cpu"  # as a saved scene brings them
    widget = _widget(sdfcar)
    widget.initializeParameterNode()  # setup()
    for _ in range(3):
        widget.exit()
        widget.enter()
    assert (node.preset, node.mode, node.device) == ("paper", "neca", "cpu")
    assert widget.ui.presetComboBox.items[widget.ui.presetComboBox.currentIndex] == "paper"
    # The widget still drives the node: a choice made in the GUI reaches it.
    widget.ui.modeComboBox.currentIndex = sdfcar.MODES.index("sdf-occ")
    assert node.mode == "sdf-occ"


def test_a_new_scene_does_not_leave_the_old_connection_live(sdfcar):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    old = widget._parameterNode
    widget.onSceneStartClose(None, None)
    assert old._parameterGUIs == {}, "the old parameter node still drives the widgets"
    widget.onSceneEndClose(None, None)
    assert len(widget._parameterNode._parameterGUIs) == 1


# --- dependencies ----------------------------------------------------------------------------------------
def test_missing_dependencies_sees_a_package_installed_while_running(sdfcar, tmp_path, monkeypatch):
    """pip installs into a folder whose listing the import system has cached: find_spec must not trust it."""
    monkeypatch.syspath_prepend(str(tmp_path))
    name = "sdfcar_probe_installed_later"
    assert importlib.util.find_spec(name) is None  # caches the folder's listing
    before = os.stat(tmp_path).st_mtime_ns
    (tmp_path / name).mkdir()
    (tmp_path / name / "__init__.py").write_text("")
    os.utime(tmp_path, ns=(before, before))  # same mtime: the cached listing looks current
    assert importlib.util.find_spec(name) is None, "the import system noticed by itself: the test proves nothing"
    assert sdfcar.SDFCARLogic.missingDependencies([name]) == []


def test_ensure_dependencies_says_what_is_still_missing_after_installing(sdfcar, monkeypatch):
    monkeypatch.setitem(sdfcar.REQUIREMENTS, "sdfcar_absent_module", "sdfcar-absent-package")
    assert sdfcar.SDFCARLogic().ensureDependencies(["sdfcar_absent_module"]) is False
    assert sdfcar.recorder.pipInstalls == [["sdfcar-absent-package"]]
    assert sdfcar.recorder.errors and "sdfcar-absent-package" in sdfcar.recorder.errors[-1]


def test_sample_case_asks_for_its_dependencies(sdfcar, monkeypatch):
    monkeypatch.setitem(sys.modules, "nrrd", None)  # find_spec: not importable
    with pytest.raises(RuntimeError, match="pynrrd"):
        sdfcar.SDFCARLogic().loadSampleCase()
    sdfcar.recorder.confirm = False  # the user declines the installation
    assert sdfcar.loadSampleCaseAsking() == []
    assert sdfcar.recorder.pipInstalls == []


def test_declining_the_sample_cases_install_from_the_console_asks_once(sdfcar, monkeypatch):
    """SampleData.downloadSample retries a load that returned False up to three times, at once."""
    asked = []
    monkeypatch.setattr(sdfcar, "loadSampleCaseAsking", lambda: asked.append(1) or [])
    monkeypatch.setattr(sdfcar.SDFCARFileReader, "refusedAt", None)
    reader = sdfcar.SDFCARFileReader(parent=None)
    assert [reader.load({}) for _ in range(3)] == [False, False, False]
    assert asked == [1]
    monkeypatch.setattr(sdfcar.SDFCARFileReader, "refusedAt", sdfcar.time.monotonic() - 10.0)  # a later, new request
    assert reader.load({}) is False and asked == [1, 1]


def test_self_test_skips_without_dependencies(sdfcar, monkeypatch):
    """The py_SDFCAR ctest on a build machine without torch: skipped, not failed."""
    monkeypatch.setitem(sdfcar.REQUIREMENTS, "sdfcar_absent_module", "sdfcar-absent-package")
    for name in ("test_SelfTestScenario", "test_WorkerReconstruction"):
        result = unittest.TestResult()
        sdfcar.SDFCARTest(name).run(result)
        assert (len(result.skipped), result.failures, result.errors) == (1, [], []), name


def test_reload_and_test_says_a_skipped_self_test_rather_than_failing(sdfcar, monkeypatch):
    """Reload and Test calls the test case directly: its SkipTest (no torch) would show as a failure dialog."""
    monkeypatch.setitem(sdfcar.REQUIREMENTS, "sdfcar_absent_module", "sdfcar-absent-package")
    try:
        sdfcar.SDFCAR(types.SimpleNamespace()).runTest()
    except unittest.SkipTest as exc:  # pytest would count it a skip, the application shows a failure
        pytest.fail(f"the skip reached Reload and Test: {exc}")
    assert sdfcar.recorder.infos and "self-test was skipped" in sdfcar.recorder.infos[-1]
    assert "sdfcar-absent-package" in sdfcar.recorder.infos[-1]


# --- DICOM module disabled ---------------------------------------------------------------------------------
def test_read_geometry_without_the_dicom_module(sdfcar, monkeypatch):
    from SDFCARLib import mrml

    assert not hasattr(sys.modules["slicer"], "dicomDatabase")  # as when the DICOM module is disabled
    monkeypatch.setattr(mrml, "dicom_frame_reference", lambda scene, node, index: ("1.2.3.4", None), raising=False)
    node = sdfcar.SDFCARLogic().getParameterNode()
    with pytest.raises(ValueError, match="DICOM module"):
        sdfcar.SDFCARLogic().readGeometryFromDicom(node)


class _FrameNode(str):
    """A frame volume node of these tests: its name, and the attributes a user set on it."""

    def __new__(cls, name, attributes=None):
        node = super().__new__(cls, name)
        node.attributes = dict(attributes or {})
        return node

    def GetAttribute(self, key):
        return self.attributes.get(key)

    def GetName(self):
        return str(self)


def test_the_frames_pixel_intensity_relationship_goes_with_the_job(sdfcar, monkeypatch, tmp_path):
    """A frame loaded from the DICOM database carries its file's (0028,1040) to the job, which reads path lengths
    only off LIN frames; a LOG frame goes on a linear scale, whichever way its values run; a frame from elsewhere
    carries None and goes as it is."""
    from SDFCARLib import mrml
    from SDFCARLib.dicom.intensity import linear_from_log
    from xa_writer import write_xa

    import numpy as np

    stored = np.arange(64, dtype=np.uint16).reshape(8, 8) * 50 + 100  # a LOG frame, larger = more intensity
    files = {}
    for uid, extra in (("1.2.3.1", {"PixelIntensityRelationship": "DISP"}), ("1.2.3.2", {}),
                       ("1.2.3.3", {"PixelIntensityRelationship": "LOG", "PixelIntensityRelationshipSign": 1}),
                       ("1.2.3.4", {"PixelIntensityRelationship": "LOG", "PixelIntensityRelationshipSign": -1})):
        photometric = "MONOCHROME1" if uid == "1.2.3.4" else "MONOCHROME2"
        files[uid] = str(write_xa(tmp_path / f"{uid}.dcm", stored[None], bits_stored=12, photometric=photometric,
                                  extra=extra))
    references = {"disp": "1.2.3.1", "lin": "1.2.3.2", "png": None, "log": "1.2.3.3", "log-mono1": "1.2.3.4",
                  "png-said-lin": None, "disp-said-lin": "1.2.3.1"}
    monkeypatch.setattr(mrml, "dicom_frame_reference", lambda scene, node, index: (references[node], None), raising=False)
    monkeypatch.setattr(sys.modules["slicer"], "dicomDatabase", types.SimpleNamespace(fileForInstance=files.get),
                        raising=False)
    said = {"SDFCAR.PixelIntensityRelationship": "lin"}  # what the user set from the console: it wins over the file
    nodes = [_FrameNode(name, said if "said" in name else None) for name in references]
    # the arrays as Slicer's DICOM reader (GDCM) gives them: larger = brighter, MONOCHROME1 mirrored
    arrays = [stored.astype(np.float32)] * len(nodes)
    frames, relationships, notes = sdfcar.SDFCARLogic.jobFrames(arrays, nodes, [-1] * len(nodes))
    assert relationships == ["DISP", "LIN", None, "LIN", "LIN", "LIN", "LIN"]
    assert notes[:3] == [None, None, None] and all("LOG" in note for note in notes[3:5])  # for the job's report.json
    assert notes[5:] == [None, None]
    for kept in frames[:3] + frames[5:]:
        np.testing.assert_array_equal(kept, stored)
    linear = linear_from_log(stored, True, 12)
    np.testing.assert_allclose(frames[3], linear, rtol=1e-6)
    np.testing.assert_allclose(frames[4], linear, rtol=1e-6)  # sign −1 of the stored values, mirrored by the reader
    with pytest.raises(ValueError, match="SDFCAR.PixelIntensityRelationship.*LIN.*DISP"):
        sdfcar.SDFCARLogic.jobFrames(arrays[:1], [_FrameNode("png", {"SDFCAR.PixelIntensityRelationship": "raw"})], [-1])


def test_the_vesselness_mask_of_a_frame_processed_for_display_does_not_trim_its_edges(sdfcar, monkeypatch, tmp_path):
    """The Vesselness button on a frame whose DICOM file says DISP (or a vendor's term) segments it as the command
    line does such a run (masks.mask_settings_for_intensity); a frame from elsewhere gets the usual rule."""
    import contextlib

    import numpy as np

    from SDFCARLib import mrml
    from SDFCARLib.masks import DISPLAY_EDGE_FRACTION, AngioMaskSettings
    from xa_writer import write_xa

    stored = np.full((1, 8, 8), 100, np.uint16)
    files = {"1.2.3.1": str(write_xa(tmp_path / "disp.dcm", stored, bits_stored=8, extra={"PixelIntensityRelationship": "DRM"})),
             "1.2.3.2": str(write_xa(tmp_path / "lin.dcm", stored, bits_stored=8, extra={"PixelIntensityRelationship": "LIN"}))}
    references = {"drm": "1.2.3.1", "lin": "1.2.3.2", "png": None}
    monkeypatch.setattr(mrml, "dicom_frame_reference", lambda scene, node, index: (references[node], None), raising=False)
    monkeypatch.setattr(sys.modules["slicer"], "dicomDatabase", types.SimpleNamespace(fileForInstance=files.get),
                        raising=False)
    used = []
    monkeypatch.setattr("SDFCARLib.masks.angiogram_mask",
                        lambda frame, spacing, magnification, settings=None: used.append(settings) or (np.zeros((8, 8), bool), {}))
    monkeypatch.setattr(mrml, "scene_transaction", lambda scene: contextlib.nullcontext())
    monkeypatch.setattr(mrml, "set_segment_mask", lambda *args: None)
    references.update({"png8": None, "png8-said-lin": None})
    logic = sdfcar.SDFCARLogic()
    eight_bit = np.arange(64, dtype=np.uint8).reshape(8, 8) * 4  # a viewer's 8-bit export
    monkeypatch.setattr(logic, "frameArray", lambda node, index: eight_bit if "png8" in node else np.zeros((8, 8)))
    monkeypatch.setattr(logic, "maskSegmentation", lambda node, mask: types.SimpleNamespace(SetAttribute=lambda *a: None))
    for name in ("drm", "lin", "png", "png8", "png8-said-lin"):
        said = {"SDFCAR.PixelIntensityRelationship": "LIN"} if "said" in name else None
        logic.vesselnessMask(_FrameNode(name, said), -1)
    # an 8-bit frame nothing is known of is taken as processed for display, unless the user said it is linear
    assert [s.edge_fraction for s in used] == [DISPLAY_EDGE_FRACTION, AngioMaskSettings().edge_fraction,
                                               AngioMaskSettings().edge_fraction, DISPLAY_EDGE_FRACTION,
                                               AngioMaskSettings().edge_fraction]
    assert not any(s.bright_vessels for s in used)
    logic.vesselnessMask(_FrameNode("drm", None), -1, brightVessels=True)  # an inverted export, said so
    assert used[-1].bright_vessels and used[-1].edge_fraction == DISPLAY_EDGE_FRACTION


# --- Sample Data from the console ----------------------------------------------------------------------------
def _register_5_6(category="Custom", sampleName=None, uris=None, fileNames=None, nodeNames=None, customDownloader=None,
                  thumbnailFileName=None, loadFileType="VolumeFile", loadFiles=None, loadFileProperties={}, checksums=None):
    """SampleDataLogic.registerCustomSampleDataSource's signature at v5.4.0 and v5.6.2."""


def _register_5_8(category="Custom", sampleName=None, uris=None, fileNames=None, nodeNames=None, customDownloader=None,
                  thumbnailFileName=None, loadFileTypes=None, loadFiles=None, loadFileProperties={}, checksums=None):
    """SampleDataLogic.registerCustomSampleDataSource's signature from v5.8.0 to main."""


@pytest.mark.parametrize("signature", [_register_5_6, _register_5_8], ids=["5.4-5.6", "5.8-main"])
def test_download_sample_loads_the_case_with_the_module_reader(sdfcar, monkeypatch, signature):
    """SampleData.downloadSample() ignores customDownloader (all versions): it loads each file with
    the reader of the source's file type, which must be SDFCARFileReader's."""
    calls = []

    def register(*args, **kwargs):
        inspect.signature(signature).bind(*args, **kwargs)  # TypeError on a keyword that version lacks
        calls.append(inspect.signature(signature).bind(*args, **kwargs).arguments)

    register.__signature__ = inspect.signature(signature)
    monkeypatch.setitem(sys.modules, "SampleData", types.SimpleNamespace(
        SampleDataLogic=types.SimpleNamespace(registerCustomSampleDataSource=register)))
    sdfcar.registerSampleData()
    (arguments,) = calls
    fileType = arguments.get("loadFileTypes", arguments.get("loadFileType"))
    reader = sdfcar.SDFCARFileReader(parent=None)
    assert fileType == reader.fileType(), "downloadSample would load the file with another reader"
    assert reader.canLoadFile(arguments["fileNames"])
    assert arguments["sampleName"] == "SDFCAR two-view case"


# --- warnings of a run reach the user ------------------------------------------------------------------
def test_report_warnings_and_warning_progress_are_shown(sdfcar, tmp_path):
    """Mask warnings (noise specks, a segmented collimator edge) were written to report.json only."""
    report = tmp_path / "report.json"
    report.write_text('{"warnings": ["view 1: the mask has 300 specks"]}', encoding="utf-8")
    assert sdfcar.reportWarnings({"report": str(report)}) == ["view 1: the mask has 300 specks"]
    assert sdfcar.reportWarnings({"report": str(tmp_path / "missing.json")}) == []
    line = sdfcar.describeProgress({"phase": "warning", "message": "view 2: 30 % of the image's border", "step": 0})
    assert line.startswith("Warning: view 2")



def test_motion_correction_checkbox_asks_for_the_calibration(sdfcar):
    node = sdfcar.SDFCARLogic().getParameterNode()
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    assert "calibrate" not in sdfcar.SDFCARLogic.settings(node)  # off by default: it costs several fits
    assert widget.ui.correctMotionCheckBox.property("SlicerParameterName") == "correctMotion"
    node.correctMotion = True  # what the check box writes (the fake connects only combo boxes)
    settings = sdfcar.SDFCARLogic.settings(node)
    assert settings["calibrate"] is True
    from SDFCARLib.settings import make_settings

    assert make_settings(**settings).calibration.calibrate  # a key the engine knows
    line = sdfcar.describeProgress({"phase": "calibrate", "message": "view 2: +2.00 mm → loss 0.00051"})
    assert "view 2: +2.00 mm" in line



def test_a_cancelled_or_failed_job_says_so_and_gives_no_files(sdfcar):
    from SDFCARLib.jobs import JobFailed

    class Job:
        def __init__(self, error=None):
            self.error = error

        def result(self):
            if self.error:
                raise self.error
            return {"report": "report.json"}

    label = types.SimpleNamespace(text="")
    assert sdfcar.finishedJobFiles(Job(), "cancelled", label, "The 3D-QCA") is None
    assert label.text == "The 3D-QCA was cancelled: the scene is unchanged."
    failed = JobFailed("ValueError: no vessel", "Traceback …")
    assert sdfcar.finishedJobFiles(Job(failed), "failed", label, "The reconstruction") is None
    assert label.text == "The reconstruction failed: the scene is unchanged."
    assert sdfcar.recorder.errors[-1] == "The reconstruction failed: ValueError: no vessel"
    assert sdfcar.finishedJobFiles(Job(), "finished", label, "The reconstruction") == {"report": "report.json"}

# --- views 3, 4, … ------------------------------------------------------------------------------------------
def _node(class_name, name):
    return slicer_fakes.FakeNode(class_name, name)


def _three_views(sdfcar, widget):
    """Views 1 and 2 complete; view 3 added through the button, with a frame only."""
    p = widget._parameterNode
    for n in (1, 2):
        setattr(p, f"frame{n}", _node("vtkMRMLScalarVolumeNode", f"frame {n}"))
        setattr(p, f"mask{n}", _node("vtkMRMLLabelMapVolumeNode", f"mask {n}"))
    p.sid2 = 1100.0
    widget.ui.addViewButton.emit("clicked(bool)", False)
    return p


def test_add_view_builds_a_row_that_edits_the_parameter_node(sdfcar):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    assert widget._viewRows == []
    p = _three_views(sdfcar, widget)
    (row,) = widget._viewRows
    assert row.n == 3 and row.box in widget.ui.additionalViewsWidget.layout().items
    # SID, SOD and pixel spacing start as the last view's: the same C-arm.
    assert row.spinBoxes["sid"].value == 1100.0 and sdfcar.SDFCARLogic.viewValue(p, 3, "sid") == 1100.0
    assert "view 3" in widget.ui.statusLabel.text.lower()
    # Without a frame and mask for view 3, Apply says what is missing.
    assert not widget.ui.applyButton.enabled and widget.ui.applyButton.toolTip == "Choose the frame of view 3 (or remove the view)"
    frame = _node("vtkMRMLScalarVolumeNode", "frame 3")
    row.frameSelector.setCurrentNode(frame)  # the user picks the frame
    row.spinBoxes["primaryAngle"].emit("valueChanged(double)", -12.5)
    row.frameIndexSpinBox.emit("valueChanged(int)", 4)
    view = widget.logic.viewParameters(p, 3)
    assert (view.frame, view.primaryAngle, view.frameIndex) == (frame, -12.5, 4)
    assert p.parameterNode.GetParameter("frame3Index") == "4"
    widget._checkCanApply()
    assert row.editMaskButton.enabled and widget.ui.applyButton.toolTip.startswith("Choose the mask of view 3")
    row.maskSelector.setCurrentNode(_node("vtkMRMLSegmentationNode", "mask 3"))
    widget._checkCanApply()
    assert widget.ui.applyButton.enabled and widget.ui.applyButton.toolTip == "Reconstruct the coronary tree"


def test_values_from_the_node_do_not_echo_back(sdfcar, monkeypatch):
    """A value set in the node (a scene loaded, the console) is shown, not written back by the row."""
    from SDFCARLib.mrml import parameter_views

    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    p = _three_views(sdfcar, widget)
    writes = []
    monkeypatch.setattr(sdfcar.SDFCARLogic, "setViewValue", staticmethod(lambda *a: writes.append(a)))
    parameter_views.set_view_value(p.parameterNode, 3, "sod", 800.0)
    parameter_views.set_view_value(p.parameterNode, 3, "frame", _node("vtkMRMLScalarVolumeNode", "from the console"))
    row = widget._viewRows[0]
    assert row.spinBoxes["sod"].value == 800.0 and row.frameSelector.currentNode().GetName() == "from the console"
    assert writes == []


def test_removing_a_middle_view_keeps_the_later_ones_and_the_nodes(sdfcar):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    p = _three_views(sdfcar, widget)
    widget.ui.addViewButton.emit("clicked(bool)", False)
    three, four = widget._viewRows
    frame4 = _node("vtkMRMLScalarVolumeNode", "frame 4")
    four.frameSelector.setCurrentNode(frame4)
    four.spinBoxes["secondaryAngle"].emit("valueChanged(double)", 30.0)
    three.removeButton.emit("clicked(bool)", False)
    assert len(widget._viewRows) == 1 and four.box.deleted
    (row,) = widget._viewRows
    assert row.frameSelector.currentNode() is frame4 and row.spinBoxes["secondaryAngle"].value == 30.0
    assert sdfcar.SDFCARLogic.viewCount(p) == 3 and slicer_fakes.SCENE[frame4.GetID()] is frame4
    assert "still in the scene" in widget.ui.statusLabel.text


def test_a_closed_scene_leaves_no_view_rows(sdfcar):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    _three_views(sdfcar, widget)
    row = widget._viewRows[0]
    widget.onSceneStartClose(None, None)
    assert widget._viewRows == [] and row.box.deleted


def _fake_inputs(sdfcar, monkeypatch, shape=(20, 30)):
    import numpy as np

    monkeypatch.setattr(sdfcar.SDFCARLogic, "frameArray", lambda self, node, index=-1: np.zeros(shape, np.float32))
    monkeypatch.setattr(sdfcar.SDFCARLogic, "maskArray", lambda self, mask, frame, index=-1: np.ones(shape, bool))
    monkeypatch.setattr(sdfcar.SDFCARLogic, "frameNode", staticmethod(lambda node, index=-1: node))


def test_apply_sends_every_view_to_the_job(sdfcar, monkeypatch):
    _fake_inputs(sdfcar, monkeypatch)
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    p = _three_views(sdfcar, widget)
    row = widget._viewRows[0]
    row.frameSelector.setCurrentNode(_node("vtkMRMLScalarVolumeNode", "frame 3"))
    row.maskSelector.setCurrentNode(_node("vtkMRMLSegmentationNode", "mask 3"))
    row.spinBoxes["secondaryAngle"].emit("valueChanged(double)", 30.0)
    p.analyseAfterReconstruction = True
    started = {}
    from SDFCARLib import mrml

    # these fake frames were not loaded from the DICOM database (the fake scene has no sequence nodes to look in)
    monkeypatch.setattr(mrml, "dicom_frame_reference", lambda scene, node, index: (None, None), raising=False)
    monkeypatch.setattr(sdfcar.SDFCARLogic, "_startJob", staticmethod(
        lambda jobDir, geometry, masks, settings, name, frames=None, frameIntensity=None, frameNotes=None:
        started.update(geometry=geometry, masks=masks, frames=frames, intensity=frameIntensity, notes=frameNotes) or "job"))
    job, context = widget.logic.startReconstruction(p)
    geometry = started["geometry"]
    assert len(started["masks"]) == 3 and len(geometry.views) == 3 and len(context["frameNodes"]) == 3
    assert [f.shape for f in started["frames"]] == [m.shape for m in started["masks"]]  # the frames go with the job
    assert started["intensity"] == [None, None, None]  # none of these frames came from the DICOM database
    assert started["notes"] == [None, None, None]
    assert (geometry.views[2].secondary_deg, geometry.views[1].sid_mm, geometry.views[2].sid_mm) == (30.0, 1100.0, 1100.0)
    assert geometry.views[2].detector_shape == (20, 30) and context["analyse"] is True


def test_the_grey_levels_box_says_what_each_frame_is_and_the_run_reads_it(sdfcar, monkeypatch):
    """Each view's "Grey levels" box writes what the user chose on the frame node (the run and Vesselness read it
    there, before the DICOM file's tags), shows what a frame node already carries without writing it back, follows
    the frame chosen, and shows a value that is no choice as the file's with the reason (the run refuses it)."""
    from SDFCARLib import mrml

    monkeypatch.setattr(mrml, "dicom_frame_reference", lambda scene, node, index: (None, None), raising=False)
    attribute = mrml.FRAME_INTENSITY_ATTRIBUTE
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    p = _three_views(sdfcar, widget)
    widget._checkCanApply()
    box1, box2, row = widget.ui.frame1IntensityComboBox, widget.ui.frame2IntensityComboBox, widget._viewRows[0]
    labels = [label for _, label in sdfcar.FRAME_INTENSITY_CHOICES]
    assert box1.items == box2.items == row.intensityComboBox.items == labels
    assert (box1.currentIndex, box1.enabled) == (0, True) and p.frame1.GetAttribute(attribute) is None
    assert not row.intensityComboBox.enabled  # view 3 has no frame yet
    box1.currentIndex = 1  # the user: linear
    assert p.frame1.GetAttribute(attribute) == "LIN" and "Frame 1" in widget.ui.statusLabel.text
    assert sdfcar.SDFCARLogic.frameIntensityTags(p.frame1).relationship == "LIN"
    box1.currentIndex = 0  # as the file says: nothing said any more
    assert p.frame1.GetAttribute(attribute) is None and sdfcar.SDFCARLogic.frameIntensityTags(p.frame1) is None
    p.frame2.SetAttribute(attribute, "disp")  # from the console
    widget._checkCanApply()
    assert box2.currentIndex == 2 and p.frame2.GetAttribute(attribute) == "disp"  # shown, not written back
    p.frame2.SetAttribute(attribute, "raw")
    widget._checkCanApply()
    assert box2.currentIndex == 0 and "'raw'" in box2.toolTip and p.frame2.GetAttribute(attribute) == "raw"
    with pytest.raises(ValueError, match="'raw'.*LIN or DISP"):
        sdfcar.SDFCARLogic.frameIntensityTags(p.frame2)
    frame3, other = _node("vtkMRMLScalarVolumeNode", "frame 3"), _node("vtkMRMLScalarVolumeNode", "frame 3b")
    row.frameSelector.setCurrentNode(frame3)
    widget._checkCanApply()
    assert row.intensityComboBox.enabled
    row.intensityComboBox.currentIndex = 2
    assert frame3.GetAttribute(attribute) == "DISP"
    row.frameSelector.setCurrentNode(other)  # the box shows the frame now chosen; the first keeps its own
    widget._checkCanApply()
    assert row.intensityComboBox.currentIndex == 0 and other.GetAttribute(attribute) is None
    assert frame3.GetAttribute(attribute) == "DISP"


def test_console_reconstruct_views_checks_the_counts(sdfcar, monkeypatch):
    from SDFCARLib.geometry import standard_geometry

    _fake_inputs(sdfcar, monkeypatch)
    geometry = standard_geometry("lao30-rao30")
    frames = [_node("vtkMRMLScalarVolumeNode", f"f{n}") for n in (1, 2, 3)]
    masks = [_node("vtkMRMLLabelMapVolumeNode", f"m{n}") for n in (1, 2, 3)]
    with pytest.raises(ValueError, match="3 frame\\(s\\), 3 mask\\(s\\) and 3 frame index\\(es\\) for a geometry of 2 views"):
        sdfcar.SDFCARLogic().reconstructViews(frames, masks, geometry)
    calls = []
    monkeypatch.setattr(sdfcar.SDFCARLogic, "reconstructViews", lambda self, *a: calls.append(a) or "nodes")
    assert sdfcar.SDFCARLogic().reconstruct(frames[0], masks[0], frames[1], masks[1], geometry, frameIndices=(2, 5)) == "nodes"
    assert calls[0][0] == frames[:2] and calls[0][1] == masks[:2] and calls[0][5] == [2, 5]


def test_the_sample_geometry_sets_the_number_of_views(sdfcar):
    from SDFCARLib.geometry import standard_geometry

    logic = sdfcar.SDFCARLogic()
    p = logic.getParameterNode()
    logic.addView(p)
    logic.addView(p)
    geometry = standard_geometry("lao30-rao30")
    logic.setGeometryParameters(p, geometry)
    assert logic.viewCount(p) == 2 and p.primaryAngle2 == geometry.views[1].primary_deg


# --- results: QA panel, analysis -------------------------------------------------------------------------------
class _FinishedJob:
    def __init__(self, files):
        self.files = files
        self.state = "finished"

    def poll(self):
        return {"phase": "done", "step": 1, "total": 1}

    def result(self):
        return self.files


def _result_node(tmp_path, with_analysis=False):
    import json

    folder = tmp_path / "result"
    folder.mkdir(exist_ok=True)
    qa = {"dice": 0.9, "area_mm2": {"result_only": 2.0, "mask_only": 9.5}, "share_of_mask": {"result_only": 0.01,
                                                                                             "mask_only": 0.12},
          "largest_blob": {"result_only": None, "mask_only": {"area_mm2": 6.0}}}
    calibration = {"method": "epipolar consistency of the frames' vessel line integrals", "views": [
        {"view": 2, "object_rotation_deg": [0.6, 0.8, 0.0], "object_translation_mm": [0.0, 0.0, 1.2],
         "consistency_gain": 4.1, "untruncated_consistency_gain": 3.2},
        {"view": 3, "left_as_given": True, "why_left_as_given": "the motion found reached the end of its range"}]}
    (folder / "report.json").write_text(json.dumps({"reprojection_qa": [qa, qa, qa], "calibration": calibration,
                                                    "warnings": ["view 3: the result does not explain 9.5 mm²"]}))
    node = _node("vtkMRMLSegmentationNode", "Tree")
    node.SetAttribute("SDFCAR.resultFolder", str(folder))
    if with_analysis:
        (folder / "analysis").mkdir()
        (folder / "analysis" / "analysis.json").write_text(json.dumps(
            {"tree": {"branches": 3, "total_length_mm": 80.0}, "lesions": [],
             "best_view": {"primary_deg": 40.0, "secondary_deg": -10.0, "label": "LAO 40 CAU 10", "foreshortening": 0.01,
                           "overlap": 0.0}}))
        node.SetAttribute("SDFCAR.analysisFolder", str(folder / "analysis"))
    return node


def test_results_panel_shows_the_qa_of_each_view(sdfcar, tmp_path):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    assert widget.ui.qaLabel.text.startswith("Choose a result") and not widget.ui.analyseButton.enabled
    widget._parameterNode.result = _result_node(tmp_path)
    widget._checkCanApply()
    text = widget.ui.qaLabel.text
    assert text.splitlines()[0].startswith("View 1: Dice 0.900") and "View 3" in text and "1 warning(s):" in text
    # what the frames' motion search did to each view's pose, before the warnings
    assert ("View 2: pose corrected from the frames: its object turned 1.00° and moved 1.20 mm (the views 4.10× more "
            "consistent; 3.20× on the planes no collimator cuts).") in text.splitlines()
    assert "View 3: pose left as given from the frames: the motion found reached the end of its range." in text
    assert widget.ui.qaViewSpinBox.maximum == 3
    assert widget.ui.analyseButton.enabled and widget.ui.showQAButton.enabled and not widget.ui.suggestedViewButton.enabled
    assert widget.ui.analysisLabel.text.startswith("Not analysed yet")
    widget._parameterNode.result = _result_node(tmp_path, with_analysis=True)
    widget._checkCanApply()
    assert widget.ui.suggestedViewButton.enabled and "suggested view: LAO 40 CAU 10" in widget.ui.analysisLabel.text


def test_a_result_whose_files_are_gone_says_so(sdfcar, tmp_path):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    node = _node("vtkMRMLSegmentationNode", "Moved")
    node.SetAttribute("SDFCAR.resultFolder", str(tmp_path / "gone"))
    node.GetStorageNode = lambda: None
    widget._parameterNode.result = node
    widget._checkCanApply()
    assert "were not found" in widget.ui.qaLabel.text
    with pytest.raises(ValueError, match="were not found"):
        widget.logic.startAnalysis(node)


def test_analyse_passes_the_segment_and_the_ostium_the_chosen_point_lists_mark(sdfcar, tmp_path, monkeypatch):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    result = _result_node(tmp_path)
    started = []
    monkeypatch.setattr(sdfcar.SDFCARLogic, "startAnalysis", staticmethod(
        lambda node, outputDir=None, options=None: started.append(options) or (_FinishedJob({}), {"name": node.GetName()})))
    monkeypatch.setattr(sdfcar.SDFCARLogic, "segmentFromPoints",
                        staticmethod(lambda node: None if node is None else [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]))
    monkeypatch.setattr(sdfcar.SDFCARLogic, "ostiumFromPoint",
                        staticmethod(lambda node: None if node is None else [7.0, 8.0, 9.0]))
    widget._startAnalysis(result)
    widget.ui.segmentPointsSelector.setCurrentNode(_node("vtkMRMLMarkupsFiducialNode", "ends"))
    widget._startAnalysis(result)
    widget.ui.ostiumPointSelector.setCurrentNode(_node("vtkMRMLMarkupsFiducialNode", "ostium"))
    widget._startAnalysis(result)
    widget.ui.segmentPointsSelector.setCurrentNode(None)
    widget._startAnalysis(result)
    segment, ostium = {"segment_mm": [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]}, {"ostium_mm": [7.0, 8.0, 9.0]}
    assert started == [None, segment, {**segment, **ostium}, ostium]


def test_finished_reconstruction_selects_its_result_and_analyses_it(sdfcar, tmp_path, monkeypatch):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    result = _result_node(tmp_path)
    added, analysed = [], []
    monkeypatch.setattr(sdfcar.SDFCARLogic, "addResults", lambda self, files, context: added.append(files) or
                        types.SimpleNamespace(segmentation=result))
    analysis = _FinishedJob({"folder": str(tmp_path / "result" / "analysis")})
    analysis.state = "running"
    monkeypatch.setattr(sdfcar.SDFCARLogic, "startAnalysis", staticmethod(
        lambda node, *a, **k: analysed.append(node) or (analysis, {"name": node.GetName(), "resultNode": node})))
    loaded = []
    monkeypatch.setattr(sdfcar.SDFCARLogic, "addAnalysis", lambda self, files, context: loaded.append(files))
    widget._job = _FinishedJob({"report": str(tmp_path / "result" / "report.json")})
    widget._jobContext = {"name": "Tree", "jobDir": str(tmp_path), "analyse": True}
    widget.onPollJob()
    assert added and widget._parameterNode.result is result and analysed == [result]
    assert widget._analysisJob is analysis and not widget.ui.analyseButton.enabled and not loaded
    analysis.state = "finished"
    widget.onPollJob()
    assert loaded and widget._analysisJob is None and widget.ui.analyseButton.enabled
    assert "3D-QCA of 'Tree' done" in widget.ui.statusLabel.text and "Ostium" not in widget.ui.statusLabel.text
    # an analysis whose root lies on a vessel's side adds the likeliest ostium: the status names it
    suggested = _node("vtkMRMLMarkupsFiducialNode", "Tree likeliest ostium")
    monkeypatch.setattr(sdfcar.SDFCARLogic, "addAnalysis", lambda self, files, context: {"likeliest_ostium": suggested})
    widget._analysisJob, widget._analysisContext = _FinishedJob({"folder": str(tmp_path)}), {"name": "Tree"}
    widget._pollAnalysis()
    assert "check the point list 'Tree likeliest ostium'" in widget.ui.statusLabel.text
    assert "choose it as the Ostium and press Analyse again" in widget.ui.statusLabel.text


def test_results_that_cannot_be_loaded_are_said_and_the_reports_warnings_still_shown(sdfcar, tmp_path, monkeypatch):
    """The error wrapper re-raises: the failure must not leave the timer's slot as a traceback before the
    report's warnings (which often say why) are shown."""
    import json

    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"warnings": ["view 1: the mask covers 0.001 % of the image"]}))

    def failing(self, files, context):
        raise ValueError("the segmentation has no voxel")

    monkeypatch.setattr(sdfcar.SDFCARLogic, "addResults", failing)
    widget._job = _FinishedJob({"report": str(report)})
    widget._jobContext = {"name": "Tree", "jobDir": str(tmp_path), "analyse": True}
    widget.onPollJob()  # no exception leaves the slot
    assert "could not be loaded" in sdfcar.recorder.errors[-1] and "no voxel" in sdfcar.recorder.errors[-1]
    assert "covers 0.001 %" in sdfcar.recorder.warnings[-1]
    assert "could not be loaded" in widget.ui.statusLabel.text and widget._analysisJob is None


def test_an_analysis_running_is_not_replaced_by_the_next_results_analysis(sdfcar, tmp_path, monkeypatch):
    widget = _widget(sdfcar)
    widget.initializeParameterNode()
    result = _result_node(tmp_path)
    monkeypatch.setattr(sdfcar.SDFCARLogic, "addResults", lambda self, files, context:
                        types.SimpleNamespace(segmentation=result))
    started = []
    monkeypatch.setattr(sdfcar.SDFCARLogic, "startAnalysis", staticmethod(lambda node, *a, **k: started.append(node)))
    running = _FinishedJob({})
    running.state = "running"
    widget._analysisJob, widget._analysisContext = running, {"name": "earlier"}
    widget._job = _FinishedJob({"report": str(tmp_path / "result" / "report.json")})
    widget._jobContext = {"name": "Tree", "jobDir": str(tmp_path), "analyse": True}
    widget.onPollJob()
    assert started == [] and widget._analysisJob is running
    assert "Another analysis is running" in widget.ui.statusLabel.text


def test_the_c_arm_sources_are_no_segment_to_measure(sdfcar):
    sources = _node("vtkMRMLMarkupsFiducialNode", "C-arm sources")
    sources.SetAttribute("SDFCAR.role", "carm-sources")  # as SDFCARLib.mrml.add_carm_geometry_to_scene marks it
    with pytest.raises(ValueError, match="holds the C-arm's X-ray sources"):
        sdfcar.SDFCARLogic.segmentFromPoints(sources)


def test_reading_the_geometry_from_dicom_changes_no_view_when_one_fails(sdfcar, monkeypatch):
    from SDFCARLib import dicom, mrml
    from SDFCARLib.geometry import CArmView

    uids = iter(["1.2.3.1", "1.2.3.2"])
    monkeypatch.setattr(mrml, "dicom_frame_reference", lambda scene, node, index: (next(uids), None))
    monkeypatch.setattr(sys.modules["slicer"], "dicomDatabase", types.SimpleNamespace(
        fileForInstance=lambda uid: "/data/run1.dcm" if uid == "1.2.3.1" else ""), raising=False)
    monkeypatch.setattr(dicom, "view_from_dicom", lambda path, frame=None, view_number=None: (
        CArmView(44.0, -11.0, 1111.0, 777.0, (0.2, 0.2), (512, 512)), {"notes": []}))
    logic = sdfcar.SDFCARLogic()
    p = logic.getParameterNode()
    before = [logic.viewValue(p, 1, field) for field in sdfcar.GEOMETRY_VIEW_FIELDS]
    with pytest.raises(ValueError, match="frame 2 was not loaded from the DICOM database"):
        logic.readGeometryFromDicom(p)
    assert [logic.viewValue(p, 1, field) for field in sdfcar.GEOMETRY_VIEW_FIELDS] == before  # view 1 as it was
    # both views read, view 2's values refused by the fields: view 1, already set, is put back
    uids = iter(["1.2.3.1", "1.2.3.1"])
    set_view = sdfcar.SDFCARLogic.setViewParameters

    def refuse_view_2(self, p, n, view):
        if n == 2:
            raise ValueError("secondaryAngle is outside its range")
        set_view(self, p, n, view)

    monkeypatch.setattr(sdfcar.SDFCARLogic, "setViewParameters", refuse_view_2)
    with pytest.raises(ValueError, match="outside its range"):
        logic.readGeometryFromDicom(p)
    assert [logic.viewValue(p, 1, field) for field in sdfcar.GEOMETRY_VIEW_FIELDS] == before


def _vesselness_widget(sdfcar, monkeypatch):
    """A widget whose view 1, 2, … has a frame, spacing and distances; returns it and the values it stores, as
    (view, field, value)."""
    widget = _widget(sdfcar)
    widget._parameterNode = types.SimpleNamespace()
    view = types.SimpleNamespace(frame="frame", frameIndex=0, mask=None, pixelSpacingRow=0.3, pixelSpacingCol=0.3,
                                 sid=1000.0, sod=750.0)
    stored = []
    monkeypatch.setattr(widget.logic, "ensureDependencies", lambda *args: True)
    monkeypatch.setattr(widget.logic, "viewParameters", lambda p, n: view)
    monkeypatch.setattr(widget.logic, "setViewValue", lambda p, n, field, value: stored.append((n, field, value)))
    return widget, stored


def _press_vesselness(sdfcar, monkeypatch, widget, n, vesselness, accepted):
    """Press view ``n``'s Vesselness with the logic's ``vesselness``, answering its one question; the question."""
    monkeypatch.setattr(widget.logic, "vesselnessMask", vesselness)
    sdfcar.recorder.confirm = accepted
    widget.onVesselness(n)
    (question,) = sdfcar.recorder.questions
    return question


@pytest.mark.parametrize("accepted", [True, False])
def test_vesselness_on_a_frame_showing_its_vessels_bright_offers_to_invert_it(sdfcar, monkeypatch, accepted):
    """The Vesselness button on an inverted export asks whether to segment it inverted, instead of only an error."""
    from SDFCARLib.masks import BrightVesselsError

    widget, stored = _vesselness_widget(sdfcar, monkeypatch)
    calls = []

    def vesselness(frame, index, mask, pixelSpacingMm=None, magnification=None, brightVessels=False):
        calls.append(brightVessels)
        if not brightVessels:
            raise BrightVesselsError("the vessels of this frame look bright, not dark")
        return "segmentation", {"vessel_fraction": 0.05, "components": 2}

    question = _press_vesselness(sdfcar, monkeypatch, widget, 2, vesselness, accepted)
    assert "look bright" in question and "frame 2 with its grey levels inverted" in question
    assert sdfcar.recorder.cursor == ["restored", "asked", "WaitCursor"]  # asked with the arrow, not the wait cursor
    assert calls == ([False, True] if accepted else [False])
    assert stored == ([(2, "mask", "segmentation")] if accepted else [])
    assert not sdfcar.recorder.errors


@pytest.mark.parametrize("accepted", [True, False])
def test_vesselness_asks_on_a_frame_of_doubtful_polarity_and_shows_the_masks_warnings(sdfcar, monkeypatch, accepted):
    widget, stored = _vesselness_widget(sdfcar, monkeypatch)
    calls = []
    clipped = "12 % of the exposed field is clipped at the frame's highest value (4095)"

    def vesselness(frame, index, mask, pixelSpacingMm=None, magnification=None, brightVessels=False):
        calls.append(brightVessels)
        if brightVessels:
            return "inverted", {"vessel_fraction": 0.05, "components": 1, "polarity": "inverted as told", "warnings": []}
        return "as it is", {"vessel_fraction": 0.05, "components": 3, "polarity": "doubtful",
                            "warnings": ["… segment it with bright_vessels (segment --bright-vessels)", clipped]}

    question = _press_vesselness(sdfcar, monkeypatch, widget, 1, vesselness, accepted)
    assert "may look bright" in question and "No keeps the mask" in question
    assert calls == ([False, True] if accepted else [False])
    assert stored == [(1, "mask", "inverted" if accepted else "as it is")]
    assert sdfcar.recorder.warnings == ([] if accepted else [clipped])  # the polarity one was asked, not shown again
    assert sdfcar.recorder.cursor == (["restored", "asked", "WaitCursor"] if accepted else
                                      ["restored", "asked", "WaitCursor", "restored", "warned", "WaitCursor"])
