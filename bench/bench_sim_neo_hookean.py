"""Batched neo-Hookean contact throughput (large deformation, frictionless, the nominal pad mesh).

    python bench/bench_sim_neo_hookean.py --write-reference ref_nh.npz --bank bank.npz --only-reference
    python bench/bench_sim_neo_hookean.py --device cuda --reference ref_nh.npz --bank bank.npz \
        --out bench/results/sim_neo_hookean_h100.json

Measures, in one run on one machine, on the shipped GelSlim pad (nu 0.48):

* equality with the CPU reference: :func:`tactile_deploy.sensors.effects.hyperelastic.solve_neo_hookean`
  (numpy/scipy, sparse factor) on ``--check-n`` contacts, computed here or read from
  ``--reference`` (written by ``--write-reference`` where the CPU simulator's operators are
  available): max displacement (mm) and force (N) differences;
* throughput of :class:`~tactile_deploy.training.simulation.batched_neo_hookean.BatchedNeoHookean`
  (intrusion, linear start, fixed point, depth map; float64) against the linear batched path in
  float64 on the same contacts (the baseline, in the same run): contacts/s, fixed-point maps per
  contact, unsolved contacts, peak device memory per sample in flight.

Contacts as the evaluation's ``large_strain`` domain: an indenter of the bank uniformly (the
primitives by default), origin uniform in a 12 mm disc, rotation uniform, depth uniform in
0.6-1.2 mm (``--depth``). Results go to ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.bench_sim_gpu import build_bank, draw_contacts, sync  # noqa: E402

NU = 0.48
RADIUS_MAX_MM = 12.0


def cpu_reference(mesh, delta: np.ndarray) -> dict:
    """The numpy reference's displacements (n, nodes, 3), forces (n, n_plane, 3) and total
    forces (n,) for intrusions ``delta`` (n, n_plane); ``solved`` False where it does not converge."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.sensors.effects.hyperelastic import HyperelasticConvergenceError, solve_neo_hookean

    sim = ContactSimulator(mesh, Material(nu=NU))
    sim.prepare()
    out = {"u": [], "forces": [], "force_n": [], "solved": [], "seconds": []}
    for d in delta:
        t0 = time.perf_counter()
        try:
            r, _ = solve_neo_hookean(sim, d, 1.0)
            u, f, fn, ok = r.displacements_mm, r.contact_forces_n, r.force_n, True
        except HyperelasticConvergenceError:
            u, f, fn, ok = np.full((mesh.n_nodes, 3), np.nan), np.full((mesh.n_plane, 3), np.nan), np.nan, False
        out["seconds"].append(time.perf_counter() - t0)
        out["u"].append(u)
        out["forces"].append(f)
        out["force_n"].append(fn)
        out["solved"].append(ok)
    return {k: np.asarray(v) for k, v in out.items()}


def run_batches(solve, linear, bank, index, poses, batch: int) -> dict:
    """Intrusion + ``solve(delta)`` over all contacts in batches; seconds and counters."""
    device = linear.device
    seconds, contacts, unsolved, maps = 0.0, 0, 0, []
    for s in range(0, len(index), batch):
        sync(device)
        t0 = time.perf_counter()
        delta = linear.intrusion(bank, index[s:s + batch].to(device), poses[s:s + batch].to(device))
        res, iters = solve(delta)
        sync(device)
        seconds += time.perf_counter() - t0
        touching = res.solved & res.contact_mask.any(dim=1)
        contacts += int(touching.sum())
        unsolved += int((~res.solved).sum())
        maps.append(iters)
    return {"seconds": seconds, "contacts_in_contact": contacts, "unsolved": unsolved,
            "contacts_per_s": contacts / seconds, "samples": len(index),
            "mean_fixed_point_maps": float(np.mean(maps)) if maps else 0.0}


