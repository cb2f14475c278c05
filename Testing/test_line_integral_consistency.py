"""Epipolar consistency of line-integral images, against Gaussian blobs whose projections and plane
integrals are known in closed form."""

import dataclasses
import math

import numpy as np
import pytest
from scipy import ndimage

from blob_phantom import AMPLITUDES, CENTRES, SIGMA_MM, VIEW_1, VIEW_2, VIEW_3, blob_image
from SDFCARLib import line_integral_consistency
from SDFCARLib.calibration import moved
from SDFCARLib.geometry import rotation_matrix
from SDFCARLib.line_integral_consistency import (MIN_UNTRUNCATED_PLANES, TRUNCATION_PLANE_MARGIN,
                                                  TRUNCATION_REACH_PX, EpipolarError, consistency, epipolar_frame,
                                                  estimate_motion, equal_total_factors, estimate_motions, motion_axes,
                                                  plane_angles, plane_derivatives, plane_sampling, rays_of,
                                                  truncated_rays, with_equal_totals)

#: VIEW_1 with pixels a third the size: its rays are pooled 3 × 3 (``RAY_PIXEL_MM``)
FINE_VIEW_1 = dataclasses.replace(VIEW_1, pixel_spacing_mm=(0.8 / 3, 0.8 / 3), detector_shape=(384, 384))


@pytest.mark.parametrize("view", [VIEW_1, FINE_VIEW_1], ids=["0.8 mm pixels", "0.27 mm pixels, pooled"])
def test_plane_derivatives_match_the_blurred_plane_integrals_of_gaussian_blobs(view):
    rays = rays_of(blob_image(view), view)
    if view is FINE_VIEW_1:  # one ray per 3 × 3 block of pixels
        assert len(rays.weights) <= np.count_nonzero(blob_image(view)) / 9 + 4 * 128
    n0, m = epipolar_frame(VIEW_1.source_position, VIEW_2.source_position, np.zeros(3))
    kappa = np.linspace(-0.04, 0.04, 9)
    normals = np.cos(kappa)[:, None] * n0 + np.sin(kappa)[:, None] * m
    blur_mm, centre = 1.0, CENTRES.mean(axis=0)
    found = plane_derivatives(rays, plane_angles(rays, VIEW_2.source_position, n0, m), kappa, (n0, m), blur_mm, centre)
    source = VIEW_1.source_position
    expected = np.zeros(len(normals))
    for k, normal in enumerate(normals):
        for c, a in zip(CENTRES, AMPLITUDES):
            # R(t) = A 2πσ² exp(−(t − δ)²/2σ²), δ = (c − S)·n; blurred by w: σ → s = √(σ² + w²), height × σ/s
            w = blur_mm * np.linalg.norm(c - source) / np.linalg.norm(centre - source)
            s = math.hypot(SIGMA_MM, w)
            delta = (c - source) @ normal
            expected[k] += a * 2 * math.pi * SIGMA_MM ** 3 / s * delta / s ** 2 * math.exp(-delta ** 2 / (2 * s ** 2))
    assert np.abs(expected).max() > 1.0  # the planes cross blobs
    np.testing.assert_allclose(found, expected, atol=0.01 * np.abs(expected).max())


def test_moved_rays_are_the_rays_of_the_moved_view():
    image = blob_image(VIEW_2)
    rotation, translation, centre = np.array([1.0, -2.0, 0.5]), np.array([2.0, 1.0, -3.0]), np.array([5.0, -4.0, 2.0])
    by_rays = rays_of(image, VIEW_2).moved(rotation, translation, centre)
    by_view = rays_of(image, moved(VIEW_2, rotation, translation, centre))
    np.testing.assert_allclose(by_rays.source_mm, by_view.source_mm, atol=1e-9)
    np.testing.assert_allclose(by_rays.directions, by_view.directions, atol=1e-12)


