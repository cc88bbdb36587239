"""Camera mapping: estimators against planted cameras, the runtime mapping, files and errors.

Virtual-sensor frames are rendered through a known camera (planted intrinsics, distortion and
an anisotropic plane-to-image homography) with OpenCV's own lens functions
(``cv2.undistortPoints`` / ``cv2.projectPoints``), independent of the Newton solver and the
fitting code under test. Recovered values are compared with the planted ones:

* mm per px in x and y: relative error < 1 % (analytic from the planted homography, or finite
  differences of ``cv2.projectPoints`` for a tilted view);
* distortion: the undistortion field (raw px -> ideal px displacement) over the output grid,
  max error < 1 % of the largest planted displacement there;
* homography: sensor positions of the true ideal pixels over the output grid, max error < 1 % of
  the grid's half-width (17.5 mm).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tactile_deploy.calibration.camera.charuco import (
    CharucoBoardSpec,
    TargetNotFoundError,
    board_corners_mm,
    calibrate_charuco,
    detect_charuco,
    print_sheet,
    save_print_sheet,
)
from tactile_deploy.calibration.camera.dots import assign_grid_indices, calibrate_dots, dot_grid_positions_mm
from tactile_deploy.calibration.camera.fitting import CalibrationError
from tactile_deploy.calibration.camera.synthetic import (
    VirtualCamera,
    board_to_sensor,
    render_charuco_frame,
    render_dot_press,
)
from tactile_deploy.imaging.camera_mapping import (
    CameraMapping,
    CameraMappingError,
    OutputGrid,
    build_remap,
    camera_mapping_from_parameters,
    compact_remap,
    grid_centres_mm,
    load_mapping,
    pixels_to_sensor_mm,
    rectify,
    save_mapping,
    sensor_mm_to_pixels,
    undistort_pixels,
)

SIZE = (640, 480)
CENTRE = ((SIZE[0] - 1) / 2.0, (SIZE[1] - 1) / 2.0)
HALF_WIDTH_MM = 17.5
SPEC = CharucoBoardSpec()


def _single_view_camera() -> VirtualCamera:
    """Barrel lens (about 37 px at the grid corners); focal 520 px, not the estimator's 640."""
    k = np.array([[520.0, 0.0, CENTRE[0]], [0.0, 520.0, CENTRE[1]], [0.0, 0.0, 1.0]])
    return VirtualCamera.from_arrays(SIZE, k, [-0.30, 0.10, 0.0, 0.0, 0.0])


def _sensor_to_undistorted(sx_mm_px: float, sy_mm_px: float, theta_deg: float,
                           mirrored: bool) -> np.ndarray:
    """Planted plane -> ideal px homography: rotation, then px per mm 1/sx along u, 1/sy along v;
    the sensor origin lands on the image centre."""
    t = np.deg2rad(theta_deg)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    flip = np.diag([1.0, 1.0 if mirrored else -1.0])  # folded optics: v along -y
    lin = np.diag([1.0 / sx_mm_px, 1.0 / sy_mm_px]) @ flip @ rot
    return np.array([[lin[0, 0], lin[0, 1], CENTRE[0]], [lin[1, 0], lin[1, 1], CENTRE[1]],
                     [0.0, 0.0, 1.0]])


def _planted_mm_per_px(sensor_to_und: np.ndarray) -> tuple[float, float]:
    """Analytic for a principal point at the image centre (lens Jacobian = identity there)."""
    return 1.0 / np.hypot(*sensor_to_und[:2, 0]), 1.0 / np.hypot(*sensor_to_und[:2, 1])


def _projected_mm_per_px(camera: VirtualCamera, sensor_to_und: np.ndarray) -> tuple[float, float]:
    """Finite differences of ``cv2.projectPoints`` at the sensor point seen at the image centre."""
    und_c = camera.undistort(np.array([CENTRE]))[0]
    q = np.linalg.inv(sensor_to_und) @ np.r_[und_c, 1.0]
    x0 = q[:2] / q[2]
    e = 1e-3
    out = []
    for step in ([e, 0.0], [0.0, e]):
        duv = camera.project(sensor_to_und, [x0 + step]) - camera.project(sensor_to_und,
                                                                          [x0 - step])
        out.append(2 * e / float(np.linalg.norm(duv)))
    return out[0], out[1]


