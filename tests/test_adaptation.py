"""The exported adaptation step on a small untrained model: export and card, the runtime's
program against the eager module, recovery of a planted shift, the adapted ONNX model against
the adapted program, plugin versions and rollback."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxscript")

ROOT = Path(__file__).resolve().parent.parent
TINY = {
    "image": {"widths": [8, 16, 32, 64, 128], "hidden": 32, "latent": 32},
    "mesh": {"channels": [8, 8, 8, 16], "cheb_k": [3, 3, 3, 3], "latent": 32},
    "projection": {"hidden": [64, 128, 64]},
    "lean_decoder": {"channels": [16, 16, 8, 8]},
    "ood_decoder": {"channels": [8, 8, 8, 8, 4]},
}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A small untrained predictor, its bundle, its fp32 ONNX model and its exported adaptation
    step. Biases of the encoder, the projection and the mesh decoder are zeroed (a random
    network's output is otherwise a constant set by its biases; without them it is proportional
    to the input) and the decoder is scaled to dents of ~0.5 mm."""
    from tactile_deploy.onnx_runtime.contract import mesh_model_metadata
    from tactile_deploy.onnx_runtime.metadata import write_metadata
    from tactile_deploy.pad.asset import load_pad
    from tactile_deploy.training.adaptation.export import export_step
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.export import export_variant
    from tactile_deploy.training.train import BUNDLE_FORMAT, build_model, git_commit

    folder = tmp_path_factory.mktemp("tiny")
    cfg = TrainConfig.model_validate({"run_dir": str(folder), "model": TINY, "data": {"synthetic": {"n_samples": 2}}})
    torch.manual_seed(0)
    model = build_model(cfg)
    model.norm.set_scales(0.8, (0.3, 0.3, 0.3))
    model.eval()
    model.deploy_decoder = "lean"  # the decoder the step uses
    with torch.no_grad():
        for part in (model.image_vae.encoder, model.projection, model.lean_decoder):
            for name, p in part.named_parameters():
                if name.endswith("bias"):
                    p.zero_()
        # unit RMS activations layer by layer (a random net's signal otherwise fades away)
        x = torch.as_tensor(_maps(8, 9)[:, None])
        layers = [m for part in (model.image_vae.encoder, model.projection, model.lean_decoder)
                  for m in part.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d, torch.nn.Linear))]
        for layer in [m for m in layers if m is not model.image_vae.encoder.logvar]:
            seen = []
            handle = layer.register_forward_hook(lambda mod, inp, out: seen.append(float(out.pow(2).mean().sqrt())))
            model(x)
            handle.remove()
            layer.weight.div_(seen[0])
        peak = float(model(x)[1].abs().max())
        model.lean_decoder.net[-1].weight.mul_(0.5 / peak)
    bundle = {"format_version": BUNDLE_FORMAT, "config": cfg.model_dump(mode="json"), "state_dict": model.state_dict(),
              "mesh_hash": model.mesh_vae.graphs.hierarchy.mesh_hash, "metrics": {}, "history": {},
              "git": git_commit(), "created_unix": 0.0}
    torch.save(bundle, folder / "model.pt")
    onnx_path = folder / "tiny.onnx"
    export_variant(model, "lean-fastood", onnx_path, optimize=False)
    n_nodes = len(load_pad().vertices)
    write_metadata(onnx_path, mesh_model_metadata("gelslim_v1", bundle["mesh_hash"], n_nodes, 1.0)
                   | {"variant": "lean-fastood"}, replace=True)
    card = export_step(folder / "model.pt", onnx_path, folder / "tiny_adapt", log=lambda m: None)
    return {"folder": folder, "model": model, "onnx": onnx_path, "step": folder / "tiny_adapt", "card": card}


def _maps(n, seed):
    from tactile_deploy.training.adaptation.export import check_inputs

    rng = np.random.default_rng(seed)
    base = check_inputs(Path("/nonexistent/model.pt"), 64)[:, 0]
    return base[rng.permutation(64)[:n]]


