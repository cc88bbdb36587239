"""Effects of virtual sensors: every registered effect reproduces the nominal sensor exactly at
its null value, and shows its physical signature at a planted value."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tactile_deploy.indenters import AnalyticSphere, ContactPose
from tactile_deploy.optics import (
    Light,
    OpticsModel,
    SensorNoise,
    Vignetting,
    simple_camera,
)
from tactile_deploy.sensors.config import EffectSpec, VirtualSensorConfig
from tactile_deploy.sensors.effects import (
    UnknownEffectError,
    effect_class,
    get_effect,
    list_effects,
)
from tactile_deploy.sensors.virtual import VirtualSensor

NOMINAL_OPTICS = OpticsModel(
    camera=simple_camera(160, 120, 0.1, k1=-0.1),
    lights=(
        Light(name="r", kind="point", position_mm=(0.0, 25.0, -6.0), colour_grey=(230, 25, 20)),
        Light(name="g", kind="point", position_mm=(-21.6, -12.5, -6.0), colour_grey=(20, 220, 30)),
        Light(name="b", kind="directional", azimuth_deg=330.0, elevation_deg=25.0,
              colour_grey=(25, 30, 200), specular_grey=(10, 10, 10)),
    ),
    ambient_grey=(40.0, 40.0, 45.0), vignetting=Vignetting(k2=-0.2), blur_sigma_px=0.5,
    noise=SensorNoise(read_noise_grey=1.5, conversion_gain_grey_per_e=0.03))


def make_sensor(sim, *effects: tuple[str, dict]) -> VirtualSensor:
    cfg = VirtualSensorConfig(name="test", family="gelslim", optics=NOMINAL_OPTICS, seed=7,
                              effects=tuple(EffectSpec(name=n, params=p) for n, p in effects))
    return VirtualSensor(cfg, simulator=sim)


@pytest.fixture(scope="module")
def nominal(pad_sim):
    return make_sensor(pad_sim)


BALL = AnalyticSphere(4.0)


def test_registry_lists_effects_and_rejects_unknown_names():
    mech, opt = list_effects("mechanical"), list_effects("optical")
    assert len(mech) >= 3 and len(opt) >= 3
    assert {"dome", "tilt", "zero_offset", "hyperelastic"} <= set(mech)
    assert {"lens_distortion", "pixel_scale", "illumination_gradient", "saturation",
            "led_drift"} <= set(opt)
    with pytest.raises(UnknownEffectError, match="known effects: .*dome"):
        get_effect("wobble")
    for name in list_effects():
        cls = effect_class(name)
        assert cls.name == name and cls.__doc__ and "Realistic range" in cls.__doc__
        assert "Signature" in cls.__doc__ and "Residual" in cls.__doc__
        assert set(cls.realistic_range) <= set(cls.Params.model_fields)
        assert get_effect(name).is_null


NON_NULL = {
    "dome": {"height_mm": 0.3}, "tilt": {"angle_deg": 1.0}, "zero_offset": {"offset_mm": 0.03},
    "hyperelastic": {"strength": 1.0}, "lens_distortion": {"k1": -0.2},
    "pixel_scale": {"anisotropy": 0.05}, "illumination_gradient": {"gain_per_mm_x": 0.01},
    "saturation": {"exposure_factor": 1.4}, "led_drift": {"sigma_rel": 0.05},
    "depth_scale": {"scale": 0.03}, "position_offset": {"dx_mm": 0.2},
    "rotation_offset": {"dtheta_deg": 3.0}, "poisson_drift": {"delta_nu": -0.02},
    "compression_set": {"depth_mm": 0.05}, "gain_gradient": {"gain_per_mm_x": 0.01},
    "blur": {"sigma_mm": 0.2}, "shading_saturation": {"inverse_max_slope": 2.0},
    "friction": {"mu": 0.5},
}


@pytest.mark.parametrize("name", sorted(NON_NULL))
def test_null_value_reproduces_nominal_sensor_exactly(name, pad_sim, nominal):
    assert set(NON_NULL) == set(list_effects())
    null = make_sensor(pad_sim, (name, {}))
    assert all(e.is_null for e in null.effects)
    assert not get_effect(name, NON_NULL[name]).is_null
    pose = ContactPose(x_mm=1.0, y_mm=-0.5, depth_mm=0.4)
    a = nominal.press(BALL, pose, np.random.default_rng(11))
    b = null.press(BALL, pose, np.random.default_rng(11))
    np.testing.assert_array_equal(a.frame, b.frame)
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    np.testing.assert_array_equal(a.vertices_mm, b.vertices_mm)
    assert a.force_n == b.force_n
    np.testing.assert_array_equal(nominal.reference_frame(np.random.default_rng(2)),
                                  null.reference_frame(np.random.default_rng(2)))


def _max_depth(sensor, x_mm, depth_mm):
    return float(sensor.press(BALL, ContactPose(x_mm=x_mm, depth_mm=depth_mm)).depth_mm.max())


def test_dome_residual_grows_toward_the_edge(pad_sim, nominal):
    dome = make_sensor(pad_sim, ("dome", {"height_mm": 0.3}))
    radii = [0.0, 5.0, 10.0]
    resid = [_max_depth(nominal, r, 0.6) - _max_depth(dome, r, 0.6) for r in radii]
    sag = [0.3 * r * r / 17.5**2 for r in radii]
    assert resid[0] < 0.005
    assert resid[0] < resid[1] < resid[2]
    assert resid[2] == pytest.approx(sag[2], rel=0.25)
    # The optics see the curved rest surface: the no-contact frame changes, most at the edge.
    ref_n = nominal.renderer.rest_radiance
    ref_d = dome.renderer.rest_radiance
    xy = nominal.renderer.pixel_xy_mm
    r = np.hypot(xy[..., 0], xy[..., 1])
    change = np.abs(ref_d - ref_n).sum(axis=-1)
    assert change[r < 2].mean() < 0.3 * change[r > 6].mean()


def _contact_uz(sensor, indenter, pose):
    out = sensor.press(indenter, pose)
    sim = sensor.simulator
    top = out.vertices_mm[: sim.mesh.n_plane].astype(np.float64)
    uz = top[:, 2] - sim.mesh.vertices[: sim.mesh.n_plane, 2]
    return uz, out


def test_tilt_residual_is_a_plane_of_slope_tan_angle(pad_sim, nominal):
    from tactile_deploy.indenters import get_indenter

    punch = get_indenter("flat_punch")
    angle, az = 1.5, 30.0
    tilted = make_sensor(pad_sim, ("tilt", {"angle_deg": angle, "azimuth_deg": az}))
    pose = ContactPose(x_mm=1.0, y_mm=0.5, depth_mm=0.4)
    # In contact in both (nodes under the punch, away from its edge).
    xy = pad_sim.mesh.vertices[: pad_sim.mesh.n_plane, :2]
    under = np.hypot(xy[:, 0] - 1.0, xy[:, 1] - 0.5) < 2.0
    u0, _ = _contact_uz(nominal, punch, pose)
    u1, _ = _contact_uz(tilted, punch, pose)
    s = (xy[under, 0] - 1.0) * math.cos(math.radians(az)) + (xy[under, 1] - 0.5) * math.sin(
        math.radians(az))
    # depth = -u_z; the tilted surface recedes along the azimuth: depth - tan(angle) s
    np.testing.assert_allclose(u1[under] - u0[under], math.tan(math.radians(angle)) * s,
                               atol=1e-7)


def test_zero_offset_shifts_the_contact_depth_exactly(pad_sim, nominal):
    shifted = make_sensor(pad_sim, ("zero_offset", {"offset_mm": 0.04}))
    pose = ContactPose(x_mm=-2.0, y_mm=1.0, depth_mm=0.5)
    u0, a = _contact_uz(nominal, BALL, pose)
    u1, b = _contact_uz(shifted, BALL, pose)
    both = (u0 < -1e-9) & np.isclose(u0, -pad_sim.intrusion(BALL, pose), atol=1e-6)
    assert both.sum() >= 5
    np.testing.assert_allclose(u1[both] - u0[both], -0.04, atol=1e-7)  # float32 vertices
    assert b.pose_reached.depth_mm == pytest.approx(0.54) and b.pose.depth_mm == 0.5
    assert b.force_n > a.force_n
    # A commanded depth the offset lifts off the gel gives the no-contact frame.
    lifted = make_sensor(pad_sim, ("zero_offset", {"offset_mm": -0.2}))
    out = lifted.press(BALL, ContactPose(depth_mm=0.1))
    assert not out.in_contact
    np.testing.assert_array_equal(out.frame, lifted.reference_frame())


def test_lens_distortion_moves_points_with_the_cube_of_the_radius(pad_sim, nominal):
    from tactile_deploy.imaging.camera_mapping import (
        sensor_mm_to_pixels,
        undistort_pixels,
    )

    lens = make_sensor(pad_sim, ("lens_distortion", {"k1": -0.2}))
    cam0, cam1 = nominal.optics.camera, lens.optics.camera
    assert cam1.distortion.k1 == pytest.approx(cam0.distortion.k1 - 0.2)
    g = np.stack(np.meshgrid(np.linspace(-6, 6, 25), np.linspace(-4.5, 4.5, 19)), -1)
    xy = g.reshape(-1, 2)
    uv0 = sensor_mm_to_pixels(xy, cam0)
    uv1 = sensor_mm_to_pixels(xy, cam1)
    und = undistort_pixels(uv0, cam0)
    k = cam0.intrinsics
    r = np.hypot(und[:, 0] - k.cx_px, und[:, 1] - k.cy_px)
    shift = np.linalg.norm(uv1 - uv0, axis=1)
    sel = r > 10
    slope = np.polyfit(np.log(r[sel]), np.log(shift[sel]), 1)[0]
    assert slope == pytest.approx(3.0, abs=0.05)
    frame = lens.press(BALL, ContactPose(x_mm=3.0, y_mm=2.0, depth_mm=0.5)).frame
    assert np.abs(frame.astype(int) - nominal.press(
        BALL, ContactPose(x_mm=3.0, y_mm=2.0, depth_mm=0.5)).frame).mean() > 0.5


def _blob_axes(sensor, pose):
    diff = np.abs(sensor.press(BALL, pose).frame.astype(float)
                  - sensor.reference_frame().astype(float)).sum(-1)
    w = np.where(diff > 0.2 * diff.max(), diff, 0.0)
    v, u = np.mgrid[0:w.shape[0], 0:w.shape[1]]
    mu, mv = (w * u).sum() / w.sum(), (w * v).sum() / w.sum()
    return math.sqrt((w * (u - mu) ** 2).sum() / w.sum()), math.sqrt(
        (w * (v - mv) ** 2).sum() / w.sum())


def test_pixel_scale_images_a_round_contact_as_an_ellipse(pad_sim, nominal):
    a = 0.1
    stretched = make_sensor(pad_sim, ("pixel_scale", {"anisotropy": a}))
    c0, c1 = nominal.optics.camera, stretched.optics.camera
    assert c1.mm_per_px_y / c1.mm_per_px_x == pytest.approx(
        (1 + a) * c0.mm_per_px_y / c0.mm_per_px_x, rel=1e-3)
    pose = ContactPose(depth_mm=0.6)
    su0, sv0 = _blob_axes(nominal, pose)
    su1, sv1 = _blob_axes(stretched, pose)
    assert (sv1 / su1) / (sv0 / su0) == pytest.approx(1.0 / (1.0 + a), rel=0.03)


def test_illumination_gradient_is_a_planar_gain(pad_sim, nominal):
    g = (0.015, -0.01)
    grad = make_sensor(pad_sim, ("illumination_gradient", {"gain_per_mm_x": g[0],
                                                           "gain_per_mm_y": g[1]}))
    xy = nominal.renderer.pixel_xy_mm
    plane = 1.0 + g[0] * xy[..., 0] + g[1] * xy[..., 1]
    clean = nominal.renderer.blurred_radiance(nominal.renderer.rest_height_mm)
    expected = np.clip(np.rint(clean * plane[..., None]), 0, 255)
    got = grad.reference_frame().astype(float)
    assert np.abs(got - expected).max() <= 1.0
    assert np.abs(got - nominal.reference_frame()).max() > 5


def test_saturation_scales_then_clips(pad_sim, nominal):
    hot = make_sensor(pad_sim, ("saturation", {"exposure_factor": 1.4}))
    pose = ContactPose(x_mm=1.0, depth_mm=0.6)
    clean = nominal.renderer.blurred_radiance(
        nominal.renderer.rest_height_mm - nominal.press(BALL, pose).surface_depth_mm)
    got = hot.press(BALL, pose).frame.astype(float)
    expected = np.clip(np.rint(1.4 * clean), 0, 255)
    assert np.abs(got - expected).max() <= 1.0
    assert (got == 255).mean() > (nominal.press(BALL, pose).frame == 255).mean() + 0.01


def test_led_drift_scatters_frame_brightness(pad_sim, nominal):
    sigma = 0.05
    drift = make_sensor(pad_sim, ("led_drift", {"sigma_rel": sigma}))
    base = nominal.renderer.blurred_radiance(nominal.renderer.rest_height_mm).mean(axis=(0, 1))
    ratios = np.array([drift.reference_frame(np.random.default_rng(i)).mean(axis=(0, 1)) / base
                       for i in range(40)])
    assert ratios.mean() == pytest.approx(1.0, abs=0.03)
    assert ratios.std() == pytest.approx(sigma, rel=0.3)


# --------------------------------------------------------------------------- hyperelastic
@pytest.fixture(scope="module")
def coarse_sim():
    """A coarse pad (2 mm spacing, 2 layers: test settings) with its operators, no disk cache."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.pad.geometry import PadGeometry
    from tactile_deploy.pad.mesh import build_pad_mesh

    mesh = build_pad_mesh(PadGeometry(name="coarse", edge_mm=2.0, n_layers=2))
    sim = ContactSimulator(mesh, Material(nu=0.48), use_cache=False)
    sim.prepare()
    return sim


