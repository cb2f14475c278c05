"""LOG frames brought to a linear intensity scale where DICOM frames are read (dicom/intensity.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from SDFCARLib import dicom
from SDFCARLib.dicom.intensity import (LINEAR_PEAK_COUNTS, LOG_SPAN_E_FOLDS, IntensityTags, intensity_tags_of_file,
                                       linear_from_log, linearised, rising_from_falling)
from SDFCARLib.evidence import unreadable_intensity, view_evidence
from SDFCARLib.geometry import CArmView
from xa_writer import write_xa

PIXEL_MM = 0.2
VIEW = CArmView(30.0, 0.0, 1000.0, 750.0, (PIXEL_MM, PIXEL_MM), (200, 200))
BITS = 12


def _tube_frame():
    """Counts (float) of a 2 mm tube on a sloping background (Beer–Lambert, μ 0.25 per detector mm), and its mask."""
    x = (np.arange(200) - 100) * PIXEL_MM
    chord = 2.0 * np.sqrt(np.clip(1.0 - x ** 2, 0.0, None))
    length = np.zeros((200, 200))
    length[20:180] = chord[None, :]
    length = ndimage.gaussian_filter(length, 0.3 / PIXEL_MM)
    background = 0.4 + 0.3 * np.linspace(0.0, 1.0, 200)[:, None]
    return 3000.0 * np.exp(-0.25 * length - background), length > 0.05


def _log_stored(counts, sign):
    """The LOG encoding of ``counts`` in 12 stored bits: affine in ln I, increasing with intensity for sign +1."""
    log = np.log(counts)
    scaled = (log - log.min()) / (log.max() - log.min()) * 3000.0 + 500.0  # a slope nobody records
    return np.round(scaled if sign > 0 else 4095.0 - scaled).astype(np.uint16)


def test_a_log_frame_on_the_linear_scale_gives_the_linear_frames_path_lengths():
    counts, mask = _tube_frame()
    linear = view_evidence(counts.astype(np.float32), mask, VIEW)
    stored = _log_stored(counts, +1)
    frame = linear_from_log(stored, True, BITS)
    assert frame.dtype == np.float32 and frame.max() == pytest.approx(LINEAR_PEAK_COUNTS)
    # −log of the result is affine in the stored values: LOG_SPAN_E_FOLDS over the 2^12 values
    np.testing.assert_allclose(-np.log(frame), (stored.max() - stored) * LOG_SPAN_E_FOLDS / 4096 - np.log(LINEAR_PEAK_COUNTS),
                               atol=1e-5)
    read = view_evidence(frame, mask, VIEW)
    # the slope is unknown: μ takes it (here 8/4096 e-folds per stored step, 3000 steps over the frame's log range)
    span = np.log(counts.max()) - np.log(counts.min())
    assert read.attenuation_per_mm == pytest.approx(linear.attenuation_per_mm * 3000.0 * 8 / 4096 / span, rel=0.01)
    # ... and the path lengths, what the fit uses, are the linear frame's
    inside = mask & (linear.line_integral_mm > 0.5)
    np.testing.assert_allclose(read.line_integral_mm[inside], linear.line_integral_mm[inside], rtol=0.02, atol=0.02)


def test_the_sign_and_the_photometric_interpretation_say_which_way_the_stored_values_run():
    counts, _ = _tube_frame()
    up, down = _log_stored(counts, +1), _log_stored(counts, -1)
    expected = linear_from_log(up, True, BITS)
    for values, tags, inverted in (
            (up, IntensityTags("LOG", 1, "MONOCHROME2", BITS), False),
            (down, IntensityTags("LOG", -1, "MONOCHROME2", BITS), False),
            (4095.0 - down, IntensityTags("LOG", -1, "MONOCHROME1", BITS), True),  # load_xa mirrors MONOCHROME1
            (down, IntensityTags("LOG", -1, "MONOCHROME1", BITS), False),  # the stored values, not mirrored
            (up, IntensityTags("LOG", None, "MONOCHROME2", BITS), False),  # no sign: brighter is more intensity
            (4095.0 - down, IntensityTags("LOG", None, "MONOCHROME1", BITS), True)):
        frame, relationship, note = linearised(values, tags, inverted)
        assert relationship == "LIN" and "LOG" in note and "linear scale" in note
        assert ("(0028,1041)" in note) and (("taken as" in note) == (tags.sign is None))
        np.testing.assert_allclose(frame, expected, rtol=1e-5)
    for tags in (None, IntensityTags("LIN", 1, "MONOCHROME2", BITS), IntensityTags("DISP", None, "MONOCHROME2", 8),
                 IntensityTags(None, None, "MONOCHROME2", BITS)):
        frame, relationship, note = linearised(up, tags)
        assert frame is up and note is None and relationship == (None if tags is None else tags.relationship)


def test_load_xa_gives_log_runs_as_linear_frames_and_says_so(tmp_path):
    counts, mask = _tube_frame()
    stored = _log_stored(counts, -1)
    path = write_xa(tmp_path / "log.dcm", np.stack([stored, stored]), VIEW, bits_stored=BITS,
                    extra={"PixelIntensityRelationship": "LOG", "PixelIntensityRelationshipSign": -1})
    run = dicom.load_xa(path)
    assert run.pixel_intensity_relationship == "LOG" and run.frames_relationship == "LIN"
    assert "LOG" in run.linearised_note and "-1" in run.linearised_note
    np.testing.assert_allclose(run.frames[1], linear_from_log(stored, False, BITS), rtol=1e-5)
    assert unreadable_intensity(run.frames_relationship) is None  # its path lengths are read
    tags = intensity_tags_of_file(path)
    assert (tags.relationship, tags.sign, tags.photometric, tags.bits_stored) == ("LOG", -1, "MONOCHROME2", BITS)
    _, provenance = dicom.view_from_dicom(run, 0)
    notes = " ".join(provenance["notes"])
    assert "LOG" in notes and "linear scale" in notes and "give no path lengths" not in notes
    # a LIN run is read as stored, and a LOG frame handed over as stored is refused with the way to read it
    linear = dicom.load_xa(write_xa(tmp_path / "lin.dcm", counts.round().astype(np.uint16), VIEW, bits_stored=BITS))
    assert linear.linearised_note is None and linear.frames_relationship == "LIN"
    np.testing.assert_array_equal(linear.frames[0], counts.round().astype(np.float32))
    assert "load_xa" in unreadable_intensity("LOG")
    assert intensity_tags_of_file(tmp_path / "missing.dcm") is None


def test_a_lin_frame_whose_values_fall_with_intensity_is_mirrored_and_gives_the_path_lengths():
    counts, mask = _tube_frame()  # counts up to 3000 of 4095: room left at the top of the 12-bit range
    linear = view_evidence(counts.astype(np.float32), mask, VIEW)
    stored = np.round(counts).astype(np.float32)
    falling = 4095.0 - stored  # LIN, Sign −1: higher values, less intensity
    for values, tags, inverted in ((falling, IntensityTags("LIN", -1, "MONOCHROME2", BITS), False),
                                   (falling, IntensityTags("LIN", 1, "MONOCHROME1", BITS), True)):
        # the second: stored rising (Sign +1) as MONOCHROME1, which the reader mirrored: the values handed over fall
        frame, relationship, note = linearised(values, tags, inverted)
        assert relationship == "LIN" and "mirrored" in note and "(0028,1041)" in note
        np.testing.assert_allclose(frame, stored, atol=1e-3)
        read = view_evidence(frame, mask, VIEW)
        inside = mask & (linear.line_integral_mm > 0.5)
        np.testing.assert_allclose(read.line_integral_mm[inside], linear.line_integral_mm[inside], rtol=0.02, atol=0.02)
    # LIN rising (as the readers hand over Sign −1 on MONOCHROME1), or without a Sign: as given
    for tags, inverted in ((IntensityTags("LIN", -1, "MONOCHROME1", BITS), True), (IntensityTags("LIN", None, "MONOCHROME2", BITS), False)):
        frame, relationship, note = linearised(stored, tags, inverted)
        assert frame is stored and relationship == "LIN" and note is None
    # a value above the stored range (a rescale) is not mirrored below zero
    assert rising_from_falling(np.array([0.0, 5000.0]), BITS).tolist() == [5000.0, 0.0]


def test_load_xa_mirrors_a_lin_run_whose_values_fall_with_intensity(tmp_path):
    counts, _ = _tube_frame()
    falling = (4095 - np.round(counts)).astype(np.uint16)
    path = write_xa(tmp_path / "lin-falling.dcm", falling, VIEW, bits_stored=BITS,
                    extra={"PixelIntensityRelationship": "LIN", "PixelIntensityRelationshipSign": -1})
    run = dicom.load_xa(path)
    assert run.frames_relationship == "LIN" and "mirrored" in run.linearised_note
    np.testing.assert_allclose(run.frames[0], np.round(counts), atol=1e-3)
