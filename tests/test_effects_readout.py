"""Effects seen in depth maps: the views of the optics effects and the read-out effects, checked
against analytic results and against the frames' own camera mappings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.imaging.camera_mapping import pixels_to_sensor_mm, sensor_mm_to_pixels
from tactile_deploy.optics import Light, OpticsModel, simple_camera
from tactile_deploy.sensors.config import EffectSpec, VirtualSensorConfig
from tactile_deploy.sensors.depth_view import DepthReadout
from tactile_deploy.sensors.effects import get_effect

CAM = DepthCamera()
XY = CAM.pixel_centres_mm()
R2 = XY[..., 0] ** 2 + XY[..., 1] ** 2


def _optics(k1: float) -> OpticsModel:
    return OpticsModel(camera=simple_camera(160, 120, 0.1, k1=k1),
                       lights=(Light(name="r", kind="point", position_mm=(0.0, 25.0, -6.0),
                                     colour_grey=(230, 25, 20)),))


def _camera_after(effect_name: str, params: dict, k1: float = 0.0):
    cfg = VirtualSensorConfig(name="t", family="gelslim", optics=_optics(k1),
                              effects=(EffectSpec(name=effect_name, params=params),))
    from tactile_deploy.sensors.virtual import VirtualSensor

    return cfg.optics.camera, VirtualSensor(cfg).optics.camera


def _grid_points(half: float = 6.0) -> np.ndarray:
    g = np.stack(np.meshgrid(np.linspace(-half, half, 13), np.linspace(-4.5, 4.5, 10)), -1)
    return g.reshape(-1, 2)


def test_lens_view_equals_the_frames_camera_and_moves_points_with_the_cube_of_the_radius():
    """Depth-map view of an added k1 about the principal point = the surface point the frames'
    distorted camera images where the calibrated one sees p (exact without own distortion)."""
    nominal, real = _camera_after("lens_distortion", {"k1": -0.2})
    p = _grid_points()
    q = get_effect("lens_distortion", {"k1": -0.2}).view_points(p, nominal)
    via_camera = pixels_to_sensor_mm(sensor_mm_to_pixels(p, nominal), real)
    np.testing.assert_allclose(q, via_camera, atol=1e-9)
    # to first order in k the shift grows with the cube of the radius
    small = get_effect("lens_distortion", {"k1": -0.01}).view_points(p, nominal)
    r = np.hypot(*p.T)
    shift = np.linalg.norm(small - p, axis=1)
    sel = r > 1.0
    assert np.polyfit(np.log(r[sel]), np.log(shift[sel]), 1)[0] == pytest.approx(3.0, abs=0.02)


def test_lens_view_distorts_about_its_centre_and_is_null_at_zero_k():
    nominal, _ = _camera_after("lens_distortion", {"k1": 0.0})
    k = nominal.intrinsics
    fx = get_effect("lens_distortion", {"k1": 0.15, "centre_dx_px": 20.0, "centre_dy_px": -10.0})
    centre_px = np.array([[k.cx_px + 20.0, k.cy_px - 10.0]])
    centre_mm = pixels_to_sensor_mm(centre_px, nominal)  # no own distortion: undistorted px
    np.testing.assert_allclose(fx.view_points(centre_mm, nominal), centre_mm, atol=1e-12)
    p = _grid_points()
    d = p - centre_mm
    q = fx.view_points(p, nominal)
    # radial about the centre: displacement parallel to p - c
    cross = d[:, 0] * (q - p)[:, 1] - d[:, 1] * (q - p)[:, 0]
    assert np.max(np.abs(cross)) < 1e-9
    null = get_effect("lens_distortion", {"centre_dx_px": 20.0, "depth_gain_exponent": 0.0})
    assert null.is_null
    np.testing.assert_array_equal(null.view_points(p, nominal), p)


@pytest.mark.parametrize("params", [{"scale": 0.05}, {"anisotropy": 0.04, "axis_deg": 0.0},
                                    {"anisotropy": -0.03, "axis_deg": 30.0, "scale": 0.02}])
def test_pixel_scale_view_equals_the_frames_camera_and_scales_mm_per_px(params):
    nominal, real = _camera_after("pixel_scale", params, k1=-0.1)
    p = _grid_points()
    q = get_effect("pixel_scale", params).view_points(p, nominal)
    via_camera = pixels_to_sensor_mm(sensor_mm_to_pixels(p, nominal), real)
    np.testing.assert_allclose(q, via_camera, atol=1e-8)
    if "scale" in params and "anisotropy" not in params:
        assert real.mm_per_px_x == pytest.approx(1.05 * nominal.mm_per_px_x, rel=1e-6)
        assert real.mm_per_px_y == pytest.approx(1.05 * nominal.mm_per_px_y, rel=1e-6)
        np.testing.assert_allclose(q, 1.05 * p, atol=1e-6)  # principal point at the centre


def test_pixel_scale_chart_covers_either_sign_along_any_axis():
    from tactile_deploy.calibration.discrepancy.candidates import candidate_library

    cand = candidate_library(["pixel_scale"])[0]
    cur = get_effect("pixel_scale").params.model_dump()
    for params in ({"scale": 0.03, "anisotropy": -0.04, "axis_deg": 10.0},
                   {"scale": -0.05, "anisotropy": 0.02, "axis_deg": 135.0}):
        full = {**cur, **params}
        back = cand.params_of(cand.coords_of(full), cur)
        a = get_effect("pixel_scale", full).stretch_px(0.0, 0.0)
        b = get_effect("pixel_scale", back).stretch_px(0.0, 0.0)
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_depth_gain_exponent_scales_the_map_with_the_views_stretch():
    """A 5 % isotropic scale: an integrating pipeline (exponent 1) reports depths / 1.05, a
    resampled map (exponent 0) keeps them; both show the contact 1 / 1.05 as large."""
    nominal, _ = _camera_after("pixel_scale", {"scale": 0.05})
    bump = 0.5 * np.exp(-R2 / (2 * 1.5**2))
    for gamma, gain in ((1.0, 1.0 / 1.05), (0.0, 1.0)):
        fx = get_effect("pixel_scale", {"scale": 0.05, "depth_gain_exponent": gamma})
        out = DepthReadout([fx], nominal)(bump)
        expected = gain * 0.5 * np.exp(-1.05**2 * R2 / (2 * 1.5**2))
        # bilinear resampling of the bump: below 0.5 % of its height
        assert np.max(np.abs(out - expected)) < 0.0025


def test_gain_gradient_is_the_map_times_a_plane():
    fx = get_effect("gain_gradient", {"gain": 0.05, "gain_per_mm_x": 0.01,
                                      "gain_per_mm_y": -0.02})
    d = np.exp(-R2 / 20.0)
    out = fx.readout_map(d, XY)
    np.testing.assert_allclose(out, d * (1.05 + 0.01 * XY[..., 0] - 0.02 * XY[..., 1]),
                               rtol=1e-12)


def test_blur_of_a_gaussian_bump_is_the_wider_gaussian():
    """Gaussian of sigma s0 blurred by s: a Gaussian of sqrt(s0^2 + s^2), peak s0^2 / (s0^2 +
    s^2) as high (analytic)."""
    s0, s = 1.0, 0.4
    d = 0.3 * np.exp(-R2 / (2 * s0**2))
    out = get_effect("blur", {"sigma_mm": s}).readout_map(d, XY)
    expected = 0.3 * s0**2 / (s0**2 + s**2) * np.exp(-R2 / (2 * (s0**2 + s**2)))
    assert np.max(np.abs(out - expected)) < 0.01 * 0.3


def test_shading_saturation_clips_a_cone_to_the_limit_slope():
    """A cone of slope 0.8 read with slopes clipped at 0.5 is a cone of slope 0.5: its apex
    0.5 / 0.8 as deep (analytic; the Poisson integration resolves it to a few percent)."""
    r = np.sqrt(R2)
    cone = np.maximum(0.8 * (2.0 - r), 0.0)  # 1.6 mm deep, 2 mm radius, slope 0.8
    out = get_effect("shading_saturation", {"inverse_max_slope": 2.0}).readout_map(cone, XY)
    assert out.max() == pytest.approx(1.6 * 0.5 / 0.8, rel=0.05)
    # slopes below the limit are untouched
    gentle = np.maximum(0.3 * (2.0 - r), 0.0)
    np.testing.assert_array_equal(
        get_effect("shading_saturation", {"inverse_max_slope": 2.0}).readout_map(gentle, XY),
        gentle)


def test_dome_of_either_sign_about_its_apex():
    fx = get_effect("dome", {"height_mm": -0.2, "centre_x_mm": 2.0, "centre_y_mm": -1.0})
    pts = np.array([[2.0, -1.0], [2.0 + 17.5, -1.0], [2.0, 7.75]])
    np.testing.assert_allclose(fx.rest_height_mm(pts), [0.0, 0.2, 0.05],
                               rtol=1e-12)
    assert get_effect("dome", {"centre_x_mm": 3.0}).is_null