def test_neo_hookean_forces_gradient_small_strain_limit_and_patch(coarse_sim):
    from tactile_deploy.fem.elasticity import assemble_stiffness_numpy
    from tactile_deploy.fem.hyperelastic import NeoHookeanGel

    mesh = coarse_sim.mesh
    E, nu = 0.3, 0.48
    pad = NeoHookeanGel(mesh.vertices, mesh.tets, E, nu)   # the one neo-Hookean model
    rng = np.random.default_rng(0)
    # Gradient of the energy (central differences).
    u = 0.05 * rng.standard_normal((mesh.n_nodes, 3))
    du = 1e-6 * rng.standard_normal(u.shape)
    fd = pad.energy(u + du) - pad.energy(u - du)
    assert fd == pytest.approx(2.0 * np.sum(pad.forces(u) * du), rel=1e-6)
    # Small strains: the locking-free linear stiffness; the rest is second order.
    K = assemble_stiffness_numpy(mesh.vertices, mesh.tets, E, nu, "nodal_pressure")
    u1 = 1e-4 * rng.standard_normal(u.shape)
    r1 = pad.forces(u1).ravel() - K @ u1.ravel()
    r2 = pad.forces(2 * u1).ravel() - K @ (2 * u1).ravel()
    assert np.linalg.norm(r1) < 1e-3 * np.linalg.norm(K @ u1.ravel())
    assert np.linalg.norm(r2) / np.linalg.norm(r1) == pytest.approx(4.0, rel=0.01)
    # Homogeneous stretch: interior nodes in equilibrium, top-face force = P_zz * area.
    F = np.diag([1.05, 0.97, 0.9])
    X = mesh.vertices
    f = pad.forces(X @ (F - np.eye(3)).T)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), np.concatenate(
        [mesh.sensing_nodes, mesh.backplate_nodes, mesh.side_nodes]))
    assert np.abs(f[interior]).max() < 1e-12
    J = np.linalg.det(F)
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    kappa = lam + 2 * mu / 3
    Fit = np.linalg.inv(F).T
    P = mu * J ** (-2 / 3) * (F - np.trace(F.T @ F) / 3 * Fit) + kappa * (J - 1) * J * Fit
    area = mesh.sensing_nodal_areas_mm2().sum()
    assert f[mesh.sensing_nodes, 2].sum() == pytest.approx(P[2, 2] * area, rel=1e-9)


