"""Vessel widths fitted to a frame's intensity profile: the model in closed form, recovery on simulated angiograms."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.analysis.diameter import projected_widths
from SDFCARLib.analysis.frame_widths import fit_profile, frame_widths
from SDFCARLib.lumen_profile import blurred_chord, chord_mm
from SDFCARLib.analysis.phantoms import grid_around, straight_tube, voxelize_exact
from SDFCARLib.angiogram import AngiogramSettings
from SDFCARLib.geometry import Geometry, standard_geometry

VIEWS = standard_geometry("lao30-rao30").views


def test_blurred_chord_keeps_the_area_and_tends_to_the_chord():
    x = np.linspace(-6.0, 6.0, 4801)
    for radius, sigma in ((0.5, 0.3), (1.5, 0.3), (2.0, 0.6)):
        area = np.trapezoid(blurred_chord(x, 0.3, radius, sigma), x)
        assert area == pytest.approx(np.pi * radius ** 2, rel=2e-3)  # a blur moves absorbance, it does not add any
    np.testing.assert_allclose(blurred_chord(x, 0.0, 1.2, 1e-9), chord_mm(x, 1.2), atol=1e-3)  # √-steep at the wall
    assert chord_mm(np.array([0.0, 1.0, 2.0]), 1.0).tolist() == [2.0, 0.0, 0.0]


@pytest.mark.parametrize("radius", [0.6, 1.0, 2.0])
def test_fit_profile_recovers_the_radius_of_a_noiseless_profile_on_a_sloped_background(radius):
    x = np.arange(-5.0, 5.0, 0.1)
    profile = 1.3 + 0.02 * x + 0.25 * blurred_chord(x, 0.17, radius, 0.3)
    assert fit_profile(x, profile, 0.3, guess_radius_mm=1.4 * radius) == pytest.approx(radius, abs=2e-3)


def test_fit_profile_refuses_profiles_without_a_vessel():
    x = np.arange(-4.0, 4.0, 0.1)
    assert fit_profile(x, np.full(x.shape, 2.0) + 0.01 * x, 0.3, 1.0) is None  # no contrast
    assert fit_profile(x[:5], np.zeros(5), 0.3, 1.0) is None  # too short to fit


def test_frame_widths_measure_the_tube_where_the_segmented_masks_are_off(tube_frames):
    realistic, points, tangents = tube_frames
    psf = AngiogramSettings().psf_sigma_mm
    for frame, mask, view in zip(realistic.frames, realistic.masks, VIEWS):
        from_mask = projected_widths(points, tangents, mask, view)
        from_frame = frame_widths(points, tangents, frame, view, from_mask, psf_sigma_mm=psf)
        assert np.isfinite(from_frame).all()
        assert np.mean(np.abs(from_frame - 2.0)) < 0.1  # the bar for healthy diameters is 0.15 mm
        assert np.mean(np.abs(from_frame - 2.0)) < 0.5 * np.mean(np.abs(from_mask - 2.0))


def test_a_display_processed_frame_is_read_as_log_intensity_not_as_counts(tube_frames):
    """The same tube's frames as a system stores them for display (logarithm, range compression, unsharp masking,
    8-bit window): read as a logarithm of the intensity their widths come out within 0.25 mm; read as counts
    (−log of the grey level) far narrower."""
    from SDFCARLib.display_processing import display_processed

    realistic, points, tangents = tube_frames
    psf = AngiogramSettings().psf_sigma_mm
    for frame, mask, view in zip(realistic.frames, realistic.masks, VIEWS):
        shown = display_processed(frame, view.pixel_spacing_mm)
        guess = projected_widths(points, tangents, mask, view)
        as_log = frame_widths(points, tangents, shown, view, guess, psf_sigma_mm=psf, grey_is_log_intensity=True)
        as_counts = frame_widths(points, tangents, shown, view, guess, psf_sigma_mm=psf)
        assert np.isfinite(as_log).mean() > 0.9
        # (the sharpened edges still narrow the 2 mm tube by about 0.17 mm; counts, by 0.7)
        assert np.nanmean(np.abs(as_log - 2.0)) < 0.25
        assert np.nanmean(as_counts) < 2.0 - 0.4 and np.nanmean(np.abs(as_counts - 2.0)) > 2 * np.nanmean(np.abs(as_log - 2.0))


def test_frame_widths_leave_unmeasurable_points_out_and_reject_bad_input(tube_frames):
    realistic, points, tangents = tube_frames
    frame, view = realistic.frames[0], VIEWS[0]
    guesses = np.full(len(points), 2.0)
    guesses[0] = np.nan
    along_the_ray = np.repeat(view.detector_direction[None], len(points), axis=0)  # seen end-on: no width
    assert np.isnan(frame_widths(points, tangents, frame, view, guesses)[0])
    assert np.isnan(frame_widths(points, along_the_ray, frame, view, guesses)).all()
    far = points + np.array([0.0, 0.0, 500.0])  # projects off the detector
    assert np.isnan(frame_widths(far, tangents, frame, view, guesses)).all()
    with pytest.raises(ValueError, match="detector"):
        frame_widths(points, tangents, frame[:100], view, guesses)
    with pytest.raises(ValueError, match="psf_sigma_mm"):
        frame_widths(points, tangents, frame, view, guesses, psf_sigma_mm=-1.0)


def _tube_result_folder(tmp_path, realistic):
    """A result folder of the 2 mm tube (its exact voxelisation as the occupancy, report.json naming the
    masks), the segmented masks and the frames as files."""
    from SDFCARLib.io import write_image_nrrd, write_json, write_mask_png, write_volume_nrrd

    tube = straight_tube(30.0, 2.0, (0.2, 0.25, 1.0))
    grid = grid_around(tube.tree, 0.3)
    folder = tmp_path / "result"
    folder.mkdir()
    write_volume_nrrd(folder / "occupancy.nrrd", voxelize_exact(tube.tree, grid).astype(np.float32), grid)
    masks = [str(write_mask_png(tmp_path / f"mask{n}.png", m)) for n, m in enumerate(realistic.masks, start=1)]
    frames = [str(write_image_nrrd(tmp_path / f"frame{n}.nrrd", f)) for n, f in enumerate(realistic.frames, start=1)]
    write_json(folder / "report.json", {"geometry": Geometry(grid, VIEWS).to_dict(), "settings": {"threshold": 0.5},
                                        "target_kind": "mask", "inputs": {"targets": masks}})
    return folder, masks, frames


def test_analyse_command_fits_the_frames(tmp_path, tube_frames, capsys):
    import json

    from SDFCARLib.cli import main

    folder, masks, frames = _tube_result_folder(tmp_path, tube_frames[0])
    assert main(["analyse", str(folder), "--frames", *frames, "--view-step-deg", "20"]) == 0
    branch = json.loads((folder / "analysis" / "analysis.json").read_text())["branches"][0]
    assert branch["diameter_frames"]["mean_mm"] == pytest.approx(2.0, abs=0.15)
    assert abs(branch["diameter_masks"]["mean_mm"] - 2.0) > abs(branch["diameter_frames"]["mean_mm"] - 2.0)
    import csv

    with open(folder / "analysis" / "profile_branch00.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {"diameter_frames_mm", "frame_width_view1_mm", "frame_width_view2_mm", "diameter_frames_density_mm",
            "density_views", "crowded_views"} <= set(rows[0])
    # one tube: no other vessel crowds either view, and both views' areas make the density wherever it is read
    assert all(r["crowded_views"] == "" for r in rows)
    assert {r["density_views"] for r in rows if r["diameter_frames_density_mm"]} == {"1+2"}
    assert branch["diameter_frames_density"]["mean_mm"] == pytest.approx(2.0, abs=0.15)
    capsys.readouterr()
    assert main(["analyse", str(folder), "--frames", frames[0], "--out", str(tmp_path / "a2")]) == 2
    assert "1 frames for 2 views" in capsys.readouterr().err
    assert main(["analyse", str(folder), "--frames", *frames, "--psf-sigma-mm", "-1", "--out", str(tmp_path / "a3")]) == 2
    assert "--psf-sigma-mm" in capsys.readouterr().err


@pytest.mark.parametrize("spoil, message", [
    ("masks", "two grey levels or fewer: it looks like a mask"),
    ("scaled", "no grey level above 1"),
    ("nan", "NaN or infinite"),
    ("inverted", "brighter than their surroundings under every mask"),
])
def test_frames_that_cannot_be_the_detector_s_are_refused_before_any_work(tmp_path, tube_frames, capsys, spoil, message):
    from SDFCARLib.cli import main
    from SDFCARLib.io import write_image_nrrd

    realistic = tube_frames[0]
    folder, masks, frames = _tube_result_folder(tmp_path, realistic)
    if spoil == "masks":
        given = masks  # the masks handed over as frames: widths fitted to a step, lesions graded "on the frames"
    else:
        frame = realistic.frames[1].astype(np.float64)
        frame = frame / frame.max() if spoil == "scaled" else np.where(np.arange(frame.shape[1]) < 5, np.nan, frame)
        given = [frames[0], str(write_image_nrrd(tmp_path / "spoilt.nrrd", frame))]
        if spoil == "inverted":  # both frames with the vessels white, as a negative display shows them
            given = [str(write_image_nrrd(tmp_path / f"inverted{n}.nrrd", f.max() + f.min() - f.astype(np.float64)))
                     for n, f in enumerate(realistic.frames, start=1)]
    capsys.readouterr()
    assert main(["analyse", str(folder), "--frames", *given, "--view-step-deg", "20"]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert {"masks": "frame of view 1", "inverted": "view 2 -"}.get(spoil, "frame of view 2") in err
    assert not (folder / "analysis").exists()


def test_vessel_contrast_is_the_darkening_under_the_mask_in_units_of_the_background_noise():
    from SDFCARLib.analysis.frame_contrast import check_vessels_dark, vessel_contrast

    rows, cols = np.mgrid[:64, :64]
    mask = (np.abs(rows - 32) <= 3) & (cols > 8) & (cols < 56)  # a 7-pixel vessel
    noise = np.random.default_rng(1).normal(0.0, 10.0, mask.shape)
    frame = 1000.0 + noise - 100.0 * mask  # the lumen 100 below the background, noise σ 10
    assert vessel_contrast(frame, mask) == pytest.approx(10.0, rel=0.15)
    assert vessel_contrast(2000.0 - frame, mask) == pytest.approx(-10.0, rel=0.15)
    assert vessel_contrast(1000.0 + noise, mask) == pytest.approx(0.0, abs=0.3)
    assert vessel_contrast(frame, np.zeros_like(mask)) is None
    with pytest.raises(ValueError, match="differs from its mask"):
        vessel_contrast(frame[:, :32], mask)
    with pytest.raises(ValueError, match="frame of view 2: frame shape"):
        check_vessels_dark([frame, frame[:, :32]], [mask, mask])
    with pytest.raises(ValueError, match="brighter than their surroundings under every mask"):
        check_vessels_dark([2000.0 - frame, 2000.0 - frame], [mask, mask])
    one_inverted = check_vessels_dark([frame, 2000.0 - frame], [mask, mask])  # a vessel seen end-on can read so
    assert one_inverted[0] > 5.0 and one_inverted[1] < -5.0


def test_frames_that_show_no_vessel_under_their_masks_are_warned_of_by_view(tmp_path, tube_frames):
    import json

    from SDFCARLib.cli import main
    from SDFCARLib.io import write_image_nrrd

    realistic = tube_frames[0]
    folder, masks, frames = _tube_result_folder(tmp_path, realistic)
    frame = realistic.frames[1].astype(np.float64)
    # view 2's frame without its vessel: the background's level and noise only
    blank = np.median(frame) + np.random.default_rng(0).normal(0.0, 30.0, frame.shape)
    inverted = str(write_image_nrrd(tmp_path / "inverted.nrrd", frame.max() + frame.min() - frame))
    cases = {"right": frames, "swapped": frames[::-1], "one inverted": [frames[0], inverted],
             "blank": [frames[0], str(write_image_nrrd(tmp_path / "blank.nrrd", blank.astype(np.uint16)))]}
    found = {}
    for name, given in cases.items():
        assert main(["analyse", str(folder), "--frames", *given, "--view-step-deg", "20", "--out", str(tmp_path / name)]) == 0
        data = json.loads((tmp_path / name / "analysis.json").read_text())
        found[name] = (data["settings"]["frame_vessel_contrast"], data["settings"]["frame_widths_measured"],
                       [w for w in data["warnings"] if w.startswith("frames:")])
    contrast, measured, warned = found["right"]
    assert min(contrast) > 1.0 and min(measured) > 0.9 and warned == []
    contrast, measured, warned = found["swapped"]
    assert max(contrast) < 0.6 and len(warned) == 1
    assert "view 1: the vessels hardly stand out" in warned[0] and "view 2: the vessels hardly stand out" in warned[0]
    contrast, measured, warned = found["one inverted"]
    assert contrast[0] > 1.0 and contrast[1] < -0.75 and len(warned) == 1
    assert "view 1:" not in warned[0] and "view 2: its frame is brighter under its mask than around it" in warned[0]
    contrast, measured, warned = found["blank"]
    assert contrast[0] > 1.0 and abs(contrast[1]) < 0.6 and measured == [1.0, 0.0] and len(warned) == 1
    assert "view 1:" not in warned[0] and "view 2: the vessels hardly stand out" in warned[0]
    assert "gave no width" in warned[0] and "rest on view 1 alone" in warned[0]


def test_a_blur_or_a_view_step_out_of_range_is_refused_before_any_work(tmp_path, tube_frames, capsys):
    from SDFCARLib.cli import main

    folder, masks, frames = _tube_result_folder(tmp_path, tube_frames[0])
    capsys.readouterr()
    assert main(["analyse", str(folder), "--frames", *frames, "--psf-sigma-mm", "1e9"]) == 2
    assert "0 to 2" in capsys.readouterr().err
    assert main(["analyse", str(folder), "--view-step-deg", "0.01"]) == 2
    assert "from 0.5°" in capsys.readouterr().err
    assert not (folder / "analysis").exists()


def test_analysis_job_passes_frames_as_options(tmp_path, tube_frames):
    """The path the Slicer module's analyse(resultNode, options=…) takes: a job folder run in this process."""
    import json

    from SDFCARLib.jobs import prepare_analysis_job, run_analysis_job

    folder, masks, frames = _tube_result_folder(tmp_path, tube_frames[0])
    job = prepare_analysis_job(tmp_path / "job", folder, masks=masks,
                               options={"frames": frames, "psf_sigma_mm": 0.3, "view_step_deg": 20.0})
    files = run_analysis_job(job)
    branch = json.loads(open(files["analysis.json"]).read())["branches"][0]
    assert branch["diameter_frames"]["mean_mm"] == pytest.approx(2.0, abs=0.15)


