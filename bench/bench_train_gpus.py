"""Data-parallel training on 1, 2 and 4 GPUs of one host: throughput, scaling, time to accuracy.

    # on the GPU machine (torchrun + NCCL; one process per GPU):
    python bench/bench_train_gpus.py run --config training/configs/gpu_surface.json --gpus 1,2,4 \\
        --budget 1=90,2=90,4=240 --out out/gpus
    # here, from its results:
    python bench/bench_train_gpus.py report --results bench/results/train_gpus_h100.json [--no-write]

``run`` trains the same configuration (``data.synthetic.split_over_ranks``: the same contacts in
total whatever the number of GPUs, the same batch per GPU) once per GPU count, one after another,
``CUDA_VISIBLE_DEVICES`` set to the first G GPUs, with ``torchrun --standalone --nproc_per_node G -m
training train``; the stage timed is ``surface`` (its ``time_budget_s`` from ``--budget``). NVLink
multicast stays off (NCCL_NVLS_ENABLE=0, TORCH_SYMM_MEM_DISABLE_MULTICAST=1, NVSHMEM_DISABLE_NVLS=1
are set for every process). From each run's ``history.json``:

* **samples/s**: training samples of all ranks per second of the training loop (validation
  excluded), median over the epochs after the first (the first compiles and warms up);
* **scaling**: samples/s over the 1-GPU run's, and that over G (efficiency);
* **time to target**: seconds of the stage (validation included) until the held-out contact-patch
  RMSE (``val_contact_patch_rmse_um``, all ranks' held-out contacts) first reaches the target
  (``--target-um``, default: the worst of the runs' final figures, so that every run reaches it).

Writes ``results.json`` (and the runs' folders) under ``--out``. ``report`` renders the table into
BENCHMARKS.md (section ``train-gpus``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

NO_MULTICAST = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}
STAGE = "surface"


def summarise(history: list[dict], gpus: int) -> dict:
    """Throughput and the accuracy curve of one run's timed stage."""
    import numpy as np

    rates = [h["samples_per_s"] for h in history[1:]] or [history[0]["samples_per_s"]]
    return {
        "gpus": gpus,
        "epochs": len(history),
        "samples_per_s": float(np.median(rates)),
        "stage_seconds": history[-1]["stage_seconds"],
        "curve": [(h["stage_seconds"], h.get("val_contact_patch_rmse_um"), h["val_rmse_mm"] * 1e3) for h in history],
        "final_contact_patch_rmse_um": history[-1].get("val_contact_patch_rmse_um"),
        "final_vertex_rmse_um": history[-1]["val_rmse_mm"] * 1e3,
    }


def time_to(curve, target_um: float) -> float | None:
    for seconds, patch, _ in curve:
        if patch is not None and patch <= target_um:
            return seconds
    return None


def run(args) -> int:
    import torch

    gpus = [int(g) for g in args.gpus.split(",")]
    budgets = dict(item.split("=") for item in args.budget.split(",")) if args.budget else {}
    available = torch.cuda.device_count() if args.device == "cuda" else max(gpus)
    if max(gpus) > available:
        print(f"error: --gpus asks for {max(gpus)} GPUs, this machine has {available}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"device": torch.cuda.get_device_name(0) if args.device == "cuda" else "cpu (gloo; a check of this script)",
               "torch": torch.__version__, "config": args.config,
               "stage": STAGE, "runs": []}
    env = dict(os.environ) | NO_MULTICAST
    for g in gpus:
        run_dir = out / f"x{g}"
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={g}", "-m", "tactile_deploy.training",
               "train", "--config", args.config, "--run-dir", str(run_dir), "--device", args.device]
        if str(g) in budgets:
            cmd += ["--time-budget", f"{STAGE}={budgets[str(g)]}"]
        t0 = time.perf_counter()
        with open(out / f"x{g}.log", "w") as log:
            rc = subprocess.run(cmd, env=env | {"CUDA_VISIBLE_DEVICES": ",".join(map(str, range(g)))},
                                stdout=log, stderr=subprocess.STDOUT, cwd=ROOT).returncode
        wall = time.perf_counter() - t0
        if rc != 0:
            print(open(out / f"x{g}.log").read()[-4000:])
            print(f"error: the {g}-GPU run failed (exit {rc})", file=sys.stderr)
            return 1
        history = json.loads((run_dir / "history.json").read_text())[STAGE]
        summary = summarise(history, g) | {"wall_seconds": wall}
        results["runs"].append(summary)
        print(f"{g} GPU(s): {summary['samples_per_s']:.0f} samples/s, {summary['epochs']} epochs in "
              f"{summary['stage_seconds']:.0f} s, held-out contact patch {summary['final_contact_patch_rmse_um']:.1f} um "
              f"(run {wall:.0f} s)", flush=True)
    finish(results, args.target_um)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    return 0