def test_neo_hookean_warp_kernels_match_numpy(coarse_sim):
    pytest.importorskip("warp", reason="warp-lang is an optional dependency of the kernels")
    from tactile_deploy.fem.hyperelastic import NeoHookeanGel
    from tactile_deploy.fem.hyperelastic_warp import NeoHookeanForces

    mesh = coarse_sim.mesh
    forces = NeoHookeanForces(NeoHookeanGel(mesh.vertices, mesh.tets, 1.0, 0.48))
    u = 0.1 * np.random.default_rng(1).standard_normal((mesh.n_nodes, 3))
    a = forces(u, "numpy")
    b = forces(u, "warp")
    assert np.abs(a - b).max() < 1e-12 * np.abs(a).max()


def test_hyperelastic_solution_is_in_equilibrium_and_grows_faster_than_linearly(coarse_sim):
    from tactile_deploy.sensors.effects.hyperelastic import (
        Hyperelastic,
        solve_neo_hookean,
    )

    sim = coarse_sim
    mesh = sim.mesh
    resid_u, resid_f = [], []
    for depth in (0.3, 0.6):
        delta = sim.intrusion(BALL, ContactPose(x_mm=0.5, depth_mm=depth))
        lin = sim.solve_intrusion(delta)
        res, _ = solve_neo_hookean(sim, delta, 1.0, backend="numpy")
        # Equilibrium of the neo-Hookean pad: internal forces = contact forces (E = 1 scale).
        from tactile_deploy.sensors.effects.hyperelastic import _pad_model

        f_int = sim.dofs.T.T @ _pad_model(sim).gel.forces(res.displacements_mm).ravel()
        f_c = np.zeros((mesh.n_nodes, 3))
        f_c[: mesh.n_plane] = -res.contact_forces_n / sim.material.E_mpa
        f_ext = sim.dofs.T.T @ f_c.ravel()
        assert np.abs(f_int + f_ext).max() < 1e-4 * np.abs(f_ext).max()
        # Non-penetration holds.
        uz = res.displacements_mm[: mesh.n_plane, 2]
        assert np.all(-delta - uz >= -1e-6)
        top = slice(0, mesh.n_plane)
        resid_u.append(np.abs(res.displacements_mm[top, 2] - lin.displacements_mm[top, 2]).max())
        resid_f.append(abs(res.force_n - lin.force_n))
        if depth == 0.3:
            via_effect = Hyperelastic(strength=1.0).correct_contact(sim, delta, lin)
            np.testing.assert_allclose(via_effect.displacements_mm, res.displacements_mm,
                                       atol=1e-5)
    # Doubling the depth more than doubles the residual (second-order terms: about x 4).
    assert resid_u[1] / resid_u[0] > 3.0, resid_u
    assert resid_f[1] / resid_f[0] > 3.0, resid_f
    assert resid_f[1] > 0.02 * sim.solve(BALL, ContactPose(x_mm=0.5, depth_mm=0.6)).force_n


