"""``tactile-deploy adapt`` end to end on the shipped gelslim2 plugin's frames (a copy of the
plugin), with the committed adaptation step of the committed family model: a new version only
when the held-out error improves, the adapted plugin runs in ``tactile-deploy run``, rollback;
and a clear message without torch."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from typer.testing import CliRunner  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
STEP = ROOT / "exported" / "gelslim_mesh_adapt"


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture()
def plugin_copy(tmp_path):
    """The shipped gelslim2 plugin copied (without adapted versions), pointing at the family model."""
    if not (STEP / "card.json").is_file():
        pytest.fail(f"{STEP} is missing: export it with `python -m tactile_deploy.training export-adapt --bundle MODEL.pt` "
                    "for the committed exported/gelslim_mesh.onnx")
    from tactile_deploy.runtime.plugins import copy_plugin

    folder = copy_plugin(ROOT / "plugins" / "gelslim2", tmp_path / "gelslim2")
    return folder


def _adapt(folder, *extra):
    from tactile_deploy.cli.main import app

    return CliRunner().invoke(app, ["adapt", "--sensor", str(folder), "--source", "demo", "--batch", "8",
                                    "--step", str(STEP), "--threads", "1", *extra])


def test_adapt_writes_a_version_that_runs_and_rolls_back(plugin_copy, tmp_path):
    from tactile_deploy.cli.main import app
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin
    from tactile_deploy.runtime.predictor import MeshPredictor

    manifest = (plugin_copy / "plugin.json").read_bytes()
    res = _adapt(plugin_copy, "--steps", "6", "--lr", "3e-5")  # lr 1e-4 at batch 8 oscillates over a few steps
    assert res.exit_code == 0, res.output
    assert "held-out label-free RMSE" in res.output and "new version 1" in res.output, res.output
    from tactile_deploy.adapt.report import AdaptationReportError, load_adaptation_report

    report_path = plugin_copy / "adapted" / "v1" / "report.json"
    report = load_adaptation_report(report_path)  # the format's reader: the writer built it through the model
    assert report.heldout_rmse_after_mm < report.heldout_rmse_before_mm
    assert (report.frames.adapt, report.frames.held_out) == (50, 10)
    assert report.parity_fp32_onnx_vs_step_max_abs_diff_mm <= 1e-4
    assert report.improved and report.verdict == "improved" and report.source.frames == 60
    # the reader refuses what the format does not hold, naming the file, the field and the value
    doc = json.loads(report_path.read_text())
    for key, value, words in ((("frames", "held_out"), 0, ("frames.held_out", "greater than or equal to 1", "0")),
                              (("settings", "optimiser"), "sgd", ("settings.optimiser", "Extra inputs", "sgd"))):
        bad = json.loads(json.dumps(doc))
        bad[key[0]][key[1]] = value
        (tmp_path / "report.json").write_text(json.dumps(bad))
        with pytest.raises(AdaptationReportError) as err:
            load_adaptation_report(tmp_path / "report.json")
        assert str(tmp_path / "report.json") in str(err.value), err.value
        assert all(w in str(err.value) for w in words), err.value
    assert (plugin_copy / "adapted" / "v1" / "adaptation.png").stat().st_size > 10_000
    plugin = SensorPlugin.load(plugin_copy)
    assert (plugin_copy / "plugin.json").read_bytes() == manifest  # the plugin's own files stay as shipped
    assert plugin.adapted_model_path() == (plugin_copy / "adapted" / "v1" / "model.onnx").resolve()
    assert validate_plugin(plugin_copy).ok
    predictor = MeshPredictor.from_plugin(plugin_copy)
    assert predictor.model_path == (plugin_copy / "adapted" / "v1" / "model.onnx").resolve()
    assert predictor.metadata["adapted"] == "true"
    run = CliRunner().invoke(app, ["run", "--sensor", str(plugin_copy), "--max-frames", "5", "--no-forces",
                                   "--out", str(tmp_path / "run"), "--format", "ply"])
    assert run.exit_code == 0, run.output
    assert json.loads((tmp_path / "run" / "run.json").read_text())["frames"] == 5
    back = CliRunner().invoke(app, ["adapt", "--sensor", str(plugin_copy), "--rollback"])
    assert back.exit_code == 0 and "the plugin's own model" in back.output
    assert SensorPlugin.load(plugin_copy).adapted_model_path() is None
    assert MeshPredictor.from_plugin(plugin_copy).model_path == (ROOT / "exported" / "gelslim_mesh.onnx").resolve()
    assert (plugin_copy / "adapted" / "v1" / "model.onnx").is_file()  # kept


def test_no_improvement_writes_nothing(plugin_copy):
    """lr 0: the weights cannot change, so the held-out error cannot improve."""
    before = (plugin_copy / "plugin.json").read_text()
    res = _adapt(plugin_copy, "--steps", "2", "--lr", "0")
    assert res.exit_code == 0, res.output
    assert "keeps its current model" in res.output
    assert (plugin_copy / "plugin.json").read_text() == before
    assert not (plugin_copy / "adapted" / "v1").exists()


def test_without_torch_the_message_says_what_to_install(plugin_copy):
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None
        from tactile_deploy.cli.main import main
        sys.argv = ["tactile-deploy", "adapt", "--sensor", {str(plugin_copy)!r}, "--steps", "1"]
        main()
        """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=120,
                         env={**os.environ, "COLUMNS": "200"})
    assert res.returncode == 2, res.stderr[-2000:]
    assert "pip install 'tactile-deploy[adapt]'" in res.stderr


