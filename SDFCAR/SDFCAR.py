"""SDFCAR: 3D coronary artery tree from two or more X-ray angiography views (SDF-CAR), as a Slicer module.

A thin GUI over SDFCARLib: every computation lives in the library (``SDFCARLib.mrml`` for the scene,
``SDFCARLib.jobs`` for the background reconstruction and 3D-QCA, ``SDFCARLib.analysis`` for the
QCA nodes); this file only wires widgets to it.
"""

import json
import logging
import os
import re
import sys
import time
from pathlib import Path
from typing import Annotated, Optional, Union

import qt
import vtk

import slicer
from slicer import vtkMRMLLabelMapVolumeNode, vtkMRMLScalarVolumeNode, vtkMRMLSegmentationNode
from slicer.parameterNodeWrapper import Choice, WithinRange, parameterNodeWrapper
from slicer.ScriptedLoadableModule import (
    ScriptedLoadableModule,
    ScriptedLoadableModuleLogic,
    ScriptedLoadableModuleTest,
    ScriptedLoadableModuleWidget,
)
from slicer.util import VTKObservationMixin


def _addLibraryPath():
    """Put the folder holding SDFCARLib on sys.path: next to this file when installed as an
    extension, the repository root when the module is used from a source checkout."""
    here = Path(__file__).resolve().parent
    for folder in (here, here.parent):
        if (folder / "SDFCARLib" / "__init__.py").is_file():
            if str(folder) not in sys.path:
                sys.path.insert(0, str(folder))
            return folder
    return None


_addLibraryPath()

import SDFCARLib.settings as SDFCARSettings  # noqa: E402  (found through the path added above)

#: The one list of Python packages SDFCAR needs that Slicer does not bundle: import name -> pip
#: requirement. Slicer bundles numpy, scipy, pydicom, pillow, requests, packaging and VTK (its
#: SuperBuild/External_python-*.cmake), so they are not here. The worker process (PythonSlicer)
#: shares Slicer's site-packages, so what is installed here serves both. torch comes first: the
#: PyTorch extension's installer picks the build for the GPU when it is installed.
#: Testing/test_slicer_dependencies.py checks this list against every import of SDFCARLib.
REQUIREMENTS = {
    "torch": "torch",
    "skimage": "scikit-image",
    "nrrd": "pynrrd",  # the worker writes its results as NRRD
    "imageio": "imageio",  # the sample case's masks are PNG files
}
#: A view's fields that a CArmView fills (``setViewParameters``), in its order: angles, distances, pixel spacing.
GEOMETRY_VIEW_FIELDS = ("primaryAngle", "secondaryAngle", "sid", "sod", "pixelSpacingRow", "pixelSpacingCol")
#: Frames are scalar volumes and their kinds that hold images: an RGB export (PNG/JPEG) loads as a vector volume
#: (a child class, made grey when read); labelmaps and diffusion volumes are not frames. The .ui's frame selectors
#: list the same (Testing/test_module_static.py).
FRAME_HIDDEN_NODE_TYPES = ["vtkMRMLLabelMapVolumeNode", "vtkMRMLDiffusionWeightedVolumeNode", "vtkMRMLDiffusionImageVolumeNode"]
#: The grey-level choices of each view's frame, in its combo box's order: (what is said on the frame node, label);
#: SDFCARLib.mrml.say_frame_intensity stores it (Testing/test_module_static.py checks the values against the library's).
FRAME_INTENSITY_CHOICES = (("", "As the DICOM file says"), ("LIN", "Linear (raw detector intensities)"),
                           ("DISP", "Processed for display"))
FRAME_INTENSITY_TOOLTIP = (
    "How the frame's grey levels were made. As the DICOM file says: its Pixel Intensity Relationship (0028,1040); a "
    "frame with no DICOM file and 8-bit grey levels (a viewer's export, a screenshot) is taken as processed for display. "
    "Linear: the detector's intensities (LIN), from which the reconstruction also reads the vessels' path lengths. "
    "Processed for display: windowed, log-scaled, contrast- or edge-enhanced (DISP); only its mask is fitted. "
    "Kept on the frame node and saved with the scene.")

#: What each action needs, so a user who only loads the sample case is not asked for torch.
SAMPLE_REQUIREMENTS = ["nrrd", "imageio"]
VESSELNESS_REQUIREMENTS = ["skimage"]
# The 3D-QCA reads the result's NRRD files, skeletonises it and writes the masks as PNG files for
# the worker; matplotlib is optional there (the figures are skipped without it, Slicer plots instead).
ANALYSIS_REQUIREMENTS = ["skimage", "nrrd", "imageio"]
# The lists come from the library's torch-free settings module, so the GUI offers what the engine runs.
PRESETS = list(SDFCARSettings.PRESETS)
MODES = list(SDFCARSettings.MODES)
DEVICES = list(SDFCARSettings.DEVICES)


class SDFCAR(ScriptedLoadableModule):
    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "SDFCAR"
        self.parent.categories = ["Cardiac"]
        self.parent.dependencies = []
        self.parent.contributors = ["The SDFCAR authors"]
        self.parent.helpText = """
Reconstructs the 3D coronary artery tree from two or more X-ray angiography views by per-patient
self-supervised optimisation of a signed-distance field (SDF-CAR). Choose the frames (DICOM XA
runs or images) and their vessel masks — two views, plus any number under "Additional views" —
check the C-arm geometry (filled from the DICOM tags), and press Apply. The result is a
segmentation ("Coronary tree") and a surface model, with the settings, losses and versions stored
as node attributes (SDFCAR.*), and per view an overlay of the mask against the result's
projection (reprojection QA). "Analyse" measures the tree (3D-QCA: centrelines with diameters,
lesions, a diameter plot) and suggests the C-arm view that shows the worst lesion best.
Method: "SDF-CAR: 3D Coronary Artery Reconstruction from Two Views with a Hybrid SDF-Occupancy
Implicit Representation" (MIDL 2026 submission); please cite it (see Acknowledgment).
"""
        self.parent.acknowledgementText = """
Please cite the method when you use this module: "SDF-CAR: 3D Coronary Artery Reconstruction from
Two Views with a Hybrid SDF-Occupancy Implicit Representation" (under review for MIDL 2026; code
of the paper: <a href="https://github.com/reda1609/SDF-CAR">github.com/reda1609/SDF-CAR</a>).
It builds on NeCA (Wang et al., 2024). Not a medical device: for research use only.
"""
        slicer.app.connect("startupCompleted()", registerSampleData)

    def runTest(self, msec=100, **kwargs):
        """Reload and Test in the application (ScriptedLoadableModule.runTest calls the test case directly, at every
        tag): a test that cannot run here is said, not shown as a failure. ctest runs SDFCARTest through unittest,
        where the same test is a skip."""
        import unittest

        try:
            ScriptedLoadableModule.runTest(self, msec, **kwargs)
        except unittest.SkipTest as exc:
            logging.warning(f"SDFCAR self-test skipped: {exc}")
            slicer.util.infoDisplay(f"The SDFCAR self-test was skipped: {exc}", windowTitle="SDFCAR")


SAMPLE_NAME = "SDFCAR two-view case"
#: The file type of SDFCARFileReader, and the name the Sample Data module gives its cached copy.
SAMPLE_FILE_TYPE = "SDFCARSampleCase"
SAMPLE_FILE_NAME = "SDFCAR-sample.sdfcar.json"


def registerSampleData():
    """Register the bundled two-view sample case with the Sample Data module."""
    import inspect

    import SampleData

    if _addLibraryPath() is None:
        return
    from SDFCARLib.sample_data import SAMPLE_DIR

    iconsPath = os.path.join(os.path.dirname(__file__), "Resources", "Icons")
    register = SampleData.SampleDataLogic.registerCustomSampleDataSource
    # The console call SampleData.downloadSample(SAMPLE_NAME) ignores customDownloader (only the
    # module's button uses it) and loads each file with the IO manager's reader for its file
    # type; SDFCARFileReader below is that reader. The keyword is loadFileType up to Slicer 5.6
    # and loadFileTypes from 5.8 (SampleData.py); the 5.6 default, "VolumeFile", would read the
    # file as an image.
    fileTypeKeyword = "loadFileTypes" if "loadFileTypes" in inspect.signature(register).parameters else "loadFileType"
    register(
        category="SDFCAR",
        sampleName=SAMPLE_NAME,
        thumbnailFileName=os.path.join(iconsPath, "SDFCAR.png"),
        # Bundled files: nothing to download; the reader loads the case from the library folder.
        uris=(SAMPLE_DIR / "geometry.json").as_uri(),
        fileNames=SAMPLE_FILE_NAME,
        nodeNames="SDFCAR sample",
        customDownloader=lambda source: loadSampleCaseAsking(),
        **{fileTypeKeyword: SAMPLE_FILE_TYPE},
    )


def loadSampleCaseAsking():
    """Load the sample case after offering to install what it needs; returns the nodes it added
    (frame and mask of each view, then the ground truth), or [] when the user declines."""
    logic = SDFCARLogic()
    with slicer.util.tryWithErrorDisplay("Could not load the SDFCAR sample case.", waitCursor=True):
        if not logic.ensureDependencies(SAMPLE_REQUIREMENTS):
            return []
        truth = logic.loadSampleCase()
        p = logic.getParameterNode()
        return [p.frame1, p.mask1, p.frame2, p.mask2, truth]