def test_consistency_is_zero_for_the_true_pose_and_grows_with_a_shift_across_the_epipolar_planes():
    rays_1 = rays_of(blob_image(VIEW_1), VIEW_1)
    n0, _ = epipolar_frame(VIEW_1.source_position, VIEW_2.source_position, np.zeros(3))
    baseline = VIEW_2.source_position - VIEW_1.source_position
    baseline /= np.linalg.norm(baseline)

    def cost(translation):
        seen = blob_image(VIEW_2.with_object_motion((0.0, 0.0, 0.0), translation))
        return consistency(rays_1, rays_of(seen, VIEW_2), 1.0, np.zeros(3))["cost"]

    at_truth = cost(np.zeros(3))
    assert at_truth < 1e-3
    costs = [cost(s * n0) for s in (0.5, 1.0, 2.0)]
    assert at_truth < costs[0] < costs[1] < costs[2] and costs[1] > 0.05
    # along the baseline every epipolar plane keeps its integrals: two views cannot see this motion
    assert cost(2.0 * baseline) < 2 * at_truth + 1e-4


def test_estimate_motion_recovers_the_motion_two_views_observe():
    true_rotation = np.array([0.8, -0.6, 0.0])  # about the baseline (x) and the depth axis (y)
    true_translation = np.array([0.0, 0.0, 1.5])  # across the epipolar planes
    seen = blob_image(VIEW_2.with_object_motion(true_rotation, true_translation))
    estimate = estimate_motion(VIEW_1, blob_image(VIEW_1), VIEW_2, seen, np.zeros(3))
    assert estimate.cost_after < 0.1 * estimate.cost_before
    np.testing.assert_allclose(estimate.rotation_deg[:2], true_rotation[:2], atol=0.1)
    assert abs(estimate.translation_mm[2] - true_translation[2]) < 0.1
    assert abs(estimate.translation_mm[0]) < 1e-6  # along the baseline: not searched
    report = estimate.report()
    assert set(report) >= {"rotation_deg", "translation_mm", "consistency_before", "consistency_after"}


def test_equal_totals_undo_a_scale_error_of_one_view_and_keep_the_volume():
    centre = CENTRES.mean(axis=0)
    rays = [rays_of(blob_image(v), v) for v in (VIEW_1, VIEW_2)]
    volumes = [float(np.sum(r.weights)) * float(np.sum((r.source_mm - centre) ** 2)) for r in rays]
    # Σ P·dω·|S − c|² is the blobs' integral ΣA(2π)^{3/2}σ³ in every view, to the blobs' spread about c
    expected = float(np.sum(AMPLITUDES)) * (2 * math.pi) ** 1.5 * SIGMA_MM ** 3
    np.testing.assert_allclose(volumes, expected, rtol=0.03)
    scaled = [rays[0], dataclasses.replace(rays[1], weights=1.15 * rays[1].weights)]
    equal, unscaled = with_equal_totals(scaled, centre), with_equal_totals(rays, centre)
    for found, without in zip(equal, unscaled):  # the same up to one factor common to both views
        np.testing.assert_allclose(found.weights / equal[0].weights.sum(), without.weights / unscaled[0].weights.sum(),
                                   rtol=1e-12)
    assert consistency(*equal, 1.0, centre)["cost"] < 0.2 * consistency(*scaled, 1.0, centre)["cost"]


def test_equal_total_factors_take_out_one_views_scale_and_multiply_to_one():
    centre = CENTRES.mean(axis=0)
    rays = [rays_of(blob_image(v), v) for v in (VIEW_1, VIEW_2, VIEW_3)]
    plain = equal_total_factors(rays, centre)
    scaled = equal_total_factors([rays[0], dataclasses.replace(rays[1], weights=1.2 * rays[1].weights), rays[2]], centre)
    assert math.prod(plain) == pytest.approx(1.0) and math.prod(scaled) == pytest.approx(1.0)
    # view 2's factor falls by the 1.2 it was given, the others rise by its cube root
    np.testing.assert_allclose(np.array(scaled) / plain, [1.2 ** (1 / 3), 1.2 ** (-2 / 3), 1.2 ** (1 / 3)], rtol=1e-9)
    with pytest.raises(EpipolarError, match="no vessel"):
        equal_total_factors([rays[0], dataclasses.replace(rays[1], weights=0 * rays[1].weights)], centre)


