"""The discrepancy workflow on effects made outside the product (small form of ``tactile-deploy
bench discrepancy --independent``).

Measured data: the clean depth maps of a small pad's virtual sensor (r 10 mm, 1,735 nodes; the
``simulate`` output of that pad: no effects), 16 commanded contacts (spheres, a punch, a lying
cylinder), each effect applied in its textbook form by ``tests/independent_effects.py`` (numpy,
scipy, OpenCV; none of the product's effect code), 4 um pixel noise. One seed; the full
benchmark runs five on the shipped sensor with the shared indenter meshes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import independent_effects as ind
from references import imports_beyond
from bench.bench_discrepancy_independent import measured_data, run_dataset
from tactile_deploy.calibration.discrepancy.workflow import DiscrepancyOptions, prepare_tables
from tactile_deploy.optics import Light, OpticsModel, simple_camera
from tactile_deploy.sensors.config import VirtualSensorConfig
from tactile_deploy.sensors.virtual import VirtualSensor

OPTS = DiscrepancyOptions(null_replicates=60, bootstrap=200, param_bootstrap=40)
OPTICS = OpticsModel(
    camera=simple_camera(160, 120, 0.1, k1=-0.1),
    lights=(Light(name="r", kind="point", position_mm=(0.0, 25.0, -6.0),
                  colour_grey=(230, 25, 20)),),
    ambient_grey=(40.0, 40.0, 45.0))
INDENTERS = ("sphere_r4", "sphere_r6", "flat_punch", "cylinder_side")


def test_independent_module_uses_no_product_code():
    # the standard library, numpy, scipy and OpenCV only: nothing of the product
    outside, product = imports_beyond(Path(__file__).parent / "independent_effects.py",
                                      {"numpy", "cv2", "scipy"})
    assert not outside, outside
    assert not product, product


def test_independent_integration_and_views_are_exact_where_they_must_be():
    """The module's own tools: slopes integrated back give the map; a radial distortion of
    k moves a point at 17.5 mm by k * 17.5 mm; a resampled 5 % scale shrinks a bump by 1.05."""
    z = 0.4 * np.exp(-(ind.X_MM**2 + (ind.Y_MM - 2.0) ** 2) / (2 * 1.5**2))
    back = ind.integrate(*ind.slopes(z))
    assert np.max(np.abs(back - z)) < 0.002 * z.max()
    dx, dy = ind.view_displacement("radial_map", {"k": 0.1, "cx_mm": 0.0, "cy_mm": 0.0}, None)
    # the point shown at p came from x_u with x_u (1 + k |x_u|^2 / 17.5^2) = p
    xu, yu = ind.X_MM + dx, ind.Y_MM + dy
    f = 1 + 0.1 * (xu**2 + yu**2) / 17.5**2
    assert np.max(np.abs(xu * f - ind.X_MM)[ind.PAD]) < 1e-9
    assert np.max(np.abs(yu * f - ind.Y_MM)[ind.PAD]) < 1e-9
    scaled = ind.pixel_scale(z, 0.05, 0.05, integrated=False)
    expected = 0.4 * np.exp(-((1.05 * ind.X_MM) ** 2 + (1.05 * ind.Y_MM - 2.0) ** 2)
                            / (2 * 1.5**2))
    assert np.max(np.abs(scaled - expected)) < 0.003


@pytest.fixture(scope="module")
def setup(small_sim):
    sensor = VirtualSensor(VirtualSensorConfig(name="small", family="gelslim", optics=OPTICS),
                           simulator=small_sim)
    rng = np.random.default_rng(5)
    contacts = []
    for k in range(16):
        r, a = 5.0 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        contacts.append(ind.Contact(INDENTERS[k % 4], float(r * np.cos(a)),
                                    float(r * np.sin(a)), float(rng.uniform(0, 180)),
                                    float(rng.uniform(0.3, 0.9))))

    def simulate(cs, material=None):
        """The clean simulate output of the small pad (nominal material, no effects)."""
        from tactile_deploy.indenters import ContactPose

        assert material is None
        out = [sensor.depth_map(c.indenter, ContactPose(x_mm=c.x_mm, y_mm=c.y_mm,
                                                        theta_deg=c.theta_deg,
                                                        depth_mm=c.depth_mm)) for c in cs]
        return np.stack([m for m, _ in out]).astype(np.float64), np.array([f for _, f in out])

    clean, forces = simulate(contacts)
    tables = prepare_tables(sensor, measured_data(contacts, clean, forces, rng, "clean"), OPTS)
    return sensor, contacts, clean, forces, simulate, tables


@pytest.mark.parametrize("effect,seed", [("radial_map", 1), ("pixel_scale_iso", 2),
                                         ("gain_gradient", 3), ("zero_offset", 4),
                                         ("none", 5), ("banding", 6), ("dust", 7)])
def test_effect_made_outside_is_named_with_its_parameters(setup, effect, seed):
    sensor, contacts, clean, forces, simulate, tables = setup
    rng = np.random.default_rng([seed, 21])
    params = ind.draw(effect, rng) if effect != "none" else {}
    entry = run_dataset(sensor, tables, contacts, clean, forces, effect, params, simulate,
                        sensor.config.optics.camera, rng, OPTS)
    print(effect, params, "->", entry["label"], entry["parameters"], entry.get("errors"))
    assert entry["label"] == ind.EXPECTED.get(effect, "none")
    static = entry["static"]
    if effect == "dust":
        # a grain in every map, too small for the energy tests: found where it is, its height
        # read to the noise of the mean (4 um / sqrt(16) = 1 um) plus the model's 1 px grid
        assert static["present"], static
        blob = static["blobs"][0]
        assert np.hypot(blob["x_mm"] - params["x_mm"], blob["y_mm"] - params["y_mm"]) < 0.2
        assert blob["peak_um"] == pytest.approx(1e3 * params["height_mm"], abs=3.0)
    elif effect != "banding":
        assert not static["present"], static
    if entry["expected"] not in ("none", "unexplained"):
        assert entry["parameters_ok"], entry["errors"]
        assert entry["gap_after_mm"] <= 0.5 * entry["gap_before_mm"]


@pytest.mark.parametrize("name,height_mm", [("sphere", 0.3), ("prism", -0.25)])
def test_independent_dome_agrees_with_the_dome_effect(pad_sim, shared_data, tmp_path, name,
                                                      height_mm):
    """Two implementations of a domed gel: the product's (the gel's rest surface lowered by the
    sag, in the FEM) and the independent one (the indenter's mesh rewritten, clean simulation):
    the same maps to 0.1 um (the effect itself: 40-120 um)."""
    from tactile_deploy.indenters import ContactPose
    from tactile_deploy.sensors.catalog import sensor_config
    from tactile_deploy.sensors.config import EffectSpec

    cfg = sensor_config("gelslim1")
    flat = VirtualSensor(cfg, simulator=pad_sim)
    domed = VirtualSensor(cfg.model_copy(update={"effects": (EffectSpec(
        name="dome", params={"height_mm": height_mm}),)}), simulator=pad_sim)
    c = ind.Contact(str(shared_data / "indenters" / f"{name}.stl"), 4.0, -5.0, 35.0, 0.6)
    (rewritten,) = ind.domed_contacts([c], height_mm, tmp_path)
    pose = ContactPose(x_mm=c.x_mm, y_mm=c.y_mm, theta_deg=c.theta_deg, depth_mm=c.depth_mm)
    effect, f_effect = domed.depth_map(c.indenter, pose)
    independent, f_ind = flat.depth_map(rewritten.indenter, pose.model_copy(
        update={"depth_mm": rewritten.depth_mm}))
    nominal, _ = flat.depth_map(c.indenter, pose)
    assert np.abs(effect - nominal).max() > 0.03
    assert np.abs(effect - independent).max() < 1e-4
    assert f_ind == pytest.approx(f_effect, rel=1e-3)
