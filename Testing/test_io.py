"""SDFCARLib.io: detector images, masks, volumes (NRRD/NIfTI → LPS), segmentations and surfaces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from SDFCARLib.geometry import VolumeGrid
from SDFCARLib.io import (
    InputError,
    align_to_grid,
    process_umask,
    read_image,
    read_label,
    read_line_integral,
    read_mask,
    read_surface_vtk,
    read_volume,
    write_image_nrrd,
    write_json,
    write_mask_png,
    write_segmentation_nrrd,
    write_surface_vtk,
    write_volume_nrrd,
)

GRID = VolumeGrid((4, 5, 6), (1.0, 2.0, 3.0), (10.0, -20.0, 30.0))


def _png(path: Path, array: np.ndarray) -> Path:
    import imageio.v3 as iio

    iio.imwrite(path, array, extension=".png")
    return path


def _marker_image(shape=(6, 9)) -> np.ndarray:
    image = np.zeros(shape, np.uint8)
    image[0, 5] = 255  # top row, right of centre: catches transposed or flipped reads
    image[4, 1] = 255
    return image


# --- detector images ----------------------------------------------------------------------------
def test_png_tiff_and_nrrd_images_read_with_row_zero_at_the_top(tmp_path):
    import nrrd
    import tifffile

    image = _marker_image()
    _png(tmp_path / "a.png", image)
    tifffile.imwrite(tmp_path / "a.tif", image)
    nrrd.write(str(tmp_path / "a.nrrd"), image, index_order="C")
    nrrd.write(str(tmp_path / "b.nrrd"), image[None], index_order="C")  # 3D with a singleton axis
    for name in ("a.png", "a.tif", "a.nrrd", "b.nrrd"):
        np.testing.assert_array_equal(read_image(tmp_path / name), image, err_msg=name)


def test_colour_images_need_equal_channels(tmp_path):
    grey = _marker_image()
    rgb = np.stack([grey] * 3, axis=-1)
    rgba = np.concatenate([rgb, np.full(grey.shape + (1,), 255, np.uint8)], axis=-1)
    np.testing.assert_array_equal(read_image(_png(tmp_path / "rgb.png", rgb)), grey)
    np.testing.assert_array_equal(read_image(_png(tmp_path / "rgba.png", rgba)), grey)
    red = rgb.copy()
    red[0, 0, 0] = 200
    with pytest.raises(InputError, match="colour image"):
        read_image(_png(tmp_path / "red.png", red))
    see_through = rgba.copy()
    see_through[1, 1, 3] = 0
    with pytest.raises(InputError, match="transparency"):
        read_image(_png(tmp_path / "alpha.png", see_through))


def test_bad_image_files_are_named_with_the_fix(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "a.jpg").write_bytes(b"\xff\xd8")
    with pytest.raises(InputError, match=r"unsupported .*PNG .*TIFF .*NRRD"):
        read_image(tmp_path / "a.jpg")
    (tmp_path / "broken.png").write_bytes(b"this is not a png")
    with pytest.raises(InputError, match="cannot read .*broken.png as a PNG"):
        read_image(tmp_path / "broken.png")
    import nrrd

    nrrd.write(str(tmp_path / "stack.nrrd"), np.zeros((3, 6, 9), np.uint8), index_order="C")
    with pytest.raises(InputError, match="3-D data .* single 2D image"):
        read_image(tmp_path / "stack.nrrd")


def test_read_mask_binarises_and_rejects_bad_masks(tmp_path):
    image = _marker_image()
    mask = read_mask(_png(tmp_path / "m.png", image), detector_shape=(6, 9))
    assert mask.dtype == bool and mask.sum() == 2 and mask[0, 5]
    cases = {
        "empty": (np.zeros((6, 9), np.uint8), "empty"),
        "full": (np.full((6, 9), 255, np.uint8), "every pixel"),
        "ternary": (np.array([[0, 1, 2] * 3] * 6, np.uint8), r"not binary \(values 0, 1, 2\)"),
    }
    for name, (data, message) in cases.items():
        with pytest.raises(InputError, match=message):
            read_mask(_png(tmp_path / f"{name}.png", data))
    with pytest.raises(InputError, match=r"shape \(6, 9\).*detector shape \(9, 6\)"):
        read_mask(tmp_path / "m.png", detector_shape=(9, 6))
    import nrrd

    nan_mask = image.astype(np.float32)
    nan_mask[2, 2] = np.nan
    nrrd.write(str(tmp_path / "nan.nrrd"), nan_mask, index_order="C")
    with pytest.raises(InputError, match="nan.nrrd.*NaN"):
        read_mask(tmp_path / "nan.nrrd")


def test_line_integral_images_round_trip_and_are_checked(tmp_path):
    image = np.zeros((6, 9), np.float32)
    image[2, 3] = 1.5
    write_image_nrrd(tmp_path / "li.nrrd", image, (0.3, 0.4))
    np.testing.assert_array_equal(read_line_integral(tmp_path / "li.nrrd", (6, 9)), image)
    write_image_nrrd(tmp_path / "neg.nrrd", -image)
    with pytest.raises(InputError, match="cannot be negative"):
        read_line_integral(tmp_path / "neg.nrrd")
    write_image_nrrd(tmp_path / "zero.nrrd", 0 * image)
    with pytest.raises(InputError, match="all zero"):
        read_line_integral(tmp_path / "zero.nrrd")
    write_mask_png(tmp_path / "mask.png", image > 0)
    with pytest.raises(InputError, match=r"only the values 0 and 255: a mask, not line integrals .* \(--mask\)"):
        read_line_integral(tmp_path / "mask.png")


def test_mask_png_is_uint8_0_255(tmp_path):
    import imageio.v3 as iio

    mask = _marker_image() > 0
    data = iio.imread(write_mask_png(tmp_path / "m.png", mask))
    assert data.dtype == np.uint8 and set(np.unique(data)) == {0, 255}
    np.testing.assert_array_equal(data > 0, mask)


# --- volumes ------------------------------------------------------------------------------------
def _volume() -> np.ndarray:
    return np.arange(np.prod(GRID.shape), dtype=np.float32).reshape(GRID.shape)


def test_nrrd_volume_round_trip(tmp_path):
    import nrrd

    volume = _volume()
    write_volume_nrrd(tmp_path / "v.nrrd", volume, GRID)
    header = nrrd.read_header(str(tmp_path / "v.nrrd"))
    assert header["space"] == "left-posterior-superior" and header["encoding"] == "gzip" and header["type"] == "float"
    np.testing.assert_allclose(header["space directions"], np.diag(GRID.spacing_mm))
    np.testing.assert_allclose(header["space origin"], GRID.origin)
    data, grid = read_volume(tmp_path / "v.nrrd")
    np.testing.assert_array_equal(data, volume)
    assert grid.shape == GRID.shape
    np.testing.assert_allclose(grid.spacing_mm, GRID.spacing_mm)
    np.testing.assert_allclose(grid.center_mm, GRID.center_mm, atol=1e-9)
    write_volume_nrrd(tmp_path / "b.nrrd", volume > 50, GRID)
    assert nrrd.read_header(str(tmp_path / "b.nrrd"))["type"] in ("uint8", "unsigned char")


def test_nrrd_in_ras_with_flipped_and_permuted_axes_lands_at_the_right_lps_position(tmp_path):
    import nrrd

    # File axes: 0 runs towards Right (−x LPS) at 1.5 mm, 1 towards Superior at 2 mm, 2 towards
    # Anterior (−y LPS) at 0.5 mm; RAS origin (10, 20, 30).
    data = np.zeros((4, 5, 6), np.uint8)
    data[1, 2, 3] = 7
    directions = np.array([[1.5, 0, 0], [0, 0, 2.0], [0, 0.5, 0]])  # RAS rows
    header = {"space": "right-anterior-superior", "space directions": directions, "space origin": np.array([10.0, 20.0, 30.0]),
              "kinds": ["domain"] * 3}
    nrrd.write(str(tmp_path / "ras.nrrd"), data, header, index_order="F")
    ras = np.array([10.0, 20.0, 30.0]) + 1 * directions[0] + 2 * directions[1] + 3 * directions[2]
    expected_lps = ras * np.array([-1, -1, 1])
    volume, grid = read_volume(tmp_path / "ras.nrrd")
    assert volume.shape == (4, 6, 5)
    np.testing.assert_allclose(grid.spacing_mm, (1.5, 0.5, 2.0))
    (index,) = np.argwhere(volume == 7)
    np.testing.assert_allclose(grid.index_to_world(index), expected_lps, atol=1e-9)
    assert volume.sum() == 7


def test_nifti_is_converted_from_ras_to_lps(tmp_path):
    import nibabel

    data = np.zeros((4, 5, 6), np.int16)
    data[1, 2, 3] = 1
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    affine[:3, 3] = (-10.0, 20.0, 5.0)
    nibabel.save(nibabel.Nifti1Image(data, affine), str(tmp_path / "v.nii.gz"))
    volume, grid = read_volume(tmp_path / "v.nii.gz")
    (index,) = np.argwhere(volume)
    # voxel (1, 2, 3) is at RAS (−8, 24, 11), i.e. LPS (8, −24, 11)
    np.testing.assert_allclose(grid.index_to_world(index), (8.0, -24.0, 11.0), atol=1e-9)
    assert np.all(np.asarray(grid.spacing_mm) == 2.0)


def test_nifti_round_trip_through_lps_affine(tmp_path):
    import nibabel

    volume = _volume()
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ GRID.ijk_to_lps_matrix()  # LPS → RAS
    nibabel.save(nibabel.Nifti1Image(volume, affine), str(tmp_path / "v.nii"))
    data, grid = read_volume(tmp_path / "v.nii")
    np.testing.assert_array_equal(data, volume)
    np.testing.assert_allclose(grid.center_mm, GRID.center_mm, atol=1e-5)


def test_oblique_volumes_are_refused(tmp_path):
    import nrrd

    c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    header = {"space": "left-posterior-superior", "space directions": np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]]),
              "space origin": np.zeros(3)}
    nrrd.write(str(tmp_path / "oblique.nrrd"), np.ones((3, 3, 3), np.uint8), header, index_order="F")
    with pytest.raises(InputError, match=r"rotated \(oblique\).*10\.00°.*resample"):
        read_volume(tmp_path / "oblique.nrrd")
    nrrd.write(str(tmp_path / "nospace.nrrd"), np.ones((3, 3, 3), np.uint8), index_order="F")
    with pytest.raises(InputError, match="no 'space directions'"):
        read_volume(tmp_path / "nospace.nrrd")
    with pytest.raises(InputError, match="unsupported volume format"):
        read_volume(_png(tmp_path / "a.png", _marker_image()))


def test_align_to_grid_pads_shifted_crops_and_refuses_other_grids():
    label = np.zeros(GRID.shape, bool)
    label[1:3, 2, 3] = True
    # A crop of the label starting at voxel (1, 2, 3), as Slicer saves segmentations.
    crop_grid = VolumeGrid((2, 1, 1), GRID.spacing_mm, tuple(GRID.index_to_world([1.5, 2, 3])))
    aligned = align_to_grid(label[1:3, 2:3, 3:4], crop_grid, GRID)
    np.testing.assert_array_equal(aligned, label)
    with pytest.raises(InputError, match="different grids"):
        align_to_grid(label, VolumeGrid(GRID.shape, (1.0, 1.0, 1.0), GRID.center_mm), GRID)
    with pytest.raises(InputError, match="fraction of a voxel"):
        align_to_grid(label, VolumeGrid(GRID.shape, GRID.spacing_mm, (10.3, -20.0, 30.0)), GRID)
    shifted = VolumeGrid(GRID.shape, GRID.spacing_mm, tuple(np.asarray(GRID.center_mm) + (3.0, 0.0, 0.0)))
    with pytest.raises(InputError, match="outside the reference grid"):
        align_to_grid(label, shifted, GRID)


def test_read_label_thresholds_continuous_volumes_and_collapses_segment_layers(tmp_path):
    import nrrd

    occupancy = np.zeros(GRID.shape, np.float32)
    occupancy[1, 1, 1], occupancy[2, 2, 2] = 0.7, 0.2
    write_volume_nrrd(tmp_path / "occ.nrrd", occupancy, GRID)
    with pytest.raises(InputError, match="continuous values.*threshold"):
        read_label(tmp_path / "occ.nrrd")
    label, _ = read_label(tmp_path / "occ.nrrd", threshold=0.5)
    assert label.sum() == 1 and label[1, 1, 1]
    # A two-layer segmentation (Slicer's 4D .seg.nrrd with overlapping segments).
    layers = np.zeros((2,) + GRID.shape, np.uint8)
    layers[0, 0, 0, 0], layers[1, 3, 4, 5] = 1, 2
    directions = np.vstack([np.full(3, np.nan), np.diag(GRID.spacing_mm)])
    nrrd.write(str(tmp_path / "layers.seg.nrrd"), layers,
               {"space": "left-posterior-superior", "space directions": directions, "space origin": GRID.origin,
                "kinds": ["list", "domain", "domain", "domain"]}, index_order="F")
    label, grid = read_label(tmp_path / "layers.seg.nrrd")
    assert grid.shape == GRID.shape and label.sum() == 2 and label[0, 0, 0] and label[3, 4, 5]


def test_read_label_voxelises_a_centreline_on_the_grid(tmp_path):
    vtk = pytest.importorskip("vtk", reason="the vtk package (extra 'headless', or Slicer) is not installed")

    points = vtk.vtkPoints()
    for p in ((5.0, -20.0, 28.5), (9.8, -20.0, 28.5)):
        points.InsertNextPoint(*p)
    line = vtk.vtkPolyLine()
    line.GetPointIds().SetNumberOfIds(2)
    for i in range(2):
        line.GetPointIds().SetId(i, i)
    cells = vtk.vtkCellArray()
    cells.InsertNextCell(line)
    radii = vtk.vtkDoubleArray()
    radii.SetName("radii")
    for r in (0.6, 0.6):
        radii.InsertNextValue(r)
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(cells)
    poly.GetPointData().AddArray(radii)
    writer = vtk.vtkPolyDataWriter()
    writer.SetFileName(str(tmp_path / "line.vtk"))
    writer.SetInputData(poly)
    writer.Write()
    with pytest.raises(InputError, match="needs a volume grid"):
        read_label(tmp_path / "line.vtk")
    label, grid = read_label(tmp_path / "line.vtk", grid=GRID)
    assert grid is GRID
    # Voxel centres: x = 8.5, 9.5, 10.5, 11.5; y = −24 … −16 by 2; z = 22.5 … 37.5 by 3. The tube
    # (x 5 → 9.8 at y = −20, z = 28.5, radius 0.6) holds x = 8.5 and 9.5 at j = 2, k = 2; x = 10.5
    # is 0.7 mm beyond its end.
    expected = np.zeros(GRID.shape, bool)
    expected[0:2, 2, 2] = True
    np.testing.assert_array_equal(label, expected)


# --- segmentations and surfaces in Slicer (slicer-core) -------------------------------------------
def _mrml():
    return pytest.importorskip("slicer", reason="slicer-core (extra 'headless') is not installed; it checks Slicer reads our files")


def _read_with_slicer(path: Path, node_class: str, storage_class: str):
    """Read ``path`` into a new node with Slicer's own storage node, as File > Add Data does."""
    slicer = _mrml()
    scene = slicer.vtkMRMLScene()
    storage = getattr(slicer, storage_class)()
    scene.AddNode(storage)
    node = scene.AddNewNodeByClass(node_class)
    storage.SetFileName(str(path))
    assert storage.ReadData(node) == 1
    return node


