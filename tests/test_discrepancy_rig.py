"""Measured data from rig presses (``tactile-deploy rig collect``), end to end on the simulated
rig: a virtual sensor with a domed gel pressed over pseudo-terminals, its frames recorded with
the commanded contacts and the gauge's forces, and the discrepancy workflow naming the dome from
those frames against the flat shipped model."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.cli.main import app


def _invoke(*args):
    return CliRunner().invoke(app, [*map(str, args)])


@pytest.fixture(scope="module")
def domed_unit(tmp_path_factory):
    from tactile_deploy.sensors.catalog import sensor_config
    from tactile_deploy.sensors.config import EffectSpec, save_sensor_config

    folder = tmp_path_factory.mktemp("rig")
    cfg = sensor_config("gelslim1")
    unit = cfg.model_copy(update={"name": "domed", "effects": (
        EffectSpec(name="dome", params={"height_mm": 0.3}),)})
    path = folder / "domed.json"
    save_sensor_config(unit, path)
    return folder, path


def test_rig_collect_records_frames_commanded_contacts_and_forces(domed_unit):
    from tactile_deploy.calibration.discrepancy.collect import load_collection_log, plan_contacts
    from tactile_deploy.calibration.discrepancy.measured import load_measured
    from tactile_deploy.indenters import ContactPose
    from tactile_deploy.sensors import load_sensor

    folder, unit = domed_unit
    out = folder / "presses.npz"
    res = _invoke("rig", "collect", "--simulated", "--source", f"virtual:{unit}", "--indenter",
                  "sphere_r4", "--n", 8, "--radius-mm", 6, "--depth-range", "0.4,0.9",
                  "--seed", 3, "--out", out)
    assert res.exit_code == 0, res.output
    assert "8 of 8 presses recorded" in res.output
    data = load_measured(out)
    log = load_collection_log(out)
    plan = plan_contacts(8, 6.0, (0.4, 0.9), 3)
    assert data.frames.shape == (8, 480, 640, 3) and data.depth_mm is None
    np.testing.assert_allclose(data.x_mm, [c.x_mm for c in plan])
    np.testing.assert_allclose(data.depth_cmd_mm, [c.depth_mm for c in plan])
    assert data.indenter == ["sphere_r4"] * 8 and len(log.presses) == 8
    # the gauge read the domed sensor's FEM force at the commanded contact (2 decimals)
    sensor = load_sensor(unit)
    for i in (0, 5):
        truth = sensor.contact_force_n("sphere_r4", ContactPose(
            x_mm=data.x_mm[i], y_mm=data.y_mm[i], depth_mm=data.depth_cmd_mm[i]))
        assert data.force_n[i] == pytest.approx(truth, abs=0.006)
    again = _invoke("rig", "collect", "--simulated", "--source", f"virtual:{unit}",
                    "--indenter", "sphere_r4", "--n", 2, "--out", out)
    assert again.exit_code == 1 and "--overwrite" in again.output


@pytest.mark.slow
def test_discrepancy_names_the_dome_from_the_rigs_frames(domed_unit):
    folder, _ = domed_unit
    res = _invoke("discrepancy", "--sensor", "gelslim1", "--measured", folder / "presses.npz",
                  "--candidates", "zero_offset,dome", "--null-replicates", 40, "--folds", 4,
                  "--json")
    assert res.exit_code == 0, res.output
    v = json.loads(res.stdout)
    print(v["message"])
    assert v["verdict"] == "effect" and v["effect"] == "dome"
    assert v["parameters"]["height_mm"] == pytest.approx(0.3, abs=0.03)


@pytest.mark.parametrize("args,message", [
    (["--no-frames"], "--no-frames needs --plugin"),
    (["--depth-range", "0.5"], "expected min,max"),
    (["--depth-range", "0.5,3.5"], "reaches through"),
    (["--plan", "PLAN"], "column(s) depth_mm missing"),
])
def test_rig_collect_refuses_bad_input(tmp_path, args, message):
    plan = tmp_path / "plan.csv"
    plan.write_text("x_mm,y_mm\n1,2\n")
    args = [str(plan) if a == "PLAN" else a for a in args]
    res = _invoke("rig", "collect", "--simulated", "--source", "virtual:gelslim1", "--indenter",
                  "sphere_r4", "--out", tmp_path / "p.npz", *args)
    assert res.exit_code == 1
    assert message in " ".join(res.output.split())
    assert not (tmp_path / "p.npz").exists()
