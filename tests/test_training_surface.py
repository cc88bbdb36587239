"""The surface-anchored predictor: its fixed parts against independent computations, one small
train + export + parity run, the metrics against hand-made errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxscript")

ROOT = Path(__file__).resolve().parents[1]


def test_anchor_is_the_bilinear_read_of_the_depth_map(pad):
    """Against scipy's map_coordinates (tactile_deploy.fem.surface_to_volume.sample_depth_at) on
    random maps, rim nodes included (their taps clamp at the image edge)."""
    from tactile_deploy.fem.surface_to_volume import sample_depth_at
    from tactile_deploy.training.networks.surface_decoder import SurfaceAnchor

    xy = pad.vertices[pad.sensing_nodes, :2]
    anchor = SurfaceAnchor(xy, 128, 17.5)
    rng = np.random.default_rng(3)
    maps = rng.random((3, 1, 128, 128)).astype(np.float32)
    got = anchor(torch.as_tensor(maps)).numpy()
    ref = np.stack([-sample_depth_at(m[0], xy) for m in maps])
    assert np.abs(got - ref).max() < 1e-6
    # on the image border's last pixels too: a map that is a ramp in x reads back the ramp
    c = -17.5 + (np.arange(128) + 0.5) * 35 / 128
    ramp = np.broadcast_to(np.clip(c, -17.5 + 35 / 256, 17.5 - 35 / 256), (128, 128)).astype(np.float32)
    np.testing.assert_allclose(-anchor(torch.as_tensor(ramp)[None, None]).numpy()[0],
                               np.clip(xy[:, 0], c[0], c[-1]), atol=1e-5)


def test_moved_anchor_reads_where_the_nodes_moved_and_is_differentiable(pad):
    """The read at rest + a lateral displacement against scipy at the displaced points; its
    gradient in the displacement against finite differences (float64)."""
    from tactile_deploy.fem.surface_to_volume import sample_depth_at
    from tactile_deploy.training.networks.surface_decoder import SurfaceAnchor

    xy = pad.vertices[pad.sensing_nodes, :2]
    anchor = SurfaceAnchor(xy, 128, 17.5)
    rng = np.random.default_rng(4)
    maps = rng.random((2, 1, 128, 128)).astype(np.float32)
    dxy = rng.normal(0.0, 0.3, (2, len(xy), 2)).astype(np.float32)  # up to ~1 mm: across pixels and the rim
    got = anchor.moved(torch.as_tensor(maps), torch.as_tensor(dxy)).numpy()
    ref = np.stack([-sample_depth_at(maps[i, 0], xy + dxy[i]) for i in range(2)])
    assert np.abs(got - ref).max() < 2e-5  # float32 pixel coordinates
    smooth = torch.as_tensor(maps[:1], dtype=torch.float64)
    q = torch.as_tensor(dxy[:1, :40], dtype=torch.float64).requires_grad_()
    pad_rest = torch.zeros(1, len(xy) - 40, 2, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda d: anchor.moved(smooth, torch.cat([d, pad_rest], 1))[:, :40], (q,),
                                    eps=1e-6, atol=1e-4)


def test_surface_decoder_reads_the_pixel_under_each_node(pad):
    """A head that writes each output pixel's own (row, column) into the first two values: every
    node of every free layer reads the 64 x 64 pixel that holds its in-plane point (computed here
    from the node's x, y), and the backplate reads 0."""
    from tactile_deploy.training.config import SurfaceDecoderConfig
    from tactile_deploy.training.networks.surface_decoder import SurfaceDecoder

    m = pad.n_plane
    xy = pad.vertices[:m, :2]
    dec = SurfaceDecoder(SurfaceDecoderConfig(), (16, 32, 64, 128, 128), 8, 128, xy, 5)
    f_side, sub, k = dec.feature_side, dec.sub, dec.out_channels
    rows, cols = torch.meshgrid(torch.arange(f_side), torch.arange(f_side), indexing="ij")
    feats = torch.zeros(1, 32, f_side, f_side)
    feats[0, 0], feats[0, 1] = rows.float(), cols.float()
    dec.features = lambda maps, z: feats
    with torch.no_grad():
        dec.head.weight.zero_()
        dec.head.bias.zero_()
        for s in range(sub * sub):
            for layer in range(k // 3):
                dec.head.weight[s * k + 3 * layer, 0] = sub
                dec.head.bias[s * k + 3 * layer] = s // sub
                dec.head.weight[s * k + 3 * layer + 1, 1] = sub
                dec.head.bias[s * k + 3 * layer + 1] = s % sub
    with torch.no_grad():
        out = dec([], torch.zeros(1, 8))[0].numpy()
    pitch = 35.0 / 64
    want_r = np.floor((17.5 - xy[:, 1]) / pitch)
    want_c = np.floor((xy[:, 0] + 17.5) / pitch)
    for layer in range(4):
        np.testing.assert_array_equal(out[layer * m:(layer + 1) * m, 0], want_r)
        np.testing.assert_array_equal(out[layer * m:(layer + 1) * m, 1], want_c)
    assert np.all(out[4 * m:] == 0)
    assert len(np.unique(want_r * 64 + want_c)) == m


def test_mesh_metrics_of_a_hand_made_error():
    from tactile_deploy.training.metrics import mesh_metrics

    n_plane, n = 3, 12  # 4 layers of 3 nodes, the last the backplate
    true = np.zeros((2, n, 3))
    true[0, :3, 2] = [-1.0, -0.5, 0.0]  # contact 0: deepest node 0 at 1 mm
    true[1, :3, 2] = [0.0, -0.2, -0.4]  # contact 1: deepest node 2 at 0.4 mm
    pred = true.copy()
    pred[0, 0] += [0.003, 0.0, 0.004]  # 5 um at the deepest node of contact 0, 0.4 % too shallow
    pred[1, 2, 2] -= 0.004  # contact 1's deepest node 4 um (1 %) too deep
    pred[1, 4] += [0.0, 0.012, 0.0]  # an interior node 12 um off
    contact = np.array([[True, True, False], [False, False, True]])
    m = mesh_metrics(pred, true, contact, n_plane)
    assert m["contact_patch_rmse_um"] == pytest.approx(np.sqrt((25 + 0 + 16) / 3))
    assert m["deepest_node_error_pct"]["mean"] == pytest.approx((-0.4 + 1.0) / 2)
    assert m["deepest_node_error_pct"]["mean_abs"] == pytest.approx((0.4 + 1.0) / 2)
    assert m["all_node_rmse_um"] == pytest.approx(np.sqrt((25 + 16 + 144) / 24))
    assert m["interior_rmse_um"] == pytest.approx(np.sqrt(144 / 12))
    assert m["surface_rmse_um"] == pytest.approx(np.sqrt((25 + 16) / 6))


def test_targets_and_table_of_an_evaluation_report():
    from tactile_deploy.training.evaluation import PHYSICS_LIFT, markdown_table, target_text

    def metrics(patch, deepest):
        return {"contact_patch_rmse_um": patch, "all_node_rmse_um": 5.0,
                "deepest_node_error_pct": {"mean": -deepest, "mean_abs": deepest, "p95_abs": deepest}}

    good, lift = metrics(20.0, 1.0), metrics(40.0, 8.0)
    good["lift_ratio"], lift["lift_ratio"] = 2.0, 1.0
    assert target_text("primitives", good).endswith("met") and "not met" not in target_text("primitives", good)
    assert "**not met** (patch, deepest node 3.50 %)" in target_text("unseen_shapes", metrics(31.0, 3.5) | {"lift_ratio": 2})
    assert "**not met** (ratio)" in target_text("stick", metrics(45.0, 9.0) | {"lift_ratio": 1.4})
    report = {"models": {"m": "x.onnx"}, "domains": {
        "primitives": {"n_samples": 4, "methods": {"m": good, PHYSICS_LIFT: lift}},
        "coulomb": {"unavailable": "no Coulomb solver"}}}
    table = markdown_table(report)
    assert "| primitives, frictionless (4) | **20.0** / 40.0 |" in table and "not measured: no Coulomb solver" in table
    # every row has the header's cells (no "|" inside a cell)
    rows = [line for line in table.splitlines() if line.startswith("|")]
    assert {line.count("|") for line in rows} == {rows[0].count("|")}


@pytest.fixture(scope="module")
def surface_run(tmp_path_factory, pad):
    """A tiny surface-anchored run on the CPU: 32 contacts of a frictionless + stick + Coulomb mixture, with
    the deepest-node term on."""
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.train import train

    tmp = tmp_path_factory.mktemp("surface")
    stage = {"epochs": 3, "batch_size": 8, "lr": 2e-3, "kl_weight": 1e-5}
    cfg = TrainConfig.model_validate({
        "run_dir": str(tmp / "run"), "threads": 2,
        "model": {"image": {"widths": [4, 8, 8, 16, 16], "hidden": 16, "latent": 16},
                  "ood_decoder": {"channels": [4, 4, 4, 4, 4]},
                  "surface": {"channels": [8, 8, 8, 8], "conv3x3_at": [8], "anchor": "moved"}},
        "data": {"synthetic": {
            "n_samples": 32, "seed": 5, "indenters": ["sphere_r4", "cube_corner"], "radius_max_mm": 3.0,
            "depth_min_mm": 0.3, "depth_max_mm": 1.0, "contact_radius_mm": 7.5, "formulation": "standard",
            "friction": ["frictionless", "stick", "coulomb"]}},
        "image_vae": None, "mesh_vae": None, "lean_decoder": None, "projection": None, "finetune": None,
        "surface": {**stage, "image_weight": 1.0, "train_ood_decoder": True, "contact_weight": 30.0,
                    "deepest_weight": 1.0},
        "ood_decoder": stage,
    })
    metrics = train(cfg, log=lambda line: None)
    return tmp / "run", metrics


@pytest.mark.slow
def test_surface_train_export_parity(surface_run, pad, tmp_path):
    from tactile_deploy.onnx_runtime.contract import check_model_contract
    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.training.export import export_run, run_session
    from tactile_deploy.training.train import load_bundle, slim_bundle

    run, metrics = surface_run
    history = json.loads((run / "history.json").read_text())
    losses = [h["train_loss"] for h in history["surface"]]
    assert len(losses) == 3 and losses[-1] < losses[0]
    assert "val_contact_patch_rmse_um" in history["surface"][-1]
    assert history["surface"][-1]["train_deepest_rel"] > 0  # the deepest-node term ran
    held = np.load(run / "heldout.npz")
    assert held["contact_mask"].shape == (len(held["depth_mm"]), pad.n_plane) and held["contact_mask"].any()
    assert metrics["mesh_metrics"]["contact_patch_rmse_um"] > 0

    # the slim bundle (float16 weights) is what gets exported; the graph follows it to float rounding
    slim = tmp_path / "slim.pt"
    info = slim_bundle(run / "model.pt", slim)
    assert info["bytes"] < (run / "model.pt").stat().st_size / 2
    out = tmp_path / "export" / "gelslim_mesh.onnx"
    card = export_run(run, out, variant="surface-fastood", optimize=False, bundle_path=slim)
    assert card["parity"]["max_abs_diff_mm"] <= 1e-4 and card["parity"]["ood_max_abs_diff_mm"] <= 1e-4
    check_model_contract(out, pad.content_hash, pad.n_nodes)
    acc = card["heldout_accuracy"]
    assert {"contact_patch_rmse_um", "deepest_node_error_pct"} <= set(acc["metrics"])
    assert acc["physics_lift"]["contact_patch_rmse_um"] > 0

    # the graph, run here, against the slim bundle's eager model; the anchor is in the graph: the
    # sensing layer's z is the depth map read where the residual moved each node, plus the residual
    model, _ = load_bundle(slim)
    depth = held["depth_mm"][:4, None].astype(np.float32)
    _, d, _ = run_session(make_session(out, providers="cpu"), depth, batch=4)
    with torch.no_grad():
        x = torch.as_tensor(depth)
        maps, z = model.image_vae.encoder.feature_maps(model.normalise_depth(x))
        residual = model.norm.denormalise_displacement(model.surface_decoder(maps, z)).numpy()
    from tactile_deploy.fem.surface_to_volume import sample_depth_at

    rest_xy = pad.vertices[:pad.n_plane, :2]
    uz = np.stack([-sample_depth_at(m[0], rest_xy + r[:pad.n_plane, :2]) for m, r in zip(depth, residual)])
    np.testing.assert_allclose(d[:, :pad.n_plane, 2], residual[:, :pad.n_plane, 2] + uz, atol=1e-4)
    np.testing.assert_allclose(d[:, pad.n_plane:], residual[:, pad.n_plane:], atol=1e-4)
    assert np.all(d[:, pad.backplate_nodes] == 0.0)
    # the float16 bundle costs nothing measurable against the float32 run
    full, _ = load_bundle(run / "model.pt")
    with torch.no_grad():
        diff = (full(x)[1] - model(x)[1]).abs().max().item()
    assert diff < 1e-3


def test_lateral_lift_residual_model_graph_and_adaptation_step_agree(pad, tmp_path):
    """``surface.lateral = "lift_residual"``: the sensing nodes' x, y are the physics lift of their
    u_z plus the decoder's residual, the same function in the eager model, its training step, the
    exported graph (ONNX, run by onnxruntime) and the adaptation step; a surface variant (no lift)
    is refused."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.surface_to_volume import SurfaceToVolume
    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.simulation.contact import get_simulator
    from tactile_deploy.training.adaptation.step import AdaptationStep
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.errors import UsageError
    from tactile_deploy.training.export import OUTPUTS, _onnx_export, deploy_module, lateral_lift_of, run_session
    from tactile_deploy.training.train import SurfaceTrainer, build_model

    cfg = TrainConfig.model_validate({
        "run_dir": str(tmp_path / "run"),
        "model": {"image": {"widths": [4, 8, 8, 16, 16], "hidden": 16, "latent": 16},
                  "ood_decoder": {"channels": [4, 4, 4, 4, 4]},
                  "surface": {"channels": [8, 8, 8, 8], "conv3x3_at": [8], "anchor": "moved",
                              "lateral": "lift_residual"}},
        "data": {"synthetic": {"n_samples": 4, "nu": 0.45}},
        "image_vae": None, "mesh_vae": None, "lean_decoder": None, "projection": None, "finetune": None,
        "surface": {"epochs": 1, "batch_size": 4, "lr": 1e-3},
    })
    torch.manual_seed(3)
    model = build_model(cfg).eval()
    assert model.lateral_adds and lateral_lift_of(model) is model.lateral_lift
    with torch.no_grad():  # a residual far from zero, so that "added" and "replaced" differ
        model.surface_decoder.head.weight.mul_(30.0)
        model.surface_decoder.head.bias.normal_(0.0, 0.5)
    yy, xx = np.mgrid[0:128, 0:128]
    depth = np.stack([np.clip(0.8 - ((xx - c) ** 2 + (yy - 64) ** 2) / 300.0, 0.0, None) for c in (50, 70)])
    depth = depth[:, None].astype(np.float32)
    x = torch.as_tensor(depth)
    with torch.no_grad():
        _, d = model(x)
        maps, z = model.image_vae.encoder.feature_maps(model.normalise_depth(x))
        residual = model.norm.denormalise_displacement(model.surface_decoder(maps, z)).numpy()
    d = d.numpy()
    # the lift of the pad's own FEM at the data's nu (built here from SurfaceToVolume, not the model's module)
    s2v = SurfaceToVolume(get_simulator(Material(nu=0.45)))
    m = pad.n_plane
    H_xy = s2v.H.reshape(pad.n_nodes, 3, m)[:m, :2]
    lift_xy = np.einsum("iaj,bj->bia", H_xy, d[:, :m, 2])
    np.testing.assert_allclose(d[:, :m, :2], residual[:, :m, :2] + lift_xy, atol=2e-5)
    assert np.abs(residual[:, :m, :2]).max() > 10 * 2e-5 and np.abs(lift_xy).max() > 10 * 2e-5

    graph = tmp_path / "g.onnx"
    _onnx_export(deploy_module(model, "hybrid-fastood"), x, graph, ["depth"], OUTPUTS, optimize=False)
    _, d_onnx, _ = run_session(make_session(graph, providers="cpu"), depth, batch=2)
    np.testing.assert_allclose(d_onnx, d, atol=1e-4)
    with torch.no_grad():
        d_step = AdaptationStep(model, lateral=lateral_lift_of(model)).displacement(x).numpy()
        pred = SurfaceTrainer(model)(model.normalise_depth(x), False)[0]
        d_train = model.norm.denormalise_displacement(pred).numpy()
    np.testing.assert_allclose(d_step, d, atol=1e-4)
    np.testing.assert_allclose(d_train, d, atol=1e-5)  # the training step learns the same function
    with pytest.raises(UsageError, match="trained on top of it.*export a hybrid variant"):
        deploy_module(model, "surface-fastood")
    with pytest.raises(ValueError, match="cannot run without it"):
        model.use_lateral_lift(None)


def test_hybrid_int8_lift_follows_presses_larger_than_any_seen(pad, tmp_path):
    """The hybrid graphs quantise the lateral lift dynamically (each call's range of u_z): on a
    press far larger and deeper than anything a static calibration saw, the int8 graph stays on its
    fp32 graph, where a statically calibrated lift saturates."""
    from tactile_deploy.onnx_runtime.quantize import quantize_int8
    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.export import OUTPUTS, _onnx_export, deploy_module, int8_nodes, quantise, run_session
    from tactile_deploy.training.train import build_model

    import onnx

    cfg = TrainConfig.model_validate({
        "run_dir": str(tmp_path / "run"),
        "model": {"image": {"widths": [4, 8, 8, 16, 16], "hidden": 16, "latent": 16},
                  "ood_decoder": {"channels": [4, 4, 4, 4, 4]},
                  "surface": {"channels": [8, 8, 8, 8], "conv3x3_at": [8], "anchor": "moved"}},
        "data": {"synthetic": {"n_samples": 4}},
        "image_vae": None, "mesh_vae": None, "lean_decoder": None, "projection": None, "finetune": None,
        "surface": {"epochs": 1, "batch_size": 4, "lr": 1e-3},
    })
    torch.manual_seed(5)
    model = build_model(cfg).eval()
    yy, xx = np.mgrid[0:128, 0:128]

    def press(radius_px: float, depth_mm: float) -> np.ndarray:
        return np.clip(depth_mm * (1 - ((xx - 64) ** 2 + (yy - 64) ** 2) / radius_px**2), 0, None).astype(np.float32)

    small = np.stack([press(8, 0.3), press(10, 0.4)])[:, None]  # what a static calibration would see
    large = press(45, 1.3)[None, None]  # a 25 mm wide, 1.3 mm deep press
    fp32 = tmp_path / "fp32.onnx"
    _onnx_export(deploy_module(model, "hybrid-fastood"), torch.as_tensor(small), fp32, ["depth"], OUTPUTS,
                 optimize=False)
    dynamic, static = tmp_path / "dynamic.onnx", tmp_path / "static.onnx"
    quantise(fp32, dynamic, None, variant="hybrid-int8-fastood")
    quantize_int8(fp32, static, small, int8_nodes(onnx.load(str(fp32)), "hybrid-int8-fastood"))
    ops = {n.op_type for n in onnx.load(str(dynamic)).graph.node}
    assert "DynamicQuantizeLinear" in ops and "QuantizeLinear" not in ops

    def lateral(path):
        return run_session(make_session(path, providers="cpu"), large, batch=1)[1][0, :pad.n_plane, :2]

    ref = lateral(fp32)
    scale = np.abs(ref).max()
    assert scale > 0.1  # mm: a lateral motion worth quantising
    # RMS over the sensing nodes, relative to the fp32 lateral motion's (measured: 0.05 dynamic, the
    # int8 weights' rounding summed over a press this wide; 0.91 static)
    ref_rms = np.sqrt(np.mean(ref**2))
    assert np.sqrt(np.mean((lateral(dynamic) - ref) ** 2)) < 0.10 * ref_rms
    assert np.sqrt(np.mean((lateral(static) - ref) ** 2)) > 0.5 * ref_rms  # the saturation the dynamic range avoids


def test_init_weights_start_a_run_from_a_bundle():
    """``init_weights``: the shipped bundle's trained modules and data scales replace a fresh model's
    (fine-tuning starts where the bundle ended); a bundle of another model is refused by name."""
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.errors import UsageError
    from tactile_deploy.training.train import build_model, load_bundle, start_from, trained_prefixes

    shipped, bundle = load_bundle(ROOT / "exported" / "gelslim_mesh.pt")
    cfg = TrainConfig.model_validate({**bundle["config"], "init_weights": str(ROOT / "exported" / "gelslim_mesh.pt")})
    torch.manual_seed(123)
    model = build_model(cfg)
    scales = start_from(model, cfg, log=lambda line: None)
    assert scales.depth_scale_mm == pytest.approx(float(shipped.norm.depth_scale_mm), rel=1e-7)
    ours, theirs = model.state_dict(), shipped.state_dict()
    kept = [k for k in theirs if k.startswith(trained_prefixes(cfg))]
    assert len(kept) > 20
    for k in kept:
        assert torch.equal(ours[k], theirs[k]), k
    other = cfg.model_copy(update={"model": cfg.model.model_copy(update={
        "image": cfg.model.image.model_copy(update={"widths": (8, 16, 32, 64, 128)})})})
    with pytest.raises(UsageError, match="init_weights .*same model"):
        start_from(build_model(other), other, log=lambda line: None)


def test_deepest_node_term_is_the_evaluations_deepest_node_error_squared():
    """The training term against training/metrics.py's deepest-node error on random contacts: with
    every true deepest depth above the floor it is the mean of (error % / 100)^2; below the floor the
    error is taken against the floor."""
    from tactile_deploy.training.metrics import mesh_metrics
    from tactile_deploy.training.train import deepest_node_term

    rng = np.random.default_rng(5)
    n_plane, n = 50, 150
    true = rng.normal(0.0, 0.01, (6, n, 3))
    true[np.arange(6), rng.integers(0, n_plane, 6), 2] = -rng.uniform(0.2, 1.0, 6)  # one clear deepest node each
    pred = true + rng.normal(0.0, 0.02, true.shape)
    pct = []
    for i in range(6):
        m = mesh_metrics(pred[i: i + 1], true[i: i + 1], None, n_plane, free_layers=2)
        pct.append(m["deepest_node_error_pct"]["mean"])
    want = np.mean((np.asarray(pct) / 100.0) ** 2)
    got = float(deepest_node_term(torch.as_tensor(pred), torch.as_tensor(true), n_plane, floor=0.05))
    assert abs(got - want) < 1e-12 * max(want, 1.0) + 1e-15
    # a contact shallower than the floor: its error is divided by the floor, not by its depth
    shallow = true[:1].copy()
    shallow[0, :n_plane, 2] = np.minimum(shallow[0, :n_plane, 2], 0.0) * 0.01  # deepest ~2-10 um
    d = -shallow[0, :n_plane, 2].min()
    k = int(np.argmin(shallow[0, :n_plane, 2]))
    p = shallow.copy()
    p[0, k, 2] -= 0.004  # 4 um deeper
    got = float(deepest_node_term(torch.as_tensor(p), torch.as_tensor(shallow), n_plane, floor=0.05))
    assert d < 0.05 and abs(got - (0.004 / 0.05) ** 2) < 1e-12
