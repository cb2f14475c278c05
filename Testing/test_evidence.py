"""Line-integral evidence read off the frames (evidence.py) and its use as the occupancy target."""

from __future__ import annotations

import math
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scipy import ndimage

from SDFCARLib.angiogram import AngiogramSettings, simulate_angiogram
from SDFCARLib.evidence import (EvidenceError, EvidenceSettings, absorbance_above_background, border_trimmed_mask,
                                estimate_attenuation_per_mm, unreadable_intensity, view_evidence)
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.losses import make_target, frame_target, occupancy_loss
from SDFCARLib.masks import segment_angiogram, unseen_pixels
from SDFCARLib.line_integral_consistency import equal_total_factors, rays_of
from SDFCARLib.optimiser import build_problem, occupancy_targets, occupancy_terms, read_frame_evidence, reconstruct
from SDFCARLib.outputs import write_reconstruction
from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize
from SDFCARLib.qa import ONE_VIEW_RGB
from SDFCARLib.settings import ReconstructionError, make_settings

MU = 0.25
PIXEL_MM = 0.2
VIEW = CArmView(0.0, 0.0, 1000.0, 750.0, (PIXEL_MM, PIXEL_MM), (200, 200))


def _tubes_image(radii_mm=(1.5, 2.0), sigma_mm=0.3):
    """Path lengths (detector mm) of two vertical circular tubes on the detector, blurred, and their masks."""
    x = (np.arange(200) - 100) * PIXEL_MM
    length = np.zeros((200, 200))
    for centre, radius in zip((-6.0, 6.0), radii_mm):
        chord = 2.0 * np.sqrt(np.clip(radius ** 2 - (x - centre) ** 2, 0.0, None))
        length[20:180] += chord[None, :]
    blurred = ndimage.gaussian_filter(length, sigma_mm / PIXEL_MM)
    return length, blurred, length > 0


def _frame(blurred_length_detector_mm, background):
    # chord at the detector = magnification × chord at the vessel, so μ per vessel mm = μ_det · magnification
    mu_detector = MU / VIEW.magnification
    return 3000.0 * np.exp(-mu_detector * blurred_length_detector_mm - background)


def test_background_removal_leaves_the_vessels_absorbance():
    length, blurred, mask = _tubes_image()
    rows, cols = np.mgrid[0:200, 0:200]
    background = 1.2 + 0.002 * rows + 0.3 * np.sin(cols / 120.0)  # smooth tissue, far wider than a vessel
    above = absorbance_above_background(_frame(blurred, background), mask, VIEW.pixel_spacing_mm)
    expected = MU / VIEW.magnification * blurred
    inside = ndimage.binary_erosion(mask, iterations=2)
    # exact for a linear background; a curved one is off by about ½σ²·B'' (here 0.01 of a 0.74 peak)
    assert np.max(np.abs(above[inside] - expected[inside])) < 0.03 * expected[inside].max()
    beside = ndimage.binary_dilation(mask, iterations=30) & ~ndimage.binary_dilation(mask, iterations=10)
    beside[:40] = beside[160:] = False  # near the image's edge the interpolation sees one side only
    assert np.max(np.abs(above[beside])) < 0.02


def test_attenuation_is_read_from_the_lumen_profile_not_the_mask_width():
    _, blurred, mask = _tubes_image()
    frame = _frame(blurred, 1.0)
    for widened in (0, 2):  # a mask two pixels too wide on each side reads the same μ
        given = ndimage.binary_dilation(mask, iterations=widened) if widened else mask
        found = estimate_attenuation_per_mm(frame, given, VIEW)
        assert found["attenuation_per_mm"] == pytest.approx(MU, rel=0.05)
        assert found["profiles"] >= 5


def test_view_evidence_is_the_path_length_inside_the_widened_mask_only():
    _, blurred, mask = _tubes_image()
    rng = np.random.default_rng(0)
    frame = _frame(blurred, 1.0) * (1.0 + 0.01 * rng.standard_normal(mask.shape))
    evidence = view_evidence(frame, mask, VIEW)
    assert evidence.line_integral_mm.shape == mask.shape and evidence.line_integral_mm.dtype == np.float32
    assert not np.any(evidence.line_integral_mm[~ndimage.binary_dilation(mask, iterations=2)])
    centre = ndimage.binary_erosion(mask, iterations=4)
    vessel_mm = blurred[centre] / VIEW.magnification  # mm of vessel along the ray
    assert np.median(evidence.line_integral_mm[centre] / vessel_mm) == pytest.approx(1.0, abs=0.06)


def test_deblurring_restores_a_thin_vessels_path_length_against_the_detectors_blur():
    length, blurred, mask = _tubes_image(radii_mm=(0.4, 0.6))  # 2–3 pixels wide: the blur halves their peak
    frame = _frame(blurred, 1.0)
    true_mm = length / VIEW.magnification
    kept = {n: view_evidence(frame, mask, VIEW, EvidenceSettings(reach_px=0, deblur_iterations=n,
                                                                  min_radius_mm=0.2)).line_integral_mm
            for n in (0, 20)}
    error = {n: np.abs(kept[n][mask] - true_mm[mask]).mean() for n in kept}
    assert error[20] < 0.6 * error[0]  # about half (the rest: the pixels' sampling of the chord)
    # a restoration moves path length back onto the vessel, it does not make any: over the vessel and its rim
    # the sum stays the blurred frame's
    rim = ndimage.binary_dilation(mask, iterations=4)
    plain, restored = (view_evidence(frame, mask, VIEW, EvidenceSettings(reach_px=4, deblur_iterations=n,
                                                                         min_radius_mm=0.2)).line_integral_mm
                       for n in (0, 20))
    assert restored[rim].sum() == pytest.approx(plain[rim].sum(), rel=0.01)


