"""3D-QCA measures (SDFCARLib.analysis) against analytic phantoms with known answers."""

from __future__ import annotations

import importlib.util
import json
import math

import numpy as np
import pytest

from SDFCARLib.analysis.centreline import bifurcation_angles, extend_to_surface, extract_centrelines, trim_free_end
from SDFCARLib.analysis.diameter import branch_cross_sections, junction_zones, mask_diameters
from SDFCARLib.analysis.lesion import ReferenceFit, find_lesions, reference_fit
from SDFCARLib.analysis.phantoms import (grid_around, helix, render_mask, stenosed_tube, straight_tube,
                                         voxelize_exact)
from SDFCARLib.analysis.views import foreshortening, foreshortening_map, overlap_fraction, view_direction, view_map
from SDFCARLib.geometry import CArmView, standard_geometry
from SDFCARLib.phantoms import Branch, CentrelineTree


def _measure(phantom, spacing_mm, ostium=None):
    grid = grid_around(phantom.tree, spacing_mm)
    label = voxelize_exact(phantom.tree, grid)
    tree = extract_centrelines(label, grid, ostium_mm=ostium)
    branch = tree.branches[0]
    return tree, branch, branch_cross_sections(label, grid, branch), junction_zones(tree, branch)


@pytest.mark.parametrize("diameter_mm, spacing_mm", [(3.0, 0.3), (1.5, 0.25)])
def test_straight_tube_diameter(diameter_mm, spacing_mm):
    tree, branch, sections, ends = _measure(straight_tube(16.0, diameter_mm), spacing_mm)
    assert len(tree.branches) == 1
    error = np.abs(sections.equivalent_diameter_mm[~ends] - diameter_mm)
    assert error.mean() <= 0.15, error.mean()
    assert branch.length_mm == pytest.approx(16.0, rel=0.02)  # flat ends: the lumen is the centreline's length


def test_helix_length_within_2_percent():
    phantom = helix(radius_mm=6.0, pitch_mm=10.0, turns=1.25, diameter_mm=2.0)
    tree, branch, sections, ends = _measure(phantom, 0.3)
    assert len(tree.branches) == 1
    assert branch.length_mm == pytest.approx(phantom.truth["length_mm"], rel=0.02)
    assert np.abs(sections.equivalent_diameter_mm[~ends] - 2.0).mean() <= 0.15



