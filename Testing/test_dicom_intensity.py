"""LOG frames brought to a linear intensity scale where DICOM frames are read (dicom/intensity.py)."""

from __future__ import annotations

import numpy as np
import pydicom
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


# --- Enhanced XA: the TO_LINEAR Pixel Intensity Relationship LUT (0028,9422) -------------------------------------
def _exact_to_linear_lut(counts, sign, entries=4096):
    """The TO_LINEAR LUT that undoes ``_log_stored(counts, sign)`` exactly: stored value → intensity (16 bits)."""
    log = np.log(counts)
    v = np.arange(entries, dtype=np.float64)
    scaled = v if sign > 0 else 4095.0 - v
    intensity = np.exp(log.min() + (scaled - 500.0) / 3000.0 * (log.max() - log.min()))
    return np.round(intensity / intensity.max() * 65535.0).astype(np.uint16)


def _lut_item(table, first=0, function="TO_LINEAR", as_ow=False):
    from pydicom.dataset import Dataset

    item = Dataset()
    item.LUTDescriptor = [len(table) % 65536, first, 16]
    if as_ow:
        item.add_new("LUTData", "OW", np.asarray(table, "<u2").tobytes())
    else:
        item.add_new("LUTData", "US", [int(t) for t in table])
    item.LUTFunction = function
    return item


def _enhanced(tmp_path, name, stored, relationship, sign=None, luts=(), per_frame_luts=None, processing=None,
              photometric="MONOCHROME2", bits=BITS):
    """An Enhanced XA file of ``stored`` (n, rows, cols) values with its pixel-data properties in the shared
    functional groups, the given LUT items there (or per frame: ``per_frame_luts``, one list per frame)."""
    import pydicom
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    from dicom_fixtures import make_enhanced

    stored = np.asarray(stored)
    handed = (2 ** bits - 1 - stored) if photometric == "MONOCHROME1" else stored  # write_xa stores top − frames
    classic = write_xa(tmp_path / f"{name}-classic.dcm", handed.astype(np.uint16), VIEW, bits_stored=bits,
                       photometric=photometric)
    path = make_enhanced(classic, tmp_path / f"{name}.dcm")
    ds = pydicom.dcmread(str(path))
    for keyword in ("PixelIntensityRelationship", "PixelIntensityRelationshipSign"):
        if keyword in ds:
            del ds[keyword]
    shared = ds.SharedFunctionalGroupsSequence[0]
    properties = shared.FramePixelDataPropertiesSequence[0]
    properties.PixelIntensityRelationship = relationship
    if sign is not None:
        properties.PixelIntensityRelationshipSign = sign
    if processing is not None:
        properties.ImageProcessingApplied = processing
    if luts:
        shared.PixelIntensityRelationshipLUTSequence = Sequence(list(luts))
    for item, frame_luts in zip(ds.PerFrameFunctionalGroupsSequence, per_frame_luts or ()):
        item.PixelIntensityRelationshipLUTSequence = Sequence(list(frame_luts))
    ds.save_as(str(path), enforce_file_format=True)
    return path


def test_an_enhanced_log_run_is_read_through_its_to_linear_lut_proportional_to_the_intensity(tmp_path):
    counts, mask = _tube_frame()
    for sign, as_ow in ((+1, False), (-1, True)):  # the LUT falls with the stored values where they fall with intensity
        stored = _log_stored(counts, sign)
        # a TO_LOG item first: only the TO_LINEAR one is read
        path = _enhanced(tmp_path, f"log{sign}", np.stack([stored, stored]), "LOG", sign,
                         luts=[_lut_item(np.arange(4096), function="TO_LOG"),
                               _lut_item(_exact_to_linear_lut(counts, sign), as_ow=as_ow)])
        run = dicom.load_xa(path)
        assert run.enhanced and run.pixel_intensity_relationship == "LOG" and run.frames_relationship == "LIN"
        assert "TO_LINEAR" in run.linearised_note and "(0028,9422)" in run.linearised_note
        # proportional to the X-ray intensity (the assumed 8-e-fold span is not: its slope differs)
        ratio = run.frames[1] / counts
        assert ratio.std() / ratio.mean() < 2e-3
        fallback = linear_from_log(stored, sign > 0, BITS) / counts
        assert fallback.std() / fallback.mean() > 0.05
        linear = view_evidence(counts.astype(np.float32), mask, VIEW)
        read = view_evidence(run.frames[0], mask, VIEW)
        assert read.attenuation_per_mm == pytest.approx(linear.attenuation_per_mm, rel=0.01)  # the slope is known now
        inside = mask & (linear.line_integral_mm > 0.5)
        np.testing.assert_allclose(read.line_integral_mm[inside], linear.line_integral_mm[inside], rtol=0.02, atol=0.02)


