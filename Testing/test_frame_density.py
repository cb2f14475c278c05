"""Lumen area from the frames' absorbance (analysis/frame_density.py): closed forms and a simulated tube."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.analysis.diameter import projected_widths
from SDFCARLib.analysis.frame_density import attenuation_per_mm, densities, density_diameter, integrated_absorbance
from SDFCARLib.analysis.frame_widths import frame_widths
from SDFCARLib.angiogram import AngiogramSettings
from SDFCARLib.geometry import standard_geometry
from SDFCARLib.lumen_profile import blurred_chord

VIEWS = standard_geometry("lao30-rao30").views


def test_integrated_absorbance_is_attenuation_times_area_on_a_sloped_background():
    x = np.arange(-5.0, 5.0, 0.05)
    mu, radius = 0.25, 1.1
    profile = 1.3 + 0.02 * x + mu * blurred_chord(x, 0.2, radius, 0.3)
    assert integrated_absorbance(x, profile, radius + 0.2 + 3 * 0.3) == pytest.approx(mu * np.pi * radius ** 2, rel=5e-3)


def test_the_area_of_a_slit_lumen_is_the_same_from_its_narrow_and_its_wide_side():
    # An elliptical throat (semi-axes 1.5 and 0.5 mm): seen across its long axis it is 3 mm wide, across the
    # short one 1 mm; the chord is 2·b·√(1 − x²/a²) either way and its integral π·a·b.
    x = np.arange(-6.0, 6.0, 0.01)
    mu = 0.3

    def chord(a, b):
        return 2.0 * b * np.sqrt(np.clip(1.0 - (x / a) ** 2, 0.0, None))

    wide, narrow = mu * chord(1.5, 0.5), mu * chord(0.5, 1.5)
    for profile in (wide, narrow):
        assert integrated_absorbance(x, profile, 2.0) == pytest.approx(mu * np.pi * 1.5 * 0.5, rel=2e-3)
    # Both views' areas give the equivalent diameter of the ellipse, 2·√(a·b), not the widths' 3 and 1 mm.
    d = density_diameter(np.array([[integrated_absorbance(x, wide, 2.0)], [integrated_absorbance(x, narrow, 2.0)]]),
                         [mu, mu])
    assert d[0] == pytest.approx(2.0 * np.sqrt(1.5 * 0.5), rel=2e-3)


def test_integrated_absorbance_needs_background_on_both_sides():
    x = np.arange(-2.0, 2.0, 0.1)
    assert integrated_absorbance(x, np.ones_like(x), 1.9) is None


def test_density_diameter_of_a_simulated_tube_after_calibrating_each_view(tube_frames):
    realistic, points, tangents = tube_frames
    psf = AngiogramSettings().psf_sigma_mm
    per_view, attenuations = [], []
    for frame, mask, view in zip(realistic.frames, realistic.masks, VIEWS):
        guesses = projected_widths(points, tangents, mask, view)
        widths = frame_widths(points, tangents, frame, view, guesses, psf_sigma_mm=psf)
        d = densities(points, tangents, frame, view, guesses, psf_sigma_mm=psf)
        assert np.isfinite(d).all() and (d > 0).all()
        attenuations.append(attenuation_per_mm(d, widths, np.ones(len(points), bool)))
        per_view.append(d)
    # The same iodine seen by two views of the same system: the same attenuation per mm of lumen.
    assert attenuations[0] == pytest.approx(attenuations[1], rel=0.1)
    diameter = density_diameter(np.stack(per_view), attenuations)
    assert np.mean(np.abs(diameter - 2.0)) < 0.1  # the bar for healthy diameters is 0.15 mm


def test_calibration_and_diameter_without_enough_points():
    d = np.array([1.0, 2.0, np.nan, 3.0])
    assert attenuation_per_mm(d, np.ones(4), np.ones(4, bool)) is None  # 3 usable points
    out = density_diameter(np.array([[1.0, np.nan], [np.nan, np.nan]]), [0.5, None])
    assert out[0] == pytest.approx(np.sqrt(4 * 2.0 / np.pi)) and np.isnan(out[1])


def test_density_diameter_averages_the_usable_views_where_one_has_an_area():
    mu = 0.25
    wide, narrow = mu * np.pi * 3.0 ** 2 / 4, mu * np.pi * 2.0 ** 2 / 4
    d = np.array([[wide, wide, wide, np.nan], [narrow, narrow, narrow, narrow]])
    usable = np.array([[True, False, False, False], [True, True, False, False]])
    out = density_diameter(d, [mu, mu], usable)
    # both usable: the mean area; view 0 crowded: view 1 alone; neither: both (as without ``usable``);
    # the only view with an area not usable: it still gives the area
    assert out == pytest.approx([np.sqrt((9.0 + 4.0) / 2), 2.0, np.sqrt((9.0 + 4.0) / 2), 2.0])


def test_the_edges_diameter_leaves_a_crowded_view_out_where_another_has_a_width():
    from SDFCARLib.analysis.diameter import ellipse_diameter
    from SDFCARLib.analysis.pipeline import _uncrowded_widths

    widths = np.array([[4.0, 4.0, 4.0, np.nan], [2.0, 2.0, 2.0, 2.0]])
    crowded = np.array([[False, True, True, False], [False, False, True, True]])
    # none crowded: the ellipse of both; view 1 crowded: view 2's width; both crowded: both; the only width crowded: kept
    assert ellipse_diameter(_uncrowded_widths(widths, crowded)) == pytest.approx([np.sqrt(8.0), 2.0, np.sqrt(8.0), 2.0])


def test_other_vessel_clearance_is_the_projected_gap_to_the_other_vessels_edge():
    from SDFCARLib.analysis.views import other_vessel_clearance

    view = VIEWS[0]  # LAO 30, no angulation: the z axis lies in the detector plane, along its rows
    z = np.linspace(-10.0, 10.0, 21)
    a = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    u = np.asarray(view.column_direction)
    magnification = view.sid_mm / view.sod_mm  # both tubes at the isocenter's depth
    beside = a + 8.0 * u  # 8 mm to the side in the image, radius 1.2 mm
    clearance = other_vessel_clearance(a, 1.0, beside, 1.2, view)
    middle = len(z) // 2  # on the central row the perspective adds nothing to the lateral distance
    assert clearance[middle] == pytest.approx((8.0 - 1.2) * magnification, rel=1e-6)
    assert np.all(clearance >= (8.0 - 1.2) * magnification - 1e-9)
    behind = a[middle] + 30.0 * np.asarray(view.detector_direction)  # on the central ray, 30 mm deeper
    assert other_vessel_clearance(a[middle:middle + 1], 1.0, behind[None], 1.2, view)[0] < 0  # it overlaps
    touching = a + 2.5 * u  # within attach_mm (2) + both radii in 3D: the vessel's own continuation or mouth
    assert np.all(np.isinf(other_vessel_clearance(a, 1.0, touching, 1.2, view)))
    assert np.all(np.isinf(other_vessel_clearance(a, 1.0, np.zeros((0, 3)), np.zeros(0), view)))


def test_a_neighbour_in_one_views_window_is_left_out_of_the_density(tube_pair_frames):
    """Two parallel 3 mm tubes 20 mm apart that LAO 30 sees 3–4 mm apart and RAO 30 far apart: in LAO 30 the
    neighbour lies in the measuring window and its iodine raises the background; the density is then RAO 30's."""
    from SDFCARLib.analysis.pipeline import crowded_in_view

    realistic, points, tangents, neighbour = tube_pair_frames
    psf = AngiogramSettings().psf_sigma_mm
    per_view, crowded, calibrations = [], [], []
    for frame, mask, view in zip(realistic.frames, realistic.masks, VIEWS):
        guesses = projected_widths(points, tangents, mask, view)
        per_view.append(densities(points, tangents, frame, view, guesses, psf_sigma_mm=psf))
        crowded.append(crowded_in_view(points, 1.5, neighbour, 1.5, view, guesses, psf))  # the pipeline's rule
        widths = frame_widths(points, tangents, frame, view, guesses, psf)
        calibrations.append(attenuation_per_mm(per_view[-1], widths, ~crowded[-1]))
    crowded = np.array(crowded)
    assert crowded[0].all() and not crowded[1].any()
    assert calibrations[0] is None  # no uncrowded point to calibrate LAO 30 on
    mu = [calibrations[1]] * 2  # one system, one iodine: the same attenuation (the test above)
    both = density_diameter(np.stack(per_view), mu)
    chosen = density_diameter(np.stack(per_view), mu, ~crowded)
    assert np.mean(both) < 3.0 - 0.3  # the neighbour's iodine in the background reads the tube narrow
    assert np.mean(np.abs(chosen - 3.0)) < 0.1


