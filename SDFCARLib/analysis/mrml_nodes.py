"""3D-QCA results as Slicer scene content: curves with diameters, a table, plots, the view map.

``add_analysis_nodes(scene, analysis_dir)`` reads what ``analyse`` wrote (analysis.json and the
per-branch CSV profiles) and adds

    one markups curve per branch      control points every ``point_step_mm`` along the centreline
                                      (linear curve, RAS), with the static measurements
                                      "Diameter" (3D equivalent diameter, mm) and "Radius" per
                                      control point; attributes SDFCAR.branchId / parentId
    a table node "… QCA"              one row per branch: length, mean/min diameter, worst lesion
                                      (graded on the frames where given, and its 3D-section measures),
                                      the branch's median angle to the views' epipolar planes
    a table node per branch profile   arc length and diameters (3D, masks, and the frames' edges and
                                      density where analyse was given the frames), the angle to the
                                      epipolar planes where analysed with two views or more, feeding
    a plot chart "… diameters"        one line per branch, diameter against arc length
    a scalar volume "… view map"      the foreshortening + overlap score (%) over (primary,
                                      secondary) in degrees as a one-slice image; attributes
                                      hold the suggested angles
    a point list "… likeliest ostium" only where the analysis found its root on a vessel's side
                                      (``root_check.through_vessel_root``): one point (RAS) at the
                                      end it names instead, for the user to check, move and give as
                                      the Ostium of the next analysis

``add_analysis_to_scene`` is what the Slicer module calls: the same nodes, all or nothing, in one
subject-hierarchy folder, linked to the result segmentation (``SDFCAR.analysisFolder``), which
``suggested_view_of`` reads back.

``camera_for_angles`` gives the 3D camera that shows the tree as the C-arm at (α, β) does and
``set_camera_to_angles`` applies it to a camera node — the Slicer module's "show suggested view"
button calls it with the analysis's best angles.

Coordinates: the files are LPS; MRML holds RAS (``mrml.lps_to_ras``). Like ``mrml.py`` the
functions take the scene as an argument (Slicer's or slicer-core's) and import ``slicer`` inside.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..mrml import lps_to_ras

PathLike = Union[str, Path]


def _slicer_module():
    try:
        import slicer
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("the QCA scene nodes need 3D Slicer's Python or 'slicer-core' (pip install slicer-core)") from exc
    return slicer


#: the "… QCA" table: one row per branch; its worst lesion as graded (MLD … lesion length, graded_on,
#: found_on, seen_on_frames, seen_on_masks), as the 3D sections measure it, and the masks' largest narrowing there
QCA_TABLE_COLUMNS = ("branch", "parent", "length_mm", "mean_diameter_mm", "mld_mm", "diameter_stenosis_pct",
                     "area_stenosis_pct", "lesion_length_mm", "graded_on", "found_on", "seen_on_frames", "seen_on_masks",
                     "diameter_stenosis_3d_pct", "mld_3d_mm", "diameter_stenosis_masks_pct", "epipolar_angle_median_deg")
#: profile columns measured on the frames (edges, density), in the branch profile tables when present
FRAME_COLUMNS = ("diameter_frames_mm", "diameter_frames_density_mm")
#: profile columns of later analyses, in the branch profile tables when present (absent from older files)
OPTIONAL_COLUMNS = FRAME_COLUMNS + ("epipolar_angle_deg",)


#: the profile columns every ``analyse`` writes, and the ones that place the curve (finite in every row)
PROFILE_COLUMNS = ("arc_mm", "diameter_3d_mm", "diameter_masks_mm", "reference_mm", "excluded", "x_mm", "y_mm", "z_mm")
_PLACING_COLUMNS = ("arc_mm", "x_mm", "y_mm", "z_mm")


def _read_profile(path: Path) -> Dict[str, np.ndarray]:
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: the analysis folder is incomplete; re-run analyse")
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
        header = reader.fieldnames or []
    if not rows:
        raise ValueError(f"{path} holds no profile rows; re-run analyse")
    missing = [k for k in PROFILE_COLUMNS if k not in header and k != "excluded"]  # older files had no "excluded"
    if missing:
        raise ValueError(f"{path} lacks the column(s) {', '.join(missing)}: it is not a profile analyse wrote; re-run analyse")

    def col(name):
        values = []
        for n, r in enumerate(rows, start=2):  # line 1 is the header
            text = r.get(name)
            try:
                values.append(float(text) if text not in (None, "") else np.nan)
            except ValueError:
                raise ValueError(f"{path}, line {n}: {name} = {text!r} is not a number; re-run analyse") from None
        return np.array(values)

    # The frame columns exist only where analyse was given the frames.
    keys = [k for k in PROFILE_COLUMNS if k in header] + [k for k in OPTIONAL_COLUMNS if k in header]
    profile = {k: col(k) for k in keys}
    for k in _PLACING_COLUMNS:
        if not np.all(np.isfinite(profile[k])):
            line = int(np.flatnonzero(~np.isfinite(profile[k]))[0]) + 2
            raise ValueError(f"{path}, line {line}: {k} is missing (a cut or edited file); re-run analyse")
    profile["excluded"] = profile.get("excluded", np.zeros(len(rows))) > 0
    return profile


def _double_array(name: str, values: Sequence[float]):
    import vtk

    array = vtk.vtkDoubleArray()
    array.SetName(name)
    for v in values:
        array.InsertNextValue(float(v))
    return array


def _add_curve(scene, name: str, profile: Dict[str, np.ndarray], point_step_mm: float, attributes: Dict[str, str]):
    slicer = _slicer_module()
    s = profile["arc_mm"]
    take = [0]
    for i in range(1, len(s)):
        if s[i] - s[take[-1]] >= point_step_mm:
            take.append(i)
    if take[-1] != len(s) - 1:
        take.append(len(s) - 1)
    lps = np.stack([profile["x_mm"], profile["y_mm"], profile["z_mm"]], axis=1)[take]
    ras = lps_to_ras(lps)
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsCurveNode", name)
    node.SetCurveTypeToLinear()
    for p in ras:
        node.AddControlPoint(float(p[0]), float(p[1]), float(p[2]))
    # A section not measured, or a junction's or an end's (excluded from the lesion search: another vessel's lumen or
    # a cut end), shows no diameter rather than a number that reads as the vessel's.
    diameter = np.where(profile["excluded"][take], np.nan, profile["diameter_3d_mm"][take])
    for measure, values in (("Diameter", diameter), ("Radius", diameter / 2)):
        m = slicer.vtkMRMLStaticMeasurement()
        m.SetName(measure)
        m.SetUnits("mm")
        m.SetPrintFormat("%-#4.4g%s")
        m.SetControlPointValues(_double_array(measure, values))
        node.AddMeasurement(m)
    node.SetLocked(True)
    for key, value in attributes.items():
        node.SetAttribute(key, value)
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    return node


def _add_table(scene, name: str, columns: Dict[str, Sequence[Any]]):
    import vtk

    node = scene.AddNewNodeByClass("vtkMRMLTableNode", name)
    table = node.GetTable()
    for title, values in columns.items():
        if values and isinstance(values[0], str):
            array = vtk.vtkStringArray()
            array.SetName(title)
            for v in values:
                array.InsertNextValue(v)
        else:
            array = _double_array(title, [np.nan if v is None else v for v in values])
        table.AddColumn(array)
    node.Modified()
    return node


def _finite_or_least(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else -math.inf


def analysis_folder(path: PathLike) -> Path:
    """The folder ``analyse`` wrote, from itself, its analysis.json, or the result folder holding it (``analysis/``)."""
    folder = Path(path).absolute()
    if folder.name == "analysis.json" and folder.is_file():
        folder = folder.parent
    if not (folder / "analysis.json").is_file() and (folder / "analysis" / "analysis.json").is_file():
        folder = folder / "analysis"  # the result folder given: analyse writes into its analysis/ by default
    if not (folder / "analysis.json").is_file():
        raise FileNotFoundError(f"{folder / 'analysis.json'} not found: run `python -m SDFCARLib analyse RESULT_DIR` first")
    return folder


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8-sig"))  # -sig: a file saved by an editor that writes a BOM
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path} is not a readable analysis ({exc}); re-run analyse") from None


def _number(value: Any) -> bool:
    return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))


def _checked_summary(data: Any, path: Path) -> Dict[str, Any]:
    """analysis.json as this module reads it; one of another shape (hand-edited, or not analyse's) is refused
    naming the key, before any node is made. Keys analyse added later (grades, view maps) may be absent."""
    def bad(where: str, what: str) -> ValueError:
        return ValueError(f"{path}: {where} {what}; it is not an analysis analyse wrote (or was edited): re-run analyse")

    if not isinstance(data, dict):
        raise bad("the file", f"holds a {type(data).__name__}, not an object")
    branches = data.get("branches")
    if not isinstance(branches, list):
        raise bad("'branches'", "is missing or not a list")
    for n, b in enumerate(branches):
        where = f"branches[{n}]"
        if not isinstance(b, dict):
            raise bad(where, "is not an object")
        if isinstance(b.get("branch_id"), bool) or not isinstance(b.get("branch_id"), int):
            raise bad(f"{where}.branch_id", f"is {b.get('branch_id')!r}, not a whole number")
        if "parent_id" not in b or not (b["parent_id"] is None or (isinstance(b["parent_id"], int)
                                                                   and not isinstance(b["parent_id"], bool))):
            raise bad(f"{where}.parent_id", "is missing or not a whole number (null for a root)")
        if "length_mm" not in b or not _number(b["length_mm"]):
            raise bad(f"{where}.length_mm", "is missing or not a number")
        if not isinstance(b.get("lesions"), list):
            raise bad(f"{where}.lesions", "is missing or not a list")
        for m, lesion in enumerate(b["lesions"]):
            grade = lesion.get("grade") if isinstance(lesion, dict) else None
            measures = [("", lesion)] + ([(".grade", grade)] if grade is not None else [])
            for suffix, entry in measures:
                lw = f"{where}.lesions[{m}]{suffix}"
                if not isinstance(entry, dict):
                    raise bad(lw, "is not an object")
                for key in ("diameter_stenosis_pct", "mld_mm", "length_mm"):
                    if key not in entry or not _number(entry[key]):
                        raise bad(f"{lw}.{key}", "is missing or not a number")
            if grade is not None and not isinstance(grade.get("source"), str):
                raise bad(f"{where}.lesions[{m}].grade.source", "is missing or not a text")
    view_map = data.get("view_map")
    if view_map:
        try:
            a, c = (np.asarray(view_map[k], float) for k in ("primary_deg", "secondary_deg"))
            shape = (c.size, a.size)
            ok = a.ndim == c.ndim == 1 and a.size > 0 and c.size > 0 and all(
                np.asarray(view_map[k], float).shape == shape for k in ("foreshortening", "overlap"))
        except (KeyError, TypeError, ValueError):
            ok = False
        if not ok:
            raise bad("'view_map'", "does not hold primary_deg, secondary_deg and foreshortening and overlap of "
                      "(secondary × primary) values")
    settings = data.get("settings")
    through = settings.get("through_vessel_root") if isinstance(settings, dict) else None
    if through is not None:
        point = through.get("likeliest_ostium_mm") if isinstance(through, dict) else None
        if not (isinstance(point, list) and len(point) == 3
                and all(v is not None and _number(v) and math.isfinite(v) for v in point)):
            raise bad("settings.through_vessel_root.likeliest_ostium_mm", "is missing or not three numbers (LPS mm)")
    return data


def add_analysis_nodes(scene, analysis_dir: PathLike, name: str = "SDFCAR", point_step_mm: float = 2.0) -> Dict[str, Any]:
    """Add the QCA nodes of an ``analyse`` output folder to ``scene`` (module docstring); return them. The files are
    read and checked first; on error the scene is left as it was."""
    from ..mrml import scene_transaction

    slicer = _slicer_module()
    if (isinstance(point_step_mm, bool) or not isinstance(point_step_mm, (int, float, np.integer, np.floating))
            or not 0 < point_step_mm < 1e3):
        raise ValueError(f"point_step_mm must be a positive number of mm (the control points' spacing), got {point_step_mm!r}")
    folder = analysis_folder(analysis_dir)
    summary_path = folder / "analysis.json"
    data = _checked_summary(_read_json(summary_path), summary_path)
    profiles = {b["branch_id"]: _read_profile(folder / f"profile_branch{b['branch_id']:02d}.csv") for b in data["branches"]}
    with scene_transaction(scene):
        return _add_nodes(scene, slicer, data, profiles, name, point_step_mm)


def _add_nodes(scene, slicer, data, profiles, name: str, point_step_mm: float) -> Dict[str, Any]:
    curves, series = [], []
    chart = scene.AddNewNodeByClass("vtkMRMLPlotChartNode", f"{name} diameters")
    chart.SetTitle("Lumen diameter along each branch")
    chart.SetXAxisTitle("arc length from the proximal end (mm)")
    chart.SetYAxisTitle("diameter (mm)")
    for b in data["branches"]:
        bid = b["branch_id"]
        prof = profiles[bid]
        attrs = {"SDFCAR.branchId": str(bid), "SDFCAR.parentId": "" if b["parent_id"] is None else str(b["parent_id"]),
                 "SDFCAR.coordinateSystem": "RAS (from LPS files)"}
        curves.append(_add_curve(scene, f"{name} branch {bid}", prof, point_step_mm, attrs))
        columns = ["arc_mm", "diameter_3d_mm", "diameter_masks_mm"] + [k for k in OPTIONAL_COLUMNS if k in prof] + ["reference_mm"]
        profile_columns = {k: list(prof[k]) for k in columns}
        profile_columns["excluded"] = [float(v) for v in prof["excluded"]]  # 1: a junction or an end, not graded
        table = _add_table(scene, f"{name} branch {bid} profile", profile_columns)
        ps = scene.AddNewNodeByClass("vtkMRMLPlotSeriesNode", f"{name} branch {bid} diameter")
        ps.SetAndObserveTableNodeID(table.GetID())
        ps.SetXColumnName("arc_mm")
        ps.SetYColumnName("diameter_3d_mm")
        ps.SetPlotType(slicer.vtkMRMLPlotSeriesNode.PlotTypeScatter)
        ps.SetMarkerStyle(slicer.vtkMRMLPlotSeriesNode.MarkerStyleNone)
        chart.AddAndObservePlotSeriesNodeID(ps.GetID())
        series.append(ps)
    rows: Dict[str, List[Any]] = {k: [] for k in QCA_TABLE_COLUMNS}
    for b in data["branches"]:
        # The worst lesion by its grade (pipeline's "Grade of a lesion"); analysis.json from before grades
        # carries the 3D measures only, which were its grade.
        graded = [(x.get("grade") or dict(x, source="3D sections"), x) for x in b["lesions"]]  # pipeline.GRADED_ON_3D
        grade, worst = max(graded, key=lambda gx: _finite_or_least(gx[0]["diameter_stenosis_pct"])) if graded else (None, None)
        rows["branch"].append(str(b["branch_id"]))
        rows["parent"].append("" if b["parent_id"] is None else str(b["parent_id"]))
        rows["length_mm"].append(b["length_mm"])
        rows["mean_diameter_mm"].append((b.get("diameter_3d") or {}).get("mean_mm"))
        rows["mld_mm"].append(grade["mld_mm"] if grade else (b.get("minimal_lumen") or {}).get("mld_mm"))
        for key, field in (("diameter_stenosis_pct", "diameter_stenosis_pct"), ("area_stenosis_pct", "area_stenosis_pct"),
                           ("lesion_length_mm", "length_mm")):
            rows[key].append(grade[field] if grade else None)
        rows["graded_on"].append(grade["source"] if grade else "")
        rows["found_on"].append(worst.get("found_on", "3D sections") if worst else "")  # pipeline.GRADED_ON_3D
        rows["seen_on_frames"].append("" if worst is None or worst.get("seen_on_frames") is None
                                      else ("yes" if worst["seen_on_frames"] else "no"))
        rows["seen_on_masks"].append("" if worst is None or worst.get("seen_on_masks") is None
                                     else ("yes" if worst["seen_on_masks"] else "no"))
        rows["diameter_stenosis_3d_pct"].append(worst["diameter_stenosis_pct"] if worst else None)
        rows["mld_3d_mm"].append(worst["mld_mm"] if worst else None)
        rows["diameter_stenosis_masks_pct"].append(worst.get("masks_diameter_stenosis_pct") if worst else None)
        rows["epipolar_angle_median_deg"].append((b.get("epipolar_angle_deg") or {}).get("median_deg"))
    table = _add_table(scene, f"{name} QCA", rows)
    view_map = _add_view_map(scene, f"{name} view map", data) if data.get("view_map") else None
    through = (data.get("settings") or {}).get("through_vessel_root")
    ostium = _add_point(scene, f"{name} likeliest ostium", through["likeliest_ostium_mm"]) if through else None
    return {"curves": curves, "table": table, "chart": chart, "series": series, "view_map": view_map,
            "best_view": data.get("best_view"), "likeliest_ostium": ostium}


def _add_point(scene, name: str, lps_mm: Sequence[float]):
    """A point list of one unlocked point at ``lps_mm`` (shown in RAS), labelled with the list's name."""
    ras = lps_to_ras(np.asarray(lps_mm, float)[None, :])[0]
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", name)
    node.AddControlPoint(float(ras[0]), float(ras[1]), float(ras[2]))
    node.SetNthControlPointLabel(0, name)
    node.SetAttribute("SDFCAR.coordinateSystem", "RAS (from LPS files)")
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    return node


def _add_view_map(scene, name: str, data: Dict[str, Any]):
    import vtk

    vm = data["view_map"]
    score = 100 * (np.asarray(vm["foreshortening"], float) + np.asarray(vm["overlap"], float))  # (B, A)
    a, b = np.asarray(vm["primary_deg"], float), np.asarray(vm["secondary_deg"], float)
    image = vtk.vtkImageData()
    image.SetDimensions(len(a), len(b), 1)
    image.AllocateScalars(vtk.VTK_FLOAT, 1)
    from vtk.util.numpy_support import vtk_to_numpy

    vtk_to_numpy(image.GetPointData().GetScalars())[:] = score.astype(np.float32).ravel()  # x (primary) fastest
    node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", name)
    node.SetAndObserveImageData(image)
    step_a = float(a[1] - a[0]) if len(a) > 1 else 1.0
    step_b = float(b[1] - b[0]) if len(b) > 1 else 1.0
    node.SetSpacing(step_a, step_b, 1.0)
    node.SetOrigin(float(a[0]), float(b[0]), 0.0)  # "mm" here are degrees: x = primary, y = secondary
    best = data.get("best_view") or {}
    for key in ("primary_deg", "secondary_deg", "label"):
        if key in best:
            node.SetAttribute(f"SDFCAR.bestView.{key}", str(best[key]))
    node.SetAttribute("SDFCAR.units", "x: primary angle (deg, LAO +), y: secondary angle (deg, CRA +), value: score (%)")
    return node


def camera_for_angles(primary_deg: float, secondary_deg: float, distance_mm: float = 800.0,
                      focal_point_lps: Sequence[float] = (0.0, 0.0, 0.0)) -> Dict[str, Tuple[float, float, float]]:
    """Camera (RAS) that shows the scene as the angiogram at (α, β) does (``geometry.py`` convention).

    The image is displayed as seen from the detector side (patient's left on the right at AP), so
    the camera sits along +d from the focal point, looks back along −d, and its up is −v (image
    rows run downwards along v).
    """
    a, b = math.radians(primary_deg), math.radians(secondary_deg)
    d = np.array([math.sin(a) * math.cos(b), -math.cos(a) * math.cos(b), math.sin(b)])
    u = np.array([math.cos(a), math.sin(a), 0.0])
    up = -np.cross(u, d)
    focal = np.asarray(focal_point_lps, float)
    position = lps_to_ras(focal + distance_mm * d)
    return {"position": tuple(float(x) for x in position), "focal_point": tuple(float(x) for x in lps_to_ras(focal)),
            "view_up": tuple(float(x) for x in lps_to_ras(up))}


def set_camera_to_angles(camera_node, primary_deg: float, secondary_deg: float, distance_mm: Optional[float] = None) -> None:
    """Point a ``vtkMRMLCameraNode`` (a 3D view's camera) along the C-arm view (α, β)."""
    if camera_node is None or not hasattr(camera_node, "GetFocalPoint"):
        raise ValueError("no camera node: give a 3D view's vtkMRMLCameraNode (threeDView().cameraNode())")
    for what, value in (("primary_deg", primary_deg), ("secondary_deg", secondary_deg)) + (
            (("distance_mm", distance_mm),) if distance_mm is not None else ()):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not math.isfinite(value):
            raise ValueError(f"{what} must be a finite number, got {value!r}")
    if distance_mm is not None and not distance_mm > 0:
        raise ValueError(f"distance_mm must be positive (the camera's distance from its focal point), got {distance_mm!r}")
    if distance_mm is None:
        fp, pos = np.array(camera_node.GetFocalPoint()), np.array(camera_node.GetPosition())
        distance_mm = float(np.linalg.norm(pos - fp))
        if not distance_mm > 1e-3:  # a collapsed camera (VTK nudges its focal point by 1e-20)
            distance_mm = 800.0
    from ..mrml import ras_to_lps

    cam = camera_for_angles(primary_deg, secondary_deg, distance_mm, ras_to_lps(np.array(camera_node.GetFocalPoint())))
    camera_node.SetFocalPoint(*cam["focal_point"])
    camera_node.SetPosition(*cam["position"])
    camera_node.SetViewUp(*cam["view_up"])


def read_best_view(analysis_dir: PathLike) -> Optional[Dict[str, Any]]:
    """The suggested view (``best_view``: primary_deg, secondary_deg, label, …) of an analysis folder, or None."""
    path = Path(analysis_dir) / "analysis.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: the analysis folder was moved or deleted; run the analysis again")
    data = _read_json(path)
    best = data.get("best_view") if isinstance(data, dict) else None
    if not (isinstance(best, dict) and "primary_deg" in best and "secondary_deg" in best):
        return None
    if not all(_number(best[k]) and best[k] is not None and math.isfinite(best[k]) for k in ("primary_deg", "secondary_deg")):
        raise ValueError(f"{path}: the suggested view ({best.get('primary_deg')!r}, {best.get('secondary_deg')!r}) is not "
                         "a pair of angles; re-run analyse")
    return best