def test_the_blur_is_estimated_from_the_frames(tmp_path, tube_frames, capsys):
    import json

    from SDFCARLib.analysis.frame_widths import estimate_psf_sigma_mm
    from SDFCARLib.cli import main

    realistic, points, tangents = tube_frames
    simulated = AngiogramSettings().psf_sigma_mm
    for frame, mask, view in zip(realistic.frames, realistic.masks, VIEWS):
        guesses = projected_widths(points, tangents, mask, view)
        assert estimate_psf_sigma_mm(points, tangents, frame, view, guesses) == pytest.approx(simulated, abs=0.1)
        assert estimate_psf_sigma_mm(points[:5], tangents[:5], frame, view, guesses[:5]) is None  # too few profiles
    folder, _, frames = _tube_result_folder(tmp_path, realistic)
    assert main(["analyse", str(folder), "--frames", *frames, "--psf-sigma-mm", "auto", "--view-step-deg", "20"]) == 0
    data = json.loads((folder / "analysis" / "analysis.json").read_text())
    assert data["settings"]["psf_sigma_estimated"] == [True, True]
    assert all(s == pytest.approx(simulated, abs=0.1) for s in data["settings"]["psf_sigma_mm"])
    assert data["branches"][0]["diameter_frames"]["mean_mm"] == pytest.approx(2.0, abs=0.15)
    capsys.readouterr()
    assert main(["analyse", str(folder), "--frames", *frames, "--psf-sigma-mm", "wide", "--out", str(tmp_path / "a4")]) == 2
    assert "'auto'" in capsys.readouterr().err


