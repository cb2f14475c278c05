"""Just enough of the Slicer application to import SDFCAR/SDFCAR.py and drive its widget and logic headless.

The parameter-node wrapper here copies the behaviour of Slicer 5.4–5.8 that matters to the
module (Base/Python/slicer/parameterNodeWrapper/wrapper.py and guiConnectors.py at v5.6.2):

- ``connectGui(gui)`` connects and returns None (``_connectGui`` drops the tag before 5.10.0);
  ``connectParametersToGui(mapping)`` returns the tag; ``disconnectGui(tag)`` ignores an unknown tag;
- a ``QComboBox`` connector fills its combo box in its constructor (``clear()`` then ``addItem``
  per choice) and reads ``choices[currentIndex]``, so a connector still connected when another
  one is built writes ``choices[-1]`` (clear: index -1), then ``choices[0]`` (first item).

The parameter node also has the raw ``vtkMRMLScriptedModuleNode`` calls the module uses for views
3, 4, … (SetParameter, GetParameter, HasParameter, UnsetParameter, node references), node
references resolving through the fake scene (``FakeNode`` registers itself there). The Qt widgets
the module builds in Python for those views record their signal connections, so a test can emit
``currentNodeChanged`` or ``valueChanged`` as the user would.

Everything else is a no-op recorder. Use ``install(monkeypatch)``; it returns the loaded module.
"""

from __future__ import annotations

import importlib.util
import sys
import types
import typing
import unittest
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "SDFCAR" / "SDFCAR.py"


# --- Qt --------------------------------------------------------------------------------------------
class Signal:
    def __init__(self):
        self._slots = []

    def connect(self, slot):
        self._slots.append(slot)

    def disconnect(self, slot):
        self._slots.remove(slot)

    def emit(self, *args):
        for slot in list(self._slots):
            slot(*args)


class Widget:
    """A Qt widget as the module uses it: properties as attributes, connections recorded by signal."""

    def __init__(self, name="", parameter=None, *args):
        self.name = name
        self._properties = {"SlicerParameterName": parameter}
        self.enabled = True
        self.toolTip = ""
        self.text = name if isinstance(name, str) else ""
        self.value = 0
        self.maximum = 99
        self.parent = None
        self.deleted = False
        self._layout = None
        self._current = None
        self.slots = {}

    def property(self, key):
        return self._properties.get(key)

    def connect(self, signal, slot):
        self.slots.setdefault(signal, []).append(slot)

    def emit(self, signal, *args):
        """What the user's action does: the connected slots run with the signal's arguments, as
        many as the slot takes (PythonQt passes a Python function at most its co_argcount
        arguments, a bound method one fewer: PythonQtSignalTarget::call)."""
        import inspect

        for slot in self.slots.get(signal, []):
            parameters = inspect.signature(slot).parameters.values()
            if any(p.kind == p.VAR_POSITIONAL for p in parameters):
                slot(*args)
                continue
            count = sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in parameters)
            slot(*args[:count])

    def setRange(self, minimum, maximum):
        self.minimum, self.maximum = minimum, maximum

    def setVisible(self, visible):
        self.visible = visible

    def setMRMLScene(self, scene):
        self.scene = scene

    def addAttribute(self, nodeType, name, value=None):
        self._properties.setdefault("attributes", []).append((nodeType, name, value))

    def currentNode(self):
        return self._current

    def setCurrentNode(self, node):
        if node is not self._current:
            self._current = node
            self.emit("currentNodeChanged(vtkMRMLNode*)", node)

    def layout(self):
        if self._layout is None:
            self._layout = Layout()
        return self._layout

    def setParent(self, parent):
        self.parent = parent

    def deleteLater(self):
        self.deleted = True


class Layout:
    def __init__(self, parent=None):
        self.items = []
        if parent is not None:
            parent._layout = self

    def addWidget(self, widget):
        self.items.append(widget)

    def addRow(self, *items):
        self.items.extend(items)