class SDFCARFileReader:
    """Reads the sample case's marker file (found by Slicer by its name: <module>FileReader), so
    that SampleData.downloadSample("SDFCAR two-view case") loads the case from the console."""

    def __init__(self, parent):
        self.parent = parent

    def description(self):
        return "SDFCAR sample case"

    def fileType(self):
        return SAMPLE_FILE_TYPE

    def extensions(self):
        return ["SDFCAR sample case (*.sdfcar.json)"]

    def canLoadFile(self, filePath):
        return str(filePath).endswith(".sdfcar.json")

    #: monotonic time the last load was declined or failed. SampleData's downloadFromSource loads a file up to three
    #: times when a load returns False (SampleData.py, every tag since 5.4): the user is asked once, not three times.
    refusedAt = None
    RETRY_QUIET_S = 3.0

    def load(self, properties):
        refused = SDFCARFileReader.refusedAt
        if refused is not None and time.monotonic() - refused < SDFCARFileReader.RETRY_QUIET_S:
            return False  # SampleData's next attempt right after a decline or a failure: already answered
        try:
            nodes = loadSampleCaseAsking()
        except Exception:  # noqa: BLE001 - already shown to the user; the IO manager wants False
            logging.exception("Could not load the SDFCAR sample case")
            nodes = None
        if not nodes:
            SDFCARFileReader.refusedAt = time.monotonic()
            return False
        self.parent.loadedNodes = [node.GetID() for node in nodes]
        return True


@parameterNodeWrapper
class SDFCARParameterNode:
    frame1: vtkMRMLScalarVolumeNode
    frame1Index: Annotated[int, WithinRange(-1, 100000)] = -1
    mask1: Union[vtkMRMLSegmentationNode, vtkMRMLLabelMapVolumeNode, None]  # None: the wrapper needs it
    frame2: vtkMRMLScalarVolumeNode
    frame2Index: Annotated[int, WithinRange(-1, 100000)] = -1
    mask2: Union[vtkMRMLSegmentationNode, vtkMRMLLabelMapVolumeNode, None]
    primaryAngle1: Annotated[float, WithinRange(-180.0, 180.0)] = 30.0
    secondaryAngle1: Annotated[float, WithinRange(-90.0, 90.0)] = 0.0
    sid1: Annotated[float, WithinRange(1.0, 5000.0)] = 1000.0
    sod1: Annotated[float, WithinRange(1.0, 5000.0)] = 757.0
    pixelSpacingRow1: Annotated[float, WithinRange(0.001, 10.0)] = 0.278
    pixelSpacingCol1: Annotated[float, WithinRange(0.001, 10.0)] = 0.278
    primaryAngle2: Annotated[float, WithinRange(-180.0, 180.0)] = -30.0
    secondaryAngle2: Annotated[float, WithinRange(-90.0, 90.0)] = 0.0
    sid2: Annotated[float, WithinRange(1.0, 5000.0)] = 1000.0
    sod2: Annotated[float, WithinRange(1.0, 5000.0)] = 757.0
    pixelSpacingRow2: Annotated[float, WithinRange(0.001, 10.0)] = 0.278
    pixelSpacingCol2: Annotated[float, WithinRange(0.001, 10.0)] = 0.278
    volumeSize: Annotated[int, WithinRange(8, 512)] = 128
    voxelSpacing: Annotated[float, WithinRange(0.05, 10.0)] = 0.8
    centerR: Annotated[float, WithinRange(-1000.0, 1000.0)] = 0.0
    centerA: Annotated[float, WithinRange(-1000.0, 1000.0)] = 0.0
    centerS: Annotated[float, WithinRange(-1000.0, 1000.0)] = 0.0
    preset: Annotated[str, Choice(PRESETS)] = SDFCARSettings.DEFAULT_PRESET
    mode: Annotated[str, Choice(MODES)] = SDFCARSettings.DEFAULT_MODE
    device: Annotated[str, Choice(DEVICES)] = "auto"
    steps: Annotated[int, WithinRange(0, 1000000)] = 0
    seed: Annotated[int, WithinRange(0, 2147483647)] = 0
    outputName: str = "Coronary tree"
    outputDirectory: Path
    includeOccupancy: bool = False
    correctMotion: bool = False
    showCArm: bool = True
    # Views 3, 4, … are stored beside these fields with the node's own API (SDFCARLib.mrml.parameter_views).
    result: Optional[vtkMRMLSegmentationNode]  # the result the Results section shows and analyses
    analyseAfterReconstruction: bool = False


class AdditionalViewRow:
    """The widgets of one view after the first two, built in Python because their number changes
    (the .ui holds views 1 and 2). The ranges, decimals and units are those of the .ui's fields for
    views 1 and 2 (Testing/test_module_static.py checks them against SDFCARLib.mrml.parameter_views)."""

    #: (field, minimum, maximum, decimals, step, suffix, tooltip), in the order of the .ui's rows.
    NUMBER_FIELDS = (
        ("primaryAngle", -180.0, 180.0, 1, 1.0, "°", "Primary angle: LAO positive, RAO negative"),
        ("secondaryAngle", -90.0, 90.0, 1, 1.0, "°", "Secondary angle: cranial positive, caudal negative"),
        ("sid", 1.0, 5000.0, 1, 1.0, " mm", "Source to detector distance"),
        ("sod", 1.0, 5000.0, 1, 1.0, " mm", "Source to isocenter distance"),
        ("pixelSpacingRow", 0.001, 10.0, 4, 0.001, " mm", "Detector pixel spacing between rows"),
        ("pixelSpacingCol", 0.001, 10.0, 4, 0.001, " mm", "Detector pixel spacing between columns"),
    )

    def __init__(self, n):
        self.n = n
        self.updating = False  # True while the widgets are set from the parameter node
        self.box = qt.QGroupBox(f"View {n}")
        form = qt.QFormLayout(self.box)
        self.frameSelector = self._nodeSelector(["vtkMRMLScalarVolumeNode"],
                                                f"The X-ray frame of view {n}: a 2D image, or a cine run loaded by the DICOM module (sequence)",
                                                FRAME_HIDDEN_NODE_TYPES)
        form.addRow("Frame:", self.frameSelector)
        self.frameIndexSpinBox = qt.QSpinBox()
        self.frameIndexSpinBox.setRange(-1, 100000)
        self.frameIndexSpinBox.specialValueText = "shown"
        self.frameIndexSpinBox.toolTip = "For a cine run: the frame (0-based) to reconstruct from; 'shown' takes the frame on display"
        form.addRow("Frame index:", self.frameIndexSpinBox)
        self.intensityComboBox = qt.QComboBox()
        for _, label in FRAME_INTENSITY_CHOICES:
            self.intensityComboBox.addItem(label)
        self.intensityComboBox.toolTip = FRAME_INTENSITY_TOOLTIP
        form.addRow("Grey levels:", self.intensityComboBox)
        self.maskSelector = self._nodeSelector(["vtkMRMLSegmentationNode", "vtkMRMLLabelMapVolumeNode"],
                                               f"The vessels of frame {n}: a segmentation on the frame or a labelmap")
        self.editMaskButton = qt.QPushButton("Edit")
        self.editMaskButton.toolTip = f"Paint the vessels of frame {n} in Segment Editor (creates the segmentation if needed)"
        self.vesselnessButton = qt.QPushButton("Vesselness")
        self.vesselnessButton.toolTip = f"Seed the mask of frame {n} with a vesselness filter; refine it with Edit"
        maskRow = qt.QHBoxLayout()
        for widget in (self.maskSelector, self.editMaskButton, self.vesselnessButton):
            maskRow.addWidget(widget)
        form.addRow("Mask:", maskRow)
        self.spinBoxes = {}
        for field, minimum, maximum, decimals, step, suffix, tooltip in self.NUMBER_FIELDS:
            spinBox = qt.QDoubleSpinBox()
            spinBox.decimals = decimals  # before the range: the range is rounded to the decimals
            spinBox.setRange(minimum, maximum)
            spinBox.singleStep = step
            spinBox.suffix = suffix
            spinBox.toolTip = tooltip
            self.spinBoxes[field] = spinBox
        for label, fields in (("Angles:", ("primaryAngle", "secondaryAngle")), ("SID, SOD:", ("sid", "sod")),
                              ("Pixel spacing:", ("pixelSpacingRow", "pixelSpacingCol"))):
            row = qt.QHBoxLayout()
            for field in fields:
                row.addWidget(self.spinBoxes[field])
            form.addRow(label, row)
        self.removeButton = qt.QPushButton(f"Remove view {n}")
        self.removeButton.toolTip = "Remove this view from the reconstruction (its frame and mask stay in the scene)"
        form.addRow(self.removeButton)

    @staticmethod
    def _nodeSelector(nodeTypes, toolTip, hiddenChildNodeTypes=None):
        selector = slicer.qMRMLNodeComboBox()
        selector.nodeTypes = nodeTypes
        selector.showChildNodeTypes = hiddenChildNodeTypes is not None
        if hiddenChildNodeTypes is not None:
            selector.hideChildNodeTypes = hiddenChildNodeTypes
        # None allowed: with a first node chosen automatically, adding a view would pick a frame unasked.
        selector.noneEnabled = True
        selector.addEnabled = False
        selector.removeEnabled = False
        selector.renameEnabled = True
        selector.toolTip = toolTip
        selector.setMRMLScene(slicer.mrmlScene)
        return selector

    def setValues(self, view):
        """Show a ViewParameters (SDFCARLib.mrml.parameter_views) without writing it back."""
        self.updating = True
        try:
            if self.frameSelector.currentNode() is not view.frame:
                self.frameSelector.setCurrentNode(view.frame)
            if self.maskSelector.currentNode() is not view.mask:
                self.maskSelector.setCurrentNode(view.mask)
            self.frameIndexSpinBox.value = int(view.frameIndex)
            for field, spinBox in self.spinBoxes.items():
                spinBox.value = float(getattr(view, field))
            hasFrame = view.frame is not None
            self.editMaskButton.enabled = hasFrame
            self.vesselnessButton.enabled = hasFrame
            showFrameIntensity(self.intensityComboBox, view.frame)
        finally:
            self.updating = False


class SDFCARWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._job = None
        self._jobContext = None
        self._analysisJob = None
        self._analysisContext = None
        self._viewRows = []
        self._updatingFrameIntensity = False  # True while the grey-level boxes show the frames' attributes
        self._resultPanelKey = None
        # Progress comes from the worker processes; polling keeps the GUI responsive.
        self._timer = qt.QTimer()
        self._timer.setInterval(500)
        self._timer.timeout.connect(self.onPollJob)

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(self.resourcePath("UI/SDFCAR.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = SDFCARLogic()
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.connectWidgets()
        self.initializeParameterNode()

    def connectWidgets(self):
        """Connect the .ui's widgets to the handlers (separate from setup() so tests can run it)."""
        # Only SDFCAR results (their segmentations carry SDFCAR.role = segmentation) are offered.
        self.ui.resultSelector.addAttribute("vtkMRMLSegmentationNode", "SDFCAR.role", "segmentation")
        self.ui.editMask1Button.connect("clicked(bool)", lambda: self.onEditMask(1))
        self.ui.editMask2Button.connect("clicked(bool)", lambda: self.onEditMask(2))
        self.ui.vesselness1Button.connect("clicked(bool)", lambda: self.onVesselness(1))
        self.ui.vesselness2Button.connect("clicked(bool)", lambda: self.onVesselness(2))
        for n in (1, 2):
            comboBox = getattr(self.ui, f"frame{n}IntensityComboBox")
            for _, label in FRAME_INTENSITY_CHOICES:  # before connecting: the first item is no user's choice
                comboBox.addItem(label)
            comboBox.toolTip = FRAME_INTENSITY_TOOLTIP
            comboBox.connect("currentIndexChanged(int)", lambda index, n=n: self.onFrameIntensityChanged(n, index))
        self.ui.addViewButton.connect("clicked(bool)", self.onAddView)
        self.ui.readGeometryButton.connect("clicked(bool)", self.onReadGeometry)
        self.ui.showCArmButton.connect("clicked(bool)", self.onShowCArm)
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.showQAButton.connect("clicked(bool)", self.onShowQA)
        self.ui.analyseButton.connect("clicked(bool)", self.onAnalyse)
        self.ui.suggestedViewButton.connect("clicked(bool)", self.onSuggestedView)
        self.ui.progressBar.setVisible(False)

    def cleanup(self):
        self.removeObservers()
        self._timer.stop()
        for job in (self._job, self._analysisJob):
            if job is not None and job.state == "running":
                job.cancel()

    def enter(self):
        self.initializeParameterNode()

    def exit(self):
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None
            self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)

    def onSceneStartClose(self, caller, event):
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self):
        self.setParameterNode(self.logic.getParameterNode())

    def setParameterNode(self, inputParameterNode):
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None
            self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
        self._parameterNode = inputParameterNode
        self._resultPanelKey = None
        if self._parameterNode:
            self._parameterNodeGuiTag = self._parameterNode.connectParametersToGui(parameterWidgets(self.ui))
            self.addObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
        # Called without a node too: a closed scene leaves no rows of views 3, 4, … behind.
        self._checkCanApply()

    def _checkCanApply(self, caller=None, event=None):
        p = self._parameterNode
        self._syncViewRows()
        for n in (1, 2):
            hasFrame = bool(p and getattr(p, f"frame{n}"))
            getattr(self.ui, f"editMask{n}Button").enabled = hasFrame
            getattr(self.ui, f"vesselness{n}Button").enabled = hasFrame
            self._updatingFrameIntensity = True
            try:
                showFrameIntensity(getattr(self.ui, f"frame{n}IntensityComboBox"), getattr(p, f"frame{n}") if p else None)
            finally:
                self._updatingFrameIntensity = False
        self._updateResultPanel()
        if self._job is not None:
            self.ui.applyButton.enabled = True  # it is the Cancel button now
            return
        missing = self.logic.missingInputs(p) if p else "no parameter node"
        self.ui.applyButton.enabled = not missing
        self.ui.applyButton.toolTip = "Reconstruct the coronary tree" if not missing else missing

    # --- views 3, 4, … ----------------------------------------------------------------------------
    def _syncViewRows(self):
        """One row of widgets per view after the first two, showing the parameter node's values."""
        p = self._parameterNode
        count = self.logic.viewCount(p) if p else 2
        container = self.ui.additionalViewsWidget.layout()
        while len(self._viewRows) < count - 2:
            row = AdditionalViewRow(len(self._viewRows) + 3)
            self._connectViewRow(row)
            container.addWidget(row.box)
            self._viewRows.append(row)
        while len(self._viewRows) > max(count - 2, 0):
            row = self._viewRows.pop()
            row.box.setParent(None)
            row.box.deleteLater()
        for row in self._viewRows:
            row.setValues(self.logic.viewParameters(p, row.n))

    def _connectViewRow(self, row):
        n = row.n
        row.frameSelector.connect("currentNodeChanged(vtkMRMLNode*)", lambda node: self.onViewValueChanged(row, "frame", node))
        row.maskSelector.connect("currentNodeChanged(vtkMRMLNode*)", lambda node: self.onViewValueChanged(row, "mask", node))
        row.frameIndexSpinBox.connect("valueChanged(int)", lambda value: self.onViewValueChanged(row, "frameIndex", value))
        row.intensityComboBox.connect("currentIndexChanged(int)",
                                      lambda index: None if row.updating else self.onFrameIntensityChanged(n, index))
        for field, spinBox in row.spinBoxes.items():
            spinBox.connect("valueChanged(double)", lambda value, field=field: self.onViewValueChanged(row, field, value))
        row.editMaskButton.connect("clicked(bool)", lambda: self.onEditMask(n))
        row.vesselnessButton.connect("clicked(bool)", lambda: self.onVesselness(n))
        row.removeButton.connect("clicked(bool)", lambda: self.onRemoveView(n))

    def onViewValueChanged(self, row, field, value):
        if row.updating or self._parameterNode is None:
            return
        with slicer.util.tryWithErrorDisplay(f"Could not set the {field} of view {row.n}."):
            self.logic.setViewValue(self._parameterNode, row.n, field, value)

    def onFrameIntensityChanged(self, n, index):
        """The user chose how frame ``n``'s grey levels were made: said on the frame node, which the reconstruction
        and Vesselness read (SDFCARLogic.frameIntensityTags)."""
        if self._updatingFrameIntensity or self._parameterNode is None or not 0 <= index < len(FRAME_INTENSITY_CHOICES):
            return
        frame = self.logic.viewValue(self._parameterNode, n, "frame")
        if frame is None:
            return
        value, label = FRAME_INTENSITY_CHOICES[index]
        with slicer.util.tryWithErrorDisplay(f"Could not set how the grey levels of frame {n} were made."):
            self.logic.setFrameIntensity(frame, value)
            self.ui.statusLabel.text = f"Frame {n} ({frame.GetName()}): grey levels read {label[0].lower() + label[1:]}."

    def onAddView(self):
        with slicer.util.tryWithErrorDisplay("Could not add a view."):
            n = self.logic.addView(self._parameterNode)
            self.ui.statusLabel.text = (f"View {n} added (SID, SOD and pixel spacing copied from view {n - 1}): choose its "
                                        "frame and mask and enter its angles.")

    def onRemoveView(self, n):
        with slicer.util.tryWithErrorDisplay(f"Could not remove view {n}."):
            self.logic.removeView(self._parameterNode, n)
            self.ui.statusLabel.text = f"View {n} removed; its frame and mask are still in the scene."

    # --- masks and geometry ---------------------------------------------------------------------
    def onEditMask(self, n):
        with slicer.util.tryWithErrorDisplay(f"Could not open the mask of frame {n} for editing.", waitCursor=True):
            p = self._parameterNode
            frame = self.logic.viewValue(p, n, "frame")
            segmentation = self.logic.maskSegmentation(frame, self.logic.viewValue(p, n, "mask"))
            self.logic.setViewValue(p, n, "mask", segmentation)
            self.logic.editInSegmentEditor(segmentation, frame, self.logic.viewValue(p, n, "frameIndex"))

    def onVesselness(self, n):
        with slicer.util.tryWithErrorDisplay(f"Vesselness could not segment frame {n}.", waitCursor=True):
            if not self.logic.ensureDependencies(VESSELNESS_REQUIREMENTS):
                return
            p = self._parameterNode
            view = self.logic.viewParameters(p, n)
            from SDFCARLib.masks import BrightVesselsError

            def segment(brightVessels):
                return self.logic.vesselnessMask(
                    view.frame, view.frameIndex, view.mask, pixelSpacingMm=(view.pixelSpacingRow, view.pixelSpacingCol),
                    magnification=view.sid / view.sod, brightVessels=brightVessels)

            question = f"Segment frame {n} with its grey levels inverted?"
            try:
                segmentation, parameters = segment(False)
            except BrightVesselsError as exc:
                # an inverted export: offer to read it the right way up rather than leave the user with an error
                if not self.askYesNo(f"{exc}\n\n{question}", "SDFCAR: vessels look bright"):
                    return
                segmentation, parameters = segment(True)
            else:
                if parameters.get("polarity") == "doubtful" and self.askYesNo(
                        "The frame's vessels may look bright rather than dark (check the frame).\n\n"
                        f"{question} (No keeps the mask made as it is.)", "SDFCAR: vessels bright or dark?"):
                    segmentation, parameters = segment(True)
            self.logic.setViewValue(p, n, "mask", segmentation)
            self.ui.statusLabel.text = (f"Vessel mask: {100 * parameters['vessel_fraction']:.1f} % of frame {n} in "
                                        f"{parameters['components']} piece(s), collimator excluded; refine it with Edit.")
            shown = [w for w in parameters.get("warnings", []) if "bright_vessels" not in w]  # that one was asked
            if shown:
                self.withArrowCursor(slicer.util.warningDisplay, "\n\n".join(shown),
                                     windowTitle=f"SDFCAR: the vessel mask of frame {n}")

    @staticmethod
    def withArrowCursor(display, *args, **kwargs):
        """``display(*args, **kwargs)`` (a dialog) inside ``tryWithErrorDisplay(waitCursor=True)``: the arrow comes back
        while it is open (the same override-cursor calls tryWithErrorDisplay makes), the wait cursor after."""
        slicer.app.restoreOverrideCursor()
        try:
            return display(*args, **kwargs)
        finally:
            slicer.app.setOverrideCursor(qt.Qt.WaitCursor)

    def askYesNo(self, text, windowTitle):
        return self.withArrowCursor(slicer.util.confirmYesNoDisplay, text, windowTitle=windowTitle)

    def onReadGeometry(self):
        with slicer.util.tryWithErrorDisplay("Could not read the C-arm geometry from the DICOM tags.", waitCursor=True):
            notes = self.logic.readGeometryFromDicom(self._parameterNode)
            self.ui.statusLabel.text = " ".join(["Geometry read from the DICOM tags."] + notes)

    def onShowCArm(self):
        with slicer.util.tryWithErrorDisplay("Could not show the C-arm set-up.", waitCursor=True):
            self.logic.showCArm(self._parameterNode)

    # --- reconstruction ---------------------------------------------------------------------------
    def onApplyButton(self):
        if self._job is not None:
            self._job.cancel()
            return
        with slicer.util.tryWithErrorDisplay("Could not start the reconstruction.", waitCursor=True):
            if not self.logic.ensureDependencies():
                return
            self._job, self._jobContext = self.logic.startReconstruction(self._parameterNode)
            self.ui.applyButton.text = "Cancel"
            self.ui.progressBar.setVisible(True)
            self.ui.progressBar.value = 0
            self.ui.statusLabel.text = "Starting…"
            self._timer.start()

    def onPollJob(self):
        if self._job is not None:
            self._pollReconstruction()
        if self._analysisJob is not None:
            self._pollAnalysis()
        if self._job is None and self._analysisJob is None:
            self._timer.stop()

    def _pollReconstruction(self):
        job = self._job
        info = job.poll()
        if info:
            self.ui.progressBar.maximum = max(1, int(info.get("total") or 1))
            self.ui.progressBar.value = int(info.get("step") or 0)
            self.ui.statusLabel.text = describeProgress(info)
        state = job.state
        if state == "running":
            return
        self._job, context = None, self._jobContext
        self.ui.applyButton.text = "Apply"
        self.ui.progressBar.setVisible(False)
        self._checkCanApply()
        files = finishedJobFiles(job, state, self.ui.statusLabel, "The reconstruction")
        if files is None:
            return
        # Not tryWithErrorDisplay, which re-raises: the report's warnings below often say why loading failed.
        nodes = None
        try:
            nodes = self.logic.addResults(files, context)
            self.ui.statusLabel.text = (f"Done: '{context['name']}' is in the scene (files in {context['jobDir']}); "
                                        "its reprojection QA is under Results.")
        except Exception as exc:
            logging.exception("SDFCAR: the results could not be loaded")
            self.ui.statusLabel.text = f"Finished, but the results could not be loaded (files in {context['jobDir']})."
            slicer.util.errorDisplay(f"The reconstruction finished but its results could not be loaded:\n\n{exc}",
                                     windowTitle="SDFCAR")
        if nodes is not None and self._parameterNode is not None:
            self._parameterNode.result = nodes.segmentation  # the Results section shows the new result
        warnings = reportWarnings(files)
        if warnings:
            self.ui.statusLabel.text += f" {len(warnings)} warning(s)."
            slicer.util.warningDisplay("The reconstruction finished with warnings:\n\n" + "\n\n".join(warnings),
                                       windowTitle="SDFCAR")
        if nodes is not None and context.get("analyse") and self._analysisJob is not None:
            self.ui.statusLabel.text += " Another analysis is running: press Analyse for this result when it ends."
        elif nodes is not None and context.get("analyse"):
            with slicer.util.tryWithErrorDisplay("The result is in the scene, but its analysis could not start.", waitCursor=True):
                if self.logic.ensureDependencies(ANALYSIS_REQUIREMENTS):
                    self._startAnalysis(nodes.segmentation)

    # --- results: QA and 3D-QCA -------------------------------------------------------------------
    def _updateResultPanel(self):
        p = self._parameterNode
        node = p.result if p else None
        running = self._analysisJob is not None
        self.ui.showQAButton.enabled = node is not None
        self.ui.analyseButton.enabled = node is not None and not running
        self.ui.suggestedViewButton.enabled = bool(node is not None and node.GetAttribute("SDFCAR.analysisFolder"))
        # None in _resultPanelKey means "not shown yet", so no result has its own key.
        key = ("no result",) if node is None else (node.GetID(), node.GetAttribute("SDFCAR.resultFolder"),
                                                   node.GetAttribute("SDFCAR.analysisFolder"))
        if key == self._resultPanelKey:
            return  # report.json and analysis.json are read once per result, not on every edit
        self._resultPanelKey = key
        if node is None:
            self.ui.qaLabel.text = "Choose a result (or reconstruct one)."
            self.ui.analysisLabel.text = ""
            return
        qaText, views = self.logic.resultQAText(node)
        self.ui.qaLabel.text = qaText
        self.ui.qaViewSpinBox.maximum = max(1, views)
        self.ui.analysisLabel.text = self.logic.analysisText(node)

    def onShowQA(self):
        with slicer.util.tryWithErrorDisplay("Could not show the QA overlay.", waitCursor=True):
            self.logic.showQAOverlay(self._parameterNode.result, int(self.ui.qaViewSpinBox.value))

    def onAnalyse(self):
        with slicer.util.tryWithErrorDisplay("Could not start the analysis.", waitCursor=True):
            if not self.logic.ensureDependencies(ANALYSIS_REQUIREMENTS):
                return
            self._startAnalysis(self._parameterNode.result)

    def _startAnalysis(self, resultNode):
        # Not wrapped in tryWithErrorDisplay: each caller shows its own message (the wrapper re-raises).
        # The point list is read from its selector, not a parameter-node field: before Slicer 5.10 (Markups
        # in core MRML) its class is not in the slicer namespace when this module's parameter class is defined.
        segment = self.logic.segmentFromPoints(self.ui.segmentPointsSelector.currentNode())
        ostium = self.logic.ostiumFromPoint(self.ui.ostiumPointSelector.currentNode())
        options = {**({} if segment is None else {"segment_mm": segment}),
                   **({} if ostium is None else {"ostium_mm": ostium})} or None
        self._analysisJob, self._analysisContext = self.logic.startAnalysis(resultNode, options=options)
        self.ui.analyseButton.enabled = False
        self.ui.statusLabel.text = f"Analysing '{resultNode.GetName()}' (3D-QCA)…"
        self._timer.start()

    def _pollAnalysis(self):
        job = self._analysisJob
        job.poll()
        state = job.state
        if state == "running":
            return
        self._analysisJob, context = None, self._analysisContext
        self._resultPanelKey = None
        self._checkCanApply()
        files = finishedJobFiles(job, state, self.ui.statusLabel, "The 3D-QCA")
        if files is None:
            return
        with slicer.util.tryWithErrorDisplay("The analysis finished but its results could not be loaded.", waitCursor=True):
            nodes = self.logic.addAnalysis(files, context) or {}
            self.ui.statusLabel.text = (f"3D-QCA of '{context['name']}' done: curves, table and diameter plot are in the scene "
                                        f"(folder '{context['name']} QCA'; files in {files['folder']}).")
            suggested = nodes.get("likeliest_ostium")
            if suggested is not None:  # the root lies on a vessel's side (the analysis's warnings say why)
                self.ui.statusLabel.text += (f" Its tree is likely rooted off the ostium: check the point list "
                                             f"'{suggested.GetName()}', move it where the artery begins if need be, "
                                             "choose it as the Ostium and press Analyse again.")
        self._resultPanelKey = None
        self._checkCanApply()

    def onSuggestedView(self):
        with slicer.util.tryWithErrorDisplay("Could not show the suggested view.", waitCursor=True):
            best = self.logic.showSuggestedView(self._parameterNode.result)
            self.ui.statusLabel.text = f"3D view: the suggested C-arm view {best.get('label', '')} (as the detector sees it)."