def test_segmentation_is_read_by_slicer_at_the_right_ras_position(tmp_path):
    _mrml()
    from vtk.util.numpy_support import vtk_to_numpy

    mask = np.zeros(GRID.shape, bool)
    mask[1, 2, 3] = mask[2, 2, 3] = mask[2, 4, 5] = True
    write_segmentation_nrrd(tmp_path / "s.seg.nrrd", mask, GRID, name="Coronary tree", color=(0.9, 0.2, 0.2))
    node = _read_with_slicer(tmp_path / "s.seg.nrrd", "vtkMRMLSegmentationNode", "vtkMRMLSegmentationStorageNode")
    segmentation = node.GetSegmentation()
    assert segmentation.GetNumberOfSegments() == 1
    segment = segmentation.GetNthSegment(0)
    assert segment.GetName() == "Coronary tree"
    assert segment.GetLabelValue() == 1
    np.testing.assert_allclose(segment.GetColor(), (0.9, 0.2, 0.2))
    labelmap = segment.GetRepresentation("Binary labelmap")
    values = vtk_to_numpy(labelmap.GetPointData().GetScalars())
    assert int((values == 1).sum()) == 3
    # RAS of the labelmap voxel that holds mask[1, 2, 3] must be LPS(1, 2, 3) with x and y negated.
    extent = labelmap.GetExtent()
    ijk = (1, 2, 3)
    flat = (ijk[2] - extent[4]) * (extent[3] - extent[2] + 1) * (extent[1] - extent[0] + 1) \
        + (ijk[1] - extent[2]) * (extent[1] - extent[0] + 1) + (ijk[0] - extent[0])
    assert values[flat] == 1
    import vtk

    matrix = vtk.vtkMatrix4x4()
    labelmap.GetImageToWorldMatrix(matrix)
    ras = np.array(matrix.MultiplyPoint((*ijk, 1.0))[:3])
    np.testing.assert_allclose(ras, GRID.index_to_world(ijk) * np.array([-1, -1, 1]), atol=1e-6)


