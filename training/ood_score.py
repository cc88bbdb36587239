"""The deployed ``ood_score``: the coarse reconstruction error of the lean image decoder,
normalised by the contact's size, appended to an exported graph as a few ONNX nodes.

The exported graph's score (``RMS(recon - depth)``, mm, :mod:`tactile_deploy.training.export`)
grows with the size of the contact: a large press of a training indenter scores like a small press
of a novel one. This module replaces it, inside the same graph, by::

    e       = AveragePool_8x8(recon - depth)                      (N, 1, 16, 16) mm, 2.2 mm blocks
    e_rms   = sqrt(mean(e**2) + NOISE_MM**2)                      (N,) mm
    d_eff   = sqrt(mean(depth**2) + NOISE_MM**2)                  (N,) mm
    ood_score = e_rms * (d_ref / d_eff) ** b                      (N,) mm

``recon`` is the lean image decoder's reconstruction of the map (mm, the model grid), ``depth`` the
input map (mm). The 8 x 8 pooling keeps the error of the contact's shape and drops the pixel-scale
error every sharp edge leaves; ``NOISE_MM`` (the smooth part of the sensor noise the evaluation adds
and the training augmentation draws, 20 um) keeps noise-sized errors and near-empty maps from
dominating; ``b`` and ``d_ref`` (mm) are fitted by least squares of ``log e_rms`` on ``log d_eff``
over fresh contacts of the training generator (:data:`FIT_SEED`, half of them with the sensor
noise, as in training), so that the score is the coarse error of a training contact of median size
``d_ref``. The threshold (``ood_threshold``) is the score's 99th percentile on fresh contacts of the
run's held-out seed (:data:`HELD_SEED`, half noisy). Nothing is fitted on novel indenters; their
separation is measured by ``bench/bench_predictor.py`` and ``bench/bench_ood_scores.py``.

:func:`append_score` edits a graph (the old score's nodes go, the mesh path is untouched: vertices
stay bit-identical); :func:`apply_to_export` edits a shipped graph, its fp32 twin, their metadata
and the model card (``python -m tactile_deploy.training ood-score``).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

#: What ``ood_score`` is in a graph edited here (metadata ``ood_score``).
SCORE_KIND = "pooled8-size-normalised"
POOL_PX = 8
NOISE_MM = 0.02
FIT_SEED, FIT_N = 4007, 1024
HELD_SEED, HELD_N = 1007, 512
NODE_PREFIX = "ood_score/"


@dataclass(frozen=True)
class OodStatistics:
    """Constants of the score (see the module docstring) and where they come from."""

    exponent: float
    d_ref_mm: float
    noise_mm: float
    pool_px: int
    source: str


def _error_and_size(recon_mm, depth_mm, pool_px: int, noise_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(e_rms, d_eff), each (N,) mm float64, of the module docstring, from the reconstruction and
    the input, both (N, 1, R, R) or (N, R, R) mm."""
    recon = np.asarray(recon_mm, np.float64).reshape(len(recon_mm), -1, *np.shape(recon_mm)[-2:])[:, 0]
    depth = np.asarray(depth_mm, np.float64).reshape(len(depth_mm), -1, *np.shape(depth_mm)[-2:])[:, 0]
    n, r, _ = depth.shape
    p = pool_px
    e = (recon - depth).reshape(n, r // p, p, r // p, p).mean((2, 4))
    return np.sqrt((e**2).mean((1, 2)) + noise_mm**2), np.sqrt((depth**2).mean((1, 2)) + noise_mm**2)


def score_numpy(recon_mm: np.ndarray, depth_mm: np.ndarray, stats: OodStatistics) -> np.ndarray:
    """The score (N,) mm from the reconstruction and the input, both (N, 1, R, R) or (N, R, R) mm,
    in float64 (the reference the graph is checked against)."""
    e_rms, d_eff = _error_and_size(recon_mm, depth_mm, stats.pool_px, stats.noise_mm)
    return e_rms * (stats.d_ref_mm / d_eff) ** stats.exponent


def _old_score_chain(model):
    """(nodes computing the exported ``ood_score`` from the reconstruction error, the Sub node
    recon - depth). Expects Sqrt <- ReduceMean <- Pow <- Sub(recon, depth)."""
    prod = {o: n for n in model.graph.node for o in n.output}
    chain, node = [], prod.get("ood_score")
    while node is not None and node.op_type != "Sub":
        chain.append(node)
        node = prod.get(node.input[0])
    ops = [n.op_type for n in chain]
    if node is None or ops != ["Sqrt", "ReduceMean", "Pow"] or list(node.input)[1] != "depth":
        raise ValueError(f"ood_score: expected Sqrt <- ReduceMean <- Pow <- Sub(recon, depth) (an exported "
                         f"*-fastood graph), found {ops} <- {node.op_type if node is not None else None}")
    return chain, node


def recon_tensor(model) -> str:
    """Name of the reconstruction (N, 1, R, R) mm in an exported or edited graph."""
    for n in model.graph.node:
        if n.name == NODE_PREFIX + "err":
            return n.input[0]
    return _old_score_chain(model)[1].input[0]


def is_edited(model) -> bool:
    return any(n.name.startswith(NODE_PREFIX) for n in model.graph.node)


def append_score(model, stats: OodStatistics):
    """A copy of the exported graph ``model`` (onnx.ModelProto) whose ``ood_score`` is this
    module's score. The old score's nodes and the constants only they used are removed; every other
    node and initializer is kept as it was."""
    import onnx
    from onnx import helper, numpy_helper

    if is_edited(model):
        raise ValueError("the graph's ood_score is already the size-normalised score (nodes "
                         f"{NODE_PREFIX}*): edit the exported graph, not an edited one")
    chain, sub = _old_score_chain(model)
    m = onnx.ModelProto()
    m.CopyFrom(model)
    chain_outputs = {o for n in chain for o in n.output} | {sub.output[0]}
    consumers = [n for n in model.graph.node if sub.output[0] in n.input and n.output[0] not in chain_outputs]
    drop = {i for i, n in enumerate(model.graph.node) if set(n.output) <= chain_outputs
            and (n.op_type != "Sub" or not consumers)}  # the old score's nodes (by position: names may be empty)
    kept = [n for i, n in enumerate(m.graph.node) if i not in drop]
    used = {i for n in kept for i in n.input}
    dropped_inputs = {i for j in drop for i in model.graph.node[j].input} - used
    init = [t for t in m.graph.initializer if t.name not in dropped_inputs]
    del m.graph.node[:]
    m.graph.node.extend(kept)
    del m.graph.initializer[:]
    m.graph.initializer.extend(init)
    p = NODE_PREFIX
    consts = {"axes": np.asarray([1, 2, 3], np.int64), "noise2": np.float32(stats.noise_mm**2),
              "d_ref2": np.float32(stats.d_ref_mm**2), "half_b": np.float32(stats.exponent / 2)}
    m.graph.initializer.extend(numpy_helper.from_array(np.asarray(v), p + k) for k, v in consts.items())
    k = stats.pool_px
    m.graph.node.extend([
        helper.make_node("Sub", [sub.input[0], "depth"], [p + "err"], name=p + "err"),
        helper.make_node("AveragePool", [p + "err"], [p + "pooled"], name=p + "pool", kernel_shape=[k, k], strides=[k, k]),
        helper.make_node("Mul", [p + "pooled", p + "pooled"], [p + "pooled2"], name=p + "pooled2"),
        helper.make_node("ReduceMean", [p + "pooled2", p + "axes"], [p + "e_ms"], name=p + "e_ms", keepdims=0),
        helper.make_node("Add", [p + "e_ms", p + "noise2"], [p + "e_ms_noise"], name=p + "e_ms_noise"),
        helper.make_node("Sqrt", [p + "e_ms_noise"], [p + "e_rms"], name=p + "e_rms"),
        helper.make_node("Mul", ["depth", "depth"], [p + "depth2"], name=p + "depth2"),
        helper.make_node("ReduceMean", [p + "depth2", p + "axes"], [p + "d_ms"], name=p + "d_ms", keepdims=0),
        helper.make_node("Add", [p + "d_ms", p + "noise2"], [p + "d_eff2"], name=p + "d_eff2"),
        helper.make_node("Div", [p + "d_ref2", p + "d_eff2"], [p + "ratio2"], name=p + "ratio2"),
        helper.make_node("Pow", [p + "ratio2", p + "half_b"], [p + "weight"], name=p + "weight"),
        helper.make_node("Mul", [p + "e_rms", p + "weight"], ["ood_score"], name=p + "score"),
    ])
    onnx.checker.check_model(m)
    return m


def graph_session(model, extra=()):
    """A one-thread CPU onnxruntime session of the in-memory ONNX ``model`` with the tensors named
    in ``extra`` added as outputs (to read intermediate values)."""
    import onnx
    import onnxruntime as ort

    m = onnx.ModelProto()
    m.CopyFrom(model)
    for e in extra:
        m.graph.output.append(onnx.helper.make_tensor_value_info(e, onnx.TensorProto.FLOAT, None))
    so = ort.SessionOptions()
    so.intra_op_num_threads = so.inter_op_num_threads = 1
    return ort.InferenceSession(m.SerializeToString(), so, providers=["CPUExecutionProvider"])


def run_graph(model, depth_mm: np.ndarray, batch: int = 64) -> dict[str, np.ndarray]:
    """{"vertices", "ood_score", "recon"} of ``model`` on maps (N, R, R) mm (onnxruntime, 1 thread)."""
    names = ["vertices", "ood_score", recon_tensor(model)]
    sess = graph_session(model, names[2:])
    parts = [sess.run(names, {"depth": np.ascontiguousarray(depth_mm[i:i + batch, None], np.float32)})
             for i in range(0, len(depth_mm), batch)]
    return {k: np.concatenate([p[j] for p in parts]) for j, k in enumerate(("vertices", "ood_score", "recon"))}


def statistics_of(graph_path: Path) -> OodStatistics | None:
    """The statistics of an edited graph, from its metadata ``ood_calibration`` (None for an
    exported graph, whose ood_score is the reconstruction RMSE)."""
    from tactile_deploy.onnx_runtime.metadata import read_metadata

    meta = read_metadata(graph_path)
    if meta.get("ood_score") != SCORE_KIND:
        return None
    return OodStatistics(**json.loads(meta["ood_calibration"])["statistics"])


def fitting_maps(spec, n: int, seed: int) -> np.ndarray:
    """``n`` fresh contacts (N, R, R) mm of the training generator ``spec`` with ``seed``, every
    second one with the evaluation's sensor noise (10 um white + 20 um smooth, seeded by ``seed``)."""
    from tactile_deploy.training.data import fresh_contacts
    from tactile_deploy.training.evaluation import add_sensor_noise

    maps = fresh_contacts(spec, n, seed).depth_mm.astype(np.float32)
    odd = np.arange(n) % 2 == 1
    maps[odd] = add_sensor_noise(maps[odd], np.random.default_rng([seed, 7]))
    return maps


def fit_statistics(model, spec) -> OodStatistics:
    """Fit ``b`` and ``d_ref`` on :data:`FIT_N` maps of :func:`fitting_maps` (seed :data:`FIT_SEED`)
    through the exported graph ``model``."""
    if FIT_SEED == spec.seed:
        raise ValueError(f"FIT_SEED {FIT_SEED} is the training seed")
    maps = fitting_maps(spec, FIT_N, FIT_SEED)
    e_rms, d_eff = _error_and_size(run_graph(model, maps)["recon"], maps, POOL_PX, NOISE_MM)
    y, x = np.log(e_rms), np.log(d_eff)
    slope = float(np.linalg.lstsq(np.c_[x, np.ones_like(x)], y, rcond=None)[0][0])
    return OodStatistics(
        exponent=slope, d_ref_mm=float(np.exp(np.median(x))), noise_mm=NOISE_MM, pool_px=POOL_PX,
        source=f"{FIT_N} fresh contacts of the training generator, seed {FIT_SEED} (training seed {spec.seed}), "
               f"every second one with 10 um white + 20 um smooth sensor noise")


def apply_to_export(onnx_path: Path, bundle_path: Path) -> dict:
    """Replace ``ood_score`` in the shipped graph ``onnx_path`` and its fp32 twin
    (``<stem>_fp32.onnx``) by this module's score, with the new threshold in their metadata and the
    model card (``<stem>.json``/``.md``); vertices are checked bit-identical on the held-out maps.
    Returns {"ood": the card's new entry, "ood_threshold_mm", "files"}. Files are replaced together
    at the end (atomic each); a graph that already has the score is a ValueError."""
    import onnx

    from tactile_deploy.onnx_runtime.metadata import read_metadata, set_metadata
    from tactile_deploy.training.card import write_card
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.export import card_metadata
    from tactile_deploy.training.train import load_bundle

    onnx_path = Path(onnx_path)
    twin = onnx_path.with_name(onnx_path.stem + "_fp32.onnx")
    card_json, card_md = onnx_path.with_suffix(".json"), onnx_path.with_suffix(".md")
    for f in (onnx_path, card_json):
        if not f.is_file():
            raise FileNotFoundError(f"{f}: no such file (the exported graph and its model card)")
    paths = [onnx_path] + ([twin] if twin.is_file() else [])
    model_pt, bundle = load_bundle(bundle_path)
    spec = TrainConfig.model_validate(bundle["config"]).data.synthetic
    if spec is None:
        raise ValueError(f"{bundle_path}: config.data.synthetic is not set: no generator for fresh contacts")
    graphs = {p: onnx.load(str(p)) for p in paths}
    for p, g in graphs.items():
        if is_edited(g):
            raise ValueError(f"{p}: ood_score is already the size-normalised score; re-export the graph first")
    stats = fit_statistics(graphs[onnx_path], spec)
    held = fitting_maps(spec, HELD_N, HELD_SEED)
    edited, results = {}, {}
    for p, g in graphs.items():
        edited[p] = append_score(g, stats)
        before, after = run_graph(g, held), run_graph(edited[p], held)
        if not np.array_equal(before["vertices"], after["vertices"]):
            raise RuntimeError(f"{p}: vertices changed by the score's nodes (max "
                               f"{np.abs(before['vertices'] - after['vertices']).max():.3g} mm); nothing written")
        ref = score_numpy(after["recon"], held, stats)
        results[p] = {"score": after["ood_score"], "vs_numpy": float(np.abs(after["ood_score"] - ref).max())}
    score = results[onnx_path]["score"].astype(np.float64)
    threshold = float(np.quantile(score, 0.99))
    card = json.loads(card_json.read_text())
    ood = {"score": SCORE_KIND,
           "formula": "sqrt(mean(avgpool_8x8(recon - depth)**2) + noise**2) * (d_ref / sqrt(mean(depth**2) + noise**2)) ** b, mm",
           "statistics": asdict(stats),
           "threshold_source": f"99th percentile on {HELD_N} fresh contacts of the training generator, seed "
                               f"{HELD_SEED}, every second one with the sensor noise",
           "recon_rmse_mm_p99_exported": card["ood"].get("recon_rmse_mm_p99"),
           **{f"score_mm_p{q}": float(np.quantile(score, q / 100)) for q in (50, 95, 99)},
           "score_mm_max": float(score.max()),
           "graph_vs_numpy_max_abs_diff_mm": max(r["vs_numpy"] for r in results.values())}
    card["ood"] = ood
    card["ood_threshold_mm"] = threshold
    card["outputs"]["ood_score"] = ("[N] float32, mm, coarse (8 x 8 px) reconstruction error of the depth map by the lean "
                                    "image decoder, normalised to a contact of median size (see ood)")
    import torch

    k = min(128, HELD_N)  # the fp32 graph's score against the formula on the torch model's reconstruction
    with torch.no_grad():
        x = model_pt.normalise_depth(torch.as_tensor(held[:k, None]))
        recon_t = (model_pt.ood_decoder(model_pt.image_vae.encoder(x)[0]) * model_pt.norm.depth_scale_mm).numpy()
    ref_graph = twin if twin in results else onnx_path
    card["parity"]["ood_max_abs_diff_mm"] = float(np.abs(results[ref_graph]["score"][:k] - score_numpy(recon_t, held[:k], stats)).max())
    card["parity"]["ood_inputs"] = f"the first {k} of the threshold's maps (seed {HELD_SEED})"
    if twin in results:
        card["parity"]["shipped_vs_fp32_ood_max_abs_diff_mm"] = float(np.abs(results[onnx_path]["score"] - results[twin]["score"]).max())
    writes = paths + [card_json, card_md]
    tmp = {p: p.with_name(f".{p.stem}.{os.getpid()}.partial{p.suffix}") for p in writes}
    try:
        for p in paths:  # the exported metadata, with the card's new OOD entries
            set_metadata(edited[p], card_metadata(card) | {"variant": read_metadata(p)["variant"],
                                                           "ood_score": SCORE_KIND})
            onnx.save(edited[p], str(tmp[p]))
        data = tmp[onnx_path].read_bytes()
        card["files"]["onnx_sha256"] = hashlib.sha256(data).hexdigest()
        card["files"]["onnx_mb"] = round(len(data) / 2**20, 3)
        write_card(card, tmp[card_json], tmp[card_md])
        for p in writes:
            os.replace(tmp[p], p)
    finally:
        for t in tmp.values():
            t.unlink(missing_ok=True)
    return {"ood": ood, "ood_threshold_mm": threshold, "files": [str(p) for p in paths]}