def test_bad_frames_are_refused_with_the_reason():
    _, blurred, mask = _tubes_image()
    frame = _frame(blurred, 1.0)
    with pytest.raises(EvidenceError, match="shape"):
        view_evidence(frame[:100], mask, VIEW)
    with pytest.raises(EvidenceError, match="mask is empty"):
        view_evidence(frame, np.zeros_like(mask), VIEW)
    with pytest.raises(EvidenceError, match="positive"):
        view_evidence(np.zeros_like(frame), mask, VIEW)
    for not_a_frame in (mask * 255.0, np.where(mask, 3000.0, 1000.0)):  # a mask, an inverted frame
        with pytest.raises(EvidenceError):
            view_evidence(not_a_frame, mask, VIEW)
    holed = frame.copy()
    holed[2:4, 5:8] = np.nan
    holed[10, 0] = np.inf
    with pytest.raises(EvidenceError, match=r"7 of the frame's pixels are NaN or infinite \(the first at row 2, column 5\)"):
        view_evidence(holed, mask, VIEW)
    thin = _tubes_image(radii_mm=(0.3, 0.3))  # no vessel thick enough to read μ across
    with pytest.raises(EvidenceError, match="attenuation"):
        view_evidence(_frame(thin[1], 1.0), thin[2], VIEW)


def test_frame_target_fits_path_lengths_and_keeps_the_mask_silhouette():
    import torch

    mask = torch.zeros(8, 8)
    mask[2:6, 3:5] = 1.0
    evidence = torch.zeros(8, 8)
    evidence[2:6, 3:5] = torch.tensor([1.0, 2.0])
    target = frame_target(evidence, make_target(mask, "mask", 0.3))
    evidence[0, 0] = 9.0  # evidence outside the mask does not set the scale
    target = frame_target(evidence, make_target(mask, "mask", 0.3))
    assert target.reference_mm == pytest.approx(1.0)  # the median over the mask's pixels: a typical vessel pixel reads 1
    assert torch.equal(target.silhouette, mask)
    assert torch.allclose(target.rendered(evidence), target.image)  # the evidence itself is a perfect rendering
    with pytest.raises(ValueError, match="no vessel"):
        frame_target(torch.zeros(8, 8), make_target(mask, "mask", 0.3))


def test_a_frame_target_with_the_detectors_blur_compares_the_blurred_rendering():
    import torch
    from SDFCARLib.losses import gaussian_blur

    mask = torch.zeros(16, 16)
    mask[4:12, 7:9] = 1.0
    evidence = gaussian_blur(mask * 2.0, (1.2, 0.8))  # a frame's path lengths are blurred by the detector
    target = frame_target(evidence, make_target(mask, "mask", 0.3), (1.2, 0.8))
    assert target.blur_sigma_px == (1.2, 0.8)
    # the unblurred vessel is now the perfect rendering; without the blur its rendering is off
    assert torch.allclose(target.rendered(mask * 2.0), target.image, atol=1e-6)
    unblurred = frame_target(evidence, make_target(mask, "mask", 0.3))
    assert float(occupancy_loss(unblurred.rendered(mask * 2.0), unblurred.image)) > 1e-3
    assert torch.equal(target.silhouette, mask)  # L_geo keeps the mask


def _vertical_vessel(columns, path_on_columns):
    """A vessel masked on rows 5–34 and ``columns`` (first, stop) of a 40² image, and its path lengths (mm):
    each (first, stop, mm) of ``path_on_columns`` in turn."""
    mask = np.zeros((40, 40), bool)
    mask[5:35, columns[0]:columns[1]] = True
    path = np.zeros((40, 40))
    for first, stop, mm in path_on_columns:
        path[5:35, first:stop] = mm
    return mask, path


def test_border_pixels_with_little_path_length_are_trimmed_and_the_centreline_stays():
    # a vertical vessel masked 9 columns wide whose frame shows 1.2 mm of path on its middle 5 columns and
    # 0.1 mm on the two columns each side (a segmentation a pixel or two outside a blurred lumen)
    mask, path = _vertical_vessel((16, 25), [(16, 25, 0.1), (18, 23, 1.2)])
    trimmed = border_trimmed_mask(mask, path, 0.3, smoothing_px=0.0)
    assert np.array_equal(np.flatnonzero(trimmed[20]), np.arange(18, 23))
    assert not (trimmed & ~mask).any()  # never wider than the mask
    # a faint vessel (0.1 mm all across) keeps its centreline: a thin vessel is not removed
    faint = border_trimmed_mask(mask, np.where(mask, 0.1, 0.0), 0.3)
    assert faint[20].sum() >= 1 and faint[20, 20]
    with pytest.raises(ValueError, match="shape"):
        border_trimmed_mask(mask, path[:, :30], 0.3)
    with pytest.raises(ValueError, match="positive"):
        border_trimmed_mask(mask, path, 0.0)