def test_empty_segmentation_is_still_a_readable_segmentation(tmp_path):
    _mrml()
    write_segmentation_nrrd(tmp_path / "e.seg.nrrd", np.zeros(GRID.shape, bool), GRID)
    node = _read_with_slicer(tmp_path / "e.seg.nrrd", "vtkMRMLSegmentationNode", "vtkMRMLSegmentationStorageNode")
    assert node.GetSegmentation().GetNumberOfSegments() == 1


def test_surface_is_marked_lps_so_slicer_shows_it_in_ras(tmp_path):
    _mrml()
    from vtk.util.numpy_support import vtk_to_numpy

    vertices = np.array([[10.0, 20.0, 30.0], [11.0, 20.0, 30.0], [10.0, 21.5, 30.0]])
    faces = np.array([[0, 1, 2]])
    write_surface_vtk(tmp_path / "m.vtk", vertices, faces)
    assert b"SPACE=LPS" in (tmp_path / "m.vtk").read_bytes()[:80]
    stored_vertices, stored_faces = read_surface_vtk(tmp_path / "m.vtk")
    np.testing.assert_allclose(stored_vertices, vertices)
    np.testing.assert_array_equal(stored_faces, faces)
    node = _read_with_slicer(tmp_path / "m.vtk", "vtkMRMLModelNode", "vtkMRMLModelStorageNode")
    ras = vtk_to_numpy(node.GetPolyData().GetPoints().GetData())
    np.testing.assert_allclose(ras, vertices * np.array([-1, -1, 1]))