def showFrameIntensity(comboBox, frameNode):
    """Show what was said of a frame's grey levels in its view's box (enabled only with a frame). A value that
    is not a choice (set from the console) shows as the file's tags and says why in the tooltip; the run refuses it."""
    index, problem = 0, ""
    if frameNode is not None:
        from SDFCARLib import mrml

        try:
            said = mrml.frame_intensity_said(frameNode) or ""
            index = [value for value, _ in FRAME_INTENSITY_CHOICES].index(said)
        except ValueError as exc:
            problem = f"\n\n{exc}"
    comboBox.currentIndex = index
    comboBox.enabled = frameNode is not None
    comboBox.toolTip = FRAME_INTENSITY_TOOLTIP + problem


def parameterWidgets(ui):
    """{parameter name: widget} of the widgets of ``ui`` (childWidgetVariables) that carry the
    SlicerParameterName property.

    The module connects this mapping with connectParametersToGui, which returns the tag that
    disconnectGui needs on every Slicer version. connectGui(ui) returns None before Slicer 5.10,
    so disconnectGui(None) left the old connectors live: the next connection rebuilt the combo
    boxes and the old connectors wrote the last, then the first choice into the parameter node
    (a scene saved with preset "paper" came back as "fast").
    """
    mapping = {}
    for widget in vars(ui).values():
        name = widget.property("SlicerParameterName") if hasattr(widget, "property") else None
        if name:
            mapping[str(name)] = widget
    return mapping


def _warningLines(data):
    """The "warnings" of a report.json or analysis.json as lines of a summary (none: no lines)."""
    warnings = [str(w) for w in data.get("warnings") or []]
    return ["", f"{len(warnings)} warning(s):"] + [f"• {w}" for w in warnings] if warnings else []


def finishedJobFiles(job, state, statusLabel, what):
    """A finished job's files; None after saying in the status line (and, on failure, in a dialog with
    the worker's traceback) why there are none. The scene is not touched either way."""
    if state == "cancelled":
        statusLabel.text = f"{what} was cancelled: the scene is unchanged."
        return None
    import SDFCARLib.jobs

    try:
        return job.result()
    except SDFCARLib.jobs.JobFailed as exc:
        statusLabel.text = f"{what} failed: the scene is unchanged."
        slicer.util.errorDisplay(f"{what} failed: {exc.message}", detailedText=exc.traceback_text)
        return None