def test_a_thin_vessels_border_is_kept_relative_to_its_centre():
    # a thin vessel masked 5 columns wide whose whole blurred profile lies below the 0.3 mm threshold:
    # 0.25 mm on its centreline column, 0.15 beside it, 0.05 on the mask's outer columns
    mask, path = _vertical_vessel((18, 23), [(18, 23, 0.05), (19, 22, 0.15), (20, 21, 0.25)])
    absolute = border_trimmed_mask(mask, path, 0.3, smoothing_px=0.0)
    assert np.array_equal(np.flatnonzero(absolute[20]), [20])  # the absolute threshold leaves the centreline alone
    # at 0.3 of the centre's 0.25 mm the threshold is 0.075: the columns at 0.15 stay, those at 0.05 go
    relative = border_trimmed_mask(mask, path, 0.3, smoothing_px=0.0, centre_fraction=0.3)
    assert np.array_equal(np.flatnonzero(relative[20]), [19, 20, 21])
    # a thick vessel (1.2 mm at its centre) keeps the absolute threshold: min(0.3, 0.3 × 1.2) = 0.3
    _, thick = _vertical_vessel((18, 23), [(18, 23, 0.1), (19, 22, 1.2)])
    assert np.array_equal(np.flatnonzero(border_trimmed_mask(mask, thick, 0.3, 0.0, 0.3)[20]), [19, 20, 21])
    with pytest.raises(ValueError, match="centre_fraction"):
        border_trimmed_mask(mask, path, 0.3, centre_fraction=1.0)


# --- in the reconstruction ---------------------------------------------------------------------------
GRID = VolumeGrid((32, 32, 32), (1.0, 1.0, 1.0))
VIEWS = [CArmView(30.0, 0.0, 1000.0, 750.0, (0.4, 0.4), (128, 128)),
         CArmView(-40.0, 15.0, 1000.0, 750.0, (0.4, 0.4), (128, 128))]


def _one_vessel_frames(collimator_fractions=(0.0, 0.0)):
    """A curved vessel's label, silhouettes and simulated frames of VIEWS, each behind its collimator."""
    tree = CentrelineTree([Branch(np.array([[-12.0, -3.0, -11.0], [0.0, 2.0, 0.0], [11.0, -2.0, 12.0]]),
                                  np.array([1.8, 1.6, 1.4]))])
    label = voxelize(tree, GRID)
    line_integrals, silhouettes = simulate_views(label, GRID, VIEWS)
    rng = np.random.default_rng(3)
    frames = [simulate_angiogram(li, v.pixel_spacing_mm, rng, AngiogramSettings(snr=40.0, collimator_fraction=c))[0]
              for li, v, c in zip(line_integrals, VIEWS, collimator_fractions)]
    return label, silhouettes, frames


@pytest.fixture(scope="module")
def angiogram_case():
    label, _, frames = _one_vessel_frames()
    masks = [segment_angiogram(f, v.pixel_spacing_mm, v.magnification).mask for f, v in zip(frames, VIEWS)]
    return Geometry(GRID, VIEWS), label, frames, masks


def test_reconstruction_fits_the_frames_when_asked(angiogram_case):
    geometry, label, frames, masks = angiogram_case
    settings = make_settings("fast", steps=150, frame_evidence=True, lambda_occ_frames=0.5)
    result = reconstruct(geometry, masks, settings, "mask", frames=frames)
    evidence = result.report["frame_evidence"]
    assert evidence["used"] is True
    # L_occ on the path lengths weighs λ_occ_frames, not the masks' λ_occ (0.25)
    assert evidence["lambda_occ"] == 0.5 != settings.loss.lambda_occ
    last = result.history[-1]
    assert last["loss"] == pytest.approx(0.5 * last["l_occ"] + settings.loss.lambda_geo * last["l_geo"], rel=1e-5)
    for view in evidence["views"]:  # the simulator's iodine
        assert view["attenuation_per_mm"] == pytest.approx(0.25, rel=0.2)
    overlap = np.sum(result.segmentation & label) / np.sum(label)
    assert overlap > 0.6 and result.segmentation.sum() < 2.0 * label.sum()


