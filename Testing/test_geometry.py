"""C-arm geometry against hand-derived pinhole answers (convention: SDFCARLib/geometry.py).

Every expected pixel position below is derived on paper from the convention
d = (sin α cos β, −cos α cos β, sin β), source −SOD·d, u = (cos α, sin α, 0), v = u × d:
a point p projects to col = c0 + SID·((p − S)·u) / ((p − S)·d) / pixel_col and likewise for rows.
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from SDFCARLib.geometry import CArmView, Geometry, GeometryError, VolumeGrid, standard_geometry

SID, SOD = 1000.0, 750.0
M = SID / SOD  # magnification at the isocenter
PS = 0.5  # detector pixel spacing (mm), square unless a test says otherwise


def view(primary: float, secondary: float = 0.0, shape=(101, 101), spacing=(PS, PS), pp=None) -> CArmView:
    return CArmView(primary, secondary, SID, SOD, spacing, shape, pp)


def project_one(v: CArmView, point):
    row, col, depth = v.project(np.asarray(point, float))
    return float(row), float(col), float(depth)


# --- analytic pinhole answers -------------------------------------------------------------------
def test_ap_point_to_patient_left_lands_right_of_centre():
    v = view(0.0)
    r0, c0 = v.principal_point
    row, col, depth = project_one(v, (10.0, 0.0, 0.0))
    assert depth == pytest.approx(SOD)
    assert col == pytest.approx(c0 + M * 10.0 / PS)  # 26.67 px right: patient's left on image right
    assert row == pytest.approx(r0)


def test_ap_head_at_top_and_depth_changes_magnification():
    v = view(0.0)
    r0, c0 = v.principal_point
    row, col, _ = project_one(v, (0.0, 0.0, 10.0))  # superior
    assert row == pytest.approx(r0 - M * 10.0 / PS)  # above the centre (rows grow downwards)
    assert col == pytest.approx(c0)
    # 20 mm anterior (towards the detector) the magnification is SID / (SOD + 20).
    row, col, depth = project_one(v, (4.0, -20.0, -6.0))
    assert depth == pytest.approx(SOD + 20.0)
    assert col == pytest.approx(c0 + SID / (SOD + 20.0) * 4.0 / PS)
    assert row == pytest.approx(r0 + SID / (SOD + 20.0) * 6.0 / PS)


def test_ap_frame_vectors():
    v = view(0.0)
    np.testing.assert_allclose(v.detector_direction, [0, -1, 0], atol=1e-15)  # detector anterior
    np.testing.assert_allclose(v.source_position, [0, SOD, 0], atol=1e-12)  # source posterior
    np.testing.assert_allclose(v.detector_center, [0, -(SID - SOD), 0], atol=1e-12)
    np.testing.assert_allclose(v.column_direction, [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(v.row_direction, [0, 0, -1], atol=1e-15)


def test_lao90_lateral_view():
    # LAO 90: d = (1, 0, 0) (detector on the patient's left), u = (0, 1, 0), v = (0, 0, −1).
    v = view(90.0)
    r0, c0 = v.principal_point
    np.testing.assert_allclose(v.detector_direction, [1, 0, 0], atol=1e-15)
    row, col, depth = project_one(v, (0.0, 10.0, 0.0))  # posterior → right of the image
    assert depth == pytest.approx(SOD)
    assert col == pytest.approx(c0 + M * 10.0 / PS)
    assert row == pytest.approx(r0)
    row, col, depth = project_one(v, (30.0, 0.0, 5.0))  # on the patient's left, 5 mm superior
    assert depth == pytest.approx(SOD + 30.0)
    assert row == pytest.approx(r0 - SID / (SOD + 30.0) * 5.0 / PS)
    assert col == pytest.approx(c0)


def test_rao30_point_on_x_axis():
    # RAO 30 (α = −30°): d = (−1/2, −√3/2, 0), u = (√3/2, −1/2, 0). The point (10, 0, 0) lies
    # 10·cos30 along u and 10·sin30 = 5 mm towards the source: depth SOD − 5.
    v = view(-30.0)
    r0, c0 = v.principal_point
    row, col, depth = project_one(v, (10.0, 0.0, 0.0))
    assert depth == pytest.approx(SOD - 5.0)
    assert col == pytest.approx(c0 + SID / (SOD - 5.0) * 10.0 * math.sqrt(3) / 2 / PS)
    assert row == pytest.approx(r0)
    np.testing.assert_allclose(v.row_direction, [0, 0, -1], atol=1e-15)


def test_cra25_point_on_z_axis():
    # CRA 25: d = (0, −cos25, sin25), u = (1, 0, 0), v = u × d = (0, −sin25, −cos25).
    # (0, 0, 10) is 10·sin25 mm beyond the isocenter (depth SOD + 10 sin25) and 10·cos25 mm up.
    b = math.radians(25.0)
    v = view(0.0, 25.0)
    r0, c0 = v.principal_point
    np.testing.assert_allclose(v.row_direction, [0, -math.sin(b), -math.cos(b)], atol=1e-15)
    row, col, depth = project_one(v, (0.0, 0.0, 10.0))
    assert depth == pytest.approx(SOD + 10.0 * math.sin(b))
    assert row == pytest.approx(r0 - SID / (SOD + 10.0 * math.sin(b)) * 10.0 * math.cos(b) / PS)
    assert col == pytest.approx(c0)
    row, col, _ = project_one(v, (10.0, 0.0, 0.0))  # x is unaffected by a pure secondary angle
    assert col == pytest.approx(c0 + M * 10.0 / PS)
    assert row == pytest.approx(r0)


def test_anisotropic_pixel_spacing():
    v = view(0.0, spacing=(0.4, 0.25))
    r0, c0 = v.principal_point
    row, col, _ = project_one(v, (3.0, 0.0, -2.0))
    assert col == pytest.approx(c0 + M * 3.0 / 0.25)
    assert row == pytest.approx(r0 + M * 2.0 / 0.4)


# --- principal point and magnification ---------------------------------------------------------------
@pytest.mark.parametrize("angles", [(0, 0), (90, 0), (-30, 0), (0, 25), (-47.5, -33.0), (180, 0), (12, 90)])
def test_isocenter_projects_to_default_principal_point(angles):
    v = view(*angles, shape=(64, 81))
    row, col, depth = project_one(v, (0.0, 0.0, 0.0))
    assert (row, col) == pytest.approx((31.5, 40.0))  # ((rows − 1) / 2, (cols − 1) / 2)
    assert depth == pytest.approx(SOD)


def test_isocenter_projects_to_given_principal_point():
    v = view(-30.0, 10.0, shape=(64, 81), pp=(20.25, 50.5))
    row, col, _ = project_one(v, (0.0, 0.0, 0.0))
    assert (row, col) == pytest.approx((20.25, 50.5))
    # and the offsets from it follow the same pinhole model
    row, col, _ = project_one(v, 7.0 * v.column_direction)
    assert col == pytest.approx(50.5 + M * 7.0 / PS)
    assert row == pytest.approx(20.25)


@pytest.mark.parametrize("angles", [(0, 0), (35, -20), (-120, 40)])
def test_magnification_at_isocenter(angles):
    v = view(*angles)
    assert v.magnification == pytest.approx(SID / SOD)
    assert v.isocenter_pixel_spacing_mm == pytest.approx((PS / M, PS / M))
    # two points 1 mm apart in the isocenter plane are SID/SOD mm apart on the detector
    r_a, c_a, _ = project_one(v, -0.5 * v.column_direction)
    r_b, c_b, _ = project_one(v, 0.5 * v.column_direction)
    assert (c_b - c_a) * PS == pytest.approx(SID / SOD)
    assert r_b - r_a == pytest.approx(0.0, abs=1e-9)


# --- a 30° view rotates by exactly 30° (guards the public "half angle" bug) -------------------------
def _angle_deg(a, b) -> float:
    return math.degrees(math.acos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


@pytest.mark.parametrize("primary", [30.0, -30.0, 60.0])
def test_primary_angle_is_applied_in_full(primary):
    ap = view(0.0)
    rotated = view(primary)
    assert _angle_deg(ap.source_position, rotated.source_position) == pytest.approx(abs(primary))
    assert _angle_deg(ap.detector_direction, rotated.detector_direction) == pytest.approx(abs(primary))
    # the rotation is about the patient's long axis (z), so the source stays in the axial plane
    assert rotated.source_position[2] == pytest.approx(0.0, abs=1e-12)


def test_point_on_lao30_central_ray_projects_to_principal_point_only_in_lao30():
    lao30, lao15 = view(30.0), view(15.0)
    point = 40.0 * lao30.detector_direction  # 40 mm from the isocenter along the central ray
    row, col, _ = project_one(lao30, point)
    assert (row, col) == pytest.approx(lao30.principal_point, abs=1e-9)
    # A projector that applies half the angle would see it here, 40·sin15 mm off-axis → ~35 px.
    row, col, _ = project_one(lao15, point)
    assert abs(col - lao15.principal_point[1]) > 20.0


@pytest.mark.parametrize("secondary", [30.0, -30.0])
def test_secondary_angle_is_applied_in_full(secondary):
    ap, tilted = view(0.0), view(0.0, secondary)
    assert _angle_deg(ap.source_position, tilted.source_position) == pytest.approx(abs(secondary))
    assert np.sign(tilted.detector_direction[2]) == np.sign(secondary)  # CRA: detector towards the head
    point = 40.0 * tilted.detector_direction
    row, col, _ = project_one(tilted, point)
    assert (row, col) == pytest.approx(tilted.principal_point, abs=1e-9)
    row, col, _ = project_one(view(0.0, secondary / 2), point)
    assert abs(row - tilted.principal_point[0]) > 20.0


def test_combined_angles_source_direction():
    # LAO 50 CRA 25: the source direction is the unit vector of the convention, in full.
    a, b = math.radians(50.0), math.radians(25.0)
    v = view(50.0, 25.0)
    expected = -SOD * np.array([math.sin(a) * math.cos(b), -math.cos(a) * math.cos(b), math.sin(b)])
    np.testing.assert_allclose(v.source_position, expected, atol=1e-9)
    assert _angle_deg(v.detector_direction, [0, -1, 0]) == pytest.approx(
        math.degrees(math.acos(math.cos(a) * math.cos(b))))


# --- frame and mappings ---------------------------------------------------------------------------------
@pytest.mark.parametrize("angles", [(0, 0), (90, 0), (-30, 0), (0, 25), (29.7, 0.1), (2, 29), (-165, -80)])
def test_frame_is_orthonormal_and_right_handed(angles):
    v = view(*angles)
    frame = np.stack([v.column_direction, v.row_direction, v.detector_direction])
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.cross(v.column_direction, v.detector_direction), v.row_direction, atol=1e-12)
    assert np.linalg.norm(v.detector_center - v.source_position) == pytest.approx(SID)


@pytest.mark.parametrize("angles", [(0, 0), (-30, 0), (41, -17)])
def test_project_and_pixel_to_world_round_trip(angles):
    v = view(*angles, shape=(64, 48), pp=(30.0, 25.0))
    rng = np.random.default_rng(1)
    points = rng.uniform(-40, 40, (50, 3))
    row, col, _ = v.project(points)
    on_detector = v.pixel_to_world(row, col)
    # the detector point lies in the detector plane, on the line from the source through the point
    np.testing.assert_allclose((on_detector - v.detector_center) @ v.detector_direction, 0.0, atol=1e-9)
    to_point = points - v.source_position
    to_pixel = on_detector - v.source_position
    np.testing.assert_allclose(np.cross(to_point, to_pixel), 0.0, atol=1e-6)
    # and a detector point projects back onto its own pixel coordinates
    r2, c2, depth = v.project(on_detector)
    np.testing.assert_allclose(r2, row, atol=1e-9)
    np.testing.assert_allclose(c2, col, atol=1e-9)
    np.testing.assert_allclose(depth, SID, rtol=1e-12)


def test_rays_pass_through_their_pixels():
    v = view(-30.0, 25.0, shape=(16, 12))
    rows, cols = v.pixel_grid()
    assert rows.shape == (16, 12) and rows[3, 5] == 3 and cols[3, 5] == 5
    origin, direction = v.rays(rows, cols)
    np.testing.assert_allclose(origin, v.source_position)
    np.testing.assert_allclose(np.linalg.norm(direction, axis=-1), 1.0, atol=1e-12)
    for t in (300.0, SOD, 900.0):  # any point along a ray projects onto that ray's pixel
        r, c, _ = v.project(origin + t * direction)
        np.testing.assert_allclose(r, rows, atol=1e-9)
        np.testing.assert_allclose(c, cols, atol=1e-9)


def test_points_behind_the_source_get_nan():
    v = view(0.0)
    row, col, depth = v.project(np.array([[0.0, SOD + 10.0, 0.0]]))
    assert depth[0] < 0 and np.isnan(row[0]) and np.isnan(col[0])


# --- volume grid --------------------------------------------------------------------------------------------
def test_volume_grid_voxel_centres():
    grid = VolumeGrid((4, 3, 2), (1.0, 2.0, 0.5), (10.0, -5.0, 1.0))
    np.testing.assert_allclose(grid.origin, [10 - 1.5, -5 - 2.0, 1 - 0.25])
    np.testing.assert_allclose(grid.extent_mm, [4, 6, 1])
    lo, hi = grid.bounds()
    np.testing.assert_allclose((lo + hi) / 2, grid.center_mm)
    np.testing.assert_allclose(hi - lo, grid.extent_mm)
    centres = grid.voxel_centers()
    assert centres.shape == (24, 3)
    # C order of [i, j, k]: flat index 1 is (0, 0, 1), a step along z; 2·3 = 6 is (1, 0, 0).
    np.testing.assert_allclose(centres[1] - centres[0], [0, 0, 0.5])
    np.testing.assert_allclose(centres[6] - centres[0], [1.0, 0, 0])
    np.testing.assert_allclose(grid.world_to_index(grid.index_to_world([[3, 2, 1]])), [[3, 2, 1]])
    m = grid.ijk_to_lps_matrix()
    np.testing.assert_allclose((m @ [3, 2, 1, 1])[:3], grid.index_to_world([3, 2, 1]))


# --- GEOM.json ----------------------------------------------------------------------------------------------
def geom_dict():
    return {
        "volume": {"shape": [32, 32, 32], "spacing_mm": [1.0, 1.0, 1.0], "center_mm": [0.0, 0.0, 0.0]},
        "views": [
            {"primary_deg": 30.0, "secondary_deg": 0.0, "sid_mm": 1000.0, "sod_mm": 750.0,
             "pixel_spacing_mm": [0.5, 0.5], "detector_shape": [128, 128]},
            {"primary_deg": -30.0, "secondary_deg": 25.0, "sid_mm": 1100.0, "sod_mm": 760.0,
             "pixel_spacing_mm": [0.4, 0.5], "detector_shape": [160, 128], "principal_point_px": [80.0, 60.5]},
        ],
    }


def test_geometry_json_round_trip(tmp_path):
    geometry = Geometry.from_dict(geom_dict())
    path = tmp_path / "GEOM.json"
    geometry.save(path)
    loaded = Geometry.load(path)
    assert loaded == geometry
    assert loaded.to_dict() == geom_dict()
    assert loaded.digest() == geometry.digest()
    assert loaded.views[1].principal_point == (80.0, 60.5)
    assert json.loads(path.read_text())["views"][1]["pixel_spacing_mm"] == [0.4, 0.5]


def test_standard_geometry_paper_protocol():
    g = standard_geometry("paper")
    assert g.volume.shape == (128, 128, 128) and g.volume.spacing_mm == (0.8, 0.8, 0.8)
    first, second = g.views
    assert (first.primary_deg, first.secondary_deg, first.sid_mm, first.sod_mm) == (29.7, 0.1, 993.0, 757.06)
    assert (second.primary_deg, second.secondary_deg, second.sid_mm, second.sod_mm) == (2.0, 29.0, 1055.0, 756.99)
    assert first.detector_shape == (512, 512) and first.pixel_spacing_mm == (0.278, 0.278)
    with pytest.raises(GeometryError, match="unknown view pair"):
        standard_geometry("lao90")


# --- validation: every error names its field -------------------------------------------------------------
_DELETE = object()


def _edit(path, value):
    data = geom_dict()
    target = data
    for key in path[:-1]:
        target = target[key]
    if value is _DELETE:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return data


BAD_FIELDS = [
    (("views", 1, "primary_deg"), 180.5, ["views[1].primary_deg"]),
    (("views", 1, "primary_deg"), -200.0, ["views[1].primary_deg"]),
    (("views", 0, "secondary_deg"), 90.5, ["views[0].secondary_deg"]),
    (("views", 0, "secondary_deg"), -91.0, ["views[0].secondary_deg"]),
    (("views", 1, "sod_mm"), 1100.0, ["views[1].sod_mm"]),  # SOD = SID
    (("views", 1, "sod_mm"), 1200.0, ["views[1].sod_mm"]),  # SOD > SID
    (("views", 1, "sod_mm"), -5.0, ["views[1].sod_mm"]),
    (("views", 0, "pixel_spacing_mm"), [0.5, 0.0], ["views[0].pixel_spacing_mm"]),
    (("views", 0, "pixel_spacing_mm"), [-0.5, 0.5], ["views[0].pixel_spacing_mm"]),
    (("views", 0, "pixel_spacing_mm"), [0.5], ["views[0].pixel_spacing_mm"]),
    (("views", 0, "detector_shape"), [128, 128, 3], ["views[0].detector_shape"]),
    (("views", 0, "detector_shape"), [128, 0], ["views[0].detector_shape"]),
    (("views", 0, "detector_shape"), [128.5, 128], ["views[0].detector_shape"]),
    (("views", 1, "principal_point_px"), [1.0], ["views[1].principal_point_px"]),
    (("views", 0, "sid_mm"), "1000", ["views[0].sid_mm"]),
    (("views", 0, "sid_mm"), float("nan"), ["views[0].sid_mm"]),
    (("views", 0, "primary_deg"), True, ["views[0].primary_deg"]),
    (("views", 1, "sid_mm"), _DELETE, ["views[1]", "sid_mm"]),
    (("views", 0, "frobnicate"), 1, ["views[0]", "frobnicate"]),
    (("volume", "spacing_mm"), [1.0, 0.0, 1.0], ["volume.spacing_mm"]),
    (("volume", "spacing_mm"), [1.0, 1.0], ["volume.spacing_mm"]),
    (("volume", "shape"), [32, 32], ["volume.shape"]),
    (("volume", "shape"), [32, -1, 32], ["volume.shape"]),
    (("volume", "center_mm"), [0.0, 0.0], ["volume.center_mm"]),
    (("volume", "shape"), _DELETE, ["volume", "shape"]),
    (("volume", "origin_mm"), [0, 0, 0], ["volume", "origin_mm"]),
    (("views",), [], ["views"]),
    (("views",), _DELETE, ["views"]),
    (("volume",), _DELETE, ["volume"]),
    (("detector",), {}, ["detector"]),
]


def _case_id(case) -> str:
    path, value, _ = case
    return ".".join(str(p) for p in path) + ("-deleted" if value is _DELETE else f"={value!r}")


@pytest.mark.parametrize("path, value, names", BAD_FIELDS, ids=[_case_id(c) for c in BAD_FIELDS])
def test_validation_errors_name_the_field(path, value, names):
    with pytest.raises(GeometryError) as info:
        Geometry.from_dict(_edit(path, value))
    message = str(info.value)
    for name in names:
        assert name in message, f"{name!r} not named in: {message}"


def test_volume_that_does_not_project_onto_a_detector():
    data = geom_dict()
    data["volume"]["center_mm"] = [0.0, 0.0, 400.0]  # 400 mm above the isocenter: off both detectors
    with pytest.raises(GeometryError, match=r"views\[0\].*does not project onto the detector"):
        Geometry.from_dict(data)
    # a principal point far off the detector moves the image of the volume off it too
    data = geom_dict()
    data["views"][1]["principal_point_px"] = [80.0, 5000.0]
    with pytest.raises(GeometryError, match=r"views\[1\].*does not project onto the detector"):
        Geometry.from_dict(data)


def test_source_inside_the_volume():
    data = geom_dict()
    data["volume"]["shape"] = [60, 60, 60]
    data["volume"]["spacing_mm"] = [20.0, 20.0, 20.0]  # 1200 mm cube: its corners lie beyond SOD = 750 mm
    with pytest.raises(GeometryError) as info:
        Geometry.from_dict(data)
    assert "views[0]" in str(info.value) and "sod_mm" in str(info.value) and "inside" in str(info.value)


def test_load_reports_the_file_and_bad_json(tmp_path):
    missing = tmp_path / "nope.json"
    with pytest.raises(GeometryError, match="nope.json"):
        Geometry.load(missing)
    bad = tmp_path / "bad.json"
    bad.write_text('{"volume": ', encoding="utf-8")
    with pytest.raises(GeometryError, match="not valid JSON"):
        Geometry.load(bad)
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps(_edit(("views", 1, "secondary_deg"), 95.0)), encoding="utf-8")
    with pytest.raises(GeometryError, match=r"wrong\.json.*views\[1\]\.secondary_deg"):
        Geometry.load(wrong)


def test_direct_construction_validates():
    with pytest.raises(GeometryError, match="secondary_deg"):
        CArmView(0.0, 91.0, SID, SOD, (PS, PS), (64, 64))
    with pytest.raises(GeometryError, match="sod_mm"):
        CArmView(0.0, 0.0, SID, SID, (PS, PS), (64, 64))
    with pytest.raises(GeometryError, match="spacing_mm"):
        VolumeGrid((8, 8, 8), (1.0, 1.0, 0.0))
    with pytest.raises(GeometryError, match="at least one"):
        Geometry(VolumeGrid((8, 8, 8), (1.0, 1.0, 1.0)), ())


def test_geometry_dict_is_not_modified_by_validation():
    data = geom_dict()
    before = copy.deepcopy(data)
    Geometry.from_dict(data)
    assert data == before


# --- object motion between acquisitions -----------------------------------------------------------------
def test_object_motion_projects_the_moved_object():
    from SDFCARLib.geometry import rotation_matrix

    nominal = CArmView(-30.0, 20.0, 1000.0, 757.0, (0.3, 0.3), (400, 500), (190.0, 260.0))
    moved = nominal.with_object_motion((1.0, -2.0, 0.5), (2.0, -1.0, 3.0))
    points = np.random.default_rng(0).uniform(-40, 40, (50, 3))
    rotation = rotation_matrix((1.0, -2.0, 0.5))
    expected = nominal.project(points @ rotation.T + np.array([2.0, -1.0, 3.0]))
    for got, want in zip(moved.project(points), expected):
        np.testing.assert_allclose(got, want, atol=1e-9)
    # rays and pixel positions agree with the projection in the reference frame
    row, col, _ = moved.project(points)
    origin, direction = moved.rays(row, col)
    along = np.einsum("ij,ij->i", points - origin, direction)
    np.testing.assert_allclose(origin + along[:, None] * direction, points, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(moved.row_direction), 1.0)


def test_rotation_matrix_is_rodrigues():
    from SDFCARLib.geometry import rotation_matrix

    np.testing.assert_allclose(rotation_matrix((0.0, 0.0, 90.0)) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    r = rotation_matrix((3.0, -4.0, 12.0))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ np.array([3.0, -4.0, 12.0]), [3.0, -4.0, 12.0], atol=1e-12)  # the axis stays
    assert math.degrees(math.acos((np.trace(r) - 1) / 2)) == pytest.approx(13.0)


def test_object_motion_round_trips_and_zero_motion_keeps_the_digest():
    view = CArmView(30.0, 0.0, 1000.0, 757.0, (0.278, 0.278), (512, 512))
    grid = VolumeGrid((8, 8, 8), (1.0, 1.0, 1.0))
    plain = Geometry(grid, (view,))
    assert "object_rotation_deg" not in view.to_dict()
    moved = Geometry(grid, (view.with_object_motion((0.0, 1.0, 0.0), (0.5, 0.0, 0.0)),))
    assert Geometry.from_dict(moved.to_dict()) == moved and moved.digest() != plain.digest()
    assert Geometry.from_dict(plain.to_dict()).digest() == plain.digest()
    with pytest.raises(GeometryError, match=r"views\[0\]\.object_translation_mm must be a list of 3 numbers"):
        Geometry.from_dict({**moved.to_dict(), "views": [{**view.to_dict(), "object_translation_mm": [1.0]}]})


def test_loading_a_geometry_that_asks_for_an_automatic_volume_names_the_reader_that_takes_it(tmp_path):
    from SDFCARLib.region import read_geometry

    view = CArmView(30.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 128)).to_dict()
    for volume in ("auto", {"auto": True, "spacing_mm": 0.5}, None):
        data = {"views": [view, dict(view, primary_deg=-30.0)]}
        if volume is not None:
            data["volume"] = volume
        path = tmp_path / "geometry.json"
        path.write_text(json.dumps(data))
        with pytest.raises(GeometryError, match="asks for an automatic volume.*SDFCARLib.region.read_geometry"):
            Geometry.load(path)
        geometry, request = read_geometry(path)
        assert request is not None and len(geometry.views) == 2


def test_a_volume_with_auto_null_is_an_explicit_grid_with_an_unknown_field_for_both_readers(tmp_path):
    from SDFCARLib.region import read_geometry

    view = CArmView(30.0, 0.0, 1000.0, 750.0, (0.5, 0.5), (128, 128)).to_dict()
    volume = {"auto": None, "shape": [8, 8, 8], "spacing_mm": [1.0, 1.0, 1.0]}
    path = tmp_path / "geometry.json"
    path.write_text(json.dumps({"views": [view, dict(view, primary_deg=-30.0)], "volume": volume}))
    for reader in (Geometry.load, read_geometry):
        with pytest.raises(GeometryError, match=r"volume has unknown field\(s\): auto"):
            reader(path)


def test_description_and_provenance_survive_a_load_and_save_but_are_no_part_of_the_geometry(tmp_path):
    geometry = standard_geometry("lao30-rao30")
    data = geometry.to_dict()
    data["description"] = "patient 7, LAD"
    data["provenance"] = {"primary_deg": "PositionerPrimaryAngle (0018,1510)"}
    data["views"][1]["provenance"] = {"sid_mm": "DistanceSourceToDetector (0018,1110)"}
    (tmp_path / "in.json").write_text(json.dumps(data))
    loaded = Geometry.load(tmp_path / "in.json")
    assert loaded == geometry and loaded.digest() == geometry.digest()  # the same geometry, annotated
    assert loaded.to_dict() == geometry.to_dict()
    loaded.save(tmp_path / "out.json")
    assert json.loads((tmp_path / "out.json").read_text()) == data
    geometry.save(tmp_path / "plain.json")  # none given, none written
    assert set(json.loads((tmp_path / "plain.json").read_text())) == {"volume", "views"}


def test_a_grid_grown_to_hold_a_box_keeps_its_lattice():
    grid = VolumeGrid((4, 4, 4), (1.0, 2.0, 0.5), (0.0, 0.0, 0.0))  # origin (-1.5, -3, -0.75)
    assert grid.grown_to_hold([-1.0, -1.0, 0.0], [1.0, 1.0, 0.5]) is grid  # inside: the grid itself
    grown = grid.grown_to_hold([-1.0, -1.0, 0.0], [5.2, 1.0, 0.5])  # x to 5.2: index (5.2 + 1.5) / 1 = 6.7 → 7
    assert grown.shape == (8, 4, 4) and grown.spacing_mm == grid.spacing_mm
    np.testing.assert_allclose(grown.origin, grid.origin)  # the same voxel centres, more of them
    lower = grid.grown_to_hold([-1.0, -7.5, 0.0], [1.0, 1.0, 0.5])  # y to −7.5: index −2.25 → −3
    assert lower.shape == (4, 7, 4)
    np.testing.assert_allclose(lower.origin, grid.origin - [0.0, 6.0, 0.0])