def _grid_points_mm() -> np.ndarray:
    x, y = grid_centres_mm(OutputGrid())
    return np.stack([x.ravel(), y.ravel()], axis=1)


def _errors_vs_truth(mapping: CameraMapping, camera: VirtualCamera, sensor_to_und: np.ndarray):
    """Errors of ``mapping`` against the planted camera, over the output grid's cell centres.

    field_px: max |ideal px (estimated) - ideal px (planted)|, the undistortion field compared
        directly; meaningful when the intrinsics are identified (several views).
    field_mod_h_px: the same after the best homography between the two ideal-pixel sets. With one
        view the split between lens and homography is fixed only up to such a homography (the
        focal length and the principal point are gauges), so this is the field error that one
        view can be held to. planted_mod_h_px: the planted field's own non-projective part (the
        error of assuming no lens at all), to show the measure has teeth.
    planted_px: largest planted displacement (raw -> ideal) over the grid.
    h_mm: max |H_est(ideal px planted) - x| (the homography on its own, several views).
    end_to_end_mm: max |pixels_to_sensor_mm(raw) - x| (lens and homography together).
    """
    xy = _grid_points_mm()
    uv_raw = camera.project(sensor_to_und, xy)
    assert np.all((uv_raw > -0.5) & (uv_raw < np.array(SIZE) - 0.5))  # grid fully in view
    und_true = camera.undistort(uv_raw)
    und_est = undistort_pixels(uv_raw, mapping)

    def mod_h(a, b):
        h, _ = cv2.findHomography(a, b, 0)
        q = a @ h[:, :2].T + h[:, 2]
        return float(np.max(np.linalg.norm(q[:, :2] / q[:, 2:3] - b, axis=1)))

    h = mapping.homography
    q = und_true @ h[:, :2].T + h[:, 2]
    return {
        "field_px": float(np.max(np.linalg.norm(und_est - und_true, axis=1))),
        "field_mod_h_px": mod_h(und_est, und_true),
        "planted_mod_h_px": mod_h(uv_raw, und_true),
        "planted_px": float(np.max(np.linalg.norm(und_true - uv_raw, axis=1))),
        "h_mm": float(np.max(np.linalg.norm(q[:, :2] / q[:, 2:3] - xy, axis=1))),
        "end_to_end_mm": float(np.max(np.linalg.norm(pixels_to_sensor_mm(uv_raw, mapping) - xy,
                                                     axis=1))),
    }


# ------------------------------------------------------------------------------- scenes
@pytest.fixture(scope="module")
def dots_scene():
    camera = _single_view_camera()
    s2u = _sensor_to_undistorted(0.070, 0.075, 3.0, mirrored=True)
    pressed, reference = render_dot_press(camera, s2u, 2.5, (15, 15), np.random.default_rng(1))
    return camera, s2u, pressed, reference


@pytest.fixture(scope="module")
def dots_fit(dots_scene):
    _, _, pressed, reference = dots_scene
    return calibrate_dots(pressed, reference, 2.5, grid_shape=(15, 15))


@pytest.fixture(scope="module")
def charuco_scene():
    """Board printed side outwards, folded optics (image not mirrored), -4 degree rotation, and
    a principal point 10.5 px right of and 7.5 px above the image centre (which the single-view
    fit assumes: the tangential terms and the homography must absorb the offset)."""
    k = np.array([[520.0, 0.0, CENTRE[0] + 10.5], [0.0, 520.0, CENTRE[1] - 7.5], [0.0, 0.0, 1.0]])
    camera = VirtualCamera.from_arrays(SIZE, k, [-0.30, 0.10, 0.0, 0.0, 0.0])
    s2u = _sensor_to_undistorted(0.072, 0.078, -4.0, mirrored=False)
    frame = render_charuco_frame(SPEC, camera, s2u @ board_to_sensor(SPEC, False),
                                 np.random.default_rng(2))
    return camera, s2u, frame