def test_a_sqrt_encoded_run_with_a_to_linear_lut_and_a_monochrome1_one_give_the_intensity(tmp_path):
    counts, _ = _tube_frame()
    # 8-bit square-root encoding (PS3.17 FFF.2.4.2.4.2), its LUT 256 entries from stored value 0
    stored = np.round(np.sqrt(counts / counts.max()) * 255.0).astype(np.uint16)
    lut = np.round((np.arange(256) / 255.0) ** 2 * 65535.0).astype(np.uint16)
    run = dicom.load_xa(_enhanced(tmp_path, "sqrt", stored[None], "SQRT", luts=[_lut_item(lut)], bits=8))
    assert run.frames_relationship == "LIN" and "SQRT" in run.linearised_note
    np.testing.assert_allclose(run.frames[0], lut[stored], rtol=0, atol=0)
    np.testing.assert_allclose(run.frames[0] / 65535.0, counts / counts.max(), rtol=0.02, atol=2e-4)
    # MONOCHROME1: load_xa mirrors the stored values; the LUT is still applied to the stored ones
    log = _log_stored(counts, -1)
    mono1 = dicom.load_xa(_enhanced(tmp_path, "mono1", log[None], "LOG", -1,
                                    luts=[_lut_item(_exact_to_linear_lut(counts, -1))], photometric="MONOCHROME1"))
    assert mono1.inverted and mono1.frames_relationship == "LIN"
    ratio = mono1.frames[0] / counts
    assert ratio.std() / ratio.mean() < 2e-3
    # the header alone (as the Slicer module reads it) gives the same frames from the mirrored values Slicer hands over
    tags = intensity_tags_of_file(tmp_path / "mono1.dcm", frame=0)
    assert tags.to_linear is not None and tags.usable_lut() is tags.to_linear
    frames, relationship, note = linearised(4095.0 - log.astype(np.float32), tags, inverted=True)
    assert relationship == "LIN" and "TO_LINEAR" in note
    np.testing.assert_allclose(frames, mono1.frames[0])


