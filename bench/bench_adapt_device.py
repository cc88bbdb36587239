"""Adaptation steps per second of the committed exported step on one torch device, with nothing
but torch, numpy, onnx, onnxruntime and pydantic installed (no camera, mesh or CLI libraries).

    python bench/bench_adapt_device.py --device cuda --out bench/results/adapt_cuda_h100.json \
        [--batch 16] [--steps 200] [--frames 200] [--repeat 50] [--step exported/gelslim_mesh_adapt]

Run from the repository root (the ``tactile_deploy`` package is imported from the source tree,
not installed). Inputs: ``--frames`` seeded synthetic presses (Gaussian dents of 0.2-1.0 mm,
radius 1.5-4 mm, centres within +-8 mm, on the model grid; the pad's disc as weight); a step
costs the same on a sensor's maps, its shapes being fixed.

Measures, in one run (:func:`run`):

* ``step``: one Adam step (forward + loss + backward + update) of the program at ``--batch``,
  median and p90 over ``--repeat`` steps after 3 warm-up steps (device synchronised), as
  steps/s and maps/s;
* ``adapt``: :func:`tactile_deploy.adapt.step.adapt` as ``tactile-deploy adapt`` runs it:
  the VAE filter's targets (onnxruntime, CPU), ``--steps`` Adam steps over the ``--frames``
  maps, and the evaluation of 20 % held-out maps before and after; wall time of each part;
* the first call's time (program load + first step: CUDA start-up and kernel selection).

Writes a JSON result to ``--out`` (``bench/results/adapt_cuda_*.json`` is quoted by
``tactile-deploy bench adapt`` in BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

GRID = 128
HALF_EXTENT_MM = 17.5


def synthetic_presses(n: int, seed: int = 0) -> np.ndarray:
    """(n, 128, 128) float32 mm: Gaussian dents on the model grid (row 0 = largest y), 0 off the pad."""
    rng = np.random.default_rng(seed)
    c = -HALF_EXTENT_MM + (np.arange(GRID) + 0.5) * 2 * HALF_EXTENT_MM / GRID
    x, y = np.meshgrid(c, -c)
    out = np.empty((n, GRID, GRID), np.float32)
    for k in range(n):
        cx, cy = rng.uniform(-8, 8, 2)
        r = rng.uniform(1.5, 4.0)
        out[k] = rng.uniform(0.2, 1.0) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r * r))
    return out * (np.hypot(x, y) < HALF_EXTENT_MM)


def pad_disc() -> np.ndarray:
    """(128, 128) float32: 1 at pixel centres on the pad (radius 17.5 mm), else 0."""
    c = -HALF_EXTENT_MM + (np.arange(GRID) + 0.5) * 2 * HALF_EXTENT_MM / GRID
    x, y = np.meshgrid(c, -c)
    return (np.hypot(x, y) < HALF_EXTENT_MM).astype(np.float32)


def _sync(torch, device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run(step_dir: Path, device_name: str, batch: int, steps: int, frames: int, repeat: int, seed: int = 0) -> dict:
    import torch

    from tactile_deploy.adapt.step import AdaptSettings, StepProgram, adapt, evaluate, vae_filter

    device = torch.device(device_name)
    t0 = time.perf_counter()
    program = StepProgram.load(step_dir, device_name)
    depth = synthetic_presses(frames, seed)
    weight = pad_disc()
    t_filter = time.perf_counter()
    target = vae_filter(program, depth)
    t_filter = time.perf_counter() - t_filter
    params = program.trainable()
    opt = torch.optim.Adam(params, lr=1e-6)
    d = torch.as_tensor(depth[:batch, None]).to(device)
    t = torch.as_tensor(target[:batch]).to(device)
    w = torch.as_tensor(weight).to(device)

    def one_step() -> float:
        _sync(torch, device)
        s = time.perf_counter()
        loss = program.module(d, t, w)[0]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        _sync(torch, device)
        return time.perf_counter() - s

    first = one_step() + (time.perf_counter() - t0)  # load + first step
    for _ in range(2):
        one_step()
    times = [one_step() for _ in range(repeat)]
    med = statistics.median(times)
    p90 = float(np.quantile(times, 0.9))

    # adapt as the command does (fresh weights)
    program = StepProgram.load(step_dir, device_name)
    n_held = max(1, frames // 5)
    tr, ho = np.arange(n_held, frames), np.arange(n_held)
    s = time.perf_counter()
    before = evaluate(program, depth[ho], target[ho], weight)
    t_eval = time.perf_counter() - s
    hist = adapt(program, depth[tr], target[tr], weight, AdaptSettings(steps=steps, batch_size=batch, lr=1e-4, seed=seed))
    s = time.perf_counter()
    after = evaluate(program, depth[ho], target[ho], weight)
    t_eval += time.perf_counter() - s
    total = t_filter + hist.seconds + t_eval
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
        mem = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        name = f"CPU {platform.processor() or platform.machine()} ({os.cpu_count()} logical CPUs)"
        mem = None
    import onnxruntime

    return {
        "benchmark": "adapt-device",
        "device": device_name,
        "device_name": name,
        "torch": torch.__version__,
        "onnxruntime": onnxruntime.__version__,
        "threads": torch.get_num_threads(),
        "step_folder": str(step_dir),
        "step_sha256": program.card.files["step"].sha256,
        "inputs": f"{frames} synthetic presses (seed {seed})",
        "batch": batch,
        "step": {"repeat": repeat, "median_s": med, "p90_s": p90, "steps_per_s": 1.0 / med, "maps_per_s": batch / med},
        "first_call_s": first,
        "adapt": {"frames": frames, "held_out": int(n_held), "steps": steps, "filter_s": t_filter,
                  "steps_s": hist.seconds, "evaluate_s": t_eval, "total_s": total,
                  "steps_per_s": steps / max(hist.seconds, 1e-9),
                  "loss_first_mm2": hist.loss_mm2[0], "loss_last_mm2": hist.loss_mm2[-1],
                  "heldout_rmse_before_mm": before.rmse_mm, "heldout_rmse_after_mm": after.rmse_mm},
        "max_memory_allocated_mib": mem,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda", help="torch device: cuda, cuda:1, cpu")
    ap.add_argument("--out", type=Path, required=True, help="JSON result file")
    ap.add_argument("--step", type=Path, default=ROOT / "exported" / "gelslim_mesh_adapt")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--steps", type=int, default=200, help="Adam steps of the adapt run")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=50, help="timed steps of the step measurement")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    args = ap.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit(f"--device {args.device}: this torch ({torch.__version__}) sees no CUDA device")
    result = run(args.step, args.device, args.batch, args.steps, args.frames, args.repeat)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".partial")
    tmp.write_text(json.dumps(result, indent=1))
    os.replace(tmp, args.out)
    st, ad = result["step"], result["adapt"]
    print(f"{result['device_name']}: Adam step at batch {args.batch}: {st['median_s'] * 1e3:.1f} ms median = "
          f"{st['steps_per_s']:.1f} steps/s ({st['maps_per_s']:.0f} maps/s); adapt on {ad['frames']} frames, "
          f"{ad['steps']} steps: {ad['total_s']:.1f} s (steps {ad['steps_s']:.1f} s); wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