# ---------------------------------------------------------------------- pressed dot grid
def test_dots_recover_planted_scale_distortion_homography(dots_scene, dots_fit):
    camera, s2u, _, _ = dots_scene
    fit, det = dots_fit
    m = fit.mapping
    sx, sy = _planted_mm_per_px(s2u)
    assert abs(m.mm_per_px_x / sx - 1) < 0.01
    assert abs(m.mm_per_px_y / sy - 1) < 0.01
    assert _projected_mm_per_px(camera, s2u) == pytest.approx((sx, sy), rel=1e-5)
    err = _errors_vs_truth(m, camera, s2u)
    assert err["planted_px"] > 30.0 and err["planted_mod_h_px"] > 10.0  # a strong lens
    assert err["field_mod_h_px"] < 0.01 * err["planted_px"]
    assert err["end_to_end_mm"] < 0.01 * HALF_WIDTH_MM
    assert m.image_mirrored is True
    assert m.fit.method == "dots-single-view"
    assert m.fit.n_points == 225 and m.fit.n_rejected == 0
    assert m.fit.rms_px < 0.3
    assert abs(m.fit.rms_mm / (m.fit.rms_px * 0.5 * (sx + sy)) - 1) < 0.2
    assert len(det.centres_px) == 225


def test_dots_without_lens_terms_fail_the_same_checks(dots_scene):
    """The checks above have teeth: a fit with no distortion misses them by far."""
    camera, s2u, pressed, reference = dots_scene
    fit, _ = calibrate_dots(pressed, reference, 2.5, grid_shape=(15, 15), free_lens=())
    err = _errors_vs_truth(fit.mapping, camera, s2u)
    assert err["field_mod_h_px"] > 0.1 * err["planted_px"]
    assert err["end_to_end_mm"] > 0.03 * HALF_WIDTH_MM


def test_dots_missing_edge_column_is_refused_with_grid_shape(dots_scene):
    _, _, pressed, reference = dots_scene
    # A 15-column grid declared as 14 columns: the extent check must fire.
    with pytest.raises(CalibrationError, match="15 x 15 lattice positions but the grid has 14"):
        calibrate_dots(pressed, reference, 2.5, grid_shape=(14, 15))


def test_dots_no_press_gives_clear_error(dots_scene):
    _, _, _, reference = dots_scene
    noisy = np.clip(reference.astype(np.int16) + np.random.default_rng(3).integers(
        -2, 3, reference.shape), 0, 255).astype(np.uint8)
    with pytest.raises(TargetNotFoundError, match="reference frame shows the unpressed gel"):
        calibrate_dots(noisy, reference, 2.5)


def test_grid_assignment_robust_to_outliers_gaps_and_rotation():
    """Lattice through a rotated (80 deg), distorted camera; 4 outliers and 3 gaps."""
    rng = np.random.default_rng(4)
    camera = _single_view_camera()
    s2u = _sensor_to_undistorted(0.07, 0.07, 80.0, mirrored=True)
    ij = np.stack(np.meshgrid(np.arange(-6, 7), np.arange(-6, 7)), -1).reshape(-1, 2)
    uv = camera.project(s2u, ij * 2.5) + rng.normal(0, 0.1, (len(ij), 2))
    keep = np.ones(len(ij), bool)
    keep[[20, 84, 130]] = False  # interior gaps
    outliers = np.array([[300.0, 251.0], [100.0, 100.0], [333.0, 150.0], [500.0, 420.0]])
    pts = np.concatenate([uv[keep], outliers])
    # Rotated by 80 degrees: sensor +x points nearly down the image, sensor +y nearly left.
    idx, ok = assign_grid_indices(pts, u_axis="-y", v_axis="+x")
    n = keep.sum()
    assert ok[:n].all()
    assert not ok[n:].any()
    offset = idx[:n] - ij[keep]
    assert (offset == offset[0]).all()
    xy = dot_grid_positions_mm(idx[:n], 2.5, grid_shape=(13, 13))
    np.testing.assert_allclose(xy, ij[keep] * 2.5)


def test_grid_assignment_rejects_unknown_axis():
    with pytest.raises(ValueError, match="u_axis='x'"):
        assign_grid_indices(np.zeros((10, 2)), u_axis="x")
    with pytest.raises(ValueError, match="different axes"):
        assign_grid_indices(np.zeros((10, 2)), u_axis="+x", v_axis="-x")