def test_what_a_collimator_hides_from_one_view_is_unknown_to_it_not_background(tmp_path, monkeypatch):
    label, silhouettes, frames = _one_vessel_frames((0.0, 0.25))  # view 2 collimated tightly
    unseen = [unseen_pixels(f, v.pixel_spacing_mm, v.magnification) for f, v in zip(frames, VIEWS)]
    masks = [s & ~u for s, u in zip(silhouettes, unseen)]  # a mask shows nothing where its frame does not
    geometry = Geometry(GRID, VIEWS)
    rows, cols, _ = VIEWS[1].project(GRID.voxel_centers())
    on_detector = (np.rint(rows) >= 0) & (np.rint(rows) < 128) & (np.rint(cols) >= 0) & (np.rint(cols) < 128)
    behind_blade = np.zeros(GRID.num_voxels, bool)
    behind_blade[on_detector] = unseen[1][np.rint(rows[on_detector]).astype(int), np.rint(cols[on_detector]).astype(int)]
    hidden = label & behind_blade.reshape(GRID.shape)
    assert hidden.sum() > 0.2 * label.sum()  # the case does what it says

    strict = build_problem(geometry, masks, make_settings("fast"), "mask", frames=frames)
    open_minded = build_problem(geometry, masks, make_settings("fast", frames_unseen_unknown=True), "mask", frames=frames)
    assert strict.unknown is None and (hidden & strict.support).sum() < 0.2 * hidden.sum()  # view 2's 0 forbade it (but its margin)
    # view 2 could not see it, so one view alone would have to place it in depth: by default the support does not follow
    assert (hidden & open_minded.support).sum() <= (hidden & strict.support).sum()
    far_reaching = build_problem(geometry, masks, make_settings("fast", frames_unseen_unknown=True, frames_unseen_reach_mm=40.0),
                                 "mask", frames=frames)
    assert (hidden & far_reaching.support).sum() > 0.9 * hidden.sum()
    with pytest.raises(ReconstructionError, match="frames_unseen_reach_mm is how far"):
        make_settings("fast", frames_unseen_reach_mm=-1.0)
    for target, mask, u in zip(open_minded.view_targets, masks, unseen):
        np.testing.assert_array_equal(target.known.cpu().numpy() == 0, u & ~mask)
    # masks handed over as the frames: nothing to read the field of view off
    as_frames = build_problem(geometry, masks, make_settings("fast", frames_unseen_unknown=True), "mask",
                              frames=[m.astype(np.uint8) * 255 for m in masks])
    assert as_frames.unknown is None and as_frames.view_targets[0].known is None
    # a frame whose field cannot be read (flat but for three values): its view keeps every pixel, and says so
    flat = np.full(frames[1].shape, 1000, np.uint16)
    flat[0, :3] = (10, 20, 30)
    unread = build_problem(geometry, masks, make_settings("fast", frames_unseen_unknown=True), "mask",
                           frames=[frames[0], flat])
    assert not unread.unknown[1].any() and np.array_equal(unread.unknown[0], open_minded.unknown[0])
    assert any("view 2: its frame's collimator and clipped parts could not be read" in w for w in unread.warnings)

    result = reconstruct(geometry, masks, make_settings("fast", steps=10, warmup_steps=2, frames_unseen_unknown=True),
                         "mask", frames=frames)
    assert result.report["unknown_pixel_fraction"] == [round(float((u & ~m).mean()), 4) for u, m in zip(unseen, masks)]
    assert result.report["one_view_share"][0] > 0.3 and result.report["one_view_share"][1] == 0.0
    # the reprojection QA (its numbers and its pictures) counts only what each view could see
    projected = [p for p, _ in result.qa_masks]
    assert not any(np.any(p & u & ~m) for p, u, m in zip(projected, unseen, masks))
    assert result.report["reprojection_qa"][1]["pixels"]["result_only"] == int((projected[1] & ~masks[1]).sum())
    # what view 1 alone shows is marked on its QA overlay and measured in its QA numbers; view 2 has none
    one_view = result.one_view_pixels
    assert one_view[0].any() and not (one_view[0] & ~masks[0]).any() and not one_view[1].any()
    along = [qa["one_view_area_mm2"]["mask"] for qa in result.report["reprojection_qa"]]
    assert along[0] > 0.0 == along[1]
    monkeypatch.setitem(sys.modules, "SDFCARLib.mrml", None)  # no scene: not what is tested here
    files = write_reconstruction(result, tmp_path / "result")
    for n, expected in ((1, one_view[0]), (2, one_view[1])):
        image = iio.imread(files[f"qa_view{n}"])[:128, :128]
        drawn = np.all(image == ONE_VIEW_RGB, axis=-1)
        # every marked pixel (a largest blob's yellow box may cross a few)
        assert not (drawn & ~expected).any() and drawn.sum() >= 0.9 * expected.sum()


def test_a_vessel_behind_the_other_views_collimator_is_named_as_such_not_as_a_wrong_geometry():
    label, silhouettes, frames = _one_vessel_frames((0.0, 0.25))  # view 2 collimated tightly
    unseen = [unseen_pixels(f, v.pixel_spacing_mm, v.magnification) for f, v in zip(frames, VIEWS)]
    masks = [s & ~u for s, u in zip(silhouettes, unseen)]
    geometry = Geometry(GRID, VIEWS)
    problem = build_problem(geometry, masks, make_settings("fast"), "mask", frames=frames)
    assert problem.consistency[0] < 0.9  # most of view 1's vessel has no partner in view 2's mask
    assert problem.one_view_shares[0] > 0.3 and problem.one_view_shares[1] == 0.0
    named = [w for w in problem.warnings if "where view 2 cannot show them (behind a collimator" in w]
    assert len(named) == 1 and named[0].startswith("view 1: ") and "no partner" in named[0]
    assert not any(w.startswith("view 1: only") for w in problem.warnings)  # not the bare geometry warning
    # masks handed over as the frames: the collimator cannot be read, and the missing partners are what they were
    as_masks = build_problem(geometry, masks, make_settings("fast"), "mask", frames=[m.astype(np.uint8) * 255 for m in masks])
    assert as_masks.one_view_shares == [0.0, 0.0]
    assert any(w.startswith("view 1: only") and "angle signs" in w and "collimator" in w for w in as_masks.warnings)


