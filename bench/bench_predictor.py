"""Image-to-mesh predictor: speed and accuracy of every export variant, one CPU thread.

    python bench/bench_predictor.py [--bundle exported/gelslim_mesh.pt | --run RUN_DIR] [--rounds 300]
                                    [--variants naive,fused,lean,fused-int8,lean-int8]
                                    [--json results.json] [--small] [--no-write]
    (or: tactile-deploy bench predictor)

For each variant of :mod:`tactile_deploy.training.export` (one ONNX graph: depth [N, 1, 128, 128] mm ->
vertices, displacement [N, 5380, 3] mm and ood_score [N]) this measures, in one run:

* p50 / p95 latency of one call at batch 1 (onnxruntime, 1 intra-op thread), and the time per
  mesh at batch 8; calls of all variants and of the baselines are interleaved round by round, so
  a busy machine slows them alike; every time is also given as a ratio to the two baselines
  measured in the same run: **torch eager** (the trained modules, fp32, 1 thread, no grad) and
  the **naive** export;
* accuracy on the run's held-out contacts (never seen in training): vertex RMSE (mm, the paper's
  metric), relative displacement error, largest node error, and the largest difference from the
  torch model the variant comes from (mm);
* with ``--ood-data`` (depth maps of novel indenters): the AUROC of ``ood_score`` separating the
  held-out maps from those (1 = perfect, 0.5 = chance);
* the file size.

Data: ``--run`` reads a training run's ``heldout.npz``; with ``--bundle`` (default: the committed
``exported/gelslim_mesh.pt``) the held-out maps are fresh contacts of the model's training
distribution (another seed, simulated on the CPU: ~15 s) and the OOD maps 256 contacts of the
novel indenters (never trained on). The GPU figures (torch on an H100, ``bench/bench_predictor_cuda.py``,
``bench/results/predictor_cuda_h100.json``) are quoted beside the CPU table. Results go to
BENCHMARKS.md (section ``predictor``) unless ``--small`` or ``--no-write``.

``--small`` builds an untrained model of the default architecture (random weights, held-out maps
from random presses of a disc) and runs two variants with few rounds: a check that the benchmark
works, in well under a minute; its accuracy columns are meaningless.
Target (issue "The learned image-to-mesh predictor"): p50 <= 1 ms per mesh at batch 1.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TARGET_P50_MS = 1.0


def _small_model():
    """Untrained default-architecture predictor and synthetic held-out maps (for --small)."""
    import numpy as np
    import torch

    from tactile_deploy.training.config import DataConfig, SyntheticData, TrainConfig
    from tactile_deploy.training.train import build_model

    cfg = TrainConfig(run_dir="unused", data=DataConfig(synthetic=SyntheticData(n_samples=1)))
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    model.norm.set_scales(0.6, (0.05, 0.05, 0.05))
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:128, 0:128]
    depth = np.zeros((16, 1, 128, 128), np.float32)
    for i in range(16):
        cy, cx, r = rng.uniform(30, 98), rng.uniform(30, 98), rng.uniform(5, 15)
        depth[i, 0] = np.clip(0.8 * (1 - ((yy - cy) ** 2 + (xx - cx) ** 2) / r**2), 0, None)
    disp = np.zeros((16, model.norm.rest_vertices_mm.shape[0], 3), np.float32)
    return model, {"metrics": {}}, depth, disp


def auroc(inside, outside) -> float:
    """Area under the ROC curve of a score meant to be larger ``outside`` (Mann-Whitney U)."""
    import numpy as np
    from scipy.stats import rankdata

    ranks = rankdata(np.concatenate([inside, outside]))
    n_in, n_out = len(inside), len(outside)
    return float((ranks[n_in:].sum() - n_out * (n_out + 1) / 2) / (n_in * n_out))


def _relative(err, true):
    """||err|| / ||true||, or None when there is no true displacement (--small)."""
    import numpy as np

    norm = float(np.linalg.norm(true))
    return float(np.linalg.norm(err) / norm) if norm > 0 else None


def main(argv=None) -> int:
    import numpy as np
    import torch

    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.training.export import VARIANTS, DeployGraph, export_variant, run_session, torch_reference

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default=str(ROOT / "exported" / "gelslim_mesh.pt"), help="training bundle (model.pt)")
    ap.add_argument("--run", help="a training run folder (model.pt, heldout.npz, config.json) instead of --bundle")
    ap.add_argument("--n-heldout", type=int, default=512, help="fresh held-out contacts with --bundle")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    ap.add_argument("--rounds", type=int, default=300)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--ood-data", help="npz with depth_mm of out-of-distribution maps (novel indenters): adds the "
                    "AUROC of each variant's ood_score, held-out maps against these")
    ap.add_argument("--json", help="also write the results to this JSON file")
    ap.add_argument("--small", action="store_true", help="untrained model, 2 variants, few rounds")
    args = ap.parse_args(argv)

    torch.set_num_threads(1)
    variants = args.variants.split(",")
    rounds = args.rounds
    if args.small:
        model, bundle, depth, true = _small_model()
        variants, rounds = ["lean", "lean-int8-fastood"], min(rounds, 20)
    else:
        from tactile_deploy.training.config import TrainConfig
        from tactile_deploy.training.data import fresh_contacts
        from tactile_deploy.training.train import load_bundle

        if args.run:
            run = Path(args.run)
            model, bundle = load_bundle(run / "model.pt")
            held = np.load(run / "heldout.npz")
            depth = held["depth_mm"][:, None].astype(np.float32)
            true = held["displacement_mm"]
        else:
            model, bundle = load_bundle(args.bundle)
            spec = TrainConfig.model_validate(bundle["config"]).data.synthetic
            held = fresh_contacts(spec, args.n_heldout, spec.seed + 1_000_000)
            depth, true = held.depth_mm[:, None].astype(np.float32), held.displacement_mm
            if not args.ood_data:
                from tactile_deploy.indenters import list_indenters

                novel = spec.model_copy(update={"indenters": tuple(list_indenters("novel")), "seed": 11})
                args.ood_maps = fresh_contacts(novel, 256, 12).depth_mm[:, None].astype(np.float32)
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")

    tmp = Path(tempfile.mkdtemp(prefix="bench_predictor_"))
    if args.small:
        calib = depth
    else:  # maps of the training distribution, as the shipped export calibrates on; never the held-out ones
        from tactile_deploy.training.config import TrainConfig
        from tactile_deploy.training.export import calibration_maps, heldout_seed

        calib, _ = calibration_maps(TrainConfig.model_validate(bundle["config"]),
                                    heldout_seed=heldout_seed(held) if args.run else None)
    sessions, sizes, export_s = {}, {}, {}
    for v in variants:
        t0 = time.perf_counter()
        path = export_variant(model, v, tmp / f"{v}.onnx", calib if "-int8" in v else None)
        export_s[v] = time.perf_counter() - t0
        sizes[v] = sum(p.stat().st_size for p in tmp.glob(f"{v}.onnx*")) / 2**20
        sessions[v] = make_session(path, threads=1, providers="cpu")
        print(f"exported {v} ({export_s[v]:.0f} s, {sizes[v]:.1f} MiB)", file=sys.stderr)

    # torch eager baselines: the trained modules (sparse products, no folding), fp32, no grad
    scale_mask = model.norm.displacement_scale_mm * model.norm.free_mask
    eager = {
        "coma": DeployGraph(model, model.mesh_vae.decoder, scale_mask).eval(),
        "lean": DeployGraph(model, model.lean_decoder, scale_mask).eval(),
    }

    # -- accuracy -------------------------------------------------------------------------------
    k = len(depth)
    refs = {fam: torch_reference(model, fam, depth) for fam in ("coma", "lean")}
    ood_maps = getattr(args, "ood_maps", None)
    if args.ood_data:
        ood_maps = np.load(args.ood_data)["depth_mm"][:, None].astype(np.float32)
    acc = {}
    for v in variants:
        _, disp, ood = run_session(sessions[v], depth)
        ood_auc = auroc(ood, run_session(sessions[v], ood_maps)[2]) if ood_maps is not None else None
        ref = refs["lean" if v.startswith("lean") else "coma"][0]
        err = (disp - true).astype(np.float64)
        acc[v] = {
            "vertex_rmse_mm": float(np.sqrt(np.mean(err**2))),
            "relative_error": _relative(err, true),
            "max_error_mm": float(np.linalg.norm(err, axis=-1).max()),
            "max_diff_vs_torch_mm": float(np.abs(disp - ref).max()),
            "ood_auroc": ood_auc,
        }
    for fam in ("coma", "lean"):
        err = (refs[fam][0] - true).astype(np.float64)
        acc[f"torch-{fam}"] = {
            "vertex_rmse_mm": float(np.sqrt(np.mean(err**2))),
            "relative_error": _relative(err, true),
            "max_error_mm": float(np.linalg.norm(err, axis=-1).max()),
            "max_diff_vs_torch_mm": 0.0,
            "ood_auroc": None,
        }

    # -- speed: interleaved rounds --------------------------------------------------------------
    inputs = [depth[i % k : i % k + 1] for i in range(16)]
    batch8 = np.concatenate([depth[i % k : i % k + 1] for i in range(8)])
    names = [f"torch-{f}" for f in eager] + variants
    t1 = {n: [] for n in names}
    t8 = {n: [] for n in names}

    def call(n, x):
        if n.startswith("torch-"):
            with torch.no_grad():
                eager[n.removeprefix("torch-")](torch.as_tensor(x))
        else:
            sessions[n].run(None, {"depth": x})

    for n in names:  # warm-up
        for x in inputs[:5]:
            call(n, x)
        call(n, batch8)
    for r in range(rounds):
        for n in names:
            x = inputs[r % len(inputs)]
            t0 = time.perf_counter_ns()
            call(n, x)
            t1[n].append((time.perf_counter_ns() - t0) / 1e6)
        if r % 10 == 0:
            for n in names:
                t0 = time.perf_counter_ns()
                call(n, batch8)
                t8[n].append((time.perf_counter_ns() - t0) / 1e6 / 8)

    def p(n, q, d=t1):
        return float(np.percentile(d[n], q))

    base_torch, base_naive = p("torch-coma", 50), (p("naive", 50) if "naive" in names else None)
    rows = []
    for n in names:
        rows.append({
            "variant": n,
            "decoder": "lean grid" if "lean" in n else "COMA",
            "precision": "int8" if "-int8" in n else "fp32",
            "p50_ms": p(n, 50), "p95_ms": p(n, 95), "per_mesh_batch8_ms": p(n, 50, t8),
            "vs_torch_eager": p(n, 50) / base_torch,
            "vs_naive": p(n, 50) / base_naive if base_naive else None,
            "file_mb": sizes.get(n),
            **acc[n],
        })
    import platform

    lines = [
        f"Predictor variants, one onnxruntime / torch thread, {platform.processor() or platform.machine()}; "
        f"{rounds} interleaved rounds, {k} held-out maps; target p50 <= {TARGET_P50_MS} ms.",
        "",
        "| variant | decoder | precision | p50 ms (batch 1) | p95 ms | ms/mesh (batch 8) | vs torch eager | vs naive "
        "| vertex RMSE mm | rel. error | max error mm | max diff vs torch mm | OOD AUROC | file MiB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['variant']} | {r['decoder']} | {r['precision']} | {r['p50_ms']:.3f} | {r['p95_ms']:.3f} "
            f"| {r['per_mesh_batch8_ms']:.3f} | {r['vs_torch_eager']:.3f} | "
            + (f"{r['vs_naive']:.3f}" if r["vs_naive"] is not None else "-")
            + f" | {r['vertex_rmse_mm']:.4f} | "
            + (f"{r['relative_error']:.3f}" if r["relative_error"] is not None else "-")
            + f" | {r['max_error_mm']:.3f} "
            f"| {r['max_diff_vs_torch_mm']:.1e} | "
            + (f"{r['ood_auroc']:.3f}" if r["ood_auroc"] is not None else "-")
            + " | " + (f"{r['file_mb']:.1f}" if r["file_mb"] else "-") + " |"
        )
    gpu_path = ROOT / "bench" / "results" / "predictor_cuda_h100.json"
    if gpu_path.exists():
        gpu = json.loads(gpu_path.read_text())
        lines += [
            "",
            f"GPU ({gpu['device_name']}, torch {gpu['torch']}; onnxruntime's CUDA provider is not in that machine's "
            f"image): the trained torch modules, eager fp32 and replayed as a CUDA graph, {gpu['rounds']} calls, "
            "CUDA events (`bench/bench_predictor_cuda.py`):",
            "",
            "| decoder | batch | eager p50 ms | CUDA graph p50 ms | graph vs eager | ms per mesh |",
            "|---|---|---|---|---|---|",
        ]
        for g in gpu["rows"]:
            lines.append(f"| {g['decoder']} | {g['batch']} | {g['eager_p50_ms']:.3f} | {g.get('graph_p50_ms', float('nan')):.3f} "
                         f"| {g['eager_p50_ms'] / g.get('graph_p50_ms', float('nan')):.1f}x | {g['per_mesh_ms']:.4f} |")
    print("\n".join(lines))
    if not args.small and not args.no_write:
        from bench.report import machine_line, write_section

        source = args.run or args.bundle
        write_section("predictor", "## Image-to-mesh predictor (`tactile-deploy bench predictor`)\n\n"
                      f"{machine_line()}; model {Path(source).name}.\n\n" + "\n".join(lines))
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "rounds": rounds, "n_heldout": k}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