def test_each_frame_is_read_through_its_own_lut(tmp_path):
    counts, _ = _tube_frame()
    stored = _log_stored(counts, +1)
    exact = _exact_to_linear_lut(counts, +1)
    half = (exact // 2).astype(np.uint16)
    run = dicom.load_xa(_enhanced(tmp_path, "per-frame", np.stack([stored, stored]), "LOG", 1,
                                  per_frame_luts=[[_lut_item(exact)], [_lut_item(half)]]))
    assert run.frames_relationship == "LIN"
    np.testing.assert_allclose(run.frames[0], exact[stored])
    np.testing.assert_allclose(run.frames[1], half[stored])


def test_a_lut_is_not_used_on_filtered_display_frames_or_where_it_is_not_monotonic(tmp_path):
    counts, _ = _tube_frame()
    stored = np.round(np.sqrt(counts / counts.max()) * 255.0).astype(np.uint16)
    lut = np.round((np.arange(256) / 255.0) ** 2 * 65535.0).astype(np.uint16)
    # DISP with an edge enhancement: the LUT cannot undo it — the frames stay DISP, said so
    filtered = dicom.load_xa(_enhanced(tmp_path, "disp-hp", stored[None], "DISP", luts=[_lut_item(lut)],
                                       processing="HIGH_PASS_FILTER", bits=8))
    assert filtered.frames_relationship == "DISP" and "not used" in filtered.linearised_note
    assert "HIGH_PASS_FILTER" in filtered.linearised_note
    np.testing.assert_array_equal(filtered.frames[0], stored.astype(np.float32))
    assert unreadable_intensity(filtered.frames_relationship) is not None
    # DISP without spatial processing (a grey-level map only): read through it
    plain = dicom.load_xa(_enhanced(tmp_path, "disp-none", stored[None], "DISP", luts=[_lut_item(lut)],
                                    processing="NONE", bits=8))
    assert plain.frames_relationship == "LIN"
    np.testing.assert_allclose(plain.frames[0], lut[stored])
    # a LUT that goes up and down maps nothing: a LOG run falls back on the assumed span, and says why
    log = _log_stored(counts, +1)
    zigzag = np.tile(np.array([0, 65535], np.uint16), 2048)
    run = dicom.load_xa(_enhanced(tmp_path, "zigzag", log[None], "LOG", 1, luts=[_lut_item(zigzag)]))
    assert run.frames_relationship == "LIN" and "not monotonic" in run.linearised_note
    np.testing.assert_allclose(run.frames[0], linear_from_log(log, True, BITS), rtol=1e-5)
    # values below the LUT's first mapped value take its first entry, above its last the last
    from SDFCARLib.dicom.intensity import IntensityLUT

    clamp = IntensityLUT(10, np.array([1.0, 2.0, 3.0]), 16)
    assert clamp(np.array([0, 10, 11, 12, 50])).tolist() == [1.0, 1.0, 2.0, 3.0, 3.0]
    assert clamp.direction == 1 and IntensityLUT(0, np.array([3.0, 3.0]), 16).direction == 0


def test_a_classic_log_run_is_read_through_its_modality_lut_back_to_linear(tmp_path):
    """In a classic XA object of LOG (or DISP) frames the Modality LUT is not a display step: it maps the stored
    values back to linear (PS3.3 C.8.7.1.1.2). load_xa reads a LOG run through it, never applies it forward, and
    leaves a DISP run (no word on its spatial processing) as it is."""
    from pydicom.sequence import Sequence

    counts, _ = _tube_frame()
    stored = _log_stored(counts, +1)
    modality = _lut_item(_exact_to_linear_lut(counts, +1))
    del modality.LUTFunction
    modality.ModalityLUTType = "US"  # unspecified
    run = dicom.load_xa(write_xa(tmp_path / "log-mlut.dcm", stored, VIEW, bits_stored=BITS, extra={
        "PixelIntensityRelationship": "LOG", "PixelIntensityRelationshipSign": 1, "ModalityLUTSequence": Sequence([modality])}))
    assert run.frames_relationship == "LIN" and "Modality LUT (0028,3000)" in run.linearised_note
    ratio = run.frames[0] / counts
    assert ratio.std() / ratio.mean() < 2e-3
    shown = np.round(np.sqrt(counts / counts.max()) * 255.0).astype(np.uint16)
    disp = dicom.load_xa(write_xa(tmp_path / "disp-mlut.dcm", shown, VIEW, bits_stored=8, extra={
        "PixelIntensityRelationship": "DISP", "ModalityLUTSequence": Sequence([modality])}))
    assert disp.frames_relationship == "DISP" and "Modality LUT (0028,3000) was not used" in disp.linearised_note
    np.testing.assert_array_equal(disp.frames[0], shown.astype(np.float32))
    linear = dicom.load_xa(write_xa(tmp_path / "lin-mlut.dcm", counts.round().astype(np.uint16), VIEW, bits_stored=BITS,
                                    extra={"ModalityLUTSequence": Sequence([modality])}))
    assert linear.frames_relationship == "LIN" and linear.linearised_note is None  # LIN: nothing to bring back
    np.testing.assert_array_equal(linear.frames[0], counts.round().astype(np.float32))


def test_a_classic_log_run_as_slicer_loads_it_is_read_through_its_modality_lut_once(tmp_path):
    """Slicer's DICOM module hands over a classic XA run's stored values untouched by its Modality LUT (GDCM warns
    "Modality LUT (0028,3000) are not handled"; ITK's GDCMImageIO applies only a rescale slope/intercept) and, for
    MONOCHROME1, mirrored onto the stored bits (mask − value). The module's path (the file's tags of that frame,
    then ``linearised``) then gives what load_xa gives: the LUT applied once, the frame ∝ the intensity."""
    from pydicom.sequence import Sequence

    counts, _ = _tube_frame()
    stored = _log_stored(counts, +1)
    modality = _lut_item(_exact_to_linear_lut(counts, +1))
    del modality.LUTFunction
    modality.ModalityLUTType = "US"
    for photometric in ("MONOCHROME2", "MONOCHROME1"):
        path = write_xa(tmp_path / f"log-mlut-{photometric}.dcm", stored, VIEW, bits_stored=BITS, photometric=photometric,
                        extra={"PixelIntensityRelationship": "LOG", "PixelIntensityRelationshipSign": 1,
                               "ModalityLUTSequence": Sequence([modality])})
        mirrored = photometric == "MONOCHROME1"
        in_file = pydicom.dcmread(path).pixel_array.astype(np.float64)  # write_xa stores 2^bits − 1 − the array there
        as_slicer_gives = ((2 ** BITS - 1) - in_file if mirrored else in_file).astype(np.float32)
        frame, relationship, note = linearised(as_slicer_gives, intensity_tags_of_file(path, 0), inverted=mirrored)
        assert relationship == "LIN" and "Modality LUT (0028,3000)" in note
        np.testing.assert_allclose(frame, dicom.load_xa(path).frames[0], rtol=1e-6)
        if not mirrored:  # the LUT was made for these stored values: the frame ∝ the intensity
            ratio = frame / counts
            assert ratio.std() / ratio.mean() < 2e-3