def add_analysis_to_scene(scene, analysis_dir: PathLike, name: str = "SDFCAR", result_node=None,
                          point_step_mm: float = 2.0) -> Dict[str, Any]:
    """``add_analysis_nodes`` for the Slicer module: all or nothing, grouped, linked to the result.

    The nodes go into one subject-hierarchy folder "<name> QCA" (item ID under "folder"), so that
    a tree of many branches does not flood the Data module; ``result_node`` (the result's
    segmentation) gets the attribute ``SDFCAR.analysisFolder``, which the module reads to show
    the suggested view after a scene reload. On error the scene is left as it was. Nodes already in
    the scene (an earlier analysis included) are never changed.
    """
    from ..mrml import prepare_scene, scene_transaction

    slicer = _slicer_module()
    if result_node is not None and (not hasattr(result_node, "IsA") or not result_node.IsA("vtkMRMLSegmentationNode")
                                    or not scene.IsNodePresent(result_node)):
        got = result_node.GetName() if hasattr(result_node, "GetName") else repr(result_node)
        raise ValueError(f"the result node {got} is not a segmentation in this scene; give the result's segmentation "
                         "node (or None)")
    folder = analysis_folder(analysis_dir)  # the folder read, which suggested_view_of reads again
    prepare_scene(scene)
    with scene_transaction(scene):
        nodes = add_analysis_nodes(scene, folder, name=name, point_step_mm=point_step_mm)
        for key in ("curves", "series"):
            for node in nodes[key]:
                node.SetAttribute("SDFCAR.analysisFolder", str(folder))
        for node in (nodes["table"], nodes["chart"], nodes["view_map"], nodes["likeliest_ostium"]):
            if node is not None:
                node.SetAttribute("SDFCAR.analysisFolder", str(folder))
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)
    item = None
    if hierarchy is not None:
        item = hierarchy.CreateFolderItem(hierarchy.GetSceneItemID(), f"{name} QCA")
        members = [*nodes["curves"], nodes["table"], nodes["chart"], *nodes["series"], nodes["view_map"],
                   nodes["likeliest_ostium"]]
        members += [scene.GetNodeByID(s.GetTableNodeID()) for s in nodes["series"]]
        invalid = hierarchy.GetInvalidItemID()
        for node in members:
            if node is None:
                continue
            node_item = hierarchy.GetItemByDataNode(node)
            if node_item == invalid:
                # Slicer's subject-hierarchy plugins give every new node an item; a bare scene does not.
                hierarchy.CreateItem(item, node)
            else:
                hierarchy.SetItemParent(node_item, item)
    if result_node is not None:
        result_node.SetAttribute("SDFCAR.analysisFolder", str(folder))
    nodes["folder"] = item
    return nodes


def suggested_view_of(result_node) -> Dict[str, Any]:
    """The suggested C-arm view of the latest analysis of a result node (``SDFCAR.analysisFolder``).

    Raises ValueError naming what is missing: no analysis yet, its folder gone, or no view map.
    """
    folder = result_node.GetAttribute("SDFCAR.analysisFolder") if result_node is not None else None
    if not folder:
        raise ValueError("this result has not been analysed yet: press Analyse first")
    best = read_best_view(folder)
    if best is None:
        raise ValueError(f"the analysis in {folder} has no suggested view (the result has no C-arm geometry in its "
                         "report.json, so no view map was made)")
    return best