def test_a_view_whose_attenuation_was_misread_still_gives_its_motion():
    true_rotation = np.array([0.8, -0.6, 0.0])
    true_translation = np.array([0.0, 0.0, 1.5])
    seen = 1.15 * blob_image(VIEW_2.with_object_motion(true_rotation, true_translation))  # μ read 13 % low
    estimate = estimate_motion(VIEW_1, blob_image(VIEW_1), VIEW_2, seen, np.zeros(3))
    np.testing.assert_allclose(estimate.rotation_deg[:2], true_rotation[:2], atol=0.1)
    assert abs(estimate.translation_mm[2] - true_translation[2]) < 0.1


def test_images_that_cannot_be_compared_are_refused():
    with pytest.raises(EpipolarError, match="shape"):
        rays_of(np.ones((64, 64)), VIEW_1)
    with pytest.raises(EpipolarError, match="no vessel"):
        rays_of(np.zeros((128, 128)), VIEW_1)


def _moved_images(views, motions_about_centre, centre):
    return [blob_image(views[0])] + [blob_image(v.with_object_motion(r, t - rotation_matrix(r) @ centre + centre))
                                     for v, (r, t) in zip(views[1:], motions_about_centre)]


def _pair_costs(views, images, estimates, centre):
    posed = [views[0]] + [v.with_object_motion(e.rotation_deg, e.translation_mm) for v, e in zip(views[1:], estimates)]
    rays = [rays_of(image, view) for image, view in zip(images, posed)]
    return {(i + 1, j + 1): consistency(rays[i], rays[j], 1.0, centre)["cost"]
            for i in range(len(rays)) for j in range(i + 1, len(rays))}


def _recording_estimate_motion(monkeypatch):
    """The ``estimate_motion`` results ``estimate_motions`` computes, in order (it matches each view to view 1 first)."""
    found = []
    search = line_integral_consistency.estimate_motion

    def recorded(*args, **kwargs):
        found.append(search(*args, **kwargs))
        return found[-1]

    monkeypatch.setattr(line_integral_consistency, "estimate_motion", recorded)
    return found


def test_three_views_are_made_consistent_in_every_pair_where_matching_each_to_view_1_is_not(monkeypatch):
    centre = CENTRES.mean(axis=0)
    baseline = VIEW_2.source_position - VIEW_1.source_position
    baseline /= np.linalg.norm(baseline)
    # view 2 moved mostly along its baseline with view 1 (invisible to that pair), view 3 across
    motions = [(np.array([0.0, 0.3, 0.5]), 1.5 * baseline), (np.array([0.4, 0.0, 0.0]), np.array([0.0, 0.8, 0.0]))]
    views = [VIEW_1, VIEW_2, VIEW_3]
    images = _moved_images(views, motions, centre)
    searched = _recording_estimate_motion(monkeypatch)
    estimates = estimate_motions(views, images, centre)
    # its first step, each view matched to view 1 alone, leaves views 2 and 3 inconsistent with each other
    alone = searched[:2]
    assert [(e.reference_view, e.jointly) for e in alone] == [(0, False), (0, False)] and len(searched) == 2
    each_to_view_1 = _pair_costs(views, images, alone, centre)
    assert each_to_view_1[(1, 2)] < 1e-3 and each_to_view_1[(1, 3)] < 1e-3 and each_to_view_1[(2, 3)] > 0.1
    assert all(e.jointly and not e.joint_fallback and not e.joint_start for e in estimates)
    assert len(estimates) == 2 and set(estimates[0].parameters) == {
        "shift_across", "rotation_about_baseline", "rotation_about_depth", "rotation_about_normal",
        "shift_in_depth", "shift_along_baseline"}
    jointly = _pair_costs(views, images, estimates, centre)
    assert max(jointly.values()) < 1e-3, jointly
    assert estimates[0].cost_after < 0.01 * estimates[0].cost_before
    # the shift along view 1–2's baseline moved toward the truth (three views see it, if weakly)
    assert estimates[0].parameters["shift_along_baseline"] > 0.3