def main(argv=None) -> dict:
    from tactile_deploy.pad.asset import load_pad
    from tactile_deploy.fem.material import Material
    from tactile_deploy.training.simulation.batched import BatchedContactSimulator
    from tactile_deploy.training.simulation.batched_neo_hookean import BatchedNeoHookean

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--n", type=int, default=8192, help="contacts timed")
    ap.add_argument("--batch", type=int, default=512, help="contacts per batch")
    ap.add_argument("--check-n", type=int, default=16, help="contacts compared with the CPU reference")
    ap.add_argument("--depth", type=float, nargs=2, default=(0.6, 1.2), help="depth range, mm")
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--indenters", default="primitive", help="indenter group of the bank (default: primitives)")
    ap.add_argument("--bank", default=None, help="envelope bank .npz (read if present, else written)")
    ap.add_argument("--reference", default=None, help="CPU reference .npz (from --write-reference)")
    ap.add_argument("--write-reference", default=None, help="compute the CPU reference here and write it")
    ap.add_argument("--only-reference", action="store_true", help="stop after --write-reference")
    ap.add_argument("--out", default=None, help="results JSON")
    ap.add_argument("--profile", action="store_true", help="print the top operators of one batch (torch profiler)")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    pad = load_pad()
    bank = build_bank(args.indenters, args.bank, "cpu")
    results = {"machine": platform.machine(), "python": platform.python_version(), "torch": torch.__version__,
               "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
               "depth_mm": list(args.depth), "batch": args.batch, "indenters": list(bank.names)}

    # -- the CPU reference on the first check-n contacts (their intrusions are the CPU simulator's input)
    index, poses = draw_contacts(args.n, len(bank), args.seed, "cpu", RADIUS_MAX_MM, tuple(args.depth))
    check = slice(0, args.check_n)
    if args.write_reference or not args.reference:
        cpu = BatchedContactSimulator(pad, Material(nu=NU), "cpu", torch.float64, operators="cache")
        delta = cpu.intrusion(bank, index[check], poses[check]).numpy()
        t0 = time.perf_counter()
        ref = cpu_reference(pad, delta)
        print(f"CPU reference: {args.check_n} contacts in {time.perf_counter() - t0:.0f} s", flush=True)
        ref["delta"] = delta
        if args.write_reference:
            np.savez_compressed(args.write_reference, **ref)
        if args.only_reference:
            return results
    else:
        ref = dict(np.load(args.reference))
    results["cpu_reference_s_per_contact"] = float(np.median(ref["seconds"]))

    # -- the batched paths on the device
    t0 = time.perf_counter()
    linear = BatchedContactSimulator(pad, Material(nu=NU), device, torch.float64, operators="torch")
    nh = BatchedNeoHookean(linear)
    sync(device)
    results["operators_s"] = time.perf_counter() - t0
    res, _ = nh.solve_intrusion(torch.as_tensor(ref["delta"], device=device), render=False)
    ok = res.solved.cpu().numpy() & ref["solved"]
    u = res.displacements_mm.cpu().numpy()
    f = res.contact_forces_n.cpu().numpy()
    results["check"] = {
        "contacts": int(args.check_n), "both_solved": int(ok.sum()),
        "reference_unsolved": int((~ref["solved"]).sum()),
        "batched_unsolved": int((~res.solved).sum()),
        "max_displacement_difference_mm": float(np.abs(u[ok] - ref["u"][ok]).max()),
        "max_force_difference_n": float(np.abs(f[ok] - ref["forces"][ok]).max()),
        "max_total_force_n": float(np.max(ref["force_n"][ok])),
    }
    print(json.dumps(results["check"]), flush=True)

    def neo(delta):
        r, st = nh.solve_intrusion(delta)
        return r, st.mean_iterations

    def lin(delta):
        return linear.solve_intrusion(delta), 1.0

    warm = min(args.batch, args.n)
    run_batches(neo, linear, bank, index[:warm], poses[:warm], args.batch)   # warm-up
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=acts) as prof:
            run_batches(neo, linear, bank, index[:warm], poses[:warm], args.batch)
        key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
        print(prof.key_averages().table(sort_by=key, row_limit=18), flush=True)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
    results["neo_hookean"] = run_batches(neo, linear, bank, index, poses, args.batch)
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device)
        results["neo_hookean"]["memory_per_sample_kb"] = (peak - base) / args.batch / 1e3
        results["neo_hookean"]["operators_mb"] = base / 1e6
    results["neo_hookean"]["bytes_per_sample_estimate_kb"] = nh.bytes_per_sample() / 1e3
    results["linear_float64"] = run_batches(lin, linear, bank, index, poses, args.batch)
    print(json.dumps({k: results[k] for k in ("neo_hookean", "linear_float64")}, indent=1), flush=True)
    if args.out:
        from tactile_deploy.atomic import write_json

        write_json(Path(args.out), results)
    return results


if __name__ == "__main__":
    main()
