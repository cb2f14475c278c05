"""SDFCARLib.outputs: the result folder (files, report, surface) written all at once or not at all."""

from __future__ import annotations

import json
import sys
import tempfile
import types
from pathlib import Path

import numpy as np
import pytest

from SDFCARLib.geometry import VolumeGrid
from SDFCARLib.outputs import OutputError, RESULT_FILES, staged_directory, surface_mesh, write_reconstruction

CENTRE = np.array([2.0, -4.0, 6.0])
RADIUS = 9.0


def _sphere_occupancy(grid: VolumeGrid, centre=CENTRE, radius=RADIUS, width_mm=1.0) -> np.ndarray:
    distance = np.linalg.norm(grid.voxel_centers() - centre, axis=1).reshape(grid.shape)
    return (1.0 / (1.0 + np.exp((distance - radius) / width_mm))).astype(np.float32)


def _reconstruction(geometry, occupancy: np.ndarray):
    from SDFCARLib.optimiser import Reconstruction
    from SDFCARLib.settings import make_settings

    settings = make_settings("fast", steps=1)
    report = {"method": "test", "settings": settings.to_dict(), "seed": settings.run.seed, "reprojection_dice": [1.0, 1.0]}
    field = np.log((1 - occupancy + 1e-6) / (occupancy + 1e-6)).astype(np.float32)
    return Reconstruction(geometry, settings, occupancy, field, occupancy >= 0.5, None, report, [])


@pytest.fixture
def no_scene(monkeypatch):
    """Make the MRML bridge unimportable, as on an install without slicer-core."""
    monkeypatch.setitem(sys.modules, "SDFCARLib.mrml", None)


def _edges_shared_twice(faces: np.ndarray) -> bool:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def test_surface_of_a_sphere_lies_at_its_radius_in_lps_mm(tiny_geometry):
    grid = tiny_geometry.volume
    vertices, faces = surface_mesh(_sphere_occupancy(grid), grid, 0.5)
    assert len(faces) > 100
    distances = np.linalg.norm(vertices - CENTRE, axis=1)
    np.testing.assert_allclose(distances, RADIUS, atol=0.25)  # linear interpolation of a 1 mm-wide edge on 2 mm voxels
    assert _edges_shared_twice(faces)


def test_surface_cut_by_the_grid_border_is_closed_and_inside_the_grid(tiny_geometry):
    grid = tiny_geometry.volume
    lo, hi = grid.bounds()
    centre = np.array([hi[0] - 2.0, 0.0, 0.0])  # most of the sphere lies outside the grid
    vertices, faces = surface_mesh(_sphere_occupancy(grid, centre, 8.0), grid, 0.5)
    assert len(faces) > 0 and _edges_shared_twice(faces)
    assert np.all(vertices >= lo - 1e-6) and np.all(vertices <= hi + 1e-6)


def test_surface_of_an_empty_volume_is_empty(tiny_geometry):
    grid = tiny_geometry.volume
    vertices, faces = surface_mesh(np.zeros(grid.shape, np.float32), grid, 0.5)
    assert vertices.shape == (0, 3) and faces.shape == (0, 3)


def test_write_reconstruction_writes_every_file_and_the_report(tmp_path, tiny_geometry, no_scene):
    import nrrd

    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")

    grid = tiny_geometry.volume
    result = _reconstruction(tiny_geometry, _sphere_occupancy(grid))
    out = tmp_path / "nested" / "result"
    files = write_reconstruction(result, out, name="Sphere", label=result.segmentation)
    expected = {k: v for k, v in RESULT_FILES.items() if k != "scene"}
    assert set(files) == set(expected)
    assert sorted(p.name for p in out.iterdir()) == sorted(expected.values())
    assert [p.name for p in tmp_path.iterdir()] == ["nested"] and [p.name for p in (tmp_path / "nested").iterdir()] == ["result"]

    occupancy, header = nrrd.read(str(files["occupancy"]))
    np.testing.assert_allclose(occupancy, result.occupancy)
    np.testing.assert_allclose(header["space origin"], grid.origin)
    segmentation, header = nrrd.read(str(files["segmentation"]))
    np.testing.assert_array_equal(segmentation, result.segmentation.astype(np.uint8))
    assert header["Segment0_Name"] == "Sphere" and header["Segment0_LabelValue"] == "1"

    report = json.loads(files["report"].read_text())
    assert report["method"] == "test" and report["name"] == "Sphere" and report["coordinate_system"] == "LPS"
    assert report["files"] == expected
    assert report["surface"]["triangles"] > 100 and report["surface"]["level"] == 0.5
    assert report["scene"]["written"] is False and "MRML bridge" in report["scene"]["reason"]
    assert any("scene.mrml was not written" in w for w in report["warnings"])
    assert report["metrics"]["prediction"]["dice"] == 1.0 and report["metrics"]["prediction"]["chamfer_l2_mm"] == 0.0
    hull = report["metrics"]["visual_hull"]
    assert hull["voxels_predicted"] >= report["metrics"]["prediction"]["voxels_predicted"]  # the hull contains the shape
    assert len(report["metrics"]["prediction"]["reprojection_dice"]) == 2


