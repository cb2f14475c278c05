"""3D-QCA results as Slicer scene content: curves with diameters, a table, plots, the view map.

``add_analysis_nodes(scene, analysis_dir)`` reads what ``analyse`` wrote (analysis.json and the
per-branch CSV profiles) and adds

    one markups curve per branch      control points every ``point_step_mm`` along the centreline
                                      (linear curve, RAS), with the static measurements
                                      "Diameter" (3D equivalent diameter, mm) and "Radius" per
                                      control point; attributes SDFCAR.branchId / parentId
    a table node "… QCA"              one row per branch: length, mean/min diameter, worst lesion
                                      (graded on the frames where given, and its 3D-section measures)
    a table node per branch profile   arc length and diameters (3D, masks, and the frames' edges and
                                      density where analyse was given the frames), feeding
    a plot chart "… diameters"        one line per branch, diameter against arc length
    a scalar volume "… view map"      the foreshortening + overlap score (%) over (primary,
                                      secondary) in degrees as a one-slice image; attributes
                                      hold the suggested angles

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
                     "diameter_stenosis_3d_pct", "mld_3d_mm", "diameter_stenosis_masks_pct")
#: profile columns measured on the frames (edges, density), in the branch profile tables when present
FRAME_COLUMNS = ("diameter_frames_mm", "diameter_frames_density_mm")


def _read_profile(path: Path) -> Dict[str, np.ndarray]:
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} holds no profile rows; re-run analyse")

    def col(name):
        return np.array([float(r[name]) if r.get(name) not in (None, "") else np.nan for r in rows])

    # The frame columns exist only where analyse was given the frames.
    keys = ["arc_mm", "diameter_3d_mm", "diameter_masks_mm", "reference_mm", "x_mm", "y_mm", "z_mm"]
    keys += [k for k in FRAME_COLUMNS if k in rows[0]]
    return {k: col(k) for k in keys}


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
    diameter = np.nan_to_num(profile["diameter_3d_mm"][take], nan=0.0)
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


def add_analysis_nodes(scene, analysis_dir: PathLike, name: str = "SDFCAR", point_step_mm: float = 2.0) -> Dict[str, Any]:
    """Add the QCA nodes of an ``analyse`` output folder to ``scene`` (module docstring); return them."""
    slicer = _slicer_module()
    folder = Path(analysis_dir)
    if not (folder / "analysis.json").is_file() and (folder / "analysis" / "analysis.json").is_file():
        folder = folder / "analysis"  # the result folder given: analyse writes into its analysis/ by default
    summary_path = folder / "analysis.json"
    if not summary_path.is_file():
        raise FileNotFoundError(f"{summary_path} not found: run `python -m SDFCARLib analyse RESULT_DIR` first")
    data = json.loads(summary_path.read_text(encoding="utf-8"))
    profiles = {b["branch_id"]: _read_profile(folder / f"profile_branch{b['branch_id']:02d}.csv") for b in data["branches"]}
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
        columns = ["arc_mm", "diameter_3d_mm", "diameter_masks_mm"] + [k for k in FRAME_COLUMNS if k in prof] + ["reference_mm"]
        table = _add_table(scene, f"{name} branch {bid} profile", {k: list(prof[k]) for k in columns})
        ps = scene.AddNewNodeByClass("vtkMRMLPlotSeriesNode", f"{name} branch {bid}")
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
        grade, worst = max(graded, key=lambda gx: gx[0]["diameter_stenosis_pct"]) if graded else (None, None)
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
    table = _add_table(scene, f"{name} QCA", rows)
    view_map = _add_view_map(scene, f"{name} view map", data) if data.get("view_map") else None
    return {"curves": curves, "table": table, "chart": chart, "series": series, "view_map": view_map,
            "best_view": data.get("best_view")}


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
    if distance_mm is None:
        fp, pos = np.array(camera_node.GetFocalPoint()), np.array(camera_node.GetPosition())
        distance_mm = float(np.linalg.norm(pos - fp)) or 800.0
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
    best = json.loads(path.read_text(encoding="utf-8")).get("best_view")
    return best if isinstance(best, dict) and "primary_deg" in best and "secondary_deg" in best else None


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
    folder = Path(analysis_dir).absolute()
    prepare_scene(scene)
    with scene_transaction(scene):
        nodes = add_analysis_nodes(scene, folder, name=name, point_step_mm=point_step_mm)
        for key in ("curves", "series"):
            for node in nodes[key]:
                node.SetAttribute("SDFCAR.analysisFolder", str(folder))
        for node in (nodes["table"], nodes["chart"], nodes["view_map"]):
            if node is not None:
                node.SetAttribute("SDFCAR.analysisFolder", str(folder))
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)
    item = None
    if hierarchy is not None:
        item = hierarchy.CreateFolderItem(hierarchy.GetSceneItemID(), f"{name} QCA")
        members = [*nodes["curves"], nodes["table"], nodes["chart"], *nodes["series"], nodes["view_map"]]
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