def test_occupancy_loss_fits_the_frames_then_the_masks_when_asked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    settings = make_settings("fast", steps=20, warmup_steps=2, frame_evidence=True, lambda_occ_frames=0.5,
                             frame_evidence_until_fraction=0.5, width_exclusion_fraction=0.0)
    result = reconstruct(geometry, masks, settings, "mask", frames=frames)
    assert result.report["frame_evidence"]["until_step"] == 10
    for entry in result.history:  # λ_occ_frames on the path lengths up to step 10, the masks' λ_occ after it
        weight = 0.5 if entry["step"] <= 10 else settings.loss.lambda_occ
        assert entry["loss"] == pytest.approx(weight * entry["l_occ"] + settings.loss.lambda_geo * entry["l_geo"], rel=1e-5)
    problem = build_problem(geometry, masks, settings, "mask", frames=frames)
    frames_targets, frames_weight = occupancy_targets(problem, 10)
    masks_targets, masks_weight = occupancy_targets(problem, 11)
    assert frames_targets is problem.view_targets and frames_weight == 0.5
    assert masks_targets is problem.mask_targets and masks_weight == settings.loss.lambda_occ
    for on_frames, on_masks, mask in zip(frames_targets, masks_targets, masks):
        assert np.array_equal(on_masks.image.cpu().numpy() > 0, mask > 0)  # the mask itself ...
        assert not np.array_equal(on_frames.image.cpu().numpy(), on_masks.image.cpu().numpy())  # ... not the path lengths
    no_frames = build_problem(geometry, masks, settings, "mask")
    assert no_frames.mask_targets is None and occupancy_targets(no_frames, 11)[0] is no_frames.view_targets
    for bad in (0.0, 1.5, -0.2):
        with pytest.raises(ReconstructionError, match="frame_evidence_until_fraction"):
            make_settings("fast", frame_evidence_until_fraction=bad)


def test_the_frames_only_cap_the_path_length_when_asked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    settings = make_settings("fast", steps=20, warmup_steps=2, frame_evidence=True, lambda_occ_frames=0.5,
                             frame_excess_factor=1.5, frame_excess_tolerance_mm=0.2,
                             frame_evidence_until_fraction=0.5, width_exclusion_fraction=0.0)
    result = reconstruct(geometry, masks, settings, "mask", frames=frames)
    record = result.report["frame_evidence"]
    assert record["excess_factor"] == 1.5 and record["excess_tolerance_mm"] == 0.2 and record["until_step"] == 10
    for entry in result.history:  # L_occ on the masks throughout (λ_occ), the cap (λ_occ_frames) up to step 10
        assert ("l_excess" in entry) == (entry["step"] <= 10)
        expected = settings.loss.lambda_occ * entry["l_occ"] + 0.5 * entry.get("l_excess", 0.0)
        assert entry["loss"] == pytest.approx(expected + settings.loss.lambda_geo * entry["l_geo"], rel=1e-5)
    # the frames' term charges only the path length beyond the cap: far below it, nothing
    problem = build_problem(geometry, masks, settings, "mask", frames=frames)
    below = [0.5 * t.image * t.reference_mm for t in problem.view_targets]
    assert float(occupancy_terms(problem, 1, below)["l_excess"]) == 0.0
    above = [3.0 * t.image * t.reference_mm + 1.0 for t in problem.view_targets]
    assert float(occupancy_terms(problem, 1, above)["l_excess"]) > 0.0
    for bad in (0.5, -1.0):
        with pytest.raises(ReconstructionError, match="frame_excess_factor"):
            make_settings("fast", frame_excess_factor=bad)
    with pytest.raises(ReconstructionError, match="frame_excess_tolerance_mm"):
        make_settings("fast", frame_excess_tolerance_mm=-0.1)


def test_the_masks_are_fitted_beside_the_frames_path_lengths_when_asked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    settings = make_settings("fast", steps=12, warmup_steps=2, frame_evidence=True, lambda_occ_frames=0.5,
                             lambda_occ_masks_with_frames=0.3, frame_evidence_until_fraction=0.5,
                             width_exclusion_fraction=0.0)
    result = reconstruct(geometry, masks, settings, "mask", frames=frames)
    for entry in result.history:  # both up to step 6; after it the masks alone, weighed λ_occ as before
        if entry["step"] <= 6:
            expected = 0.5 * entry["l_occ"] + 0.3 * entry["l_occ_masks"]
        else:
            assert "l_occ_masks" not in entry
            expected = settings.loss.lambda_occ * entry["l_occ"]
        assert entry["loss"] == pytest.approx(expected + settings.loss.lambda_geo * entry["l_geo"], rel=1e-5)
    with pytest.raises(ReconstructionError, match="lambda_occ_masks_with_frames"):
        make_settings("fast", lambda_occ_masks_with_frames=-0.1)