class ComboBox(Widget):
    """QComboBox as the connectors and the module see it: currentIndexChanged fires when the index changes, set by
    the user or by code (Qt emits it for setCurrentIndex and for the first addItem alike)."""

    def __init__(self, name="", parameter=None):
        super().__init__(name, parameter)
        self.items = []
        self._index = -1
        self.currentIndexChanged = Signal()

    @property
    def currentIndex(self):
        return self._index

    @currentIndex.setter
    def currentIndex(self, index):
        if index != self._index:
            self._index = index
            self.currentIndexChanged.emit(index)
            self.emit("currentIndexChanged(int)", index)

    def clear(self):
        self.items = []
        self.currentIndex = -1

    def addItem(self, text):
        self.items.append(text)
        if self._index == -1:
            self.currentIndex = 0


class Timer:
    def __init__(self):
        self.timeout = Signal()

    def setInterval(self, ms):
        pass

    def start(self):
        pass

    def stop(self):
        pass


# --- parameter-node wrapper (5.4–5.8 behaviour) ----------------------------------------------------
class Choice:
    def __init__(self, choices):
        self.choices = list(choices)


class WithinRange:
    def __init__(self, minimum, maximum):
        self.minimum, self.maximum = minimum, maximum


class ComboConnector:
    def __init__(self, widget, choices):
        self._widget, self._choices, self._callback = widget, choices, None
        widget.clear()
        for choice in choices:
            widget.addItem(str(choice))

    def _changed(self, index):
        if self._callback:
            self._callback()

    def onChanged(self, callback):
        self._callback = callback
        if callback is None:
            self._widget.currentIndexChanged.disconnect(self._changed)
        else:
            self._widget.currentIndexChanged.connect(self._changed)

    def read(self):
        return self._choices[self._widget.currentIndex]

    def write(self, value):
        self._widget.currentIndex = self._choices.index(value)


class OtherConnector:
    def __init__(self, widget, datatype):
        self._widget = widget

    def onChanged(self, callback):
        pass

    def write(self, value):
        pass


class FakeNode:
    """An MRML node in the fake scene: ID, name, class (IsA), attributes."""

    _count = 0

    def __init__(self, class_name, name):
        FakeNode._count += 1
        self._class, self._name, self._id = class_name, name, f"{class_name}{FakeNode._count}"
        self._attributes = {}
        SCENE[self._id] = self

    def GetID(self):
        return self._id

    def GetName(self):
        return self._name

    def GetClassName(self):
        return self._class

    def IsA(self, class_name):
        return class_name == self._class

    def GetAttribute(self, name):
        return self._attributes.get(name)

    def SetAttribute(self, name, value):
        self._attributes[name] = value

    def RemoveAttribute(self, name):
        self._attributes.pop(name, None)


SCENE = {}  # node ID -> FakeNode


class ParameterNode:
    """The MRML parameter node: values shared by every wrapper made on it, and the raw calls of
    vtkMRMLScriptedModuleNode the module makes for views 3, 4, … Like the real node, every change
    fires the observers (ModifiedEvent), once at the end of a StartModify/EndModify block."""

    def __init__(self):
        self.values = {}
        self.parameters = {}
        self.references = {}
        self._modifying = 0
        self._pending = False

    def Modified(self):
        if self._modifying:
            self._pending = True
            return
        for callback in list(OBSERVERS):
            callback()

    def GetScene(self):
        return None  # no MRML scene here: the views' same-scene check is tested against slicer-core (test_mrml_inputs)

    def SetParameter(self, name, value):
        if self.parameters.get(name) != str(value):
            self.parameters[name] = str(value)
            self.Modified()

    def GetParameter(self, name):
        return self.parameters.get(name, "")

    def HasParameter(self, name):
        return name in self.parameters

    def UnsetParameter(self, name):
        if self.parameters.pop(name, None) is not None:
            self.Modified()

    def SetNodeReferenceID(self, role, node_id):
        if self.references.get(role) != node_id:
            if node_id is None:
                self.references.pop(role, None)
            else:
                self.references[role] = node_id
            self.Modified()

    def GetNodeReferenceID(self, role):
        return self.references.get(role)

    def GetNodeReference(self, role):
        return SCENE.get(self.references.get(role))

    def RemoveNodeReferenceIDs(self, role):
        if self.references.pop(role, None) is not None:
            self.Modified()

    def StartModify(self):
        self._modifying += 1
        return self._modifying - 1

    def EndModify(self, previous):
        self._modifying = previous
        if not self._modifying and self._pending:
            self._pending = False
            self.Modified()
        return 0


