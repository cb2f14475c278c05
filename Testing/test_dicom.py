"""X-ray angiography DICOM input: pixel values, frame choice, geometry from tags, errors, round trip."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pydicom
import pytest
from pydicom.encaps import encapsulate
from pydicom.uid import (CTImageStorage, DeflatedExplicitVRLittleEndian, ExplicitVRLittleEndian,
                         ImplicitVRLittleEndian, JPEG2000Lossless, JPEGBaseline8Bit, JPEGLosslessSV1, MPEG2MPML,
                         RLELossless)

import dicom_fixtures as fx
import xa_writer
from SDFCARLib import dicom
from SDFCARLib.dicom import DicomInputError
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.phantoms import beer_lambert_counts, line_integrals_from_counts

VIEW = CArmView(30.0, -20.0, 1000.0, 757.0, (0.3, 0.3), (40, 48))
RNG = np.random.default_rng(7)


def frames16(n=3, bits=12, shape=(40, 48)):
    return RNG.integers(0, 2**bits, size=(n,) + shape).astype(np.uint16)


def xa(tmp_path, name="run.dcm", frames=None, view=VIEW, **kwargs):
    frames = frames16() if frames is None else frames
    kwargs.setdefault("bits_stored", 12 if frames.dtype == np.uint16 else 8)
    return xa_writer.write_xa(tmp_path / name, frames, view, **kwargs)


def field(prov, key):
    return prov["fields"][key]


# --- pixel values ----------------------------------------------------------------------------------
@pytest.mark.parametrize("bits", [8, 12, 16])
def test_uncompressed_monochrome2_values(tmp_path, bits):
    stored = RNG.integers(0, 2**bits, size=(4, 10, 12))
    path = fx.raw_xa(tmp_path / "a.dcm", stored, bits)
    run = dicom.load_xa(path)
    assert run.frames.dtype == np.float32 and run.frames.shape == (4, 10, 12)
    assert np.array_equal(run.frames, stored.astype(np.float32))
    assert not run.inverted and run.num_frames == 4 and run.detector_shape == (10, 12)


@pytest.mark.parametrize("bits", [8, 12])
def test_monochrome1_is_inverted_so_larger_is_brighter(tmp_path, bits):
    stored = RNG.integers(0, 2**bits, size=(2, 6, 7))
    run = dicom.load_xa(fx.raw_xa(tmp_path / "m1.dcm", stored, bits, photometric="MONOCHROME1"))
    assert run.inverted
    assert np.array_equal(run.frames, (2**bits - 1 - stored).astype(np.float32))


def test_rescale_is_applied_before_inversion(tmp_path):
    stored = RNG.integers(0, 256, size=(1, 5, 5))
    run = dicom.load_xa(fx.raw_xa(tmp_path / "r.dcm", stored, 8, RescaleSlope=2.0, RescaleIntercept=-10.0))
    assert np.allclose(run.frames[0], stored[0] * 2.0 - 10.0)
    run1 = dicom.load_xa(fx.raw_xa(tmp_path / "r1.dcm", stored, 8, photometric="MONOCHROME1",
                                   RescaleSlope=2.0, RescaleIntercept=-10.0))
    # The stored range [0, 255] maps to [-10, 500]; MONOCHROME1 mirrors it: v -> 490 - v.
    assert np.allclose(run1.frames[0], 490.0 - (stored[0] * 2.0 - 10.0))


def test_single_frame_gives_one_frame(tmp_path):
    stored = RNG.integers(0, 4096, size=(9, 11))
    run = dicom.load_xa(fx.raw_xa(tmp_path / "s.dcm", stored, 12))
    assert run.frames.shape == (1, 9, 11)
    choice = dicom.choose_frame(run)
    assert (choice.index, choice.method) == (0, "single")


@pytest.mark.parametrize("syntax", [ExplicitVRLittleEndian, ImplicitVRLittleEndian, DeflatedExplicitVRLittleEndian,
                                    RLELossless, JPEG2000Lossless])
@pytest.mark.parametrize("photometric", ["MONOCHROME2", "MONOCHROME1"])
def test_write_read_round_trip_every_encodable_syntax(tmp_path, syntax, photometric):
    frames = frames16(n=3)
    path = xa(tmp_path, frames=frames, transfer_syntax=syntax, photometric=photometric)
    run = dicom.load_xa(path)
    assert str(run.transfer_syntax) == str(syntax)
    assert np.array_equal(run.frames, frames.astype(np.float32))
    assert run.photometric == photometric


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_jpeg_lossless_sv1_multiframe_decodes_exactly(tmp_path, bits):
    frames = RNG.integers(0, 2**bits, size=(3, 40, 48)).astype(np.uint8 if bits == 8 else np.uint16)
    native = xa(tmp_path, "n.dcm", frames=frames, bits_stored=bits)
    path = fx.recompress(native, tmp_path / "jpl.dcm", JPEGLosslessSV1)
    run = dicom.load_xa(path)
    assert "Selection Value 1" in run.transfer_syntax_name
    assert np.array_equal(run.frames, frames.astype(np.float32))


def test_jpeg_baseline_decodes_close_to_the_original(tmp_path):
    yy, xx = np.mgrid[0:40, 0:48]
    smooth = (100 + 60 * np.sin(xx / 7.0) + 40 * np.cos(yy / 5.0)).astype(np.uint8)
    frames = np.stack([smooth, smooth[::-1]])
    path = fx.recompress(xa(tmp_path, "n.dcm", frames=frames, bits_stored=8), tmp_path / "jb.dcm", JPEGBaseline8Bit)
    run = dicom.load_xa(path)
    assert run.frames.shape == (2, 40, 48)
    assert float(np.abs(run.frames - frames).mean()) < 2.0  # lossy, quality 95


def test_xrf_sop_class_is_accepted(tmp_path):
    run = dicom.load_xa(xa(tmp_path, sop_class="XRF"))
    assert "XRF" in run.sop_class_name


# --- input errors ----------------------------------------------------------------------------------
def test_missing_file_and_not_dicom(tmp_path):
    with pytest.raises(DicomInputError, match="DICOM file not found"):
        dicom.load_xa(tmp_path / "nope.dcm")
    text = tmp_path / "notes.txt"
    text.write_text("not an image")
    with pytest.raises(DicomInputError, match="is not a DICOM file"):
        dicom.load_xa(text)


def test_not_xa_names_the_sop_class(tmp_path):
    path = fx.raw_xa(tmp_path / "ct.dcm", np.zeros((4, 4)), 16, sop_class=CTImageStorage, Modality="CT")
    with pytest.raises(DicomInputError, match=r"not an X-ray angiography image: its SOP class is CT Image Storage"):
        dicom.load_xa(path)


def test_video_syntax_is_refused_with_the_syntax_name(tmp_path):
    ds = pydicom.dcmread(str(xa(tmp_path)))
    ds.PixelData = encapsulate([b"\x00\x00\x01\xb3" + b"\x00" * 12])
    ds["PixelData"].VR = "OB"
    ds.file_meta.TransferSyntaxUID = MPEG2MPML
    ds.save_as(str(tmp_path / "mpeg.dcm"), enforce_file_format=True)
    with pytest.raises(DicomInputError, match=r"MPEG2 Main Profile / Main Level.*cannot decode.*dcmdjpeg"):
        dicom.load_xa(tmp_path / "mpeg.dcm")


def test_missing_decoder_names_the_package(tmp_path, monkeypatch):
    from pydicom.pixels.decoders.base import get_decoder

    native = xa(tmp_path, "n.dcm")
    path = fx.recompress(native, tmp_path / "jpl.dcm", JPEGLosslessSV1)
    decoder = get_decoder(JPEGLosslessSV1)
    # As on a machine without pylibjpeg-libjpeg: no available plugin, one with a missing dependency.
    monkeypatch.setattr(decoder, "_available", {})
    monkeypatch.setattr(decoder, "_unavailable", {"pylibjpeg": ("pylibjpeg-libjpeg",)})
    with pytest.raises(DicomInputError) as info:
        dicom.load_xa(path)
    message = str(info.value)
    assert "JPEG Lossless, Non-Hierarchical, First-Order Prediction" in message
    assert "pip install pylibjpeg pylibjpeg-libjpeg" in message and "requires pylibjpeg-libjpeg" in message


def test_frame_index_out_of_range(tmp_path):
    run = dicom.load_xa(xa(tmp_path, frames=frames16(n=5)))
    for bad in (5, -1):
        with pytest.raises(DicomInputError, match=r"frame %d is out of range: this run has 5 frames, numbered 0 to 4 "
                                                   r"\(0-based" % bad):
            dicom.choose_frame(run, bad)
    with pytest.raises(DicomInputError, match="whole number"):
        dicom.choose_frame(run, 1.5)
    assert dicom.choose_frame(run, 4).index == 4 and dicom.choose_frame(run, 4).method == "user"


def test_missing_sod_names_the_tag_and_the_override(tmp_path):
    path = xa(tmp_path, omit=("DistanceSourceToPatient", "EstimatedRadiographicMagnificationFactor"))
    with pytest.raises(DicomInputError) as info:
        dicom.view_from_dicom(path, 0, view_number=1)
    message = str(info.value)
    assert "source-to-isocenter distance (SOD) is missing" in message
    assert "(0018,1111) DistanceSourceToPatient" in message and "(0018,1114)" in message
    assert "overrides1 = {'sod_mm': 765}" in message and "--sod1 MM" in message


def test_missing_pixel_spacing_names_the_tags_and_the_override(tmp_path):
    path = xa(tmp_path, omit=("ImagerPixelSpacing",))
    with pytest.raises(DicomInputError) as info:
        dicom.view_from_dicom(path, 0, view_number=2)
    message = str(info.value)
    assert "detector pixel spacing is missing" in message
    for tag in ("(0018,1164) ImagerPixelSpacing", "(0028,0030) PixelSpacing", "(0018,1149) FieldOfViewDimensions"):
        assert tag in message
    assert "'pixel_spacing_mm': [0.3, 0.3]" in message and "--pixel-spacing2 ROW COL" in message


def test_missing_sid_and_angles(tmp_path):
    with pytest.raises(DicomInputError, match=r"source-to-detector distance \(SID\) is missing.*\(0018,1110\).*--sid1"):
        dicom.view_from_dicom(xa(tmp_path, "a.dcm", omit=("DistanceSourceToDetector",
                                                          "EstimatedRadiographicMagnificationFactor")), 0, view_number=1)
    with pytest.raises(DicomInputError, match=r"primary angle .* is missing.*\(0018,1510\).*'primary_deg'.*--primary1"):
        dicom.view_from_dicom(xa(tmp_path, "b.dcm", omit=("PositionerPrimaryAngle",)), 0, view_number=1)
    with pytest.raises(DicomInputError, match=r"secondary angle .* is missing.*\(0018,1511\)"):
        dicom.view_from_dicom(xa(tmp_path, "c.dcm", omit=("PositionerSecondaryAngle",)), 0)


def test_bad_overrides_are_refused(tmp_path):
    path = xa(tmp_path)
    with pytest.raises(DicomInputError, match="unknown override.*sod;.*allowed"):
        dicom.view_from_dicom(path, 0, {"sod": 700})
    with pytest.raises(DicomInputError, match="pixel_spacing_mm must be two numbers"):
        dicom.view_from_dicom(path, 0, {"pixel_spacing_mm": [0.1, 0.2, 0.3]})
    with pytest.raises(DicomInputError, match="sod_mm must be a number"):
        dicom.view_from_dicom(path, 0, {"sod_mm": "far"})


def test_impossible_values_are_reported_with_their_source(tmp_path):
    path = xa(tmp_path, view=None, extra=dict(PositionerPrimaryAngle=0, PositionerSecondaryAngle=0,
                                              DistanceSourceToDetector=700, DistanceSourceToPatient=900,
                                              ImagerPixelSpacing=[0.3, 0.3]))
    with pytest.raises(DicomInputError, match=r"sod_mm = 900.0 must be smaller than .*sid_mm = 700.0"):
        dicom.view_from_dicom(path, 0)


# --- geometry from tags ----------------------------------------------------------------------------
def test_every_field_and_its_source_with_all_tags(tmp_path):
    view, prov = dicom.view_from_dicom(xa(tmp_path), 1)
    assert view == VIEW
    expected = {
        "primary_deg": (30.0, "tag (0018,1510) PositionerPrimaryAngle"),
        "secondary_deg": (-20.0, "tag (0018,1511) PositionerSecondaryAngle"),
        "sid_mm": (1000.0, "tag (0018,1110) DistanceSourceToDetector"),
        "sod_mm": (757.0, "tag (0018,1111) DistanceSourceToPatient"),
        "pixel_spacing_mm": ([0.3, 0.3], "tag (0018,1164) ImagerPixelSpacing"),
        "detector_shape": ([40, 48], "tags (0028,0010) Rows, (0028,0011) Columns"),
        "principal_point_px": ([19.5, 23.5], "default: the image centre (no DICOM tag gives the principal point)"),
    }
    for key, (value, source) in expected.items():
        assert field(prov, key) == {"value": value, "source": source}
    assert prov["frame"]["index"] == 1 and prov["frame"]["dicom_frame_number"] == 2
    assert prov["sop_class"] == "X-Ray Angiographic Image (XA)" and prov["notes"] == []


def test_dicom_angle_convention_matches_the_detector_direction(tmp_path):
    # PS3.3 C.8.7.5.1.2: +90° primary = patient's left (LAO), +90° secondary = cranial, 0/0 = facing the detector.
    for (a, b), d in (((90.0, 0.0), (1, 0, 0)), ((-90.0, 0.0), (-1, 0, 0)), ((0.0, 0.0), (0, -1, 0)),
                      ((0.0, 89.0), (0, -math.cos(math.radians(89)), math.sin(math.radians(89))))):
        view = CArmView(a, b, 1000.0, 757.0, (0.3, 0.3), (40, 48))
        read, _ = dicom.view_from_dicom(xa(tmp_path, f"v{a}_{b}.dcm", view=view), 0)
        assert np.allclose(read.detector_direction, d, atol=1e-12)


def test_sod_and_sid_fallbacks_from_the_magnification(tmp_path):
    m = 1000.0 / 757.0
    view, prov = dicom.view_from_dicom(xa(tmp_path, "a.dcm", omit=("DistanceSourceToPatient",)), 0)
    assert math.isclose(view.sod_mm, 1000.0 / float(xa_writer._ds(m)), rel_tol=1e-12)
    assert field(prov, "sod_mm")["source"].startswith("fallback: SID / tag (0018,1114) EstimatedRadiographicMagnificationFactor")
    view, prov = dicom.view_from_dicom(xa(tmp_path, "b.dcm", omit=("DistanceSourceToDetector",)), 0)
    assert math.isclose(view.sid_mm, 757.0 * float(xa_writer._ds(m)), rel_tol=1e-12)
    assert field(prov, "sid_mm")["source"].startswith("fallback: SOD × tag (0018,1114)")


def test_pixel_spacing_fallbacks(tmp_path):
    # PixelSpacing without a calibration type: taken as the detector spacing.
    view, prov = dicom.view_from_dicom(xa(tmp_path, "a.dcm", pixel_spacing_tag="PixelSpacing"), 0)
    assert view.pixel_spacing_mm == (0.3, 0.3)
    assert field(prov, "pixel_spacing_mm")["source"].startswith("fallback: tag (0028,0030) PixelSpacing, taken as the detector")
    # PixelSpacing calibrated at the patient: times the magnification (0018,1114).
    iso = CArmView(30.0, -20.0, 1000.0, 800.0, (0.2, 0.24), (40, 48))
    view, prov = dicom.view_from_dicom(xa(tmp_path, "b.dcm", view=iso, pixel_spacing_tag="PixelSpacing",
                                          extra={"PixelSpacingCalibrationType": "GEOMETRY"}), 0)
    assert np.allclose(view.pixel_spacing_mm, (0.25, 0.3))
    assert "calibrated at the patient" in field(prov, "pixel_spacing_mm")["source"]
    # Field of view (row, col mm) / image size.
    view, prov = dicom.view_from_dicom(xa(tmp_path, "c.dcm", omit=("ImagerPixelSpacing",),
                                          extra={"FieldOfViewDimensions": [20, 36]}), 0)
    assert np.allclose(view.pixel_spacing_mm, (0.5, 0.75))
    assert field(prov, "pixel_spacing_mm")["source"].startswith("fallback: tag (0018,1149) FieldOfViewDimensions")
    # Intensifier diameter / larger image side.
    view, prov = dicom.view_from_dicom(xa(tmp_path, "d.dcm", omit=("ImagerPixelSpacing",),
                                          extra={"IntensifierSize": 240}), 0)
    assert np.allclose(view.pixel_spacing_mm, (5.0, 5.0))
    assert "(0018,1162) IntensifierSize" in field(prov, "pixel_spacing_mm")["source"]


def test_user_values_replace_or_supply_tags(tmp_path):
    view, prov = dicom.view_from_dicom(xa(tmp_path, "a.dcm"), 0, {"sod_mm": 740, "primary_deg": 31.5})
    assert view.sod_mm == 740.0 and view.primary_deg == 31.5
    assert field(prov, "sod_mm")["source"] == "user (replaces tag (0018,1111) DistanceSourceToPatient = 757.0)"
    assert field(prov, "primary_deg")["source"] == "user (replaces tag (0018,1510) PositionerPrimaryAngle = 30.0)"
    view, prov = dicom.view_from_dicom(xa(tmp_path, "b.dcm", omit=("ImagerPixelSpacing",)), 0,
                                       {"pixel_spacing_mm": 0.3})
    assert view.pixel_spacing_mm == (0.3, 0.3) and field(prov, "pixel_spacing_mm")["source"] == "user"


def test_rotational_increments_per_frame_and_average(tmp_path):
    n = 4
    view = CArmView(170.0, 10.0, 1000.0, 757.0, (0.3, 0.3), (40, 48))
    per_frame = xa(tmp_path, "a.dcm", frames=frames16(n), view=view,
                   angle_increments_deg=([0.0, 5.0, 10.0, 15.0], [0.0, -1.0, -2.0, -3.0]))
    read, prov = dicom.view_from_dicom(per_frame, 2)
    assert (read.primary_deg, read.secondary_deg) == (180.0, 8.0)  # offsets from the first frame's angles
    assert "start + increment[2] = 10° from tag (0018,1520)" in field(prov, "primary_deg")["source"]
    read, prov = dicom.view_from_dicom(per_frame, 3)
    assert (read.primary_deg, read.secondary_deg) == (-175.0, 7.0)  # 185° is -175° (LAO past 180 = RAO)
    assert "wrapped from 185° into [-180, 180]" in field(prov, "primary_deg")["source"]
    # an angle already in range is neither moved by the modulo's rounding nor reported as wrapped
    in_range, prov = dicom.view_from_dicom(xa(tmp_path, "e.dcm", view=CArmView(-0.8, 10.0, 1000.0, 757.0, (0.3, 0.3),
                                                                             (40, 48))), 0)
    assert in_range.primary_deg == -0.8 and "wrapped" not in field(prov, "primary_deg")["source"]
    average = xa(tmp_path, "b.dcm", frames=frames16(n), view=view, angle_increments_deg=([2.5], [1.0]))
    read, prov = dicom.view_from_dicom(average, 3)
    assert (read.primary_deg, read.secondary_deg) == (177.5, 13.0)
    assert "start + 3 × 2.5° (single average increment per frame)" in field(prov, "primary_deg")["source"]
    with pytest.raises(ValueError, match="primary angle increments need 1 or 4 values, got 2"):
        xa(tmp_path, "c.dcm", frames=frames16(n), view=view, angle_increments_deg=([1.0, 2.0], [0.0]))
    wrong = xa(tmp_path, "d.dcm", frames=frames16(n), view=view,
               extra={"PositionerMotion": "DYNAMIC", "PositionerPrimaryAngleIncrement": [1.0, 2.0]})
    with pytest.raises(DicomInputError, match=r"\(0018,1520\) PositionerPrimaryAngleIncrement has 2 values; DICOM "
                                              r"\(PS3.3 C.8.7.5.1.3\) allows one .* or one per frame \(4\)"):
        dicom.view_from_dicom(wrong, 0)


def test_enhanced_xa_reads_functional_groups(tmp_path):
    n = 5
    classic = xa(tmp_path, "c.dcm", frames=fx.contrast_run(n, peak=3, shape=(40, 48)))
    path = fx.make_enhanced(classic, tmp_path / "e.dcm", per_frame_primary=[30, 31, 32, 33, 34], end_diastole=[1, 4])
    run = dicom.load_xa(path)
    assert run.enhanced and run.sop_class_name == "Enhanced XA Image"
    view, prov = dicom.view_from_dicom(run, 2)
    assert (view.primary_deg, view.secondary_deg, view.sid_mm, view.sod_mm) == (32.0, -20.0, 1000.0, 757.0)
    assert view.pixel_spacing_mm == (0.3, 0.3)
    assert field(prov, "primary_deg")["source"] == ("tag (0018,1510) PositionerPrimaryAngle in (0018,9405) "
                                                    "PositionerPositionSequence (per-frame functional groups)")
    assert field(prov, "sod_mm")["source"] == ("tag (0018,9402) DistanceSourceToIsocenter in (0018,9476) "
                                               "XRayGeometrySequence (shared functional groups)")
    choice = dicom.choose_frame(run)
    assert choice.method == "end-diastole" and choice.candidates == [1, 4] and choice.index == 4
    assert "(0018,9236) CardiacCyclePosition = END_DIASTOLE" in choice.reason


def test_untreated_tilts_and_flips_are_noted(tmp_path):
    _, prov = dicom.view_from_dicom(xa(tmp_path, extra={"DetectorPrimaryAngle": 3.0, "FieldOfViewHorizontalFlip": "YES",
                                                        "PatientOrientation": ["R", "F"]}), 0)
    notes = " | ".join(prov["notes"])
    assert "(0018,1530) DetectorPrimaryAngle = 3°: not modelled" in notes
    assert "FieldOfViewHorizontalFlip = YES" in notes and "PatientOrientation = R/F" in notes


def test_frames_processed_for_display_are_noted_with_the_geometry(tmp_path):
    for relationship, noted in (("DISP", True), ("DRM", True), ("LIN", False)):
        _, prov = dicom.view_from_dicom(xa(tmp_path, f"{relationship}.dcm", extra={"PixelIntensityRelationship": relationship}), 0)
        said = [n for n in prov["notes"] if "(0028,1040)" in n]
        assert bool(said) == noted, relationship
        if noted:
            assert f"is {relationship}" in said[0] and "fits the masks alone" in said[0]


# --- frame choice ----------------------------------------------------------------------------------
@pytest.mark.parametrize("peak", [3, 8])
def test_automatic_frame_is_the_most_contrast(tmp_path, peak):
    run = dicom.load_xa(xa(tmp_path, frames=fx.contrast_run(12, peak=peak), view=None))
    choice = dicom.choose_frame(run)
    assert (choice.index, choice.method) == (peak, "contrast")
    assert "no R-wave information" in choice.reason and "most contrast-filled vessel" in choice.reason


def test_contrast_score_ignores_exposure_and_counts_vessels():
    frames = fx.contrast_run(9, peak=4, gain_drift=0.0).astype(float)
    scores = dicom.contrast_scores(frames)
    assert int(np.argmax(scores)) == 4 and scores[4] > 5 * scores[0]
    # A global exposure change (gain) leaves the score unchanged up to the noise: log + top-hat.
    brighter = dicom.contrast_scores(frames * 1.5)
    assert np.allclose(brighter[2:7], scores[2:7], rtol=0.1)


def test_r_wave_pointer_picks_the_end_diastolic_frame_with_contrast(tmp_path):
    path = xa(tmp_path, frames=fx.contrast_run(12, peak=6), view=None, r_wave_frames=[1, 5, 9])
    choice = dicom.choose_frame(dicom.load_xa(path))
    assert (choice.index, choice.method, choice.candidates) == (5, "end-diastole", [1, 5, 9])
    assert "(0028,6040) RWavePointer (DICOM frame numbers 2, 6, 10)" in choice.reason


def test_r_wave_time_vector_with_frame_time_and_frame_time_vector(tmp_path):
    frames = fx.contrast_run(12, peak=6)
    path = xa(tmp_path, "a.dcm", frames=frames, view=None, frame_time_ms=50.0,
              extra={"RWaveTimeVector": [52.0, 348.0, 610.0]})  # frames 1, 7, 12 → 12 is past the run
    choice = dicom.choose_frame(dicom.load_xa(path))
    assert choice.candidates == [1, 7] and choice.index == 7
    assert "(0018,6060) RWaveTimeVector" in choice.reason and "(0018,1063) FrameTime" in choice.reason
    vector = [0.0] + [40.0] * 5 + [80.0] * 6  # frames at 0, 40, …, 200, 280, …, 680 ms
    path = xa(tmp_path, "b.dcm", frames=frames, view=None, frame_time_vector_ms=vector,
              extra={"RWaveTimeVector": [118.0, 361.0]})  # frames 3 (120 ms) and 7 (360 ms)
    choice = dicom.choose_frame(dicom.load_xa(path))
    assert choice.candidates == [3, 7] and choice.index == 7
    assert "(0018,1065) FrameTimeVector" in choice.reason


@pytest.mark.parametrize("inverted", [False, True])
def test_ecg_waveform_r_peaks_pick_the_frame(tmp_path, inverted):
    frames = fx.contrast_run(15, peak=9)
    path = xa(tmp_path, frames=frames, view=None, frame_time_ms=66.0, heart_rate_bpm=75)
    fx.add_ecg(path, r_peaks_ms=[140.0, 940.0], duration_ms=1000.0, offset_ms=-10.0, inverted=inverted)
    choice = dicom.choose_frame(dicom.load_xa(path))
    # R peaks at 130 and 930 ms from the first frame: frames 2 (132 ms) and 14 (924 ms).
    assert choice.method == "end-diastole" and choice.candidates == [2, 14]
    assert "ECG channel 1" in choice.reason and "HeartRate" in choice.reason


# --- GEOM.json and the command line ----------------------------------------------------------------
def test_geometry_from_dicom_and_geom_json(tmp_path):
    view2 = CArmView(-25.0, 15.0, 1100.0, 780.0, (0.3, 0.3), (40, 48))
    p1 = xa(tmp_path, "v1.dcm", frames=fx.contrast_run(6, peak=2, shape=(40, 48)))
    p2 = fx.recompress(xa(tmp_path, "n2.dcm", view=view2), tmp_path / "v2.dcm", JPEGLosslessSV1)
    geometry, prov = dicom.geometry_from_dicom(p1, p2, frame2=1)
    assert geometry.views == (VIEW, view2)
    assert geometry.volume == VolumeGrid((128, 128, 128), (0.8, 0.8, 0.8), (0.0, 0.0, 0.0))
    assert prov["volume"]["source"].startswith("default: 128³ voxels of 0.8 mm")
    assert prov["views"][0]["frame"]["index"] == 2 and prov["views"][1]["frame"]["method"] == "user"
    out = dicom.write_geometry_json(tmp_path / "GEOM.json", geometry, prov)
    assert Geometry.load(out) == geometry
    data = json.loads(out.read_text(encoding="utf-8"))
    assert data["provenance"]["views"][1]["fields"]["sod_mm"] == {"value": 780.0,
                                                                  "source": "tag (0018,1111) DistanceSourceToPatient"}


def test_failed_geometry_leaves_an_existing_geom_json_alone(tmp_path):
    out = tmp_path / "GEOM.json"
    out.write_text("{\"old\": true}\n")
    p1 = xa(tmp_path, "v1.dcm")
    p2 = xa(tmp_path, "v2.dcm", omit=("ImagerPixelSpacing",))
    with pytest.raises(DicomInputError, match="view 2"):
        dicom.write_geometry_json(out, *dicom.geometry_from_dicom(p1, p2, 0, 0))
    assert out.read_text() == "{\"old\": true}\n"


def test_cli_wiring(tmp_path):
    parser = argparse.ArgumentParser()
    dicom.add_dicom_arguments(parser)
    p1 = xa(tmp_path, "v1.dcm")
    p2 = xa(tmp_path, "v2.dcm", omit=("ImagerPixelSpacing", "DistanceSourceToPatient"),
            view=CArmView(-40.0, 0.0, 1000.0, 757.0, (0.3, 0.3), (40, 48)))
    args = parser.parse_args(["--dicom1", str(p1), "--frame1", "2", "--dicom2", str(p2), "--pixel-spacing2", "0.25",
                              "0.3", "--sod2", "750", "--volume-shape", "64", "64", "32", "--volume-spacing", "1.0"])
    geometry, prov = dicom.cli_geometry_from_args(args)
    assert geometry.views[1].pixel_spacing_mm == (0.25, 0.3) and geometry.views[1].sod_mm == 750.0
    assert geometry.volume == VolumeGrid((64, 64, 32), (1.0, 1.0, 1.0))
    assert prov["views"][0]["frame"]["index"] == 2 and prov["views"][1]["fields"]["sod_mm"]["source"] == "user"
    with pytest.raises(DicomInputError, match="--dicom1 and --dicom2 are both needed"):
        dicom.cli_geometry_from_args(parser.parse_args(["--dicom1", str(p1)]))


# --- the tests' XA writer (xa_writer.py) ----------------------------------------------------------
def test_write_xa_refuses_what_it_cannot_write(tmp_path):
    with pytest.raises(ValueError, match="pydicom has no encoder for JPEG Lossless.*RLE Lossless"):
        xa(tmp_path, "a.dcm", transfer_syntax=JPEGLosslessSV1)
    with pytest.raises(ValueError, match="non-negative integers"):
        xa_writer.write_xa(tmp_path / "b.dcm", np.zeros((40, 48), np.float32), VIEW)
    with pytest.raises(ValueError, match="detector shape"):
        xa_writer.write_xa(tmp_path / "c.dcm", np.zeros((10, 10), np.uint8), VIEW)
    with pytest.raises(ValueError, match="more than 8 bits"):
        xa_writer.write_xa(tmp_path / "d.dcm", np.full((40, 48), 300, np.uint16), VIEW, bits_stored=8)
    path = xa(tmp_path, "e.dcm")
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        xa(tmp_path, "e.dcm")
    assert path.read_bytes() == before


def test_written_object_is_a_valid_multiframe_xa(tmp_path):
    ds = pydicom.dcmread(str(xa(tmp_path, frames=frames16(n=3), r_wave_frames=[0, 2], heart_rate_bpm=70)))
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.12.1" and ds.Modality == "XA"
    assert int(ds.NumberOfFrames) == 3 and ds.FrameIncrementPointer == 0x00181063
    assert list(ds.RWavePointer) == [1, 3] and int(ds.HeartRate) == 70
    assert ds.BitsStored == 12 and ds.HighBit == 11 and ds.BitsAllocated == 16
    assert float(ds.EstimatedRadiographicMagnificationFactor) == pytest.approx(1000.0 / 757.0)


# --- round trip through DICOM and the reconstruction -----------------------------------------------
def test_round_trip_phantom_dicom_geometry_reconstruction(tmp_path):
    from SDFCARLib.optimiser import reconstruct
    from SDFCARLib.settings import make_settings
    from SDFCARLib.phantoms import Branch, CentrelineTree, lad_tree, make_case

    tree = lad_tree(0)
    tree = CentrelineTree([Branch(b.points * 0.6, b.radii * 1.5, b.name) for b in tree.branches], tree.name)
    views = (CArmView(30.0, 0.0, 1000.0, 757.0, (1.0, 1.0), (96, 96)),
             CArmView(-25.0, 20.0, 1050.0, 760.0, (1.0, 1.0), (96, 96)))
    original = Geometry(VolumeGrid((32, 32, 32), (2.0, 2.0, 2.0)), views)
    case = make_case(tree, original)
    contrast = [0.1, 0.5, 1.0, 0.6]  # the run fills and washes out; frame 2 is full
    i0, mu = 3000.0, 0.25
    paths = []
    for n, (view, line_integral) in enumerate(zip(views, case.line_integrals), start=1):
        frames = np.stack([beer_lambert_counts(c * line_integral, mu, i0, 12) for c in contrast])
        native = xa_writer.write_xa(tmp_path / f"n{n}.dcm", frames, view, bits_stored=12,
                                    omit=("ImagerPixelSpacing",) if n == 1 else ())
        paths.append(fx.recompress(native, tmp_path / f"v{n}.dcm", JPEGLosslessSV1) if n == 1 else native)
    # View 1: multi-frame JPEG Lossless without ImagerPixelSpacing — refused, then supplied by the user.
    with pytest.raises(DicomInputError, match="pixel spacing is missing"):
        dicom.geometry_from_dicom(paths[0], paths[1], volume=original.volume)
    rebuilt, prov = dicom.geometry_from_dicom(paths[0], paths[1], volume=original.volume,
                                              overrides1={"pixel_spacing_mm": [1.0, 1.0]})
    assert rebuilt == original
    for n, view in enumerate(views):
        for key in ("primary_deg", "secondary_deg", "sid_mm", "sod_mm"):
            assert getattr(rebuilt.views[n], key) == getattr(view, key)
        assert rebuilt.views[n].pixel_spacing_mm == view.pixel_spacing_mm
        assert rebuilt.views[n].detector_shape == view.detector_shape
        assert prov["views"][n]["frame"]["index"] == 2
    assert prov["views"][0]["fields"]["pixel_spacing_mm"]["source"] == "user"
    masks = []
    for n, path in enumerate(paths):
        run = dicom.load_xa(path)
        frame = run.frames[prov["views"][n]["frame"]["index"]]
        masks.append(line_integrals_from_counts(frame, i0, mu) > 0.2)
    for mask, simulated in zip(masks, case.masks):
        # 12-bit rounding moves the recovered line integrals by < 0.02 mm: no pixel crosses 0.2 mm here.
        assert np.array_equal(mask, simulated)
    # small field: a quick check; on the CPU, where equal inputs give bit-equal runs (CUDA's atomic
    # additions do not: a second run differs in the last bits, RESULTS §34)
    settings = dict(steps=20, seed=0, log2_table_size=14, width=32, depth=2, device="cpu")
    from_dicom = reconstruct(rebuilt, masks, make_settings("fast", **settings))
    from_original = reconstruct(original, masks, make_settings("fast", **settings))
    assert np.array_equal(from_dicom.occupancy, from_original.occupancy)
    assert np.array_equal(from_dicom.segmentation, from_original.segmentation)
    assert from_dicom.report["geometry_digest"] == from_original.report["geometry_digest"]