def test_the_frames_path_lengths_reach_as_far_beyond_the_masks_as_asked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    for reach in (0, 2):
        problem = build_problem(geometry, masks, make_settings("fast", frame_evidence_reach_px=reach), "mask",
                                frames=frames)
        assert problem.evidence["reach_px"] == reach  # report.json says how far
        assert problem.evidence["deblur_iterations"] == 0
        for target, mask in zip(problem.view_targets, masks):
            kept = target.image.cpu().numpy() > 0
            allowed = ndimage.binary_dilation(mask > 0, iterations=reach) if reach else mask > 0
            assert not (kept & ~allowed).any()  # nothing beyond the reach ...
            assert (kept & ~(mask > 0)).any() == (reach > 0)  # ... and the blurred rim kept where it reaches
    for bad in (-1, 1.5):
        with pytest.raises(ReconstructionError, match="frame_evidence_reach_px"):
            make_settings("fast", frame_evidence_reach_px=bad)


def test_the_views_path_lengths_are_brought_to_one_total_when_asked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    read = {on: read_frame_evidence(frames, masks, geometry, make_settings("fast", frame_evidence_equal_totals=on), "mask")
            for on in (False, True)}
    factors = [v["equal_total_factor"] for v in read[True].record["views"]]
    assert all("equal_total_factor" not in v for v in read[False].record["views"])
    assert math.prod(factors) == pytest.approx(1.0, abs=2e-4)
    for plain, equal, f in zip(read[False].images, read[True].images, factors):
        np.testing.assert_allclose(equal, plain * f, rtol=1e-3)  # one factor per view, nothing else changed
    # brought to one total: the views read afterwards need no further factor
    equalised = [rays_of(i, v) for i, v in zip(read[True].images, geometry.views)]
    np.testing.assert_allclose(equal_total_factors(equalised, geometry.volume.center_mm), [1.0, 1.0], rtol=1e-4)
    # the fit's L_occ reads what was brought to one total
    problem = build_problem(geometry, masks, make_settings("fast", frame_evidence_equal_totals=True), "mask", frames=frames)
    for target, image in zip(problem.view_targets, read[True].images):
        np.testing.assert_allclose(target.image.cpu().numpy() * target.reference_mm, image, rtol=1e-5, atol=1e-6)


def test_the_frames_path_lengths_are_deblurred_when_asked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    plain, sharp = (build_problem(geometry, masks, make_settings("fast", frame_deblur_iterations=n), "mask",
                                  frames=frames) for n in (0, 5))
    assert sharp.evidence["deblur_iterations"] == 5
    for p, s, mask in zip(plain.view_targets, sharp.view_targets, masks):
        inside = torch.as_tensor(mask > 0)
        path_p, path_s = (t.image[inside] * t.reference_mm for t in (p, s))
        assert path_s.max() > path_p.max()  # the vessels' centres gain what their blurred rims gave away
    for bad in (-1, 2.5, 51):
        with pytest.raises(ReconstructionError, match="frame_deblur_iterations"):
            make_settings("fast", frame_deblur_iterations=bad)


