"""The shipped graph's ``ood_score`` (training/ood_score.py): the graph computes the score its card
describes, the score does not follow the contact's size on training contacts, novel indenters
score higher, and the edit leaves the mesh path alone."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "exported" / "gelslim_mesh.onnx"
CARD = ROOT / "exported" / "gelslim_mesh.json"
pytest.importorskip("onnx")
pytest.importorskip("torch")


def _score(recon, depth, st):
    """The card's formula, written out here: (N, R, R) mm float64 -> (N,) mm."""
    n, r, _ = depth.shape
    p = st["pool_px"]
    blocks = (recon - depth).reshape(n, r // p, p, r // p, p).mean(axis=(2, 4))
    e_rms = np.sqrt(np.mean(blocks**2, axis=(1, 2)) + st["noise_mm"] ** 2)
    d_eff = np.sqrt(np.mean(depth**2, axis=(1, 2)) + st["noise_mm"] ** 2)
    return e_rms * (st["d_ref_mm"] / d_eff) ** st["exponent"]


@pytest.fixture(scope="module")
def shipped():
    """Fresh contacts (32 each) of the training generator (seed 6007) and of the novel indenters
    (seed 14): seeds neither the statistics (4007), the threshold (1007) nor the benchmark use."""
    import onnxruntime as ort
    import torch

    from tactile_deploy.indenters import list_indenters
    from tactile_deploy.training.config import SyntheticData, TrainConfig
    from tactile_deploy.training.data import fresh_contacts
    from tactile_deploy.training.train import load_bundle

    model, bundle = load_bundle(ROOT / "exported" / "gelslim_mesh.pt")
    spec = TrainConfig.model_validate(bundle["config"]).data.synthetic
    prim = fresh_contacts(spec, 32, 6007).depth_mm.astype(np.float32)
    novel_spec = SyntheticData(n_samples=1, indenters=tuple(list_indenters("novel")), seed=11)
    novel = fresh_contacts(novel_spec, 32, 14).depth_mm.astype(np.float32)
    sess = ort.InferenceSession(str(SHIPPED), providers=["CPUExecutionProvider"])
    card = json.loads(CARD.read_text())
    with torch.no_grad():  # the lean image decoder on the encoder's mean latent, in torch (not the graph)
        recon = {k: (model.ood_decoder(model.image_vae.encoder(model.normalise_depth(torch.as_tensor(x[:, None])))[0])
                     * model.norm.depth_scale_mm).numpy()[:, 0].astype(np.float64) for k, x in (("prim", prim), ("novel", novel))}
    return {"prim": prim, "novel": novel, "sess": sess, "card": card, "recon": recon,
            "score": {k: sess.run(["ood_score"], {"depth": x[:, None]})[0] for k, x in (("prim", prim), ("novel", novel))}}


def test_graph_score_is_the_cards_formula_on_the_torch_reconstruction(shipped):
    """The graph's ood_score equals the card's formula applied to the torch model's reconstruction
    (float32 graph against float64 numpy: relative 1e-4; measured ~1e-6)."""
    st = shipped["card"]["ood"]["statistics"]
    for k in ("prim", "novel"):
        ref = _score(shipped["recon"][k], shipped[k].astype(np.float64), st)
        np.testing.assert_allclose(shipped["score"][k], ref, rtol=1e-4, err_msg=k)


def test_threshold_metadata_is_the_cards(shipped):
    meta = shipped["sess"].get_modelmeta().custom_metadata_map
    assert meta["ood_score"] == shipped["card"]["ood"]["score"] == "pooled8-size-normalised"
    assert float(meta["ood_threshold"]) == pytest.approx(shipped["card"]["ood_threshold_mm"], rel=1e-12)
    assert shipped["card"]["ood_threshold_mm"] == pytest.approx(shipped["card"]["ood"]["score_mm_p99"], rel=1e-12)


def test_score_does_not_follow_contact_size_and_passes_training_contacts(shipped):
    """On training contacts the score barely follows the map's RMS depth (the exported
    reconstruction RMSE: Spearman +0.84), and the threshold passes (almost) every training contact."""
    from scipy.stats import spearmanr

    prim = shipped["score"]["prim"]
    size = np.sqrt(np.mean(shipped["prim"].astype(np.float64) ** 2, axis=(1, 2)))
    rho = spearmanr(prim, size).correlation
    assert abs(rho) < 0.5, f"Spearman(score, RMS depth) on training contacts {rho:.2f}: the score follows contact size"
    thr = shipped["card"]["ood_threshold_mm"]
    assert np.mean(prim > thr) <= 2 / 32, np.mean(prim > thr)


@pytest.mark.xfail(strict=True, reason="the graph trained on procedural pressing faces reconstructs the library's "
                   "novel indenters nearly as well as the primitives (OOD AUROC 0.845, target 0.9; docs/predictor.md, "
                   "'The out-of-distribution score')")
def test_novel_indenters_score_higher(shipped):
    """Novel indenters score 1.4x higher than training contacts on average and the threshold flags
    a quarter of them (held for the graph trained on the primitives alone: 2.2x)."""
    prim, novel = shipped["score"]["prim"], shipped["score"]["novel"]
    thr = shipped["card"]["ood_threshold_mm"]
    assert novel.mean() > 1.4 * prim.mean(), (novel.mean(), prim.mean())
    assert np.mean(novel > thr) >= 0.25, np.mean(novel > thr)


def test_append_score_keeps_the_mesh_path_and_refuses_a_second_edit():
    """On a small graph of the exported form (recon = 0.9 depth + 0.01 mm), the edit keeps the other
    outputs bit-identical, computes the formula, and refuses an edited graph."""
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from tactile_deploy.training.ood_score import OodStatistics, append_score, score_numpy

    c = lambda name, v: numpy_helper.from_array(np.asarray(v), name)
    g = helper.make_graph(
        [helper.make_node("Mul", ["depth", "k"], ["scaled"]), helper.make_node("Add", ["scaled", "off"], ["recon"]),
         helper.make_node("Sub", ["recon", "depth"], ["err"]), helper.make_node("Pow", ["err", "two"], ["err2"]),
         helper.make_node("ReduceMean", ["err2", "axes"], ["ms"], keepdims=0),
         helper.make_node("Sqrt", ["ms"], ["ood_score"]), helper.make_node("Flatten", ["scaled"], ["vertices"])],
        "g", [helper.make_tensor_value_info("depth", TensorProto.FLOAT, ["N", 1, 16, 16])],
        [helper.make_tensor_value_info("vertices", TensorProto.FLOAT, ["N", 256]),
         helper.make_tensor_value_info("ood_score", TensorProto.FLOAT, ["N"])],
        [c("k", np.float32(0.9)), c("off", np.float32(0.01)), c("two", np.float32(2.0)),
         c("axes", np.asarray([1, 2, 3], np.int64))])
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)])
    st = OodStatistics(exponent=0.3, d_ref_mm=0.05, noise_mm=0.02, pool_px=8, source="test")
    edited = append_score(model, st)
    assert {t.name for t in edited.graph.initializer}.isdisjoint({"two"}), "the old score's constants stay"
    depth = np.random.default_rng(0).uniform(0, 0.5, (3, 1, 16, 16)).astype(np.float32)
    run = lambda m: ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(
        ["vertices", "ood_score"], {"depth": depth})
    (v0, _), (v1, s1) = run(model), run(edited)
    assert np.array_equal(v0, v1)
    recon = 0.9 * depth.astype(np.float64) + 0.01
    np.testing.assert_allclose(s1, score_numpy(recon, depth, st), rtol=1e-5)
    np.testing.assert_allclose(s1, _score(recon[:, 0], depth[:, 0].astype(np.float64), vars(st)), rtol=1e-5)
    with pytest.raises(ValueError, match="already"):
        append_score(edited, st)
    onnx.checker.check_model(edited)


def test_cli_refuses_a_graph_that_already_has_the_score(tmp_path, capsys):
    """`ood-score` on the shipped (edited) graph: one error naming the file, nothing written."""
    import shutil

    from tactile_deploy.training.__main__ import main

    for name in ("gelslim_mesh.onnx", "gelslim_mesh_fp32.onnx", "gelslim_mesh.json", "gelslim_mesh.md"):
        shutil.copy(ROOT / "exported" / name, tmp_path / name)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    rc = main(["ood-score", "--onnx", str(tmp_path / "gelslim_mesh.onnx"), "--bundle", str(ROOT / "exported" / "gelslim_mesh.pt")])
    err = capsys.readouterr().err
    assert rc != 0 and "already" in err and str(tmp_path / "gelslim_mesh.onnx") in err, err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