def test_json_files_get_the_mode_of_a_new_file_or_keep_the_one_they_had(tmp_path):
    """write_json stages in a private temporary file: the file put in place is readable as any new file is
    (0666 less the umask), and one replaced keeps its own mode."""
    new = write_json(tmp_path / "report.json", {"a": 1})
    assert new.stat().st_mode & 0o777 == 0o666 & ~process_umask()
    new.chmod(0o640)
    write_json(new, {"a": 2})
    assert new.stat().st_mode & 0o777 == 0o640
    assert new.read_text() == '{\n  "a": 2\n}\n'


def test_volume_units_other_than_mm_are_read_as_such_or_refused(tmp_path):
    import nibabel
    import nrrd

    data = np.zeros((4, 5, 6), np.int16)
    data[1, 2, 3] = 1
    image = nibabel.Nifti1Image(data, np.diag([0.002, 0.002, 0.002, 1.0]))  # 2 mm voxels, in metres
    image.header.set_xyzt_units("meter")
    nibabel.save(image, str(tmp_path / "metres.nii.gz"))
    _, grid = read_volume(tmp_path / "metres.nii.gz")
    np.testing.assert_allclose(grid.spacing_mm, (2.0, 2.0, 2.0))
    nrrd.write(str(tmp_path / "cm.nrrd"), data, {"space": "left-posterior-superior", "space directions": np.eye(3) * 0.2,
                                                "space units": ["cm", "cm", "cm"], "space origin": np.zeros(3)})
    with pytest.raises(InputError, match=r"space units are \['cm', 'cm', 'cm'\], not mm"):
        read_volume(tmp_path / "cm.nrrd")