# ------------------------------------------------------------------------------ ChArUco
def test_charuco_single_view_recovers_planted_camera(charuco_scene):
    camera, s2u, frame = charuco_scene
    fit = calibrate_charuco([frame], SPEC, board_faces_camera=False)
    m = fit.mapping
    sx, sy = _projected_mm_per_px(camera, s2u)
    assert abs(m.mm_per_px_x / sx - 1) < 0.01
    assert abs(m.mm_per_px_y / sy - 1) < 0.01
    err = _errors_vs_truth(m, camera, s2u)
    assert err["planted_px"] > 30.0 and err["planted_mod_h_px"] > 10.0
    assert err["field_mod_h_px"] < 0.01 * err["planted_px"]
    assert err["end_to_end_mm"] < 0.01 * HALF_WIDTH_MM
    assert m.image_mirrored is False
    assert m.fit.method == "charuco-single-view" and m.fit.focal_assumed
    assert abs(m.intrinsics.cx_px - (CENTRE[0] + 10.5)) < 5.0
    assert abs(m.intrinsics.cy_px - (CENTRE[1] - 7.5)) < 5.0
    assert m.fit.n_points >= 140 and m.fit.rms_px < 0.3


def test_charuco_detection_ids_match_board_geometry(charuco_scene):
    camera, s2u, frame = charuco_scene
    uv, ids = detect_charuco(frame, SPEC)
    b2s = board_to_sensor(SPEC, False)
    bxy = board_corners_mm(SPEC, ids)
    expected = camera.project(s2u @ b2s, bxy)
    assert np.max(np.linalg.norm(uv - expected, axis=1)) < 0.5