def test_export_writes_a_complete_card(tiny):
    from tactile_deploy.adapt.card import load_card

    card = load_card(tiny["step"])
    assert card == tiny["card"]
    assert card.trainable and all(n.split(".")[0] in ("convs", "fc", "mu", "projection") for n in card.trainable)
    assert not any(n.startswith("decoder") for n in card.trainable)
    first = next(m for m in card.parameter_map if m.parameter == "convs.0.weight")
    assert first.scale == pytest.approx(1 / 0.8)  # 1 / depth_scale_mm folded by the ONNX export
    assert all(m.scale == 1.0 for m in card.parameter_map if m.parameter != "convs.0.weight")
    assert card.parity["fp32_onnx_vs_step_max_abs_diff_mm"] < 1e-5
    assert card.parity["rewritten_onnx_vs_step_max_abs_diff_mm"] < 1e-5
    change = card.parity["rewrite_check_displacement_change_mm"]  # the check moved the mesh ...
    assert change > 1e-4 and change > 1000 * card.parity["rewritten_onnx_vs_step_max_abs_diff_mm"]
    assert card.versions["torch"] == torch.__version__ and card.int8_nodes == []
    assert (tiny["step"] / "card.md").read_text().startswith("# Adaptation step")


def test_runtime_program_equals_the_eager_step(tiny):
    """Same loss and same gradients as the eager module built from the training code."""
    from tactile_deploy.adapt.step import StepProgram
    from tactile_deploy.training.adaptation.step import AdaptationStep

    program = StepProgram.load(tiny["step"])
    eager = AdaptationStep(tiny["model"]).train()
    depth = _maps(6, 0)
    target = depth * 0.7
    weight = eager.renderer.mask.flip(0).float()
    a = program(depth, target, weight.numpy())
    b = eager(torch.as_tensor(depth[:, None]), torch.as_tensor(target), weight)
    torch.testing.assert_close(a[0], b[0], rtol=1e-6, atol=1e-9)
    a[0].backward()
    b[0].backward()
    pa = dict(program.module.named_parameters())
    pb = dict(eager.named_parameters())
    for name in program.card.trainable:
        torch.testing.assert_close(pa[name].grad, pb[name].grad, rtol=1e-5, atol=1e-9)
    assert all(p.grad is None for n, p in pa.items() if n not in program.card.trainable)


def test_adaptation_recovers_a_planted_shift_and_the_onnx_model_follows(tmp_path):
    """On the committed step of the shipped model: targets rendered by the same network with
    planted weights after the encoder; Adam on the program brings the rendered maps and the meshes
    towards the planted ones, and the adapted ONNX model (the shipped fp32 graph with replaced
    initializers) gives the adapted program's meshes."""
    from tactile_deploy.adapt.step import AdaptSettings, StepProgram, adapt, evaluate
    from tactile_deploy.adapt.weights import read_adapted_weights, write_adapted_onnx
    from tactile_deploy.onnx_runtime.session import make_session

    program = StepProgram.load(ROOT / "exported" / "gelslim_mesh_adapt")
    depth = _maps(8, 1)
    weight = np.ones((128, 128), np.float32)
    start = program.weights()
    rng = np.random.default_rng(2)
    # the part after the encoder that the step trains: the latent projection, or the surface decoder
    part = "projection" if any(k.startswith("projection") for k in start) else "decoder."
    planted = {k: v + (rng.normal(0, 0.3 * v.std(), v.shape).astype(np.float32) if k.startswith(part) else 0)
               for k, v in start.items()}
    program.load_weights(planted)
    truth = evaluate(program, depth, np.zeros_like(depth), weight, keep=("rendered", "displacement"))
    program.load_weights(start)
    before = evaluate(program, depth, truth.rendered_mm, weight, keep=("displacement",))
    # the rendered depth sees the sensing surface (its first n_sensing nodes), not the interior
    k = program.card.n_sensing_nodes
    err_before = np.sqrt(np.mean((before.displacement_mm - truth.displacement_mm)[:, :k] ** 2))
    hist = adapt(program, depth, truth.rendered_mm, weight, AdaptSettings(steps=30, batch_size=8, lr=3e-4))
    after = evaluate(program, depth, truth.rendered_mm, weight, keep=("displacement",))
    err_after = np.sqrt(np.mean((after.displacement_mm - truth.displacement_mm)[:, :k] ** 2))
    assert before.rmse_mm > 0.01
    assert after.rmse_mm < 0.5 * before.rmse_mm, (before.rmse_mm, after.rmse_mm, hist.loss_mm2[::8])
    assert err_after < 0.7 * err_before
    # the adapted ONNX model == the adapted program; its weights read back == the program's
    fp32 = program.card.path(program.folder, "fp32_model")
    out = write_adapted_onnx(program.card, fp32, program.weights(), tmp_path / "adapted.onnx", {"adapted": "true"})
    session = make_session(out, providers="cpu")
    disp = session.run(["displacement"], {"depth": depth[:, None]})[0]
    assert np.abs(disp - after.displacement_mm).max() < 1e-5
    assert session.get_modelmeta().custom_metadata_map["mesh_hash"] == program.card.mesh_hash
    back = read_adapted_weights(program.card, out)
    for k, v in program.weights().items():
        np.testing.assert_allclose(back[k], v, rtol=1e-6, atol=1e-7)