@pytest.fixture(scope="module")
def tube_pair_frames():
    from SDFCARLib.analysis.phantoms import grid_around, voxelize_exact
    from SDFCARLib.geometry import Geometry
    from SDFCARLib.phantoms import Branch, CentrelineTree
    from SDFCARLib.realistic import RealisticOptions, realistic_input

    axis = np.array([0.0, 0.15, 1.0]) / np.hypot(0.15, 1.0)
    angle = np.radians(108.5)  # the pair's offset: nearly along LAO 30's rays, across RAO 30's
    offset = 20.0 * np.array([np.cos(angle), np.sin(angle), 0.0])
    s = np.linspace(-15.0, 15.0, 31)
    first, second = s[:, None] * axis - offset / 2, s[:, None] * axis + offset / 2
    tree = CentrelineTree([Branch(first, np.full(len(s), 1.5), "a"), Branch(second, np.full(len(s), 1.5), "b")], "pair")
    grid = grid_around(tree, 0.2)
    realistic = realistic_input(voxelize_exact(tree, grid), Geometry(grid, VIEWS), 3,
                                RealisticOptions(max_shift_mm=0.0, max_rotation_deg=0.0))
    inner = np.linspace(-10.0, 10.0, 21)[:, None] * axis - offset / 2  # clear of the flat ends
    return realistic, inner, np.repeat(axis[None], len(inner), axis=0), second


