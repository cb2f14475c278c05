"""SDFCARLib.qa: per-view reprojection QA numbers, the overlay image, the warning, and the result folder."""

from __future__ import annotations

import json
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from SDFCARLib.geometry import CArmView
from SDFCARLib.qa import (AGREE_RGB, LEGEND, LEGEND_HEIGHT_PX, MASK_ONLY_RGB, ONE_VIEW_RGB, OUTLINE_RGB,
                          RESULT_ONLY_RGB, qa_overlay_rgb, qa_summary, qa_summary_lines, qa_warnings, reprojection_qa)

# Magnification 1000 / 800 = 1.25: 0.5 mm detector pixels are 0.4 mm at the isocenter, 0.16 mm².
VIEW = CArmView(0.0, 0.0, 1000.0, 800.0, (0.5, 0.5), (60, 80))
PIXEL_MM2 = 0.16


def _constructed():
    """A vessel both show; an extra bar only the mask has; a blob and a one-pixel rim only the result has."""
    mask = np.zeros((60, 80), dtype=bool)
    mask[10:16, 5:55] = True  # 300 px, both
    mask[40:44, 10:40] = True  # 120 px, mask only
    projected = np.zeros_like(mask)
    projected[10:16, 5:55] = True
    projected[16, 5:55] = True  # 50 px rim, result only, not a blob
    projected[20:28, 60:70] = True  # 80 px, result only
    return projected, mask


def test_areas_in_isocenter_mm2_and_largest_blobs():
    projected, mask = _constructed()
    qa = reprojection_qa(projected, mask, VIEW)
    assert qa["area_plane"] == "isocenter" and qa["pixel_area_mm2"] == pytest.approx(PIXEL_MM2)
    assert qa["pixels"] == {"agree": 300, "result_only": 130, "mask_only": 120}
    assert qa["area_mm2"]["agree"] == pytest.approx(48.0)
    assert qa["area_mm2"]["result_only"] == pytest.approx(20.8)
    assert qa["area_mm2"]["mask_only"] == pytest.approx(19.2)
    assert qa["mask_area_mm2"] == pytest.approx(420 * PIXEL_MM2)
    assert qa["dice"] == pytest.approx(600 / 850)
    assert qa["share_of_mask"]["mask_only"] == pytest.approx(120 / 420)
    ghost = qa["largest_blob"]["result_only"]  # the rim is wider than the blob is tall, yet is no blob
    assert ghost["pixels"] == 80 and ghost["area_mm2"] == pytest.approx(12.8)
    assert ghost["centroid_rc"] == pytest.approx([23.5, 64.5]) and ghost["bbox_rc"] == [20, 60, 27, 69]
    missing = qa["largest_blob"]["mask_only"]
    assert missing["pixels"] == 120 and missing["area_mm2"] == pytest.approx(19.2)
    assert missing["centroid_rc"] == pytest.approx([41.5, 24.5]) and missing["bbox_rc"] == [40, 10, 43, 39]


def test_perfect_agreement_has_no_blob_and_no_warning():
    _, mask = _constructed()
    qa = reprojection_qa(mask, mask, VIEW)
    assert qa["dice"] == 1.0 and qa["pixels"]["result_only"] == qa["pixels"]["mask_only"] == 0
    assert qa["largest_blob"] == {"result_only": None, "mask_only": None}
    assert qa_warnings([qa, qa]) == []


def test_rims_alone_do_not_warn():
    _, mask = _constructed()
    projected = mask.copy()
    projected[16, 5:55] = True  # a one-pixel rim along the vessel: 50 px, 12 % of the mask, no blob
    projected[9, 5:55] = False
    qa = reprojection_qa(projected, mask, VIEW)
    assert qa["largest_blob"]["result_only"] is None and qa["largest_blob"]["mask_only"] is None
    assert qa_warnings([qa], share=0.2) == []
    assert len(qa_warnings([qa], share=0.1)) == 1  # but the share still counts


def test_warning_names_the_view_the_place_and_what_to_check():
    projected, mask = _constructed()
    good = reprojection_qa(mask, mask, VIEW)
    warnings = qa_warnings([good, reprojection_qa(projected, mask, VIEW)])
    assert len(warnings) == 2 and all(w.startswith("view 2:") for w in warnings)
    ghost, missing = warnings
    assert "12.8 mm²" in ghost and "row 24, column 64" in ghost and "ghost branch" in ghost and "qa_view2.png" in ghost
    assert "19.2 mm²" in missing and "row 42, column 24" in missing
    assert "frame" in missing and "angles" in missing and "this view only" in missing


def _one_view_centreline(rows=slice(41, 42), cols=slice(10, 40)):
    """The centreline of the mask-only bar (rows 40–43): a vessel the check before the run found only this view shows."""
    centreline = np.zeros((60, 80), dtype=bool)
    centreline[rows, cols] = True
    return centreline