def test_charuco_multi_view_recovers_intrinsics():
    """Off-centre principal point, fx != fy, tangential terms: identifiable from tilted views."""
    k = np.array([[600.0, 0.0, 327.0], [0.0, 570.0, 236.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.28, 0.09, 0.0015, -0.001, 0.0])
    camera = VirtualCamera.from_arrays(SIZE, k, dist)
    rng = np.random.default_rng(5)

    def board_to_und(rvec, z_mm):
        r, _ = cv2.Rodrigues(np.asarray(rvec, float))
        t = -r @ np.array([SPEC.board_width_mm / 2, SPEC.board_height_mm / 2, 0.0]) + [0, 0, z_mm]
        return k @ np.c_[r[:, 0], r[:, 1], t]

    plane = board_to_und([0.03, -0.02, 0.01], 42.0)  # the sensor plane, nearly square-on
    s2u = plane @ np.linalg.inv(board_to_sensor(SPEC, True))
    tilted = [([0.5, 0.0, 0.0], 60.0), ([0.0, 0.55, 0.2], 60.0), ([0.1, -0.55, -0.3], 60.0),
              ([-0.45, 0.3, 0.5], 62.0)]
    frames = [render_charuco_frame(SPEC, camera, plane, rng)]
    frames += [render_charuco_frame(SPEC, camera, board_to_und(rv, z), rng) for rv, z in tilted]
    fit = calibrate_charuco(frames, SPEC, plane_index=0)
    m = fit.mapping
    assert m.fit.method == "charuco-multi-view" and not m.fit.focal_assumed
    assert m.fit.n_frames == 5
    assert abs(m.intrinsics.fx_px / 600.0 - 1) < 0.01
    assert abs(m.intrinsics.fy_px / 570.0 - 1) < 0.01
    assert abs(m.intrinsics.cx_px - 327.0) < 3.0 and abs(m.intrinsics.cy_px - 236.0) < 3.0
    sx, sy = _projected_mm_per_px(camera, s2u)
    assert abs(m.mm_per_px_x / sx - 1) < 0.01
    assert abs(m.mm_per_px_y / sy - 1) < 0.01
    err = _errors_vs_truth(m, camera, s2u)
    assert err["planted_px"] > 25.0
    assert err["field_px"] < 0.01 * err["planted_px"]  # direct: the intrinsics are identified
    assert err["h_mm"] < 0.01 * HALF_WIDTH_MM
    assert err["end_to_end_mm"] < 0.01 * HALF_WIDTH_MM


def test_charuco_blank_frame_gives_clear_error():
    blank = np.full((SIZE[1], SIZE[0]), 128, np.uint8)
    with pytest.raises(TargetNotFoundError, match=r"found 0 ChArUco corners.*in focus.*--board"):
        calibrate_charuco([blank], SPEC, names=["blank.png"])
    with pytest.raises(TargetNotFoundError, match="blank.png"):
        calibrate_charuco([blank], SPEC, names=["blank.png"])


def test_print_sheet_has_true_size_and_detectable_board(tmp_path):
    from PIL import Image

    sheet, size_mm = print_sheet(SPEC, dpi=600)
    assert abs(size_mm[0] - 42.0) < 0.05 and abs(size_mm[1] - 42.0) < 0.05
    small = cv2.resize(sheet, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    _, ids = detect_charuco(small, SPEC)
    assert len(ids) == (SPEC.squares_x - 1) * (SPEC.squares_y - 1)
    out = tmp_path / "board.png"
    save_print_sheet(SPEC, out, dpi=600)
    with Image.open(out) as im:
        assert tuple(round(v) for v in im.info["dpi"]) == (600, 600)
    assert CharucoBoardSpec.model_validate_json((tmp_path / "board.json").read_text()) == SPEC


def test_board_spec_validation():
    with pytest.raises(ValueError, match="needs 200 markers but DICT_4X4_100 has 100"):
        CharucoBoardSpec(squares_x=20, squares_y=20)
    with pytest.raises(ValueError, match="marker_mm=3.0 must be smaller"):
        CharucoBoardSpec(marker_mm=3.0)


# ---------------------------------------------------------------------- runtime mapping
def _planted_mapping(mirrored: bool = True, dist=(-0.3, 0.1, 0.001, -0.0005, 0.0)) -> CameraMapping:
    k = np.array([[520.0, 0.0, 322.0], [0.0, 520.0, 241.0], [0.0, 0.0, 1.0]])
    s2u = _sensor_to_undistorted(0.07, 0.075, 2.0, mirrored)
    return camera_mapping_from_parameters(SIZE, k, dist, np.linalg.inv(s2u))


def test_round_trip_pixels_mm_pixels():
    m = _planted_mapping()
    uv = np.random.default_rng(6).uniform([-0.5, -0.5], [SIZE[0] - 0.5, SIZE[1] - 0.5], (2000, 2))
    assert np.max(np.abs(sensor_mm_to_pixels(pixels_to_sensor_mm(uv, m), m) - uv)) < 1e-6
    xy = _grid_points_mm()
    assert np.max(np.abs(pixels_to_sensor_mm(sensor_mm_to_pixels(xy, m), m) - xy)) < 1e-7


def test_newton_undistortion_agrees_with_opencv():
    m = _planted_mapping()
    uv = np.random.default_rng(7).uniform([0, 0], [639, 479], (500, 2))
    cam = VirtualCamera.from_arrays(SIZE, m.camera_matrix, m.dist_coeffs)
    assert np.max(np.abs(undistort_pixels(uv, m) - cam.undistort(uv))) < 1e-6


def test_output_grid_convention_and_rectify():
    """No lens, axis-aligned: map_x/map_y follow x = x_min + (j+0.5) p, y = y_max - (i+0.5) p."""
    k = np.array([[500.0, 0.0, CENTRE[0]], [0.0, 500.0, CENTRE[1]], [0.0, 0.0, 1.0]])
    # u = cx + x / 0.07, v = cy + y / 0.075
    s2u = _sensor_to_undistorted(0.07, 0.075, 0.0, mirrored=True)
    m = camera_mapping_from_parameters(SIZE, k, np.zeros(5), np.linalg.inv(s2u))
    map_x, map_y = build_remap(m)
    assert map_x.dtype == np.float32 and map_x.shape == (128, 128)
    p = 35.0 / 128
    j = np.arange(128)
    np.testing.assert_allclose(map_x[5], CENTRE[0] + (-17.5 + (j + 0.5) * p) / 0.07, atol=1e-3)
    np.testing.assert_allclose(map_y[:, 9], CENTRE[1] + (17.5 - (j + 0.5) * p) / 0.075, atol=1e-3)
    # A frame whose value is its own u (a ramp) rectifies to map_x exactly (bilinear is exact).
    ramp = np.tile(np.arange(SIZE[0], dtype=np.float32), (SIZE[1], 1))
    np.testing.assert_allclose(rectify(ramp, m, (map_x, map_y)), map_x, atol=1e-3)
    color = np.dstack([ramp, ramp * 0 + 7, ramp * 2]).astype(np.float32)
    out = rectify(color, m)
    assert out.shape == (128, 128, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out[..., 2], 2 * map_x, atol=2e-3)
    u8 = rectify(np.zeros((SIZE[1], SIZE[0]), np.uint8), m)
    assert u8.dtype == np.uint8 and u8.shape == (128, 128)
    assert rectify(np.zeros((SIZE[1], SIZE[0], 1), np.uint16), m).shape == (128, 128, 1)
    assert m.image_mirrored is True
    assert abs(m.mm_per_px_x - 0.07) < 1e-9 and abs(m.mm_per_px_y - 0.075) < 1e-9


def test_compact_remap_matches_float_tables():
    m = _planted_mapping()
    remap = build_remap(m)
    ramp_u = np.tile(np.arange(SIZE[0], dtype=np.float32), (SIZE[1], 1))
    ramp_v = np.tile(np.arange(SIZE[1], dtype=np.float32)[:, None], (1, SIZE[0]))
    frame = np.dstack([ramp_u, ramp_v, ramp_u + ramp_v])
    a = rectify(frame, m, remap)
    b = rectify(frame, m, compact_remap(remap))
    assert b.shape == a.shape == (128, 128, 3)
    np.testing.assert_allclose(a[..., 0], remap[0], atol=1e-3)
    np.testing.assert_allclose(a[..., 1], remap[1], atol=1e-3)
    assert np.max(np.abs(b - a)) <= 1.0 / 32 + 1e-3  # fixed point: 1/32 px positions


def test_benchmark_runs_at_small_settings():
    from tactile_deploy.calibration.camera.benchmark import run

    result = run(n_calls=3)
    assert set(result) == {"rectify_gray_us", "rectify_bgr_us", "rectify_gray_compact_us",
                           "rectify_bgr_compact_us", "build_remap_us"}
    assert all(np.isfinite(v) and v > 0 for v in result.values())


def test_rectify_refuses_frame_of_other_size():
    m = _planted_mapping()
    with pytest.raises(CameraMappingError, match=r"frame is 800x600 px.*calibrated for 640x480"):
        rectify(np.zeros((600, 800), np.uint8), m)
    with pytest.raises(ValueError, match="frame dtype bool is not supported"):
        rectify(np.zeros((480, 640), bool), m)
    with pytest.raises(ValueError, match="remap tables have shape"):
        rectify(np.zeros((480, 640), np.uint8), m, (np.zeros((64, 64), np.float32),) * 2)


def test_mirror_flag_follows_homography():
    assert _planted_mapping(mirrored=True).image_mirrored is True
    assert _planted_mapping(mirrored=False).image_mirrored is False


def test_non_invertible_lens_is_refused():
    with pytest.raises(ValueError, match="not invertible over the image"):
        _planted_mapping(dist=(-1.5, 0.0, 0.0, 0.0, 0.0))


# ------------------------------------------------------------------------------- files
def test_save_load_round_trip(tmp_path, dots_fit):
    m = dots_fit[0].mapping
    path = tmp_path / "camera_mapping.json"
    save_mapping(m, path)
    assert load_mapping(path) == m
    assert not list(tmp_path.glob(".*partial*"))  # atomic write left no temporary file


def _write_doc(tmp_path, edit) -> object:
    doc = json.loads(_planted_mapping().model_dump_json())
    edit(doc)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize(
    "edit, pattern",
    [
        (lambda d: d["intrinsics"].update(fx_px=-3.0),
         r"field 'intrinsics.fx_px'.*greater than 0.*got -3.0"),
        (lambda d: d["intrinsics"].update(fy_px="abc"), r"field 'intrinsics.fy_px'.*got \"abc\""),
        (lambda d: d.pop("image_width_px"), r"field 'image_width_px': Field required"),
        (lambda d: d.update(colour="red"), r"field 'colour': Extra inputs are not permitted"),
        (lambda d: d.update(mm_per_px_x=0.08), r"mm_per_px_x=0.08 does not match the value 0.07"),
        (lambda d: d.update(format_version=2), r"field 'format_version'.*reads version 1.*has 2"),
        (lambda d: d.pop("format_version"), r"field 'format_version' is missing"),
        (lambda d: d["grid"].update(nx=1), r"field 'grid.nx'.*greater than or equal to 2"),
    ],
)
def test_load_reports_bad_field(tmp_path, edit, pattern):
    path = _write_doc(tmp_path, edit)
    with pytest.raises(CameraMappingError, match=pattern) as info:
        load_mapping(path)
    assert str(path) in str(info.value)


def test_load_reports_nan_and_broken_json(tmp_path):
    path = tmp_path / "m.json"
    path.write_text(_planted_mapping().model_dump_json().replace('"k2":0.1', '"k2":NaN'))
    with pytest.raises(CameraMappingError, match=r"field 'distortion.k2'.*finite"):
        load_mapping(path)
    path.write_text('{"format_version": 1, "image_width_px": 640,,}')
    with pytest.raises(CameraMappingError, match=r"m.json: not valid JSON \(line 1, column 45"):
        load_mapping(path)
    with pytest.raises(FileNotFoundError, match="calibrate camera"):
        load_mapping(tmp_path / "missing.json")


# --------------------------------------------------------------------------------- CLI
def test_cli_camera_dots_and_make_board(tmp_path, dots_scene):
    from typer.testing import CliRunner

    from tactile_deploy.calibration.camera.cli import camera_app

    _, s2u, pressed, reference = dots_scene
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "press.png"), pressed)
    cv2.imwrite(str(frames / "reference.png"), reference)
    out = tmp_path / "camera_mapping.json"
    runner = CliRunner()
    res = runner.invoke(camera_app, ["camera", "--frames", str(frames), "--target", "dots",
                                     "--pitch-mm", "2.5", "--dot-grid", "15x15",
                                     "--out", str(out)])
    assert res.exit_code == 0, res.output
    m = load_mapping(out)
    sx, sy = _planted_mm_per_px(s2u)
    assert abs(m.mm_per_px_x / sx - 1) < 0.01 and abs(m.mm_per_px_y / sy - 1) < 0.01

    res = runner.invoke(camera_app, ["camera", "--frames", str(frames), "--target", "charuco",
                                     "--out", str(tmp_path / "x.json")])
    assert res.exit_code == 1 and "ChArUco corners" in res.output

    res = runner.invoke(camera_app, ["make-board", "--out", str(tmp_path / "board.png"),
                                     "--dpi", "300"])
    assert res.exit_code == 0, res.output
    printed_mm = round(42.0 / 25.4 * 300) / 300 * 25.4  # whole pixels at 300 dpi
    assert f"board {printed_mm:.2f} x {printed_mm:.2f} mm" in res.output
    assert (tmp_path / "board.png").is_file() and (tmp_path / "board.json").is_file()


def test_cli_camera_charuco_single_frame_with_figure(tmp_path, charuco_scene):
    from typer.testing import CliRunner

    from tactile_deploy.calibration.camera.cli import camera_app

    camera, s2u, frame = charuco_scene
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "00_plane.png"), frame)
    out, fig = tmp_path / "m.json", tmp_path / "fit.png"
    res = CliRunner().invoke(camera_app, [
        "camera", "--frames", str(frames), "--target", "charuco", "--board-faces", "outside",
        "--out", str(out), "--figure", str(fig)])
    assert res.exit_code == 0, res.output
    m = load_mapping(out)
    sx, sy = _projected_mm_per_px(camera, s2u)
    assert abs(m.mm_per_px_x / sx - 1) < 0.01 and abs(m.mm_per_px_y / sy - 1) < 0.01
    assert m.image_mirrored is False
    assert fig.stat().st_size > 10_000 and cv2.imread(str(fig)) is not None
    res = CliRunner().invoke(camera_app, [
        "camera", "--frames", str(frames), "--target", "charuco", "--board",
        str(tmp_path / "missing.json"), "--out", str(out)])
    assert res.exit_code == 1 and "missing.json not found" in res.output
