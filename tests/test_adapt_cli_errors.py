"""``tactile-deploy adapt`` on a copy of the shipped gelslim2 plugin: what it judges with (the model
``run`` uses, against the start and the active model), the checks made before frames are
collected, rollback and ``--activate`` over damaged or incomplete versions, and its messages
for user mistakes (one ``error:`` line naming the value)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from test_adapt_cli import ROOT, STEP, _adapt, plugin_copy  # noqa: F401 (plugin_copy: a fixture)
from typer.testing import CliRunner

pytestmark = pytest.mark.usefixtures("one_torch_thread")

FAMILY = ROOT / "exported" / "gelslim_mesh.onnx"
FAMILY_FP32 = ROOT / "exported" / "gelslim_mesh_fp32.onnx"
RECORD = {"created": "2026-01-01T00:00:00+00:00", "heldout_rmse_before_mm": 0.02, "heldout_rmse_after_mm": 0.01,
          "summary": "test"}


def _cli(*args):
    """The result, and its output on one line each message (no wrapping)."""
    from tactile_deploy.cli import common
    from tactile_deploy.cli.main import app

    consoles = (common.console, common.err_console)
    widths = [c._width for c in consoles]
    for c in consoles:
        c.width = 10_000
    try:
        res = CliRunner().invoke(app, [str(a) for a in args])
    finally:
        for c, w in zip(consoles, widths):
            c._width = w
    return res, " ".join(res.output.split())


def _version(folder, model=FAMILY):
    """A version made by copying ``model`` (no adaptation), made active."""
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.runtime.plugins.versions import add_version, staging_folder

    plugin = SensorPlugin.load(folder)
    stage = staging_folder(plugin)
    shutil.copy(model, stage / "model.onnx")
    return add_version(plugin, stage, RECORD).version


def _history(folder) -> dict:
    return json.loads((folder / "adapted" / "history.json").read_text())


def _edit_history(folder, **fields) -> None:
    doc = _history(folder)
    doc.update(fields)
    (folder / "adapted" / "history.json").write_text(json.dumps(doc))


def _one_error(res, text) -> None:
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    assert text.count("error:") == 1 and "Traceback" not in text, text


def test_the_gate_judges_the_written_model_against_the_start_and_the_active_one(plugin_copy):
    """The figures that decide and that are printed are those of model.onnx (int8, as `run` uses
    it), computed independently here; a --from-family run worse than the active version writes
    nothing and says so with both figures."""
    from tactile_deploy.adapt.step import StepProgram, adaptation_target, evaluate
    from tactile_deploy.adapt.workflow import (
        collect_depths,
        evaluate_model,
        split_blocks,
        view_weight,
    )
    from tactile_deploy.pad.asset import load_pad
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.runtime.sources.config import parse_source

    res = _adapt(plugin_copy, "--steps", "6", "--lr", "3e-5")
    assert res.exit_code == 0 and "new version 1" in res.output, res.output
    from tactile_deploy.adapt.report import load_adaptation_report

    report = load_adaptation_report(plugin_copy / "adapted" / "v1" / "report.json").model_dump()
    plugin = SensorPlugin.load(plugin_copy)
    depth, _ = collect_depths(plugin, parse_source("demo"), max_frames=200, log=lambda m: None)
    step = StepProgram.load(STEP)
    _, ho = split_blocks(len(depth), 0.2, 10, 0)
    assert report["settings"]["use_filter"] is False  # the shipped surface-anchored graph: towards the map itself
    t, _ = adaptation_target(step, depth[ho])  # the design's default
    d, w, pad = depth[ho], view_weight(plugin), load_pad()
    family = evaluate_model(FAMILY, pad, d, t, w)
    adapted = evaluate_model(plugin_copy / "adapted" / "v1" / "model.onnx", pad, d, t, w)
    assert report["heldout_rmse_before_mm"] == pytest.approx(family.rmse_mm, abs=1e-9)
    assert report["heldout_rmse_after_mm"] == pytest.approx(adapted.rmse_mm, abs=1e-9)
    assert report["int8"] and report["int8_vs_fp32_max_abs_diff_mm"] > 0
    # the fp32 figure of the report is the step's; the depth camera gives the step's figure
    assert evaluate_model(FAMILY_FP32, pad, d, t, w).rmse_mm == pytest.approx(evaluate(step, d, t, w).rmse_mm, abs=1e-4)
    assert report["heldout_rmse_before_fp32_mm"] == pytest.approx(evaluate(step, d, t, w).rmse_mm, abs=1e-7)
    # int8 differs (the shipped graph quantises only its lateral lift, which the rendered depth
    # barely sees; figures of one model agree to 1e-9, see above)
    assert abs(report["heldout_rmse_before_fp32_mm"] - report["heldout_rmse_before_mm"]) > 1e-7
    out = " ".join(res.output.split())
    assert f"{family.rmse_mm * 1e3:.2f} um (family model) -> {adapted.rmse_mm * 1e3:.2f} um" in out
    assert f"worst {report['int8_vs_fp32_max_abs_diff_mm'] * 1e3:.1f} um" in out

    history = (plugin_copy / "adapted" / "history.json").read_bytes()
    res = _adapt(plugin_copy, "--steps", "2", "--lr", "3e-5", "--from-family")
    out = " ".join(res.output.split())
    assert res.exit_code == 0, res.output
    assert f"not better than the active adapted model v1 ({adapted.rmse_mm * 1e3:.2f} um)" in out, out
    assert f"{family.rmse_mm * 1e3:.2f} um (family model)" in out  # it did improve on the family model
    assert (plugin_copy / "adapted" / "history.json").read_bytes() == history
    assert not (plugin_copy / "adapted" / "v2").exists()


def test_too_few_held_out_frames_are_refused_with_how_many_to_collect(plugin_copy):
    res, out = _cli("adapt", "--sensor", plugin_copy, "--source", "demo", "--max-frames", "9", "--steps", "1",
                    "--step", STEP, "--threads", "1")
    _one_error(res, out)
    assert "only 2 of the 9 frames would be held out" in out and "--max-frames 20" in out, out
    assert not (plugin_copy / "adapted").exists()


def test_rollback_skips_a_version_that_lost_its_model(plugin_copy):
    for _ in range(3):
        _version(plugin_copy)
    (plugin_copy / "adapted" / "v2" / "model.onnx").unlink()
    res, out = _cli("adapt", "--sensor", plugin_copy, "--rollback")
    assert res.exit_code == 0, out
    assert "warning: version 2 of plugin 'gelslim2' lost its model file adapted/v2/model.onnx: skipped" in out, out
    assert "version 3 -> version 1" in out
    assert _history(plugin_copy)["active"] == 1 and _history(plugin_copy)["previous"] == [None]
    res, out = _cli("adapt", "--sensor", plugin_copy, "--rollback")
    assert res.exit_code == 0 and "version 1 -> the plugin's own model" in out, out


@pytest.mark.parametrize("fields, field", [({"active": 7}, "field 'active' names version 7"),
                                           ({"previous": [None, 5]}, "field 'previous' names version 5")])
def test_a_history_naming_unlisted_versions_is_refused_cleanly(plugin_copy, tmp_path, fields, field):
    _version(plugin_copy)
    _edit_history(plugin_copy, **fields)
    for args in (["run", "--sensor", plugin_copy, "--max-frames", "2", "--no-forces", "--out", tmp_path / "run"],
                 ["adapt", "--sensor", plugin_copy, "--rollback"]):
        res, out = _cli(*args)
        _one_error(res, out)
        assert "history.json: not a valid adaptation history" in out and field in out, out
        assert "restore it from a backup or correct it" in out


def test_a_truncated_history_names_the_file_and_the_way_out(plugin_copy):
    _version(plugin_copy)
    path = plugin_copy / "adapted" / "history.json"
    path.write_text(path.read_text()[:80])
    res, out = _cli("adapt", "--sensor", plugin_copy, "--rollback")
    _one_error(res, out)
    assert f"{path}: not valid JSON (line" in out and "restore it from a backup" in out, out


def test_a_missing_frames_folder_gives_one_error(plugin_copy, tmp_path):
    res, out = _cli("adapt", "--sensor", plugin_copy, "--frames", tmp_path / "missing")
    _one_error(res, out)
    assert "is not a folder of images" in out and "error: 2" not in out


def test_rollback_and_activate_dry_runs_write_nothing(plugin_copy):
    _version(plugin_copy)
    _version(plugin_copy)
    before = (plugin_copy / "adapted" / "history.json").read_bytes()
    res, out = _cli("adapt", "--sensor", plugin_copy, "--rollback", "--dry-run")
    assert res.exit_code == 0 and "would go version 2 -> version 1; nothing written" in out, out
    res, out = _cli("adapt", "--sensor", plugin_copy, "--activate", "1", "--dry-run")
    assert res.exit_code == 0 and "would go version 2 -> version 1" in out, out
    assert (plugin_copy / "adapted" / "history.json").read_bytes() == before


@pytest.mark.parametrize("case", ["history", "step", "cuda", "cuda:abc", "read-only"])
def test_checks_that_need_no_frames_come_before_collecting_them(plugin_copy, tmp_path, monkeypatch, case):
    """An empty --frames folder would stop the collection: each check must speak first."""
    import torch

    empty = tmp_path / "empty"
    empty.mkdir()
    args = ["adapt", "--sensor", plugin_copy, "--frames", empty, "--steps", "1", "--threads", "1", "--step", STEP]
    if case == "history":
        _version(plugin_copy)
        _edit_history(plugin_copy, active=4)
        expect = "field 'active' names version 4"
    elif case == "step":
        args[-1], expect = tmp_path / "no_step", "no_step"
    elif case == "cuda":
        monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # as on a machine without CUDA
        args += ["--device", "cuda"]
        expect = "this torch has no CUDA device"
    elif case == "cuda:abc":
        args += ["--device", "cuda:abc"]
        expect = "--device must be cpu, cuda or cuda:N (N: the index of a CUDA device), got 'cuda:abc'"
    else:
        from tactile_deploy.runtime.plugins import versions

        real = versions.os.access  # root writes anywhere: the plugin folder says it is read-only
        monkeypatch.setattr(versions.os, "access", lambda path, mode, **k: Path(path) != plugin_copy and real(path, mode, **k))
        expect = "cannot write adapted versions into"
    res, out = _cli(*args)
    _one_error(res, out)
    assert expect in out and "no image files" not in out, out


def test_a_camera_refusing_every_frame_stops(plugin_copy, monkeypatch):
    from tactile_deploy.adapt import workflow
    from tactile_deploy.adapt.workflow import collect_depths
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.runtime.sources.base import Frame

    class Camera:  # live, endless, frames of the wrong size
        name, finite, index = "camera 0", False, 0

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def read(self):
            if self.index >= 200:  # a test that never ends proves nothing
                return None
            self.index += 1
            return Frame(image=np.zeros((7, 9, 3), np.uint8), index=self.index, t_wall_ns=0, t_mono_ns=0)

    camera = Camera()
    monkeypatch.setattr(workflow, "make_source", lambda *a, **k: camera)
    logged = []
    with pytest.raises(ValueError, match="camera 0: 50 frames in a row were refused by the imaging pipeline"):
        collect_depths(SensorPlugin.load(plugin_copy), None, max_frames=40, log=logged.append)
    assert camera.index == 50 and len(logged) == 3


def test_hints_name_a_sensor_that_works_from_any_folder(plugin_copy, monkeypatch):
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin

    _version(plugin_copy)
    _version(plugin_copy)
    monkeypatch.chdir(plugin_copy.parent)
    res, out = _cli("adapt", "--sensor", "./gelslim2", "--rollback")
    assert res.exit_code == 0, out
    assert f"`tactile-deploy adapt --sensor {plugin_copy.resolve()} --rollback`" in out, out
    with open(plugin_copy / "adapted" / "v1" / "model.onnx", "ab") as f:
        f.write(b"x")
    with pytest.raises(PluginError, match=re.escape(f"--sensor {plugin_copy.resolve()} --rollback")):
        SensorPlugin.load("./gelslim2").model_path()


def test_activate_makes_a_kept_version_active_and_rollback_returns(plugin_copy):
    for _ in range(2):
        _version(plugin_copy)
    res, out = _cli("adapt", "--sensor", plugin_copy, "--activate", "1")
    assert res.exit_code == 0 and "version 2 -> version 1" in out, out
    assert _history(plugin_copy)["active"] == 1 and _history(plugin_copy)["previous"] == [None, 1, 2]
    res, out = _cli("adapt", "--sensor", plugin_copy, "--rollback")
    assert res.exit_code == 0 and "version 1 -> version 2" in out, out
    res, out = _cli("adapt", "--sensor", plugin_copy, "--activate", "5")
    _one_error(res, out)
    assert "history.json lists no version 5 (kept versions: 1, 2)" in out, out
    with open(plugin_copy / "adapted" / "v1" / "model.onnx", "ab") as f:
        f.write(b"x")
    res, out = _cli("adapt", "--sensor", plugin_copy, "--activate", "1")
    _one_error(res, out)
    assert "version 1 of plugin 'gelslim2' model file adapted/v1/model.onnx no longer matches its sha256" in out
    doc = _history(plugin_copy)
    doc["versions"][1]["family_model_sha256"] = "0" * 64
    (plugin_copy / "adapted" / "history.json").write_text(json.dumps(doc))
    res, out = _cli("adapt", "--sensor", plugin_copy, "--activate", "2")
    _one_error(res, out)
    assert "was adapted from another family model" in out, out
    assert _history(plugin_copy)["active"] == 2


def test_an_interrupted_add_leaves_no_version_folder(plugin_copy, monkeypatch):
    from tactile_deploy.runtime.plugins import SensorPlugin, versions

    plugin = SensorPlugin.load(plugin_copy)
    stage = versions.staging_folder(plugin)
    shutil.copy(FAMILY, stage / "model.onnx")

    def no_space(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(versions, "write_json", no_space)
    with pytest.raises(OSError):
        versions.add_version(plugin, stage, RECORD)
    assert not (plugin_copy / "adapted" / "v1").exists() and (stage / "model.onnx").is_file()
    monkeypatch.undo()
    (plugin_copy / "adapted" / "v1").mkdir()  # an orphan, as a killed process may leave
    assert versions.add_version(plugin, stage, RECORD).version == 2
    import socket

    host = socket.gethostname()
    killed = plugin_copy / "adapted" / f".staging-{host}-{2 ** 22 + 1}"  # above Linux's largest pid
    killed.mkdir()
    elsewhere = plugin_copy / "adapted" / f".staging-another-host-{2 ** 22 + 1}"  # a shared folder
    elsewhere.mkdir()
    shutil.rmtree(versions.staging_folder(plugin))
    assert not killed.exists() and elsewhere.exists()
    assert _history(plugin_copy)["active"] == 2


@pytest.mark.parametrize("value", ["0", "1.5"])
def test_held_out_out_of_range_shows_the_value(plugin_copy, value):
    res, out = _cli("adapt", "--sensor", plugin_copy, "--held-out", value)
    _one_error(res, out)
    assert f"--held-out must be a share of the frames from 0.01 to 0.9, got {value}" in out, out


def test_a_model_without_an_adaptation_step_names_the_command_that_exports_one(tmp_path):
    """A plugin that runs the graph for gels that grip (no step shipped for it): `adapt` stops
    before collecting frames and names the export-adapt command with the model's bundle."""
    from tactile_deploy.runtime.plugins import copy_plugin

    grip = ROOT / "exported" / "gelslim_mesh_grip.onnx"
    folder = copy_plugin(ROOT / "plugins" / "gelslim2", tmp_path / "grip1", model=grip)
    res, out = _cli("adapt", "--sensor", folder, "--source", "demo", "--steps", "1", "--threads", "1")
    _one_error(res, out)
    flat = " ".join(out.split())
    assert "has no adaptation step" in flat and "gelslim_mesh_grip_adapt" in flat, out
    assert f"export-adapt --bundle {grip.with_suffix('.pt')} --onnx {grip}" in flat, out
    assert not (folder / "adapted").exists()
