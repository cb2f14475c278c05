"""Static checks of the Slicer module and the extension packaging (no Slicer application needed).

The GUI cannot run here, so what can break it without running is checked from the sources:
Python 3.9 grammar, widget names against the .ui, parameter-node bindings against the wrapper
class and against the widget kinds Slicer's GUI connectors accept, the CMake lists against the
files, the icon, the Extensions Index entry and the import-time rules.
"""

from __future__ import annotations

import ast
import fnmatch
import json
import re
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODULE = ROOT / "SDFCAR"
SCRIPT = MODULE / "SDFCAR.py"
UI = MODULE / "Resources" / "UI" / "SDFCAR.ui"
ICON = MODULE / "Resources" / "Icons" / "SDFCAR.png"
LIBRARY = ROOT / "SDFCARLib"


def source(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def ui_widgets():
    """{widget name: (class, SlicerParameterName or None, element)} of the .ui file."""
    out = {}
    for element in ET.parse(UI).getroot().iter("widget"):
        parameter = None
        for prop in element.findall("property"):
            if prop.get("name") == "SlicerParameterName":
                parameter = prop.find("string").text
        out[element.get("name")] = (element.get("class"), parameter, element)
    return out


def wrapper_parameters():
    """{name: annotation source} of the class decorated with @parameterNodeWrapper."""
    tree = ast.parse(source(SCRIPT))
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and any(
                (isinstance(d, ast.Name) and d.id == "parameterNodeWrapper") for d in node.decorator_list):
            return {item.target.id: ast.unparse(item.annotation) for item in node.body if isinstance(item, ast.AnnAssign)}
    raise AssertionError("SDFCAR.py has no @parameterNodeWrapper class")


# --- Python ------------------------------------------------------------------------------------------
# Slicer 5.4–5.8 run Python 3.9, and everything in SDFCAR/ and SDFCARLib/ is installed into Slicer.
SLICER_PYTHON_FILES = sorted(p for p in [*MODULE.rglob("*.py"), *LIBRARY.rglob("*.py")] if "__pycache__" not in p.parts)


@pytest.mark.parametrize("path", SLICER_PYTHON_FILES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_python_39_grammar(path):
    tree = ast.parse(source(path), filename=str(path), feature_version=(3, 9))
    future_annotations = any(isinstance(n, ast.ImportFrom) and n.module == "__future__" and
                             any(a.name == "annotations" for a in n.names) for n in tree.body)
    # "X | Y" in an annotation is evaluated at runtime unless annotations are postponed (3.10+ only).
    if not future_annotations:
        for node in ast.walk(tree):
            annotation = getattr(node, "annotation", None) or getattr(node, "returns", None)
            if annotation is not None:
                assert not any(isinstance(n, ast.BinOp) and isinstance(n.op, ast.BitOr) for n in ast.walk(annotation)), \
                    f"{path.name}:{node.lineno}: 'X | Y' annotation needs Python 3.10"


def _python39():
    """A Python 3.9 interpreter on this machine (pyenv's included), or None."""
    import shutil
    import subprocess

    candidates = [shutil.which("python3.9")] + sorted(str(p) for p in Path.home().glob(".pyenv/versions/3.9*/bin/python3.9"))
    for candidate in filter(None, candidates):
        try:
            out = subprocess.run([candidate, "-c", "import sys; print(sys.version_info[:2] == (3, 9))"],
                                 capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.SubprocessError):
            continue
        if out.stdout.strip() == "True":
            return candidate
    return None


def test_python_39_compiles_everything_slicer_imports():
    """The real 3.9 compiler where one is installed: ast's feature_version misses some newer syntax
    (e.g. parenthesised context managers) and every newer builtin-generic or library call."""
    import subprocess

    python39 = _python39()
    if python39 is None:
        pytest.skip("no Python 3.9 interpreter here (test_python_39_grammar still checks the grammar)")
    script = ("import sys\nbad = []\nfor path in sys.argv[1:]:\n"
              "    try:\n        compile(open(path, encoding='utf-8').read(), path, 'exec')\n"
              "    except SyntaxError as exc:\n        bad.append(f'{path}:{exc.lineno}: {exc.msg}')\n"
              "print('\\n'.join(bad))\nsys.exit(1 if bad else 0)\n")
    out = subprocess.run([python39, "-c", script, *map(str, SLICER_PYTHON_FILES)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, f"Python 3.9 cannot compile:\n{out.stdout}{out.stderr}"


def test_every_ui_widget_the_code_uses_exists():
    text = source(SCRIPT)
    used = set(re.findall(r"self\.ui\.(\w+)", text))
    for template in re.findall(r'getattr\(self\.ui, f"([^"]+)"\)', text):
        used |= {template.replace("{n}", str(n)) for n in (1, 2)}
    assert used, "no self.ui.X found: the check would be empty"
    missing = sorted(used - set(ui_widgets()))
    assert not missing, f"widgets used in SDFCAR.py but absent from SDFCAR.ui: {missing}"


def test_every_slicer_parameter_name_maps_to_a_parameter_and_back():
    parameters = wrapper_parameters()
    bound = {parameter: name for name, (_, parameter, _) in ui_widgets().items() if parameter}
    assert set(bound) - set(parameters) == set(), "SlicerParameterName without a parameter"
    assert set(parameters) - set(bound) == set(), "parameters without a widget (invisible to the user)"


# The oldest Slicer the module supports: parameterNodeWrapper first ships in 5.4.0. README,
# the top-level CMakeLists.txt (find_package) and this table must agree (test below).
OLDEST_SLICER = "5.4.0"

# Widget classes the GUI connectors of each Slicer version accept per parameter type: the
# canRepresent() methods of Base/Python/slicer/parameterNodeWrapper/guiConnectors.py at each
# tag. They compare type(widget) exactly, so a subclass (ctkDoubleSpinBox is no QDoubleSpinBox
# here) is refused, and connectGui raises in the module's setup(). "choice" is a str with Choice.
_CONNECTORS_5_4 = {
    "bool": {"QCheckBox", "QPushButton"},
    "int": {"QSlider", "QSpinBox"},
    "float": {"QDoubleSpinBox", "ctkSliderWidget"},
    "str": {"QLineEdit", "QTextEdit"},
    "choice": {"QComboBox"},
    "node": {"qMRMLNodeComboBox"},
    "Path": {"ctkPathLineEdit", "ctkDirectoryButton"},
}
_CONNECTORS_5_6 = dict(_CONNECTORS_5_4, float=_CONNECTORS_5_4["float"] | {"qMRMLSliderWidget"})
_CONNECTORS_5_8 = dict(
    _CONNECTORS_5_6,
    bool=_CONNECTORS_5_6["bool"] | {"ctkCheckBox"},
    float=_CONNECTORS_5_6["float"] | {"ctkDoubleSlider", "ctkDoubleSpinBox", "qMRMLSpinBox"},
    str=_CONNECTORS_5_6["str"] | {"QLabel"},
    choice=_CONNECTORS_5_6["choice"] | {"ctkComboBox"},
)
# 5.10.0: floats' widgets also take ints (QDoubleSpinBoxCtkSliderWidgetToFloatIntConnector).
_CONNECTORS_5_10 = dict(_CONNECTORS_5_8, bool=_CONNECTORS_5_8["bool"] | {"ctkCheckablePushButton"},
                        int=_CONNECTORS_5_8["int"] | _CONNECTORS_5_8["float"])
CONNECTORS_BY_SLICER = {
    "5.4.0": _CONNECTORS_5_4,    # tag v5.4.0
    "5.6.2": _CONNECTORS_5_6,    # tag v5.6.2 (same as v5.6.0)
    "5.8.1": _CONNECTORS_5_8,    # tags v5.8.0, v5.8.1
    "5.10.0": _CONNECTORS_5_10,  # tag v5.10.0 and branch 5.10
    "5.12.3": _CONNECTORS_5_10,  # tag v5.12.3: unchanged
    "main": _CONNECTORS_5_10,    # main, 2026-11: unchanged
}


def kind_of(annotation: str) -> str:
    if "Choice(" in annotation:
        return "choice"
    if "vtkMRML" in annotation:
        return "node"
    base = re.sub(r"^Annotated\[(\w+),.*\]$", r"\1", annotation)
    return base


def test_connector_table_only_grows():
    versions = list(CONNECTORS_BY_SLICER)
    assert versions[0] == OLDEST_SLICER
    for older, newer in zip(versions, versions[1:]):
        for kind, classes in CONNECTORS_BY_SLICER[older].items():
            assert classes <= CONNECTORS_BY_SLICER[newer][kind], (older, newer, kind)


@pytest.mark.parametrize("slicer_version", list(CONNECTORS_BY_SLICER))
def test_widget_kinds_match_parameter_types(slicer_version):
    """Every bound widget is of a class the connectors of each supported Slicer accept."""
    connectors = CONNECTORS_BY_SLICER[slicer_version]
    parameters = wrapper_parameters()
    bound = [(name, cls, parameter, element) for name, (cls, parameter, element) in ui_widgets().items() if parameter]
    assert len(bound) == len(parameters)
    for name, cls, parameter, element in bound:
        kind = kind_of(parameters[parameter])
        assert cls in connectors[kind], \
            f"{name} ({cls}) cannot show parameter {parameter} ({parameters[parameter]}) in Slicer {slicer_version}: use one of {sorted(connectors[kind])}"
        if kind == "node":
            types = [s.text for p in element.findall("property") if p.get("name") == "nodeTypes" for s in p.iter("string")]
            assert types and all(t in parameters[parameter] for t in types), f"{name} offers {types}, {parameter} takes {parameters[parameter]}"


def test_node_selectors_get_the_scene():
    root = ET.parse(UI).getroot()
    receivers = {c.find("receiver").text for c in root.iter("connection")
                 if c.find("signal").text == "mrmlSceneChanged(vtkMRMLScene*)"}
    selectors = {name for name, (cls, _, _) in ui_widgets().items() if cls == "qMRMLNodeComboBox"}
    assert selectors and selectors <= receivers, f"node selectors without the scene: {sorted(selectors - receivers)}"


def test_frame_selectors_list_colour_frames_but_no_labelmaps():
    """An RGB export of a frame loads as a vector volume, a child class of the scalar volume (Slicer's
    vtkSlicerVolumesLogic tries the vector reader first): the frame selectors show child classes but labelmaps and
    diffusion volumes, in the .ui (views 1 and 2) as in the Python-built rows (views 3, …)."""
    hidden = ast.literal_eval(re.search(r"^FRAME_HIDDEN_NODE_TYPES = (\[.*\])$", source(SCRIPT), re.M).group(1))
    assert "vtkMRMLLabelMapVolumeNode" in hidden
    widgets = ui_widgets()
    for name in ("frame1Selector", "frame2Selector"):
        properties = {p.get("name"): p for p in widgets[name][2].findall("property")}
        assert properties["showChildNodeTypes"].find("bool").text == "true", name
        assert [s.text for s in properties["hideChildNodeTypes"].iter("string")] == hidden, name
    assert "FRAME_HIDDEN_NODE_TYPES)" in source(SCRIPT)  # the Python-built frame selector gets the same list


def test_widget_names_are_unique_and_custom_widgets_declared():
    root = ET.parse(UI).getroot()
    names = [w.get("name") for w in root.iter("widget")]
    assert len(names) == len(set(names))
    declared = {c.find("class").text for c in root.iter("customwidget")}
    used = {w.get("class") for w in root.iter("widget")}
    custom = {c for c in used if c.startswith(("qMRML", "ctk", "qSlicer"))}
    assert custom <= declared, f"undeclared custom widgets: {sorted(custom - declared)}"


def test_import_time_rules():
    # The module must load without the heavy packages: they are offered for install on first Apply.
    # Of the library it imports at load time only the settings (torch-free: test_settings.py).
    heavy = {"torch", "kornia", "skimage", "pydicom", "scipy"}
    for node in ast.parse(source(SCRIPT)).body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            library = [n for n in names if n.split(".")[0] == "SDFCARLib"]
            assert not any(n.split(".")[0] in heavy for n in names), ast.unparse(node)
            assert all(n == "SDFCARLib.settings" for n in library), ast.unparse(node)
    # "import slicer.x" inside a function makes "slicer" local to it: earlier uses then fail.
    for node in ast.walk(ast.parse(source(SCRIPT))):
        if isinstance(node, (ast.FunctionDef, ast.Lambda)):
            for inner in ast.walk(node):
                if isinstance(inner, ast.Import):
                    assert not any(a.name.startswith("slicer.") and not a.asname for a in inner.names), ast.unparse(inner)
    # SDFCARLib never imports Qt or the Slicer application; slicer (slicer-core) only inside functions.
    for path in sorted(LIBRARY.rglob("*.py")):  # sub-packages (mrml/, ...) too
        for node in ast.parse(source(path)).body:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                assert not any(n.split(".")[0] in {"slicer", "qt", "ctk", "vtk"} for n in names), f"{path.name}: {ast.unparse(node)}"
        assert not re.search(r"^\s*(import|from)\s+(qt|ctk)\b", source(path), re.M), f"{path.name} imports Qt"
        assert "slicer.app" not in source(path), f"{path.name} uses the Slicer application"


# --- packaging ---------------------------------------------------------------------------------------
def cmake_words(path: Path) -> str:
    return re.sub(r"#[^\n]*", "", source(path))


def test_module_cmake_lists_every_file_of_the_module():
    text = cmake_words(MODULE / "CMakeLists.txt").replace("${MODULE_NAME}", "SDFCAR")
    files = [p.relative_to(MODULE).as_posix() for p in MODULE.rglob("*")
             if p.is_file() and "__pycache__" not in p.parts and p.name != "CMakeLists.txt"]
    assert files
    missing = [f for f in files if not re.search(r"(^|\s)" + re.escape(f) + r"(\s|$)", text)]
    assert not missing, f"files of SDFCAR/ not in SDFCAR/CMakeLists.txt: {missing}"
    assert re.search(r"slicerMacroBuildScriptedModule\(\s*NAME SDFCAR\s+SCRIPTS \$\{MODULE_PYTHON_SCRIPTS\}\s+RESOURCES \$\{MODULE_PYTHON_RESOURCES\}", text)


def test_module_cmake_installs_the_whole_library():
    text = cmake_words(MODULE / "CMakeLists.txt")
    script_globs = re.search(r"file\(GLOB_RECURSE SDFCARLIB_PYTHON_SCRIPTS\s+RELATIVE \$\{SDFCARLIB_SOURCE_DIR\}\s+CONFIGURE_DEPENDS\s+([^)]*)\)", text)
    data_globs = re.search(r"file\(GLOB_RECURSE SDFCARLIB_PYTHON_RESOURCES\s+RELATIVE \$\{SDFCARLIB_SOURCE_DIR\}\s+CONFIGURE_DEPENDS\s+([^)]*)\)", text)
    assert script_globs and data_globs
    assert re.search(r"set\(SDFCARLIB_SOURCE_DIR \$\{CMAKE_CURRENT_SOURCE_DIR\}/\.\.\)", text)
    assert re.search(r"ctkMacroCompilePythonScript\(\s*TARGET_NAME SDFCARLib\s+SCRIPTS \"\$\{SDFCARLIB_PYTHON_SCRIPTS\}\"\s+"
                     r"RESOURCES \"\$\{SDFCARLIB_PYTHON_RESOURCES\}\"\s+SOURCE_DIR \$\{SDFCARLIB_SOURCE_DIR\}\s+"
                     r"DESTINATION_DIR \$\{CMAKE_BINARY_DIR\}/\$\{Slicer_QTSCRIPTEDMODULES_LIB_DIR\}\s+"
                     r"INSTALL_DIR \$\{Slicer_INSTALL_QTSCRIPTEDMODULES_LIB_DIR\}\s+NO_INSTALL_SUBDIR", text)
    patterns = [g.replace("${SDFCARLIB_SOURCE_DIR}/", "") for g in script_globs.group(1).split()]
    data_patterns = [g.replace("${SDFCARLIB_SOURCE_DIR}/", "") for g in data_globs.group(1).split()]
    files = [p.relative_to(ROOT).as_posix() for p in LIBRARY.rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    for f in files:
        if f.startswith("SDFCARLib/data/"):
            assert any(fnmatch.fnmatch(f, d) for d in data_patterns), f
        else:
            # file(GLOB_RECURSE) "SDFCARLib/*.py" takes the .py files of every sub-package too.
            matched = [p for p in patterns if fnmatch.fnmatch(Path(f).name, Path(p).name)
                       and Path(f).parent.is_relative_to(Path(p).parent)]
            assert matched, f"{f} would not be installed with the extension"


def test_top_level_cmake_follows_the_extension_template():
    text = cmake_words(ROOT / "CMakeLists.txt")
    assert re.search(r"^project\(SDFCAR\)", text, re.M)
    for key in ("HOMEPAGE", "CATEGORY", "CONTRIBUTORS", "DESCRIPTION", "ICONURL", "SCREENSHOTURLS", "DEPENDS"):
        assert re.search(rf"set\(EXTENSION_{key}\s+\S", text), key
    assert re.search(r'set\(EXTENSION_ICONURL\s*"https://[^"]+\.png"\s*\)', text)
    assert re.search(r'set\(EXTENSION_SCREENSHOTURLS\s*"https://[^"]+"\)', text)
    order = ["find_package(Slicer ", "include(${Slicer_USE_FILE})", "add_subdirectory(SDFCAR)",
             "include(${Slicer_EXTENSION_GENERATE_CONFIG})", "include(${Slicer_EXTENSION_CPACK})"]
    positions = [text.find(s) for s in order]
    assert all(p >= 0 for p in positions) and positions == sorted(positions), dict(zip(order, positions))


def test_supported_slicer_versions_are_stated_alike():
    """README, CMake and the connector table name the same oldest Slicer."""
    major_minor = ".".join(OLDEST_SLICER.split(".")[:2])
    cmake = cmake_words(ROOT / "CMakeLists.txt")
    assert re.search(rf"find_package\(Slicer {re.escape(major_minor)} REQUIRED\)", cmake), "CMakeLists.txt: find_package(Slicer X.Y REQUIRED)"
    readme = source(ROOT / "README.md")
    stated = re.findall(r"3D Slicer (\d+\.\d+) or newer", readme)
    assert stated and set(stated) == {major_minor}, f"README states {stated}, the checks assume {major_minor}"
    # The Extensions Index entry has no version field (schema v1.0.2 allows no extra keys): the
    # Index picks Slicer versions by its branches, so SDFCAR.json cannot state it.


def test_icon_is_a_128_pixel_png():
    data = ICON.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    length, chunk, width, height = struct.unpack(">I4sII", data[8:24])
    assert chunk == b"IHDR" and (width, height) == (128, 128)


def test_extensions_index_entry():
    entry = json.loads(source(ROOT / "SDFCAR.json"))
    for key in ("$schema", "category", "scm_url"):
        assert entry.get(key), key
    assert "slicer-extension-catalog-entry-schema-v1.0.2.json" in entry["$schema"]
    allowed = {"$schema", "category", "scm_url", "scm_revision", "scm_type", "build_dependencies", "dicom_support_rule",
               "build_subdirectory", "enabled", "tier"}
    assert set(entry) <= allowed, set(entry) - allowed
    assert entry["scm_type"] in ("git", "local") and 1 <= entry["tier"] <= 5
    assert entry["scm_url"].rstrip("/").split("/")[-1].startswith("Slicer"), "the Extensions Index wants 'Slicer…' repositories"
    cmake = cmake_words(ROOT / "CMakeLists.txt")
    assert re.search(rf'set\(EXTENSION_CATEGORY\s+"{re.escape(entry["category"])}"\)', cmake)
    depends = re.search(r"set\(EXTENSION_DEPENDS\s+([^)]*)\)", cmake).group(1).replace('"', "").split()
    assert sorted(entry["build_dependencies"]) == sorted(d for d in depends if d != "NA")
    assert "\r" not in source(ROOT / "SDFCAR.json")


def test_license_is_apache_2():
    text = source(ROOT / "LICENSE")
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert "Copyright 2026 the SDFCAR authors" in text


def test_extension_icon_and_screenshots_are_in_the_repository():
    text = cmake_words(ROOT / "CMakeLists.txt")
    for key in ("ICONURL", "SCREENSHOTURLS"):
        url = re.search(rf'set\(EXTENSION_{key}\s*"([^"]+)"', text).group(1)
        for one in url.split():
            path = one.split("/main/", 1)[1]
            assert (ROOT / path).is_file(), f"EXTENSION_{key} names {path}, which is not in the repository"
            assert path.startswith("Resources/"), "extension-level resources live in the top-level Resources/"


# --- views 3, 4, … built in Python --------------------------------------------------------------------------
def _row_number_fields():
    tree = ast.parse(source(SCRIPT))
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef) and node.name == "AdditionalViewRow":
            for item in node.body:
                if isinstance(item, ast.Assign) and item.targets[0].id == "NUMBER_FIELDS":
                    return {row[0]: row[1:] for row in ast.literal_eval(item.value)}
    raise AssertionError("SDFCAR.py has no AdditionalViewRow.NUMBER_FIELDS")


def _ui_spin_box(name):
    element = ui_widgets()[name][2]
    out = {}
    for prop in element.findall("property"):
        value = prop[0]
        if value.tag in ("double", "number"):
            out[prop.get("name")] = float(value.text)
        elif value.tag == "string":
            out[prop.get("name")] = value.text or ""
    return out


def test_rows_of_views_3_and_later_match_views_1_and_2():
    """The Python-built rows, the stored views' checks, the wrapper's fields and the .ui agree per field."""
    from SDFCARLib.mrml.parameter_views import VIEW_NODE_FIELDS, VIEW_VALUE_FIELDS, parameter_name

    rows = _row_number_fields()
    parameters = wrapper_parameters()
    assert set(rows) | {"frameIndex"} == set(VIEW_VALUE_FIELDS)
    for field, (kind, low, high, _) in VIEW_VALUE_FIELDS.items():
        for n in (1, 2):
            name = parameter_name(field, n)
            assert name in parameters, f"the wrapper has no field {name}: views 3+ would be stored under other names"
            assert f"Annotated[{kind.__name__}, WithinRange({low!r}, {high!r})]" == parameters[name], (name, parameters[name])
        spin = _ui_spin_box(f"{parameter_name(field, 1)}SpinBox")
        assert (spin["minimum"], spin["maximum"]) == (low, high), field
        if field in rows:
            r_low, r_high, decimals, step, suffix, tooltip = rows[field]
            assert (r_low, r_high) == (low, high), field
            assert (decimals, step, suffix, tooltip) == (spin["decimals"], spin["singleStep"], spin["suffix"], spin["toolTip"]), field
    assert "self.frameIndexSpinBox.setRange(-1, 100000)" in source(SCRIPT)
    for field, classes in VIEW_NODE_FIELDS.items():
        assert all(c in parameters[f"{field}1"] for c in classes), field


# --- every Slicer, Qt and VTK name the module uses, read in Slicer's source ----------------------------------
# Each was read at the tags v5.4.0, v5.6.2, v5.8.1, v5.10.0, v5.12.3 and main of github.com/Slicer/Slicer
# (the file named), or is plain Qt 5 (Slicer's Qt) API. A new call fails this test until it is read
# there and added, with the file that declares it.
VERIFIED_MODULE_NAMES = {
    "slicer.app": "qSlicerApplication (Base/QTGUI/qSlicerApplication.h)",
    "slicer.app.connect": "QObject::connect through PythonQt (startupCompleted() signal of qSlicerCoreApplication)",
    "slicer.app.layoutManager": "qSlicerApplication::layoutManager (Base/QTGUI/qSlicerApplication.h)",
    "slicer.app.temporaryPath": "qSlicerCoreApplication temporaryPath property (Base/QTCore/qSlicerCoreApplication.h)",
    "slicer.app.setOverrideCursor": "QApplication; so called by tryWithErrorDisplay (util.py) at every tag",
    "slicer.app.restoreOverrideCursor": "QApplication; so called by tryWithErrorDisplay (util.py) at every tag",
    "slicer.modules": "module proxies; slicer.modules.plots.logic() is used in Base/Python/slicer/util.py (plot())",
    "slicer.mrmlScene": "the application scene",
    "slicer.mrmlScene.AddNewNodeByClass": "vtkMRMLScene (Libs/MRML/Core/vtkMRMLScene.h)",
    "slicer.mrmlScene.Clear": "vtkMRMLScene",
    "slicer.mrmlScene.EndCloseEvent": "vtkMRMLScene::SceneEventType",
    "slicer.mrmlScene.StartCloseEvent": "vtkMRMLScene::SceneEventType",
    "slicer.mrmlScene.GetFirstNodeByName": "vtkMRMLScene",
    "slicer.mrmlScene.IsNodePresent": "vtkMRMLScene (vtkCollection::IsItemPresent: 1-based position, 0 when absent)",
    "slicer.mrmlScene.RemoveNode": "vtkMRMLScene",
    "slicer.qMRMLNodeComboBox": "Libs/MRML/Widgets/qMRMLNodeComboBox.h; created from Python in "
                                "Modules/Scripted/CropVolumeSequence/CropVolumeSequence.py at every tag",
    "slicer.util": "Base/Python/slicer/util.py",
    "slicer.util.childWidgetVariables": "util.py", "slicer.util.confirmOkCancelDisplay": "util.py",
    "slicer.util.confirmYesNoDisplay": "Base/Python/slicer/util.py (text, windowTitle=None, parent=None) at every tag",
    "slicer.util.errorDisplay": "util.py", "slicer.util.warningDisplay": "util.py",
    "slicer.util.infoDisplay": "Base/Python/slicer/util.py (text, windowTitle=…) at every tag",
    "slicer.util.getModuleWidget": "util.py", "slicer.util.getModuleWidget().editor": "Segment Editor widget",
    "slicer.util.getNodesByClass": "util.py", "slicer.util.loadUI": "util.py", "slicer.util.pip_install": "util.py",
    "slicer.util.selectModule": "util.py", "slicer.util.setSliceViewerLayers": "util.py (fit= at every tag)",
    "slicer.util.tryWithErrorDisplay": "util.py",
    "qt.QTimer": "Qt", "qt.Qt": "Qt namespace",
    "qt.Qt.WaitCursor": "Qt::WaitCursor, as tryWithErrorDisplay (util.py) uses it at every tag",
    "qt.QGroupBox": "Qt", "qt.QFormLayout": "Qt", "qt.QHBoxLayout": "Qt",
    "qt.QSpinBox": "Qt", "qt.QDoubleSpinBox": "Qt", "qt.QPushButton": "Qt",
    "qt.QComboBox": "Qt; built from Python with addItem, currentIndex and currentIndexChanged(int) in "
                    "Modules/Scripted/ScreenCapture/ScreenCapture.py at every tag",
    "vtk.vtkCommand": "VTK", "vtk.vtkCommand.ModifiedEvent": "VTK",
}
# VTK/MRML methods (capitalised) called on nodes, loggers and cameras: the header that declares each.
VERIFIED_MRML_METHODS = {
    "AddEmptySegment": "vtkSegmentation", "AddNewNodeByClass": "vtkMRMLScene", "Clear": "vtkMRMLScene",
    "CreateDefaultDisplayNodes": "vtkMRMLDisplayableNode", "GetAttribute": "vtkMRMLNode", "SetAttribute": "vtkMRMLNode",
    "GetDisplayNode": "vtkMRMLDisplayableNode", "GetFirstNodeByName": "vtkMRMLScene", "GetID": "vtkMRMLNode",
    "GetName": "vtkMRMLNode", "GetSegmentation": "vtkMRMLSegmentationNode",
    "IsNodePresent": "vtkMRMLScene (int IsNodePresent(vtkMRMLNode*) at every tag)",
    "IsA": "vtkObject", "RemoveNode": "vtkMRMLScene", "SetVisibility": "vtkMRMLDisplayNode",
    "SetReferenceImageGeometryParameterFromVolumeNode": "vtkMRMLSegmentationNode",
    "SetSelectedItemNumber": "vtkMRMLSequenceBrowserNode",
    "GetRASBounds": "vtkMRMLSegmentationNode (override of vtkMRMLDisplayableNode)",
    "SetFocalPoint": "vtkMRMLCameraNode", "ResetClippingRange": "vtkMRMLCameraNode",
    "ShowChartInLayout": "vtkSlicerPlotsLogic (Modules/Loadable/Plots/Logic/vtkSlicerPlotsLogic.h)",
    "PyTorchUtilsLogic": "the PyTorch extension's PyTorchUtils module",
    "GetNumberOfControlPoints": "vtkMRMLMarkupsNode (Modules/Loadable/Markups/MRML/ to 5.8, Libs/MRML/Core/ from 5.10)",
    "GetNthControlPointPositionWorld": "vtkMRMLMarkupsNode (int index, double worldxyz[3]) at every tag",
}
# Qt/CTK/qMRML methods called on widgets, layouts, the layout manager and its views.
VERIFIED_WIDGET_METHODS = {
    "connect": "PythonQt signal connection", "setRange": "QSpinBox/QDoubleSpinBox", "addRow": "QFormLayout",
    "addWidget": "QBoxLayout", "setParent": "QWidget", "deleteLater": "QObject", "layout": "QWidget",
    "setVisible": "QWidget", "setInterval": "QTimer", "start": "QTimer", "stop": "QTimer",
    "setMRMLScene": "qMRMLNodeComboBox", "currentNode": "qMRMLNodeComboBox", "setCurrentNode": "qMRMLNodeComboBox",
    "addAttribute": "qMRMLNodeComboBox (Q_INVOKABLE)", "threeDWidget": "qSlicerLayoutManager",
    "threeDView": "qMRMLThreeDWidget", "resetFocalPoint": "qMRMLThreeDView", "cameraNode": "qMRMLThreeDView (Q_INVOKABLE)",
    "logic": "qSlicerAbstractCoreModule",
    "addItem": "QComboBox (ScreenCapture.py at every tag)",
}
# Properties set on widgets the module builds in Python (Qt properties, or qMRMLNodeComboBox's Q_PROPERTYs).
VERIFIED_WIDGET_PROPERTIES = {
    "specialValueText", "toolTip", "decimals", "singleStep", "suffix", "value", "enabled", "maximum", "text",
    "nodeTypes", "showChildNodeTypes", "hideChildNodeTypes", "noneEnabled", "addEnabled", "removeEnabled", "renameEnabled",
    "currentIndex",  # QComboBox (DICOM.py, DICOMScalarVolumePlugin.py set it at every tag)
}
VERIFIED_SIGNALS = {"clicked(bool)", "currentNodeChanged(vtkMRMLNode*)", "valueChanged(int)", "valueChanged(double)",
                    "startupCompleted()", "currentIndexChanged(int)"}
_WIDGET_ROOTS = {"row", "selector", "spinBox", "comboBox", "form", "maskRow", "container", "layoutManager", "view", "plots"}


def _chain(node):
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        return ".".join([node.id] + parts[::-1])
    if isinstance(node, ast.Call):
        inner = _chain(node.func)
        return None if inner is None else ".".join([inner + "()"] + parts[::-1])
    return None


def _module_uses():
    tree = ast.parse(source(SCRIPT))
    names, mrml_methods, widget_methods, properties, signals = set(), set(), set(), set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            chain = _chain(node)
            if chain and chain.split(".")[0] in ("slicer", "qt", "vtk") and not chain.startswith("slicer.util.VTK"):
                names.add(chain)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            receiver = _chain(node.func.value) or ""
            method = node.func.attr
            if method[:1].isupper() and receiver.split(".")[0] not in ("qt", "self") and receiver != "logic":
                mrml_methods.add(method)
            root = receiver.split(".")[0]
            if (receiver.startswith(("self.ui.", "self._timer")) or root in _WIDGET_ROOTS
                    or receiver in ("self.frameSelector", "self.maskSelector", "self.frameIndexSpinBox", "self.intensityComboBox",
                                    "self.layout")
                    or receiver.startswith(("layoutManager.", "plots."))):
                if method[:1].islower() and method not in ("items", "append", "pop", "setValues"):
                    widget_methods.add(method)
            if method == "connect" and node.args and isinstance(node.args[0], ast.Constant):
                signals.add(node.args[0].value)
        if isinstance(node, ast.Assign):
            for target in node.targets:
                if isinstance(target, ast.Attribute):
                    receiver = _chain(target.value) or ""
                    if (receiver.split(".")[0] in _WIDGET_ROOTS or receiver.startswith("self.ui.")
                            or receiver in ("self.frameIndexSpinBox", "self.intensityComboBox", "self.editMaskButton",
                                            "self.vesselnessButton", "self.removeButton")):
                        properties.add(target.attr)
    return names, mrml_methods, widget_methods, properties, signals


def test_every_slicer_qt_and_vtk_name_the_module_uses_was_verified():
    names, mrml_methods, widget_methods, properties, signals = _module_uses()
    assert {"slicer.qMRMLNodeComboBox", "qt.QGroupBox"} <= names and "GetRASBounds" in mrml_methods  # the scan works
    assert not names - set(VERIFIED_MODULE_NAMES), f"read these in Slicer's source, then list them: {sorted(names - set(VERIFIED_MODULE_NAMES))}"
    own = {"ViewParameters"}  # SDFCARLib classes
    unverified = mrml_methods - set(VERIFIED_MRML_METHODS) - own
    assert not unverified, f"VTK/MRML methods not read in Slicer's source: {sorted(unverified)}"
    assert not widget_methods - set(VERIFIED_WIDGET_METHODS), sorted(widget_methods - set(VERIFIED_WIDGET_METHODS))
    assert not properties - VERIFIED_WIDGET_PROPERTIES, sorted(properties - VERIFIED_WIDGET_PROPERTIES)
    assert not signals - VERIFIED_SIGNALS, sorted(signals - VERIFIED_SIGNALS)
    # No stale entries: the tables describe what the module uses today.
    assert not set(VERIFIED_MODULE_NAMES) - names, sorted(set(VERIFIED_MODULE_NAMES) - names)
    assert not set(VERIFIED_MRML_METHODS) - mrml_methods, sorted(set(VERIFIED_MRML_METHODS) - mrml_methods)
    assert not set(VERIFIED_WIDGET_METHODS) - widget_methods, sorted(set(VERIFIED_WIDGET_METHODS) - widget_methods)


def test_the_results_section_is_wired():
    """Every button of the Results section has a handler, and the result selector offers SDFCAR results only."""
    text = source(SCRIPT)
    for button, handler in (("addViewButton", "onAddView"), ("showQAButton", "onShowQA"), ("analyseButton", "onAnalyse"),
                            ("suggestedViewButton", "onSuggestedView")):
        assert f'self.ui.{button}.connect("clicked(bool)", self.{handler})' in text, button
        assert f"def {handler}(self" in text, handler
    assert 'self.ui.resultSelector.addAttribute("vtkMRMLSegmentationNode", "SDFCAR.role", "segmentation")' in text
    assert ui_widgets()["additionalViewsWidget"][0] == "QWidget"
    layouts = [l.get("class") for l in ui_widgets()["additionalViewsWidget"][2].findall("layout")]
    assert layouts == ["QVBoxLayout"], "the rows of views 3+ go into this widget's layout"


def test_the_grey_level_choices_are_the_librarys():
    """The "Grey levels" boxes offer nothing said and exactly the values SDFCARLib.mrml.say_frame_intensity takes,
    and the .ui holds a box for views 1 and 2 (views 3, 4, … build theirs from the same list)."""
    from SDFCARLib.mrml.inputs import FRAME_INTENSITY_VALUES

    (choices,) = [ast.literal_eval(node.value) for node in ast.parse(source(SCRIPT)).body
                  if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "FRAME_INTENSITY_CHOICES"]
    assert tuple(value for value, _ in choices) == ("",) + FRAME_INTENSITY_VALUES
    assert len({label for _, label in choices}) == len(choices)
    widgets = ui_widgets()
    assert all(widgets[f"frame{n}IntensityComboBox"][0] == "QComboBox" for n in (1, 2))
    assert 'form.addRow("Grey levels:", self.intensityComboBox)' in source(SCRIPT)
