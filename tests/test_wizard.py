"""Calibration wizard end to end: a virtual sensor pressed by a simulated rig on pseudo-terminals.

Truth is independent of the wizard: the virtual sensor's own camera mapping (mm per px), FEM
material (E) and zero offset of its pressing axis (planted in its config), and the surface its
frames are shaded from, on new presses the wizard never saw. The plugin is checked by the
runtime's own loader (``validate_plugin``, ``SensorPlugin``, ``ImagingPipeline``).

Settings are small (6 reference frames, 16 presses, nu fixed at the sensor's operator node):
each wizard run takes about 10-15 s once the sensor's surface operators are cached.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.cli.main import app

ROOT = Path(__file__).resolve().parent.parent
SENSOR = "gelslim2"
CONFIG = {
    "description": "test unit",
    "reference": {"n_frames": 6},
    "camera": {"n_frames": 1},
    "presses": {"n_presses": 24},
    "shading": {"folds": 4},
    "fem": {"bootstrap": 0},
    "rig": {"approach_step_mm": 0.2, "approach_clearance_mm": 0.4},
}


def _invoke(*args):
    return CliRunner().invoke(app, ["calibrate", *map(str, args)])


@pytest.fixture(scope="module")
def sensor():
    from tactile_deploy.sensors import load_sensor

    s = load_sensor(SENSOR)
    s.prepare()
    return s


@pytest.fixture(scope="module")
def wizard_run(tmp_path_factory, sensor):
    """One non-interactive run: ``calibrate --sensor acme --source virtual:gelslim2 --rig
    simulated --config cfg.json --yes``."""
    folder = tmp_path_factory.mktemp("wizard")
    cfg = folder / "cfg.json"
    cfg.write_text(json.dumps(CONFIG))
    out = folder / "acme"
    res = _invoke("--sensor", "acme", "--source", f"virtual:{SENSOR}", "--rig", "simulated",
                  "--config", cfg, "--out", out, "--yes")
    print(res.output)
    assert res.exit_code == 0, res.output
    return folder, out, cfg, res.output


@pytest.fixture
def wizard_copy(wizard_run, tmp_path):
    """A copy of the wizard run's folder (config, work folder, plugin) for tests that redo
    steps: the module's run stays as the wizard wrote it, whatever order the tests run in."""
    import shutil

    folder, out, cfg, output = wizard_run
    copy = tmp_path / folder.name
    shutil.copytree(folder, copy)
    out_copy = copy / out.relative_to(folder)
    state = copy / f"{out.name}.calibration" / "state.json"   # the plugin it wrote is the copy
    state.write_text(json.dumps({**json.loads(state.read_text()),
                                 "plugin_written": str(out_copy.resolve())}))
    return copy, out_copy, copy / cfg.relative_to(folder), output


def test_plugin_is_loaded_by_the_runtime(wizard_run):
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin

    folder, out, _, _ = wizard_run
    report = validate_plugin(out)
    assert report.ok, report.problems
    assert {"manifest", "shading model", "reference frame", "noise reference", "demo clip",
            "topology", "model contract"} <= set(report.checked)
    plugin = SensorPlugin.load(out)
    assert plugin.name == "acme" and plugin.manifest.description == "test unit"
    assert plugin.manifest.default_source.kind == "virtual"
    # written atomically: nothing half-made is left beside it
    assert not [p for p in folder.iterdir() if p.name.startswith(".acme")]
    # the report shows every step with its figures
    html = (out / "calibration" / "report.html").read_text()
    for step in ("reference", "camera", "presses", "shading", "fem", "plugin"):
        assert f"<h2>{step}:" in html
    for png in ("reference", "camera", "presses", "shading", "shading_cv", "fem", "plugin"):
        assert (out / "calibration" / f"{png}.png").stat().st_size > 10_000
    from tactile_deploy.calibration.wizard.report import load_calibration_metrics

    metrics = load_calibration_metrics(out / "calibration" / "metrics.json")
    assert metrics.steps["presses"]["presses used"] >= 22 and metrics.sensor == "acme"
    # and the main command runs on it: its demo clip (the calibration frames) -> pad meshes
    res = CliRunner().invoke(app, ["run", "--sensor", str(out), "--source", "demo", "--out",
                                   str(folder / "run"), "--no-forces", "--format", "ply"])
    assert res.exit_code == 0, res.output
    assert len(list((folder / "run").glob("mesh_*.ply"))) == 4 + 24   # 4 rest frames + presses