def test_the_detectors_blur_reaches_each_frame_target_in_its_pixels(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    blurred = build_problem(geometry, masks, make_settings("fast", frame_blur_sigma_mm=0.3), "mask", frames=frames)
    assert [t.blur_sigma_px for t in blurred.view_targets] == [pytest.approx((0.75, 0.75))] * 2  # 0.3 mm / 0.4 mm
    plain = build_problem(geometry, masks, make_settings("fast"), "mask", frames=frames)
    assert [t.blur_sigma_px for t in plain.view_targets] == [(0.0, 0.0)] * 2


def test_trimmed_masks_reach_the_losses_and_the_finishing_but_not_the_support(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    plain = build_problem(geometry, masks, make_settings("fast"), "mask", frames=frames)
    trimmed = build_problem(geometry, masks, make_settings("fast", frame_trim_mask_mm=0.3), "mask", frames=frames)
    assert np.array_equal(trimmed.support, plain.support)  # a vessel a pixel off in one view is not forbidden
    for before, after, silhouette in zip(plain.targets, trimmed.targets, (t.silhouette for t in trimmed.view_targets)):
        assert after.sum() < before.sum() and not ((after > 0) & ~(before > 0)).any()
        assert np.array_equal(silhouette.cpu().numpy() > 0, after > 0)  # L_geo reads the trimmed mask
    without_frames = build_problem(geometry, masks, make_settings("fast", frame_trim_mask_mm=0.3), "mask")
    assert all(np.array_equal(a, b) for a, b in zip(without_frames.targets, plain.targets))  # nothing to read it off
    with pytest.raises(ReconstructionError, match="frame_trim_mask_mm"):
        make_settings("fast", frame_trim_mask_mm=-0.1)
    # relative to the centreline the threshold only falls: at least the pixels of the absolute trim stay
    relative = build_problem(geometry, masks, make_settings("fast", frame_trim_mask_mm=0.3, frame_trim_centre_fraction=0.3),
                             "mask", frames=frames)
    for absolute, kept, before in zip(trimmed.targets, relative.targets, plain.targets):
        assert not ((absolute > 0) & ~(kept > 0)).any() and not ((kept > 0) & ~(before > 0)).any()
    with pytest.raises(ReconstructionError, match="frame_trim_centre_fraction"):
        make_settings("fast", frame_trim_centre_fraction=1.0)


def test_the_geometric_losss_tolerance_reaches_the_loss_and_is_checked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    problem = build_problem(geometry, masks, make_settings("fast", dt_tolerance_mm=0.28), "mask", frames=frames)
    assert problem.geometric.settings.tolerance_mm == 0.28
    assert build_problem(geometry, masks, make_settings("fast"), "mask").geometric.settings.tolerance_mm == 0.0
    for bad in (-0.1, 5.0):  # negative, or the whole truncated distance
        with pytest.raises(ReconstructionError, match="dt_tolerance_mm"):
            make_settings("fast", dt_tolerance_mm=bad)


def test_frames_are_ignored_unless_asked_and_checked_when_used(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    assert make_settings("fast").loss.frame_evidence is True  # measured better (bench/RESULTS.md §15)
    assert make_settings("paper").loss.frame_evidence is False  # the published recipe fits masks
    off = reconstruct(geometry, masks, make_settings("fast", steps=5, frame_evidence=False), "mask", frames=frames)
    assert off.report["frame_evidence"] == {"used": False, "why": "frame_evidence is off"}
    on = make_settings("fast", steps=5, frame_evidence=True)
    none = reconstruct(geometry, masks, on, "mask")
    assert none.report["frame_evidence"]["why"] == "no frames were given"
    masks_as_frames = [m.astype(np.float32) * 255.0 for m in masks]  # the sample case's "frames": no evidence, no warning
    binary = reconstruct(geometry, masks, on, "mask", frames=masks_as_frames)
    assert binary.report["frame_evidence"] == {"used": False, "why": "the frames are binary images (masks), not recorded "
                                                                    "X-ray frames"}
    assert not any("frames" in w for w in binary.report["warnings"])
    inverted = [f.max() + 1.0 - f.astype(np.float32) for f in frames]  # vessels bright: not usable, and said so
    fallback = reconstruct(geometry, masks, on, "mask", frames=inverted)
    assert fallback.report["frame_evidence"]["used"] is False
    assert any("frames are not used" in w for w in fallback.report["warnings"])
    with pytest.raises(ReconstructionError, match="1 frame"):
        reconstruct(geometry, masks, on, "mask", frames=frames[:1])
    with pytest.raises(ReconstructionError, match="view 2: the frame has shape"):
        reconstruct(geometry, masks, on, "mask", frames=[frames[0], frames[1][:64]])


def test_the_motion_is_read_from_the_frames_when_asked(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    assert make_settings("fast").calibration.calibrate_from_frames is True  # measured better (bench/RESULTS.md §16)
    assert make_settings("paper").calibration.calibrate_from_frames is False
    settings = make_settings("fast", steps=5)
    result = reconstruct(geometry, masks, settings, "mask", frames=frames)
    calibration = result.report["calibration"]
    assert "consistency" in calibration["method"] and calibration["views"][0]["view"] == 2
    # simulated without motion: the shift found is a fraction of a millimetre (one bent tube pins the
    # rotations only loosely; their accuracy on trees is measured in bench/motion_from_frames.py)
    entry = calibration["views"][0]
    assert abs(entry["shift_across"]["value"]) < 0.5
    corrected = [round(v, 4) for v in result.geometry.views[1].object_translation_mm]
    assert corrected == entry["object_translation_mm"]  # the reconstruction used the corrected pose
    # no motion beyond noise: `fast` prunes once more at the end (prune_last_only_without_motion)
    assert entry["motion_found"] is False and result.report["motion_found"] is False
    assert not (result.report["last_pruning"] or {}).get("skipped")  # (None where 5 steps leave nothing to prune)
    without = reconstruct(geometry, masks, settings, "mask")
    assert without.report["calibration"] == {"method": "none", "why": "no frames to read the motion from"}
    assert without.report["motion_found"] is None and "no pose check" in without.report["last_pruning"]["skipped"]


def test_only_linear_frames_give_path_lengths():
    assert unreadable_intensity("LIN") is None and unreadable_intensity(" lin ") is None
    assert unreadable_intensity(None) is None and unreadable_intensity("") is None  # not known: arrays handed over
    for value, meaning in (("DISP", "processed for display"), ("LOG", "a logarithm"), ("DRM", "a vendor's")):
        why = unreadable_intensity(value)
        assert f"(0028,1040) is {value}" in why and meaning in why and "not LIN" in why
        # a term outside the standard's (a vendor's, or a misspelt LIN) says so and what to give instead
        assert ("none of the standard's terms LIN, LOG, DISP" in why) == (value == "DRM")
    assert "give 'LIN' if the frame's grey levels follow the X-ray intensity" in unreadable_intensity("LINEAR")


def test_a_frame_with_nan_pixels_is_named_not_taken_for_a_mask(angiogram_case):
    geometry, _, frames, masks = angiogram_case
    holed = [frames[0].astype(np.float32), frames[1]]  # detector counts: integers, NaN only once they are floats
    holed[0][:5, :5] = np.nan
    evidence = read_frame_evidence(holed, masks, geometry, make_settings("fast"), "mask")
    assert evidence.images is None and "view 1" in evidence.record["why"]
    assert "25 of the frame's pixels are NaN or infinite" in evidence.record["why"]
    blank = [np.full(frames[0].shape, np.nan, np.float32), frames[1]]  # not "binary images (masks)"
    assert "NaN or infinite" in read_frame_evidence(blank, masks, geometry, make_settings("fast"), "mask").record["why"]


def test_display_processed_frames_place_the_views_but_are_not_fitted(angiogram_case):
    """A frame whose DICOM says its grey levels were processed (DISP, LOG, a vendor's DRM) gives no path lengths:
    L_occ fits the masks, the report and the warnings say which view and why; the line integrals still reach the
    motion search. LIN frames, and frames of no known relationship, are fitted as before."""
    geometry, _, frames, masks = angiogram_case
    settings = make_settings("fast")
    linear = read_frame_evidence(frames, masks, geometry, settings, "mask", ["LIN", None])
    assert linear.fits_path_lengths and linear.record["used"] is True and not linear.warnings
    processed = read_frame_evidence(frames, masks, geometry, settings, "mask", ["LIN", "DISP"])
    assert not processed.fits_path_lengths and processed.record["used"] is False
    assert "view 2" in processed.record["why"] and "DISP" in processed.record["why"] and "view 1" not in processed.record["why"]
    assert processed.record["pixel_intensity_relationship"] == ["LIN", "DISP"]
    assert processed.warnings == [processed.record["why"]]
    for kept, read in zip(processed.images, linear.images):  # the motion search reads the same line integrals
        np.testing.assert_array_equal(kept, read)
    problem = build_problem(geometry, masks, settings, "mask", evidence=processed)
    assert problem.mask_targets is None and problem.evidence["used"] is False  # L_occ fits the masks
    for target, mask in zip(problem.view_targets, masks):
        np.testing.assert_array_equal(target.image.cpu().numpy() > 0, mask > 0)
    assert processed.record["why"] in problem.warnings
    fitted = build_problem(geometry, masks, settings, "mask", evidence=linear)
    assert fitted.mask_targets is not None and fitted.evidence["used"] is True
    with pytest.raises(ReconstructionError, match="1 pixel intensity relationship\\(s\\) for 2 views"):
        read_frame_evidence(frames, masks, geometry, settings, "mask", ["LIN"])


def test_an_eight_bit_frame_nothing_is_known_of_is_taken_as_processed_for_display():
    from SDFCARLib.evidence import DISPLAY_INTENSITY, assumed_frame_intensity, is_eight_bit_frame

    ramp = (np.arange(256 * 4).reshape(32, 32) % 256).astype(np.uint8)
    assert is_eight_bit_frame(ramp) and is_eight_bit_frame(ramp.astype(np.float32))  # as a PNG export reads
    counts = ramp.astype(np.uint16) * 16 + 40  # 12-bit detector counts
    for not_eight_bit in (counts, ramp / 255.0, ramp.astype(np.float32) + 0.5, ramp.astype(np.int16) - 10,
                          (ramp > 100).astype(np.uint8), np.zeros((0, 0), np.uint8)):
        assert not is_eight_bit_frame(not_eight_bit)  # counts, scaled to [0, 1], fractions, negatives, masks
    read, notes = assumed_frame_intensity([ramp, counts], None)
    assert read == [DISPLAY_INTENSITY, None] and len(notes) == 1
    assert notes[0].startswith("view 1:") and "8-bit" in notes[0] and "frame_intensity=['LIN'" in notes[0]
    assert "Grey levels box" in notes[0]  # the fix in Slicer, not a console attribute
    assert assumed_frame_intensity([ramp, counts], ["LIN", None]) == (["LIN", None], [])  # said: kept as said
    assert assumed_frame_intensity([counts, counts], None) == (None, [])  # nothing assumed: as before
    assert assumed_frame_intensity(None, ["LIN", "DISP"]) == (["LIN", "DISP"], [])
    assert assumed_frame_intensity([ramp], ["LIN", None]) == (["LIN", None], [])  # the fit refuses the counts


def test_a_reconstruction_from_eight_bit_frames_fits_the_masks_and_says_why(angiogram_case):
    """Frames handed over as 8-bit images (a viewer's export) with no relationship: their path lengths are not
    fitted, and the report and the warnings say they were taken as processed for display."""
    geometry, _, frames, masks = angiogram_case
    shown = []
    for frame in frames:  # a linear window to 8 bits: still 8-bit grey levels, as a display export is
        lo, hi = np.percentile(frame, [0.5, 99.5])
        shown.append(np.round(np.clip((frame - lo) / (hi - lo), 0, 1) * 255).astype(np.uint8))
    result = reconstruct(geometry, masks, make_settings("fast", steps=5), "mask", frames=shown)
    assert result.report["frame_intensity"] == ["DISP", "DISP"]
    assert len(result.report["frame_intensity_assumed"]) == 2
    assert all(note in result.report["warnings"] for note in result.report["frame_intensity_assumed"])
    assert result.report["frame_evidence"]["used"] is False
    said = reconstruct(geometry, masks, make_settings("fast", steps=5), "mask", frames=shown, frame_intensity=["LIN", "LIN"])
    assert "frame_intensity_assumed" not in said.report and said.report["frame_evidence"]["used"] is True
