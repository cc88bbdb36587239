"""RGB optics model and renderer: analytic shading, a second implementation, noise statistics,
validation, parameter recovery on a planted sensor, and the real GelSight ball presses."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pydantic import ValidationError

from tactile_deploy.optics import (
    GelTexture,
    Light,
    OpticsModel,
    OpticsModelError,
    OpticsRenderer,
    SensorNoise,
    Vignetting,
    load_optics,
    radiance_reference,
    save_optics,
    simple_camera,
)
from tactile_deploy.optics.render import grid_centres


def small_model(**kw) -> OpticsModel:
    """A 160 x 120 px camera, 0.1 mm/px, mild barrel distortion and perspective."""
    cam = simple_camera(160, 120, 0.1, k1=-0.1, tilt=(2e-5, -1e-5), rotation_deg=3.0)
    lights = (
        Light(name="r", kind="point", position_mm=(25.0, 3.0, -6.0), colour_grey=(220, 20, 10),
              falloff_per_mm=0.01, specular_grey=(15, 15, 15), shininess=30),
        Light(name="g", kind="directional", azimuth_deg=200.0, elevation_deg=25.0,
              colour_grey=(15, 180, 20), falloff_per_mm=0.03),
        Light(name="b", kind="directional", azimuth_deg=300.0, elevation_deg=35.0,
              colour_grey=(10, 20, 190)),
    )
    base = {"camera": cam, "lights": lights, "ambient_grey": (30.0, 25.0, 35.0),
                "vignetting": Vignetting(k2=-0.2, k4=0.05), "texture": GelTexture(rms=0.03, seed=4)}
    base.update(kw)
    return OpticsModel(**base)


def bump(grid, centre=(1.0, -0.5), depth_mm=0.6, sigma_mm=1.2):
    x, y = grid_centres(grid)
    r2 = (x - centre[0]) ** 2 + (y - centre[1]) ** 2
    return (-depth_mm * np.exp(-r2 / (2 * sigma_mm**2))).astype(np.float32)


def test_renderer_matches_direct_per_light_implementation():
    """Fast renderer (float32, precomputed maps, cv2) vs the direct float64 equations (scipy)."""
    model = small_model()
    r = OpticsRenderer(model)
    h = bump(r.grid)
    fast = r.radiance(h)
    ref = radiance_reference(model, r.grid, h)
    err = np.abs(fast - ref)
    assert err.max() < 0.05 + 2e-3 * np.abs(ref).max(), err.max()
    assert np.median(err) < 0.02
    # The surface matters: a flat surface renders differently in the bump.
    assert np.abs(fast - r.radiance(r.flat_height())).max() > 20.0


def test_features_render_where_the_camera_mapping_projects_them():
    """A symmetric dent under an overhead light images centred on the pixel that
    ``sensor_mm_to_pixels`` gives for its centre (lens distortion and perspective included)."""
    from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels

    cam = simple_camera(320, 240, 0.06, k1=-0.2, tilt=(3e-5, 2e-5), rotation_deg=7.0)
    model = OpticsModel(camera=cam, lights=(Light(elevation_deg=90.0, colour_grey=(200, 0, 0)),))
    r = OpticsRenderer(model)
    flat = r.radiance(r.flat_height())[..., 0]
    v, u = np.mgrid[0:240, 0:320]
    for c in ((0.0, 0.0), (5.0, 3.0), (-4.0, -3.5)):
        img = r.radiance(bump(r.grid, centre=c, depth_mm=0.3, sigma_mm=0.5))[..., 0]
        mag = np.abs(img - flat)
        w = np.where(mag > 0.2 * mag.max(), mag, 0.0)
        got = np.array([(w * u).sum() / w.sum(), (w * v).sum() / w.sum()])
        want = sensor_mm_to_pixels(np.array([c]), cam)[0]
        # (the lens magnifies one side of the blob more: centroid bias of a fraction of a px)
        assert np.linalg.norm(got - want) < 0.3, (c, got, want)


def test_flat_surface_is_ambient_plus_lights_at_their_elevation():
    """Flat pad, directional light, no vignetting/texture: gain x (ambient + colour sin(el))."""
    cam = simple_camera(64, 48, 0.2)
    model = OpticsModel(camera=cam, ambient_grey=(10.0, 20.0, 30.0), lights=(
        Light(azimuth_deg=40.0, elevation_deg=30.0, colour_grey=(100.0, 50.0, 20.0)),))
    rad = OpticsRenderer(model).radiance(np.zeros((OpticsRenderer(model).grid.ny,
                                                   OpticsRenderer(model).grid.nx), np.float32))
    expected = np.array([10.0, 20.0, 30.0]) + 0.5 * np.array([100.0, 50.0, 20.0])
    np.testing.assert_allclose(rad.reshape(-1, 3), np.broadcast_to(expected, (64 * 48, 3)),
                               rtol=1e-6)
    # A point light straight above the origin pixel: n.l = 1 there, (r0 / r)^2 = 1.
    pt = OpticsModel(camera=simple_camera(65, 49, 0.2), lights=(
        Light(kind="point", position_mm=(0.0, 0.0, -10.0), colour_grey=(80.0, 0.0, 0.0)),))
    rp = OpticsRenderer(pt)
    img = rp.radiance(rp.flat_height())
    assert img[24, 32, 0] == pytest.approx(80.0, rel=1e-6)
    # 3 mm off axis: (10 / sqrt(109))^2 * (10 / sqrt(109)) = (100 / 109)^1.5
    u = 32 + 15  # 15 px * 0.2 mm = 3 mm along +x
    assert img[24, u, 0] == pytest.approx(80.0 * (100 / 109) ** 1.5, rel=1e-4)


def test_sphere_cap_shading_matches_analytic_normals():
    """Shading of a spherical dent from finite-difference normals vs exact sphere normals."""
    cam = simple_camera(120, 120, 0.05)
    light = Light(azimuth_deg=60.0, elevation_deg=40.0, colour_grey=(200.0, 200.0, 200.0))
    model = OpticsModel(camera=cam, lights=(light,))
    r = OpticsRenderer(model)
    x, y = grid_centres(r.grid)
    big = 4.0
    rr2 = np.minimum(x**2 + y**2, (0.9 * big) ** 2)
    h = (-(0.5 - (big - np.sqrt(big**2 - rr2)))).astype(np.float32)
    img = r.radiance(h)[..., 0]
    xy = r.pixel_xy_mm
    rho2 = np.minimum(xy[..., 0] ** 2 + xy[..., 1] ** 2, (0.9 * big) ** 2)
    inside = rho2 < (0.8 * big) ** 2
    root = np.sqrt(big**2 - rho2)
    fx, fy = xy[..., 0] / root, xy[..., 1] / root  # dz/dx of z = -(d - (R - sqrt(R^2 - r^2)))
    n = np.stack([fx, fy, -np.ones_like(fx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    exact = 200.0 * np.maximum(n @ np.array(light.direction()), 0.0)
    err = np.abs(img - exact)[inside]
    assert err.max() < 0.3, err.max()  # central differences: O(pitch^2 / R^2)


def test_region_rendering_equals_full_frame():
    """Shading only the changed region gives the same blurred radiance as the whole frame."""
    import cv2

    model = small_model(blur_sigma_px=0.8)
    r = OpticsRenderer(model)
    h = bump(r.grid, centre=(3.0, 2.0), sigma_mm=0.6)
    h[np.abs(h) < 1e-6] = 0.0
    roi = r.changed_roi(h)
    assert roi is not None and (roi[1] - roi[0]) * (roi[3] - roi[2]) < 0.5 * 160 * 120
    full = cv2.GaussianBlur(r.radiance(h), (0, 0), 0.8)
    np.testing.assert_allclose(r.blurred_radiance(h), full, atol=1e-3)
    assert r.changed_roi(r.flat_height()) is None


def test_noise_statistics_quantisation_and_saturation():
    model = small_model(texture=GelTexture(), noise=SensorNoise(
        read_noise_grey=2.0, conversion_gain_grey_per_e=0.1))
    r = OpticsRenderer(model, noise_seed=1)
    clean = r.blurred_radiance(r.flat_height())
    frames = [r.reference_frame(np.random.default_rng(i)).astype(np.float64) for i in range(6)]
    noise = np.stack(frames) - clean
    ok = (clean > 5) & (clean < 240)
    expected_var = 4.0 + 0.1 * np.broadcast_to(clean, noise.shape) + 1.0 / 12.0
    z = noise / np.sqrt(expected_var)
    sel = np.broadcast_to(ok, z.shape)
    assert abs(z[sel].mean()) < 0.02
    assert z[sel].std() == pytest.approx(1.0, abs=0.03)
    # Independent frames, not shifted copies of one noise field.
    a, b = noise[0][ok], noise[1][ok]
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.03
    np.testing.assert_array_equal(r.reference_frame(np.random.default_rng(3)),
                                  r.reference_frame(np.random.default_rng(3)))
    # Noise-free frames are the rounded radiance; over-exposure saturates at 255.
    np.testing.assert_array_equal(r.reference_frame(), np.clip(np.rint(clean), 0, 255))
    hot = OpticsRenderer(small_model(exposure_gain=3.0))
    f = hot.reference_frame()
    assert f.max() == 255 and (f == 255).mean() > 0.05
    capped = OpticsRenderer(small_model(exposure_gain=3.0, saturation_grey=200.0))
    assert capped.reference_frame().max() == 200


def test_model_validation_and_files(tmp_path):
    with pytest.raises(ValidationError, match="below the sensing surface"):
        Light(kind="point", position_mm=(0.0, 10.0, 1.0))
    with pytest.raises(ValidationError, match="colour_grey"):
        Light(colour_grey=(-1.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match="darkens the corners"):
        Vignetting(k2=-1.0, k4=0.0)
    model = small_model()
    path = tmp_path / "optics.json"
    save_optics(model, path)
    assert load_optics(path) == model
    doc = json.loads(path.read_text())
    doc["lights"][1]["elevation_deg"] = 120.0
    path.write_text(json.dumps(doc))
    with pytest.raises(OpticsModelError) as err:
        load_optics(path)
    assert str(path) in str(err.value) and "lights.1.elevation_deg" in str(err.value)
    assert "120" in str(err.value)
    doc["format_version"] = 7
    path.write_text(json.dumps(doc))
    with pytest.raises(OpticsModelError, match="format_version"):
        load_optics(path)


def _synthetic_presses(model: OpticsModel, n: int, ball_mm: float, sinking: float, seed: int):
    """Frames of a planted sensor: reference + n ball presses rendered by the fast renderer."""
    from tactile_deploy.calibration.optics_fit import PressFrames, sphere_press_surface
    from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels

    rng = np.random.default_rng(seed)
    r = OpticsRenderer(model, noise_seed=seed)
    x, y = grid_centres(r.grid)
    xy = np.stack([x.ravel(), y.ravel()], 1)
    frames, circles = [], []
    for _ in range(n):
        c = rng.uniform([-4.0, -3.0], [4.0, 3.0])
        a = rng.uniform(0.8, 1.5)
        z, _, _ = sphere_press_surface(xy, c, a, ball_mm, sinking)
        frames.append(r.render(z.reshape(x.shape).astype(np.float32), rng))
        uv = sensor_mm_to_pixels(c[None], model.camera)[0]
        circles.append([uv[0], uv[1], a / model.camera.mm_per_px_x])
    ref = r.reference_frame(rng)
    return PressFrames(ref, np.stack(frames), [f"{i}" for i in range(n)], np.array(circles))


def test_fit_recovers_planted_optics_parameters():
    """Done-criterion: fit a synthetic sensor with known parameters and recover them."""
    from tactile_deploy.calibration.optics_fit import (
        SurfaceParameters,
        fit_optics,
        parameter_paths,
        parameter_vector,
        press_samples,
        with_parameters,
    )

    cam = simple_camera(160, 120, 0.08)
    truth = OpticsModel(camera=cam, lights=(
        Light(name="r", azimuth_deg=85.0, elevation_deg=22.0, colour_grey=(140, 10, 15),
              falloff_per_mm=0.06),
        Light(name="g", azimuth_deg=265.0, elevation_deg=18.0, colour_grey=(30, 120, 10),
              falloff_per_mm=0.09),
        Light(name="b", azimuth_deg=170.0, elevation_deg=15.0, colour_grey=(15, 20, 150),
              falloff_per_mm=0.04)),
        ambient_grey=(60.0, 70.0, 80.0), vignetting=Vignetting(k2=-0.15),
        noise=SensorNoise(read_noise_grey=1.0, conversion_gain_grey_per_e=0.02))
    press = _synthetic_presses(truth, 6, 2.5, 0.7, seed=5)
    free = ["ambient_grey", "vignetting.k2", "lights.*.azimuth_deg", "lights.*.elevation_deg",
            "lights.*.colour_grey", "lights.*.falloff_per_mm"]
    paths = parameter_paths(truth, free)
    x_true = parameter_vector(truth, paths)
    rng = np.random.default_rng(0)
    start = with_parameters(truth, paths, x_true * rng.uniform(0.8, 1.2, len(x_true))
                            + rng.normal(0, 4.0, len(x_true)) * np.array(
                                ["azimuth" in p[2] if p[0] == "lights" else False for p in paths]))
    start = start.model_copy(update={"noise": SensorNoise()})
    s = press_samples(press, cam, range(6), sinking_scale=0.3, stride=4, near_factor=2.5,
                      near_stride=2, ball_radius_mm=2.5)
    surf = SurfaceParameters(["sinking_scale"], np.array([0.3]), np.array([0.0]),
                             np.array([2.0]), lambda v: s.press_surface(float(v[0]), 2.5))
    fit = fit_optics(start, s, free, surface=surf, frame_offsets_on=False)
    got = parameter_vector(fit.model, paths)
    for p, t, g in zip(paths, x_true, got):
        field = p[-2] if isinstance(p[-1], int) and p[0] != "ambient_grey" else p[-1]
        if p[0] == "lights" and p[2] == "azimuth_deg":
            d = (g - t + 180.0) % 360.0 - 180.0
            assert abs(d) < 1.0, (p, t, g)
        elif p[0] == "lights" and p[2] == "elevation_deg":
            assert abs(g - t) < 1.0, (p, t, g)
        elif p[0] == "lights" and p[2] == "falloff_per_mm":
            assert abs(g - t) < 0.005, (p, t, g)
        elif p[0] == "vignetting":
            assert abs(g - t) < 0.01, (p, t, g)
        else:  # colours and ambient, grey levels (frames shaded from finite differences,
            # fitted with exact slopes: a few percent of trade-off with elevation and sinking)
            assert abs(g - t) < max(3.0, 0.05 * t), (p, field, t, g)
    assert fit.extra["sinking_scale"] == pytest.approx(0.7, abs=0.1)
    assert max(fit.rmse_grey) < 2.0  # noise (~1.6 grey) + quantisation


def test_real_gelsight_presses_held_out_error(shared_data):
    """Fit on a few real presses; the held-out presses are predicted far better than by the
    reference frame alone (the figures of docs/optics.md come from the full fit)."""
    from tactile_deploy.calibration.optics_fit import (
        FOTS_BALL_RADIUS_MM,
        SurfaceParameters,
        fit_optics,
        fots_camera,
        fots_initial_model,
        load_fots,
        press_samples,
    )
    from tactile_deploy.calibration.optics_fit.fots import FOTS_FREE, _held_out_errors

    press = load_fots(shared_data / "real" / "fots_gelsight_ballpress")
    assert press.frames.shape == (42, 320, 240, 3)
    cam = fots_camera()
    train = [0, 7, 14, 21, 28, 35]
    s = press_samples(press, cam, train, sinking_scale=1.0, stride=10, near_factor=2.5,
                      near_stride=5)
    surf = SurfaceParameters(["sinking_scale"], np.array([1.5]), np.array([0.0]),
                             np.array([4.0]), lambda v: s.press_surface(float(v[0]),
                                                                        FOTS_BALL_RADIUS_MM))
    fit = fit_optics(fots_initial_model(cam), s, FOTS_FREE, surface=surf, max_evaluations=150)
    test = [3, 10, 17, 24, 31, 38]
    rows = _held_out_errors(fit.model, press, cam, test, fit.extra["sinking_scale"])
    model = np.array(rows["model"]["contact_rmse_grey"])
    base = np.array(rows["real reference only (baseline)"]["contact_rmse_grey"])
    assert np.all(model < 12.0), model
    assert np.all(model < 0.5 * base), (model, base)
    # Lights where the colours say: red from +y, green from -y, blue from -x.
    az = {lt.name: lt.azimuth_deg for lt in fit.model.lights}
    assert abs((az["red"] - 90 + 180) % 360 - 180) < 25
    assert abs((az["green"] - 270 + 180) % 360 - 180) < 25
    assert abs((az["blue"] - 180 + 180) % 360 - 180) < 25