def parameterNodeWrapper(cls):
    hints = typing.get_type_hints(cls, include_extras=True)
    defaults = {name: getattr(cls, name, None) for name in hints}

    class Wrapper:
        allParameters = hints

        def __init__(self, node):
            object.__setattr__(self, "parameterNode", node)
            object.__setattr__(self, "_parameterGUIs", {})
            object.__setattr__(self, "_nextTag", 0)
            for name, default in defaults.items():
                node.values.setdefault(name, default)

        def __getattr__(self, name):
            if name in hints:
                return self.parameterNode.values[name]
            raise AttributeError(name)

        def __setattr__(self, name, value):
            if name not in hints:
                raise AttributeError(name)
            self.parameterNode.values[name] = value
            self.parameterNode.Modified()

        def _choices(self, name):
            for extra in getattr(hints[name], "__metadata__", ()):
                if isinstance(extra, Choice):
                    return extra.choices
            return None

        def connectParametersToGui(self, mapping):
            connectors = {}
            for name, widget in mapping.items():
                choices = self._choices(name)
                connectors[name] = ComboConnector(widget, choices) if isinstance(widget, ComboBox) else OtherConnector(widget, hints[name])
            tag = self._nextTag
            object.__setattr__(self, "_nextTag", tag + 1)
            self._parameterGUIs[tag] = connectors
            for name, connector in connectors.items():
                connector.write(getattr(self, name))
                connector.onChanged(self._callback(name, connector))
            return tag

        def _callback(self, name, connector):
            return lambda: setattr(self, name, connector.read())

        def connectGui(self, gui):
            mapping = {w.property("SlicerParameterName"): w for w in vars(gui).values()
                       if hasattr(w, "property") and w.property("SlicerParameterName")}
            self.connectParametersToGui(mapping)  # 5.4–5.8: the tag is not returned

        def disconnectGui(self, tag):
            if tag in self._parameterGUIs:
                for connector in self._parameterGUIs[tag].values():
                    connector.onChanged(None)
                del self._parameterGUIs[tag]

    Wrapper.__name__ = cls.__name__
    return Wrapper


# --- ScriptedLoadableModule, util ----------------------------------------------------------------------
class ScriptedLoadableModule:
    def __init__(self, parent):
        self.parent = parent

    def runTest(self, msec=100, **kwargs):
        # as Slicer's (Base/Python/slicer/ScriptedLoadableModule.py, every tag): the <Module>Test case's runTest,
        # called directly, not through a unittest runner (Reload and Test)
        # (Slicer imports the module by name; the tests load SDFCAR.py unregistered: its namespace is the module's)
        test_case = type(self).__init__.__globals__[type(self).__name__ + "Test"]()
        test_case.messageDelay = msec
        test_case.runTest(**kwargs)


class ScriptedLoadableModuleWidget:
    def __init__(self, parent=None):
        self.parent = parent


class ScriptedLoadableModuleLogic:
    _node = None  # one parameter node per module, as Slicer keeps it in the scene

    def getParameterNode(self):
        if ScriptedLoadableModuleLogic._node is None:
            ScriptedLoadableModuleLogic._node = ParameterNode()
        return ScriptedLoadableModuleLogic._node