# ------------------------------------------------------------------ contact-stage effects
def test_depth_scale_residual_grows_in_proportion_to_the_depth(pad_sim, nominal):
    scaled = make_sensor(pad_sim, ("depth_scale", {"scale": 0.04}))
    for depth in (0.4, 0.8):
        pose = ContactPose(x_mm=1.0, y_mm=-1.5, depth_mm=depth)
        u0, _ = _contact_uz(nominal, BALL, pose)
        u1, out = _contact_uz(scaled, BALL, pose)
        both = (u0 < -1e-9) & np.isclose(u0, -pad_sim.intrusion(BALL, pose), atol=1e-6)
        assert both.sum() >= 5
        # contact nodes follow the ball: deeper by exactly scale * depth
        np.testing.assert_allclose(u1[both] - u0[both], -0.04 * depth, atol=1e-7)
        assert out.pose_reached.depth_mm == pytest.approx(depth * 1.04)


def test_position_offset_moves_every_contact_by_the_same_vector(pad_sim, nominal):
    from tactile_deploy.indenters import get_indenter

    off = make_sensor(pad_sim, ("position_offset", {"dx_mm": 0.05, "dy_mm": -0.03}))
    punch = get_indenter("flat_punch")
    for ind, pose in ((BALL, ContactPose(x_mm=2.0, y_mm=1.0, depth_mm=0.5)),
                      (punch, ContactPose(x_mm=-4.0, y_mm=3.0, depth_mm=0.4))):
        moved = pose.model_copy(update={"x_mm": pose.x_mm + 0.05, "y_mm": pose.y_mm - 0.03})
        d_off, f_off = off.depth_map(ind, pose)
        d_ref, f_ref = nominal.depth_map(ind, moved)
        np.testing.assert_array_equal(d_off, d_ref)
        assert f_off == f_ref
    # First order: the residual is -(dx, dy) . grad(depth) (a dipole across the contact).
    pose = ContactPose(x_mm=2.0, y_mm=1.0, depth_mm=0.5)
    d0 = nominal.depth_map(BALL, pose)[0].astype(float)
    d1 = off.depth_map(BALL, pose)[0].astype(float)
    gy, gx = np.gradient(d0, 35.0 / 128)  # rows run along -y
    predicted = -(0.05 * gx + (-0.03) * (-gy))
    ring = np.abs(predicted) > 0.2 * np.abs(predicted).max()
    assert np.corrcoef(predicted[ring], (d1 - d0)[ring])[0, 1] > 0.9  # 1 mm mesh vs pixels


