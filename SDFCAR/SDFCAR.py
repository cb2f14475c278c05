"""SDFCAR: 3D coronary artery tree from two X-ray angiography views (SDF-CAR), as a Slicer module.

A thin GUI over SDFCARLib: every computation lives in the library (``SDFCARLib.mrml`` for the scene,
``SDFCARLib.jobs`` for the background reconstruction); this file only wires widgets to it.
"""

import json
import logging
import os
import re
import sys
import time
from pathlib import Path
from typing import Annotated, Union

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
#: What each action needs, so a user who only loads the sample case is not asked for torch.
SAMPLE_REQUIREMENTS = ["nrrd", "imageio"]
VESSELNESS_REQUIREMENTS = ["skimage"]
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
Reconstructs the 3D coronary artery tree from two X-ray angiography views by per-patient
self-supervised optimisation of a signed-distance field (SDF-CAR). Choose the two frames (DICOM
XA runs or images) and their vessel masks, check the C-arm geometry (filled from the DICOM tags),
and press Apply. The result is a segmentation ("Coronary tree") and a surface model, with the
settings, losses and versions stored as node attributes (SDFCAR.*).
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

    def load(self, properties):
        try:
            nodes = loadSampleCaseAsking()
        except Exception:  # noqa: BLE001 - already shown to the user; the IO manager wants False
            logging.exception("Could not load the SDFCAR sample case")
            return False
        if not nodes:
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
    showCArm: bool = True


class SDFCARWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._job = None
        self._jobContext = None
        # Progress comes from the worker process; polling keeps the GUI responsive.
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
        self.ui.editMask1Button.connect("clicked(bool)", lambda: self.onEditMask(1))
        self.ui.editMask2Button.connect("clicked(bool)", lambda: self.onEditMask(2))
        self.ui.vesselness1Button.connect("clicked(bool)", lambda: self.onVesselness(1))
        self.ui.vesselness2Button.connect("clicked(bool)", lambda: self.onVesselness(2))
        self.ui.readGeometryButton.connect("clicked(bool)", self.onReadGeometry)
        self.ui.showCArmButton.connect("clicked(bool)", self.onShowCArm)
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.progressBar.setVisible(False)
        self.initializeParameterNode()

    def cleanup(self):
        self.removeObservers()
        self._timer.stop()
        if self._job is not None and self._job.state == "running":
            self._job.cancel()

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
        if self._parameterNode:
            self._parameterNodeGuiTag = self._parameterNode.connectParametersToGui(parameterWidgets(self.ui))
            self.addObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
            self._checkCanApply()

    def _checkCanApply(self, caller=None, event=None):
        p = self._parameterNode
        for n in (1, 2):
            hasFrame = bool(p and getattr(p, f"frame{n}"))
            getattr(self.ui, f"editMask{n}Button").enabled = hasFrame
            getattr(self.ui, f"vesselness{n}Button").enabled = hasFrame
        if self._job is not None:
            self.ui.applyButton.enabled = True  # it is the Cancel button now
            return
        ready = bool(p and p.frame1 and p.mask1 and p.frame2 and p.mask2)
        self.ui.applyButton.enabled = ready
        self.ui.applyButton.toolTip = "Reconstruct the coronary tree" if ready else "Choose both frames and their masks"

    # --- masks and geometry ---------------------------------------------------------------------
    def onEditMask(self, n):
        with slicer.util.tryWithErrorDisplay(f"Could not open the mask of frame {n} for editing.", waitCursor=True):
            p = self._parameterNode
            frame = getattr(p, f"frame{n}")
            segmentation = self.logic.maskSegmentation(frame, getattr(p, f"mask{n}"))
            setattr(p, f"mask{n}", segmentation)
            self.logic.editInSegmentEditor(segmentation, frame, getattr(p, f"frame{n}Index"))

    def onVesselness(self, n):
        with slicer.util.tryWithErrorDisplay(f"Vesselness could not segment frame {n}.", waitCursor=True):
            if not self.logic.ensureDependencies(VESSELNESS_REQUIREMENTS):
                return
            p = self._parameterNode
            segmentation, parameters = self.logic.vesselnessMask(
                getattr(p, f"frame{n}"), getattr(p, f"frame{n}Index"), getattr(p, f"mask{n}"),
                pixelSpacingMm=(getattr(p, f"pixelSpacingRow{n}"), getattr(p, f"pixelSpacingCol{n}")),
                magnification=getattr(p, f"sid{n}") / getattr(p, f"sod{n}"))
            setattr(p, f"mask{n}", segmentation)
            self.ui.statusLabel.text = (f"Vessel mask: {100 * parameters['vessel_fraction']:.1f} % of frame {n} in "
                                        f"{parameters['components']} piece(s), collimator excluded; refine it with Edit.")

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
        job = self._job
        if job is None:
            self._timer.stop()
            return
        info = job.poll()
        if info:
            self.ui.progressBar.maximum = max(1, int(info.get("total") or 1))
            self.ui.progressBar.value = int(info.get("step") or 0)
            self.ui.statusLabel.text = describeProgress(info)
        state = job.state
        if state == "running":
            return
        self._timer.stop()
        self._job, context = None, self._jobContext
        self.ui.applyButton.text = "Apply"
        self.ui.progressBar.setVisible(False)
        self._checkCanApply()
        if state == "cancelled":
            self.ui.statusLabel.text = "Cancelled: the scene is unchanged."
            return
        import SDFCARLib.jobs

        try:
            files = job.result()
        except SDFCARLib.jobs.JobFailed as exc:
            self.ui.statusLabel.text = "Failed: the scene is unchanged."
            slicer.util.errorDisplay(f"The reconstruction failed: {exc.message}", detailedText=exc.traceback_text)
            return
        with slicer.util.tryWithErrorDisplay("The reconstruction finished but its results could not be loaded.", waitCursor=True):
            self.logic.addResults(files, context)
            self.ui.statusLabel.text = f"Done: '{context['name']}' is in the scene (files in {context['jobDir']})."
        warnings = reportWarnings(files)
        if warnings:
            self.ui.statusLabel.text += f" {len(warnings)} warning(s)."
            slicer.util.warningDisplay("The reconstruction finished with warnings:\n\n" + "\n\n".join(warnings),
                                       windowTitle="SDFCAR")


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
        return mrml.mask_from_volume_node(frame, slice_index=self.sliceIndex(maskNode, frame, index))

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

    def vesselnessMask(self, frameNode, index=-1, maskNode=None, pixelSpacingMm=None, magnification=None):
        """Seed a frame's vessel segmentation with the angiogram mask pipeline (the command line's
        ``segment``); returns (segmentation, parameters). Pixel spacing (mm) and magnification
        (SID/SOD) set the physical vessel scales; without them typical values are assumed and reported."""
        from SDFCARLib import mrml
        from SDFCARLib.masks import angiogram_mask

        mask, parameters = angiogram_mask(self.frameArray(frameNode, index), pixelSpacingMm, magnification)
        with mrml.scene_transaction(slicer.mrmlScene):
            segmentation = self.maskSegmentation(frameNode, maskNode)
            mrml.set_segment_mask(segmentation, mask, frameNode, "Vessels")
        segmentation.SetAttribute("SDFCAR.vesselness", str(parameters))
        return segmentation, parameters

    # --- geometry ---------------------------------------------------------------------------------
    @staticmethod
    def geometryFromParameters(p, detectorShapes):
        """The Geometry the parameters describe (volume centre entered in RAS, kept in LPS)."""
        from SDFCARLib import mrml
        from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid

        views = []
        for n, shape in enumerate(detectorShapes, start=1):
            views.append(CArmView(
                getattr(p, f"primaryAngle{n}"), getattr(p, f"secondaryAngle{n}"), getattr(p, f"sid{n}"), getattr(p, f"sod{n}"),
                (getattr(p, f"pixelSpacingRow{n}"), getattr(p, f"pixelSpacingCol{n}")), tuple(int(s) for s in shape)))
        center = mrml.ras_to_lps([p.centerR, p.centerA, p.centerS])
        grid = VolumeGrid((int(p.volumeSize),) * 3, (float(p.voxelSpacing),) * 3, tuple(float(c) for c in center))
        return Geometry(grid, tuple(views))

    @staticmethod
    def setViewParameters(p, n, view):
        setattr(p, f"primaryAngle{n}", float(view.primary_deg))
        setattr(p, f"secondaryAngle{n}", float(view.secondary_deg))
        setattr(p, f"sid{n}", float(view.sid_mm))
        setattr(p, f"sod{n}", float(view.sod_mm))
        setattr(p, f"pixelSpacingRow{n}", float(view.pixel_spacing_mm[0]))
        setattr(p, f"pixelSpacingCol{n}", float(view.pixel_spacing_mm[1]))

    def setGeometryParameters(self, p, geometry):
        from SDFCARLib import mrml

        for n, view in enumerate(geometry.views[:2], start=1):
            self.setViewParameters(p, n, view)
        p.volumeSize = int(max(geometry.volume.shape))
        p.voxelSpacing = float(max(geometry.volume.spacing_mm))
        p.centerR, p.centerA, p.centerS = (float(c) + 0.0 for c in mrml.lps_to_ras(geometry.volume.center_mm))  # no -0.0

    def readGeometryFromDicom(self, p):
        """Fill the view fields from the frames' DICOM tags; returns notes for the user."""
        from SDFCARLib import mrml
        from SDFCARLib.dicom import view_from_dicom

        notes = []
        for n in (1, 2):
            uid, fileFrame = mrml.dicom_frame_reference(slicer.mrmlScene, getattr(p, f"frame{n}"), getattr(p, f"frame{n}Index"))
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
            self.setViewParameters(p, n, view)
            notes += [f"View {n}: {note}" for note in provenance.get("notes", [])]
        return notes

    def inputs(self, p):
        """(geometry, masks, frames) of the parameter node's choices, as arrays (rows, cols)."""
        frames = [self.frameArray(p.frame1, p.frame1Index), self.frameArray(p.frame2, p.frame2Index)]
        masks = [self.maskArray(p.mask1, p.frame1, p.frame1Index), self.maskArray(p.mask2, p.frame2, p.frame2Index)]
        return self.geometryFromParameters(p, [m.shape for m in masks]), masks, frames

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
        if p.steps > 0:
            values["steps"] = int(p.steps)
        return values

    @staticmethod
    def jobDirectory(p):
        chosen = str(p.outputDirectory) if p.outputDirectory is not None else ""
        base = Path(chosen) if chosen not in ("", ".") else Path(slicer.app.temporaryPath) / "SDFCAR"
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", p.outputName).strip("._") or "result"
        return base / f"{safe}-{time.strftime('%Y%m%d-%H%M%S')}"

    @staticmethod
    def _startJob(jobDir, geometry, masks, settings, name):
        import shutil

        from SDFCARLib.jobs import ReconstructionJob

        jobDir.parent.mkdir(parents=True, exist_ok=True)
        # The worker runs in Slicer's own Python (PythonSlicer), outside the GUI process.
        return ReconstructionJob.start(jobDir, geometry, masks, settings, name, python=shutil.which("PythonSlicer"))

    def startReconstruction(self, p):
        """Start a background job; returns (job, context for ``addResults``)."""
        geometry, masks, frames = self.inputs(p)
        jobDir = self.jobDirectory(p)
        job = self._startJob(jobDir, geometry, masks, self.settings(p), p.outputName)
        context = {"name": p.outputName, "geometry": geometry, "frames": frames, "jobDir": str(jobDir),
                   "includeOccupancy": p.includeOccupancy, "showCArm": p.showCArm}
        return job, context

    def addResults(self, files, context):
        """A job's result files into the scene (all or nothing) and into the 3D view."""
        from SDFCARLib import mrml

        scene = slicer.mrmlScene
        with mrml.scene_transaction(scene):
            nodes = mrml.add_reconstruction_to_scene(scene, files, context["name"], include_occupancy=context["includeOccupancy"],
                                                     attributes={"jobFolder": context["jobDir"]})
            if context["showCArm"]:
                mrml.add_carm_geometry_to_scene(scene, context["geometry"], images=context["frames"], name=f"{context['name']} C-arm")
        layoutManager = slicer.app.layoutManager()
        if layoutManager is not None and layoutManager.threeDViewCount > 0:
            layoutManager.threeDWidget(0).threeDView().resetFocalPoint()
        return nodes

    def reconstruct(self, frame1, mask1, frame2, mask2, geometry, settings=None, name="Coronary tree",
                    frameIndices=(-1, -1), jobDir=None, showCArm=True, includeOccupancy=False, timeout=None):
        """Console use: reconstruct and wait; returns SDFCARLib.mrml.ResultNodes.

        ``geometry``: an SDFCARLib Geometry whose detectors match the frames (e.g.
        ``Geometry.load("geometry.json")``); ``settings``: a dict (preset, mode, device, steps, seed).
        """
        frames = [self.frameArray(frame1, frameIndices[0]), self.frameArray(frame2, frameIndices[1])]
        masks = [self.maskArray(mask1, frame1, frameIndices[0]), self.maskArray(mask2, frame2, frameIndices[1])]
        jobDir = Path(jobDir) if jobDir else Path(slicer.app.temporaryPath) / "SDFCAR" / f"console-{time.strftime('%Y%m%d-%H%M%S')}"
        job = self._startJob(jobDir, geometry, masks, settings or {"preset": "fast"}, name)
        if job.wait(timeout) == "running":
            job.cancel()
        context = {"name": name, "geometry": geometry, "frames": frames, "jobDir": str(jobDir),
                   "includeOccupancy": includeOccupancy, "showCArm": showCArm}
        return self.addResults(job.result(), context)

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
                setattr(p, f"frame{n}", frame)
                setattr(p, f"mask{n}", label)
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
