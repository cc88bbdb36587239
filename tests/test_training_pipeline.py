"""End to end on CPU: simulate a tiny data set, train all stages for a few epochs, export, check
parity with torch and the runtime's model contract. Runs in well under a minute."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxscript")


@pytest.mark.slow
def test_train_export_parity(tmp_path, pad):
    from tactile_deploy.onnx_runtime.contract import check_model_contract
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.training.export import export_run, run_session
    from tactile_deploy.training.train import load_bundle, train

    stage = {"epochs": 3, "batch_size": 16, "lr": 2e-3, "kl_weight": 1e-5}
    cfg = TrainConfig.model_validate({
        "run_dir": str(tmp_path / "run"),
        "threads": 2,
        "model": {
            "image": {"widths": [8, 16, 32, 64, 128], "hidden": 32, "latent": 32},
            "mesh": {"channels": [8, 8, 8, 16], "cheb_k": [3, 3, 3, 3], "latent": 32},
            "projection": {"hidden": [64, 128, 64]},
            "lean_decoder": {"channels": [16, 16, 8, 8]},
            "ood_decoder": {"channels": [8, 8, 8, 8, 4]},
        },
        "data": {
            "synthetic": {
                "n_samples": 64, "seed": 5, "indenters": ["sphere_r2", "sphere_r4", "cube_corner"],
                "radius_max_mm": 3.0, "depth_min_mm": 0.3, "depth_max_mm": 1.0, "contact_radius_mm": 7.5,
                "formulation": "standard",
            },
            "cache_file": str(tmp_path / "data.npz"),
        },
        "image_vae": stage, "mesh_vae": stage, "lean_decoder": stage, "ood_decoder": stage, "projection": stage,
    })
    lines = []
    metrics = train(cfg, log=lines.append)
    run = tmp_path / "run"
    from tactile_deploy.training.run_files import load_training_history, load_training_metrics

    history = load_training_history(run / "history.json").model_dump(exclude_unset=True)  # the formats' readers
    from tactile_deploy.atomic import finite_or_null

    assert load_training_metrics(run / "metrics.json").model_dump(mode="json", exclude_unset=True) == finite_or_null(
        json.loads(json.dumps(metrics)))  # the file holds what train() returned
    for name in ("image_vae", "mesh_vae", "lean_decoder", "ood_decoder", "projection"):
        losses = [h["train_loss"] for h in history[name]]
        assert len(losses) == 3
        assert losses[-1] < losses[0], (name, losses)
    assert (run / "learning_curves.png").stat().st_size > 1000
    assert metrics["data"]["train"]["n_samples"] + metrics["data"]["val"]["n_samples"] == 64
    held_all = np.load(run / "heldout.npz")
    rmse_reported = metrics["vertex_rmse_mm"]

    # a second start finds every stage complete and only re-evaluates
    lines.clear()
    train(cfg, log=lines.append)
    assert sum("skipped" in line for line in lines) == 5

    out = tmp_path / "export" / "gelslim_mesh.onnx"
    card = export_run(run, out, variant="lean-fastood", optimize=False)
    assert card["parity"]["max_abs_diff_mm"] <= 1e-4
    assert card["parity"]["ood_max_abs_diff_mm"] <= 1e-4
    meta = check_model_contract(out, pad.content_hash, pad.n_nodes)
    assert meta["units"] == "mm" and meta["mesh_hash"] == pad.content_hash
    assert float(meta["ood_threshold"]) == pytest.approx(card["ood_threshold_mm"])
    assert json.loads(meta["dataset"])["train"]["n_samples"] > 0

    # the graph against the eager model, run here step by step (not the exporter's own reference)
    model, _ = load_bundle(run / "model.pt")
    held = held_all["depth_mm"][:5, None].astype(np.float32)
    session = make_session(out, providers="cpu")
    v, d, ood = run_session(session, held, batch=5)
    model.deploy_decoder = "lean"
    with torch.no_grad():
        x = model.normalise_depth(torch.as_tensor(held))
        z = model.image_vae.encoder(x)[0]
        d_eager = model.decode_displacement(model.project(z)).numpy()
        recon = model.ood_decoder(z)
        ood_eager = torch.sqrt(torch.mean(((recon - x) * model.norm.depth_scale_mm) ** 2, dim=(1, 2, 3))).numpy()
    np.testing.assert_allclose(d, d_eager, atol=1e-4)
    np.testing.assert_allclose(ood, ood_eager, atol=1e-4)
    # the training report's held-out vertex RMSE is the eager model's error on the held-out maps
    with torch.no_grad():
        model.deploy_decoder = "coma"
        d_all = model(torch.as_tensor(held_all["depth_mm"][:, None].astype(np.float32)))[1].numpy()
    rmse = float(np.sqrt(np.mean((d_all - held_all["displacement_mm"]) ** 2)))
    assert rmse_reported == pytest.approx(rmse, rel=1e-3)

    # batch independence and vertices = rest + displacement, read back from the file
    v1, d1, _ = run_session(session, held[2:3], batch=1)
    np.testing.assert_allclose(d1[0], d[2], atol=1e-5)
    np.testing.assert_allclose(v, pad.vertices[None] + d, atol=1e-4)
    assert np.all(d[:, pad.backplate_nodes] == 0.0) and ood.shape == (5,)
    assert (out.with_suffix(".md")).read_text().startswith("# Model card")


@pytest.mark.slow
def test_data_parallel_run_with_time_budget_and_finetune(tmp_path):
    """Two ranks under torchrun (gloo on CPU), each simulating its own contacts: the ranks stop a
    time-budgeted stage together, run the finetune stage, and rank 0 alone writes the bundle."""
    import os
    import socket
    import subprocess
    import sys

    from tactile_deploy.training.train import load_bundle

    stage = {"epochs": 2, "batch_size": 8, "lr": 2e-3, "kl_weight": 1e-5}
    cfg = {
        "run_dir": str(tmp_path / "run"), "threads": 1,
        "model": {
            "image": {"widths": [8, 8, 16, 16, 32], "hidden": 16, "latent": 16},
            "mesh": {"channels": [4, 4, 4, 8], "cheb_k": [2, 2, 2, 2], "latent": 16},
            "projection": {"hidden": [32, 32, 32]},
            "lean_decoder": {"channels": [8, 8, 8, 8]},
            "ood_decoder": {"channels": [4, 4, 4, 4, 4]},
        },
        "data": {"synthetic": {
            "n_samples": 24, "seed": 9, "indenters": ["sphere_r4", "cube_corner"], "radius_max_mm": 3.0,
            "depth_min_mm": 0.3, "depth_max_mm": 1.0, "contact_radius_mm": 7.5, "formulation": "standard"}},
        "image_vae": stage, "mesh_vae": stage, "ood_decoder": stage, "projection": stage,
        "lean_decoder": {**stage, "time_budget_s": 1e-3},  # stops after its first epoch, on both ranks
        "finetune": stage,
    }
    path = tmp_path / "ddp.json"
    path.write_text(json.dumps(cfg))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with socket.socket() as s:                    # a free port: other runs may hold a fixed one
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", str(port),
         "-m", "tactile_deploy.training", "train", "--config", str(path)],
        capture_output=True, text=True, timeout=600, env=env,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert len(history["lean_decoder"]) == 1 and len(history["finetune"]) == 2
    assert len(history["image_vae"]) == 2
    model, bundle = load_bundle(tmp_path / "run" / "model.pt")
    metrics = bundle["metrics"]
    assert metrics["data"]["train"]["source"].endswith("rank=0")  # rank 0 reports its own shard
    assert {"coma", "lean", "lean_staged"} <= set(metrics["decoders"])
    assert proc.stdout.count("held-out:") == 1  # only rank 0 logs
