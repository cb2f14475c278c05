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


@pytest.fixture
def sdfcar(monkeypatch):
    return slicer_fakes.install(monkeypatch)


def _widget(sdfcar):
    widget = sdfcar.SDFCARWidget()
    widget.ui = slicer_fakes.module_ui(sdfcar)
    widget.logic = sdfcar.SDFCARLogic()
    widget.parent = types.SimpleNamespace(isEntered=True)
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


def test_self_test_skips_without_dependencies(sdfcar, monkeypatch):
    """The py_SDFCAR ctest on a build machine without torch: skipped, not failed."""
    monkeypatch.setitem(sdfcar.REQUIREMENTS, "sdfcar_absent_module", "sdfcar-absent-package")
    for name in ("test_SelfTestScenario", "test_WorkerReconstruction"):
        result = unittest.TestResult()
        sdfcar.SDFCARTest(name).run(result)
        assert (len(result.skipped), result.failures, result.errors) == (1, [], []), name


# --- DICOM module disabled ---------------------------------------------------------------------------------
def test_read_geometry_without_the_dicom_module(sdfcar, monkeypatch):
    from SDFCARLib import mrml

    assert not hasattr(sys.modules["slicer"], "dicomDatabase")  # as when the DICOM module is disabled
    monkeypatch.setattr(mrml, "dicom_frame_reference", lambda scene, node, index: ("1.2.3.4", None), raising=False)
    node = sdfcar.SDFCARLogic().getParameterNode()
    with pytest.raises(ValueError, match="DICOM module"):
        sdfcar.SDFCARLogic().readGeometryFromDicom(node)


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