def test_frames_of_display_processed_runs_give_widths_but_no_lumen_area(tmp_path, tube_frames, capsys):
    """Where report.json says one of the reconstruction's DICOM runs was processed for display (DISP), that
    frame's absorbance is no path length: its widths are still fitted to its edges, no densitometric area is
    read from it, and the analysis says why; the other view's LIN frame keeps its densitometry."""
    import json

    from SDFCARLib.cli import main

    from SDFCARLib.display_processing import display_processed
    from SDFCARLib.io import write_image_nrrd

    folder, masks, frames = _tube_result_folder(tmp_path, tube_frames[0])
    report = json.loads((folder / "report.json").read_text())
    (folder / "report.json").write_text(json.dumps(dict(report, frame_intensity=["LIN", "DISP"])))
    # view 2's frame as that run stored it (its widths are read on the grey level as log-intensity)
    linear_frames = list(frames)
    frames[1] = str(write_image_nrrd(tmp_path / "frame2_disp.nrrd", display_processed(tube_frames[0].frames[1],
                                                                                      VIEWS[1].pixel_spacing_mm)))
    assert main(["analyse", str(folder), "--frames", *frames, "--view-step-deg", "20"]) == 0
    err = capsys.readouterr().err
    data = json.loads((folder / "analysis" / "analysis.json").read_text())
    branch = data["branches"][0]
    assert branch["diameter_frames"]["mean_mm"] == pytest.approx(2.0, abs=0.15)  # the edges
    settings = data["settings"]
    assert settings["densitometry"] == [True, False] and settings["psf_sigma_estimated"] == [False, True]
    assert settings["attenuation_per_mm"][0] > 0 and settings["attenuation_per_mm"][1] is None
    assert branch["diameter_frames_density"]["mean_mm"] == pytest.approx(2.0, abs=0.15)  # view 1's areas alone
    [note] = [n for n in data["notes"] if "densitometry" in n]
    assert "view 2" in note and "DISP" in note and "view 1" not in note and "from the other views" in note
    assert "DISP" in err
    (folder / "report.json").write_text(json.dumps(dict(report, frame_intensity=["DISP", "DISP"])))
    both = list(frames)
    both[0] = str(write_image_nrrd(tmp_path / "frame1_disp.nrrd", display_processed(tube_frames[0].frames[0],
                                                                                    VIEWS[0].pixel_spacing_mm)))
    assert main(["analyse", str(folder), "--frames", *both, "--view-step-deg", "20", "--out", str(tmp_path / "d")]) == 0
    shown = json.loads((tmp_path / "d" / "analysis.json").read_text())
    assert shown["branches"][0]["diameter_frames_density"] is None and shown["settings"]["densitometry"] == [False, False]
    assert shown["branches"][0]["diameter_frames"]["mean_mm"] == pytest.approx(2.0, abs=0.15)
    assert any("the frames' widths are fitted to their edges" in n for n in shown["notes"])
    (folder / "report.json").write_text(json.dumps(dict(report, frame_intensity=["LIN", "LIN"])))
    assert main(["analyse", str(folder), "--frames", *linear_frames, "--view-step-deg", "20", "--overwrite"]) == 0
    linear = json.loads((folder / "analysis" / "analysis.json").read_text())
    assert linear["branches"][0]["diameter_frames_density"]["mean_mm"] == pytest.approx(2.0, abs=0.15)
    assert linear["settings"]["densitometry"] == [True, True] and not linear["notes"]