def test_depth_matches_the_virtual_sensor_on_new_presses(wizard_run, sensor):
    """New presses (places, depths, noise the wizard never saw), through the runtime's imaging
    pipeline of the written plugin, against the surface the frames were shaded from (area
    averaged onto the model grid). Whole-frame RMSE is held to the shading target (20 um); the
    error near the contact is reported (docs/calibration.md: 20 um not met, a known gap) and
    guarded against regression (measured mean 30.5 um with the FEM targets around the contacts,
    36.1 um without them)."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.runtime.pipeline import GridResampler, ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin

    _, out, _, _ = wizard_run
    plugin = SensorPlugin.load(out)
    pipeline = ImagingPipeline.from_plugin(plugin)
    to_model = GridResampler(sensor.renderer.grid, OutputGrid())
    g = OutputGrid()
    x = g.x_min_mm + (np.arange(g.nx) + 0.5) * g.pitch_x_mm
    y = g.y_max_mm - (np.arange(g.ny) + 0.5) * g.pitch_y_mm
    ig = plugin.manifest.camera.grid
    rng = np.random.default_rng(2024)
    whole, near, peak = [], [], []
    for i in range(8):
        depth = rng.uniform(0.3, 0.8)
        a = math.sqrt(2 * 3.0 * depth)
        # inside the view by two contact radii (near the border the gel sinks beyond the view
        # and the integration's zero border costs accuracy: docs/calibration.md)
        pose = ContactPose(x_mm=rng.uniform(ig.x_min_mm + 2 * a, ig.x_max_mm - 2 * a),
                           y_mm=rng.uniform(ig.y_min_mm + 2 * a, ig.y_max_mm - 2 * a),
                           depth_mm=depth)
        frame = sensor.press(AnalyticSphere(3.0), pose, np.random.default_rng([77, i]))
        truth = to_model(frame.surface_depth_mm.astype(np.float32))
        est = pipeline.frame_to_depth(frame.frame)
        m = np.hypot(x[None] - pose.x_mm, y[:, None] - pose.y_mm) < 1.5 * a
        whole.append(np.sqrt(np.mean((est - truth) ** 2)) * 1e3)
        near.append(np.sqrt(np.mean((est[m] - truth[m]) ** 2)) * 1e3)
        peak.append(abs(float(est.max()) - float(truth.max())) * 1e3)
    print(f"\nplugin depth vs virtual truth, um: whole-frame RMSE {np.round(whole, 1)} (mean "
          f"{np.mean(whole):.1f}); within 1.5 contact radii {np.round(near, 1)} (mean "
          f"{np.mean(near):.1f}); peak {np.round(peak, 1)}")
    assert np.mean(whole) <= 20.0
    assert np.mean(near) <= 33.0         # regression guards, not the 20 um target
    assert np.max(near) < 80.0


def test_camera_mapping_and_material_match_the_planted_sensor(wizard_run, sensor):
    """mm per px within 1 % of the virtual camera's; E within 5 % of the FEM's, and the rig's
    depth zero error found (the sensor's zero_offset effect, 0.03 mm)."""
    from tactile_deploy.runtime.plugins import SensorPlugin

    folder, out, _, _ = wizard_run
    m = SensorPlugin.load(out).manifest
    true_cam = sensor.optics.camera
    assert abs(m.camera.mm_per_px_x / true_cam.mm_per_px_x - 1) < 0.01
    assert abs(m.camera.mm_per_px_y / true_cam.mm_per_px_y - 1) < 0.01
    planted_offset = next(e.params["offset_mm"] for e in sensor.config.effects
                          if e.name == "zero_offset")
    fem = json.loads((folder / "acme.calibration" / "fem.json").read_text())
    print(f"\nE {m.material.E_mpa:.4f} MPa (true {sensor.config.material.E_mpa}), depth offset "
          f"{fem['depth_offset_mm'] * 1e3:.1f} um (planted {planted_offset * 1e3:.0f} um)")
    assert m.material.E_mpa == pytest.approx(sensor.config.material.E_mpa, rel=0.05)
    assert m.material.nu == pytest.approx(0.48)            # fixed: one operator node
    assert "fixed at 0.48" in m.material.source
    assert fem["depth_offset_mm"] == pytest.approx(planted_offset, abs=0.01)


def test_redo_resume_and_config_checks(wizard_copy):
    """--redo reruns from a step (the plugin it wrote is replaced without --overwrite); a
    finished calibration says so; another config needs --redo or --restart; bad input names
    the file and field."""
    from tactile_deploy.calibration.wizard.state import WorkFolder

    folder, out, cfg, _ = wizard_copy
    work = WorkFolder(folder / "acme.calibration")
    before = work.load()
    res = _invoke("--sensor", "acme", "--source", f"virtual:{SENSOR}", "--rig", "simulated",
                  "--config", cfg, "--out", out, "--yes", "--redo", "fem")
    assert res.exit_code == 0, res.output
    after = work.load()
    assert "step 5/7" in res.output and "step 4/7" not in res.output
    for step in ("reference", "camera", "presses", "shading"):
        assert after.steps[step] == before.steps[step]
    assert (out / "plugin.json").is_file()
    res = _invoke("--sensor", "acme", "--source", f"virtual:{SENSOR}", "--rig", "simulated",
                  "--config", cfg, "--out", out, "--yes")
    assert res.exit_code == 0 and "Every step is done" in res.output
    other = folder / "other.json"
    other.write_text(json.dumps({**CONFIG, "presses": {"n_presses": 20}}))
    res = _invoke("--sensor", "acme", "--source", f"virtual:{SENSOR}", "--rig", "simulated",
                  "--config", other, "--out", out, "--yes")
    assert res.exit_code == 2 and "presses" in res.output and "--redo" in res.output
    res = _invoke("--sensor", "other", "--source", f"virtual:{SENSOR}", "--out", out, "--yes",
                  "--work", work.folder)
    assert res.exit_code == 2 and "holds a calibration of 'acme'" in res.output
    bad = folder / "bad.json"
    bad.write_text(json.dumps({"presses": {"depth_range_mm": [0.9, 0.3]}}))
    res = _invoke("--sensor", "x", "--source", f"virtual:{SENSOR}", "--config", bad, "--yes")
    assert res.exit_code == 2 and "bad.json" in res.output and "depth_range_mm" in res.output
    res = _invoke("--sensor", "x", "--source", "virtual:nosuch", "--yes", "--out",
                  folder / "x")
    assert res.exit_code == 2 and "gelslim1" in res.output
    res = _invoke("--sensor", "x", "--source", "0", "--yes")
    assert res.exit_code == 2 and "--yes cannot wait for hand presses" in res.output
    res = _invoke("--sensor", "x", "shading")
    assert res.exit_code == 2 and "belong to the wizard" in res.output


def test_calibrate_fem_on_the_wizard_presses(wizard_run):
    """The FEM step as a plain command, on the rig presses of the wizard's work folder."""
    folder, _, _, _ = wizard_run
    res = CliRunner().invoke(app, ["calibrate", "fem", "--work", str(folder / "acme.calibration"),
                                   "--nu-grid", "0.48", "--bootstrap", "0",
                                   "--fit-depth-offset", "--out", str(folder / "fem_cli.json")])
    assert res.exit_code == 0, res.output
    doc = json.loads((folder / "fem_cli.json").read_text())
    wiz = json.loads((folder / "acme.calibration" / "fem.json").read_text())
    assert doc["E_mpa"] == pytest.approx(wiz["E_mpa"], rel=1e-9)
    assert doc["n_contacts"] >= 14
    res = CliRunner().invoke(app, ["calibrate", "fem", "--contacts", str(folder / "none.csv")])
    assert res.exit_code == 2 and "none.csv not found" in res.output
    # into the work folder: a new file is fine, a file the step reads is never replaced
    work = folder / "acme.calibration"
    args = ["calibrate", "fem", "--work", str(work), "--nu-grid", "0.48", "--bootstrap", "0", "--out"]
    res = CliRunner().invoke(app, [*args, str(work / "camera_mapping.json"), "--overwrite"])
    assert res.exit_code == 2 and "is also an input" in " ".join(res.output.split())
    res = CliRunner().invoke(app, [*args, str(work / "fem_cli.json")])
    assert res.exit_code == 0, res.output


# ------------------------------------------------------------------------------ interactive
@pytest.mark.slow
def test_interactive_wizard_through_a_pty(tmp_path):
    """A person at a terminal (pexpect): every step, one redo (camera), a circle corrected by
    hand, an interruption (Ctrl-C) after the shading step, and a resume that finishes."""
    import pexpect

    from tactile_deploy.calibration.wizard.state import WorkFolder
    from tactile_deploy.runtime.plugins import validate_plugin

    cfg = tmp_path / "cfg.json"       # fewer frames and presses: the dialogue is under test
    cfg.write_text(json.dumps({**CONFIG, "reference": {"n_frames": 3},
                               "presses": {"n_presses": 6}, "shading": {"folds": 2},
                               "discrepancy": {"n_presses": 4}}))
    out = tmp_path / "unit7"
    cmd = [sys.executable, "-m", "tactile_deploy.cli.main", "calibrate", "--sensor", "unit7",
           "--source", f"virtual:{SENSOR}", "--rig", "simulated", "--config", str(cfg),
           "--out", str(out)]
    env = dict(os.environ, TERM="xterm", COLUMNS="120", PYTHONUNBUFFERED="1")
    import io

    log = io.StringIO()

    def spawn():
        child = pexpect.spawn(cmd[0], cmd[1:], cwd=str(tmp_path), env=env, encoding="utf-8",
                              timeout=120, dimensions=(50, 140))
        child.logfile_read = log
        return child

    def next_prompt(child, step):
        child.expect(f"Step '{step}' done. Next\\?")

    c = spawn()
    next_prompt(c, "reference")
    c.send("1\r")                                   # accept
    next_prompt(c, "camera")
    c.send("3\r")                                   # redo the camera step (2: open pictures)
    next_prompt(c, "camera")
    c.send("1\r")
    next_prompt(c, "presses")
    c.send("2\r")                                   # correct a circle by hand
    c.expect("Which press to correct")
    c.send("\x15" + "3\r")
    c.expect("Circle of press_002.png")
    c.send("\x15" + "41.5 30.25 6\r")
    c.expect("circle set by hand")
    next_prompt(c, "presses")
    c.send("1\r")
    next_prompt(c, "shading")
    c.send("1\r")
    next_prompt(c, "fem")
    c.sendintr()                                    # Ctrl-C: stop, progress kept
    c.expect("Interrupted")
    c.expect(pexpect.EOF)
    c.close()
    assert c.exitstatus == 130
    state = WorkFolder(tmp_path / "unit7.calibration").load()
    assert list(state.steps) == ["reference", "camera", "presses", "shading"]
    with np.load(tmp_path / "unit7.calibration" / "presses.npz") as z:
        np.testing.assert_allclose(z["circles"][2], [41.5, 30.25, 6.0])
    assert not out.exists()

    c = spawn()                                     # resume
    c.expect("Resuming the calibration of")
    c.expect("Resume\\?")
    c.send("1\r")
    next_prompt(c, "fem")
    c.send("1\r")
    next_prompt(c, "plugin")
    c.send("1\r")
    next_prompt(c, "discrepancy")
    c.send("1\r")
    c.expect("Done.")
    c.expect(pexpect.EOF)
    c.close()
    assert c.exitstatus == 0
    transcript = log.getvalue()
    assert transcript.count("step 2/7: camera mapping") == 2       # run, then redone
    assert transcript.count("step 1/7: reference") == 1             # not rerun on resume
    report = validate_plugin(out)
    assert report.ok, report.problems
    state = WorkFolder(tmp_path / "unit7.calibration").load()
    assert list(state.steps) == ["reference", "camera", "presses", "shading", "fem", "plugin",
                                 "discrepancy"]
    assert any("circle set by hand" in n for n in state.steps["presses"].notes)


def test_calibrate_fem_on_a_contacts_csv(tmp_path, sensor):
    """``calibrate fem --contacts``: the virtual sensor's own depth maps (model grid) and FEM
    forces at the contacts it reached give back its E; the CSV is checked line by line."""
    from tactile_deploy.indenters import ContactPose

    rows = ["depth_file,indenter,x_mm,y_mm,depth_mm,force_n"]
    for i, (x, y, d) in enumerate([(-3.0, 1.0, 0.5), (2.0, -2.0, 0.8), (4.0, 3.0, 0.35)]):
        out = sensor.press("sphere_r4", ContactPose(x_mm=x, y_mm=y, depth_mm=d), None)
        np.save(tmp_path / f"d{i}.npy", out.depth_mm)
        r = out.pose_reached
        rows.append(f"d{i}.npy,sphere_r4,{r.x_mm},{r.y_mm},{r.depth_mm},{out.force_n}")
    rows.append("d0.npy,sphere_r4,,,,")            # contact and force unknown: estimated
    (tmp_path / "c.csv").write_text("\n".join(rows) + "\n")
    res = CliRunner().invoke(app, ["calibrate", "fem", "--contacts", str(tmp_path / "c.csv"),
                                   "--nu-grid", "0.48", "--bootstrap", "0", "--out",
                                   str(tmp_path / "fem.json")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "fem.json").read_text())
    assert doc["n_contacts"] == 4
    assert doc["E_mpa"] == pytest.approx(sensor.config.material.E_mpa, rel=0.05)
    (tmp_path / "bad.csv").write_text("depth_file,indenter,x_mm,y_mm,depth_mm,force_n\n"
                                      "d0.npy,sphere_r4,1,abc,0.5,1\n")
    res = CliRunner().invoke(app, ["calibrate", "fem", "--contacts", str(tmp_path / "bad.csv")])
    assert res.exit_code == 2 and "bad.csv, line 2: field 'y_mm'" in res.output
    (tmp_path / "hdr.csv").write_text("file,indenter\n")
    res = CliRunner().invoke(app, ["calibrate", "fem", "--contacts", str(tmp_path / "hdr.csv")])
    assert res.exit_code == 2 and "header must be depth_file,indenter" in res.output


def test_wizard_drives_a_rig_on_serial_ports_with_recorded_frames(tmp_path, sensor):
    """The hardware path: ``--source clip.npz --rig PORT --gauge PORT``. A simulated rig runs
    on two pseudo-terminals (as `tactile-deploy rig simulate` would); the frames come from a clip
    recorded beforehand at the contacts the wizard will command (the crop target: frames taken as
    rectified). The stage is driven to every planned contact, the gauge's forces are recorded."""
    from tactile_deploy.calibration.rig.simulated import HertzForce, SimulatedRig
    from tactile_deploy.calibration.wizard.steps.presses import plan_presses
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.runtime.plugins import validate_plugin
    from tactile_deploy.imaging.camera_mapping import crop_camera_mapping
    from tactile_deploy.runtime.sources.npz import save_clip

    mm_per_px, crop = sensor.optics.camera.mm_per_px_x, (160, 120, 320, 240)
    cfg = {**CONFIG, "reference": {"n_frames": 3}, "presses": {"n_presses": 8},
           "shading": {"folds": 0}, "fem": {"enabled": False},
           "camera": {"target": "crop", "mm_per_px": mm_per_px, "crop": list(crop)},
           "discrepancy": {"n_presses": 0}}   # the clip holds no frames for more presses
    (tmp_path / "cfg.json").write_text(json.dumps(cfg))
    grid = crop_camera_mapping(640, 480, mm_per_px, crop).grid
    plan = plan_presses(grid, 3.0, 8, (0.3, 0.9), 0)
    frames = [sensor.reference_frame(np.random.default_rng([5, i])) for i in range(4)]
    for i, (x, y, d) in enumerate(plan):
        frames.append(sensor.press(AnalyticSphere(3.0), ContactPose(x_mm=x, y_mm=y, depth_mm=d),
                                   np.random.default_rng([6, i]), truth=False).frame)
    save_clip(tmp_path / "clip.npz", np.stack(frames), np.arange(len(frames)) * 33_000_000)
    force = HertzForce(1.3)
    with SimulatedRig(force) as sim:
        res = _invoke("--sensor", "bench1", "--source", tmp_path / "clip.npz", "--rig",
                      sim.stage_port, "--gauge", sim.gauge_port, "--config",
                      tmp_path / "cfg.json", "--out", tmp_path / "bench1", "--yes")
        history = np.array(sim.stage.history_mm)
    assert res.exit_code == 0, res.output
    assert validate_plugin(tmp_path / "bench1").ok
    with np.load(tmp_path / "bench1.calibration" / "presses.npz") as z:
        tips, forces = z["tip_mm"], z["force_n"]
    np.testing.assert_allclose(tips, plan, atol=0.011)          # M114 reports 0.01 mm
    np.testing.assert_allclose(forces, [force(d, 0, 0) for d in plan[:, 2]], atol=0.011)
    for x, y, d in plan:                                        # the stage went to each contact
        target = sim.frame.sensor_to_stage(x, y, -d)
        assert np.min(np.linalg.norm(history - target, axis=1)) < 1e-3  # G-code: 4 decimals


def test_plugin_step_with_the_learned_readout(wizard_copy):
    """``--redo plugin`` with the design's learned read-out in the config: the plugin names it,
    its depth gain is calibrated from the rig's presses, and its noise reference is made through
    it (a no-contact frame comes out flat)."""
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin

    folder, out, _, _ = wizard_copy
    readout = Path(__file__).resolve().parent.parent / "exported" / "gelslim_readout.onnx"
    cfg = folder / "readout.json"
    cfg.write_text(json.dumps({**CONFIG, "readout": str(readout), "readout_steps": 0}))
    res = _invoke("--sensor", "acme", "--source", f"virtual:{SENSOR}", "--rig", "simulated",
                  "--config", cfg, "--out", out, "--yes", "--redo", "plugin")
    assert res.exit_code == 0, res.output
    report = validate_plugin(out)
    assert report.ok and "learned read-out" in report.checked, report.problems
    plugin = SensorPlugin.load(out)
    m = plugin.manifest
    assert m.readout is not None and m.readout.path.endswith("exported/gelslim_readout.onnx")
    assert 0.85 < m.readout_depth_gain < 1.15
    assert "rig presses" in m.provenance["readout"] and "zero offset" in m.provenance["readout"]
    pipe = ImagingPipeline.from_plugin(plugin)
    assert pipe.readout is not None and pipe.readout_gain == np.float32(m.readout_depth_gain)
    from tactile_deploy.sensors import load_sensor

    sensor = load_sensor(SENSOR)
    flat = pipe.frame_to_depth(sensor.renderer.reference_frame(np.random.default_rng(9)))
    assert np.abs(flat).max() < 0.02, np.abs(flat).max()
    # new presses the wizard never saw, against the surface their frames were shaded from
    from tactile_deploy.calibration.shading.virtual_check import (
        near_contact_errors,
        virtual_ball_presses,
    )

    presses = virtual_ball_presses(sensor, m.camera.grid, n_inside=8, n_edge=0, seed=31)
    e = near_contact_errors([pipe.frame_to_depth(f) for f in presses.frames], presses)
    print("near-contact RMSE um: mean", e["near"].mean(), "worst", e["near"].max())
    assert e["near"].mean() <= 20.0                           # the calibration's depth target


@pytest.mark.slow
def test_plugin_step_fine_tunes_the_readout_on_the_unit(wizard_copy, sensor):
    """With ``readout_steps`` the plugin step continues the design's read-out on the unit's rig
    presses (their FEM depth at the rig's intrusion plus the fitted zero offset) and writes it
    into the plugin. It reproduces those targets much better than the design's network does,
    and against the true surface of new presses the wizard never saw it still reads the ball's
    depth within the calibration's 20 um target near the contact. (It is not better there than
    the design's network as it is: docs/shading.md says why; the wizard's default is 0 steps.)"""
    import hashlib

    from tactile_deploy.calibration.shading.virtual_check import (
        near_contact_errors,
        virtual_ball_presses,
    )
    from tactile_deploy.imaging.learned_readout import LearnedReadout
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin

    folder, out, _, _ = wizard_copy
    base = ROOT / "exported" / "gelslim_readout.onnx"
    cfg = folder / "readout_tuned.json"
    cfg.write_text(json.dumps({**CONFIG, "readout": str(base), "readout_steps": 400}))
    res = _invoke("--sensor", "acme", "--source", f"virtual:{SENSOR}", "--rig", "simulated",
                  "--config", cfg, "--out", out, "--yes", "--redo", "plugin")
    assert res.exit_code == 0, res.output
    assert "fine-tuning the learned read-out on" in res.output
    report = validate_plugin(out)
    assert report.ok and "learned read-out" in report.checked, report.problems
    plugin = SensorPlugin.load(out)
    m = plugin.manifest
    assert m.readout is not None and m.readout.path == "readout.onnx"
    tuned = plugin.readout
    assert tuned.metadata["finetuned_on"] == "acme"
    assert tuned.metadata["base_sha256"] == hashlib.sha256(base.read_bytes()).hexdigest()
    assert tuned.metadata["design"] == LearnedReadout(base).metadata["design"]
    assert "fine-tuned on this unit's" in m.provenance["readout"]
    assert 0.9 < m.readout_depth_gain < 1.1      # the targets are absolute: no scale left

    pipe = ImagingPipeline.from_plugin(plugin)
    design = ImagingPipeline(m.camera, plugin.shading_model, plugin.reference_frame,
                             readout=LearnedReadout(base))
    # its own targets: the rig presses' FEM depth maps, as the wizard drew them
    from tactile_deploy.calibration.wizard.config import wizard_config_from_dict
    from tactile_deploy.calibration.wizard.press_data import press_profiles

    work = out.parent / f"{out.name}.calibration"
    with np.load(work / "presses.npz") as z:
        d = {k: z[k] for k in z.files}
    material = json.loads((work / "fem.json").read_text())
    profiles = press_profiles(wizard_config_from_dict(CONFIG, "CONFIG"), d, m.camera, 4.0,
                              material["depth_offset_mm"], material["nu"])
    keep = np.flatnonzero(d["keep"])

    def target_rmse_um(p):
        return 1e3 * np.sqrt(np.mean([(p.imaging_depth(d["raw"][i]) - prof.depth_map(m.camera.grid)) ** 2
                                      for i, prof in zip(keep, profiles)]))

    fit_tuned, fit_design = target_rmse_um(pipe), target_rmse_um(design)
    presses = virtual_ball_presses(sensor, m.camera.grid, n_inside=8, n_edge=0, seed=31)
    e_tuned = near_contact_errors([pipe.frame_to_depth(f) for f in presses.frames], presses)
    print("RMSE to the rig presses' targets um, design / fine-tuned:", fit_design, fit_tuned,
          "new presses near the contact: mean", e_tuned["near"].mean(), "worst", e_tuned["near"].max())
    assert fit_tuned < 0.7 * fit_design                        # it learned its targets
    assert e_tuned["near"].mean() <= 20.0                     # the calibration's depth target


def test_wizard_writes_the_units_sensor_model_and_discrepancy_presses(wizard_run, sensor):
    """The last step: the unit's model in the plugin folder (its camera, E and nu) and rig
    presses in the measured format; ``discrepancy --sensor <plugin>`` runs on them."""
    from tactile_deploy.calibration.discrepancy.collect import load_collection_log
    from tactile_deploy.calibration.discrepancy.measured import load_measured
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.sensors.config import load_sensor_config

    folder, out, _, _ = wizard_run
    model = load_sensor_config(out / "sensor_model.json")
    plugin = SensorPlugin.load(out)
    assert model.optics.camera == plugin.manifest.camera
    assert model.material.E_mpa == pytest.approx(plugin.manifest.material.E_mpa)
    assert model.material.nu == pytest.approx(plugin.manifest.material.nu)
    presses = folder / "acme.calibration" / "discrepancy_presses.npz"
    data = load_measured(presses)
    log = load_collection_log(presses)
    assert data.n == len(log.recorded) == 16 and data.frames is not None
    assert data.depth_mm is not None and data.depth_mm.max() > 0.2
    assert all(data.known(i) for i in range(data.n)) and np.all(data.force_n > 0)
    assert log.noise_mm is not None and 0 < log.noise_mm < 0.02
    res = CliRunner().invoke(app, ["discrepancy", "--sensor", str(out), "--measured",
                                   str(presses), "--candidates", "zero_offset,dome,tilt",
                                   "--null-replicates", "40", "--folds", "4", "--json"])
    assert res.exit_code == 0, res.output
    verdict = json.loads(res.stdout)
    print(verdict["message"])
    assert verdict["sensor"] == "acme" and verdict["n_samples"] == 16