@pytest.fixture()
def tiny_plugin(tiny, tmp_path):
    """A copy of the shipped gelslim2 plugin whose family model is the tiny one."""
    import sys

    from tactile_deploy.runtime.plugins import copy_plugin

    folder = copy_plugin(ROOT / "plugins" / "gelslim2", tmp_path / "gelslim2")
    sys.path.insert(0, str(ROOT / "plugins"))
    try:
        from build_shipped import relink_model
    finally:
        sys.path.remove(str(ROOT / "plugins"))
    relink_model(folder, tiny["onnx"])
    return folder


def test_versions_are_atomic_kept_and_rolled_back(tiny, tiny_plugin):
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin
    from tactile_deploy.runtime.plugins.versions import (
        add_version,
        load_history,
        rollback,
        staging_folder,
    )

    plugin = SensorPlugin.load(tiny_plugin)
    manifest = (tiny_plugin / "plugin.json").read_bytes()
    record = {"created": "2026-01-01T00:00:00+00:00", "heldout_rmse_before_mm": 0.2, "heldout_rmse_after_mm": 0.1,
              "summary": "test"}
    for k in range(2):
        stage = staging_folder(plugin)
        shutil.copy(tiny["onnx"], stage / "model.onnx")
        (stage / "note.txt").write_text(str(k))
        rec = add_version(plugin, stage, record)
        assert rec.version == k + 1 and not stage.exists()
    (tiny_plugin / "adapted" / "v3").mkdir()  # left by an interrupted run: never overwritten
    stage = staging_folder(plugin)
    shutil.copy(tiny["onnx"], stage / "model.onnx")
    assert add_version(plugin, stage, record).version == 4
    plugin = SensorPlugin.load(tiny_plugin)
    assert (tiny_plugin / "plugin.json").read_bytes() == manifest  # never rewritten

    def active():
        path = SensorPlugin.load(tiny_plugin).adapted_model_path()
        return None if path is None else path.relative_to(tiny_plugin.resolve()).as_posix()

    assert active() == "adapted/v4/model.onnx"
    assert validate_plugin(tiny_plugin).ok
    assert rollback(plugin) == (4, 2)
    assert active() == "adapted/v2/model.onnx"
    assert rollback(plugin) == (2, 1)
    assert rollback(plugin) == (1, None)
    assert active() is None
    with pytest.raises(ValueError, match="no earlier adapted version"):
        rollback(plugin)
    assert [v.version for v in load_history(plugin).versions] == [1, 2, 4]
    assert all((tiny_plugin / "adapted" / f"v{k}" / "model.onnx").is_file() for k in (1, 2, 4))


def test_a_version_of_another_family_model_is_not_used_and_a_changed_one_is_refused(tiny, tiny_plugin):
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin
    from tactile_deploy.runtime.plugins.versions import add_version, history_path, staging_folder

    plugin = SensorPlugin.load(tiny_plugin)
    stage = staging_folder(plugin)
    shutil.copy(tiny["onnx"], stage / "model.onnx")
    add_version(plugin, stage, {"created": "2026-01-01T00:00:00+00:00", "heldout_rmse_before_mm": 0.2,
                                "heldout_rmse_after_mm": 0.1, "summary": "test"})
    assert SensorPlugin.load(tiny_plugin).adapted_model_path() is not None
    doc = json.loads(history_path(plugin).read_text())
    doc["versions"][0]["family_model_sha256"] = "0" * 64  # as after the family model was replaced
    history_path(plugin).write_text(json.dumps(doc))
    assert SensorPlugin.load(tiny_plugin).adapted_model_path() is None
    assert SensorPlugin.load(tiny_plugin).model_path() == tiny["onnx"].resolve()
    doc["versions"][0]["family_model_sha256"] = plugin.manifest.model.sha256
    history_path(plugin).write_text(json.dumps(doc))
    with open(tiny_plugin / "adapted" / "v1" / "model.onnx", "ab") as f:
        f.write(b"x")
    with pytest.raises(PluginError, match="--rollback"):
        SensorPlugin.load(tiny_plugin).model_path()


