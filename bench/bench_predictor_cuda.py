"""Image-to-mesh predictor on a GPU: torch latency and throughput of the trained model.

    python bench/bench_predictor_cuda.py --bundle exported/gelslim_mesh.pt [--device cuda] --out results.json

onnxruntime's CUDA provider is not part of the GPU machines' image (only its CPU build is), so
the GPU figures are those of the trained torch modules: eager fp32 (the baseline), and the same
calls replayed as a CUDA graph (one launch per call), for the lean and the COMA decoders, at
batch 1 (p50 / p95 of one call, depth map to vertices) and batch 32 (time per mesh). Timed with
CUDA events after a warm-up, median of ``--rounds`` calls; written as JSON (``bench/results/``),
quoted by ``bench/bench_predictor.py``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _time_calls(fn, device, rounds: int) -> list[float]:
    import torch

    times = []
    for _ in range(rounds):
        if device.type == "cuda":
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            b.synchronize()
            times.append(a.elapsed_time(b))
        else:
            import time

            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
    return times


def run(bundle: str, device_name: str = "cuda", rounds: int = 300) -> dict:
    import numpy as np
    import torch

    from tactile_deploy.training.train import load_bundle

    device = torch.device(device_name)
    model, meta = load_bundle(bundle, device_name)
    model.to(device).eval()
    rng = np.random.default_rng(0)
    out = {"bundle": str(bundle), "device": device_name, "torch": torch.__version__,
           "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor(),
           "rounds": rounds, "rows": []}
    for decoder in ("lean", "coma"):
        model.deploy_decoder = decoder
        for batch in (1, 32):
            depth = torch.as_tensor(rng.uniform(0, 1, (batch, 1, 128, 128)).astype(np.float32), device=device)
            with torch.no_grad():
                eager = lambda: model(depth)  # noqa: E731
                for _ in range(20):
                    eager()
                t_eager = _time_calls(eager, device, rounds)
                row = {"decoder": decoder, "batch": batch, "eager_p50_ms": float(np.median(t_eager)),
                       "eager_p95_ms": float(np.percentile(t_eager, 95))}
                if device.type == "cuda":
                    static = depth.clone()
                    s = torch.cuda.Stream()
                    s.wait_stream(torch.cuda.current_stream())
                    with torch.cuda.stream(s):
                        for _ in range(3):
                            model(static)
                    torch.cuda.current_stream().wait_stream(s)
                    graph = torch.cuda.CUDAGraph()
                    with torch.cuda.graph(graph):
                        g_out = model(static)
                    graph.replay()
                    ref = model(static)
                    row["graph_max_diff_mm"] = float((g_out[0] - ref[0]).abs().max())
                    t_graph = _time_calls(graph.replay, device, rounds)
                    row.update(graph_p50_ms=float(np.median(t_graph)), graph_p95_ms=float(np.percentile(t_graph, 95)))
            row["per_mesh_ms"] = min(row.get("graph_p50_ms", np.inf), row["eager_p50_ms"]) / batch
            out["rows"].append(row)
            print(json.dumps(row))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default=str(ROOT / "exported" / "gelslim_mesh.pt"))
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--rounds", type=int, default=300)
    ap.add_argument("--out", help="JSON file to write")
    args = ap.parse_args()
    res = run(args.bundle, args.device, args.rounds)
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