def test_rotation_offset_changes_only_indenters_that_are_not_round(pad_sim, nominal):
    from tactile_deploy.indenters import get_indenter

    rot = make_sensor(pad_sim, ("rotation_offset", {"dtheta_deg": 4.0}))
    pose = ContactPose(x_mm=1.0, y_mm=2.0, theta_deg=10.0, depth_mm=0.5)
    np.testing.assert_array_equal(rot.depth_map(BALL, pose)[0], nominal.depth_map(BALL, pose)[0])
    cyl = get_indenter("cylinder_side")
    turned = pose.model_copy(update={"theta_deg": 14.0})
    d_rot = rot.depth_map(cyl, pose)[0]
    np.testing.assert_array_equal(d_rot, nominal.depth_map(cyl, turned)[0])
    assert np.abs(d_rot - nominal.depth_map(cyl, pose)[0]).max() > 0.05


def test_poisson_drift_solves_the_pad_at_the_drifted_ratio(coarse_sim):
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.sensors.effects.poisson_drift import PoissonDrift

    sim = coarse_sim
    mesh = sim.mesh
    pose = ContactPose(x_mm=0.5, depth_mm=0.5)
    delta = sim.intrusion(BALL, pose)
    lin = sim.solve_intrusion(delta)
    drifted = PoissonDrift(delta_nu=-0.03).correct_contact(sim, delta, lin)
    ref = ContactSimulator(mesh, sim.material.model_copy(update={"nu": 0.45}), use_cache=False)
    ref_contact = ref.solve(BALL, pose)
    np.testing.assert_allclose(drifted.displacements_mm, ref_contact.displacements_mm, atol=1e-9)
    assert drifted.force_n == pytest.approx(ref_contact.force_n, rel=1e-6)
    # A softer bulk: the surface just outside the contact sinks further, the force drops.
    xy = mesh.vertices[: mesh.n_plane, :2]
    r = np.hypot(xy[:, 0] - 0.5, xy[:, 1])
    ring = (r > 2.5) & (r < 4.5)
    duz = drifted.displacements_mm[: mesh.n_plane, 2] - lin.displacements_mm[: mesh.n_plane, 2]
    assert duz[ring].mean() < -1e-3
    assert drifted.force_n < 0.95 * lin.force_n
    with pytest.raises(ValueError, match="outside"):
        PoissonDrift(delta_nu=0.03).correct_contact(sim, delta, lin)


