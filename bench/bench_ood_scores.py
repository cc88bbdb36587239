"""Out-of-distribution scores of the shipped predictor side by side: which cheap score, computed
from what the shipped graph already holds, separates novel indenters from the training ones.

    python bench/bench_ood_scores.py [--shipped exported/gelslim_mesh.onnx] [--bundle exported/gelslim_mesh.pt]
        [--json bench/results/ood_scores.json] [--baseline EXPORTED.onnx [--rounds 600]]

Every score is computed from tensors of the shipped graph (``--shipped``, run with onnxruntime on
one CPU thread, those tensors added as outputs): the image encoder's latent mean ``mu`` (128) and
the hidden layer it is read from (128), the lean image decoder's reconstruction ``recon``
(N, 1, 128, 128) mm and the input ``depth`` (mm); the latent log-variance comes from the committed
bundle's ``logvar`` layer (``--bundle``) applied to that hidden layer (not in the shipped graph:
one 128 x 128 product). ``exported`` is the score the export writes, ``RMS(recon - depth)`` (mm);
the graph's own ``ood_score`` is the size-normalised score of :mod:`tactile_deploy.training.ood_score`
once ``python -m tactile_deploy.training ood-score`` has run.

Sets (the first two are the ones ``bench/bench_predictor.py`` measures its OOD AUROC on):

* ``inside``: 256 fresh frictionless contacts of the training indenters
  (:func:`tactile_deploy.training.evaluation.simulate_domain` ``primitives``, seed 3003);
* ``novel``: 256 contacts of the library's novel indenters (``list_indenters("novel")``, seed 12);
* ``noisy``: both sets with the evaluation's sensor noise (10 um white + 20 um smooth,
  :func:`tactile_deploy.training.evaluation.add_sensor_noise`): the training run augmented its
  maps with noise of that size (pixel noise 10 um, smooth noise up to 30 um, half of the maps);
* ``confirm``: another sample of both (training generator seed 5005, novel seed 13);
* ``shared STL``: 256 contacts of the shared STL indenters (``unseen_shapes``, seed 3003) against
  ``inside``.

Statistics (latent Gaussians with 1 % shrinkage, the exponents of the size-normalised scores, the
z-scores) are fitted on the maps :mod:`tactile_deploy.training.ood_score` fits on (1,024 fresh
contacts of the training generator, seed 4007, every second one with the sensor noise); the
threshold of each score is its 99th percentile on 512 fresh contacts of seed 1007 (half noisy).
Nothing is fitted on a novel indenter. Columns: AUROC (Mann-Whitney; 1 = perfect, 0.5 = chance)
per pair of sets, and the share of each set above the score's threshold.

``pool p ratio[, noise allowance s]``: ``sqrt(RMS(avgpool_p(recon - depth))**2 + s**2) * (d_ref / d_eff) ** b``
(mm), ``d_eff = sqrt(mean(depth**2) + 0.02**2)`` mm, ``b`` and ``d_ref`` fitted on the fit set
(least squares of the log score on ``log d_eff``; ``d_ref`` its median): the coarse reconstruction
error relative to what a training contact of that size shows. ``z(a) + z(b)``: the sum of the two
log scores standardised on the fit set. ``--baseline`` times the shipped graph against another
graph (batch 1, one thread, interleaved rounds).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CONFIRM_SEED, NOVEL_CONFIRM_SEED = 5005, 13
FLOOR_MM = 0.02


def _graph_tensors(model):
    """Names of the reconstruction, latent mean and hidden layer in the shipped graph (exported or
    with the size-normalised score): the reconstruction as :func:`tactile_deploy.training.ood_score.recon_tensor`
    finds it; the latent mean is the layer with weight ``mu.weight``: one Gemm, or a MatMul with
    the (transposed) weight followed by the Add of ``mu.bias`` (as the dynamo exporter writes it)."""
    from tactile_deploy.training.ood_score import recon_tensor

    nodes = model.graph.node
    gemm = [n for n in nodes if n.op_type == "Gemm" and n.input[1] == "mu.weight"]
    if len(gemm) == 1:
        return {"recon": recon_tensor(model), "mu": gemm[0].output[0], "hidden": gemm[0].input[0]}
    matmul = [n for n in nodes if n.op_type == "MatMul" and n.input[1].startswith("mu.weight")]
    bias = [n for n in nodes if n.op_type == "Add" and matmul and matmul[0].output[0] in n.input
            and "mu.bias" in n.input]
    if len(matmul) != 1 or len(bias) != 1:
        raise ValueError(f"expected the latent mean as one Gemm, or one MatMul + Add, with weight mu.weight; "
                         f"found {len(gemm)} Gemm, {len(matmul)} MatMul, {len(bias)} Add")
    return {"recon": recon_tensor(model), "mu": bias[0].output[0], "hidden": matmul[0].input[0]}


def _sets(spec, shared: Path):
    """{name: depth maps (N, 128, 128) float32 mm}."""
    import numpy as np

    from tactile_deploy.indenters import list_indenters
    from tactile_deploy.training.config import SyntheticData
    from tactile_deploy.training.data import fresh_contacts
    from tactile_deploy.training.evaluation import add_sensor_noise, simulate_domain
    from tactile_deploy.training.ood_score import FIT_N, FIT_SEED, HELD_N, HELD_SEED, fitting_maps

    novel = SyntheticData(n_samples=1, indenters=tuple(list_indenters("novel")), seed=11)
    s = {"inside": simulate_domain("primitives", 256, 3003, shared).depth_mm,
         "novel": fresh_contacts(novel, 256, 12).depth_mm,
         "confirm_inside": fresh_contacts(spec, 256, CONFIRM_SEED).depth_mm,
         "confirm_novel": fresh_contacts(novel, 256, NOVEL_CONFIRM_SEED).depth_mm,
         "shared_stl": simulate_domain("unseen_shapes", 256, 3003, shared).depth_mm,
         "fit": fitting_maps(spec, FIT_N, FIT_SEED), "held": fitting_maps(spec, HELD_N, HELD_SEED)}
    s["noisy_inside"] = add_sensor_noise(s["inside"], np.random.default_rng([3003, 99]))
    s["noisy_novel"] = add_sensor_noise(s["novel"], np.random.default_rng([12, 99]))
    return {k: v.astype(np.float32) for k, v in s.items()}


def main(argv=None) -> int:
    import numpy as np
    import onnx
    import torch

    from bench.bench_predictor import auroc
    from tactile_deploy.training.config import TrainConfig
    from tactile_deploy.training.ood_score import FIT_SEED, HELD_SEED, graph_session
    from tactile_deploy.training.train import load_bundle

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shipped", default=str(ROOT / "exported" / "gelslim_mesh.onnx"))
    ap.add_argument("--bundle", default=str(ROOT / "exported" / "gelslim_mesh.pt"))
    ap.add_argument("--shared", default=str(ROOT.parent / "shared" / "data" / "indenters"))
    ap.add_argument("--json", help="write the table to this JSON file")
    ap.add_argument("--baseline", help="a graph to time the shipped one against (batch 1, one thread, interleaved), "
                    "e.g. the exported graph before `python -m tactile_deploy.training ood-score`")
    ap.add_argument("--rounds", type=int, default=600, help="timing rounds")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    model_pt, bundle = load_bundle(args.bundle)
    spec = TrainConfig.model_validate(bundle["config"]).data.synthetic
    if spec is None:
        raise SystemExit(f"{args.bundle}: config.data.synthetic is not set: no generator to draw fresh contacts from")
    t0 = time.perf_counter()
    sets = _sets(spec, Path(args.shared))
    print(f"sets simulated ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)

    graph = onnx.load(args.shipped)
    kind = {p.key: p.value for p in graph.metadata_props}.get("ood_score", "exported: RMS(recon - depth)")
    t = _graph_tensors(graph)
    names = ["ood_score", t["recon"], t["mu"], t["hidden"]]
    sess = graph_session(graph, names[1:])
    out = {}
    for k, x in sets.items():
        parts = [sess.run(names, {"depth": x[i:i + 64, None]}) for i in range(0, len(x), 64)]
        out[k] = {n: np.concatenate([p[j] for p in parts]).astype(np.float64) for j, n in enumerate(names)}
    enc = model_pt.image_vae.encoder
    w_lv, b_lv = (p.detach().double().numpy() for p in (enc.logvar.weight, enc.logvar.bias))

    def gaussian(x, shrink=0.01):
        c = np.cov(x, rowvar=False)
        c = (1 - shrink) * c + shrink * np.trace(c) / len(c) * np.eye(len(c))
        return x.mean(0), np.linalg.inv(c)

    def maha(x, g):
        d = x - g[0]
        return np.sqrt(np.einsum("ij,jk,ik->i", d, g[1], d))

    def pooled(k, p):
        err = out[k][t["recon"]][:, 0] - sets[k]
        e = err.reshape(len(err), 128 // p, p, 128 // p, p).mean((2, 4))
        return np.sqrt((e**2).mean((1, 2)))

    def d_eff(k):
        return np.sqrt((sets[k].astype(np.float64) ** 2).mean((1, 2)) + FLOOR_MM**2)

    fitted = {}

    def pool_ratio(p, sigma=0.0):
        y, d = np.log(np.sqrt(pooled("fit", p) ** 2 + sigma**2)), d_eff("fit")
        b = float(np.linalg.lstsq(np.c_[np.log(d), np.ones(len(d))], y, rcond=None)[0][0])
        d_ref = float(np.exp(np.median(np.log(d))))
        fitted[f"pool {p} ratio, noise allowance {sigma} mm"] = {"b": b, "d_ref_mm": d_ref}
        return lambda k: np.sqrt(pooled(k, p) ** 2 + sigma**2) * (d_ref / d_eff(k)) ** b

    g_mu = gaussian(out["fit"][t["mu"]])
    g_h = gaussian(out["fit"][t["hidden"]])
    fit_mu = out["fit"][t["mu"]]

    def kl(k):
        mu, lv = out[k][t["mu"]], out[k][t["hidden"]] @ w_lv.T + b_lv
        return 0.5 * np.sum(mu**2 + np.exp(lv) - lv - 1, axis=1)

    def knn1(k):
        x = out[k][t["mu"]]
        d2 = (x**2).sum(1)[:, None] + (fit_mu**2).sum(1)[None] - 2 * x @ fit_mu.T
        d2 = np.sort(np.maximum(d2, 0), 1)
        return np.sqrt(d2[:, 1] if k == "fit" else d2[:, 0])

    def contact_recon(k):
        err, m = out[k][t["recon"]][:, 0] - sets[k], sets[k] > 0.02
        return np.sqrt((err**2 * m).sum((1, 2)) / np.maximum(m.sum((1, 2)), 1))

    def full_vae(k):
        with torch.no_grad():
            return model_pt.image_reconstruction_rmse(torch.as_tensor(sets[k][:, None]), "vae").double().numpy()

    scores = {
        "exported: RMS(recon - depth) mm": lambda k: np.sqrt(np.mean((out[k][t["recon"]][:, 0] - sets[k]) ** 2, axis=(1, 2))),
        f"the graph's ood_score ({kind})": lambda k: out[k]["ood_score"],
        "VAE KL term of the latent": kl,
        "Mahalanobis of mu": lambda k: maha(out[k][t["mu"]], g_mu),
        "Mahalanobis of the encoder's hidden layer": lambda k: maha(out[k][t["hidden"]], g_h),
        "nearest fit latent (L2 of mu)": knn1,
        "RMS(recon - depth) where depth > 0.02 mm": contact_recon,
        "full image VAE decoder RMS (not cheap: 2x the graph)": full_vae,
        "pool 1 ratio": pool_ratio(1),
        "pool 4 ratio": pool_ratio(4),
        "pool 8 ratio": pool_ratio(8),
        "pool 16 ratio": pool_ratio(16),
        "pool 4 ratio, noise allowance 0.02 mm": pool_ratio(4, 0.02),
        "pool 8 ratio, noise allowance 0.01 mm": pool_ratio(8, 0.01),
        "pool 8 ratio, noise allowance 0.02 mm (training/ood_score.py)": pool_ratio(8, 0.02),
        "pool 8 ratio, noise allowance 0.03 mm": pool_ratio(8, 0.03),
    }
    values = {name: {k: f(k) for k in sets} for name, f in scores.items()}

    def z(name):
        f = np.log(np.maximum(values[name]["fit"], 1e-12))
        return {k: (np.log(np.maximum(v, 1e-12)) - f.mean()) / f.std() for k, v in values[name].items()}

    for other in ("pool 8 ratio", "pool 4 ratio", "Mahalanobis of mu"):
        a, b_ = z("exported: RMS(recon - depth) mm"), z(other)
        values[f"z(exported) + z({other})"] = {k: a[k] + b_[k] for k in sets}

    pairs = {"bench (clean)": ("inside", "novel"), "noisy": ("noisy_inside", "noisy_novel"),
             "confirm": ("confirm_inside", "confirm_novel"), "shared STL": ("inside", "shared_stl")}
    rows = []
    for name, v in values.items():
        thr = float(np.quantile(v["held"], 0.99))
        rows.append({"score": name, **{f"auroc {p}": auroc(v[a], v[b]) for p, (a, b) in pairs.items()},
                     **{f"share>p99 {k}": float(np.mean(v[k] > thr)) for k in ("inside", "noisy_inside", "novel", "noisy_novel")},
                     "threshold": thr})
    cols = list(rows[0])[1:-1]
    print("| score | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols))
    for r in rows:
        print(f"| {r['score']} | " + " | ".join(f"{r[c]:.3f}" for c in cols) + " |")

    timing = None
    if args.baseline:
        base = graph_session(onnx.load(args.baseline))
        s1 = graph_session(graph)
        xs = [sets["inside"][i:i + 1, None] for i in range(16)]
        for s_ in (base, s1):
            for x in xs[:5]:
                s_.run(None, {"depth": x})
        t_a, t_b = [], []
        for r in range(args.rounds):
            x = xs[r % len(xs)]
            for s_, acc in ((base, t_a), (s1, t_b)):
                c = time.perf_counter()
                s_.run(None, {"depth": x})
                acc.append((time.perf_counter() - c) * 1e3)
        timing = {"baseline": Path(args.baseline).name, "baseline_p50_ms": float(np.median(t_a)),
                  "shipped_p50_ms": float(np.median(t_b)), "paired_median_diff_ms": float(np.median(np.array(t_b) - np.array(t_a))),
                  "rounds": args.rounds}
        print(json.dumps(timing, indent=1))
    if args.json:
        from tactile_deploy.atomic import write_json

        write_json(args.json, {
            "shipped": str(Path(args.shipped).name), "seeds": {"fit": FIT_SEED, "threshold": HELD_SEED, "bench": 3003,
                                                              "novel": 12, "confirm": CONFIRM_SEED, "confirm_novel": NOVEL_CONFIRM_SEED},
            "fitted": fitted, "rows": rows, "timing_batch1_one_thread": timing})
    return 0


if __name__ == "__main__":
    sys.exit(main())