class ScriptedLoadableModuleTest(unittest.TestCase):  # as in Slicer: a unittest.TestCase
    def delayDisplay(self, message, *args, **kwargs):
        pass


OBSERVERS = []  # parameter-node observers (the module's _checkCanApply): called on every wrapper write


class VTKObservationMixin:
    def __init__(self):
        pass

    def addObserver(self, obj, event=None, callback=None, *args):
        if isinstance(obj, ParameterNode) or hasattr(obj, "parameterNode"):
            OBSERVERS.append(callback)

    def removeObserver(self, obj, event=None, callback=None, *args):
        if callback in OBSERVERS:
            OBSERVERS.remove(callback)

    def removeObservers(self, *args):
        pass


class _Recorder:
    def __init__(self):
        self.errors = []
        self.warnings = []
        self.infos = []
        self.sliceLayers = []
        self.confirm = True
        self.questions = []
        self.cursor = []  # setOverrideCursor / restoreOverrideCursor calls, in order
        self.pipInstalls = []

    def errorDisplay(self, text, **kwargs):
        self.errors.append(text)

    def warningDisplay(self, text, **kwargs):
        self.warnings.append(text)
        self.cursor.append("warned")

    def infoDisplay(self, text, **kwargs):
        self.infos.append(text)

    def setSliceViewerLayers(self, background="keep-current", **kwargs):
        self.sliceLayers.append(dict(kwargs, background=background))

    def confirmOkCancelDisplay(self, text, **kwargs):
        return self.confirm

    def confirmYesNoDisplay(self, text, **kwargs):
        self.questions.append(text)
        self.cursor.append("asked")
        return self.confirm

    def pip_install(self, requirements):
        self.pipInstalls.append(requirements)


def _module(name, **attributes):
    module = types.ModuleType(name)
    module.__dict__.update(attributes)
    return module


class _RealMRML(types.ModuleType):
    """The fake ``slicer`` module in front of slicer-core: what the fake does not define (MRML classes,
    vtkSlicer… logics) comes from the real MRML."""

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._real, name)


class _ThreeDView:
    def __init__(self, camera):
        self._camera = camera

    def cameraNode(self):
        return self._camera

    def resetFocalPoint(self):
        pass


class LayoutManager:
    """A layout with one 3D view whose camera is a real vtkMRMLCameraNode of the scene."""

    def __init__(self, scene):
        self.threeDViewCount = 1
        self.camera = scene.AddNewNodeByClass("vtkMRMLCameraNode", "Camera")
        self.camera.SetFocalPoint(0.0, 0.0, 0.0)
        self.camera.SetPosition(0.0, 500.0, 0.0)

    def threeDWidget(self, index):
        return types.SimpleNamespace(threeDView=lambda: _ThreeDView(self.camera))