def test_compression_set_makes_contacts_over_the_dent_shallower(pad_sim, nominal):
    dent = make_sensor(pad_sim, ("compression_set", {"depth_mm": 0.06, "x_mm": 3.0,
                                                     "y_mm": -2.0, "width_mm": 2.0}))
    over = ContactPose(x_mm=3.0, y_mm=-2.0, depth_mm=0.5)
    u0, _ = _contact_uz(nominal, BALL, over)
    u1, _ = _contact_uz(dent, BALL, over)
    xy = pad_sim.mesh.vertices[: pad_sim.mesh.n_plane, :2]
    both = (u1 < -1e-9) & np.isclose(u1, -(pad_sim.intrusion(BALL, over) + dent.rest_height_mm(
        xy)), atol=1e-6)
    assert both.sum() >= 5
    sag = 0.06 * np.exp(-((xy[both, 0] - 3.0) ** 2 + (xy[both, 1] + 2.0) ** 2) / 8.0)
    np.testing.assert_allclose(u1[both] - u0[both], sag, atol=1e-6)
    far = ContactPose(x_mm=-6.0, y_mm=5.0, depth_mm=0.5)
    assert np.abs(dent.depth_map(BALL, far)[0] - nominal.depth_map(BALL, far)[0]).max() < 2e-3