def test_same_lesion_on_another_profile_is_the_one_inside_the_lesions_extent():
    from SDFCARLib.analysis.lesion import Lesion, same_lesion_on

    s = np.arange(0.0, 80.0, 0.25)
    diameter = 3.0 - 1.5 * np.exp(-0.5 * ((s - 20.0) / 2.0) ** 2) - 0.9 * np.exp(-0.5 * ((s - 60.0) / 2.0) ** 2)
    usable = np.ones(s.shape, bool)
    at_20 = Lesion(1.6, 21.0, 3.0, 47.0, 72.0, 17.0, 24.0, 7.0)
    same = same_lesion_on(s, diameter, usable, at_20)
    assert same is not None and same.mld_position_mm == pytest.approx(20.0, abs=0.3)
    assert same.diameter_stenosis_pct == pytest.approx(50.0, abs=2.0)  # find_lesions smooths by 0.5 mm: 48.3
    at_40 = Lesion(2.0, 40.0, 3.0, 33.0, 55.0, 37.0, 43.0, 6.0)
    assert same_lesion_on(s, diameter, usable, at_40) is None  # the frames see no narrowing there
    assert same_lesion_on(s[:2], diameter[:2], usable[:2], at_20) is None  # too few points for a reference


def test_a_short_bump_of_the_reconstruction_inside_a_long_lesion_of_the_frames_is_that_lesion():
    from SDFCARLib.analysis.lesion import Lesion, same_lesion_on
    from SDFCARLib.analysis.phantoms import lesion_weight

    s = np.arange(0.0, 40.0, 0.25)
    frames = 3.0 * (1 - 0.5 * lesion_weight(s - 12.5, 15.0))  # 50 % over 12.5–27.5 mm
    bump = Lesion(2.2, 14.0, 3.0, 27.0, 46.0, 13.5, 14.5, 1.0)  # the 3D sections' reading, near one end
    same = same_lesion_on(s, frames, np.ones(s.shape, bool), bump)
    assert same is not None and same.diameter_stenosis_pct == pytest.approx(50.0, abs=2.0)
    assert same.start_mm < 14.0 < same.end_mm and same.length_mm == pytest.approx(15.0, abs=2.0)
    apart = Lesion(2.2, 6.0, 3.0, 27.0, 46.0, 5.5, 6.5, 1.0)  # a bump outside it is another lesion
    assert same_lesion_on(s, frames, np.ones(s.shape, bool), apart) is None


def test_frames_that_read_another_vessel_over_a_lesion_are_left_out_and_the_lesion_keeps_its_length():
    """A side branch whose first millimetres run back beside a lesion's distal half in both views (RESULTS §54b):
    the frames read the lumen 2.5 mm wider there than the 3D sections, which ends the frames' lesion halfway.
    Left out where they exceed 1.4 × the sections, the profile is bridged across and the lesion keeps its
    10 mm; a frames' reading 30 % over the sections stays. (The rule is off by default: FRAMES_MAX_OVER_3D.)"""
    from SDFCARLib.analysis.lesion import find_lesions, reference_fit
    from SDFCARLib.analysis.phantoms import lesion_weight
    from SDFCARLib.analysis.pipeline import left_out_beyond_sections

    s = np.arange(0.0, 40.0, 0.25)
    lumen = 3.0 * (1 - 0.5 * lesion_weight(s - 15.0, 10.0))  # 50 % over 15–25 mm
    sections = lumen + 0.3  # a reconstruction reads a little wide
    frames = lumen + np.where((s > 20.0) & (s < 25.0), 2.5, 0.0)

    def lesion_length(values):
        usable = np.isfinite(values)
        found = find_lesions(s, values, reference_fit(s, values, usable), usable)
        return max(found, key=lambda x: x.diameter_stenosis_pct).length_mm

    assert lesion_length(frames) < 7.0  # the trap is real
    kept = left_out_beyond_sections(frames, sections, max_ratio=1.4)
    assert np.isnan(kept[(s > 20.5) & (s < 24.5)]).all() and np.isfinite(kept[s <= 20.0]).all()
    assert lesion_length(kept) == pytest.approx(10.0, abs=1.0)
    wide = 1.3 * sections
    assert np.array_equal(left_out_beyond_sections(wide, sections, max_ratio=1.4), wide)
    assert np.array_equal(left_out_beyond_sections(frames, sections), frames)  # off by default


def _tube_frames(stenosis_pct: float, seed: int = 4):
    """A 3 mm tube (50 % lesion over 8 mm, or healthy), its simulated angiograms and segmented masks."""
    from SDFCARLib.analysis.phantoms import grid_around, stenosed_tube, straight_tube, voxelize_exact
    from SDFCARLib.geometry import Geometry
    from SDFCARLib.realistic import RealisticOptions, realistic_input

    direction = (0.2, 0.25, 1.0)
    tube = (stenosed_tube(length_mm=30.0, diameter_mm=3.0, stenosis_pct=stenosis_pct, lesion_length_mm=8.0,
                          direction=direction) if stenosis_pct else straight_tube(30.0, 3.0, direction))
    fine = grid_around(tube.tree, 0.2)
    return tube, realistic_input(voxelize_exact(tube.tree, fine), Geometry(fine, VIEWS), seed,
                                 RealisticOptions(max_shift_mm=0.0, max_rotation_deg=0.0))


@pytest.fixture(scope="module")
def stenosed_tube_frames():
    return _tube_frames(50.0)