def reportWarnings(files):
    """The ``warnings`` of a finished job's report.json (mask checks, support, outputs); [] when none."""
    try:
        with open(files["report"], encoding="utf-8") as handle:
            return [str(w) for w in json.load(handle).get("warnings", [])]
    except (KeyError, OSError, ValueError, AttributeError):
        return []


def describeProgress(info):
    """One status line from a job progress dict (step, total, loss, ETA, device)."""
    phase = info.get("phase")
    if phase == "warning":
        return f"Warning: {info.get('message', '')}"
    if phase == "setup":
        return f"Preparing ({info.get('device', '')})…"
    if phase == "output":
        return "Writing the results…"
    if phase == "prune":
        return "Pruning the branches that no mask pixel needs…"
    if phase == "calibrate":
        return f"Correcting the shift between views: {info.get('message', '')}"
    text = f"Step {info.get('step', 0)} / {info.get('total', '?')}"
    if info.get("loss") is not None:
        text += f" · loss {info['loss']:.4g} (occ {info.get('l_occ', 0):.3g}, geo {info.get('l_geo', 0):.3g})"
    if info.get("eta_s") is not None:
        text += f" · ETA {int(info['eta_s'] // 60)}:{int(info['eta_s'] % 60):02d}"
    if info.get("device"):
        text += f" · {info['device']}"
    return text