def test_a_blob_along_a_vessel_only_this_view_shows_is_named_as_such():
    projected, mask = _constructed()
    plain = reprojection_qa(projected, mask, VIEW)
    assert "one_view_area_mm2" not in plain and "one_view_share" not in plain["largest_blob"]["mask_only"]
    qa = reprojection_qa(projected, mask, VIEW, _one_view_centreline())
    assert qa["pixels"] == plain["pixels"] and qa["dice"] == plain["dice"]  # the numbers do not change
    # the bar's every pixel is within reach of its centreline, and the result explains none of it
    assert qa["one_view_area_mm2"] == pytest.approx({"mask": 120 * PIXEL_MM2, "mask_only": 120 * PIXEL_MM2})
    assert qa["largest_blob"]["mask_only"]["one_view_share"] == 1.0
    assert qa["largest_blob"]["result_only"]["one_view_share"] == 0.0
    good = reprojection_qa(mask, mask, VIEW)
    ghost, missing = qa_warnings([good, qa])
    assert ghost == qa_warnings([good, plain])[0]
    assert missing.startswith("view 2: the result does not explain 19.2 mm²") and "row 42, column 24" in missing
    assert "only this view shows" in missing and "reddish purple" in missing and "check the angles" in missing
    assert missing != qa_warnings([good, plain])[1]
    # the centreline of another vessel (the one both show): the blob is not along it, the old warning stands
    elsewhere = reprojection_qa(projected, mask, VIEW, _one_view_centreline(slice(12, 13), slice(5, 55)))
    assert elsewhere["largest_blob"]["mask_only"]["one_view_share"] == 0.0
    assert elsewhere["one_view_area_mm2"]["mask_only"] == 0.0 < elsewhere["one_view_area_mm2"]["mask"]
    assert qa_warnings([good, elsewhere]) == qa_warnings([good, plain])
    # a short stretch of the bar: the largest blob is not mostly along it, but the area there is named
    part = reprojection_qa(projected, mask, VIEW, _one_view_centreline(slice(41, 42), slice(10, 14)))
    assert part["largest_blob"]["mask_only"]["one_view_share"] < 0.5
    (_, partly) = qa_warnings([good, part])
    assert partly.startswith(qa_warnings([good, plain])[1].split("; check")[0])
    assert f"; {part['one_view_area_mm2']['mask_only']:.1f} mm² of it lies along vessels that only this view shows" in partly
    with pytest.raises(ValueError, match="one-view centreline image"):
        reprojection_qa(projected, mask, VIEW, _one_view_centreline()[:50])
    # the status panel's line (Slicer's Results section) says it too, and only where there is such an area
    plain_line, marked_line, elsewhere_line = (qa_summary_lines({"reprojection_qa": [q]})[0] for q in (plain, qa, elsewhere))
    assert marked_line == plain_line + ", 19.2 mm² of it where only this view sees" and elsewhere_line == plain_line
    assert qa_summary({"reprojection_qa": [plain]})[0]["one_view_mask_only_mm2"] is None


def test_shape_mismatch_is_refused():
    projected, mask = _constructed()
    with pytest.raises(ValueError, match="shape"):
        reprojection_qa(projected[:50], mask, VIEW)
    with pytest.raises(ValueError, match="detector"):
        reprojection_qa(projected[:50], mask[:50], VIEW)


def _colour(image, r, c):
    return tuple(int(v) for v in image[r, c])


def test_overlay_has_the_palette_in_place_the_outlines_and_a_legend():
    projected, mask = _constructed()
    image = qa_overlay_rgb(None, projected, mask, title="view 2")
    assert image.dtype == np.uint8 and image.shape[0] == 60 + LEGEND_HEIGHT_PX and image.shape[1] >= 80
    detector = image[:60, :80]
    assert _colour(detector, 12, 30) == AGREE_RGB
    assert _colour(detector, 16, 30) == RESULT_ONLY_RGB and _colour(detector, 23, 64) == RESULT_ONLY_RGB
    assert _colour(detector, 41, 24) == MASK_ONLY_RGB
    assert _colour(detector, 2, 2) == (0, 0, 0)
    # One-pixel boxes two pixels outside each largest blob.
    assert _colour(detector, 18, 58) == _colour(detector, 29, 71) == _colour(detector, 23, 58) == OUTLINE_RGB
    assert _colour(detector, 38, 8) == _colour(detector, 45, 41) == OUTLINE_RGB
    assert _colour(detector, 19, 59) == (0, 0, 0)
    expected = np.zeros((60, 80, 3), dtype=np.uint8)
    expected[projected & mask] = AGREE_RGB
    expected[projected & ~mask] = RESULT_ONLY_RGB
    expected[mask & ~projected] = MASK_ONLY_RGB
    not_outline = ~np.all(detector == OUTLINE_RGB, axis=-1)
    np.testing.assert_array_equal(detector[not_outline], expected[not_outline])
    legend = image[60:]
    for _, colour in LEGEND:
        assert np.all(legend == colour, axis=-1).sum() >= 50, colour  # a swatch of 10 × 9 pixels
    assert (legend.min(axis=-1) > 200).sum() > 100  # the text, white (anti-aliased)