def test_the_committed_step_belongs_to_the_shipped_model():
    """The committed step was exported from the shipped bundle for the shipped ONNX model (sha256
    of both), every trainable tensor has its initializer in the shipped fp32 graph, and the
    program's meshes equal the shipped fp32 graph's (onnxruntime) on virtual-sensor-like maps."""
    import numpy as np

    from tactile_deploy.adapt.step import StepProgram
    from tactile_deploy.checksums import file_sha256
    from tactile_deploy.onnx_runtime.session import make_session

    step = StepProgram.load(STEP)
    card = step.card
    for key, path in (("family_model", "gelslim_mesh.onnx"), ("fp32_model", "gelslim_mesh_fp32.onnx"),
                      ("source_bundle", "gelslim_mesh.pt")):
        assert card.path(STEP, key) == (ROOT / "exported" / path).resolve()
        assert card.files[key].sha256 == file_sha256(ROOT / "exported" / path), key
    assert sorted(m.parameter for m in card.parameter_map) == sorted(card.trainable)
    assert len({m.initializer for m in card.parameter_map}) == len(card.trainable)
    c = -17.5 + (np.arange(128) + 0.5) * 35 / 128
    x, y = np.meshgrid(c, -c)
    depth = np.stack([a * np.exp(-((x - u) ** 2 + (y - v) ** 2) / (2 * r * r)) for a, u, v, r in
                      ((0.8, 2.0, -3.0, 3.0), (0.4, -6.0, 4.0, 2.0), (1.1, 0.0, 0.0, 4.5))]).astype(np.float32)
    disp = step(depth, np.zeros_like(depth), np.ones((128, 128), np.float32))[3].detach().numpy()
    onnx_disp = make_session(card.path(STEP, "fp32_model"), providers="cpu").run(
        ["displacement"], {"depth": depth[:, None]})[0]
    assert np.abs(disp).max() > 0.1  # the maps move the mesh ...
    assert np.abs(disp - onnx_disp).max() < 1e-4  # ... as the shipped graph does


def test_device_benchmark_runs_with_only_torch_numpy_onnx_onnxruntime_pydantic(tmp_path):
    """bench/bench_adapt_device.py (the GPU machine's script) in a process where every other
    library of the project cannot be imported."""
    blocked = ["trimesh", "warp", "cv2", "typer", "rich", "questionary", "matplotlib", "meshio", "zmq", "serial",
               "pexpect", "tactile_deploy.training", "scipy"]
    script = textwrap.dedent(f"""
        import runpy, sys
        for m in {blocked!r}:
            sys.modules[m] = None
        sys.argv = ["bench_adapt_device.py", "--device", "cpu", "--out", {str(tmp_path / "r.json")!r},
                    "--steps", "2", "--repeat", "1", "--frames", "10", "--batch", "4", "--threads", "1"]
        runpy.run_path({str(ROOT / "bench" / "bench_adapt_device.py")!r}, run_name="__main__")
        """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["device"] == "cpu" and result["batch"] == 4 and result["adapt"]["steps"] == 2
    assert result["step"]["steps_per_s"] > 0 and result["adapt"]["heldout_rmse_before_mm"] > 0


def test_benchmark_runs_at_small_settings(capsys):
    sys.path.insert(0, str(ROOT))
    try:
        from bench.bench_adapt import main
    finally:
        sys.path.remove(str(ROOT))
    assert main(["--small", "--no-write", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "steps/s" in out and "adapt on 30 frames" in out
