"""Self-calibration of the views' poses (calibration.py): the searched direction, the composition of
motions and the search against closed forms; recovery of a known shift with a stand-in score."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.calibration import calibrate, epipolar_normal, parabola_minimum, shifted
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid, rotation_matrix
from SDFCARLib.settings import ReconstructionError, make_settings


def _view(primary=30.0, secondary=0.0):
    return CArmView(primary, secondary, 1000.0, 750.0, (0.5, 0.5), (64, 64))


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

    settings = make_settings("fast", calibrate=True)
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

    result = calibrate(geometry, [np.zeros((64, 64))] * 2, make_settings("fast", calibrate=True), "mask", score=score)
    assert result.geometry.views[1].object_translation_mm == (0.0, 0.0, 0.0)
    assert result.views[0]["shift_mm"] == 0.0
    (warning,) = result.warnings
    assert "view 2" in warning and "no minimum within ±4 mm" in warning and "left as given" in warning
