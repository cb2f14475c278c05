"""The views of the Slicer module beyond the first two, stored in its parameter node.

The module's parameter node (a ``vtkMRMLScriptedModuleNode``) holds views 1 and 2 through
Slicer's ``parameterNodeWrapper`` (typed fields ``frame1``, ``primaryAngle1``, …, kept so that
scenes saved before stay readable). Views 3, 4, … are stored here with the node's own API, under
the same names the wrapper uses for views 1 and 2:

    viewCount               total number of views (absent: 2)
    frame<n>, mask<n>       node references (role = name), as the wrapper stores a node
    frame<n>Index, primaryAngle<n>, secondaryAngle<n>, sid<n>, sod<n>,
    pixelSpacingRow<n>, pixelSpacingCol<n>
                            parameters holding ``str(value)``, as the wrapper stores a number
                            (the field ``frameIndex`` is named ``frame<n>Index``, as the wrapper's
                            ``frame1Index``)

Why not a ``List[...]`` field of the wrapper: Slicer 5.4–5.8 have a list serializer but no GUI
connector for lists, and a list of nodes or of parameter packs cannot be bound to the rows the
module builds in Python; plain references and parameters are saved with the scene (.mrml, .mrb)
by every Slicer version, and a node reference is cleared by MRML itself when its node is deleted.

Every function takes the raw node (``wrapper.parameterNode`` in the module) and touches only the
names of views ``n >= FIRST_STORED_VIEW``; it needs no ``slicer`` import, so it runs on Slicer's
node, on slicer-core's and on a test double alike.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from .scene import MRMLBridgeError

#: Views 1 and 2 are the wrapper's; the first view stored here.
FIRST_STORED_VIEW = 3
#: An upper bound that keeps the module's rows usable (the engine itself has none).
MAX_VIEWS = 12
VIEW_COUNT_PARAMETER = "viewCount"

#: Numeric fields of a view: name -> (type, minimum, maximum, default). The ranges are those of the
#: wrapper's fields for views 1 and 2 (SDFCAR.py; Testing/test_module_static.py checks they agree).
VIEW_VALUE_FIELDS: Dict[str, Tuple[type, float, float, Any]] = {
    "frameIndex": (int, -1, 100000, -1),
    "primaryAngle": (float, -180.0, 180.0, 0.0),
    "secondaryAngle": (float, -90.0, 90.0, 0.0),
    "sid": (float, 1.0, 5000.0, 1000.0),
    "sod": (float, 1.0, 5000.0, 757.0),
    "pixelSpacingRow": (float, 0.001, 10.0, 0.278),
    "pixelSpacingCol": (float, 0.001, 10.0, 0.278),
}
#: Node fields of a view: name -> the MRML classes it takes.
VIEW_NODE_FIELDS: Dict[str, Tuple[str, ...]] = {
    "frame": ("vtkMRMLScalarVolumeNode",),
    "mask": ("vtkMRMLSegmentationNode", "vtkMRMLLabelMapVolumeNode"),
}
VIEW_FIELDS = tuple(VIEW_NODE_FIELDS) + tuple(VIEW_VALUE_FIELDS)
_UNITS = {"primaryAngle": "°", "secondaryAngle": "°", "sid": " mm", "sod": " mm", "pixelSpacingRow": " mm",
          "pixelSpacingCol": " mm", "frameIndex": ""}


@dataclass
class ViewParameters:
    """One view's choices as the module shows them (numbers as in the fields, nodes or None)."""

    frame: Any = None
    mask: Any = None
    frameIndex: int = -1
    primaryAngle: float = 0.0
    secondaryAngle: float = 0.0
    sid: float = 1000.0
    sod: float = 757.0
    pixelSpacingRow: float = 0.278
    pixelSpacingCol: float = 0.278

    def values(self) -> Dict[str, Any]:
        return {name: getattr(self, name) for name in VIEW_FIELDS}


def parameter_name(field: str, view_number: int) -> str:
    """The parameter (or reference role) name of a view's field, as the wrapper names those of views
    1 and 2: ``primaryAngle3``, ``frame4``, ``frame3Index``."""
    if field not in VIEW_FIELDS:
        raise MRMLBridgeError(f"a view has no field {field!r}; the fields are {', '.join(VIEW_FIELDS)}")
    if field == "frameIndex":
        return f"frame{int(view_number)}Index"
    return f"{field}{int(view_number)}"


def view_count(node) -> int:
    """Number of views the parameter node describes (2 when it never had more)."""
    if node is None or not node.HasParameter(VIEW_COUNT_PARAMETER):
        return FIRST_STORED_VIEW - 1
    text = node.GetParameter(VIEW_COUNT_PARAMETER)
    try:
        count = int(text)
    except (TypeError, ValueError):
        raise MRMLBridgeError(f"the module's parameter {VIEW_COUNT_PARAMETER} is {text!r}, not a number of views; "
                              "the scene was edited by hand or is damaged: remove the extra views and add them again")
    return min(max(count, FIRST_STORED_VIEW - 1), MAX_VIEWS)


def _check_stored(node, view_number: int) -> int:
    if isinstance(view_number, bool) or not isinstance(view_number, numbers.Integral):
        raise MRMLBridgeError(f"a view number is a whole number (3, 4, …), got {view_number!r}")
    n = int(view_number)
    if n < FIRST_STORED_VIEW:
        raise MRMLBridgeError(f"view {n} is one of the module's first two views, which the parameter node wrapper "
                              f"holds (frame{n}, primaryAngle{n}, …); use its fields")
    count = view_count(node)
    if n > count:
        raise MRMLBridgeError(f"there is no view {n}: the module has {count} views; add one first")
    return n


