"""From a folder of real GelSight ball presses to meshes, in the two commands users type:

    tactile-deploy calibrate --sensor NAME --pad gelsight_mini --presses DIR --annotations CSV \
        --ball-radius-mm 2.35 --mm-per-px 0.05107 --plugins-dir DIR --yes
    tactile-deploy run --sensor NAME --plugins-dir DIR --source DIR --format npz --out OUT

calibrated on the odd-numbered presses of ../shared/data/real/fots_gelsight_ballpress, run on the
even-numbered ones (never seen by the calibration). Inside each held-out contact the mesh's
sensing surface must be the ball: a sphere of the ball's radius fitted to the displaced sensing
nodes within 0.8 contact radii (hand-labelled circles) has an RMS error <= 25 um on average and
the sphere with a free radius is within 5 % of the ball's on every press. Then every plausibility
error of the one-command calibration, on the same data."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.cli.main import app

runner = CliRunner()
BALL_MM = 2.35
MM_PER_PX = 1 / 19.58


@pytest.fixture(autouse=True)
def _plugin_path_restored():
    """`--plugins-dir` puts folders on $TACTILE_DEPLOY_PLUGIN_PATH for the process: restore it
    after each test, so that no other test finds these plugins."""
    import os

    old = os.environ.get("TACTILE_DEPLOY_PLUGIN_PATH")
    yield
    if old is None:
        os.environ.pop("TACTILE_DEPLOY_PLUGIN_PATH", None)
    else:
        os.environ["TACTILE_DEPLOY_PLUGIN_PATH"] = old


@pytest.fixture(scope="module")
def presses(shared_data) -> Path:
    folder = shared_data / "real" / "fots_gelsight_ballpress"
    assert (folder / "annotate.csv").is_file(), f"{folder}: the real ball presses are missing"
    return folder


def _labels(presses: Path) -> dict[str, list[float]]:
    with open(presses / "annotate.csv", newline="") as f:
        return {r["img_names"]: [float(r["center_x"]), float(r["center_y"]), float(r["radius"])]
                for r in csv.DictReader(f)}


def _clean_error(res) -> str:
    assert res.exit_code == 2, res.output
    assert "error:" in res.output and "Traceback" not in res.output, res.output
    return " ".join(res.output.split())


@pytest.fixture(scope="module")
def real_run(presses, tmp_path_factory, private_cache):
    """Calibrate on the odd presses (one command), run on the even ones (one command)."""
    import os

    tmp = tmp_path_factory.mktemp("real")
    # the folder of plugins does not exist yet: calibrate makes it (a user's first plugin)
    train, test, plugins, out = tmp / "train", tmp / "test", tmp / "my" / "plugins", tmp / "out"
    for d in (train, test):
        d.mkdir()
    labels = _labels(presses)
    shutil.copy(presses / "background.png", train / "background.png")
    rows = ["img_names,center_x,center_y,radius"]
    for name, (cx, cy, r) in labels.items():
        if int(Path(name).stem) % 2:
            shutil.copy(presses / name, train / name)
            rows.append(f"{name},{cx},{cy},{r}")
        else:
            shutil.copy(presses / name, test / name)
    (train / "annotate.csv").write_text("\n".join(rows) + "\n")
    old = os.environ.get("TACTILE_DEPLOY_PLUGIN_PATH")
    cal = runner.invoke(app, ["calibrate", "--sensor", "mini1", "--pad", "gelsight_mini",
                              "--presses", str(train), "--annotations",
                              str(train / "annotate.csv"), "--ball-radius-mm", str(BALL_MM),
                              "--mm-per-px", str(MM_PER_PX), "--plugins-dir", str(plugins),
                              "--yes"])
    assert cal.exit_code == 0, cal.output
    run = runner.invoke(app, ["run", "--sensor", "mini1", "--plugins-dir", str(plugins),
                              "--source", str(test), "--format", "npz", "--out", str(out)])
    if old is None:
        os.environ.pop("TACTILE_DEPLOY_PLUGIN_PATH", None)
    else:
        os.environ["TACTILE_DEPLOY_PLUGIN_PATH"] = old
    assert run.exit_code == 0, run.output
    return {"calibrate": cal.output, "run": run.output, "plugin": plugins / "mini1", "out": out,
            "labels": labels}


@pytest.mark.slow
def test_one_command_makes_a_plugin_without_a_learned_model(real_run):
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin

    text = " ".join(real_run["calibrate"].split())
    assert "background.png (picked" in text            # the no-contact frame of the recording
    assert "rows run along +x" in text                  # portrait frames on a landscape area
    assert "held-out shape error mean" in text
    assert "depth at its edge is carried 1 mm past it" in text   # the Mini's grid: 1.13 mm unseen
    report = validate_plugin(real_run["plugin"])
    assert report.ok, report.problems
    plugin = SensorPlugin.load(real_run["plugin"])
    assert plugin.manifest.model is None and plugin.manifest.family.pad == "gelsight_mini"
    assert plugin.manifest.reference_range is not None
    assert not [p for p in real_run["plugin"].parent.iterdir() if p.name.startswith(".")]
    run_text = " ".join(real_run["run"].split())
    assert "no learned model" in run_text and "physics lift" in run_text


def test_held_out_meshes_are_the_ball_inside_each_contact(real_run):
    from tactile_deploy.calibration.recording.mesh_check import circles_to_sensor_mm, press_mesh_fit
    from tactile_deploy.runtime.plugins import SensorPlugin

    import json

    from tactile_deploy.runtime.predictor import MeshTopology

    camera = SensorPlugin.load(real_run["plugin"]).manifest.camera
    sensing = MeshTopology.from_pad("gelsight_mini").sensing_nodes
    out = real_run["out"]
    with open(out / "frames.csv", newline="") as f:
        frames = list(csv.DictReader(f))
    assert len(frames) == 21
    fits = []
    for row in frames:
        name = Path(row["source_label"]).name
        z = np.load(out / f"mesh_{int(row['frame_index']):06d}.npz")
        assert z["vertices"].shape == z["rest_vertices"].shape == (10716, 3)
        assert z["depth"].shape == (96, 124)                    # the family's depth grid
        assert json.loads(str(z["metadata"]))["depth_grid_mm"]["nx"] == 124
        centre, radius = circles_to_sensor_mm(np.array([real_run["labels"][name]]), camera)
        fits.append(press_mesh_fit(name, z["vertices"], z["rest_vertices"], sensing,
                                   centre[0], radius[0], BALL_MM))
    shape = np.array([f.shape_um for f in fits])
    radius_err = np.array([f.radius_error for f in fits])
    print(f"\nmesh sphere fits, 21 held-out real presses: shape {shape.mean():.1f} um mean, "
          f"{shape.max():.1f} worst; free radius {100 * radius_err.mean():+.1f} % mean, "
          f"{100 * np.abs(radius_err).max():.1f} % worst")
    assert shape.mean() <= 25.0
    assert np.abs(radius_err).max() <= 0.05


# --------------------------------------------------------------------------- plausibility errors
def _calibrate(presses: Path, tmp_path: Path, *extra: str, radius: str = str(BALL_MM),
               annotations: Path | None = None):
    args = ["calibrate", "--sensor", "x1", "--pad", "gelsight_mini", "--presses", str(presses),
            "--ball-radius-mm", radius, "--plugins-dir", str(tmp_path), "--yes", *extra]
    if annotations is not None:
        args += ["--annotations", str(annotations)]
    res = runner.invoke(app, args)
    assert not (tmp_path / "x1").exists()             # nothing written, nothing half-written
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    return res


def test_diameter_given_as_radius(presses, tmp_path):
    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", str(MM_PER_PX),
                                   radius="4.7", annotations=presses / "annotate.csv"))
    assert "DIAMETER" in text and "--ball-radius-mm 2.35" in text and "--shallow-presses" in text


def test_radius_in_micrometres_and_too_small(presses, tmp_path):
    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", str(MM_PER_PX),
                                   radius="2350", annotations=presses / "annotate.csv"))
    assert "micrometres" in text and "um deep" in text
    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", str(MM_PER_PX),
                                   radius="1.5", annotations=presses / "annotate.csv"))
    assert "larger than the ball" in text


def test_swapped_annotation_axes(presses, tmp_path):
    swapped = tmp_path / "swapped.csv"
    lines = ["img_names,center_x,center_y,radius"]
    lines += [f"{n},{cy},{cx},{r}" for n, (cx, cy, r) in _labels(presses).items()]
    swapped.write_text("\n".join(lines) + "\n")
    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", str(MM_PER_PX),
                                   annotations=swapped))
    assert "swap the two columns" in text


def test_readout_of_another_design(presses, tmp_path):
    from tactile_deploy.shipped import model_path

    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", str(MM_PER_PX), "--readout",
                                   str(model_path("digit_readout.onnx")),
                                   annotations=presses / "annotate.csv"))
    assert "design 'digit'" in text and "not --pad 'gelsight_mini'" in text
    assert "exported/gelsight_mini_readout.onnx" in text and "leave --readout out" in text
    text = _clean_error(_calibrate(presses, tmp_path, "--readout", str(tmp_path / "none.onnx"),
                                   annotations=presses / "annotate.csv"))
    assert "--readout" in text and "none.onnx" in text and "not found" in text


def test_reference_with_a_contact(presses, tmp_path):
    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", str(MM_PER_PX),
                                   "--reference", str(presses / "0007.png")))
    assert "0007.png" in text and "shows a contact" in text


def test_no_frame_without_contact(presses, tmp_path):
    folder = tmp_path / "only_presses"
    folder.mkdir()
    for name in list(_labels(presses))[:6]:
        shutil.copy(presses / name, folder / name)
    text = _clean_error(_calibrate(folder, tmp_path, "--mm-per-px", str(MM_PER_PX)))
    assert "no frame without contact" in text and "--reference" in text


def test_greyscale_frames(presses, tmp_path):
    folder = tmp_path / "grey"
    folder.mkdir()
    for name in ["background.png", *list(_labels(presses))[:5]]:
        grey = cv2.cvtColor(cv2.imread(str(presses / name)), cv2.COLOR_BGR2GRAY)
        cv2.imwrite(str(folder / name), grey)
    text = _clean_error(_calibrate(folder, tmp_path, "--mm-per-px", str(MM_PER_PX)))
    assert "greyscale" in text and "RGB" in text


def test_view_edge_extension_is_the_unseen_strip_at_most_a_millimetre():
    from tactile_deploy.calibration.recording.checks import VIEW_EDGE_EXTENSION_MAX_MM, view_edge_extension
    from tactile_deploy.imaging.camera_mapping import OutputGrid

    depth_grid = OutputGrid(x_min_mm=-9.3, x_max_mm=9.3, y_min_mm=-7.2, y_max_mm=7.2, nx=124, ny=96)
    view = OutputGrid(x_min_mm=-9.0, x_max_mm=9.1, y_min_mm=-6.6, y_max_mm=6.7, nx=66, ny=48)
    ext, notes = view_edge_extension(view, depth_grid)
    assert ext == pytest.approx(0.6) and notes == ["the view leaves up to 0.60 mm of the depth grid unseen "
                                                   "along a side; the depth at its edge is carried across it"]
    assert view_edge_extension(depth_grid, depth_grid) == (0.0, [])
    small = OutputGrid(x_min_mm=-6.0, x_max_mm=6.0, y_min_mm=-6.0, y_max_mm=6.0, nx=44, ny=44)
    ext, notes = view_edge_extension(small, depth_grid)
    assert ext == VIEW_EDGE_EXTENSION_MAX_MM == 1.0
    assert "up to 3.30 mm of the depth grid unseen" in notes[0] and "1 mm past it" in notes[0]


def test_scale_that_does_not_fit(presses, tmp_path):
    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", "0.2",
                                   annotations=presses / "annotate.csv"))
    assert "more than the whole gelsight_mini gel" in text and "mm per px" in text
    text = _clean_error(_calibrate(presses, tmp_path, "--mm-per-px", "0.004",
                                   annotations=presses / "annotate.csv"))
    assert "too small" in text or "um deep" in text


def test_drift_beyond_the_calibration_is_reported():
    from tactile_deploy.runtime.drift import DriftMonitor, ReferenceRange

    rng = np.random.default_rng(0)
    ref = rng.integers(60, 200, (60, 80, 3)).astype(np.uint8)
    monitor = DriftMonitor(ReferenceRange(offset_grey_max=(5.0, 4.0, 6.0), residual_grey_max=1.0,
                                          n_frames=10), ref, sensor="mini1", every=1)
    assert monitor.check(ref) is None
    bright = np.clip(ref.astype(int) + [30, 0, 0], 0, 255).astype(np.uint8)
    message = monitor.check(bright, 12)
    assert "frame 12" in message and "tactile-deploy reference --sensor mini1" in message
    assert monitor.check(bright) is None                # said once
    assert "back within" in monitor.check(ref)


def test_reference_retakes_the_no_contact_frame(real_run, presses, tmp_path):
    """`tactile-deploy reference` averages no-contact frames into a new reference (the plugin is
    switched over in one manifest write and still validates), and refuses frames with a contact."""
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin

    plugins = tmp_path / "plugins"
    shutil.copytree(real_run["plugin"], plugins / "mini1")
    frames = tmp_path / "nocontact"
    frames.mkdir()
    bg = cv2.imread(str(presses / "background.png")).astype(int)
    for i in range(3):   # the LEDs brightened: +20 grey levels of red, camera noise
        noisy = bg + [0, 0, 20] + np.random.default_rng(i).normal(0, 1.5, bg.shape)
        cv2.imwrite(str(frames / f"{i}.png"), np.clip(noisy, 0, 255).astype(np.uint8))
    before = SensorPlugin.load(plugins / "mini1").manifest.reference_frame.path
    args = ["reference", "--sensor", "mini1", "--plugins-dir", str(plugins), "--source",
            str(frames), "--frames", "3"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "+20" in " ".join(res.output.split()).replace("+19", "+20")
    plugin = SensorPlugin.load(plugins / "mini1")
    assert plugin.manifest.reference_frame.path != before
    assert "reference_retaken" in plugin.manifest.provenance
    assert validate_plugin(plugins / "mini1").ok
    assert np.abs(plugin.reference_frame.astype(int) - bg[..., ::-1]).mean() == pytest.approx(
        20 / 3, abs=0.5)
    shutil.copy(presses / "0011.png", frames / "3.png")      # a ball on the gel
    text = _clean_error(runner.invoke(app, [*args[:-1], "4"]))
    assert "something touches the sensor" in text


def test_run_refuses_a_learned_mesh_without_a_model_and_a_missing_plugins_dir(real_run, tmp_path):
    plugins = str(real_run["plugin"].parent)
    text = _clean_error(runner.invoke(app, ["run", "--sensor", "mini1", "--plugins-dir", plugins,
                                            "--mesh", "learned", "--max-frames", "1"]))
    assert "no learned model" in text and "--mesh physics" in text
    text = _clean_error(runner.invoke(app, ["run", "--sensor", "mini1", "--plugins-dir",
                                            str(tmp_path / "nowhere")]))
    assert "--plugins-dir" in text and "not found" in text
    text = _clean_error(runner.invoke(app, ["run", "--sensor", "mini1", "--plugins-dir", plugins,
                                            "--mesh", "magic"]))
    assert "learned, physics" in text
