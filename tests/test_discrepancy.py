"""The discrepancy workflow on data with hidden effects (fast subset; the full runs are
``tactile-deploy bench discrepancy``).

Measured data come from a virtual sensor on a small pad (r 10 mm, 1,735 nodes) with one effect
switched on at a parameter drawn from its realistic range that the workflow is not told; 20
commanded contacts (spheres of two radii, a flat punch, a lying cylinder), 5 um pixel noise.
The response tables of those contacts are made once per module and shared by every dataset.

Parameter tolerances (absolute): what 20 contacts at 5 um noise resolve, widened where the
simulator's 1 mm mesh makes the response to a contact move piecewise (position and rotation:
nodes switch in and out of contact).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tactile_deploy.calibration.discrepancy.apply import apply_effect
from tactile_deploy.calibration.discrepancy.candidates import CANDIDATES, lagrange_weights
from tactile_deploy.calibration.discrepancy.measured import (
    MeasuredDataError,
    load_measured,
    save_measured,
)
from tactile_deploy.calibration.discrepancy.noise import estimate_noise
from tactile_deploy.calibration.discrepancy.synthetic import draw_hidden, hidden_effect_data, random_contacts
from tactile_deploy.calibration.discrepancy.workflow import DiscrepancyOptions, find_discrepancy, prepare_tables
from tactile_deploy.optics import Light, OpticsModel, simple_camera
from tactile_deploy.sensors.config import EffectSpec, VirtualSensorConfig, load_sensor_config
from tactile_deploy.sensors.effects import REGISTRY, effect_class
from tactile_deploy.sensors.virtual import VirtualSensor

NOISE_MM = 0.005
OPTS = DiscrepancyOptions(null_replicates=60, bootstrap=200, param_bootstrap=40)
OPTICS = OpticsModel(
    camera=simple_camera(160, 120, 0.1, k1=-0.1),
    lights=(Light(name="r", kind="point", position_mm=(0.0, 25.0, -6.0),
                  colour_grey=(230, 25, 20)),),
    ambient_grey=(40.0, 40.0, 45.0))
TOLERANCE = {"offset_mm": 0.002, "scale": 0.003, "dx_mm": 0.03, "dy_mm": 0.03,
             "dtheta_deg": 1.0, "angle_deg": 0.1, "azimuth_deg": 5.0, "height_mm": 0.02,
             "strength": 0.05, "delta_nu": 0.002}


def make_sensor(sim, effects=()) -> VirtualSensor:
    cfg = VirtualSensorConfig(name="small", family="gelslim", optics=OPTICS,
                              effects=tuple(effects))
    return VirtualSensor(cfg, simulator=sim)


@pytest.fixture(scope="module")
def setup(small_sim):
    sensor = make_sensor(small_sim)
    contacts = random_contacts(20, 0, radius_mm=5.5)
    tables = prepare_tables(sensor, hidden_effect_data(sensor, [], contacts, NOISE_MM, 0))
    return sensor, contacts, tables


# ----------------------------------------------------------------------- hidden effects
@pytest.mark.slow
@pytest.mark.parametrize("effect,seed", [
    ("zero_offset", 1), ("depth_scale", 1), ("position_offset", 1), ("tilt", 1), ("dome", 1),
    ("hyperelastic", 1), ("poisson_drift", 1), ("rotation_offset", 1), ("tilt", 2)])
def test_hidden_effect_is_named_recovered_and_closes_the_gap(setup, effect, seed):
    sensor, contacts, tables = setup
    truth = draw_hidden(effect, seed)
    data = hidden_effect_data(sensor, [EffectSpec(name=effect, params=truth)], contacts,
                              NOISE_MM, seed)
    v = find_discrepancy(sensor, data, OPTS, tables=tables).verdict
    print(effect, truth, "->", v.parameters, v.gap_before_mm, v.gap_after_mm)
    assert v.verdict == "effect" and v.effect == effect
    assert v.gap_after_mm <= 0.5 * v.gap_before_mm
    for name, value in truth.items():
        assert v.parameters[name] == pytest.approx(value, abs=TOLERANCE[name]), name
    assert v.confidence > 0.9


@pytest.mark.parametrize("seed", [3, 4])
def test_effect_free_data_give_none(setup, seed):
    sensor, contacts, tables = setup
    data = hidden_effect_data(sensor, [], contacts, NOISE_MM, seed)
    v = find_discrepancy(sensor, data, OPTS, tables=tables).verdict
    assert v.verdict == "none" and v.effect is None
    assert not any(c.significant for c in v.candidates)
    assert abs(v.excess) < 0.02


def test_effect_left_out_of_the_library_is_unexplained(setup):
    sensor, contacts, tables = setup
    dent = EffectSpec(name="compression_set", params={"depth_mm": 0.06, "x_mm": 2.0,
                                                     "y_mm": 1.0, "width_mm": 2.0})
    assert "compression_set" not in {c.name for c in CANDIDATES}
    data = hidden_effect_data(sensor, [dent], contacts, NOISE_MM, 7)
    v = find_discrepancy(sensor, data, OPTS, tables=tables).verdict
    assert v.verdict == "unexplained"
    assert v.excess_z > 10  # there is structure, and it is reported rather than named
    assert v.fingerprint["where_rms_mm"]["inside_contact"] > 0


def test_static_grain_beside_a_named_effect_keeps_the_effect_and_is_reported(setup, small_sim):
    """A zero offset (in the library, the same for every contact) and a 15 um grain 0.6 mm wide
    on the gel in every map: the offset is named from the contacts, the grain, where no
    candidate reaches it, is reported as structure that remains (with where it is)."""
    import dataclasses

    from tactile_deploy.camera.depth import DepthCamera

    sensor, contacts, tables = setup
    data = hidden_effect_data(sensor, [EffectSpec(name="zero_offset",
                                                  params={"offset_mm": 0.02})],
                              contacts, NOISE_MM, 12)
    cam = DepthCamera()
    pad = cam.render(small_sim.mesh, small_sim.mesh.vertices).mask
    pix = cam.pixel_centres_mm()
    grain = 0.015 * np.exp(-((pix[..., 0] - 6.5) ** 2 + (pix[..., 1] + 4.0) ** 2) / (2 * 0.6**2))
    data = dataclasses.replace(data, depth_mm=(data.depth_mm + np.where(pad, grain, 0.0)[None]
                                               ).astype(np.float32))
    v = find_discrepancy(sensor, data, OPTS, tables=tables).verdict
    print(v.message)
    assert v.verdict == "effect" and v.effect == "zero_offset"
    assert v.parameters["offset_mm"] == pytest.approx(0.02, abs=TOLERANCE["offset_mm"])
    assert v.remaining_structure and "static relief" in v.message
    blob = v.fingerprint["static_structure"]["blobs"][0]
    # located to a pixel (0.27 mm): the blob's z-weighted centre at z 10 over 20 maps
    assert np.hypot(blob["x_mm"] - 6.5, blob["y_mm"] + 4.0) < 35.0 / 128


def test_refinement_goes_down_the_list_until_a_candidate_explains_the_gap(setup, monkeypatch):
    """With no candidate refined up front (REFINE_CANDIDATES = 0), the refinement before the
    selection still goes down the candidates, best first, and stops at the first whose
    re-centred table removes 75 % of the excess: a hidden dome, refined once before the
    selection (last of that walk) and once in the verification."""
    from tactile_deploy.calibration.discrepancy import workflow

    sensor, contacts, tables = setup
    data = hidden_effect_data(sensor, [EffectSpec(name="dome", params={"height_mm": 0.3})],
                              contacts, NOISE_MM, 13)
    refined = []
    real = workflow.refine_table

    def recording(repro, tables, table, *args, **kwargs):
        refined.append(table.name)
        return real(repro, tables, table, *args, **kwargs)

    monkeypatch.setattr(workflow, "refine_table", recording)
    monkeypatch.setattr(workflow, "REFINE_CANDIDATES", 0)
    v = find_discrepancy(sensor, data, OPTS, tables=tables).verdict
    print(refined, v.message)
    assert v.verdict == "effect" and v.effect == "dome"
    assert v.parameters["height_mm"] == pytest.approx(0.3, abs=TOLERANCE["height_mm"])
    assert refined[-2:] == ["dome", "dome"] and refined.count("dome") == 2


def test_two_effects_are_found_in_turn(setup, small_sim, tmp_path):
    sensor, contacts, tables = setup
    hidden = [EffectSpec(name="dome", params={"height_mm": 0.3}),
              EffectSpec(name="zero_offset", params={"offset_mm": 0.02})]
    data = hidden_effect_data(sensor, hidden, contacts, NOISE_MM, 9)
    first = find_discrepancy(sensor, data, OPTS, tables=tables)
    v1 = first.verdict
    assert v1.verdict == "effect" and v1.effect in ("dome", "zero_offset")
    other = ({"dome", "zero_offset"} - {v1.effect}).pop()
    assert v1.second_effect == other and v1.remaining_structure
    model = tmp_path / "small.json"
    model.write_text(sensor.config.model_dump_json(indent=2))
    applied = apply_effect(str(model), sensor.config, first.verification.spec, {"test": 1})
    updated = VirtualSensor(load_sensor_config(applied.path), simulator=small_sim)
    v2 = find_discrepancy(updated, data, OPTS).verdict
    assert v2.verdict == "effect" and v2.effect == other
    assert v2.gap_after_mm <= 0.5 * v2.gap_before_mm


@pytest.mark.slow
def test_contacts_are_estimated_when_not_commanded(small_sim):
    sensor = make_sensor(small_sim)
    contacts = random_contacts(10, 1, radius_mm=5.5, indenters=("sphere_r4", "sphere_r6"))
    data = hidden_effect_data(sensor, [EffectSpec(name="hyperelastic",
                                                  params={"strength": 1.0})],
                              contacts, NOISE_MM, 2, commanded=False)
    result = find_discrepancy(sensor, data, OPTS)
    for c, (_, true) in zip(result.tables.contacts, contacts):
        assert c.estimated
        assert np.hypot(c.pose.x_mm - true.x_mm, c.pose.y_mm - true.y_mm) < 0.05
    v = result.verdict
    assert v.contacts == "estimated"
    untestable = {c.name for c in v.candidates if not c.testable}
    assert {"zero_offset", "depth_scale", "position_offset", "rotation_offset"} <= untestable
    assert v.verdict == "effect" and v.effect == "hyperelastic"
    assert v.parameters["strength"] == pytest.approx(1.0, abs=0.08)


def test_look_alikes_are_reported_as_ambiguous_with_the_experiment_that_separates_them(small_sim):
    """Every contact pressed to the same 0.5 mm: a zero offset of 0.02 mm and a depth scale of
    4 % move every contact by the same 0.02 mm, so the data cannot tell them apart; at 1.0 mm
    they differ by 0.02 mm, at 0.4 mm by 0.004 mm: the experiment is a 1.0 mm press."""
    sensor = make_sensor(small_sim)
    contacts = random_contacts(12, 3, radius_mm=5.5, depth_range_mm=(0.5, 0.5))
    data = hidden_effect_data(sensor, [EffectSpec(name="zero_offset",
                                                  params={"offset_mm": 0.02})],
                              contacts, NOISE_MM, 4)
    v = find_discrepancy(sensor, data, OPTS).verdict
    assert v.verdict == "ambiguous"
    assert {v.effect, *v.ambiguous_with} >= {"zero_offset", "depth_scale"}
    fitted = v.parameters.get("offset_mm", 0.5 * v.parameters.get("scale", np.nan))
    assert fitted == pytest.approx(0.02, abs=0.002)
    assert v.experiment is not None and "to 1.0 mm" in v.experiment


# ------------------------------------------------------------------------------ pieces
def test_library_has_registered_candidates_null_at_their_centre():
    assert len(CANDIDATES) >= 14 and len({c.name for c in CANDIDATES}) == len(CANDIDATES)
    for c in CANDIDATES:
        assert c.effect in REGISTRY
        null = effect_class(c.effect).Params().model_dump()
        centre = c.coords_of(null)
        assert np.allclose(centre, 0.0)
        assert effect_class(c.effect)(c.params_of(centre, null)).is_null
        for nodes, (lo, hi) in c.axes(centre):
            assert len(set(np.round(nodes, 12))) == len(nodes) >= 3
            assert lo <= nodes.min() <= nodes.max() <= hi
    tilt = next(c for c in CANDIDATES if c.name == "tilt")
    p = tilt.params_of([0.01, -0.02], {"angle_deg": 0.0, "azimuth_deg": 0.0})
    assert np.allclose(tilt.coords_of(p), [0.01, -0.02])


def test_lagrange_weights_reproduce_quadratics():
    nodes = np.array([-0.05, 0.0, 0.07])
    t = np.linspace(-0.1, 0.12, 9)
    w = lagrange_weights(nodes, t)
    f = 3.0 - 2.0 * nodes + 40.0 * nodes**2
    np.testing.assert_allclose(w @ f, 3.0 - 2.0 * t + 40.0 * t**2, rtol=1e-12)


def test_noise_is_estimated_under_smooth_structure():
    rng = np.random.default_rng(0)
    mask = np.zeros((128, 128), bool)
    mask[10:118, 10:118] = True
    y, x = np.mgrid[0:128, 0:128] * (35.0 / 128)
    smooth = 0.05 * np.exp(-((x - 17) ** 2 + (y - 17) ** 2) / 20.0)  # a 50 um bump, 3 mm wide
    res = smooth[None] + rng.normal(0.0, 0.004, (12, 128, 128))
    est = estimate_noise(res, mask)
    assert est.sigma_mm == pytest.approx(0.004, rel=0.02)
    assert 0 < est.se_mm < 0.0002


def test_static_relief_is_found_in_the_mean_of_the_maps_and_nothing_else_is():
    """The static test on synthetic residuals (40 maps, 4 um white noise, contacts as 1.5 mm
    discs 0.5 mm deep): the mean of effect-free residuals has the noise's spread over the square
    root of the samples (its standard error is right) and no blob; a 10 um grain 0.5 mm wide in every map (1.7 % of the noise's energy) is
    found where it is; 50 um of leftover under every contact (moving with it) is not static."""
    from tactile_deploy.calibration.discrepancy.static import static_structure
    from tactile_deploy.camera.depth import DepthCamera

    cam = DepthCamera()
    pix = cam.pixel_centres_mm()
    x, y = pix[..., 0], pix[..., 1]
    pad = np.hypot(x, y) < 17.0
    rng = np.random.default_rng(11)
    n = 40
    centres = rng.uniform(-8.0, 8.0, (n, 2))
    disc = np.stack([np.hypot(x - cx, y - cy) < 1.5 for cx, cy in centres])
    base = np.where(disc, 0.5, 0.0)
    noise = np.where(pad, rng.normal(0.0, 0.004, (n, 128, 128)), 0.0)

    null = static_structure(noise, base, pad, cam, 0.004)
    assert not null.present
    # the mean's spread is the noise's over sqrt(samples); z <= mean / that (the samples' own
    # scatter replaces it where larger)
    t = null.tested
    assert np.std(null.mean_mm[t] * np.sqrt(null.count[t])) == pytest.approx(0.004, rel=0.03)
    assert 0.9 < np.std(null.z[t]) <= 1.0
    assert null.tested.sum() > 0.95 * pad.sum()

    grain = 0.010 * np.exp(-((x - 3.0) ** 2 + (y + 2.0) ** 2) / (2 * 0.5**2))
    found = static_structure(noise + np.where(pad, grain, 0.0)[None], base, pad, cam, 0.004)
    assert found.present and len(found.blobs) == 1
    blob = found.blobs[0]
    assert np.hypot(blob["x_mm"] - 3.0, blob["y_mm"] + 2.0) < 0.15
    assert blob["peak_um"] == pytest.approx(10.0, abs=3.0)

    leftover = np.where(disc, 0.050, 0.0)
    moving = static_structure(noise + leftover, base, pad, cam, 0.004)
    assert not moving.present
    # each sample's contact is left out where it presses: the mean under the first contact's
    # centre is made of the others' maps only
    row, col = np.unravel_index(np.argmin(np.hypot(x - centres[0, 0], y - centres[0, 1])),
                                x.shape)
    assert moving.count[row, col] <= n - disc[:, row, col].sum() < n


def test_view_warp_is_identity_at_the_null_value_and_stretches_for_pixel_scale(small_sim):
    from tactile_deploy.calibration.discrepancy.reproduce import ContactReproducer
    from tactile_deploy.imaging.camera_mapping import pixels_to_sensor_mm
    from tactile_deploy.sensors.depth_view import effect_view_warp
    from tactile_deploy.sensors.effects import get_effect

    sensor = make_sensor(small_sim)
    repro = ContactReproducer(sensor)
    cam = sensor.optics.camera
    assert effect_view_warp(get_effect("pixel_scale"), cam, repro.camera) is None
    warp = effect_view_warp(get_effect("pixel_scale", {"anisotropy": 0.05}), cam, repro.camera)
    # a pad point seen at image row offset v is reported at 1 / (1 + a) of its distance along
    # the rows: q - c = (1 + a) (p - c) along the image's v direction
    cy = cam.intrinsics.cy_px
    row_dir = pixels_to_sensor_mm(np.array([[cam.intrinsics.cx_px, cy + 10.0]]), cam) - \
        pixels_to_sensor_mm(np.array([[cam.intrinsics.cx_px, cy]]), cam)
    assert abs(row_dir[0, 1]) > abs(row_dir[0, 0])  # rows run along sensor y here
    depth, _ = repro.depth_map("sphere_r4", random_contacts(1, 5, radius_mm=0.1)[0][1])
    seen = warp(depth)
    # an integrating pipeline (exponent 1) reports depths over the stretched grid
    assert seen.max() == pytest.approx(depth.max() / np.sqrt(1.05), rel=0.03)
    cols = (depth > 0.2 * depth.max()).any(axis=1).sum(), (seen > 0.2 * seen.max()).any(
        axis=1).sum()
    assert cols[1] < cols[0]  # squeezed along the rows
    # a resampled map (exponent 0) keeps its values
    resampled = effect_view_warp(get_effect("pixel_scale", {"anisotropy": 0.05,
                                                            "depth_gain_exponent": 0.0}),
                                 cam, repro.camera)
    assert resampled(depth).max() == pytest.approx(depth.max(), rel=0.01)


def test_measured_data_round_trip_and_errors(setup, tmp_path):
    sensor, contacts, _ = setup
    data = hidden_effect_data(sensor, [], contacts[:4], NOISE_MM, 0)
    path = tmp_path / "m.npz"
    save_measured(path, data)
    back = load_measured(path)
    np.testing.assert_array_equal(back.depth_mm, data.depth_mm)
    assert back.indenter == data.indenter and back.pose(2) == data.pose(2)
    header = back.metadata["header"]   # written by save_measured, checked by load_measured
    assert (header.n_samples, header.n_known, header.maps) == (4, 4, ["depth"])
    assert header.noise_mm == data.noise_mm and header.units["depth"].startswith("mm")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    # arrays changed after writing are refused, naming the file, the field and both values
    np.savez(tmp_path / "cut.npz", **{k: (v[:3] if v.ndim and k != "header_json" else v)
                                      for k, v in arrays.items()})
    with pytest.raises(MeasuredDataError, match=r"cut.npz: field 'header_json.n_samples': the "
                                                r"header says 4, the arrays hold 3"):
        load_measured(tmp_path / "cut.npz")
    broken = json.loads(str(arrays["header_json"]))
    broken["maps"] = ["depth", "video"]
    np.savez(tmp_path / "bad_header.npz", **{**arrays, "header_json": np.array(json.dumps(broken))})
    with pytest.raises(MeasuredDataError, match=r"bad_header.npz: field 'header_json'.*\n  field "
                                                r"'maps.1'.*got \"video\""):
        load_measured(tmp_path / "bad_header.npz")
    # files without a header (written by hand, or before the header) still read
    np.savez(tmp_path / "plain.npz", **{k: v for k, v in arrays.items() if k != "header_json"})
    assert "header" not in load_measured(tmp_path / "plain.npz").metadata
    folder = tmp_path / "folder"
    folder.mkdir()
    rows = ["indenter,x_mm,y_mm,theta_deg,depth_mm,force_n,depth_file"]
    for i in range(4):
        np.save(folder / f"d{i}.npy", data.depth_mm[i])
        rows.append(f"{data.indenter[i]},{data.x_mm[i] if i else ''},"
                    f"{data.y_mm[i] if i else ''},,"
                    f"{data.depth_cmd_mm[i] if i else ''},{data.force_n[i]},d{i}.npy")
    (folder / "contacts.csv").write_text("\n".join(rows) + "\n")
    f = load_measured(folder)
    assert f.known(1) and not f.known(0) and f.pose(0) is None
    np.testing.assert_array_equal(f.depth_mm, data.depth_mm)
    bad = tmp_path / "bad.npz"
    np.savez(bad, indenter=np.array(["sphere_r4"]), depth=np.zeros((1, 64, 64), np.float32))
    with pytest.raises(MeasuredDataError, match="'depth' must have shape .1, 128, 128.*got "
                                                "\\(1, 64, 64\\)"):
        load_measured(bad)
    with pytest.raises(MeasuredDataError, match="contacts.csv not found"):
        load_measured(tmp_path)


def test_apply_writes_versions_and_keeps_the_previous(small_sim, tmp_path):
    sensor = make_sensor(small_sim)
    model = tmp_path / "unit.json"
    model.write_text(sensor.config.model_dump_json(indent=2) + "\n")
    first = apply_effect(str(model), load_sensor_config(model),
                         EffectSpec(name="zero_offset", params={"offset_mm": 0.02}), {"a": 1})
    second = apply_effect(str(model), load_sensor_config(model),
                          EffectSpec(name="zero_offset", params={"offset_mm": 0.03}), {"b": 2})
    assert (first.version, second.version) == (2, 3)
    history = json.loads(second.history.read_text())
    assert [v["version"] for v in history["versions"]] == [1, 2, 3]
    v1 = load_sensor_config(second.history.parent / "v1.json")
    assert v1.effects == ()
    now = load_sensor_config(model)
    assert [(e.name, e.params["offset_mm"]) for e in now.effects] == [("zero_offset", 0.03)]
    assert second.previous.name == "v2.json"
    # a shipped sensor is copied, never changed in place, and not overwritten
    applied = apply_effect("gelslim1", sensor.config.model_copy(update={"name": "gelslim1"}),
                           EffectSpec(name="dome", params={"height_mm": 0.1}), {}, tmp_path)
    assert applied.path == tmp_path / "gelslim1.json" and applied.version == 2
    with pytest.raises(FileExistsError, match="exists already"):
        apply_effect("gelslim1", sensor.config.model_copy(update={"name": "gelslim1"}),
                     EffectSpec(name="dome", params={"height_mm": 0.1}), {}, tmp_path)


@pytest.mark.slow
def test_command_prints_json_writes_report_and_applies(pad_sim, tmp_path):
    from typer.testing import CliRunner

    from tactile_deploy.cli.main import app

    model = tmp_path / "unit.json"
    cfg = VirtualSensorConfig(name="unit", family="gelslim", optics=OPTICS)
    model.write_text(cfg.model_dump_json(indent=2) + "\n")
    sensor = VirtualSensor(cfg, simulator=pad_sim)
    contacts = random_contacts(8, 4, radius_mm=7.0, indenters=("sphere_r4", "flat_punch"))
    data = hidden_effect_data(sensor, [EffectSpec(name="zero_offset",
                                                  params={"offset_mm": 0.03})],
                              contacts, NOISE_MM, 4)
    save_measured(tmp_path / "m.npz", data)
    args = ["discrepancy", "--sensor", str(model), "--measured", str(tmp_path / "m.npz"),
            "--candidates", "zero_offset,depth_scale,dome,tilt", "--null-replicates", "40",
            "--folds", "4"]
    out = CliRunner().invoke(app, [*args, "--json", "--report", str(tmp_path / "rep"),
                                   "--apply"])
    assert out.exit_code == 0, out.output
    doc = json.loads(out.stdout)
    assert {"verdict", "effect", "parameters", "gap_before_mm", "gap_after_mm",
            "candidates"} <= set(doc)
    assert doc["verdict"] == "effect" and doc["effect"] == "zero_offset"
    assert doc["parameters"]["offset_mm"] == pytest.approx(0.03, abs=0.003)
    assert doc["gap_after_mm"] < 0.5 * doc["gap_before_mm"]
    for name in ("report.md", "verdict.json", "residual_maps.png", "candidates.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 0
    assert [e.name for e in load_sensor_config(model).effects] == ["zero_offset"]
    assert (tmp_path / "unit.versions" / "v1.json").exists()
    # with the effect in the model, the same data show nothing missing
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0, again.output
    assert "verdict: NONE" in again.stdout
    missing = CliRunner().invoke(app, ["discrepancy", "--sensor", str(model), "--measured",
                                       str(tmp_path / "nothing.npz")])
    assert missing.exit_code == 2 and "not found" in " ".join(missing.output.split())