def test_a_transposed_mask_is_named_as_such(tmp_path):
    mask = np.zeros((40, 30), bool)
    mask[5:10, 3:20] = True
    path = write_mask_png(tmp_path / "m.png", mask)
    with pytest.raises(InputError, match=r"the detector shape \(30, 40\) with rows and columns swapped: transpose"):
        read_mask(path, detector_shape=(30, 40))


def test_label_file_warnings_name_merged_segments_and_disagreeing_nifti_placements(tmp_path):
    import nibabel
    import nrrd

    from SDFCARLib.io import label_file_warnings

    write_segmentation_nrrd(tmp_path / "one.seg.nrrd", _volume() > 0, GRID, name="Coronary tree")
    assert label_file_warnings(tmp_path / "one.seg.nrrd") == []
    data, header = nrrd.read(str(tmp_path / "one.seg.nrrd"))
    header.update({"Segment1_Name": "Catheter", "Segment1_Layer": "0", "Segment1_LabelValue": "2"})
    nrrd.write(str(tmp_path / "two.seg.nrrd"), data, header)
    (warning,) = label_file_warnings(tmp_path / "two.seg.nrrd")
    assert "2 segments (Coronary tree, Catheter) are merged into one label" in warning

    data = np.zeros((4, 5, 6), np.uint8)
    data[1, 2, 3] = 1
    image = nibabel.Nifti1Image(data, np.diag([2.0, 2.0, 2.0, 1.0]))
    image.set_qform(np.diag([2.0, 2.0, 2.0, 1.0]), code=1)
    nibabel.save(image, str(tmp_path / "agree.nii"))
    assert label_file_warnings(tmp_path / "agree.nii") == []
    shifted = np.diag([2.0, 2.0, 2.0, 1.0])
    shifted[:3, 3] = (0.0, 3.0, 4.0)  # the qform 5 mm away
    image.set_qform(shifted, code=1)
    nibabel.save(image, str(tmp_path / "disagree.nii"))
    (warning,) = label_file_warnings(tmp_path / "disagree.nii")
    assert "sform and qform place the volume up to 5.00 mm apart" in warning
    image.set_qform(shifted, code=0)  # an uncoded qform is no placement
    nibabel.save(image, str(tmp_path / "uncoded.nii"))
    assert label_file_warnings(tmp_path / "uncoded.nii") == []