def test_overlay_draws_the_centreline_of_vessels_only_this_view_shows_over_the_colours():
    projected, mask = _constructed()
    centreline = _one_view_centreline()
    plain = qa_overlay_rgb(None, projected, mask)
    marked = qa_overlay_rgb(None, projected, mask, one_view=centreline)
    assert plain.shape == marked.shape
    detector = marked[:60, :80]
    assert np.all(detector[centreline] == ONE_VIEW_RGB)
    assert _colour(detector, 40, 24) == _colour(detector, 42, 24) == MASK_ONLY_RGB  # the vessel's colour either side
    np.testing.assert_array_equal(detector[~centreline], plain[:60, :80][~centreline])
    assert not np.all(plain[:60, :80] == ONE_VIEW_RGB, axis=-1).any()
    with pytest.raises(ValueError, match="one-view centreline image"):
        qa_overlay_rgb(None, projected, mask, one_view=centreline[:, :10])


def test_overlay_shows_the_frame_in_grey_under_the_colours():
    projected, mask = _constructed()
    frame = np.tile(np.linspace(0.0, 1000.0, 80), (60, 1))
    image = qa_overlay_rgb(frame, projected, mask)[:60, :80]
    background = ~(projected | mask)
    background[np.all(image == OUTLINE_RGB, axis=-1)] = False
    grey = image[background]
    assert np.all(grey[:, 0] == grey[:, 1]) and np.all(grey[:, 1] == grey[:, 2])
    assert image[30, 79, 0] > image[30, 0, 0]  # brighter where the frame is
    assert _colour(image, 41, 24) == MASK_ONLY_RGB and _colour(image, 12, 30) == AGREE_RGB
    with pytest.raises(ValueError, match="frame"):
        qa_overlay_rgb(frame[:10], projected, mask)


def test_result_folder_holds_the_overlays_and_the_report_the_numbers(tmp_path, tiny_geometry, tiny_case, monkeypatch):
    from SDFCARLib.optimiser import reconstruct, reprojected_masks
    from SDFCARLib.outputs import OutputError, check_destination, result_file_names, write_reconstruction
    from SDFCARLib.settings import make_settings

    monkeypatch.setitem(sys.modules, "SDFCARLib.mrml", None)  # no scene: faster, and not what is tested here
    masks = [m.astype(bool) for m in tiny_case.masks]
    result = reconstruct(tiny_geometry, masks, make_settings("fast", steps=3, threads=1))
    files = write_reconstruction(result, tmp_path / "result")
    report = json.loads(files["report"].read_text())
    qa = report["reprojection_qa"]
    assert len(qa) == 2 and report["reprojection_dice"] == [q["dice"] for q in qa]
    assert report["files"]["qa_view1"] == "qa_view1.png" and report["files"]["qa_view2"] == "qa_view2.png"
    projected = reprojected_masks(result.segmentation, tiny_geometry)
    for n in (1, 2):
        assert files[f"qa_view{n}"] == tmp_path / "result" / f"qa_view{n}.png"
        image = iio.imread(files[f"qa_view{n}"])
        assert image.shape[0] == 96 + LEGEND_HEIGHT_PX and image.shape[2] == 3
        np.testing.assert_array_equal(result.qa_masks[n - 1][0], projected[n - 1])
        np.testing.assert_array_equal(result.qa_masks[n - 1][1], masks[n - 1])
        numbers = reprojection_qa(projected[n - 1], masks[n - 1], tiny_geometry.views[n - 1])
        assert qa[n - 1]["pixels"] == numbers["pixels"]
        assert qa[n - 1]["area_mm2"]["mask_only"] == pytest.approx(numbers["area_mm2"]["mask_only"])
    for message in qa_warnings(qa):
        assert message in report["warnings"]
    assert "qa_view2.png" in result_file_names(2)
    with pytest.raises(OutputError, match="qa_view1.png"):
        check_destination(tmp_path / "result", result_file_names(2))


def test_the_summary_names_the_pieces_of_the_result_and_the_largest_share():
    from SDFCARLib.metrics import component_counts
    from SDFCARLib.qa import pieces_line

    volume = np.zeros((12, 12, 12), bool)
    volume[1:4, 1:4, 1:4] = True  # 27 voxels
    volume[8, 8, 2:11] = True  # 9 voxels, apart
    report = {"components": component_counts(volume), "reconnection": {"max_gap_mm": 8.0}}
    line = pieces_line(report)
    assert line.startswith("The result is in 2 pieces (26-connected voxels); the largest holds 75 % of them.")
    assert "no bridge to within 8 mm, or ghosts" in line
    volume[4, 4, 4] = volume[5:8, 5:8, 3] = True  # joined through diagonal contacts: one piece
    assert pieces_line({"components": component_counts(volume)}) == "The result is one piece (26-connected voxels)."
    unjoined = pieces_line({"components": {"components": 3, "largest_component_fraction": 0.5}, "reconnection": None})
    assert "holds 50 % of them" in unjoined and "joined no pieces (the reconnect setting is off)" in unjoined
    assert pieces_line({"components": {"components": 2, "largest_component_fraction": 0.9}}).endswith(
        "one piece per ostium: the others are broken-off vessels or ghosts; look at them in 3D and on the QA overlays.")
    assert pieces_line({}) is None and pieces_line({"components": {"components": 0}}) is None