def test_estimate_motions_with_two_views_is_estimate_motion_and_refuses_a_missing_image(monkeypatch):
    images = [blob_image(VIEW_1), blob_image(VIEW_2.with_object_motion((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)))]
    searched = _recording_estimate_motion(monkeypatch)
    (joint,) = estimate_motions([VIEW_1, VIEW_2], images, np.zeros(3))
    assert len(searched) == 1 and searched[0] is joint and not joint.jointly  # the pair's own search, nothing more
    assert joint.translation_mm[2] == pytest.approx(1.0, abs=0.1)  # the shift across the planes, found
    with pytest.raises(EpipolarError, match="one image per view"):
        estimate_motions([VIEW_1, VIEW_2, VIEW_3], images, np.zeros(3))


def _shutter_rows(rows: int) -> np.ndarray:
    """View 2's detector behind a shutter over its first ``rows`` rows: the epipolar lines of the LAO/RAO pair run
    along rows, so the shutter's edge lies along the planes, as a collimator's top edge does."""
    unseen = np.zeros(VIEW_2.detector_shape, dtype=bool)
    unseen[:rows] = True
    return unseen


def test_truncated_rays_are_the_vessel_pixels_next_to_what_the_view_cannot_see():
    image = blob_image(VIEW_2)
    assert truncated_rays(image, None, VIEW_2) is None
    assert truncated_rays(image, _shutter_rows(2), VIEW_2) is None  # no vessel reaches the shutter
    unseen = _shutter_rows(50)
    image[unseen] = 0.0  # what the shutter hides is not in the frame
    rays = truncated_rays(image, unseen, VIEW_2)
    # the vessel pixels of the TRUNCATION_REACH_PX rows next to the shutter, one ray each
    expected = np.count_nonzero(image[50:50 + TRUNCATION_REACH_PX] > 0)
    assert expected > 0 and len(rays.weights) == expected and rays.directions.shape == (expected, 3)
    with pytest.raises(EpipolarError, match="unseen-pixel image"):
        truncated_rays(image, unseen[:64], VIEW_2)


def test_planes_through_truncated_rays_are_left_out_and_no_others():
    centre = CENTRES.mean(axis=0)
    unseen = _shutter_rows(50)
    image_2 = blob_image(VIEW_2)
    image_2[unseen] = 0.0
    rays_1, rays_2 = rays_of(blob_image(VIEW_1), VIEW_1), rays_of(image_2, VIEW_2)
    cut = truncated_rays(image_2, unseen, VIEW_2)
    blur = 1.0
    every = plane_sampling(rays_1, rays_2, blur, centre)
    kept = plane_sampling(rays_1, rays_2, blur, centre, truncated=(None, cut))
    n0, m = epipolar_frame(rays_1.source_mm, rays_2.source_mm, centre)
    cut_kappa = plane_angles(cut, rays_1.source_mm, n0, m)
    epsilon = blur / float(np.linalg.norm(rays_1.source_mm - centre))
    distance = np.abs(every[:, None] - cut_kappa[None, :]).min(axis=1)
    np.testing.assert_array_equal(kept, every[distance > TRUNCATION_PLANE_MARGIN * epsilon])
    assert 0 < len(kept) < len(every)
    # without truncated rays: every plane, as before
    np.testing.assert_array_equal(plane_sampling(rays_1, rays_2, blur, centre, truncated=(None, None)), every)


def test_a_shutter_that_touches_no_vessel_changes_nothing_in_the_motion_search():
    true_rotation, true_translation = np.array([0.8, -0.6, 0.0]), np.array([0.0, 0.0, 1.5])
    seen = blob_image(VIEW_2.with_object_motion(true_rotation, true_translation))
    # one search stage: the planes compared, not the coarse-to-fine accuracy, are what a shutter could change
    plain = estimate_motion(VIEW_1, blob_image(VIEW_1), VIEW_2, seen, np.zeros(3), blurs_mm=ONE_STAGE["blurs_mm"])
    shuttered = estimate_motion(VIEW_1, blob_image(VIEW_1), VIEW_2, seen, np.zeros(3), unseen=(_shutter_rows(2), None),
                                blurs_mm=ONE_STAGE["blurs_mm"])
    np.testing.assert_array_equal(shuttered.added, plain.added)
    assert shuttered.truncated_pixels == (0, 0) and shuttered.planes_compared == plain.planes_compared == 256


