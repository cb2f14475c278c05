"""Where two views place a vessel in depth: its angle to their epipolar planes (analysis/views.py), closed-form."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from SDFCARLib.analysis.phantoms import grid_around, render_mask, stenosed_tube, voxelize_exact
from SDFCARLib.analysis.pipeline import analyse_volume, summary
from SDFCARLib.analysis.views import (EPIPOLAR_WEAK_DEG, chord_tangents, depth_view, epipolar_angles_deg,
                                      foreshortening_map)
from SDFCARLib.geometry import CArmView, standard_geometry

SOD_MM = 757.0


def _view(primary, secondary):
    return CArmView(primary, secondary, 1000.0, SOD_MM, (0.278, 0.278), (512, 512))


LAO30, RAO30, AP_CRA30 = _view(30.0, 0.0), _view(-30.0, 0.0), _view(0.0, 30.0)


def _sources(*views):
    return [v.source_position for v in views]


@pytest.mark.parametrize("elevation_deg", [0.0, 10.0, 30.0, 60.0, 90.0])
def test_at_the_isocentre_lao30_rao30_s_epipolar_plane_is_horizontal(elevation_deg):
    # Both sources lie at z = 0 and the isocentre too: the plane is z = 0, the angle a tangent's elevation.
    e = math.radians(elevation_deg)
    tangent = np.array([[math.cos(e) * 0.6, math.cos(e) * 0.8, math.sin(e)]])
    angle = epipolar_angles_deg(np.zeros((1, 3)), tangent, _sources(LAO30, RAO30))
    assert angle[0] == pytest.approx(elevation_deg, abs=1e-9)


def test_off_the_isocentre_the_plane_tilts_towards_the_sources():
    # The plane through both sources (y = SOD cos 30°, z = 0) and (0, 0, h) holds x and the direction
    # (0, SOD cos 30°, −h): a tangent at elevation φ in the y–z plane lies φ + atan(h / (SOD cos 30°)) off it.
    h, phi = 30.0, math.radians(10.0)
    tangent = np.array([[0.0, math.cos(phi), math.sin(phi)]])
    angle = epipolar_angles_deg(np.array([[0.0, 0.0, h]]), tangent, _sources(LAO30, RAO30))
    tilt = math.degrees(math.atan(h / (SOD_MM * math.cos(math.radians(30.0)))))
    assert angle[0] == pytest.approx(10.0 + tilt, abs=1e-9)
    along_baseline = np.array([[1.0, 0.0, 0.0]])  # the sources' line lies in every epipolar plane
    assert epipolar_angles_deg(np.array([[5.0, -20.0, h]]), along_baseline, _sources(LAO30, RAO30))[0] == pytest.approx(0.0, abs=1e-9)


def test_three_views_take_the_pair_that_crosses_the_vessel_best_and_one_view_has_no_angle():
    rng = np.random.default_rng(0)
    points = rng.normal(scale=20.0, size=(50, 3))
    tangents = rng.normal(size=(50, 3))
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    pairs = [epipolar_angles_deg(points, tangents, _sources(a, b))
             for a, b in ((LAO30, RAO30), (LAO30, AP_CRA30), (RAO30, AP_CRA30))]
    np.testing.assert_allclose(epipolar_angles_deg(points, tangents, _sources(LAO30, RAO30, AP_CRA30)),
                               np.max(pairs, axis=0), atol=1e-12)
    # a vessel along x at the isocentre lies in LAO 30 / RAO 30's plane, and AP CRA 30 crosses it
    assert epipolar_angles_deg(np.zeros((1, 3)), [[1.0, 0, 0]], _sources(LAO30, RAO30))[0] == pytest.approx(0.0, abs=1e-9)
    assert epipolar_angles_deg(np.zeros((1, 3)), [[1.0, 0, 0]], _sources(LAO30, RAO30, AP_CRA30))[0] > 30.0
    assert np.isnan(epipolar_angles_deg(points, tangents, _sources(LAO30))).all()


def test_chord_tangents_follow_a_circle_and_clip_at_its_ends():
    s = np.linspace(0.0, math.pi, 400)
    circle = 10.0 * np.stack([np.cos(s), np.sin(s), np.zeros_like(s)], axis=1)
    t = chord_tangents(circle, half_window_mm=1.0)
    exact = np.stack([-np.sin(s), np.cos(s), np.zeros_like(s)], axis=1)
    inner = slice(20, -20)  # 1 mm of arc is 13 samples here: the chords are centred away from the ends
    assert np.all(np.abs(np.sum(t[inner] * exact[inner], axis=1)) > math.cos(math.radians(0.5)))
    assert np.abs(np.sum(t[0] * exact[0])) > math.cos(math.radians(3.0))  # a one-sided chord of 1 mm at the end
    assert np.isnan(chord_tangents(circle[:1])).all()


def test_the_third_view_for_depth_is_the_best_of_the_range_and_says_what_it_gives():
    segment = np.linspace([-6.0, 0.0, 0.0], [6.0, 0.0, 0.0], 49)  # along the LAO 30 / RAO 30 baseline
    third = depth_view(segment, [LAO30, RAO30], step_deg=5.0)
    tangents = chord_tangents(segment)
    candidate = _view(third["primary_deg"], third["secondary_deg"])
    again = np.median(epipolar_angles_deg(segment, tangents, _sources(LAO30, RAO30, candidate)))
    assert third["epipolar_angle_median_deg"] == pytest.approx(again, abs=1e-6) and again > 45.0
    assert third["foreshortening"] == pytest.approx(
        float(foreshortening_map(segment, third["primary_deg"], third["secondary_deg"])), abs=1e-12)
    for primary in range(-60, 61, 10):  # no view of the range crosses it better
        for secondary in range(-40, 41, 10):
            other = np.median(epipolar_angles_deg(segment, tangents, _sources(LAO30, RAO30, _view(primary, secondary))))
            assert other <= third["epipolar_angle_median_deg"] + 1.0 + 1e-9
    assert depth_view(segment, []) is None


def _analysed_tube(direction):
    phantom = stenosed_tube(length_mm=24.0, diameter_mm=3.0, stenosis_pct=50.0, lesion_length_mm=8.0, direction=direction)
    grid = grid_around(phantom.tree, 0.3)
    views = standard_geometry("lao30-rao30").views
    masks = [render_mask(phantom.tree, v) for v in views]
    result = analyse_volume(voxelize_exact(phantom.tree, grid).astype(np.float32), grid, views=views, masks=masks,
                            view_step_deg=10.0, ostium_mm=phantom.truth["ostium_mm"])
    return result, summary(result)


@pytest.mark.parametrize("direction, elevation_deg", [((1.0, 0.15, 0.08), 4.5), ((0.5, 0.3, 1.0), 59.75)])
def test_the_analysis_reports_each_branch_s_angle_and_warns_where_the_target_runs_along_the_planes(direction, elevation_deg):
    # The tube is centred on the isocentre, whose epipolar plane is horizontal: its angle is its elevation.
    result, data = _analysed_tube(direction)
    assert math.degrees(math.asin(direction[2] / np.linalg.norm(direction))) == pytest.approx(elevation_deg, abs=0.05)
    branch = data["branches"][0]["epipolar_angle_deg"]
    assert branch["median_deg"] == pytest.approx(elevation_deg, abs=1.5)
    target = data["target_segment"]
    assert target["kind"] == "worst lesion"
    assert target["epipolar_angle_deg"]["median_deg"] == pytest.approx(elevation_deg, abs=1.5)
    warned = [w for w in data["warnings"] if "epipolar planes" in w]
    json.dumps(data)  # analysis.json is written from it
    if elevation_deg < EPIPOLAR_WEAK_DEG:
        assert target["epipolar_angle_deg"]["share_under_weak"] == 1.0
        (warning,) = warned
        third = target["depth_view"]
        assert f"A third view at {third['label']} would cross it at" in warning
        assert third["epipolar_angle_median_deg"] > 45.0
    else:
        assert not warned and "depth_view" not in target
        assert target["epipolar_angle_deg"]["share_under_weak"] == 0.0
    # one value per centreline point, in the profile and the centrelines' arrays
    assert result.epipolar_deg[0].shape == (len(result.tree.branches[0].points_mm),)


def test_analyse_writes_the_angle_into_the_profiles_the_centrelines_and_its_summary(tmp_path, capsys):
    from test_analysis import _result_folder

    from SDFCARLib.cli import main

    folder, phantom = _result_folder(tmp_path, direction=(1.0, 0.15, 0.08))
    assert main(["analyse", str(folder), "--view-step-deg", "10", "--ostium", *map(str, phantom.truth["ostium_mm"])]) == 0
    captured = capsys.readouterr()
    assert "crosses the views' epipolar planes at 5° (median) (weak: see the warning)" in captured.out
    assert "warning: the target segment (branch 0," in captured.err and "A third view at" in captured.err
    rows = (folder / "analysis" / "profile_branch00.csv").read_text().splitlines()
    header = rows[0].split(",")
    angles = np.array([float(r.split(",")[header.index("epipolar_angle_deg")]) for r in rows[1:]])
    assert np.median(angles) == pytest.approx(4.5, abs=1.5)
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtk.vtkPolyDataReader()
    reader.SetFileName(str(folder / "analysis" / "centrelines.vtk"))
    reader.Update()
    np.testing.assert_allclose(vtk_to_numpy(reader.GetOutput().GetPointData().GetArray("EpipolarAngle")), angles, atol=1e-4)