def test_a_tight_helix_keeps_its_bends_once_centred_on_its_sections():
    # A bend of 3.8 mm radius (helix R 4 mm, pitch 12 mm): the 1 mm smoothing of the voxel path pulls the
    # centreline ~0.12 mm towards the helix's axis and shortens it by ~1.3 % (the ostium end, followed along
    # the bend, gives back part of the 2.4 %); the sections' centroids put it back on the tube's axis (RESULTS §72)
    from scipy.spatial import cKDTree

    from SDFCARLib.analysis.pipeline import analyse_volume

    phantom = helix(radius_mm=4.0, pitch_mm=12.0, turns=1.25, diameter_mm=2.0)
    truth = phantom.tree.branches[0].points
    grid = grid_around(phantom.tree, 0.3)
    label = voxelize_exact(phantom.tree, grid).astype(np.float32)
    measured = {}
    for centred in (False, True):
        result = analyse_volume(label, grid, ostium_mm=truth[0], best_view=False, centre_on_sections=centred)
        assert len(result.tree.branches) == 1
        branch = result.tree.branches[0]
        inner = slice(len(branch.points_mm) // 10, -(len(branch.points_mm) // 10))
        measured[centred] = (cKDTree(truth).query(branch.points_mm[inner])[0].mean(),
                             branch.length_mm / phantom.truth["length_mm"] - 1)
    assert measured[False][0] > 0.09 and measured[True][0] < 0.05, measured
    assert measured[False][1] < -0.01 and abs(measured[True][1]) < 0.01, measured
    placement = result.settings["centred_on_sections"]
    assert placement[0]["measured_share"] > 0.7 and 0.05 < placement[0]["mean_shift_mm"] < 0.2



def test_a_side_branch_stays_on_its_parent_s_junction_once_centred_on_its_sections():
    from SDFCARLib.analysis.pipeline import analyse_volume
    from SDFCARLib.analysis.section_centreline import centre_on_sections

    root = np.stack([np.linspace(-12.0, 12.0, 241), np.zeros(241), np.zeros(241)], axis=1)
    side = root[100] + np.linspace(0.0, 12.0, 121)[:, None] * np.array([0.5, np.sqrt(3) / 2, 0.0])
    phantom_tree = CentrelineTree([Branch(root, np.full(241, 1.5), "root"), Branch(side, np.full(121, 0.8), "side")])
    grid = grid_around(phantom_tree, 0.3)
    label = voxelize_exact(phantom_tree, grid).astype(np.float32)
    result = analyse_volume(label, grid, ostium_mm=root[0], best_view=False)
    children = [b for b in result.tree.branches if b.parent_id is not None]
    assert len(result.tree.branches) == 2 and len(children) == 1
    child = children[0]
    parent = result.tree.branch(child.parent_id)
    np.testing.assert_array_equal(child.points_mm[0], parent.points_mm[child.parent_index])
    # straight tubes' sections are centred already: nothing moves by half a voxel (0.15 mm) or more
    assert all(p["mean_shift_mm"] < 0.15 for p in result.settings["centred_on_sections"])
    # no sections at all: every branch keeps its points
    unmoved, report = centre_on_sections(result.tree, {})
    for before, after in zip(result.tree.branches, unmoved.branches):
        np.testing.assert_array_equal(before.points_mm, after.points_mm)
    assert all(p.measured_share == 0.0 for p in report)


def test_a_free_end_that_fans_to_the_rim_is_cut_back_before_it_turns():
    # A skeleton along L whose last 1.2 mm turns 1.5 mm sideways towards the rim of a 2 mm vessel
    # (the inscribed radius falls there): 1.5 radii (3 mm) are cut, so the end keeps to the axis.
    axis = np.stack([np.arange(0.0, 20.01, 0.4), np.zeros(51), np.zeros(51)], axis=1)
    turn = np.array([[20.4, 0.5, 0.0], [20.8, 1.0, 0.0], [21.2, 1.5, 0.0]])
    points = np.vstack([axis, turn])
    radius = np.r_[np.full(51, 2.0), [1.2, 0.8, 0.4]]
    kept, vessel_radius = trim_free_end(points, radius)
    assert vessel_radius == 2.0
    assert np.all(kept[:, 1] == 0.0)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    assert arc[len(kept) - 1] <= arc[-1] - 1.5 * 2.0 < arc[len(kept)]
    # The proximal end is cut the same way; a path shorter than three radii keeps its first half.
    start, _ = trim_free_end(points[::-1], radius[::-1], at_start=True)
    np.testing.assert_array_equal(start, points[::-1][-len(kept):])
    short, _ = trim_free_end(axis[:6], np.full(6, 2.0))
    np.testing.assert_array_equal(short, axis[:3])



def test_an_end_that_follows_the_lumen_reaches_a_bent_vessel_s_end_where_a_straight_one_leaves_through_the_wall():
    # A quarter circle of 6 mm radius (a 3 mm vessel, flat ends), its axis known for the first 2 mm only:
    # the straight extension runs along its end tangent and out through the side wall 4.6 mm from the end;
    # following the sections' centroids stays on the axis to the end face (off by default: RESULTS §72d)
    from SDFCARLib.analysis.centreline import follow_to_surface

    phi = np.linspace(0.0, np.pi / 2, 400)
    axis = np.stack([6.0 * np.cos(phi), 6.0 * np.sin(phi), np.zeros_like(phi)], axis=1)
    tree = CentrelineTree([Branch(axis, np.full(len(phi), 1.5), "bend")])
    grid = grid_around(tree, 0.25)
    volume = voxelize_exact(tree, grid).astype(np.float32)
    start = axis[axis[:, 1] < 2.0]

    def off_axis(points):
        return np.abs(np.linalg.norm(points[:, :2], axis=1) - 6.0)

    straight = extend_to_surface(start, volume, grid, 0.5, reach_mm=12.0, step_mm=0.25)
    followed = follow_to_surface(start, volume, grid, 0.5, reach_mm=12.0, step_mm=0.25)
    assert np.linalg.norm(straight[-1] - axis[-1]) > 3.0 and off_axis(straight).max() > 1.2
    assert np.linalg.norm(followed[-1] - axis[-1]) < 0.3 and off_axis(followed).max() < 0.1
    np.testing.assert_array_equal(followed[:len(start)], start)
    # at the start of the polyline the same, reversed
    back = follow_to_surface(start[::-1], volume, grid, 0.5, reach_mm=12.0, step_mm=0.25, at_start=True)
    assert np.linalg.norm(back[0] - axis[-1]) < 0.3


def test_a_free_ends_extension_stops_at_a_hole_on_its_line_unless_it_reads_across_the_lumen():
    from SDFCARLib.geometry import VolumeGrid

    grid = VolumeGrid((40, 15, 15), (0.25, 0.25, 0.25))  # x from −4.875 to +4.875 mm
    x, y, z = (grid.index_to_world(np.argwhere(np.ones(grid.shape, bool))).T.reshape(3, *grid.shape))
    lumen = (y ** 2 + z ** 2 <= 1.0 ** 2) & (x <= 3.0)  # a 1 mm-radius tube ending at x = 3 mm ...
    lumen &= ~((np.abs(x - 1.0) < 0.3) & (y ** 2 + z ** 2 < 0.2 ** 2))  # ... with a hole on its axis at x = 1 mm
    volume = lumen.astype(np.float32)
    line = np.stack([np.linspace(-3.0, 0.0, 13), np.zeros(13), np.zeros(13)], axis=1)
    on_line = extend_to_surface(line, volume, grid, 0.5, reach_mm=5.0, step_mm=0.25)
    across = extend_to_surface(line, volume, grid, 0.5, reach_mm=5.0, step_mm=0.25, probe_radius_mm=0.5)
    assert on_line[-1, 0] < 1.0  # stopped at the hole
    assert across[-1, 0] == pytest.approx(3.0, abs=0.2)  # the tube's end
    np.testing.assert_allclose(across[:, 1:], 0.0, atol=1e-9)  # along the line only


def test_a_root_that_starts_with_a_bend_is_measured_from_its_ostium_face(monkeypatch):
    # A 3 mm vessel whose first quarter turns on a 6 mm radius, then runs straight for 20 mm, its ostium the flat
    # face at the bend's start: the trimmed skeleton's straight extension leaves through the bend's side wall
    # millimetres short of the face; the ostium end reaches as far as the lumen's followed sections do
    from SDFCARLib.analysis import centreline

    phi = np.linspace(np.pi / 2, 0.0, 200)
    bend = np.stack([6.0 * np.cos(phi) - 6.0, 6.0 * np.sin(phi), np.zeros_like(phi)], axis=1)  # ends at the origin, along −y
    run = np.stack([np.zeros(81), -np.linspace(0.0, 20.0, 81), np.zeros(81)], axis=1)[1:]
    axis = np.vstack([bend, run])
    tree = CentrelineTree([Branch(axis, np.full(len(axis), 1.5), "bent root")])
    grid = grid_around(tree, 0.25)
    volume = voxelize_exact(tree, grid).astype(np.float32)
    ostium = axis[0]

    def root_start(follows):
        monkeypatch.setattr(centreline, "OSTIUM_FOLLOWS_LUMEN", follows)
        result = extract_centrelines(volume, grid, ostium_mm=ostium)
        return result.branches[0].points_mm[0]

    assert np.linalg.norm(root_start(True) - ostium) < 0.4
    assert np.linalg.norm(root_start(False) - ostium) > 1.0  # what the straight extension alone gives


def test_the_ostium_end_takes_the_straight_extension_where_the_followed_one_meets_a_hole():
    # A straight 3 mm tube ending at x = 3 mm with a small hole on its axis at x = 1 mm; the skeleton's end runs
    # 0.6 mm beside the axis. Followed onto the sections' centroids it stops at the hole; straight it reaches the face
    from SDFCARLib.analysis.centreline import extend_ostium, follow_to_surface
    from SDFCARLib.geometry import VolumeGrid

    grid = VolumeGrid((48, 21, 21), (0.25, 0.25, 0.25))
    x, y, z = (grid.index_to_world(np.argwhere(np.ones(grid.shape, bool))).T.reshape(3, *grid.shape))
    lumen = (y ** 2 + z ** 2 <= 1.5 ** 2) & (x <= 3.0) & ((x - 1.0) ** 2 + y ** 2 + z ** 2 > 0.4 ** 2)
    volume = lumen.astype(np.float32)
    line = np.stack([np.linspace(0.0, -4.0, 17), np.full(17, 0.6), np.zeros(17)], axis=1)  # its start faces the end
    followed = follow_to_surface(line, volume, grid, 0.5, reach_mm=6.0, step_mm=0.25, at_start=True)
    chosen = extend_ostium(line, volume, grid, 0.5, reach_mm=6.0, step_mm=0.25)
    assert followed[0, 0] < 1.0  # stopped at the hole
    assert chosen[0, 0] == pytest.approx(3.0, abs=0.2)  # the tube's face
    np.testing.assert_allclose(chosen[:, 1], 0.6, atol=1e-9)  # along the straight line


@pytest.mark.parametrize("eccentric", [False, True])
def test_fifty_percent_stenosis(eccentric):
    phantom = stenosed_tube(length_mm=30.0, diameter_mm=3.0, stenosis_pct=50.0, lesion_length_mm=10.0,
                            eccentric=eccentric, curvature_radius_mm=40.0 if eccentric else None)
    truth = phantom.truth
    _, branch, sections, ends = _measure(phantom, 0.3, ostium=truth["ostium_mm"])
    s = branch.arc_length_mm
    reference = reference_fit(s, sections.equivalent_diameter_mm, ~ends)
    lesions = find_lesions(s, sections.equivalent_diameter_mm, reference, ~ends, sections.area_mm2)
    assert len(lesions) == 1
    lesion = lesions[0]
    assert lesion.reference_diameter_mm == pytest.approx(3.0, abs=0.15)
    assert lesion.diameter_stenosis_pct == pytest.approx(50.0, abs=8.0)
    assert lesion.area_stenosis_pct == pytest.approx(75.0, abs=8.0)
    assert lesion.mld_mm == pytest.approx(1.5, abs=0.2)
    assert lesion.length_mm == pytest.approx(10.0, abs=2.0)
    assert lesion.start_mm == pytest.approx(truth["lesion_start_mm"], abs=1.5)


def test_reference_fit_ignores_the_lesion_and_keeps_the_taper():
    s = np.arange(0.0, 60.0, 0.25)
    healthy = 3.5 - 0.02 * s
    d = healthy * (1 - 0.6 * ((s > 20) & (s < 35)))
    d = d + np.random.default_rng(0).normal(0, 0.04, len(s))
    fit = reference_fit(s, d)
    assert fit.slope_mm_per_mm == pytest.approx(-0.02, abs=0.003)
    assert fit.intercept_mm == pytest.approx(3.5, abs=0.05)
    assert not fit.kept[(s > 22) & (s < 33)].any()


def test_a_section_missing_inside_a_lesion_does_not_split_it():
    s = np.arange(0.0, 30.0, 0.25)
    d = np.where((s >= 10) & (s <= 20), 1.5, 3.0)  # 50 % over 10 mm, flat
    d[s == 14.0] = np.nan  # one cross-section failed
    lesions = find_lesions(s, d, ReferenceFit(3.0, 0.0, np.ones(len(s), bool)), smoothing_mm=0.0)
    assert len(lesions) == 1
    assert lesions[0].diameter_stenosis_pct == pytest.approx(50.0)
    # each edge is one 0.25 mm step; the flank line through its 75 % and 25 % points reaches 0 a step out
    assert (lesions[0].start_mm, lesions[0].end_mm) == pytest.approx((9.75, 20.25))
    assert lesions[0].mld_position_mm != 14.0


def test_no_lesion_on_a_healthy_profile():
    s = np.arange(0.0, 30.0, 0.25)
    d = 3.0 + np.random.default_rng(1).normal(0, 0.05, len(s))
    assert find_lesions(s, d, ReferenceFit(3.0, 0.0, np.ones(len(s), bool))) == []


def test_bifurcation_angle_and_ostium():
    # A thick main vessel with a thinner side branch leaving at 60° from its continuation.
    main = np.linspace([-15.0, 0, 0], [15.0, 0, 0], 301)
    side_dir = np.array([math.cos(math.radians(60)), math.sin(math.radians(60)), 0.0])
    side = np.array([0.0, 0, 0]) + np.linspace(0, 14.0, 141)[:, None] * side_dir
    tree_in = CentrelineTree([Branch(main, np.linspace(1.6, 1.3, 301), "main"), Branch(side, np.full(141, 0.9), "side")])
    grid = grid_around(tree_in, 0.3)
    tree = extract_centrelines(voxelize_exact(tree_in, grid), grid)
    assert len(tree.branches) == 2
    assert tree.branches[0].points_mm[0][0] < -13.0  # rooted at the thick end (x = −15)
    angles = bifurcation_angles(tree)
    assert len(angles) == 1
    assert angles[0]["distal_angle_deg"] == pytest.approx(60.0, abs=8.0)
    assert angles[0]["parent_arc_mm"] == pytest.approx(15.0, abs=1.5)


@pytest.mark.parametrize("primary, secondary", [(0.0, 0.0), (30.0, 20.0), (-45.0, -25.0), (60.0, 40.0)])
def test_foreshortening_of_a_straight_segment_is_analytic(primary, secondary):
    t = np.array([0.3, -0.8, 0.52])
    t /= np.linalg.norm(t)
    points = np.linspace(-10, 10, 41)[:, None] * t
    view = CArmView(primary, secondary, 1000.0, 750.0, (0.278, 0.278), (512, 512))
    analytic = 1 - math.sqrt(1 - float(t @ view.detector_direction) ** 2)
    assert foreshortening(points, view, perspective=False) == pytest.approx(analytic, abs=1e-9)
    assert foreshortening(points, view) == pytest.approx(analytic, abs=0.01)  # perspective, at the isocenter
    assert float(foreshortening_map(points, primary, secondary)) == pytest.approx(analytic, abs=1e-9)


def test_best_view_of_a_straight_segment_is_perpendicular_to_it():
    t = np.array([0.5, -0.6, 0.62])
    t /= np.linalg.norm(t)
    points = np.linspace(-8, 8, 33)[:, None] * t
    vm = view_map(points, 1.0, step_deg=5.0)
    best = vm.best()
    d = view_direction(best["primary_deg"], best["secondary_deg"])
    assert abs(float(d @ t)) < math.sin(math.radians(5.0))
    assert best["foreshortening"] < 0.01
    assert vm.foreshortening.max() > 0.3  # the map does see the segment end-on somewhere


def test_overlap_of_crossing_vessels():
    segment = np.linspace([-10.0, 0, 0], [10.0, 0, 0], 81)  # along L
    other = np.linspace([0.0, -20, -10], [0.0, -20, 10], 81)  # along S, 20 mm anterior: crosses it in AP
    assert 0.0 < overlap_fraction(segment, 1.0, other, 1.0, 0.0, 0.0) < 0.5
    # In LAO α the other projects at u = −20 sin α, the segment over |u| <= 10 cos α: apart beyond ~31°.
    assert overlap_fraction(segment, 1.0, other, 1.0, 60.0, 0.0) == 0.0
    alone = view_map(segment, 1.0, step_deg=5.0).best()
    assert alone["primary_deg"] == 0.0 and alone["foreshortening"] < 1e-9  # AP shows it whole...
    # ...but the other hides it there; tilting CRA/CAU beyond ~31° (tan β > 0.6) lifts the other off it
    # and keeps the segment parallel to the detector.
    crossed = view_map(segment, 1.0, other, 1.0, step_deg=5.0).best()
    assert crossed["overlap"] == 0.0 and crossed["foreshortening"] < 1e-9
    assert crossed["primary_deg"] == 0.0 and abs(crossed["secondary_deg"]) >= 30.0


def test_rendered_mask_of_a_tube_across_the_view_has_its_flat_ends_and_width():
    # AP: a tube along L (the columns) through the isocentre, radius r, length L. Its far end's
    # nearest edge (depth SOD − r) projects farthest: |col − c0| · ps ≤ (L/2) · SID / (SOD − r)
    # on the central row. Across it, the tangent rays from the source: half-width SID · r / √(SOD² − r²).
    # A union of spheres would reach a radius beyond each end.
    view = CArmView(0.0, 0.0, 1000.0, 750.0, (0.2, 0.2), (200, 400), principal_point_px=(100.0, 200.0))
    length, radius = 40.0, 2.0
    tube = straight_tube(length, 2 * radius, direction=(1.0, 0.0, 0.0))
    mask = render_mask(tube.tree, view)
    r0, c0 = view.principal_point
    cols = np.arange(400) - c0
    rows = np.arange(200) - r0
    along = np.abs(cols) * 0.2 <= (length / 2) * view.sid_mm / (view.sod_mm - radius)
    across = np.abs(rows) * 0.2 <= view.sid_mm * radius / math.sqrt(view.sod_mm ** 2 - radius ** 2)
    np.testing.assert_array_equal(mask[int(r0)], along)
    np.testing.assert_array_equal(mask[:, int(c0)], across)


def test_mask_widths_of_a_tube_in_two_views():
    phantom = straight_tube(20.0, 2.5, direction=(0.2, 0.3, 1.0))
    geometry = standard_geometry("lao30-rao30")
    masks = [render_mask(phantom.tree, view) for view in geometry.views]
    points = phantom.tree.branches[0].points
    tangents = np.tile(phantom.truth["direction"], (len(points), 1))
    widths = mask_diameters(points[2:-2], tangents[2:-2], masks, geometry.views)
    assert np.nanmean(np.abs(widths["equivalent_diameter_mm"] - 2.5)) <= 0.15
    assert widths["view_widths_mm"].shape == (2, len(points) - 4)


# --- the `analyse` command on a small synthetic result folder ---------------------------------------
def _result_folder(tmp_path, direction=(1.0, 0.2, 0.4)):
    from SDFCARLib.geometry import Geometry
    from SDFCARLib.io import write_json, write_mask_png, write_volume_nrrd

    phantom = stenosed_tube(length_mm=24.0, diameter_mm=3.0, stenosis_pct=50.0, lesion_length_mm=8.0,
                            direction=direction)
    grid = grid_around(phantom.tree, 0.3)
    geometry = Geometry(grid, standard_geometry("lao30-rao30").views)
    folder = tmp_path / "result"
    folder.mkdir()
    write_volume_nrrd(folder / "occupancy.nrrd", voxelize_exact(phantom.tree, grid).astype(np.float32), grid)
    masks = []
    for n, view in enumerate(geometry.views):
        masks.append(str(write_mask_png(tmp_path / f"view{n + 1}_mask.png", render_mask(phantom.tree, view))))
    write_json(folder / "report.json", {"geometry": geometry.to_dict(), "settings": {"threshold": 0.5},
                                        "target_kind": "mask", "inputs": {"targets": masks}})
    return folder, phantom


def test_analyse_command_writes_every_output(tmp_path, capsys):
    import json

    from SDFCARLib.cli import main

    folder, phantom = _result_folder(tmp_path)
    assert main(["analyse", str(folder), "--view-step-deg", "10", "--ostium", *map(str, phantom.truth["ostium_mm"])]) == 0
    out = folder / "analysis"
    data = json.loads((out / "analysis.json").read_text())
    assert (out / "centrelines.vtk").read_text().startswith("# vtk DataFile")
    assert (out / "profile_branch00.csv").read_text().splitlines()[0].startswith("arc_mm,diameter_3d_mm")
    lesion = data["lesions"][0]
    assert lesion["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0)
    assert lesion["length_mm"] == pytest.approx(8.0, abs=2.0)
    assert data["branches"][0]["diameter_masks"]["max_mm"] == pytest.approx(3.0, abs=0.3)
    assert data["best_view"]["foreshortening"] <= 0.05
    assert len(data["target_segment"]["acquisition_views"]) == 2
    assert "suggested view" in capsys.readouterr().out
    pytest.importorskip("matplotlib")
    assert (out / "diameter_profiles.png").is_file() and (out / "view_map.png").is_file()
    # A second run refuses to replace the files unless asked to.
    assert main(["analyse", str(folder)]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_a_marked_segment_is_measured_between_the_marks(tmp_path, capsys):
    import json

    from SDFCARLib.cli import main

    folder, phantom = _result_folder(tmp_path)  # a straight 24 mm tube centred on the origin
    axis = phantom.tree.branches[0].points
    t = (axis[-1] - axis[0]) / np.linalg.norm(axis[-1] - axis[0])
    marks = np.array([-8.0 * t, 8.0 * t])
    argv = ["analyse", str(folder), "--view-step-deg", "10", "--segment", *map(str, marks.ravel())]
    assert main(argv) == 0
    target = json.loads((folder / "analysis" / "analysis.json").read_text())["target_segment"]
    assert target["kind"] == "marked"
    np.testing.assert_allclose(target["marked_mm"], marks)
    assert target["length_mm"] == pytest.approx(16.0, rel=0.02)
    assert max(target["marks_from_centreline_mm"]) < 0.3
    for view, seen in zip(standard_geometry("lao30-rao30").views, target["acquisition_views"]):
        assert 100 * seen["foreshortening"] == pytest.approx(100 * foreshortening(marks, view), abs=1.0)
    assert "target segment (marked): branch 0" in capsys.readouterr().out


@pytest.mark.parametrize("marks, message", [
    ([[0, 0, 0], [0, 0, 0]], "fall on one place"),
    ([[0, 0, 0], [0, 30, 0]], "point 2 is"),
])
def test_marks_that_mark_no_segment_are_refused_and_nothing_is_written(tmp_path, capsys, marks, message):
    from SDFCARLib.cli import main

    folder, _ = _result_folder(tmp_path)
    assert main(["analyse", str(folder), "--segment", *map(str, np.ravel(marks))]) == 2
    err = capsys.readouterr().err
    assert "--segment" in err and message in err
    assert not (folder / "analysis").exists()


def test_marks_on_two_branches_are_named():
    from SDFCARLib.analysis.centreline import CentrelineBranch, CentrelineTree
    from SDFCARLib.analysis.pipeline import SegmentError, segment_between

    main_axis = np.c_[np.linspace(0, 40, 81), np.zeros(81), np.zeros(81)]
    side = np.c_[np.full(41, 20.0), np.linspace(0, 20, 41), np.zeros(41)]
    tree = CentrelineTree([CentrelineBranch(0, main_axis, np.ones(81)), CentrelineBranch(1, side, np.ones(41), 0, 40)])
    target = segment_between(tree, [5, 0.5, 0], [35, -0.5, 0])
    assert (target["branch_id"], target["start_mm"], target["end_mm"]) == (0, pytest.approx(5.0), pytest.approx(35.0))
    with pytest.raises(SegmentError, match=r"different branches \(0 and 1\)"):
        segment_between(tree, [5, 0, 0], [20, 15, 0])


def test_analyse_places_the_centreline_on_the_masks_unless_told_otherwise(tmp_path, capsys):
    import json

    from SDFCARLib.cli import main

    folder, phantom = _result_folder(tmp_path)
    for choice, expected in (("auto", True), ("volume", False)):
        out = tmp_path / choice
        assert main(["analyse", str(folder), "--out", str(out), "--view-step-deg", "10", "--centreline", choice]) == 0
        settings = json.loads((out / "analysis.json").read_text())["settings"]
        assert settings["centreline_on_masks"] is expected
        assert (settings["centreline_placement"] is not None) is expected
    # asked for without masks: a clear error, nothing written
    report = json.loads((folder / "report.json").read_text())
    report["inputs"]["targets"] = []
    (folder / "report.json").write_text(json.dumps(report))
    capsys.readouterr()
    assert main(["analyse", str(folder), "--out", str(tmp_path / "none"), "--centreline", "masks"]) == 2
    assert "needs the masks of two views or more" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_centrelines_vtk_reads_back_with_radii(tmp_path):
    pytest.importorskip("vtk")
    from SDFCARLib.analysis.outputs import centrelines_vtk_text
    from SDFCARLib.analysis.pipeline import analyse_volume
    from SDFCARLib.phantoms import load_centreline_vtk

    phantom = straight_tube(12.0, 2.0)
    grid = grid_around(phantom.tree, 0.3)
    result = analyse_volume(voxelize_exact(phantom.tree, grid), grid, best_view=False)
    path = tmp_path / "centrelines.vtk"
    path.write_text(centrelines_vtk_text(result))
    tree = load_centreline_vtk(path)
    assert len(tree.branches) == 1
    assert np.allclose(tree.branches[0].points, result.tree.branches[0].points_mm, atol=1e-4)
    assert np.median(tree.branches[0].radii) == pytest.approx(1.0, abs=0.08)
    # every point array reaches a reader as it comes, without ReadAllScalarsOn (Slicer's model reader)
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtk.vtkPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    point_data = reader.GetOutput().GetPointData()
    assert point_data.GetScalars().GetName() == "Radius"
    profile = result.profiles[0]
    arrays = {name: vtk_to_numpy(point_data.GetArray(name)) for name in ("Diameter3D", "DiameterMasks", "ArcLength")}
    assert np.allclose(arrays["ArcLength"], profile.branch.arc_length_mm, atol=1e-4)
    measured = np.isfinite(profile.diameter_mm)
    assert np.allclose(arrays["Diameter3D"][measured], profile.diameter_mm[measured], atol=1e-4)
    assert (arrays["Diameter3D"][~measured] == -1).all() and (arrays["DiameterMasks"] == -1).all()  # no masks given
    assert vtk_to_numpy(reader.GetOutput().GetCellData().GetArray("BranchId")).tolist() == [0]


def test_analyse_names_the_missing_volume(tmp_path, capsys):
    from SDFCARLib.cli import main

    (tmp_path / "empty").mkdir()
    assert main(["analyse", str(tmp_path / "empty")]) == 2
    assert "neither occupancy.nrrd nor segmentation.seg.nrrd" in capsys.readouterr().err


# --- Slicer scene content (slicer-core, headless) ---------------------------------------------------
def test_analysis_nodes_in_a_scene(tmp_path):
    pytest.importorskip("slicer")
    from vtk.util.numpy_support import vtk_to_numpy

    from SDFCARLib.analysis.mrml_nodes import add_analysis_nodes, camera_for_angles, set_camera_to_angles
    from SDFCARLib.analysis.outputs import analyse_result_dir
    from SDFCARLib.mrml import new_scene

    folder, phantom = _result_folder(tmp_path)
    analyse_result_dir(folder, view_step_deg=10.0, ostium_mm=phantom.truth["ostium_mm"])
    scene = new_scene()
    nodes = add_analysis_nodes(scene, folder / "analysis", name="case")
    # the result folder itself finds the analysis analyse wrote into it by default
    again = add_analysis_nodes(scene, folder, name="again")
    assert again["table"].GetNumberOfRows() == nodes["table"].GetNumberOfRows() and len(again["curves"]) == len(nodes["curves"])
    curve = nodes["curves"][0]
    assert curve.GetNumberOfControlPoints() > 10
    lps_first = np.array(json.loads((folder / "analysis" / "analysis.json").read_text())["branches"][0]["start_mm"])
    assert np.allclose(curve.GetNthControlPointPosition(0), lps_first * [-1, -1, 1], atol=1e-3)  # RAS
    diameters = curve.GetMeasurement("Diameter").GetControlPointValues()
    values = [diameters.GetValue(i) for i in range(diameters.GetNumberOfTuples())]
    assert len(values) == curve.GetNumberOfControlPoints() and np.nanmax(values) == pytest.approx(3.0, abs=0.3)
    assert np.isnan(values[0])  # the cut end is excluded from grading (its sections are no lumen): no diameter shown
    assert nodes["series"][0].GetName() == "case branch 0 diameter"  # not the curve's name
    table = nodes["table"]
    assert table.GetNumberOfRows() == 1
    assert table.GetTable().GetColumnByName("diameter_stenosis_pct").GetValue(0) == pytest.approx(50.0, abs=8.0)
    # the tube (1, 0.2, 0.4) at the isocentre rises 21.4° out of LAO 30 / RAO 30's horizontal epipolar plane
    assert table.GetTable().GetColumnByName("epipolar_angle_median_deg").GetValue(0) == pytest.approx(21.4, abs=1.5)
    profile = scene.GetFirstNodeByName("case branch 0 profile").GetTable().GetColumnByName("epipolar_angle_deg")
    assert profile.GetNumberOfTuples() > 10 and np.nanmedian(vtk_to_numpy(profile)) == pytest.approx(21.4, abs=1.5)
    assert nodes["chart"].GetNumberOfPlotSeriesNodes() == 1
    image = nodes["view_map"].GetImageData()
    assert image.GetDimensions()[:2] == (13, 9)  # −60..60 and −40..40 every 10°
    # AP: the camera sits anterior (RAS +A... LPS −y), head up; LAO 90 would put it on the patient's left.
    cam = camera_for_angles(0.0, 0.0, 500.0)
    assert np.allclose(cam["position"], (0, 500, 0)) and np.allclose(cam["view_up"], (0, 0, 1))
    camera = scene.AddNewNodeByClass("vtkMRMLCameraNode")
    set_camera_to_angles(camera, 90.0, 0.0, 500.0)
    assert np.allclose(camera.GetPosition(), (-500, 0, 0), atol=1e-6)  # LPS +x (left) = RAS −x


def test_reconstruct_takes_the_analyse_flag():
    from SDFCARLib.cli import build_parser

    args = build_parser().parse_args(["reconstruct", "--geometry", "g.json", "--mask1", "a.png", "--mask2", "b.png",
                                      "--out", "r", "--analyse"])
    assert args.analyse is True
    assert build_parser().parse_args(["analyse", "r", "--ostium", "1", "2", "3"]).ostium == [1.0, 2.0, 3.0]


# --- broken reconstructions (analysis/fragments.py) -----------------------------------------------
def _tube_phantom(stenosis_pct):
    """A 40 mm tube of 3 mm, oblique to the grid, with a 10 mm concentric stenosis in its middle (at the origin)."""
    phantom = stenosed_tube(length_mm=40.0, diameter_mm=3.0, stenosis_pct=stenosis_pct, lesion_length_mm=10.0,
                            direction=(1.0, 0.5, 0.25))
    grid = grid_around(phantom.tree, 0.3, margin_mm=8.0)
    axis = np.array([1.0, 0.5, 0.25]) / np.linalg.norm([1.0, 0.5, 0.25])
    return phantom, grid, voxelize_exact(phantom.tree, grid), axis


def _remove(label, grid, keep):
    ijk = np.argwhere(label)
    drop = ijk[~keep(grid.index_to_world(ijk))]
    out = label.copy()
    out[tuple(drop.T)] = False
    return out


def _ball(label, grid, centre_mm, radius_mm):
    ijk = np.argwhere(np.ones(label.shape, bool))
    inside = np.linalg.norm(grid.index_to_world(ijk) - centre_mm, axis=1) <= radius_mm
    out = label.copy()
    out[tuple(ijk[inside].T)] = True
    return out


@pytest.mark.parametrize("stenosis_pct", [0.0, 50.0])
def test_a_tube_cut_by_a_two_voxel_gap_is_not_a_reliable_stenosis(stenosis_pct):
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    # 0 %: a clean cut; 50 %: the vessel thins into the break, as a reconstruction does before it breaks.
    _, grid, label, axis = _tube_phantom(stenosis_pct)
    cut = _remove(label, grid, lambda x: np.abs(x @ axis) >= 0.3)  # 0.6 mm = 2 voxels across the throat
    data = summary(analyse_volume(cut, grid, best_view=False))
    assert data["connectivity"]["components"] == 2 and data["connectivity"]["analysed_components"] == 2
    assert data["lesions"] == []
    if stenosis_pct:  # each half's taper into the gap: kept, flagged, with the reason
        flagged = data["unreliable_lesions"]
        assert len(flagged) == 2 and all(f["reliable"] is False for f in flagged)
        assert all(f["flag"] == "unreliable: the reconstruction is broken here" for f in flagged)
        assert all(any(r.startswith("gap: another piece") for r in f["reasons"]) for f in flagged)
        assert all(f["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0) for f in flagged)
    assert "the reconstruction is in 2 pieces; the largest holds 50 %" in data["warnings"][0]


def test_an_intact_stenosis_stays_reliable_and_debris_beside_it_flags_it():
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    _, grid, label, axis = _tube_phantom(50.0)
    side = np.cross(axis, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)

    def lesions(volume, **options):
        return summary(analyse_volume(volume, grid, best_view=False, **options))

    intact = lesions(label)
    assert len(intact["lesions"]) == 1 and intact["unreliable_lesions"] == [] and intact["warnings"] == []
    assert intact["lesions"][0]["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0)
    assert intact["lesions"][0]["reliable"] is True and intact["connectivity"]["components"] == 1
    # A 1 mm ball of debris (under 10 % of the tube: not analysed), its surface 1 mm beside the healthy wall at the
    # throat, flags the lesion; 6 mm away it does not.
    near = lesions(_ball(label, grid, (1.5 + 1.0 + 1.0) * side, 1.0))
    assert near["lesions"] == [] and len(near["unreliable_lesions"]) == 1
    assert near["unreliable_lesions"][0]["reasons"][0].startswith("gap: another piece of the reconstruction")
    assert near["connectivity"]["not_analysed"]["components"] == 1 and near["tree"]["branches"] == 1
    far = lesions(_ball(label, grid, (1.5 + 6.0 + 1.0) * side, 1.0))
    assert len(far["lesions"]) == 1 and far["unreliable_lesions"] == []
    # A gap that reconnection bridged at the throat (report.json's bridges) flags it; one 15 mm away does not.
    bridged = lesions(label, bridges=[{"gap_mm": 1.9, "radius_mm": 0.7, "points_mm": [[0.0, 0.0, 0.0]]}])
    assert bridged["lesions"] == [] and bridged["unreliable_lesions"][0]["reasons"][0].startswith("bridge:")
    elsewhere = lesions(label, bridges=[{"gap_mm": 1.9, "radius_mm": 0.7, "points_mm": [list(15.0 * axis)]}])
    assert len(elsewhere["lesions"]) == 1


def test_a_stenosis_on_a_piece_cut_off_from_the_main_tree_is_flagged():
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    phantom, grid, label, axis = _tube_phantom(50.0)
    side = np.cross(axis, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    # The main tree: a thicker healthy tube 12 mm to the side, longer than the stenosed piece.
    main = straight_tube(44.0, 4.0, direction=axis, center_mm=12.0 * side)
    both = CentrelineTree(list(phantom.tree.branches) + list(main.tree.branches))
    grid = grid_around(both, 0.3)
    volume = voxelize_exact(both, grid)
    data = summary(analyse_volume(volume, grid, best_view=False))
    assert data["lesions"] == [] and len(data["unreliable_lesions"]) == 1
    reasons = data["unreliable_lesions"][0]["reasons"]  # the main tree is 8.5 mm from its wall: no gap
    assert len(reasons) == 1 and reasons[0].startswith("fragment: the vessel lies on a piece of")
    # With the ostium on the stenosed vessel, it is the tree analysed and its lesion is reliable.
    data = summary(analyse_volume(volume, grid, best_view=False, ostium_mm=phantom.truth["ostium_mm"]))
    assert len(data["lesions"]) == 1 and data["unreliable_lesions"] == []
    assert [b["component"]["main"] for b in data["branches"] if b["lesions"]] == [True]
    # Pieces under --min-component-share of the main tree are not analysed at all.
    data = summary(analyse_volume(volume, grid, best_view=False, min_component_share=0.9))
    assert data["tree"]["branches"] == 1 and data["lesions"] == [] and data["unreliable_lesions"] == []
    assert data["connectivity"]["not_analysed"]["components"] == 1


def test_analyse_warns_about_a_broken_reconstruction(tmp_path, capsys):
    from SDFCARLib.cli import main
    from SDFCARLib.io import write_json, write_volume_nrrd

    _, grid, label, axis = _tube_phantom(50.0)
    cut = _remove(label, grid, lambda x: np.abs(x @ axis) >= 0.3)
    folder = tmp_path / "result"
    folder.mkdir()
    write_volume_nrrd(folder / "occupancy.nrrd", cut.astype(np.float32), grid)
    write_json(folder / "report.json", {"settings": {"threshold": 0.5},
                                        "reconnection": {"joined": 1, "gap_mm": [1.0]}})
    assert main(["analyse", str(folder), "--view-step-deg", "10"]) == 0
    captured = capsys.readouterr()
    assert "warning: the reconstruction is in 2 pieces; the largest holds 50 % of the vessel voxels" in captured.err
    assert "bridged 1 gap(s) but not where" in captured.err  # a result from before bridges were recorded
    assert "2 more narrowing(s) flagged \"unreliable: the reconstruction is broken here\"" in captured.out
    data = json.loads((folder / "analysis" / "analysis.json").read_text())
    assert data["connectivity"]["components"] == 2 and len(data["unreliable_lesions"]) == 2
    assert main(["analyse", str(folder), "--out", str(tmp_path / "a2"), "--min-component-share", "2"]) == 2
    assert "between 0 and 1" in capsys.readouterr().err


def test_strands_that_run_inside_their_parents_lumen_are_told_from_side_branches():
    # A rough reconstruction thins into a main path plus strands beside it inside its lumen (RESULTS §22e).
    from SDFCARLib.analysis.centreline import CentrelineBranch, CentrelineTree
    from SDFCARLib.analysis.pipeline import strands_within_parents

    def line(start, direction, length, step=0.25):
        t = np.arange(0.0, length + 1e-9, step)
        return np.asarray(start, float) + t[:, None] * (np.asarray(direction, float) / np.linalg.norm(direction))

    def branch(bid, points, parent=None, at=None):
        return CentrelineBranch(bid, points, np.full(len(points), 0.5), parent_id=parent, parent_index=at)

    main = branch(0, line((0, 0, 0), (1, 0, 0), 40.0))
    strand = branch(1, line((10, 0.3, 0), (1, 0.12, 0), 8.0), 0, 40)  # 1.3 mm off the axis at most, along it
    side = branch(2, line((20, 0, 0), (0.5, 0.87, 0), 10.0), 0, 80)  # leaves at 60°
    stub_of_strand = branch(3, line((14, 0.8, 0), (1, -0.1, 0), 3.0), 1, 16)
    short_side = branch(4, line((30, 0, 0), (0, 1, 0), 4.0), 0, 120)  # across the vessel: not along it
    tree = CentrelineTree([main, strand, side, stub_of_strand, short_side])
    diameters = {0: 3.0, 1: 3.0}  # the parents' median diameters
    assert strands_within_parents(tree, diameters) == {1, 3}
    diameters[0] = 1.0  # beside a 1 mm vessel the same path leaves its lumen: a branch
    assert 1 not in strands_within_parents(tree, diameters)
    from SDFCARLib.analysis.outputs import analysis_summary_lines

    header = analysis_summary_lines({"tree": {"branches": 3, "total_length_mm": 54.0, "strands_dropped": 2}})[0]
    assert header.startswith("3D-QCA: 3 branches, 54.0 mm") and "2 strand(s)" in header
    assert "strand" not in analysis_summary_lines({"tree": {"branches": 3, "total_length_mm": 54.0, "strands_dropped": 0}})[0]


@pytest.mark.parametrize("stenosis_pct, voxel_mm, thin", [(50.0, 0.5, False), (70.0, 0.5, True), (70.0, 0.3, False)])
def test_a_throat_thinner_than_the_grid_resolves_is_flagged_and_warned_about(stenosis_pct, voxel_mm, thin):
    from SDFCARLib.analysis.pipeline import RESOLVABLE_VOXELS, analyse_volume, summary

    # The 3 mm tube: a 50 % throat is 1.5 mm, a 70 % one 0.9 mm, under 2.5 voxels of 0.5 mm (1.25 mm), not of 0.3 mm.
    phantom = stenosed_tube(length_mm=40.0, diameter_mm=3.0, stenosis_pct=stenosis_pct, lesion_length_mm=10.0,
                            direction=(1.0, 0.5, 0.25))
    grid = grid_around(phantom.tree, voxel_mm, margin_mm=8.0)
    data = summary(analyse_volume(voxelize_exact(phantom.tree, grid), grid, best_view=False))
    assert data["settings"]["voxel_mm"] == pytest.approx(voxel_mm)
    [lesion] = data["lesions"]
    assert lesion["mld_mm"] == pytest.approx(3.0 * (1 - stenosis_pct / 100), abs=2 * voxel_mm)
    assert lesion["mld_below_resolution"] is (lesion["mld_mm"] < RESOLVABLE_VOXELS * voxel_mm) is thin
    warned = [w for w in data["warnings"] if "minimal lumen under 2.5 voxels" in w]
    assert len(warned) == int(thin)
    if thin:  # names the lesion and the fix
        assert "branch 0" in warned[0] and "1.25 mm on this 0.5 mm grid" in warned[0] and "--frames" in warned[0]


@pytest.mark.parametrize("step", ["reconnection", "final_reconnection"])
def test_analyse_reads_the_bridges_of_either_reconnection_from_report_json(tmp_path, capsys, step):
    from SDFCARLib.cli import main
    from SDFCARLib.io import write_json, write_volume_nrrd

    _, grid, label, _ = _tube_phantom(50.0)
    folder = tmp_path / "result"
    folder.mkdir()
    write_volume_nrrd(folder / "occupancy.nrrd", label.astype(np.float32), grid)
    bridge = {"gap_mm": 1.9, "radius_mm": 0.7, "points_mm": [[0.0, 0.0, 0.0]]}  # at the throat
    write_json(folder / "report.json", {"settings": {"threshold": 0.5}, step: {"joined": 1, "bridges": [bridge]}})
    assert main(["analyse", str(folder), "--view-step-deg", "10"]) == 0
    assert "but not where" not in capsys.readouterr().err
    data = json.loads((folder / "analysis" / "analysis.json").read_text())
    assert data["lesions"] == [] and data["unreliable_lesions"][0]["reasons"][0].startswith("bridge:")


def test_without_frames_a_lesion_the_masks_show_on_a_vessel_too_thin_for_the_grid_is_reported_from_the_masks(tmp_path):
    from SDFCARLib.analysis.outputs import analysis_summary_lines
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    # A 1.5 mm tube with a 50 % lesion over 10 mm on a 0.6 mm grid: its reference spans under 2.5 voxels, so the
    # 3D sections narrow there but report no lesion; its clean masks show it.
    phantom = stenosed_tube(length_mm=30.0, diameter_mm=1.5, stenosis_pct=50.0, lesion_length_mm=10.0)
    grid = grid_around(phantom.tree, 0.6)
    volume = voxelize_exact(phantom.tree, grid).astype(np.float32)
    views = standard_geometry("lao30-rao30").views
    masks = [render_mask(phantom.tree, v) for v in views]

    def analysed(search_masks):
        return analyse_volume(volume, grid, views=views, masks=masks, ostium_mm=phantom.truth["ostium_mm"],
                              best_view=False, search_masks=search_masks)

    before = summary(analysed(False))
    assert before["lesions"] == [] and before["branches"][0]["narrowings_below_resolution"] >= 1
    result = analysed(True)
    data = summary(result)
    [lesion] = data["lesions"]
    grade = lesion["grade"]
    assert lesion["found_on"] == "masks" and grade["source"] == "masks (two-view diameter)"
    assert grade["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0)
    assert grade["length_mm"] == pytest.approx(10.0, abs=2.0)
    assert grade["reference_diameter_mm"] == pytest.approx(1.5, abs=0.3)
    assert lesion["diameter_stenosis_pct"] >= 20.0  # the 3D sections narrow over the masks' extent too
    assert any("found on the masks only" in w and "branch 0" in w and "--frames" in w for w in data["warnings"])
    assert "found on the masks only" in analysis_summary_lines(data)[1]
    if importlib.util.find_spec("slicer") is not None:  # the Slicer QCA table leads with the masks' grade
        from test_frame_density import _qca_table

        table = _qca_table(tmp_path / "masks", result, data)
        assert table.GetColumnByName("found_on").GetValue(0) == "masks"
        assert table.GetColumnByName("graded_on").GetValue(0) == "masks (two-view diameter)"
        assert table.GetColumnByName("diameter_stenosis_pct").GetValue(0) == pytest.approx(grade["diameter_stenosis_pct"])


def test_without_frames_a_narrowing_of_the_masks_alone_is_not_a_lesion():
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    # The masks of a tube with a 50 % lesion, a volume of the same tube without one: the masks' narrowing is not
    # confirmed by the 3D sections (an overlap or a ghost spur narrows the 2D widths alike), so no lesion.
    stenosed = stenosed_tube(length_mm=30.0, diameter_mm=3.0, stenosis_pct=50.0, lesion_length_mm=10.0)
    healthy = straight_tube(30.0, 3.0, (1.0, 0.5, 0.25))
    grid = grid_around(healthy.tree, 0.4)
    views = standard_geometry("lao30-rao30").views
    masks = [render_mask(stenosed.tree, v) for v in views]
    data = summary(analyse_volume(voxelize_exact(healthy.tree, grid).astype(np.float32), grid, views=views, masks=masks,
                                  ostium_mm=stenosed.truth["ostium_mm"], best_view=False))
    assert data["lesions"] == [] and data["unreliable_lesions"] == []


def test_relative_scatter_is_the_robust_sd_of_the_profile_about_its_reference():
    from SDFCARLib.analysis.lesion import ReferenceFit, relative_scatter

    s = np.arange(0.0, 20.0, 0.5)
    reference = ReferenceFit(3.0, -0.05, np.ones(len(s), bool))  # a tapering vessel
    alternating = np.where(np.arange(len(s)) % 2 == 0, 1.1, 0.9)  # ±10 % about the reference
    assert relative_scatter(s, reference(s) * alternating, reference) == pytest.approx(1.4826 * 0.1)
    assert relative_scatter(s, reference(s), reference) == pytest.approx(0.0)


@pytest.mark.parametrize("masks_dip, dip_sd_mm, scatter, in_3d, found", [
    (0.5, 2.5, 0.0, 0.5, True),     # a 50 % lesion over ~10 mm on smooth masks, the 3D sections narrow too
    (0.5, 2.5, 0.0, 0.1, False),    # the 3D sections narrow 10 %: the masks' narrowing alone is no lesion
    (0.5, 2.5, 0.25, 0.5, False),   # masks that stray ±25 % about their reference: a 50 % dip is under 2.5 scatters
    (0.5, 0.3, 0.0, 0.5, False),    # a dip ~1 mm long on a 3 mm vessel: shorter than its diameter
])
def test_a_lesion_is_found_on_the_masks_only_where_the_3d_sections_narrow_and_it_stands_out(
        masks_dip, dip_sd_mm, scatter, in_3d, found):
    from SDFCARLib.analysis.centreline import CentrelineBranch
    from SDFCARLib.analysis.diameter import CrossSections
    from SDFCARLib.analysis.lesion import ReferenceFit
    from SDFCARLib.analysis.pipeline import BranchProfile, masks_lesions

    s = np.arange(0.0, 40.0, 0.25)
    branch = CentrelineBranch(branch_id=0, points_mm=np.stack([s, 0 * s, 0 * s], axis=1),
                              inscribed_radius_mm=np.full(len(s), 1.5))
    bump = np.exp(-0.5 * ((s - 20.0) / dip_sd_mm) ** 2)
    sections_mm = 3.0 * (1 - in_3d * bump)
    sections = CrossSections(np.pi * sections_mm ** 2 / 4, sections_mm, sections_mm, sections_mm)
    profile = BranchProfile(branch, sections, np.zeros(len(s), bool))
    profile.reference = ReferenceFit(3.0, 0.0, np.ones(len(s), bool))
    stray = np.where(np.arange(len(s)) % 2 == 0, 1 + scatter, 1 - scatter)
    profile.mask_diameter_mm = 3.0 * stray * (1 - masks_dip * bump)
    masks_lesions(profile, 20.0)
    assert len(profile.masks_only) == int(found) and len(profile.lesions) == int(found)
    if found:
        assert profile.masks_only[0].mld_position_mm == pytest.approx(20.0, abs=0.5)


@pytest.mark.parametrize("step_deg", [0.0, 0.01, 0.49, -2.0, 31.0, 200.0, float("nan")])
def test_a_view_map_step_outside_half_a_degree_to_30_degrees_is_refused(step_deg):
    segment = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 10.0]])
    with pytest.raises(ValueError, match="angle step must be from 0.5° .* to 30°"):
        view_map(segment, 1.0, step_deg=step_deg)
    assert view_map(segment, 1.0, step_deg=30.0).foreshortening.shape == (3, 5)  # the coarsest: 5 × 3 views
    assert view_map(segment, 1.0, step_deg=0.5).foreshortening.shape == (161, 241)  # the finest: ±40° by ±60°


def test_an_ostium_far_from_the_tree_is_refused_with_its_distance_and_a_near_one_is_taken():
    from SDFCARLib.analysis.pipeline import check_ostium
    phantom = straight_tube(16.0, 2.0)
    grid = grid_around(phantom.tree, 0.5)
    lumen = voxelize_exact(phantom.tree, grid) >= 0.5
    end = phantom.tree.branches[0].points[0]
    check_ostium(lumen, grid, end)  # at the tube's end
    check_ostium(lumen, grid, end + np.array([0.0, 6.0, 0.0]))  # a click beside it
    check_ostium(lumen, grid, None)
    far = end + np.array([0.0, 0.0, -40.0])
    with pytest.raises(ValueError, match=r"is 3\d\.\d mm from the nearest voxel of the vessel tree.*negate x and y"):
        check_ostium(lumen, grid, far)
    with pytest.raises(ValueError, match="three finite coordinates"):
        check_ostium(lumen, grid, [0.0, float("nan"), 0.0])


def test_a_volume_with_nan_or_of_another_shape_than_its_grid_is_refused():
    from SDFCARLib.analysis.pipeline import analyse_volume

    phantom = straight_tube(16.0, 2.0)
    grid = grid_around(phantom.tree, 0.5)
    volume = voxelize_exact(phantom.tree, grid).astype(np.float32)
    holed = volume.copy()
    holed[volume.shape[0] // 2] = np.nan  # a slice lost: the sections read NaN as no lumen and break the tree
    with pytest.raises(ValueError, match=rf"holds {volume.shape[1] * volume.shape[2]} NaN or infinite values"):
        analyse_volume(holed, grid, best_view=False)
    with pytest.raises(ValueError, match=r"has shape .* and its grid"):
        analyse_volume(volume[:-1], grid, best_view=False)
    assert len(analyse_volume(volume, grid, best_view=False).tree.branches) == 1


def test_an_ostium_given_at_a_distal_tip_is_warned_of_naming_the_thick_end_and_the_root_end_is_not():
    from SDFCARLib.analysis.pipeline import analyse_volume, summary
    from SDFCARLib.phantoms import lad_tree

    tree = lad_tree(0)  # its main vessel 4 mm wide at the ostium, 1.4 mm at its distal tip
    grid = grid_around(tree, 0.5)
    volume = voxelize_exact(tree, grid).astype(np.float32)
    ostium, tip = tree.branches[0].points[0], tree.branches[0].points[-1]

    def ostium_warnings(point):
        data = summary(analyse_volume(volume, grid, ostium_mm=point, best_view=False))
        return data, [w for w in data["warnings"] if "the ostium given" in w]

    data, warnings = ostium_warnings(ostium)
    assert warnings == [] and data["settings"]["given_root"]["distance_to_thickest_end_mm"] < 3.0
    data, [warning] = ostium_warnings(tip)
    given = data["settings"]["given_root"]
    assert 2 * given["given_radius_mm"] < 0.6 * 2 * given["thickest_end_radius_mm"]
    assert np.linalg.norm(np.asarray(given["thickest_end_mm"]) - ostium) < 3.0  # it names where the ostium is
    assert "backwards" in warning and "leave --ostium out" in warning
    assert data["branches"][0]["start_mm"] == pytest.approx(list(tip), abs=2.0)  # the user's choice is still followed


def test_masks_given_in_the_wrong_view_order_are_warned_of_naming_the_order_that_matches():
    from SDFCARLib.analysis.mask_order import share_on_masks
    from SDFCARLib.analysis.pipeline import analyse_volume, summary
    from SDFCARLib.phantoms import lad_tree

    tree = lad_tree(0)
    grid = grid_around(tree, 0.6)
    volume = voxelize_exact(tree, grid).astype(np.float32)
    views = standard_geometry("lao30-rao30").views
    masks = [render_mask(tree, v) for v in views]

    def analysed(given):
        return summary(analyse_volume(volume, grid, views=views, masks=given, ostium_mm=tree.branches[0].points[0],
                                      best_view=False))

    data = analysed(masks)
    assert min(data["settings"]["centreline_share_on_masks"]) > 0.95
    assert not any("do not match their views" in w for w in data["warnings"])
    data = analysed(masks[::-1])
    assert max(data["settings"]["centreline_share_on_masks"]) < 0.5 and data["settings"]["masks_better_order"] == [1, 0]
    [warning] = [w for w in data["warnings"] if "do not match their views" in w]
    assert "mask 2 for view 1, mask 1 for view 2" in warning
    points = np.concatenate([b.points for b in tree.branches])
    far = views[0].source_position * 3  # behind the source: on no detector
    assert share_on_masks(far[None], masks[:1], views[:1]) == [None]
    assert share_on_masks(points, [np.zeros_like(masks[0])], views[:1]) == [0.0]


def test_masks_given_to_analyse_volume_read_alike_whatever_their_vessel_value_and_need_their_views():
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    phantom = straight_tube(24.0, 3.0, (1.0, 0.2, 0.4))
    grid = grid_around(phantom.tree, 0.3)
    volume = voxelize_exact(phantom.tree, grid).astype(np.float32)
    views = standard_geometry("lao30-rao30").views
    masks = [render_mask(phantom.tree, v) for v in views]

    def mask_diameter(given):
        data = summary(analyse_volume(volume, grid, views=views, masks=given, best_view=False, centreline_on_masks=False))
        return data["branches"][0]["diameter_masks"]["mean_mm"]

    as_bool = mask_diameter(masks)
    assert as_bool == pytest.approx(3.0, abs=0.15)
    # a PNG's 0/255: the edges at half the vessel value, not at 0.5 of 255 (a pixel wider each side)
    assert mask_diameter([m.astype(np.uint8) * 255 for m in masks]) == pytest.approx(as_bool, abs=1e-6)
    with pytest.raises(ValueError, match="2 masks for 0 views"):
        analyse_volume(volume, grid, masks=masks, best_view=False)
    with pytest.raises(ValueError, match=r"mask of view 2: mask shape \(256, 256\) differs from the detector shape"):
        analyse_volume(volume, grid, views=views, masks=[masks[0], masks[1][::2, ::2]], best_view=False)


def test_an_analysis_folder_in_the_way_is_found_before_the_reconstruction_and_before_the_analysis(tmp_path, capsys,
                                                                                                  monkeypatch):
    from SDFCARLib.cli import main, reconstruct as cli_reconstruct
    from SDFCARLib.sample_data import SAMPLE_DIR

    out = tmp_path / "r"
    (out / "analysis").mkdir(parents=True)
    (out / "analysis" / "analysis.json").write_text("{}", encoding="utf-8")  # an earlier run's analysis

    def no_fit(*args, **kwargs):
        raise AssertionError("the reconstruction ran although its analysis could not be written")

    monkeypatch.setattr(cli_reconstruct, "run_reconstruction", no_fit)
    assert main(["reconstruct", "--geometry", str(SAMPLE_DIR / "geometry.json"), "--mask1", str(SAMPLE_DIR / "view1_mask.png"),
                 "--mask2", str(SAMPLE_DIR / "view2_mask.png"), "--out", str(out), "--analyse", "--no-progress"]) == 2
    assert "already holds analysis.json" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["analysis"]  # nothing of a new result beside the old analysis

    folder, _ = _result_folder(tmp_path)
    (folder / "analysis").mkdir()
    (folder / "analysis" / "view_map.png").write_bytes(b"not ours to replace")
    monkeypatch.setattr("SDFCARLib.analysis.outputs.analyse_volume", no_fit)
    assert main(["analyse", str(folder)]) == 2
    assert "already holds view_map.png" in capsys.readouterr().err
    assert main(["analyse", str(folder), "--out", ""]) == 2
    assert "empty name" in capsys.readouterr().err
    from SDFCARLib.analysis.outputs import analyse_result_dir
    from SDFCARLib.io import InputError

    for option in ("masks", "frames"):  # from Python: one path, not a list of one per view
        with pytest.raises(InputError, match=f"{option} is a list of paths, one per view"):
            analyse_result_dir(folder, tmp_path / "a", **{option: str(tmp_path / "view1_mask.png")})
    for option, value in (("view_step_deg", "2"), ("min_stenosis_pct", None)):
        with pytest.raises(InputError, match=f"{option} must be a number"):
            analyse_result_dir(folder, tmp_path / "a", **{option: value})
    with pytest.raises(InputError, match="--psf-sigma-mm must be a blur in mm"):
        analyse_result_dir(folder, tmp_path / "a", frames=[str(tmp_path / "f1.nrrd"), str(tmp_path / "f2.nrrd")],
                           psf_sigma_mm="wide")
    from SDFCARLib.analysis.pipeline import analyse_volume

    with pytest.raises(ValueError, match="min_stenosis_pct is the least diameter stenosis"):
        analyse_volume(np.zeros((4, 4, 4), np.float32), None, min_stenosis_pct=float("nan"))


@pytest.mark.parametrize("dtype, level", [(np.float32, 0.5), (np.float32, 0.7), (np.float64, 0.3), (np.uint8, 0.5),
                                          (bool, 0.5)])
def test_only_cavities_the_lumen_encloses_are_filled_and_they_then_read_as_lumen(dtype, level):
    from SDFCARLib.analysis.centreline import fill_lumen_cavities

    volume = np.zeros((12, 12, 12), dtype)
    volume[2:10, 2:10, 2:10] = 1
    volume[5, 5, 5] = 0                      # a cavity of one voxel
    volume[4, 6:8, 6:8] = 0                  # and one of four
    volume[8, 8, 8] = 0                      # touches the outside diagonally only: enclosed for face-connected paths
    volume[9, 3, 3] = 0                      # a dent open to the outside through a face
    volume[9, 3, 2] = 0
    before = volume.copy()
    filled, n = fill_lumen_cavities(volume, level)
    assert n == 6
    lumen = filled if dtype is bool else filled >= level
    assert lumen[5, 5, 5] and lumen[4, 6:8, 6:8].all() and lumen[8, 8, 8]
    assert not lumen[9, 3, 3] and not lumen[9, 3, 2]
    assert (volume == before).all()          # the caller's volume is left as it was
    assert fill_lumen_cavities(filled, level)[1] == 0


def test_a_voxel_the_fit_left_empty_inside_the_ostium_does_not_root_the_tree_at_a_distal_end():
    from SDFCARLib.analysis.phantoms import branch_arc_length_mm
    from SDFCARLib.analysis.pipeline import analyse_volume
    from SDFCARLib.phantoms import rca_tree

    tree = rca_tree(0)
    grid = grid_around(tree, 0.8)  # the realistic protocol's voxel
    volume = voxelize_exact(tree, grid).astype(np.float32)
    main = tree.branches[0]
    at_1_6_mm = main.points[np.searchsorted(branch_arc_length_mm(main), 1.6)]
    volume[tuple(np.round(grid.world_to_index(at_1_6_mm[None])[0]).astype(int))] = 0.2  # thinning rings such a voxel with a loop: the ostium is then no end of the skeleton
    ostium_end = extract_centrelines(volume, grid).branches[0].points_mm[0]
    assert np.linalg.norm(ostium_end - main.points[0]) < 4.0
    result = analyse_volume(volume, grid, best_view=False)
    assert result.settings["lumen_cavities_filled"] == 1
    assert np.linalg.norm(result.tree.branches[0].points_mm[0] - main.points[0]) < 4.0


def test_a_tunnel_a_voxel_wide_is_closed_before_thinning_and_a_gap_of_three_is_not():
    from SDFCARLib.analysis.centreline import close_tunnels

    lumen = np.zeros((14, 14, 14), bool)
    lumen[3:11, 3:11, 3:11] = True
    lumen[6, 6, :] = False                      # a channel one voxel wide straight through the block
    closed = close_tunnels(lumen)
    assert closed[6, 6, 4:10].all() and (closed >= lumen).all()  # only its two mouths stay open, as dents
    assert not closed[6, 6, :3].any()          # nothing grows outside the block
    apart = np.zeros((14, 14, 14), bool)
    apart[2:12, 2:12, 2:5] = apart[2:12, 2:12, 8:11] = True   # two slabs three voxels apart stay apart
    assert (close_tunnels(apart) == apart).all()


def test_a_tunnel_through_the_ostium_does_not_root_the_tree_at_a_distal_end():
    from SDFCARLib.analysis.phantoms import branch_arc_length_mm

    from SDFCARLib.phantoms import rca_tree

    tree = rca_tree(0)
    grid = grid_around(tree, 0.8)
    volume = voxelize_exact(tree, grid).astype(np.float32)
    main = tree.branches[0]
    centre = np.round(grid.world_to_index(main.points[np.searchsorted(branch_arc_length_mm(main), 1.6)][None])[0]).astype(int)
    axis = int(np.argmin(np.abs(main.points[10] - main.points[0])))  # the grid axis most across the vessel
    index = list(centre)
    for k in range(-4, 5):                     # a channel one voxel wide across the vessel, open to the outside
        index[axis] = centre[axis] + k
        volume[tuple(index)] = 0.2
    assert np.linalg.norm(extract_centrelines(volume, grid).branches[0].points_mm[0] - main.points[0]) < 4.0