def finish(results: dict, target_um: float | None) -> None:
    """Scaling against the 1-GPU run and time to the target, in place."""
    runs = results["runs"]
    base = next((r for r in runs if r["gpus"] == 1), None)
    target = target_um if target_um is not None else max(r["final_contact_patch_rmse_um"] for r in runs)
    results["target_contact_patch_um"] = target
    for r in runs:
        r["speedup"] = r["samples_per_s"] / base["samples_per_s"] if base else None
        r["efficiency"] = r["speedup"] / r["gpus"] if base else None
        r["seconds_to_target"] = time_to(r["curve"], target)


def report(args) -> int:
    results = json.loads(Path(args.results).read_text())
    finish(results, args.target_um)
    lines = [
        f"{results['device']} x {max(r['gpus'] for r in results['runs'])} (one host, NCCL, NVLink multicast off), "
        f"torch {results['torch']}; config `{results['config']}`, stage `{results['stage']}` (image encoder + surface "
        "decoder + image VAE decoder), same contacts in total and same batch per GPU in every run. samples/s: median "
        "over the epochs after the first, validation excluded; time to target: seconds of the stage until the held-out "
        f"contact-patch RMSE reaches {results['target_contact_patch_um']:.1f} um.",
        "",
        "| GPUs | samples/s | speed-up | scaling efficiency | target | epochs run | stage s | held-out contact patch um "
        "(end) | time to target s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    goal = {1: None, 2: 1.7, 4: 3.2}
    for r in results["runs"]:
        g = goal.get(r["gpus"])
        met = "-" if g is None else (f">= {g}x: " + ("met" if r["speedup"] >= g else "**not met**"))
        t = r["seconds_to_target"]
        lines.append(f"| {r['gpus']} | {r['samples_per_s']:.0f} | {r['speedup']:.2f}x | {r['efficiency']:.2f} | {met} "
                     f"| {r['epochs']} | {r['stage_seconds']:.0f} | {r['final_contact_patch_rmse_um']:.1f} | "
                     + (f"{t:.0f}" if t is not None else "not reached") + " |")
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        from bench.report import write_section

        write_section("train-gpus", "## Data-parallel training on several GPUs (`bench/bench_train_gpus.py`)\n\n" + text)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="train on 1, 2, 4 GPUs one after another (on the GPU machine)")
    r.add_argument("--config", required=True)
    r.add_argument("--gpus", default="1,2,4")
    r.add_argument("--budget", default="", help="GPUS=SECONDS of the timed stage per run, e.g. 1=90,2=90,4=240")
    r.add_argument("--out", required=True)
    r.add_argument("--target-um", type=float, default=None)
    r.add_argument("--device", default="cuda", choices=["cuda", "cpu"], help="cpu: ranks on the CPU (gloo), to check the script")
    p = sub.add_parser("report", help="BENCHMARKS.md table from a results.json")
    p.add_argument("--results", required=True)
    p.add_argument("--target-um", type=float, default=None)
    p.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    return run(args) if args.command == "run" else report(args)


if __name__ == "__main__":
    sys.exit(main())