def _check_value(field: str, value: Any, view_number: int) -> Any:
    kind, low, high, _ = VIEW_VALUE_FIELDS[field]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):  # numpy's numbers are Real
        raise MRMLBridgeError(f"view {view_number}: {field} must be a number, got {value!r}")
    if kind is int:
        if int(value) != value:
            raise MRMLBridgeError(f"view {view_number}: {field} must be a whole number, got {value!r}")
        value = int(value)
    else:
        value = float(value)
    if not low <= value <= high:
        unit = _UNITS.get(field, "")
        raise MRMLBridgeError(f"view {view_number}: {field} {value:g}{unit} is outside {low:g}{unit} to {high:g}{unit}; "
                              "enter a value in that range")
    return value


def _check_node(field: str, value: Any, view_number: int, scene=None) -> Any:
    if value is None:
        return None
    classes = VIEW_NODE_FIELDS[field]
    if not hasattr(value, "IsA") or not any(value.IsA(c) for c in classes):
        got = value.GetClassName() if hasattr(value, "GetClassName") else type(value).__name__
        raise MRMLBridgeError(f"view {view_number}: the {field} must be a {' or a '.join(classes)}, got a {got}")
    if value.GetID() is None or (scene is not None and value.GetScene() is not scene):
        raise MRMLBridgeError(f"view {view_number}: the {field} node {value.GetName()!r} is not in the parameter node's "
                              "scene; add it to that scene first")
    return value


def _write(node, n: int, field: str, value: Any) -> None:
    name = parameter_name(field, n)
    if field in VIEW_NODE_FIELDS:
        # As the wrapper writes a node: an empty parameter marks it present, the reference holds it.
        node.SetParameter(name, "")
        node.SetNodeReferenceID(name, value.GetID() if value is not None else None)
    else:
        node.SetParameter(name, str(value))


def _read(node, n: int, field: str) -> Any:
    name = parameter_name(field, n)
    if field in VIEW_NODE_FIELDS:
        return node.GetNodeReference(name)
    kind, _, _, default = VIEW_VALUE_FIELDS[field]
    if not node.HasParameter(name):
        return default
    text = node.GetParameter(name)
    try:
        return kind(float(text)) if kind is int else kind(text)
    except (TypeError, ValueError):
        raise MRMLBridgeError(f"view {n}: the stored {field} is {text!r}, not a number; enter it again")


def _remove(node, n: int) -> None:
    for field in VIEW_FIELDS:
        name = parameter_name(field, n)
        node.UnsetParameter(name)
        if field in VIEW_NODE_FIELDS:
            node.RemoveNodeReferenceIDs(name)


def get_view_value(node, view_number: int, field: str) -> Any:
    """One field of stored view ``view_number`` (a node or None, or a number)."""
    return _read(node, _check_stored(node, view_number), field)


def get_view(node, view_number: int) -> ViewParameters:
    """All fields of stored view ``view_number``."""
    n = _check_stored(node, view_number)
    return ViewParameters(**{field: _read(node, n, field) for field in VIEW_FIELDS})


def set_view_value(node, view_number: int, field: str, value: Any) -> None:
    """Set one field of stored view ``view_number`` (checked as the wrapper checks views 1 and 2)."""
    n = _check_stored(node, view_number)
    parameter_name(field, n)  # names the fields when ``field`` is unknown
    value = _check_node(field, value, n, node.GetScene()) if field in VIEW_NODE_FIELDS else _check_value(field, value, n)
    _write(node, n, field, value)


def add_view(node, values: Optional[Mapping[str, Any]] = None) -> int:
    """Append a view (defaults, overridden by ``values``); returns its number. Nothing changes on error."""
    count = view_count(node)
    n = count + 1
    if n > MAX_VIEWS:
        raise MRMLBridgeError(f"the module takes at most {MAX_VIEWS} views; remove one before adding another")
    unknown = sorted(set(values or {}) - set(VIEW_FIELDS))
    if unknown:
        raise MRMLBridgeError(f"a view has no field {', '.join(unknown)}; the fields are {', '.join(VIEW_FIELDS)}")
    record = ViewParameters().values()
    record.update(values or {})
    checked = {f: (_check_node(f, v, n, node.GetScene()) if f in VIEW_NODE_FIELDS else _check_value(f, v, n))
               for f, v in record.items()}
    modified = node.StartModify()
    try:
        for field, value in checked.items():
            _write(node, n, field, value)
        node.SetParameter(VIEW_COUNT_PARAMETER, str(n))
    finally:
        node.EndModify(modified)
    return n


def remove_view(node, view_number: int) -> None:
    """Remove stored view ``view_number``; the views after it move up one number."""
    n = _check_stored(node, view_number)
    count = view_count(node)
    later = [get_view(node, m) for m in range(n + 1, count + 1)]
    modified = node.StartModify()
    try:
        for m, view in enumerate(later, start=n):
            for field, value in view.values().items():
                _write(node, m, field, value)
        _remove(node, count)
        if count - 1 < FIRST_STORED_VIEW:
            node.UnsetParameter(VIEW_COUNT_PARAMETER)
        else:
            node.SetParameter(VIEW_COUNT_PARAMETER, str(count - 1))
    finally:
        node.EndModify(modified)


def set_view_count(node, count: int) -> None:
    """Keep views 1 … ``count`` (at least 2): add default views or remove the last ones."""
    count = int(count)
    if not FIRST_STORED_VIEW - 1 <= count <= MAX_VIEWS:
        raise MRMLBridgeError(f"the module takes {FIRST_STORED_VIEW - 1} to {MAX_VIEWS} views, not {count}")
    while view_count(node) < count:
        add_view(node)
    while view_count(node) > count:
        remove_view(node, view_count(node))