def install(monkeypatch, real_mrml=False):
    """Put the fakes in sys.modules (undone after the test) and load SDFCAR.py; returns the module.

    ``real_mrml``: ``slicer.mrmlScene`` is a real slicer-core scene (``module.scene``), the MRML
    classes are slicer-core's, and the application has a layout manager with one 3D view
    (``module.layoutManager``), so the logic runs on real MRML; Qt and the wrapper stay fakes.
    """
    import contextlib

    recorder = _Recorder()
    real = None
    if real_mrml:
        import slicer as real  # slicer-core, imported before the fake takes its name

        from SDFCARLib import mrml

    @contextlib.contextmanager
    def tryWithErrorDisplay(message=None, show=True, waitCursor=False):
        try:
            yield
        except Exception as exc:
            recorder.errors.append(f"{message}\n\n{exc}")
            raise

    node_names = ("vtkMRMLLabelMapVolumeNode", "vtkMRMLScalarVolumeNode", "vtkMRMLSegmentationNode")
    node_classes = {n: (getattr(real, n) if real is not None else type(n, (), {})) for n in node_names}
    SCENE.clear()
    OBSERVERS.clear()
    util = _module("slicer.util", VTKObservationMixin=VTKObservationMixin, tryWithErrorDisplay=tryWithErrorDisplay,
                   errorDisplay=recorder.errorDisplay, warningDisplay=recorder.warningDisplay, infoDisplay=recorder.infoDisplay,
                   setSliceViewerLayers=recorder.setSliceViewerLayers,
                   confirmOkCancelDisplay=recorder.confirmOkCancelDisplay, confirmYesNoDisplay=recorder.confirmYesNoDisplay,
                   pip_install=recorder.pip_install)
    app = types.SimpleNamespace(connect=lambda *a: None, temporaryPath="/tmp", layoutManager=lambda: None,
                                setOverrideCursor=lambda cursor: recorder.cursor.append(cursor),
                                restoreOverrideCursor=lambda: recorder.cursor.append("restored"))
    scene = types.SimpleNamespace(Clear=lambda *a: None, GetNodeByID=SCENE.get)
    layout_manager = None
    if real is not None:
        scene = mrml.new_scene()
        layout_manager = LayoutManager(scene)
        app.layoutManager = lambda: layout_manager
    slicer = _module("slicer", util=util, app=app, mrmlScene=scene, modules=types.SimpleNamespace(),
                     qMRMLNodeComboBox=Widget, **node_classes)
    if real is not None:
        slicer.__class__ = _RealMRML
        slicer._real = real
    slicer.__path__ = []  # a package, so "from slicer import packaging" looks for a submodule (absent before 5.12)
    slicer.parameterNodeWrapper = _module("slicer.parameterNodeWrapper", Choice=Choice, WithinRange=WithinRange,
                                          parameterNodeWrapper=parameterNodeWrapper)
    slicer.ScriptedLoadableModule = _module(
        "slicer.ScriptedLoadableModule", ScriptedLoadableModule=ScriptedLoadableModule,
        ScriptedLoadableModuleWidget=ScriptedLoadableModuleWidget, ScriptedLoadableModuleLogic=ScriptedLoadableModuleLogic,
        ScriptedLoadableModuleTest=ScriptedLoadableModuleTest)
    for name, module in {"slicer": slicer, "slicer.util": util, "slicer.parameterNodeWrapper": slicer.parameterNodeWrapper,
                         "slicer.ScriptedLoadableModule": slicer.ScriptedLoadableModule,
                         "qt": _module("qt", QTimer=Timer, QWidget=Widget, QGroupBox=Widget, QPushButton=Widget,
                                       QSpinBox=Widget, QDoubleSpinBox=Widget, QLabel=Widget, QComboBox=ComboBox,
                                       QFormLayout=Layout, QHBoxLayout=Layout,
                                       Qt=types.SimpleNamespace(WaitCursor="WaitCursor"))}.items():
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.delitem(sys.modules, "slicer.packaging", raising=False)
    ScriptedLoadableModuleLogic._node = None
    spec = importlib.util.spec_from_file_location("SDFCAR_under_test", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.recorder = recorder
    module.scene = scene
    module.layoutManager = layout_manager
    return module


def module_ui(module):
    """Every widget of the .ui under its name (as childWidgetVariables gives them), with its
    SlicerParameterName; QComboBox widgets are ComboBox (the connector fills them)."""
    import xml.etree.ElementTree as ET

    ui = types.SimpleNamespace()
    for element in ET.parse(SCRIPT.parent / "Resources" / "UI" / "SDFCAR.ui").getroot().iter("widget"):
        parameter = None
        for prop in element.findall("property"):
            if prop.get("name") == "SlicerParameterName":
                parameter = prop.find("string").text
        cls = ComboBox if element.get("class") == "QComboBox" else Widget
        setattr(ui, element.get("name"), cls(element.get("name"), parameter))
    return ui