def test_empty_segmentation_gives_an_empty_surface_a_warning_and_null_metrics(tmp_path, tiny_geometry, no_scene):
    grid = tiny_geometry.volume
    result = _reconstruction(tiny_geometry, np.zeros(grid.shape, np.float32))
    label = np.zeros(grid.shape, bool)
    label[10:14, 10:14, 10:14] = True
    files = write_reconstruction(result, tmp_path / "out", label=label)
    report_text = files["report"].read_text()
    assert "NaN" not in report_text
    report = json.loads(report_text)
    assert report["surface"]["triangles"] == 0
    empty = [w for w in report["warnings"] if "segmentation is empty" in w]
    # one step of fast's 400: the hint names the cut-short fit, not the masks
    assert len(empty) == 1 and "the fit ran only 1 steps (1 of them warming the learning rates up): leave --steps out " \
                               "to run the fast preset's 400" in empty[0]
    assert report["metrics"]["prediction"]["chamfer_l2_mm"] is None  # NaN written as null
    assert report["metrics"]["prediction"]["dice"] == 0.0


def test_an_empty_result_of_a_full_length_fit_points_at_the_seed_and_the_masks():
    from SDFCARLib.outputs import _empty_result_hint
    from SDFCARLib.settings import make_settings

    hint = _empty_result_hint(make_settings("fast"))
    assert "--seed" in hint and "masks" in hint and "steps" not in hint
    unknown = make_settings("fast", steps=30)
    unknown.run.preset = "no-such-preset"  # a settings file of another version
    assert "give more --steps" in _empty_result_hint(unknown)


def test_existing_results_are_kept_unless_overwrite(tmp_path, tiny_geometry, no_scene):
    grid = tiny_geometry.volume
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "scene.mrml").write_text("<MRML/> from an earlier run")
    result = _reconstruction(tiny_geometry, _sphere_occupancy(grid))
    with pytest.raises(OutputError, match=r"already holds scene\.mrml.*--overwrite"):
        write_reconstruction(result, out)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "scene.mrml"]
    write_reconstruction(result, out, overwrite=True)
    names = sorted(p.name for p in out.iterdir())
    # The earlier run's scene would mix two runs: it is removed; unrelated files stay.
    assert "scene.mrml" not in names and "notes.txt" in names and "report.json" in names
    with pytest.raises(OutputError, match="is not a folder"):
        write_reconstruction(result, out / "notes.txt")


def test_an_output_folder_that_cannot_be_made_is_refused_before_any_work(tmp_path, monkeypatch):
    """check_destination (called by reconstruct, analyse, demo … before they work): a folder inside a file, or in a
    folder the user cannot write to, is named with the fix; nothing is made."""
    from SDFCARLib.outputs import check_destination
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match=r"lies inside .*notes\.txt, which is a file, not a folder"):
        check_destination(tmp_path / "notes.txt" / "result", ["report.json"])
    locked = tmp_path / "locked"
    locked.mkdir()
    real_mkdtemp = tempfile.mkdtemp

    def mkdtemp(*args, dir=None, **kwargs):
        if Path(dir) == locked:
            raise PermissionError(13, "Permission denied")
        return real_mkdtemp(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "mkdtemp", mkdtemp)
    for out in (locked / "result", locked / "a" / "b"):
        with pytest.raises(OutputError, match=r"cannot write in .*locked \(Permission denied\): the output folder .* cannot be made there"):
            check_destination(out, ["report.json"])
    with pytest.raises(OutputError, match=r"cannot write in .*locked \(Permission denied\): the output folder .* cannot be written to"):
        check_destination(locked, ["report.json"])
    check_destination(tmp_path / "new" / "deeper", ["report.json"])  # writable: fine
    assert sorted(p.name for p in tmp_path.iterdir()) == ["locked", "notes.txt"]  # nothing made


@pytest.mark.parametrize("existing", [False, True])
def test_a_failure_leaves_the_output_folder_as_it_was(tmp_path, tiny_geometry, monkeypatch, no_scene, existing):
    import SDFCARLib.outputs as outputs

    out = tmp_path / "out"
    before = {}
    if existing:
        out.mkdir()
        for name in ("report.json", "occupancy.nrrd", "notes.txt"):
            (out / name).write_text(f"earlier {name}")
        before = {p.name: p.read_text() for p in out.iterdir()}

    def failing_writer(*args, **kwargs):
        raise OSError("No space left on device")

    monkeypatch.setattr(outputs, "write_surface_vtk", failing_writer)
    result = _reconstruction(tiny_geometry, _sphere_occupancy(tiny_geometry.volume))
    with pytest.raises(OSError, match="No space left"):
        write_reconstruction(result, out, overwrite=True)
    if existing:
        assert {p.name: p.read_text() for p in out.iterdir()} == before
    else:
        assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["out"] if existing else [])  # no temporary folder left