def test_split_keeps_blocks_of_consecutive_frames_together():
    from tactile_deploy.adapt.workflow import split_blocks

    tr, ho = split_blocks(95, 0.2, 10, seed=0)
    assert len(np.intersect1d(tr, ho)) == 0 and len(tr) + len(ho) == 95
    assert set(np.unique(ho // 10)).isdisjoint(np.unique(tr // 10))
    assert 10 <= len(ho) <= 20
    tr, ho = split_blocks(5, 0.2, 10, seed=0)  # fewer frames than a block: single frames
    assert len(ho) == 1 and len(tr) == 4


def test_a_step_for_another_model_is_refused(tiny):
    from tactile_deploy.adapt.card import CardError
    from tactile_deploy.adapt.step import StepProgram

    program = StepProgram.load(tiny["step"])
    with pytest.raises(CardError, match="export the step for this model"):
        program.check_family_model(ROOT / "plugins" / "gelslim2" / "topology.npz")


def test_missing_torch_gives_the_install_command(monkeypatch):
    import builtins

    from tactile_deploy.adapt.step import require_torch
    from tactile_deploy.adapt.weights import AdaptationUnavailable

    real = builtins.__import__

    def no_torch(name, *args, **kwargs):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("No module named 'torch'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_torch)
    with pytest.raises(AdaptationUnavailable, match=r"pip install 'tactile-deploy\[adapt\]'"):
        require_torch()


def test_card_problems_name_the_file_and_field(tiny, tmp_path):
    from tactile_deploy.adapt.card import CardError, load_card

    with pytest.raises(CardError, match="export-adapt"):
        load_card(tmp_path)
    doc = json.loads((tiny["step"] / "card.json").read_text())
    doc["trainable"] = "all"
    (tmp_path / "card.json").write_text(json.dumps(doc))
    with pytest.raises(CardError, match="trainable"):
        load_card(tmp_path)


def test_program_moves_to_another_device_whole(tiny):
    """The program exported on the CPU runs on another device (here PyTorch's meta device, as
    a stand-in for CUDA): no tensor the graph creates stays on the CPU, forward and backward."""
    from tactile_deploy.adapt.step import StepProgram

    program = StepProgram.load(tiny["step"], device="meta")
    graph = program.module.graph
    assert not [n for n in graph.nodes if "cpu" in str(n.kwargs.get("device", ""))]
    out = program(torch.zeros(3, 1, 128, 128, device="meta"), torch.zeros(3, 128, 128, device="meta"),
                  torch.zeros(128, 128, device="meta"))
    assert all(o.device.type == "meta" for o in out)
    out[0].backward()
    assert all(p.grad is not None and p.grad.device.type == "meta" for p in program.trainable())


def test_runtime_adapts_without_the_training_package(tiny, tmp_path):
    """Load the step, filter, run Adam steps and write the adapted ONNX model in a process where
    importing ``tactile_deploy.training`` fails."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(f"""
        import sys
        sys.modules["tactile_deploy.training"] = None
        import numpy as np
        import torch
        torch.set_num_threads(1)
        from tactile_deploy.adapt.step import AdaptSettings, StepProgram, adapt, vae_filter
        from tactile_deploy.adapt.weights import write_adapted_onnx
        step = StepProgram.load({str(tiny["step"])!r})
        depth = np.zeros((4, 128, 128), np.float32)
        depth[:, 50:70, 60:80] = 0.5
        target = vae_filter(step, depth)
        hist = adapt(step, depth, target, np.ones((128, 128), np.float32), AdaptSettings(steps=2, batch_size=4))
        write_adapted_onnx(step.card, step.card.path(step.folder, "fp32_model"), step.weights(), {str(tmp_path / "a.onnx")!r})
        assert not any(k.startswith("tactile_deploy.training") for k in sys.modules if sys.modules[k] is not None)
        print("ok", len(hist.loss_mm2))
        """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert res.returncode == 0 and res.stdout.strip() == "ok 2", res.stderr[-3000:]
    assert (tmp_path / "a.onnx").stat().st_size > 0


def test_adaptation_target_follows_the_design():
    """The surface-anchored graphs adapt towards the measured map I, the latent design towards VAE(I);
    an explicit choice overrides the design's."""
    from types import SimpleNamespace

    from tactile_deploy.adapt.step import adaptation_target, filters_by_default

    def step(variant):
        return SimpleNamespace(card=SimpleNamespace(family_variant=variant))

    assert not filters_by_default(step("hybrid-int8-fastood")) and not filters_by_default(step("surface-fastood"))
    assert filters_by_default(step("lean-int8-fastood")) and filters_by_default(step("fused"))
    depth = np.random.default_rng(0).random((2, 128, 128)).astype(np.float32)
    target, filtered = adaptation_target(step("hybrid-int8-fastood"), depth)
    assert not filtered and np.array_equal(target, depth) and target is not depth