def test_the_frame_diameters_reach_the_slicer_profile_table(tmp_path, tube_frames):
    pytest.importorskip("slicer", reason="needs the slicer-core package (pip install slicer-core)")
    from SDFCARLib.analysis.mrml_nodes import add_analysis_nodes
    from SDFCARLib.analysis.outputs import analyse_result_dir
    from SDFCARLib.mrml import new_scene

    folder, masks, frames = _tube_result_folder(tmp_path, tube_frames[0])
    analyse_result_dir(folder, masks=masks, frames=frames, view_step_deg=20.0)
    scene = new_scene()
    table = add_analysis_nodes(scene, folder / "analysis")["series"][0].GetTableNode().GetTable()
    for column in ("diameter_frames_mm", "diameter_frames_density_mm"):
        array = table.GetColumnByName(column)
        values = np.array([array.GetValue(i) for i in range(array.GetNumberOfTuples())])
        assert np.nanmedian(values) == pytest.approx(2.0, abs=0.15), column
    analyse_result_dir(folder, masks=masks, out_dir=tmp_path / "no-frames", view_step_deg=20.0)
    plain_scene = new_scene()
    plain = add_analysis_nodes(plain_scene, tmp_path / "no-frames")["series"][0].GetTableNode().GetTable()
    assert plain.GetColumnByName("diameter_frames_mm") is None