def test_depth_map_is_the_deformed_surface_of_press(pad_sim):
    """The depth map of a sensor with mechanical effects is its deformed sensing surface,
    interpolated here by matplotlib on the mesh's own surface triangles (not our rasteriser),
    at the depth grid's pixel centres; the force is the press's."""
    from matplotlib.tri import LinearTriInterpolator, Triangulation

    from tactile_deploy.camera.depth import DepthCamera

    tilt = make_sensor(pad_sim, ("tilt", {"angle_deg": 1.0, "azimuth_deg": 40.0}),
                       ("zero_offset", {"offset_mm": 0.02}))
    pose = ContactPose(x_mm=-1.0, y_mm=2.0, depth_mm=0.6)
    depth, force = tilt.depth_map(BALL, pose)
    out = tilt.press(BALL, pose)
    assert force == out.force_n > 0
    mesh = pad_sim.mesh
    v = out.vertices_mm.astype(np.float64)
    tri = Triangulation(v[:, 0], v[:, 1], mesh.sensing_faces)
    pushed_in = LinearTriInterpolator(tri, -(v[:, 2] - mesh.vertices[:, 2]))
    centres = DepthCamera().pixel_centres_mm()
    reference = np.ma.filled(pushed_in(centres[..., 0], centres[..., 1]), np.nan)
    inside = np.isfinite(reference)
    assert inside.sum() > 0.7 * inside.size
    assert depth[inside].max() == pytest.approx(0.62, abs=0.05)  # ball 0.6 mm + 0.02 mm offset
    np.testing.assert_allclose(depth[inside], reference[inside], atol=2e-5)