def test_a_pair_truncated_on_almost_every_plane_is_not_measured():
    image_2 = blob_image(VIEW_2.with_object_motion((0.5, 0.0, 0.0), (0.0, 0.0, 1.0)))
    unseen = ~(image_2 > 0)  # every vessel pixel next to what the view cannot see
    estimate = estimate_motion(VIEW_1, blob_image(VIEW_1), VIEW_2, image_2, np.zeros(3), unseen=(None, unseen))
    assert not estimate.measured and estimate.planes_compared < MIN_UNTRUNCATED_PLANES
    np.testing.assert_array_equal(estimate.added, np.zeros(6))
    np.testing.assert_array_equal(estimate.rotation_deg, VIEW_2.object_rotation_deg)
    # the vessel pixels within the reach (taxicab, as the dilation counts it) of a pixel the view cannot see
    rim = (image_2 > 0) & (ndimage.distance_transform_cdt(image_2 > 0, metric="taxicab") <= TRUNCATION_REACH_PX)
    assert estimate.truncated_pixels == (0, int(np.count_nonzero(rim)))


def _beyond_view_1s_range(centre):
    """View 3 moved along its baseline with view 2 (invisible to that pair) by 4 mm, which crosses view 1–3's
    epipolar planes by 3.7 mm, and 1 mm across view 2–3's planes; view 2 not moved."""
    along_23 = motion_axes(VIEW_2, VIEW_3, centre)["shift_along_baseline"][3:]
    across_23 = motion_axes(VIEW_2, VIEW_3, centre)["shift_across"][3:]
    return [blob_image(VIEW_1), blob_image(VIEW_2), blob_image(VIEW_3.with_object_motion((0.0, 0.0, 0.0),
                                                                                         4.0 * along_23 + across_23))]


#: one blur per search stage instead of three: the tests of what happens at the range's end need the mechanism, not
#: the coarse-to-fine accuracy (a third of the time)
ONE_STAGE = {"blurs_mm": (1.0,), "joint_blurs_mm": (1.0,)}
#: and fewer Gauss–Newton evaluations: the joint search reaches the range's end well within them
JOINT_EVALUATIONS_TO_THE_LIMIT = 20


def test_a_view_the_joint_search_cannot_place_within_its_range_is_matched_to_the_view_it_agrees_with(monkeypatch):
    monkeypatch.setattr(line_integral_consistency, "JOINT_MAX_EVALUATIONS", JOINT_EVALUATIONS_TO_THE_LIMIT)
    centre = np.zeros(3)
    views, images = [VIEW_1, VIEW_2, VIEW_3], _beyond_view_1s_range(centre)
    second, third = estimate_motions(views, images, centre, max_translation_mm=2.0, **ONE_STAGE)  # a 2 mm range
    for estimate in (second, third):
        assert not estimate.jointly and estimate.joint_fallback.startswith(
            "the search over every pair of views at once reached the end of its range (")
        assert set(estimate.parameters) == {"shift_across", "rotation_about_baseline", "rotation_about_depth"}
    # matched to view 1, view 3 ends at the limit; matched to view 2 it does not, and that pair's 1 mm is found
    to_view_1 = estimate_motion(VIEW_1, images[0], VIEW_3, images[2], centre, max_translation_mm=2.0,
                                blurs_mm=ONE_STAGE["blurs_mm"])
    assert "shift_across" in to_view_1.at_limit and not third.at_limit
    assert second.reference_view == 0 and third.reference_view == 1
    np.testing.assert_allclose(second.added, estimate_motion(VIEW_1, images[0], VIEW_2, images[1], centre,
                                                             max_translation_mm=2.0, blurs_mm=ONE_STAGE["blurs_mm"]).added)
    assert abs(third.parameters["shift_across"]) == pytest.approx(1.0, abs=0.1)