def test_on_display_processed_frames_the_blur_is_estimated_unless_given(tmp_path, tube_frames):
    """A DISP run's sharpening is no detector blur: by default analyse estimates the blur of such frames (report.json
    says they were processed for display) and keeps 0.3 mm on frames that hold the intensity."""
    import json

    from SDFCARLib.analysis.pipeline import psf_for_frames
    from SDFCARLib.cli import main
    from SDFCARLib.display_processing import display_processed
    from SDFCARLib.io import write_image_nrrd, write_json
    from SDFCARLib.lumen_profile import DEFAULT_PSF_SIGMA_MM, PSF_BY_FRAMES

    realistic, _, _ = tube_frames
    folder, _, frames = _tube_result_folder(tmp_path, realistic)
    assert main(["analyse", str(folder), "--frames", *frames, "--view-step-deg", "20"]) == 0
    linear = json.loads((folder / "analysis" / "analysis.json").read_text())["settings"]
    assert linear["psf_sigma_estimated"] == [False, False] and linear["psf_sigma_mm"] == [DEFAULT_PSF_SIGMA_MM] * 2
    shown = [str(write_image_nrrd(tmp_path / f"shown{n}.nrrd", display_processed(f, v.pixel_spacing_mm)))
             for n, (f, v) in enumerate(zip(realistic.frames, VIEWS), start=1)]
    report = json.loads((folder / "report.json").read_text())
    write_json(folder / "report.json", {**report, "frame_intensity": ["DISP", "DISP"]})
    diameters = {}
    for name, extra in (("default", []), ("given", ["--psf-sigma-mm", "0.3"])):
        assert main(["analyse", str(folder), "--frames", *shown, "--view-step-deg", "20", "--out",
                     str(tmp_path / name)] + extra) == 0
        data = json.loads((tmp_path / name / "analysis.json").read_text())
        diameters[name] = data["branches"][0]["diameter_frames"]["mean_mm"]
        if name == "default":  # estimated: sharper than the detector's 0.3 mm
            assert data["settings"]["psf_sigma_estimated"] == [True, True]
            assert all(0.05 < s < 0.25 for s in data["settings"]["psf_sigma_mm"])
        else:
            assert data["settings"]["psf_sigma_estimated"] == [False, False]
    # the sharpened edges narrow the 2 mm tube less read with the estimated blur
    assert abs(diameters["default"] - 2.0) < abs(diameters["given"] - 2.0)
    assert psf_for_frames(PSF_BY_FRAMES, True) == DEFAULT_PSF_SIGMA_MM and psf_for_frames(PSF_BY_FRAMES, False) is None
    assert psf_for_frames(0.4, False) == 0.4 and psf_for_frames(None, True) is None
    with pytest.raises(ValueError, match="psf_sigma_mm"):
        psf_for_frames("fast", True)