def _analyse(tube, realistic, frames=True):
    from SDFCARLib.analysis.phantoms import grid_around, voxelize_exact
    from SDFCARLib.analysis.pipeline import analyse_volume

    grid = grid_around(tube.tree, 0.3)
    return analyse_volume(voxelize_exact(tube.tree, grid).astype(np.float32), grid, views=VIEWS, masks=realistic.masks,
                          frames=realistic.frames if frames else None, ostium_mm=tube.truth["ostium_mm"], best_view=False,
                          psf_sigma_mm=AngiogramSettings().psf_sigma_mm)


def test_analysis_reports_each_lesion_as_the_frames_measure_it_and_grades_it_on_their_density(stenosed_tube_frames):
    from SDFCARLib.analysis.outputs import analysis_summary_lines
    from SDFCARLib.analysis.pipeline import summary

    tube, realistic = stenosed_tube_frames
    data = summary(_analyse(tube, realistic))
    lesions = data["lesions"]
    assert len(lesions) == 1
    on_frames = lesions[0]["frames"]
    assert set(on_frames) == {"edges", "density"}
    for source in ("edges", "density"):
        assert on_frames[source]["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0), source
        assert on_frames[source]["mld_mm"] == pytest.approx(1.5, abs=0.3), source
    assert lesions[0]["grade"] == dict(on_frames["density"], source="frames (density)")
    assert lesions[0]["seen_on_frames"] is True and data["warnings"] == []
    line = analysis_summary_lines(data)[1]
    assert f"DS {on_frames['density']['diameter_stenosis_pct']:.0f}%" in line and "graded on the frames (density)" in line
    assert f"3D sections DS {lesions[0]['diameter_stenosis_pct']:.0f}%" in line  # the other measures beside it
    without = summary(_analyse(tube, realistic, frames=False))["lesions"]
    assert without[0]["frames"] is None and without[0]["seen_on_frames"] is None
    graded = without[0]["grade"]
    assert graded.pop("source") == "3D sections"
    assert graded == {k: without[0][k] for k in graded}  # the 3D sections' own measures


def test_a_lesion_on_the_frames_keeps_its_reference_where_side_strands_exclude_the_sections():
    # A rough reconstruction's side strands mark most of a branch as junction zones; the 3D sections must
    # leave those out, but the frames' profile keeps them, else its reference runs through the lesion.
    from SDFCARLib.analysis.centreline import CentrelineBranch
    from SDFCARLib.analysis.lesion import Lesion, same_lesion_on
    from SDFCARLib.analysis.pipeline import BranchProfile, lesion_on_2d_profile

    s = np.arange(0.0, 40.0, 0.25)
    points = np.stack([s, np.zeros_like(s), np.zeros_like(s)], axis=1)
    branch = CentrelineBranch(branch_id=0, points_mm=points, inscribed_radius_mm=np.full(len(s), 1.5))
    frames = 3.0 - 2.1 * np.exp(-0.5 * ((s - 20.0) / 2.5) ** 2)  # a 70 % lesion at 20 mm
    excluded = (s > 24.0) | ((s > 10.0) & (s < 15.0))  # junction zones of side strands
    profile = BranchProfile(branch, sections=None, excluded=excluded)
    lesion = Lesion(0.9, 20.0, 3.0, 70.0, 91.0, 15.0, 25.0, 10.0)
    same = lesion_on_2d_profile(profile, frames, lesion)
    assert same is not None and same.reference_diameter_mm == pytest.approx(3.0, abs=0.1)
    assert same.diameter_stenosis_pct == pytest.approx(70.0, abs=3.0)
    assert lesion_on_2d_profile(profile, None, lesion) is None
    # Left out like the 3D sections, the reference would be fitted to the stretch before 10 mm and the throat.
    old = same_lesion_on(s, frames, ~excluded, lesion)
    assert old is None or old.diameter_stenosis_pct < 60.0


def _straight_branch_with_a_lesion():
    """A straight 3 mm branch, a 60 % lesion at 20 mm as the 3D sections found it, its profile (no 2D
    measures yet), and a narrowed and a healthy 2D diameter profile along it."""
    from SDFCARLib.analysis.centreline import CentrelineBranch
    from SDFCARLib.analysis.lesion import Lesion
    from SDFCARLib.analysis.pipeline import BranchProfile

    s = np.arange(0.0, 40.0, 0.25)
    branch = CentrelineBranch(branch_id=0, points_mm=np.stack([s, 0 * s, 0 * s], axis=1),
                              inscribed_radius_mm=np.full(len(s), 1.5))
    narrowed = 3.0 - 1.8 * np.exp(-0.5 * ((s - 20.0) / 2.5) ** 2)  # 60 % at 20 mm
    lesion = Lesion(1.2, 20.0, 3.0, 60.0, 84.0, 15.0, 25.0, 10.0)
    return s, BranchProfile(branch, sections=None, excluded=np.zeros(len(s), bool)), lesion, narrowed, np.full(len(s), 3.0)


def test_a_lesion_is_graded_on_the_density_else_the_edges_else_the_3d_sections():
    from SDFCARLib.analysis.pipeline import lesion_grade

    _, profile, lesion, narrowed, healthy = _straight_branch_with_a_lesion()
    assert (lesion_grade(profile, lesion).source, lesion_grade(profile, lesion).seen_on_frames) == ("3D sections", None)
    profile.frame_diameter_mm, profile.frame_density_diameter_mm = 1.1 * narrowed, narrowed
    grade = lesion_grade(profile, lesion)
    assert grade.source == "frames (density)" and grade.measure.diameter_stenosis_pct == pytest.approx(60.0, abs=3.0)
    profile.frame_density_diameter_mm = healthy  # the density sees nothing there: the edges grade it
    assert lesion_grade(profile, lesion).source == "frames (edges)"
    profile.frame_diameter_mm = healthy
    grade = lesion_grade(profile, lesion)
    assert grade.source == "3D sections" and grade.measure is lesion and grade.seen_on_frames is False


def test_one_lesion_of_the_frames_is_reported_once_as_the_3d_bump_that_narrows_most():
    from SDFCARLib.analysis.lesion import Lesion, ReferenceFit
    from SDFCARLib.analysis.pipeline import frames_lesions, lesion_grade

    s, profile, _, narrowed, _ = _straight_branch_with_a_lesion()
    profile.frame_diameter_mm, profile.frame_density_diameter_mm = narrowed, narrowed
    profile.reference = ReferenceFit(3.0, 0.0, np.ones(len(s), bool))
    before = Lesion(2.2, 17.0, 3.0, 27.0, 46.0, 16.5, 17.5, 1.0)  # two bumps of a rough reconstruction
    after = Lesion(2.0, 23.0, 3.0, 33.0, 55.0, 22.5, 23.5, 1.0)  # inside the frames' 60 % lesion at 20 mm
    elsewhere = Lesion(2.1, 33.0, 3.0, 30.0, 51.0, 32.0, 34.0, 2.0)  # the frames show nothing there
    profile.lesions = [before, after, elsewhere]
    frames_lesions(profile, 20.0)
    assert profile.lesions == [after, elsewhere] and profile.frames_only == []
    assert lesion_grade(profile, after).measure.mld_position_mm == pytest.approx(20.0, abs=0.5)
    assert lesion_grade(profile, elsewhere).source == "3D sections"


def test_a_lesion_the_frames_show_and_the_reconstruction_does_not_is_reported_from_the_frames(tmp_path, stenosed_tube_frames):
    import importlib.util

    from SDFCARLib.analysis.outputs import analysis_summary_lines
    from SDFCARLib.analysis.phantoms import grid_around, stenosed_tube, voxelize_exact
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    # The frames and masks of a tube with a 50 % lesion over 8 mm; a reconstruction too smooth to narrow
    # there by the 20 % of a lesion, as a fit to segmented masks narrows a 30 % lesion by 14 % (RESULTS §45).
    stenosed, realistic = stenosed_tube_frames
    smoothed = stenosed_tube(length_mm=30.0, diameter_mm=3.0, stenosis_pct=15.0, lesion_length_mm=8.0,
                             direction=(0.2, 0.25, 1.0))
    grid = grid_around(smoothed.tree, 0.3)

    def analysed(frames):
        return analyse_volume(voxelize_exact(smoothed.tree, grid).astype(np.float32), grid, views=VIEWS,
                              masks=realistic.masks, frames=realistic.frames if frames else None,
                              ostium_mm=stenosed.truth["ostium_mm"], best_view=False,
                              psf_sigma_mm=AngiogramSettings().psf_sigma_mm)

    assert summary(analysed(False))["lesions"] == []  # the 3D sections alone find none
    result = analysed(True)
    data = summary(result)
    assert len(data["lesions"]) == 1
    lesion = data["lesions"][0]
    grade = lesion["grade"]
    assert lesion["found_on"] == "frames" and grade["source"] == "frames (density)"
    assert grade["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0)
    assert grade["length_mm"] == pytest.approx(stenosed.truth["lesion_length_mm"], abs=2.0)
    assert 10.0 <= lesion["diameter_stenosis_pct"] < 20.0  # the 3D sections over the frames' extent
    assert (lesion["start_mm"], lesion["end_mm"]) == (grade["start_mm"], grade["end_mm"])
    assert lesion["missed_in_3d"] == "narrows less"
    [warning] = [w for w in data["warnings"] if "found on the frames only" in w]
    assert "branch 0" in warning and "narrow there less than a lesion" in warning and "finer grid" not in warning
    line = analysis_summary_lines(data)[1]
    assert "found on the frames only (the 3D sections narrow there less than a lesion)" in line
    if importlib.util.find_spec("slicer") is not None:
        assert _qca_table(tmp_path / "frames", result, data).GetColumnByName("found_on").GetValue(0) == "frames"


def test_a_lesion_of_the_frames_that_the_3d_sections_narrow_as_much_but_do_not_resolve_is_not_said_to_narrow_less(
        stenosed_tube_frames):
    from SDFCARLib.analysis.outputs import analysis_summary_lines
    from SDFCARLib.analysis.phantoms import grid_around, voxelize_exact
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    # The exact 50 % lesion on a 1.25 mm grid: the 3 mm tube spans under 2.5 voxels, so the 3D sections narrow
    # there by far more than a lesion but report none. The messages said "the 3D sections narrow less there".
    stenosed, realistic = stenosed_tube_frames
    grid = grid_around(stenosed.tree, 1.25)
    data = summary(analyse_volume(voxelize_exact(stenosed.tree, grid).astype(np.float32), grid, views=VIEWS,
                                  masks=realistic.masks, frames=realistic.frames, ostium_mm=stenosed.truth["ostium_mm"],
                                  best_view=False, psf_sigma_mm=AngiogramSettings().psf_sigma_mm))
    [lesion] = data["lesions"]
    assert lesion["found_on"] == "frames" and lesion["diameter_stenosis_pct"] >= 30.0
    assert lesion["missed_in_3d"] == "unresolved" and lesion["reference_diameter_mm"] < 2.5 * 1.25
    [warning] = [w for w in data["warnings"] if "found on the frames only" in w]
    line = analysis_summary_lines(data)[1]
    for message in (warning, line):
        assert "narrow there too" in message and "2.5 voxels" in message and "less" not in message
    assert "finer grid" in warning


def test_a_narrowing_of_the_frames_that_a_healthy_reconstruction_does_not_show_is_counted_not_reported(
        stenosed_tube_frames):
    from SDFCARLib.analysis.phantoms import grid_around, straight_tube, voxelize_exact
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    # The frames narrow where the volume, fitted to the same views, does not at all: on a tree, what a
    # crossing or a neighbouring branch does to a view's profile (RESULTS §45).
    stenosed, realistic = stenosed_tube_frames
    healthy = straight_tube(30.0, 3.0, (0.2, 0.25, 1.0))
    grid = grid_around(healthy.tree, 0.3)
    data = summary(analyse_volume(voxelize_exact(healthy.tree, grid).astype(np.float32), grid, views=VIEWS,
                                  masks=realistic.masks, frames=realistic.frames, ostium_mm=stenosed.truth["ostium_mm"],
                                  best_view=False, psf_sigma_mm=AngiogramSettings().psf_sigma_mm))
    assert data["lesions"] == [] and data["unreliable_lesions"] == []
    assert not any("found on the frames only" in w for w in data["warnings"])
    assert [b["narrowings_2d_unconfirmed"] for b in data["branches"]] == [1]


@pytest.mark.parametrize("frames_centre_mm, dip_sd_mm, sections_3d, crowded, found", [
    (20.0, 1.5, "narrowed 15 % with the frames", "", True),  # smoothed under the lesion threshold, not erased
    (20.0, 1.5, "healthy", "", False),                          # the frames narrow alone
    (20.0, 1.5, "narrowed 8 % with the frames", "", False),     # under half the threshold
    (36.0, 1.5, "cut short in the end cap", "", False),         # the rounded end of a vessel is no lesion
    (36.0, 1.5, "narrowed 15 % with the frames", "", True),     # near the end, but the sections outside the cap narrow
    (20.0, 0.3, "narrowed 15 % with the frames", "", False),    # ~1 mm long on a 3 mm vessel: shorter than its diameter
    (20.0, 1.5, "narrowed 15 % with the frames", "1", True),   # another vessel beside it in one view: the other sees it
    (20.0, 1.5, "narrowed 15 % with the frames", "1+2", False),  # … in both views at the throat: neither measures it
])
def test_a_lesion_of_the_frames_alone_needs_the_3d_sections_to_narrow_a_diameter_of_length_and_a_clear_view(
        frames_centre_mm, dip_sd_mm, sections_3d, crowded, found):
    from SDFCARLib.analysis.centreline import CentrelineBranch
    from SDFCARLib.analysis.diameter import CrossSections
    from SDFCARLib.analysis.lesion import ReferenceFit
    from SDFCARLib.analysis.pipeline import BranchProfile, frames_lesions

    s = np.arange(0.0, 40.0, 0.25)  # a root branch: its free-end caps are its first and last 3 mm
    branch = CentrelineBranch(branch_id=0, points_mm=np.stack([s, 0 * s, 0 * s], axis=1),
                              inscribed_radius_mm=np.full(len(s), 1.5))
    bump = np.exp(-0.5 * ((s - frames_centre_mm) / dip_sd_mm) ** 2)
    sections_mm = {"healthy": np.full(len(s), 3.0), "narrowed 15 % with the frames": 3.0 * (1 - 0.15 * bump),
                   "narrowed 8 % with the frames": 3.0 * (1 - 0.08 * bump),
                   "cut short in the end cap": np.where(s > 37.5, 1.5, 3.0)}[sections_3d]
    sections = CrossSections(np.pi * sections_mm ** 2 / 4, sections_mm, sections_mm, sections_mm)
    profile = BranchProfile(branch, sections, np.zeros(len(s), bool))
    profile.reference = ReferenceFit(3.0, 0.0, np.ones(len(s), bool))
    profile.frame_diameter_mm = profile.frame_density_diameter_mm = 3.0 * (1 - 0.5 * bump)  # 50 % on the frames
    profile.frame_views_crowded = np.zeros((2, len(s)), bool)
    for view in crowded.split("+") if crowded else ():
        profile.frame_views_crowded[int(view) - 1] = np.abs(s - frames_centre_mm) < 2.0
    frames_lesions(profile, 20.0)
    assert (len(profile.frames_only), profile.unconfirmed) == ((1, 0) if found else (0, 1))
    if found:
        assert profile.frames_only[0].mld_position_mm == pytest.approx(frames_centre_mm, abs=0.5)


def _qca_table(folder, result, data):
    """The Slicer "… QCA" table of an analysis written to ``folder``."""
    import json

    from SDFCARLib.analysis.mrml_nodes import add_analysis_nodes
    from SDFCARLib.analysis.outputs import profile_csv_text
    from SDFCARLib.mrml import new_scene

    folder.mkdir()
    (folder / "analysis.json").write_text(json.dumps(data), encoding="utf-8")
    for p in result.profiles:
        (folder / f"profile_branch{p.branch.branch_id:02d}.csv").write_text(profile_csv_text(result, p.branch.branch_id))
    return add_analysis_nodes(new_scene(), folder)["table"].GetTable()


def test_the_slicer_qca_table_carries_the_grade_and_the_3d_measure(tmp_path, stenosed_tube_frames):
    pytest.importorskip("slicer", reason="needs the slicer-core package (pip install slicer-core)")
    from SDFCARLib.analysis.mrml_nodes import QCA_TABLE_COLUMNS
    from SDFCARLib.analysis.pipeline import summary

    result = _analyse(*stenosed_tube_frames)
    data = summary(result)
    table = _qca_table(tmp_path / "graded", result, data)
    assert [table.GetColumnName(i) for i in range(table.GetNumberOfColumns())] == list(QCA_TABLE_COLUMNS)
    lesion = data["lesions"][0]
    assert table.GetColumnByName("graded_on").GetValue(0) == "frames (density)"
    assert table.GetColumnByName("found_on").GetValue(0) == "3D sections"
    assert table.GetColumnByName("seen_on_frames").GetValue(0) == "yes"
    assert table.GetColumnByName("seen_on_masks").GetValue(0) == "yes"
    assert table.GetColumnByName("diameter_stenosis_pct").GetValue(0) == pytest.approx(lesion["grade"]["diameter_stenosis_pct"])
    assert table.GetColumnByName("mld_mm").GetValue(0) == pytest.approx(lesion["grade"]["mld_mm"])
    assert table.GetColumnByName("diameter_stenosis_3d_pct").GetValue(0) == pytest.approx(lesion["diameter_stenosis_pct"])


def test_a_narrowing_of_the_reconstruction_that_the_frames_do_not_show_is_warned_about(tmp_path):
    pytest.importorskip("slicer", reason="needs the slicer-core package (pip install slicer-core)")
    from SDFCARLib.analysis.outputs import analysis_summary_lines
    from SDFCARLib.analysis.pipeline import summary

    # A 3D volume with a 50 % lesion, the frames and masks of the same tube without one (a rough reconstruction).
    tube, _ = _tube_frames(50.0, seed=5)
    _, healthy = _tube_frames(0.0, seed=5)
    result = _analyse(tube, healthy)
    data = summary(result)
    lesion = data["lesions"][0]
    assert lesion["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0)
    assert lesion["seen_on_frames"] is False and lesion["grade"]["source"] == "3D sections"
    assert any("not seen on the frames" in w and "branch 0" in w for w in data["warnings"])
    assert "NOT seen on the frames" in analysis_summary_lines(data)[1]
    table = _qca_table(tmp_path / "unseen", result, data)
    assert table.GetColumnByName("graded_on").GetValue(0) == "3D sections"
    assert table.GetColumnByName("seen_on_frames").GetValue(0) == "no"
    assert table.GetColumnByName("seen_on_masks").GetValue(0) == "no"
    assert table.GetColumnByName("diameter_stenosis_3d_pct").GetValue(0) == pytest.approx(lesion["diameter_stenosis_pct"])
    assert table.GetColumnByName("diameter_stenosis_masks_pct").GetValue(0) == pytest.approx(lesion["masks_diameter_stenosis_pct"])


def test_a_lesion_is_seen_on_the_masks_when_either_view_or_their_diameter_narrows_there():
    from SDFCARLib.analysis.pipeline import lesion_grade, seen_on_masks

    s, profile, lesion, narrowed, healthy = _straight_branch_with_a_lesion()
    assert seen_on_masks(profile, lesion) is None  # no masks given
    profile.mask_diameter_mm, profile.view_widths_mm = healthy, np.stack([healthy, healthy])
    assert seen_on_masks(profile, lesion) is False
    assert lesion_grade(profile, lesion).seen_on_masks is False
    profile.view_widths_mm = np.stack([healthy, narrowed])  # an eccentric throat: one view sees it narrow
    assert seen_on_masks(profile, lesion) is True
    profile.view_widths_mm = np.stack([healthy, healthy])
    profile.mask_diameter_mm = narrowed
    assert seen_on_masks(profile, lesion) is True
    # elsewhere on the branch does not count
    profile.mask_diameter_mm = 3.0 - 1.8 * np.exp(-0.5 * ((s - 36.0) / 1.0) ** 2)
    assert seen_on_masks(profile, lesion) is False


def test_the_masks_stenosis_at_a_lesion_is_their_largest_narrowing_there():
    from SDFCARLib.analysis.pipeline import masks_stenosis_pct

    s, profile, lesion, narrowed, healthy = _straight_branch_with_a_lesion()
    assert masks_stenosis_pct(profile, lesion) is None  # no masks given
    profile.mask_diameter_mm, profile.view_widths_mm = healthy, np.stack([healthy, healthy])
    assert masks_stenosis_pct(profile, lesion) == 0.0
    mild = 3.0 - 0.75 * np.exp(-0.5 * ((s - 20.0) / 2.5) ** 2)  # 25 % at the lesion
    profile.view_widths_mm = np.stack([mild, healthy])
    assert masks_stenosis_pct(profile, lesion) == pytest.approx(25.0, abs=2.0)
    profile.mask_diameter_mm = narrowed  # the two-view diameter narrows 60 %: the largest counts
    assert masks_stenosis_pct(profile, lesion) == pytest.approx(60.0, abs=3.0)
    profile.mask_diameter_mm = 3.0 - 1.8 * np.exp(-0.5 * ((s - 36.0) / 1.0) ** 2)  # elsewhere on the branch
    assert masks_stenosis_pct(profile, lesion) == pytest.approx(25.0, abs=2.0)


def test_without_frames_a_narrowing_of_the_reconstruction_that_the_masks_do_not_show_is_warned_about(stenosed_tube_frames):
    from SDFCARLib.analysis.outputs import analysis_summary_lines
    from SDFCARLib.analysis.pipeline import summary

    # The masks of the stenosed tube show its lesion: no warning.
    data = summary(_analyse(*stenosed_tube_frames, frames=False))
    assert [d["seen_on_masks"] for d in data["lesions"]] == [True] and data["warnings"] == []
    shown = data["lesions"][0]["masks_diameter_stenosis_pct"]
    assert shown >= 20.0 and f"masks DS {shown:.0f}%" in analysis_summary_lines(data)[1]
    # A 3D volume with a 50 % lesion, masks of the same tube without one (a rough reconstruction's bump).
    tube, _ = _tube_frames(50.0, seed=5)
    _, healthy = _tube_frames(0.0, seed=5)
    data = summary(_analyse(tube, healthy, frames=False))
    lesion = data["lesions"][0]
    assert lesion["diameter_stenosis_pct"] == pytest.approx(50.0, abs=8.0)
    assert lesion["seen_on_frames"] is None and lesion["seen_on_masks"] is False
    assert lesion["masks_diameter_stenosis_pct"] < 20.0  # the healthy masks show (almost) no narrowing there
    assert lesion["grade"]["source"] == "3D sections"
    assert any("not seen on the masks" in w and "branch 0" in w for w in data["warnings"])
    assert "NOT seen on the masks" in analysis_summary_lines(data)[1]
    # With the frames, they decide (and the frames' warning is the one given).
    data = summary(_analyse(tube, healthy))
    assert data["lesions"][0]["seen_on_masks"] is False and data["lesions"][0]["seen_on_frames"] is False
    assert not any("not seen on the masks" in w for w in data["warnings"])


def test_a_throat_below_the_grids_resolution_is_warned_about_only_where_the_3d_sections_grade_it(stenosed_tube_frames):
    from SDFCARLib.analysis.phantoms import grid_around, voxelize_exact
    from SDFCARLib.analysis.pipeline import analyse_volume, summary

    tube, realistic = stenosed_tube_frames
    grid = grid_around(tube.tree, 0.6)  # the 1.5 mm throat is under 2.5 voxels (1.5 mm)

    def analysed(frames):
        return summary(analyse_volume(voxelize_exact(tube.tree, grid).astype(np.float32), grid, views=VIEWS,
                                      masks=realistic.masks, frames=realistic.frames if frames else None,
                                      ostium_mm=tube.truth["ostium_mm"], best_view=False,
                                      psf_sigma_mm=AngiogramSettings().psf_sigma_mm))

    def thin_throat_warnings(data):
        return [w for w in data["warnings"] if "minimal lumen under 2.5 voxels" in w]

    with_frames, without = analysed(True), analysed(False)
    assert [d["mld_below_resolution"] for d in with_frames["lesions"] + without["lesions"]] == [True, True]
    assert with_frames["lesions"][0]["grade"]["source"] != "3D sections"  # graded on the frames, which resolve it
    assert thin_throat_warnings(with_frames) == []
    assert without["lesions"][0]["grade"]["source"] == "3D sections"
    assert len(thin_throat_warnings(without)) == 1


def test_density_diameter_of_three_views_outvotes_the_one_that_disagrees():
    mu = 0.25
    area = lambda diameter_mm: mu * np.pi * diameter_mm ** 2 / 4  # noqa: E731
    # a 2 mm lumen; view 3 reads it 3 mm (another vessel's iodine no crowding rule caught) at the first point,
    # view 1 reads 1 mm at the second; at the third, view 2 is not usable and the other two disagree
    d = np.array([[area(2.0), area(1.0), area(2.0)],
                  [area(2.0), area(2.0), area(2.0)],
                  [area(3.0), area(2.0), area(3.0)]])
    usable = np.array([[True, True, True], [True, True, False], [True, True, True]])
    out = density_diameter(d, [mu, mu, mu], usable)
    assert out[:2] == pytest.approx([2.0, 2.0])  # the median area, not the mean's 2.38 / 1.73 mm
    assert out[2] == pytest.approx(np.sqrt((4.0 + 9.0) / 2))  # two usable views: their mean, as before
    # two views are unchanged: the mean area, to the last bit
    two = np.array([[area(3.0), area(2.5)], [area(2.0), np.nan]])
    assert np.array_equal(density_diameter(two, [mu, mu]), np.sqrt(4.0 * np.array([(two[0, 0] + two[1, 0]) / 2 / mu, two[0, 1] / mu]) / np.pi))
