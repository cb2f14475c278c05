"""Self-calibration of the views' poses (calibration.py): the searched direction, the composition of
motions and the search against closed forms; recovery of a known shift with a stand-in score."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.calibration import calibrate, epipolar_normal, moved, parabola_minimum, search_1d, search_axes, shifted
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid, rotation_matrix
from SDFCARLib.settings import ReconstructionError, make_settings


def _view(primary=30.0, secondary=0.0):
    return CArmView(primary, secondary, 1000.0, 750.0, (0.5, 0.5), (64, 64))


@pytest.fixture
def searches_once(monkeypatch):
    """``estimate_motions`` run once per distinct input: a test that calibrates the same frames several times, to
    compare what the steps after the search decide, does not repeat the search (deterministic). Returns the inputs
    searched."""
    from SDFCARLib import line_integral_consistency

    search, results, searched = line_integral_consistency.estimate_motions, {}, []

    def key_of(views, images, centre, *args, unseen=None, progress=None, **kwargs):
        arrays = [np.asarray(a) for a in images] + [np.asarray(u) for u in (unseen or ()) if u is not None]
        return (repr(views), tuple(a.tobytes() for a in arrays), tuple(np.asarray(centre, float)), args,
                tuple(sorted(kwargs.items())), tuple(u is None for u in (unseen or ())))

    def once(*args, **kwargs):
        key = key_of(*args, **kwargs)
        if key not in results:
            searched.append(key)
            results[key] = search(*args, **kwargs)
        return results[key]

    monkeypatch.setattr(line_integral_consistency, "estimate_motions", once)
    return searched


def test_epipolar_normal_is_perpendicular_to_both_viewing_directions():
    # LAO 30 / RAO 30: both directions in the axial plane, so the shift that crosses the epipolar
    # lines is cranio-caudal
    normal = epipolar_normal(_view(30.0), _view(-30.0))
    np.testing.assert_allclose(np.abs(normal), [0.0, 0.0, 1.0], atol=1e-12)
    a, b = _view(30.0, 20.0), _view(-40.0, -10.0)
    normal = epipolar_normal(a, b)
    assert abs(np.dot(normal, a.detector_direction)) < 1e-12 and abs(np.dot(normal, b.detector_direction)) < 1e-12
    assert np.linalg.norm(normal) == pytest.approx(1.0)
    assert epipolar_normal(a, _view(30.0, 20.0)) is None  # the same direction: nothing to search
    assert epipolar_normal(a, _view(31.0, 20.0)) is None  # 1° apart: below the 5° guard


def test_shifted_moves_the_object_before_the_motion_the_view_already_carries():
    view = _view().with_object_motion((0.0, 0.0, 10.0), (1.0, 2.0, 3.0))
    moved = shifted(view, np.array([0.0, -1.0, 0.5]))
    x = np.array([10.0, -20.0, 30.0])
    expected = rotation_matrix((0, 0, 10)) @ (x + [0, -1, 0.5]) + [1, 2, 3]
    got = rotation_matrix(moved.object_rotation_deg) @ x + np.asarray(moved.object_translation_mm)
    np.testing.assert_allclose(got, expected, atol=1e-9)
    # a view without motion: the shift is its translation
    np.testing.assert_allclose(shifted(_view(), np.array([0, 0, 2.5])).object_translation_mm, [0, 0, 2.5])


def test_moved_turns_about_the_centre_before_the_motion_the_view_already_carries():
    view = _view().with_object_motion((0.0, 5.0, 0.0), (1.0, 2.0, 3.0))
    centre, rotation, translation = np.array([10.0, -5.0, 20.0]), np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.0, -0.7])
    result = moved(view, rotation, translation, centre)
    for x in (np.zeros(3), centre, np.array([40.0, 30.0, -25.0])):
        expected = rotation_matrix((0, 5, 0)) @ (rotation_matrix(rotation) @ (x - centre) + centre + translation) + [1, 2, 3]
        got = rotation_matrix(result.object_rotation_deg) @ x + np.asarray(result.object_translation_mm)
        np.testing.assert_allclose(got, expected, atol=1e-9)


def test_search_axes_are_orthonormal_and_tied_to_the_views():
    reference, view = _view(30.0, 20.0), _view(-40.0, -10.0)
    axes = search_axes(reference, view)
    np.testing.assert_allclose(axes["shift"], epipolar_normal(reference, view))
    np.testing.assert_allclose(axes["rotation_in_plane"], view.detector_direction, atol=1e-12)
    matrix = np.stack([axes["shift"], axes["rotation_in_plane"], axes["rotation_tilt"]])
    np.testing.assert_allclose(matrix @ matrix.T, np.eye(3), atol=1e-12)
    # the tilt axis lies in the view's image plane, along its epipolar lines with the reference
    assert abs(np.dot(axes["rotation_tilt"], view.detector_direction)) < 1e-12
    assert search_axes(reference, _view(30.0, 20.0)) is None


def test_search_1d_finds_a_parabola_vertex_and_flags_the_range_end():
    calls = []

    def loss(x):
        calls.append(x)
        return (x - 1.1) ** 2
    value, scores, at_edge = search_1d(loss, 3.0, 5)
    assert value == pytest.approx(1.1) and not at_edge and len(calls) == len(scores) == 7
    value, _, at_edge = search_1d(lambda x: -x, 3.0, 5)
    assert value == 3.0 and at_edge


def test_parabola_minimum():
    xs = [0.0, 1.0, 2.0]
    assert parabola_minimum(xs, [(x - 1.3) ** 2 + 5 for x in xs]) == pytest.approx(1.3)
    assert parabola_minimum(xs, [-(x - 1.0) ** 2 for x in xs]) in xs  # concave: the best sample
    assert parabola_minimum(xs, [3.0, 2.0, 1.0]) <= 2.0  # the vertex is kept within the samples


def test_calibrate_finds_the_shift_of_a_known_minimum_and_keeps_view_one():
    grid = VolumeGrid((16, 16, 16), (1.0, 1.0, 1.0))
    geometry = Geometry(grid, (_view(30.0), _view(-30.0), _view(0.0, 30.0)))
    true_mm = {1: 1.7, 2: -2.6}
    calls = []

    def score(candidate: Geometry) -> float:
        # a stand-in for the re-fitted loss: quadratic in each view's shift along its searched direction
        calls.append(candidate)
        total = 0.0
        for k, want in true_mm.items():
            normal = epipolar_normal(candidate.views[0], geometry.views[k])
            total += (float(np.dot(candidate.views[k].object_translation_mm, normal)) - want) ** 2
        return total

    settings = make_settings("fast", calibrate=True, calibration_rotation_range_deg=0.0)  # the shift alone
    result = calibrate(geometry, [np.zeros((64, 64))] * 3, settings, "mask", score=score)
    assert result.geometry.views[0] == geometry.views[0]
    for k, want in true_mm.items():
        normal = epipolar_normal(geometry.views[0], geometry.views[k])
        found = np.asarray(result.geometry.views[k].object_translation_mm)
        assert float(np.dot(found, normal)) == pytest.approx(want, abs=1e-6)
        np.testing.assert_allclose(found, want * normal, atol=1e-6)  # nothing along other directions
        assert result.views[k - 1]["shift_mm"] == pytest.approx(want, abs=1e-3)
    assert len(calls) == 2 * (settings.calibration.calibration_candidates + 2)
    assert result.report()["views"][0]["view"] == 2


def test_calibration_settings_are_checked():
    with pytest.raises(ReconstructionError, match="calibration_candidates"):
        make_settings("fast", calibrate=True, calibration_candidates=2).validate()


def test_a_minimum_at_the_end_of_the_range_leaves_the_view_as_given_and_warns():
    geometry = Geometry(VolumeGrid((16, 16, 16), (1.0, 1.0, 1.0)), (_view(30.0), _view(-30.0)))
    normal = epipolar_normal(geometry.views[0], geometry.views[1])

    def score(candidate: Geometry) -> float:  # keeps falling beyond the range's end
        return -float(np.dot(candidate.views[1].object_translation_mm, normal))

    settings = make_settings("fast", calibrate=True, calibration_rotation_range_deg=0.0)
    result = calibrate(geometry, [np.zeros((64, 64))] * 2, settings, "mask", score=score)
    assert result.geometry.views[1].object_translation_mm == (0.0, 0.0, 0.0)
    assert result.views[0]["shift_mm"] == 0.0
    (warning,) = result.warnings
    assert "view 2" in warning and "no minimum within ±4 mm" in warning and "left as given" in warning


def test_calibrate_finds_a_known_shift_and_rotations_of_each_view():
    grid = VolumeGrid((16, 16, 16), (1.0, 1.0, 1.0), (5.0, -3.0, 8.0))
    geometry = Geometry(grid, (_view(30.0), _view(-30.0), _view(0.0, 30.0)))
    centre = np.asarray(grid.center_mm)
    # per view: shift (mm), in-plane and tilt rotation (degrees), all within the default ranges
    truth = {1: (1.7, -1.2, 0.8), 2: (-2.6, 2.1, -0.4)}
    axes = {k: search_axes(geometry.views[0], geometry.views[k]) for k in truth}

    def motion_parameters(view, k):
        # the view's motion written as a turn about the centre then a shift: x → R (x − c) + c + s
        r = rotation_matrix(view.object_rotation_deg)
        shift = r @ centre + np.asarray(view.object_translation_mm) - centre
        vector = np.asarray(view.object_rotation_deg)
        return (float(shift @ axes[k]["shift"]), float(vector @ axes[k]["rotation_in_plane"]),
                float(vector @ axes[k]["rotation_tilt"]))

    def score(candidate: Geometry) -> float:  # a stand-in for the re-fitted loss, minimal at the truth
        return sum(float(np.sum((np.subtract(motion_parameters(candidate.views[k], k), want)) ** 2))
                   for k, want in truth.items())

    settings = make_settings("fast", calibrate=True, calibration_rotation_range_deg=3.0)
    result = calibrate(geometry, [np.zeros((64, 64))] * 3, settings, "mask", score=score)
    assert result.geometry.views[0] == geometry.views[0] and not result.warnings
    for k, want in truth.items():
        np.testing.assert_allclose(motion_parameters(result.geometry.views[k], k), want, atol=0.02)
        entry = result.views[k - 1]
        assert entry["shift"]["value"] == pytest.approx(want[0], abs=0.02)
        assert entry["rotation_in_plane"]["value"] == pytest.approx(want[1], abs=0.02)
        assert entry["rotation_tilt"]["value"] == pytest.approx(want[2], abs=0.02)
        np.testing.assert_allclose(entry["object_rotation_deg"], result.geometry.views[k].object_rotation_deg, atol=1e-3)
        # nothing along the axes two views cannot tell: the shift along the epipolar lines
        np.testing.assert_allclose(motion_parameters(result.geometry.views[k], k)[0] * axes[k]["shift"],
                                   rotation_matrix(entry["object_rotation_deg"]) @ centre
                                   + np.asarray(entry["object_translation_mm"]) - centre, atol=1e-3)


def test_benchmark_columns_compare_the_motion_found_with_the_simulated_one_about_the_same_centre():
    from SDFCARLib.benchmark.run import _calibration_columns

    reference, view = _view(30.0), _view(-30.0)
    axes = search_axes(reference, view)
    found = {"view": 2, "shift_mm": 1.1, "direction_lps": list(axes["shift"]), "rotation_centre_mm": [0.0, 10.0, 0.0],
             "rotation_in_plane": {"value": 0.4, "axis_lps": list(axes["rotation_in_plane"])},
             "rotation_tilt": {"value": -0.2, "axis_lps": list(axes["rotation_tilt"])}}
    # simulated: 2° about x (about the isocenter) and 1 mm along z; about the centre (0, 10, 0) the same
    # motion is that turn plus a shift of 1 + 10·sin 2° along z (n = ±z for LAO 30 / RAO 30)
    realistic = {"motion": [{}, {"rotation_deg": [2.0, 0.0, 0.0], "translation_mm": [0.0, 0.0, 1.0]}]}
    columns = _calibration_columns({"views": [found]}, realistic)
    assert columns["calibration_shift_mm_view2"] == 1.1 and columns["calibration_rotation_tilt_deg_view2"] == -0.2
    assert columns["true_shift_mm_view2"] == pytest.approx((1.0 + 10.0 * np.sin(np.radians(2.0))) * axes["shift"][2])
    assert columns["true_rotation_in_plane_deg_view2"] == pytest.approx(2.0 * axes["rotation_in_plane"][0])
    assert columns["true_rotation_tilt_deg_view2"] == pytest.approx(2.0 * axes["rotation_tilt"][0])
    assert _calibration_columns(None, realistic) == {}


def test_calibration_recovers_a_known_shift_on_a_small_reconstruction():
    # the real score (a field re-fitted per candidate) on a coarse clean case: view 2's object moved
    # 2.5 mm across the epipolar lines; the search must find it within the 0.5 mm
    from SDFCARLib.phantoms import rca_tree, simulate_views, voxelize

    grid = VolumeGrid((32, 32, 32), (3.2, 3.2, 3.2))
    views = tuple(CArmView(primary, 0.0, 1000.0, 757.0, (2.0, 2.0), (80, 80)) for primary in (30.0, -30.0))
    normal = epipolar_normal(*views)
    label = voxelize(rca_tree(0), grid)
    _, masks = simulate_views(label, grid, [views[0], shifted(views[1], 2.5 * normal)])
    settings = make_settings("fast", calibrate=True, calibration_steps=100)
    result = calibrate(Geometry(grid, views), masks, settings, "mask")
    (entry,) = result.views
    assert entry["shift_mm"] == pytest.approx(2.5, abs=0.5) and not result.warnings
    losses = dict(zip(entry["shift"]["candidates"], entry["shift"]["losses"]))
    assert min(losses, key=losses.get) in (2.0, 3.0) and losses[0.0] > 1.5 * min(losses.values())
    np.testing.assert_allclose(result.geometry.views[1].object_translation_mm, entry["shift_mm"] * normal, atol=1e-3)
    assert result.geometry.views[0] == views[0]


def test_calibrate_from_frames_corrects_the_motion_two_views_observe_and_says_what_it_cannot():
    from blob_phantom import VIEW_1, VIEW_2, blob_image
    from SDFCARLib.calibration import calibrate_from_frames

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    true_rotation, true_translation = np.array([0.7, 0.5, 0.0]), np.array([0.0, 0.0, -1.2])
    images = [blob_image(VIEW_1), blob_image(VIEW_2.with_object_motion(true_rotation, true_translation))]
    result = calibrate_from_frames(Geometry(grid, (VIEW_1, VIEW_2)), images)
    corrected = result.geometry.views[1]
    np.testing.assert_allclose(corrected.object_rotation_deg[:2], true_rotation[:2], atol=0.1)
    assert corrected.object_translation_mm[2] == pytest.approx(true_translation[2], abs=0.1)
    assert result.geometry.views[0] == VIEW_1  # the reference stays
    entry = result.views[0]
    assert entry["view"] == 2 and entry["consistency_after"] < 0.1 * entry["consistency_before"]
    assert entry["consistency_gain"] > 10 and "left_as_given" not in entry
    assert entry["shift_across"]["unit"] == "mm" and entry["rotation_about_baseline"]["unit"] == "deg"
    assert "shift_along_baseline" in entry["not_observed"]
    assert "consistency" in result.report()["method"] and not result.warnings
    assert entry["motion_found"] is True and result.motion_found() is True


def test_calibrate_from_frames_leaves_the_views_as_given_when_the_motion_found_explains_only_noise():
    from blob_phantom import VIEW_1, VIEW_2, blob_image
    from SDFCARLib.calibration import calibrate_from_frames

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    rng = np.random.default_rng(0)
    # no motion; noise lets the search lower the inconsistency a little with a spurious turn
    images = [np.clip(blob_image(view) + 0.05 * rng.standard_normal(view.detector_shape), 0.0, None) for view in (VIEW_1, VIEW_2)]
    geometry = Geometry(grid, (VIEW_1, VIEW_2))
    kept = calibrate_from_frames(geometry, images)
    (entry,) = kept.views
    assert 1.0 < entry["consistency_gain"] < 2.0
    assert kept.geometry.views == (VIEW_1, VIEW_2) and entry["left_as_given"] is True
    assert "more consistent" in entry["why_left_as_given"] and not kept.warnings  # the normal outcome without motion
    assert entry["motion_found"] is False and kept.motion_found() is False  # searched, and nothing beyond noise
    applied = calibrate_from_frames(geometry, images, min_consistency_gain=1.0)
    assert applied.geometry.views[1] != VIEW_2 and "left_as_given" not in applied.views[0]
    with pytest.raises(ReconstructionError, match="calibration_min_consistency_gain must be at least 1"):
        make_settings("fast", calibration_min_consistency_gain=0.5)


def test_calibrate_from_frames_with_three_views_matches_every_pair_and_reports_all_six_motions():
    from blob_phantom import VIEW_1, VIEW_2, VIEW_3, blob_image
    from SDFCARLib.calibration import calibrate_from_frames

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    views = (VIEW_1, VIEW_2, VIEW_3)
    images = [blob_image(VIEW_1), blob_image(VIEW_2.with_object_motion((0.0, 0.0, 0.0), (1.5, 0.0, 0.0))),
              blob_image(VIEW_3.with_object_motion((0.0, 0.0, 0.0), (0.0, 0.0, 0.8)))]
    result = calibrate_from_frames(Geometry(grid, views), images)
    assert result.geometry.views[0] == VIEW_1 and not result.warnings
    assert [entry["view"] for entry in result.views] == [2, 3]
    for entry, others, view in zip(result.views, ([1, 3], [1, 2]), result.geometry.views[1:]):
        assert entry["matched_with"] == others
        assert {"shift_along_baseline", "rotation_about_normal", "shift_in_depth", "shift_across"} <= set(entry)
        assert entry["consistency_after"] < 0.01 * entry["consistency_before"]
        assert "view 1's axis" in entry["not_observed"][0]
        np.testing.assert_allclose(view.object_translation_mm, entry["object_translation_mm"], atol=1e-4)
    # view 3 moved across both of its pairs' planes: found to a fraction of a millimetre
    assert result.geometry.views[2].object_translation_mm[2] == pytest.approx(0.8, abs=0.25)


def test_calibrate_from_frames_leaves_a_pose_beyond_its_range_as_given_and_warns():
    from blob_phantom import VIEW_1, VIEW_2, blob_image
    from SDFCARLib.calibration import FRAME_CALIBRATION_LIMITS, calibrate_from_frames

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    far = (0.0, 0.0, 2.0 * FRAME_CALIBRATION_LIMITS["mm"])  # across the epipolar planes, twice the range
    images = [blob_image(VIEW_1), blob_image(VIEW_2.with_object_motion((0.0, 0.0, 0.0), far))]
    result = calibrate_from_frames(Geometry(grid, (VIEW_1, VIEW_2)), images)
    assert result.geometry.views[1] == VIEW_2
    assert result.views[0]["left_as_given"] is True
    assert len(result.warnings) == 1 and "end of its range" in result.warnings[0] and "view 2" in result.warnings[0]
    assert "motion_found" not in result.views[0] and result.motion_found() is None  # not known: the pose is unsure


def _behind_a_shutter(image, shutter):
    return np.where(shutter, 0.0, image)  # the frame shows nothing where the collimator is


def test_a_turn_that_only_hides_what_a_collimator_cuts_is_not_applied_and_a_real_motion_still_is(searches_once):
    from blob_phantom import VIEW_1, VIEW_2, blob_image
    from SDFCARLib.calibration import calibrate_from_frames
    from SDFCARLib.line_integral_consistency import untruncated_gain

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    geometry = Geometry(grid, (VIEW_1, VIEW_2))
    shutter = np.zeros(VIEW_2.detector_shape, bool)
    shutter[-60:] = True  # view 2's lower collimator blade cuts blobs
    static = [blob_image(VIEW_1), _behind_a_shutter(blob_image(VIEW_2), shutter)]
    moved = [blob_image(VIEW_1), _behind_a_shutter(blob_image(VIEW_2.with_object_motion((0.0, 0.0, 0.0), (0.0, 0.0, 1.5))),
                                                   shutter)]

    # no motion: searched on every plane, the cut makes a turn look like a gain over the gate, as on collimated pairs
    blind = calibrate_from_frames(geometry, static)
    assert blind.views[0]["consistency_gain"] >= 2.0 and blind.geometry.views[1] != VIEW_2
    checked = calibrate_from_frames(geometry, static, confirm_unseen=[None, shutter])
    (entry,) = checked.views
    assert checked.geometry.views == (VIEW_1, VIEW_2) and entry["left_as_given"] is True
    assert entry["untruncated_consistency_gain"] < 1.5 and entry["untruncated_planes"] >= 64
    assert "hides what the field of view cuts" in entry["why_left_as_given"] and not checked.warnings
    off = calibrate_from_frames(geometry, static, confirm_unseen=[None, shutter], min_untruncated_gain=0.0)
    assert off.geometry.views[1] == blind.geometry.views[1] and "untruncated_consistency_gain" not in off.views[0]

    # the views moved: the planes the shutter leaves whole agree far better after the motion found, so it is applied
    found = calibrate_from_frames(geometry, moved, confirm_unseen=[None, shutter])
    (entry,) = found.views
    assert "left_as_given" not in entry and entry["untruncated_consistency_gain"] > 5
    assert found.geometry.views[1] == calibrate_from_frames(geometry, moved).geometry.views[1]
    assert len(searches_once) == 2  # every check above judged one of two searches: the static frames', the moved ones'

    # what the command line and the Slicer module say of it
    from SDFCARLib.calibration import calibration_lines

    (said,) = calibration_lines({"calibration": checked.report()})
    assert said.startswith("View 2: pose left as given from the frames: the motion found made the views")
    (said,) = calibration_lines({"calibration": found.report()})
    rotation, shift = (float(np.linalg.norm(found.geometry.views[1].object_rotation_deg)),
                       float(np.linalg.norm(found.geometry.views[1].object_translation_mm)))
    assert said.startswith(f"View 2: pose corrected from the frames: its object turned {rotation:.2f}° and moved {shift:.2f} mm")
    assert f"{entry['untruncated_consistency_gain']:.2f}× on the planes no collimator cuts" in said

    # nothing runs into the shutter (none given, or one that cuts no vessel): nothing to check
    centre = (0.0, 0.0, 0.0)
    assert untruncated_gain(VIEW_1, static[0], VIEW_2, static[1], centre, np.zeros(6), (None, None)) is None
    edge = np.zeros(VIEW_2.detector_shape, bool)
    edge[:2] = True
    assert untruncated_gain(VIEW_1, static[0], VIEW_2, static[1], centre, np.zeros(6), (None, edge)) is None
    gain, planes = untruncated_gain(VIEW_1, static[0], VIEW_2, static[1], centre, np.zeros(6), (None, shutter))
    assert gain == pytest.approx(1.0) and 64 <= planes < 256  # no motion, no change; the cut planes left out


def test_too_few_untruncated_planes_leave_the_search_to_decide(searches_once):
    from blob_phantom import VIEW_1, VIEW_2, blob_image
    from SDFCARLib.calibration import calibrate_from_frames

    geometry = Geometry(VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0)), (VIEW_1, VIEW_2))
    shutter = np.zeros(VIEW_2.detector_shape, bool)
    shutter[:, -30:] = True  # across the epipolar lines: most planes are cut
    images = [blob_image(VIEW_1), _behind_a_shutter(blob_image(VIEW_2), shutter)]
    checked = calibrate_from_frames(geometry, images, confirm_unseen=[None, shutter])
    (entry,) = checked.views
    assert entry["untruncated_planes"] < 64 and entry["untruncated_check"].startswith("not made: only")
    # the check comes after the search: without it the same search decides the same pose (run once, see searches_once)
    assert checked.geometry.views[1] == calibrate_from_frames(geometry, images).geometry.views[1]
    assert len(searches_once) == 1


def test_calibrate_from_frames_leaves_a_view_whose_vessels_run_into_its_collimator_everywhere_as_given_and_warns():
    from blob_phantom import VIEW_1, VIEW_2, blob_image
    from SDFCARLib.calibration import calibrate_from_frames

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    images = [blob_image(VIEW_1), blob_image(VIEW_2.with_object_motion((0.7, 0.5, 0.0), (0.0, 0.0, -1.2)))]
    geometry = Geometry(grid, (VIEW_1, VIEW_2))
    unseen = [None, ~(images[1] > 0)]  # view 2 sees only its vessels' pixels: every plane through them is cut
    result = calibrate_from_frames(geometry, images, unseen=unseen)
    assert result.geometry.views == (VIEW_1, VIEW_2)
    (entry,) = result.views
    assert entry["left_as_given"] is True and "not truncated" in entry["why_left_as_given"]
    assert entry["consistency_gain"] is None and entry["truncated_pixels"][1] > 0
    assert len(result.warnings) == 1 and "collimator" in result.warnings[0] and "view 2" in result.warnings[0]
    assert result.motion_found() is None  # the frames could not show the motion
    # the same frames with nothing said of what they cannot see: the motion is found, as without collimators
    open_field = calibrate_from_frames(geometry, images, unseen=[None, None])
    assert open_field.geometry.views[1] != VIEW_2 and open_field.views[0]["planes_compared"] == 256
    assert open_field.views[0]["truncated_pixels"] == [0, 0]


def test_calibration_lines_say_per_view_what_each_search_did():
    from SDFCARLib.calibration import calibration_lines

    assert calibration_lines({}) == [] and calibration_lines({"calibration": {"method": "none", "why": "no frames"}}) == []
    refit = {"method": "search of the observable rigid motion, re-fitted field per candidate", "views": [
        {"view": 2, "shift_mm": 1.5, "object_rotation_deg": [0.0, 0.0, 0.0], "object_translation_mm": [0.0, 1.2, 0.9]},
        {"view": 3, "skipped": "looks along the same line as view 1"}]}
    frames = {"method": "epipolar consistency of the frames' vessel line integrals", "views": [
        {"view": 2, "left_as_given": True, "why_left_as_given": "the motion found reached the end of its range"}]}
    lines = calibration_lines({"calibration": {**refit, "first": frames}})
    assert lines == ["View 2: pose left as given from the frames: the motion found reached the end of its range.",
                     "View 2: pose corrected by re-fitting: its object turned 0.00° and moved 1.50 mm.",
                     "View 3: pose not searched by re-fitting (looks along the same line as view 1)."]
    in_turn = {"method": "epipolar consistency of the frames' vessel line integrals", "views": [
        {"view": 3, "matched_with": [2], "joint_search": "not used: the search … reached the end of its range",
         "consistency_gain": 30.4, "object_rotation_deg": [0.0, 0.0, 0.0], "object_translation_mm": [0.0, 3.0, 4.0]}]}
    assert calibration_lines({"calibration": in_turn}) == [
        "View 3: pose corrected from the frames: its object turned 0.00° and moved 5.00 mm (the views 30.40× more "
        "consistent; matched to view 2 alone: the search over all views at once could not be used)."]


def test_calibrate_from_frames_matches_a_view_to_another_corrected_view_where_the_joint_search_ends_at_its_range(
        monkeypatch):
    from blob_phantom import VIEW_1, VIEW_2, VIEW_3
    from test_line_integral_consistency import JOINT_EVALUATIONS_TO_THE_LIMIT, ONE_STAGE, _beyond_view_1s_range
    from SDFCARLib import calibration, line_integral_consistency
    from SDFCARLib.line_integral_consistency import motion_axes

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    centre = np.zeros(3)
    monkeypatch.setitem(calibration.FRAME_CALIBRATION_LIMITS, "mm", 2.0)
    searched = line_integral_consistency.estimate_motions
    monkeypatch.setattr(line_integral_consistency, "estimate_motions", lambda *a, **k: searched(*a, **k, **ONE_STAGE))
    monkeypatch.setattr(line_integral_consistency, "JOINT_MAX_EVALUATIONS", JOINT_EVALUATIONS_TO_THE_LIMIT)
    result = calibration.calibrate_from_frames(Geometry(grid, (VIEW_1, VIEW_2, VIEW_3)), _beyond_view_1s_range(centre))
    (warning,) = result.warnings
    assert warning.startswith("the frames' pose search over all 3 views at once could not be used: the search over every "
                              "pair of views at once reached the end of its range") and "matched to one other view" in warning
    second, third = result.views
    assert second["matched_with"] == [1] and third["matched_with"] == [2]
    for entry in (second, third):
        assert entry["joint_search"].startswith("not used: ") and "shift_along_baseline" not in entry
    # view 2 did not move (left as given); view 3 gets what view 2 sees of its motion: 1 mm across their planes
    assert second["left_as_given"] is True and "left_as_given" not in third
    across_23 = motion_axes(VIEW_2, VIEW_3, centre)["shift_across"][3:]
    assert float(np.asarray(result.geometry.views[2].object_translation_mm) @ across_23) == pytest.approx(1.0, abs=0.15)


def test_calibrate_from_frames_with_a_third_view_cut_on_almost_every_plane_matches_each_view_to_view_1():
    from blob_phantom import VIEW_1, VIEW_2, VIEW_3, blob_image
    from SDFCARLib.calibration import calibrate_from_frames
    from SDFCARLib.line_integral_consistency import motion_axes

    grid = VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    across_2 = motion_axes(VIEW_1, VIEW_2, np.zeros(3))["shift_across"][3:]
    images = [blob_image(VIEW_1), blob_image(VIEW_2.with_object_motion((0.0, 0.0, 0.0), 1.5 * across_2)),
              blob_image(VIEW_3)]
    unseen = [None, None, ~(images[2] > 0)]  # every vessel pixel of view 3 next to what it cannot see
    result = calibrate_from_frames(Geometry(grid, (VIEW_1, VIEW_2, VIEW_3)), images, unseen=unseen)
    second, third = result.views
    for entry in (second, third):
        assert entry["matched_with"] == [1] and "epipolar planes no collimator or image edge cuts" in entry["joint_search"]
    assert second["shift_across"]["value"] == pytest.approx(1.5, abs=0.1) and "left_as_given" not in second
    assert third["left_as_given"] is True and "epipolar planes" in third["why_left_as_given"]
    assert any("could not be used" in w for w in result.warnings) and any("view 3" in w for w in result.warnings)


def test_motion_found_over_the_views_and_the_checks_says_not_known_unless_every_view_was_searched():
    from blob_phantom import VIEW_1, VIEW_2
    from SDFCARLib.calibration import Calibration
    from SDFCARLib.optimiser import motion_found_by

    geometry = Geometry(VolumeGrid((8, 8, 8), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), (VIEW_1, VIEW_2))

    def checked(*entries):
        return Calibration(geometry, [dict(entry, view=n + 2) for n, entry in enumerate(entries)])

    noise, applied, unsure = {"motion_found": False}, {"motion_found": True}, {"left_as_given": True}
    skipped = {"skipped": "looks along the same line as view 1"}
    assert checked(noise, noise).motion_found() is False
    assert checked(noise, applied).motion_found() is True
    assert checked(unsure, applied).motion_found() is True  # one view moved is enough
    assert checked(noise, unsure).motion_found() is None and checked(noise, skipped).motion_found() is None
    assert checked().motion_found() is None  # nothing searched
    assert motion_found_by([]) is None  # no check ran (masks alone)
    assert motion_found_by([checked(noise), checked(noise)]) is False
    assert motion_found_by([checked(noise), checked(unsure)]) is None  # the re-fit search does not say
    assert motion_found_by([checked(unsure), checked(applied)]) is True