def test_a_failure_while_moving_files_in_restores_the_earlier_files(tmp_path, monkeypatch):
    import os

    import SDFCARLib.outputs as outputs

    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old a")
    (out / "b.txt").write_text("old b")
    real_replace = os.replace
    failures = []

    def replace_failing_on_b(source, target):
        if Path(target) == out / "b.txt" and not failures:  # the new b.txt cannot be moved in, once
            failures.append(target)
            raise OSError("device went away")
        return real_replace(source, target)

    monkeypatch.setattr(outputs.os, "replace", replace_failing_on_b)
    with pytest.raises(OSError, match="went away"):
        with staged_directory(out, ["a.txt", "b.txt"], overwrite=True) as staging:
            (staging / "a.txt").write_text("new a")
            (staging / "b.txt").write_text("new b")
    assert {p.name: p.read_text() for p in out.iterdir()} == {"a.txt": "old a", "b.txt": "old b"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_scene_is_written_by_the_mrml_bridge_inside_the_staging_folder(tmp_path, tiny_geometry, monkeypatch):
    pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")
    calls = []

    def write_result_scene(directory, name, geometry, segmentation_file, surface_file, attributes):
        calls.append((Path(segmentation_file).is_file(), Path(surface_file).is_file(), attributes))
        path = Path(directory) / "scene.mrml"
        path.write_text(f"<MRML name='{name}'/>")
        return path

    monkeypatch.setitem(sys.modules, "SDFCARLib.mrml", types.SimpleNamespace(write_result_scene=write_result_scene))
    result = _reconstruction(tiny_geometry, _sphere_occupancy(tiny_geometry.volume))
    files = write_reconstruction(result, tmp_path / "out", name="Tree")
    assert files["scene"].read_text() == "<MRML name='Tree'/>"
    assert calls and calls[0][0] and calls[0][1]  # both files existed when the scene was written
    assert calls[0][2]["SDFCAR.coordinateSystem"] == "LPS"
    assert json.loads(files["report"].read_text())["scene"] == {"written": True}


def test_real_scene_still_finds_its_files_after_the_move_into_place(tmp_path, tiny_geometry):
    slicer = pytest.importorskip("slicer", reason="slicer-core (extra 'headless') is not installed; scene.mrml needs it")
    pytest.importorskip("SDFCARLib.mrml", reason="the MRML bridge module is not in this checkout yet")
    result = _reconstruction(tiny_geometry, _sphere_occupancy(tiny_geometry.volume))
    files = write_reconstruction(result, tmp_path / "out", name="Sphere")
    text = files["scene"].read_text()
    assert ".sdfcar-" not in text  # nothing points into the temporary folder
    scene = slicer.vtkMRMLScene()
    scene.SetURL(str(files["scene"]))
    assert scene.Import() == 1
    segmentation = scene.GetFirstNodeByClass("vtkMRMLSegmentationNode")
    model = scene.GetFirstNodeByClass("vtkMRMLModelNode")
    assert segmentation.GetSegmentation().GetNumberOfSegments() == 1
    report = json.loads(files["report"].read_text())
    assert model.GetPolyData().GetNumberOfPoints() == report["surface"]["vertices"]
    # Both nodes at the right place: the segment holds exactly the result's voxels (read back at
    # the voxel centres' RAS positions) and the model's points are the LPS surface with x, y negated.
    from vtk.util.numpy_support import vtk_to_numpy

    from SDFCARLib import mrml
    from SDFCARLib.io import read_surface_vtk

    np.testing.assert_array_equal(mrml.segmentation_mask_lps(segmentation, tiny_geometry.volume), result.segmentation)
    vertices_lps, _ = read_surface_vtk(files["surface"])
    model_ras = vtk_to_numpy(model.GetPolyData().GetPoints().GetData())
    np.testing.assert_allclose(model_ras, vertices_lps * np.array([-1.0, -1.0, 1.0]), atol=1e-4)


def test_analyse_finds_the_masks_report_json_names_inside_the_result_folder(tmp_path):
    """reconstruct --auto-masks names its masks relative to the result folder (auto_maskN.png): analyse finds them
    there, wherever it is run from."""
    import numpy as np

    from SDFCARLib.analysis.outputs import _masks_for
    from SDFCARLib.geometry import Geometry, VolumeGrid, standard_geometry
    from SDFCARLib.io import write_mask_png

    views = standard_geometry("lao30-rao30").views
    geometry = Geometry(VolumeGrid((8, 8, 8), (1.0, 1.0, 1.0)), views)
    folder = tmp_path / "result"
    folder.mkdir()
    masks = []
    for n, view in enumerate(views, start=1):
        mask = np.zeros(view.detector_shape, bool)
        mask[10 * n:10 * n + 5, 20:40] = True
        write_mask_png(folder / f"auto_mask{n}.png", mask)
        masks.append(mask)
    report = {"target_kind": "mask", "inputs": {"targets": ["auto_mask1.png", "auto_mask2.png"]}}
    found, note = _masks_for(report, geometry, None, folder)
    assert note is None and all(np.array_equal(f, m) for f, m in zip(found, masks))
    _, missing = _masks_for(report, geometry, None, tmp_path)  # not the folder that holds them
    assert "not found" in missing