class SDFCARLogic(ScriptedLoadableModuleLogic):
    """Everything the module does, usable from the Python console without the GUI (see README)."""

    def getParameterNode(self):
        return SDFCARParameterNode(super().getParameterNode())

    # --- dependencies -----------------------------------------------------------------------------
    @staticmethod
    def missingDependencies(names=None):
        """The import names of ``names`` (default: all of REQUIREMENTS) that cannot be imported."""
        import importlib.util

        # find_spec trusts the import system's directory caches: without this, a package pip
        # installed while Slicer runs can look missing until the next start.
        importlib.invalidate_caches()
        return [name for name in (names or list(REQUIREMENTS)) if importlib.util.find_spec(name) is None]

    @staticmethod
    def dependencyError(missing):
        """What to tell the user when the packages ``missing`` (import names) cannot be imported."""
        requirements = [REQUIREMENTS.get(name, name) for name in missing]
        return (f"SDFCAR needs these Python packages, which are not installed: {', '.join(requirements)}. "
                "Install them with the SDFCAR module (Apply or Sample Data asks to), or in Slicer's Python console: "
                f"slicer.util.pip_install({' '.join(requirements)!r}); then restart Slicer if they still look missing.")

    def ensureDependencies(self, names=None):
        """Offer to install missing packages (after confirmation); True when all are importable."""
        missing = self.missingDependencies(names)
        if not missing:
            return True
        if "torch" in missing:
            try:
                import PyTorchUtils  # the PyTorch extension's installer picks the build for the GPU
            except ImportError:
                PyTorchUtils = None
            if PyTorchUtils is not None:
                if PyTorchUtils.PyTorchUtilsLogic().installTorch(askConfirmation=True) is None:
                    return False
                missing.remove("torch")
        if missing:
            requirements = [REQUIREMENTS[name] for name in missing]
            if not slicer.util.confirmOkCancelDisplay(
                    f"SDFCAR needs these Python packages: {', '.join(requirements)}. Download and install them now?",
                    windowTitle="SDFCAR dependencies"):
                return False
            try:
                from slicer import packaging  # not "import slicer.packaging": that would make slicer local here
            except ImportError:  # Slicer before slicer.packaging
                slicer.util.pip_install(requirements)
            else:
                packaging.pip_ensure(requirements, prompt_install=False, requester="SDFCAR")
        stillMissing = self.missingDependencies(names)
        if stillMissing:
            slicer.util.errorDisplay("The installation did not make every package importable. " + self.dependencyError(stillMissing),
                                     windowTitle="SDFCAR dependencies")
            return False
        return True

    # --- inputs -----------------------------------------------------------------------------------
    @staticmethod
    def frameNode(node, index=-1):
        """The volume node holding the chosen frame: item ``index`` of the sequence a proxy node
        shows (-1: the item on display), or the node itself."""
        from SDFCARLib import mrml

        if node is None:
            raise ValueError("choose the frame's volume first")
        browser, sequence = mrml.sequence_of_proxy_node(slicer.mrmlScene, node)
        if sequence is None or index is None or index < 0:
            return node
        return mrml.sequence_frame_node(sequence, index)

    @staticmethod
    def sliceIndex(node, frame, index):
        """Slice of a multi-frame volume to use: ``index`` unless it picked a sequence item."""
        return index if frame is node and index is not None and index >= 0 else None

    def frameArray(self, node, index=-1):
        from SDFCARLib import mrml

        frame = self.frameNode(node, index)
        return mrml.frame_from_volume_node(frame, self.sliceIndex(node, frame, index))

    def maskArray(self, maskNode, frameNode, index=-1):
        from SDFCARLib import mrml

        if maskNode is None:
            raise ValueError(f"frame '{frameNode.GetName() if frameNode else ''}' has no mask: use Edit or Vesselness")
        if maskNode.IsA("vtkMRMLSegmentationNode"):
            # A segmentation painted on a cine run's proxy holds the frame on display.
            sliceIndex = self.sliceIndex(frameNode, self.frameNode(frameNode, index), index)
            return mrml.mask_from_segmentation_node(maskNode, frameNode, slice_index=sliceIndex)
        frame = self.frameNode(maskNode, index)
        reference = self.frameNode(frameNode, index)
        # a labelmap exported cropped to the vessels is placed on the frame's pixels
        return mrml.mask_from_volume_node(frame, slice_index=self.sliceIndex(maskNode, frame, index),
                                          reference_volume_node=reference,
                                          reference_slice_index=self.sliceIndex(frameNode, reference, index))

    @staticmethod
    def maskSegmentation(frameNode, maskNode=None):
        """The segmentation to paint the vessels of a frame in (created, empty, when needed)."""
        if frameNode is None:
            raise ValueError("choose the frame first")
        if maskNode is not None and maskNode.IsA("vtkMRMLSegmentationNode"):
            return maskNode
        segmentation = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLSegmentationNode", f"{frameNode.GetName()} vessels")
        segmentation.CreateDefaultDisplayNodes()
        segmentation.SetReferenceImageGeometryParameterFromVolumeNode(frameNode)
        segmentation.GetSegmentation().AddEmptySegment("Vessels", "Vessels", [1.0, 0.3, 0.3])
        return segmentation

    @staticmethod
    def editInSegmentEditor(segmentation, frameNode, index=-1):
        from SDFCARLib import mrml

        browser, _ = mrml.sequence_of_proxy_node(slicer.mrmlScene, frameNode)
        if browser is not None and index is not None and index >= 0:
            browser.SetSelectedItemNumber(index)
        slicer.util.setSliceViewerLayers(background=frameNode, fit=True)
        slicer.util.selectModule("SegmentEditor")
        editor = slicer.util.getModuleWidget("SegmentEditor").editor
        editor.setSegmentationNode(segmentation)
        editor.setSourceVolumeNode(frameNode)

    def vesselnessMask(self, frameNode, index=-1, maskNode=None, pixelSpacingMm=None, magnification=None,
                       brightVessels=False):
        """Seed a frame's vessel segmentation with the angiogram mask pipeline (the command line's
        ``segment``); returns (segmentation, parameters). Pixel spacing (mm) and magnification
        (SID/SOD) set the physical vessel scales; without them typical values are assumed and reported.
        ``brightVessels``: the frame shows its vessels bright (an inverted export); its grey levels are inverted first."""
        from SDFCARLib import mrml
        from SDFCARLib.evidence import assumed_relationship
        from SDFCARLib.masks import AngioMaskSettings, angiogram_mask, mask_settings_for_intensity

        # a frame processed for display (its DICOM file says DISP or a vendor's term, or it is an 8-bit image nothing
        # is known of): the edge rule does not trim it
        tags = self.frameIntensityTags(frameNode, index)
        frame = self.frameArray(frameNode, index)
        relationship, note = assumed_relationship(frame, tags.relationship if tags is not None else None,
                                                  frameNode.GetName())
        if note:
            logging.warning(f"SDFCAR: {note}")
        settings = mask_settings_for_intensity(relationship, AngioMaskSettings(bright_vessels=bool(brightVessels)))
        mask, parameters = angiogram_mask(frame, pixelSpacingMm, magnification, settings)
        for warning in parameters.get("warnings", []):
            logging.warning(f"SDFCAR: {frameNode.GetName()}: {warning}")
        if note:
            parameters["pixel_intensity_relationship"] = f"{relationship} (assumed: 8-bit grey levels)"
        with mrml.scene_transaction(slicer.mrmlScene):
            segmentation = self.maskSegmentation(frameNode, maskNode)
            mrml.set_segment_mask(segmentation, mask, frameNode, "Vessels")
        segmentation.SetAttribute("SDFCAR.vesselness", str(parameters))
        return segmentation, parameters

    # --- views ------------------------------------------------------------------------------------
    # Views 1 and 2 are fields of the parameter-node wrapper; views 3, 4, … are stored beside them
    # (SDFCARLib.mrml.parameter_views). These methods read and write any view the same way.
    @staticmethod
    def viewCount(p):
        from SDFCARLib.mrml import parameter_views

        return parameter_views.view_count(p.parameterNode)

    @staticmethod
    def viewValue(p, n, field):
        from SDFCARLib.mrml import parameter_views

        if n < parameter_views.FIRST_STORED_VIEW:
            return getattr(p, parameter_views.parameter_name(field, n))
        return parameter_views.get_view_value(p.parameterNode, n, field)

    @staticmethod
    def setViewValue(p, n, field, value):
        from SDFCARLib.mrml import parameter_views

        if n < parameter_views.FIRST_STORED_VIEW:
            kind = parameter_views.VIEW_VALUE_FIELDS.get(field, (None,))[0]
            setattr(p, parameter_views.parameter_name(field, n), kind(value) if kind is not None else value)
        else:
            parameter_views.set_view_value(p.parameterNode, n, field, value)

    def viewParameters(self, p, n):
        """All fields of view ``n`` (SDFCARLib.mrml.parameter_views.ViewParameters)."""
        from SDFCARLib.mrml import parameter_views

        if n >= parameter_views.FIRST_STORED_VIEW:
            return parameter_views.get_view(p.parameterNode, n)
        return parameter_views.ViewParameters(**{f: self.viewValue(p, n, f) for f in parameter_views.VIEW_FIELDS})

    def addView(self, p, values=None):
        """Append a view; SID, SOD and pixel spacing start as the last view's (same C-arm). Returns its number."""
        from SDFCARLib.mrml import parameter_views

        last = self.viewParameters(p, self.viewCount(p))
        start = {f: getattr(last, f) for f in ("sid", "sod", "pixelSpacingRow", "pixelSpacingCol")}
        start.update(values or {})
        return parameter_views.add_view(p.parameterNode, start)

    @staticmethod
    def removeView(p, n):
        """Remove view ``n`` (3 or later); later views move up. Its frame and mask nodes stay in the scene."""
        from SDFCARLib.mrml import parameter_views

        parameter_views.remove_view(p.parameterNode, n)

    def missingInputs(self, p):
        """What Apply still needs, as a sentence ("" when every view has its frame and mask)."""
        for n in range(1, self.viewCount(p) + 1):
            if not self.viewValue(p, n, "frame"):
                return f"Choose the frame of view {n}" + (" (or remove the view)" if n > 2 else "")
            if not self.viewValue(p, n, "mask"):
                return f"Choose the mask of view {n}, or make one with Edit or Vesselness"
        return ""

    # --- geometry ---------------------------------------------------------------------------------
    def geometryFromParameters(self, p, detectorShapes):
        """The Geometry the parameters describe (volume centre entered in RAS, kept in LPS)."""
        from SDFCARLib import mrml
        from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid

        views = []
        for n, shape in enumerate(detectorShapes, start=1):
            v = self.viewParameters(p, n)
            views.append(CArmView(v.primaryAngle, v.secondaryAngle, v.sid, v.sod, (v.pixelSpacingRow, v.pixelSpacingCol),
                                  tuple(int(s) for s in shape)))
        center = mrml.ras_to_lps([p.centerR, p.centerA, p.centerS])
        grid = VolumeGrid((int(p.volumeSize),) * 3, (float(p.voxelSpacing),) * 3, tuple(float(c) for c in center))
        return Geometry(grid, tuple(views))

    def setViewParameters(self, p, n, view):
        values = (view.primary_deg, view.secondary_deg, view.sid_mm, view.sod_mm, *view.pixel_spacing_mm)
        for field, value in zip(GEOMETRY_VIEW_FIELDS, values):
            self.setViewValue(p, n, field, float(value))

    def setGeometryParameters(self, p, geometry):
        """Fill the fields from a Geometry; the module gets as many views as it has (views beyond
        them are removed from the parameters, their nodes stay in the scene)."""
        from SDFCARLib import mrml
        from SDFCARLib.mrml import parameter_views

        parameter_views.set_view_count(p.parameterNode, len(geometry.views))
        for n, view in enumerate(geometry.views, start=1):
            self.setViewParameters(p, n, view)
        p.volumeSize = int(max(geometry.volume.shape))
        p.voxelSpacing = float(max(geometry.volume.spacing_mm))
        p.centerR, p.centerA, p.centerS = (float(c) + 0.0 for c in mrml.lps_to_ras(geometry.volume.center_mm))  # no -0.0

    def readGeometryFromDicom(self, p):
        """Fill the view fields from the frames' DICOM tags; returns notes for the user."""
        from SDFCARLib import mrml
        from SDFCARLib.dicom import view_from_dicom

        notes, read = [], []
        for n in range(1, self.viewCount(p) + 1):
            uid, fileFrame = mrml.dicom_frame_reference(slicer.mrmlScene, self.viewValue(p, n, "frame"),
                                                        self.viewValue(p, n, "frameIndex"))
            # slicer.dicomDatabase does not exist while the DICOM module is disabled.
            database = getattr(slicer, "dicomDatabase", None)
            if uid and not database:
                raise ValueError(f"frame {n} came from a DICOM file but the DICOM database is not available: enable the "
                                 "DICOM module (Edit > Application Settings > Modules) or type the geometry instead")
            path = database.fileForInstance(uid) if uid else None
            if not path:
                raise ValueError(f"frame {n} was not loaded from the DICOM database, so there are no tags to read; "
                                 "type the angles, distances and pixel spacing instead")
            view, provenance = view_from_dicom(path, frame=fileFrame, view_number=n)
            read.append((n, view))
            notes += [f"View {n}: {note}" for note in provenance.get("notes", [])]
        # Every view read before any is set, and a value the fields refuse puts back what was there: all or nothing.
        before = {n: {field: self.viewValue(p, n, field) for field in GEOMETRY_VIEW_FIELDS} for n, _ in read}
        try:
            for n, view in read:
                self.setViewParameters(p, n, view)
        except Exception:
            for n, values in before.items():
                for field, value in values.items():
                    self.setViewValue(p, n, field, value)
            raise
        return notes

    def _viewInputs(self, frameNodes, maskNodes, frameIndices):
        """(frames, masks, nodes holding the frames) as arrays, one per view; errors name the view."""
        frames, masks, shown = [], [], []
        for n, (frame, mask, index) in enumerate(zip(frameNodes, maskNodes, frameIndices), start=1):
            try:
                frames.append(self.frameArray(frame, index))
                masks.append(self.maskArray(mask, frame, index))
                shown.append(self.frameNode(frame, index))
            except ValueError as exc:
                raise type(exc)(f"view {n}: {exc}") from exc
        return frames, masks, shown

    def inputs(self, p, withFrameNodes=False):
        """(geometry, masks, frames) of the parameter node's choices for every view, as arrays (rows, cols);
        with ``withFrameNodes`` also the volume nodes holding the chosen frames."""
        count = self.viewCount(p)
        views = [self.viewParameters(p, n) for n in range(1, count + 1)]
        frames, masks, shown = self._viewInputs([v.frame for v in views], [v.mask for v in views],
                                                [v.frameIndex for v in views])
        geometry = self.geometryFromParameters(p, [m.shape for m in masks])
        return (geometry, masks, frames, shown) if withFrameNodes else (geometry, masks, frames)

    def showCArm(self, p):
        """Show the C-arm set-up of the current choices (replacing an earlier display of it)."""
        from SDFCARLib import mrml

        geometry, masks, frames = self.inputs(p)
        name = f"{p.outputName} C-arm"
        for node in list(slicer.util.getNodesByClass("vtkMRMLDisplayableNode")):
            if node.GetName().startswith(name) and (node.GetAttribute("SDFCAR.role") or "").startswith("carm"):
                slicer.mrmlScene.RemoveNode(node)
        return mrml.add_carm_geometry_to_scene(slicer.mrmlScene, geometry, images=frames, name=name)

    # --- reconstruction ---------------------------------------------------------------------------
    @staticmethod
    def settings(p):
        values = {"preset": p.preset, "mode": p.mode, "device": p.device, "seed": int(p.seed)}
        if p.correctMotion:
            values["calibrate"] = True
        if p.steps > 0:
            values["steps"] = int(p.steps)
        return values

    @staticmethod
    def jobDirectory(p):
        chosen = str(p.outputDirectory) if p.outputDirectory is not None else ""
        base = Path(chosen) if chosen not in ("", ".") else Path(slicer.app.temporaryPath) / "SDFCAR"
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", p.outputName).strip("._") or "result"
        stamp = f"{safe}-{time.strftime('%Y%m%d-%H%M%S')}"
        folder, n = base / stamp, 1
        while folder.exists():  # two runs of one name within a second
            n += 1
            folder = base / f"{stamp}-{n}"
        return folder

    @staticmethod
    def setFrameIntensity(frameNode, relationship):
        """Say how a frame's grey levels were made ("LIN", "DISP"; "" or None: as its DICOM file says). The view's
        "Grey levels" box does this; from the console too."""
        from SDFCARLib import mrml

        mrml.say_frame_intensity(frameNode, relationship)

    @staticmethod
    def frameIntensityTags(frameNode, index=-1):
        """What the user said of a frame's grey levels (the "Grey levels" box: SDFCARLib.mrml.frame_intensity_said),
        else what the header of the DICOM file it was loaded from says (SDFCARLib.dicom.intensity.IntensityTags), or
        None where neither is known."""
        from SDFCARLib import mrml
        from SDFCARLib.dicom.intensity import IntensityTags, intensity_tags_of_file

        said = mrml.frame_intensity_said(frameNode)
        if said:
            return IntensityTags(said, None, "MONOCHROME2", 16)

        database = getattr(slicer, "dicomDatabase", None)
        uid, frame = mrml.dicom_frame_reference(slicer.mrmlScene, frameNode, index)
        path = database.fileForInstance(uid) if uid and database else None
        # the frame matters to an enhanced object: its TO_LINEAR LUT may be given per frame
        return intensity_tags_of_file(path, frame if frame is not None else 0) if path else None

    @staticmethod
    def jobFrames(frames, frameNodes, frameIndices):
        """(frames, relationships, notes): the views' frame arrays as the job reads them, per view the Pixel
        Intensity Relationship (0028,1040) of those arrays, from the header of the DICOM file each frame was loaded
        from (None where it was not loaded from the DICOM database), and per view how the frame was read where it
        was changed (None elsewhere; the job's report.json keeps them). Path lengths are read only off LIN frames: a
        LOG frame is brought to a linear scale here, a LIN frame whose values fall with intensity mirrored
        (SDFCARLib.dicom.intensity). Slicer's DICOM readers (the image sequence plugin's GDCM ImageIO, Slicer
        5.4 to main) hand over the stored values rescaled by a slope/intercept only, with MONOCHROME1 mirrored, as
        SDFCARLib's own reader does; never through a Modality LUT (0028,3000), which GDCM does not apply, so a
        classic LOG run's LUT is applied here once (Testing/test_dicom_intensity.py)."""
        from SDFCARLib.dicom.intensity import linearised

        arrays, relationships, notes = [], [], []
        for n, (frame, node, index) in enumerate(zip(frames, frameNodes, frameIndices), start=1):
            tags = SDFCARLogic.frameIntensityTags(node, index)
            array, relationship, note = linearised(frame, tags, inverted=tags is not None and tags.photometric == "MONOCHROME1")
            if note:
                logging.info(f"SDFCAR: view {n}: {note}")
            arrays.append(array)
            relationships.append(relationship)
            notes.append(note or None)
        return arrays, relationships, notes

    @staticmethod
    def _startJob(jobDir, geometry, masks, settings, name, frames=None, frameIntensity=None, frameNotes=None):
        import shutil

        from SDFCARLib.jobs import ReconstructionJob

        jobDir.parent.mkdir(parents=True, exist_ok=True)
        # The worker runs in Slicer's own Python (PythonSlicer), outside the GUI process. The frames go
        # with the masks: with the frame_evidence setting the occupancy is fitted to them.
        return ReconstructionJob.start(jobDir, geometry, masks, settings, name, python=shutil.which("PythonSlicer"),
                                       frames=frames, frame_intensity=frameIntensity,
                                       frame_notes=frameNotes if frameNotes and any(frameNotes) else None)

    def startReconstruction(self, p):
        """Start a background job; returns (job, context for ``addResults``)."""
        geometry, masks, frames, frameNodes = self.inputs(p, withFrameNodes=True)
        views = [self.viewParameters(p, n) for n in range(1, self.viewCount(p) + 1)]
        jobFrames, intensity, notes = self.jobFrames(frames, [v.frame for v in views], [v.frameIndex for v in views])
        jobDir = self.jobDirectory(p)
        job = self._startJob(jobDir, geometry, masks, self.settings(p), p.outputName, jobFrames, intensity, notes)
        context = {"name": p.outputName, "geometry": geometry, "frames": frames, "frameNodes": frameNodes,
                   "jobDir": str(jobDir), "includeOccupancy": p.includeOccupancy, "showCArm": p.showCArm,
                   "analyse": p.analyseAfterReconstruction}
        return job, context

    def addResults(self, files, context):
        """A job's result files into the scene: segmentation, surface and optionally the C-arm all
        or nothing, then the QA overlay of each view (a damaged overlay is logged, the result kept),
        then into the 3D view."""
        from SDFCARLib import mrml

        scene = slicer.mrmlScene
        resultFolder = str(Path(files["segmentation"]).parent)
        # Where the files are, so that Analyse and the QA panel find them after a scene reload.
        where = {"jobFolder": context["jobDir"], "resultFolder": resultFolder}
        with mrml.scene_transaction(scene):
            nodes = mrml.add_reconstruction_to_scene(scene, files, context["name"], include_occupancy=context["includeOccupancy"],
                                                     attributes=where)
            if context["showCArm"]:
                mrml.add_carm_geometry_to_scene(scene, context["geometry"], images=context["frames"], name=f"{context['name']} C-arm")
        try:
            # Outside the transaction: a damaged overlay must not cost the user the result itself.
            mrml.add_qa_overlays_to_scene(scene, files, context["name"], context["geometry"],
                                          frame_nodes=context.get("frameNodes"), attributes=where)
        except mrml.MRMLBridgeError as exc:
            logging.warning(f"SDFCAR: the QA overlays of '{context['name']}' were not loaded: {exc}")
        layoutManager = slicer.app.layoutManager()
        if layoutManager is not None and layoutManager.threeDViewCount > 0:
            layoutManager.threeDWidget(0).threeDView().resetFocalPoint()
        return nodes

    def reconstructViews(self, frames, masks, geometry, settings=None, name="Coronary tree", frameIndices=None, jobDir=None,
                         showCArm=True, includeOccupancy=False, timeout=None):
        """Console use, any number of views: reconstruct and wait; returns SDFCARLib.mrml.ResultNodes.

        ``frames``, ``masks``: one volume node (frame) and one segmentation or labelmap node (mask)
        per view of ``geometry``, in its order; ``frameIndices``: per view the frame of a cine run
        (-1 or None: the frame on display); ``geometry``: an SDFCARLib Geometry whose detectors
        match the frames (e.g. ``Geometry.load("geometry.json")``); ``settings``: a dict (preset,
        mode, device, steps, seed).
        """
        frames, masks = list(frames), list(masks)
        count = len(geometry.views)
        indices = list(frameIndices) if frameIndices is not None else [-1] * len(frames)
        if not (len(frames) == len(masks) == len(indices) == count):
            raise ValueError(f"{len(frames)} frame(s), {len(masks)} mask(s) and {len(indices)} frame index(es) for a geometry "
                             f"of {count} views: give one frame, one mask and one index per view, in the geometry's order")
        frameArrays, maskArrays, frameNodes = self._viewInputs(frames, masks, indices)
        jobDir = Path(jobDir) if jobDir else Path(slicer.app.temporaryPath) / "SDFCAR" / f"console-{time.strftime('%Y%m%d-%H%M%S')}"
        job = self._startJob(jobDir, geometry, maskArrays, settings or {"preset": "fast"}, name,
                             *self.jobFrames(frameArrays, frames, indices))
        if job.wait(timeout) == "running":
            job.cancel()
        context = {"name": name, "geometry": geometry, "frames": frameArrays, "frameNodes": frameNodes, "jobDir": str(jobDir),
                   "includeOccupancy": includeOccupancy, "showCArm": showCArm}
        return self.addResults(job.result(), context)

    def reconstruct(self, frame1, mask1, frame2, mask2, geometry, settings=None, name="Coronary tree",
                    frameIndices=(-1, -1), jobDir=None, showCArm=True, includeOccupancy=False, timeout=None):
        """Console use with two views (see ``reconstructViews`` for any number): reconstruct and wait."""
        return self.reconstructViews([frame1, frame2], [mask1, mask2], geometry, settings, name, list(frameIndices), jobDir,
                                     showCArm, includeOccupancy, timeout)

    # --- results: QA and 3D-QCA -------------------------------------------------------------------
    @staticmethod
    def resultFolder(resultNode):
        """The folder of a result node's files; raises ValueError saying why it cannot be found."""
        from SDFCARLib import mrml

        if resultNode is None:
            raise ValueError("choose a result first (Results > Result), or reconstruct one")
        folder = mrml.result_folder_of(resultNode)
        if folder is None:
            raise ValueError(f"the files of result '{resultNode.GetName()}' were not found (moved or deleted, or it was not "
                             "made by SDFCAR); open the result folder's scene.mrml, or reconstruct again")
        return folder

    def resultQAText(self, resultNode):
        """(text for the Results section: per-view QA numbers and the run's warnings, number of views)."""
        from SDFCARLib import mrml
        from SDFCARLib.calibration import calibration_lines
        from SDFCARLib.qa import ensemble_choice_line, pieces_line, qa_summary_lines

        try:
            report = mrml.read_report(self.resultFolder(resultNode))
        except ValueError as exc:
            return str(exc)[0].upper() + str(exc)[1:] + ".", 1
        lines = qa_summary_lines(report)
        views = len(lines) or len((report.get("geometry") or {}).get("views") or []) or 1
        if not lines:
            lines = ["This result has no reprojection QA (made by an SDFCAR version before it existed)."]
        pieces = pieces_line(report)  # a tree in pieces is the first thing to look at in 3D
        choice = ensemble_choice_line(report)  # which of several fits was kept, by this QA
        poses = calibration_lines(report)  # what the frames' motion search corrected, or why not
        return "\n".join(lines + ([pieces] if pieces else []) + ([choice] if choice else []) + poses
                         + _warningLines(report)), views

    @staticmethod
    def analysisText(resultNode):
        """Summary of the result's latest 3D-QCA (or what to do when there is none)."""
        from SDFCARLib.analysis.outputs import analysis_summary_lines

        folder = resultNode.GetAttribute("SDFCAR.analysisFolder") if resultNode is not None else None
        if not folder:
            return "Not analysed yet: press Analyse."
        analysis = Path(folder) / "analysis.json"
        try:
            data = json.loads(analysis.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            return f"The analysis in {folder} cannot be read ({exc}); press Analyse to run it again."
        # With what the command line prints as warnings (a broken reconstruction, lesions the frames do not show).
        return "\n".join(analysis_summary_lines(data) + _warningLines(data))

    def showQAOverlay(self, resultNode, viewNumber):
        """Show the QA overlay of a view in the slice views (loaded from the result folder when the scene lacks it)."""
        from SDFCARLib import mrml

        folder = self.resultFolder(resultNode)
        overlays = mrml.qa_overlay_nodes(slicer.mrmlScene, folder)
        if viewNumber not in overlays:
            where = {"resultFolder": str(folder)}
            if resultNode.GetAttribute("SDFCAR.jobFolder"):
                where["jobFolder"] = resultNode.GetAttribute("SDFCAR.jobFolder")
            mrml.add_qa_overlays_to_scene(slicer.mrmlScene, folder, resultNode.GetName(), attributes=where)
            overlays = mrml.qa_overlay_nodes(slicer.mrmlScene, folder)
        if viewNumber not in overlays:
            raise ValueError(f"result '{resultNode.GetName()}' has no QA overlay of view {viewNumber} (qa_view{viewNumber}.png "
                             f"in {folder}): it has {len(overlays)} view(s) with overlays")
        slicer.util.setSliceViewerLayers(background=overlays[viewNumber], fit=True)
        return overlays[viewNumber]

    @staticmethod
    def _pointsInLPS(pointsNode, count, what, place, otherwise):
        """The ``count`` control points of a point list in LPS mm (None without a list); the C-arm's source list
        or another number of points is refused, saying what to ``place`` or choose ``otherwise``."""
        from SDFCARLib import mrml

        if pointsNode is None:
            return None
        name = pointsNode.GetName()
        if (pointsNode.GetAttribute("SDFCAR.role") or "").startswith("carm"):
            raise ValueError(f"'{name}' holds the C-arm's X-ray sources, not {what}: place {place} in a new point list, "
                             f"or choose none to {otherwise}")
        found = pointsNode.GetNumberOfControlPoints()
        if found != count:
            raise ValueError(f"the point list '{name}' has {found} point(s): place exactly {place}, or choose no point "
                             f"list to {otherwise}")
        points = []
        for index in range(count):
            ras = [0.0, 0.0, 0.0]
            pointsNode.GetNthControlPointPositionWorld(index, ras)
            points.append([float(c) for c in mrml.ras_to_lps(ras)])
        return points

    @staticmethod
    def segmentFromPoints(pointsNode):
        """The first two control points of a point list in LPS mm, as ``analyse --segment`` takes them (the
        segment whose 3D length, foreshortening and best view the analysis reports); None without a list."""
        return SDFCARLogic._pointsInLPS(pointsNode, 2, "the ends of a segment",
                                        "two points, at the ends of the segment to measure", "measure the worst lesion")

    @staticmethod
    def ostiumFromPoint(pointsNode):
        """The one control point of a point list in LPS mm, as ``analyse --ostium`` takes it (the tree is rooted
        there); None without a list."""
        points = SDFCARLogic._pointsInLPS(pointsNode, 1, "the ostium", "one point, where the artery begins (its ostium)",
                                          "root the tree at its thickest end")
        return None if points is None else points[0]

    @staticmethod
    def startAnalysis(resultNode, outputDir=None, options=None):
        """Start the 3D-QCA of a result in a worker process; returns (job, context for ``addAnalysis``).

        The files go to a new folder beside the result's (analysis, analysis-2, …: an earlier
        analysis is kept). The view masks of the reconstruction job, when its folder is still
        there, give the 2D diameters, and its frames the widths fitted to their intensity profiles
        (unless ``options`` names other frames)."""
        import shutil
        import tempfile

        from SDFCARLib.jobs import AnalysisJob, job_frames, job_masks

        folder = SDFCARLogic.resultFolder(resultNode)
        jobFolder = resultNode.GetAttribute("SDFCAR.jobFolder")
        masks = job_masks(jobFolder) if jobFolder else None
        frames = job_frames(jobFolder) if jobFolder and masks is not None else None
        options = dict(options or {})
        if frames and "frames" not in options:
            options["frames"] = frames
        base = Path(slicer.app.temporaryPath) / "SDFCAR"
        base.mkdir(parents=True, exist_ok=True)
        jobDir = Path(tempfile.mkdtemp(prefix=f"analysis-{time.strftime('%Y%m%d-%H%M%S')}-", dir=str(base)))
        job = AnalysisJob.start(jobDir, folder, outputDir, masks=masks, options=options, python=shutil.which("PythonSlicer"))
        # the node itself, not its ID: a scene closed meanwhile gives its IDs to new nodes
        context = {"name": resultNode.GetName(), "resultNode": resultNode, "jobDir": str(jobDir),
                   "resultFolder": str(folder)}
        return job, context

    def addAnalysis(self, files, context):
        """A finished analysis into the scene (all or nothing; the result node, if still there, is linked
        to it) and its diameter plot into the layout."""
        from SDFCARLib.analysis.mrml_nodes import add_analysis_to_scene

        resultNode = context.get("resultNode")
        if resultNode is not None and not slicer.mrmlScene.IsNodePresent(resultNode):
            resultNode = None  # removed, or its scene closed, while the analysis ran
        nodes = add_analysis_to_scene(slicer.mrmlScene, files["folder"], context["name"], result_node=resultNode)
        plots = getattr(slicer.modules, "plots", None)
        if plots is not None and slicer.app.layoutManager() is not None:
            plots.logic().ShowChartInLayout(nodes["chart"])  # switches to a layout with a plot view if needed
        return nodes

    def analyse(self, resultNode, outputDir=None, options=None, timeout=None):
        """Console use: run the 3D-QCA of a result, wait, add its nodes; returns them (a dict, see
        SDFCARLib.analysis.mrml_nodes.add_analysis_nodes)."""
        job, context = self.startAnalysis(resultNode, outputDir, options)
        if job.wait(timeout) == "running":
            job.cancel()
        return self.addAnalysis(job.result(), context)

    @staticmethod
    def showSuggestedView(resultNode, viewIndex=0):
        """Point the 3D view's camera along the suggested C-arm view of the result's latest analysis,
        centred on the result; returns the suggested view (primary_deg, secondary_deg, label, …)."""
        from SDFCARLib.analysis.mrml_nodes import set_camera_to_angles, suggested_view_of

        best = suggested_view_of(resultNode)
        layoutManager = slicer.app.layoutManager()
        if layoutManager is None or layoutManager.threeDViewCount <= viewIndex:
            raise ValueError("there is no 3D view to point: choose a layout with a 3D view (View > Layout)")
        view = layoutManager.threeDWidget(viewIndex).threeDView()
        camera = view.cameraNode()
        bounds = [0.0] * 6
        resultNode.GetRASBounds(bounds)
        if bounds[0] <= bounds[1]:  # a valid box: look at the tree, not at the whole C-arm set-up
            camera.SetFocalPoint((bounds[0] + bounds[1]) / 2, (bounds[2] + bounds[3]) / 2, (bounds[4] + bounds[5]) / 2)
        set_camera_to_angles(camera, best["primary_deg"], best["secondary_deg"])
        camera.ResetClippingRange()
        return best

    # --- sample data and self-test ----------------------------------------------------------------
    def loadSampleCase(self):
        """Load the bundled two-view case: its masks (as frames and masks), geometry and ground truth."""
        missing = self.missingDependencies(SAMPLE_REQUIREMENTS)
        if missing:  # the case's files are PNG and NRRD: say so rather than fail inside the reader
            raise RuntimeError(self.dependencyError(missing))
        from SDFCARLib import mrml
        from SDFCARLib.sample_data import load_sample_case

        case = load_sample_case()
        p = self.getParameterNode()
        scene = slicer.mrmlScene
        with mrml.scene_transaction(scene):
            for n, (mask, view) in enumerate(zip(case.masks, case.geometry.views), start=1):
                frame = mrml.add_frame_volume_node(scene, mask.astype("uint8") * 255, f"SDFCAR sample view {n}", view.pixel_spacing_mm)
                label = mrml.add_frame_volume_node(scene, mask, f"SDFCAR sample view {n} mask", view.pixel_spacing_mm,
                                                   class_name="vtkMRMLLabelMapVolumeNode")
                self.setViewValue(p, n, "frame", frame)
                self.setViewValue(p, n, "mask", label)
            truth = mrml.add_segmentation_node(scene, case.label, case.geometry.volume, "SDFCAR sample ground truth",
                                               segment_name="Ground truth", color=(0.2, 0.8, 0.2))
            truth.GetDisplayNode().SetVisibility(False)
        self.setGeometryParameters(p, case.geometry)
        p.outputName = "SDFCAR sample"
        return truth

    @staticmethod
    def runSelfTest(log=logging.info, **kwargs):
        from SDFCARLib.selftest import run_selftest

        return run_selftest(slicer.mrmlScene, log=log, **kwargs)


class SDFCARTest(ScriptedLoadableModuleTest):
    def setUp(self):
        slicer.mrmlScene.Clear()

    def runTest(self):
        self.setUp()
        self.test_SelfTestScenario()
        self.setUp()
        self.test_WorkerReconstruction()

    def _skipWithoutDependencies(self, logic):
        # A build machine without torch cannot run these: a skip, not a failure of the ctest.
        missing = logic.missingDependencies()
        if missing:
            self.skipTest(logic.dependencyError(missing))

    def test_SelfTestScenario(self):
        """The scenario the headless test runs (SDFCARLib.selftest), in Slicer's own scene."""
        self.delayDisplay("Starting the SDFCAR self-test")
        logic = SDFCARLogic()
        self._skipWithoutDependencies(logic)
        result = logic.runSelfTest(log=self.delayDisplay)
        self.assertIsNotNone(slicer.mrmlScene.GetFirstNodeByName("SDFCAR self-test"))
        self.delayDisplay(f"Self-test passed: {result.metrics}")

    def test_WorkerReconstruction(self):
        """The Apply path: the worker process (PythonSlicer) reconstructs and writes the result
        files, the module loads them. The self-test above runs in-process and never reaches the
        worker's own imports (writing NRRD) or its interpreter."""
        from SDFCARLib.jobs import JobFailed
        from SDFCARLib.selftest import SETTINGS, selftest_case

        self.delayDisplay("Starting the SDFCAR worker test")
        logic = SDFCARLogic()
        self._skipWithoutDependencies(logic)
        case = selftest_case()
        name = "SDFCAR worker test"
        jobDir = Path(slicer.app.temporaryPath) / "SDFCAR" / f"worker-test-{time.strftime('%Y%m%d-%H%M%S')}"
        job = logic._startJob(jobDir, case.geometry, case.masks, dict(SETTINGS, steps=20), name)
        if job.wait(600) == "running":
            job.cancel()
        try:
            files = job.result()
        except JobFailed as exc:
            self.fail(f"the worker failed: {exc.message}\n{exc.traceback_text}")
        context = {"name": name, "geometry": case.geometry, "frames": case.frames(), "jobDir": str(jobDir),
                   "includeOccupancy": False, "showCArm": False}
        logic.addResults(files, context)
        self.assertIsNotNone(slicer.mrmlScene.GetFirstNodeByName(name))
        self.delayDisplay("Worker test passed")
