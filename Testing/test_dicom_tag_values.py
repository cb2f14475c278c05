"""DICOM tags that hold what the reader did not expect — several values, text that is no number, distances in
cm, a folder, a dataset without its preamble, signed pixels, the same run twice — are named, not crashed on."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest

import xa_writer
from SDFCARLib import dicom
from SDFCARLib.cli import main
from SDFCARLib.consistency import view_separation_deg, view_separation_warnings
from SDFCARLib.dicom import DicomInputError
from SDFCARLib.evidence import EvidenceError, view_evidence
from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid

VIEW = CArmView(30.0, -20.0, 1000.0, 757.0, (0.3, 0.3), (40, 48))


def xa(tmp_path, name="run.dcm", view=VIEW, **kwargs):
    frames = np.random.default_rng(3).integers(0, 4096, size=(2, 40, 48)).astype(np.uint16)
    return xa_writer.write_xa(tmp_path / name, frames, view, bits_stored=12, **kwargs)


def rewritten(path, out, **values):
    ds = pydicom.dcmread(str(path))
    for keyword, value in values.items():
        setattr(ds, keyword, value)
    ds.save_as(str(out))
    return out


def test_a_tag_with_several_values_is_named_with_the_fix(tmp_path):
    path = xa(tmp_path)
    for keyword, key, option in (("PositionerPrimaryAngle", "primary_deg", "--primary1"),
                                 ("DistanceSourceToDetector", "sid_mm", "--sid1"),
                                 ("DistanceSourceToPatient", "sod_mm", "--sod1")):
        bad = rewritten(path, tmp_path / f"{keyword}.dcm", **{keyword: ["30", "10"]})
        with pytest.raises(DicomInputError, match=rf"view 1 .*{keyword} holds 2 values \(30\\10\) where it has one\..*{option}"):
            dicom.view_from_dicom(bad, 0, view_number=1)
        # the user's value replaces the tag, and the tag that could not be read is noted
        view, provenance = dicom.view_from_dicom(bad, 0, {key: 40.0 if key == "primary_deg" else 900.0}, view_number=1)
        assert any(f"{keyword} holds 2 values" in note for note in provenance["notes"])
    # tags used for a note or a fallback only: noted, the geometry read
    for keyword in ("DetectorPrimaryAngle", "EstimatedRadiographicMagnificationFactor", "IntensifierSize"):
        view, provenance = dicom.view_from_dicom(rewritten(path, tmp_path / f"{keyword}.dcm", **{keyword: ["1", "2"]}), 0)
        assert view.primary_deg == 30.0 and view.sod_mm == 757.0
    _, provenance = dicom.view_from_dicom(tmp_path / "DetectorPrimaryAngle.dcm", 0)
    assert any("DetectorPrimaryAngle holds 2 values (1\\2) where it has one: not read" in n for n in provenance["notes"])
    with pytest.raises(DicomInputError, match=r"RescaleSlope holds 2 values"):
        dicom.load_xa(rewritten(path, tmp_path / "slope.dcm", RescaleSlope=["1", "2"]))


def test_an_angle_that_is_no_number_is_named_with_the_fix(tmp_path, capsys):
    path = xa(tmp_path, view=CArmView(12.3456, -20.0, 1000.0, 757.0, (0.3, 0.3), (40, 48)))
    data = path.read_bytes()
    assert data.count(b"12.3456") == 1
    comma = tmp_path / "comma.dcm"
    comma.write_bytes(data.replace(b"12.3456", b"12,3456"))  # a decimal comma, as some exports write
    with pytest.raises(DicomInputError, match=r"PositionerPrimaryAngle = '12,3456' is not a number\..*--primary1"):
        dicom.view_from_dicom(comma, 0, view_number=1)
    assert main(["geometry", "--dicom", str(comma), str(path), "--out", str(tmp_path / "G.json")]) == 2
    err = capsys.readouterr().err
    assert "'12,3456' is not a number" in err and "could not convert" not in err and not (tmp_path / "G.json").exists()


def test_distances_in_cm_are_named_as_such(tmp_path):
    cm = xa(tmp_path, "cm.dcm", extra={"DistanceSourceToDetector": "100", "DistanceSourceToPatient": "75.7",
                                      "EstimatedRadiographicMagnificationFactor": "1.321"})
    other = xa(tmp_path, "other.dcm", view=CArmView(-30.0, 20.0, 1000.0, 757.0, (0.3, 0.3), (40, 48)))
    with pytest.raises(DicomInputError, match=rf"view 1 \({cm}\).*under 300 mm: DICOM gives distances in mm"):
        dicom.geometry_from_dicom_runs([cm, other])


def test_a_folder_and_a_dataset_without_preamble(tmp_path):
    with pytest.raises(DicomInputError, match="is a folder; give one run's DICOM file in it"):
        dicom.load_xa(tmp_path)
    path = xa(tmp_path)
    ds = pydicom.dcmread(str(path))
    del ds.file_meta
    ds.preamble = None
    bare = tmp_path / "bare.dcm"
    pydicom.dcmwrite(str(bare), ds, enforce_file_format=False, implicit_vr=False, little_endian=True)
    assert bare.read_bytes()[:2] == b"\x08\x00"  # the dataset's first element (group 0008): no preamble, no file meta
    with pytest.raises(pydicom.errors.InvalidDicomError):
        pydicom.dcmread(str(bare))  # pydicom alone refuses it without force
    np.testing.assert_array_equal(dicom.load_xa(bare).frames, dicom.load_xa(path).frames)


def test_signed_or_shifted_frames_give_no_path_lengths():
    view = CArmView(30.0, 0.0, 1000.0, 750.0, (0.3, 0.3), (64, 64))
    frame = np.tile(np.linspace(1000.0, 3000.0, 64), (64, 1))  # unsigned counts, brighter to the right
    mask = np.zeros((64, 64), bool)
    mask[20:44, 30:33] = True
    frame[mask] *= 0.6
    with pytest.raises(EvidenceError, match=r"5\d % of the frame's pixels are negative \(the least -1048\).*Pixel "
                                            r"Representation 1"):
        view_evidence(frame - 2048.0, mask, view)  # stored signed: shifted by 2^11


def test_views_along_one_line_are_warned_of():
    def geometry(*angles):
        return Geometry(VolumeGrid((8, 8, 8), (1.0, 1.0, 1.0)),
                        tuple(CArmView(a, b, 1000.0, 750.0, (0.5, 0.5), (64, 64)) for a, b in angles))

    assert view_separation_deg(*geometry((30, 0), (-30, 0)).views) == pytest.approx(60.0)
    assert view_separation_deg(*geometry((30, -20), (-150, 20)).views) == pytest.approx(0.0, abs=1e-6)  # opposite
    assert view_separation_warnings(geometry((30, 0), (-30, 0))) == []
    same = view_separation_warnings(geometry((30, -20), (30, -20)))
    assert len(same) == 1 and "views 1 and 2 look along the same line" in same[0] and "given twice" in same[0]
    close = view_separation_warnings(geometry((30, 0), (40, 0)))
    assert len(close) == 1 and "at most 10.0° apart" in close[0] and "at least 25° apart" in close[0]
    # a third view far from a close pair gives the depth: no warning about the spread
    assert view_separation_warnings(geometry((30, 0), (40, 0), (-40, 25))) == []


def test_the_same_run_given_twice_is_warned_of_by_geometry(tmp_path, capsys):
    path = xa(tmp_path)
    _, provenance = dicom.geometry_from_dicom_runs([path, path])
    assert any("look along the same line" in w for w in provenance["warnings"])
    assert main(["geometry", "--dicom", str(path), str(path), "--out", str(tmp_path / "G.json")]) == 0
    assert "warning: views 1 and 2 look along the same line" in capsys.readouterr().err


def test_spacing_tags_that_cannot_be_used_are_named(tmp_path):
    path = xa(tmp_path, omit=("ImagerPixelSpacing",))
    one_value = rewritten(path, tmp_path / "one.dcm", ImagerPixelSpacing="0.3")
    with pytest.raises(DicomInputError, match=r"gives it \(present but not usable: \(0018,1164\) ImagerPixelSpacing = '0.3'\)"):
        dicom.view_from_dicom(one_value, 0)
    three = rewritten(path, tmp_path / "three.dcm", FieldOfViewDimensions=["200", "200", "5"])
    with pytest.raises(DicomInputError, match=r"FieldOfViewDimensions = "):
        dicom.view_from_dicom(three, 0)  # three values are no field of view: not silently the first
    square = rewritten(path, tmp_path / "square.dcm", FieldOfViewDimensions=["192"])
    view, _ = dicom.view_from_dicom(square, 0)
    assert view.pixel_spacing_mm == pytest.approx((4.0, 4.0))  # 192 mm over the 48-pixel side


def test_a_file_with_no_sop_class_and_an_output_that_is_a_folder(tmp_path, capsys):
    path = xa(tmp_path)
    ds = pydicom.dcmread(str(path))
    del ds.SOPClassUID
    del ds.file_meta.MediaStorageSOPClassUID
    nameless = tmp_path / "nameless.dcm"
    ds.save_as(str(nameless), enforce_file_format=False)
    with pytest.raises(DicomInputError, match=r"it has no SOP Class UID \(0008,0016\), modality XA"):
        dicom.load_xa(nameless)
    other = xa(tmp_path, "other.dcm", view=CArmView(-30.0, 20.0, 1000.0, 757.0, (0.3, 0.3), (40, 48)))
    folder = tmp_path / "G.json"
    folder.mkdir()
    assert main(["geometry", "--dicom", str(path), str(other), "--out", str(folder), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "a folder of that name exists; give a file name" in err and ".tmp" not in err
    assert folder.is_dir() and not list(folder.iterdir()) and not list(tmp_path.glob(".G.json.*"))


def test_a_file_meta_without_a_transfer_syntax_is_read_as_its_reader_found_it(tmp_path):
    path = xa(tmp_path)
    ds = pydicom.dcmread(str(path))
    del ds.file_meta.TransferSyntaxUID
    no_syntax = tmp_path / "no_syntax.dcm"
    pydicom.dcmwrite(str(no_syntax), ds, enforce_file_format=False, implicit_vr=False, little_endian=True)
    assert "TransferSyntaxUID" not in pydicom.dcmread(str(no_syntax)).file_meta
    np.testing.assert_array_equal(dicom.load_xa(no_syntax).frames, dicom.load_xa(path).frames)


def test_an_angle_increment_that_is_no_number_is_named(tmp_path):
    path = xa(tmp_path, angle_increments_deg=([1.2345, 1.2345], [0.0, 0.0]))
    data = path.read_bytes()
    comma = tmp_path / "comma.dcm"
    comma.write_bytes(data.replace(b"1.2345", b"1,2345"))
    with pytest.raises(DicomInputError, match=r"PositionerPrimaryAngleIncrement = .*is not a list of numbers.*primary_deg"):
        dicom.view_from_dicom(comma, 1)
