"""Batched torch simulator throughput: samples/s of intrusion + contact + volume + depth.

    python bench/bench_sim_gpu.py --device cuda --n 200000 --out bench/results/sim_gpu_h100.json
    python bench/bench_sim_gpu.py --small            (a quick CPU run, seconds)

Measures, in one run on this machine, for each friction law asked for:

* operators: C and G computed on the device by a dense Cholesky (or taken from the CPU cache),
  with the time taken and, given a reference file, their difference to the CPU operators;
* equality with the CPU path: the batched results in float64 and in float32 against the CPU
  simulator's results (``ContactSimulator`` + ``DepthCamera``) for the same contacts: max
  differences of displacements (mm), forces (N) and depth maps (mm), contact-mask mismatches.
  The CPU results are computed in this run when the CPU simulator and the indenter meshes are
  available, or read from ``--reference`` (written here by ``--write-reference``);
* float32 against float64 of the batched path on a larger subset;
* throughput in float32 at the chosen batch size (the best of ``--batch-sizes`` on a short
  trial): samples/s over all drawn poses and over those that touch the pad, time per stage,
  peak device memory per sample in flight, host-fallback counts.

Contacts are drawn as by ``tactile-deploy simulate`` (DatasetSpec defaults): an indenter of the
bank uniformly, origin uniform in a 12 mm disc, rotation uniform, depth uniform in 0.2-1.2 mm;
gel nu = 0.48 (as ``bench/bench_sim.py``); Coulomb contact (``--friction coulomb``) draws a
friction coefficient per contact uniformly in 0.3-1.5 and solves contact in float64 (the
"float32" rows keep displacements and depth in float32). Results go to ``--out`` as JSON; the first friction
law of ``--friction`` gives the headline keys (``samples_per_s``, ``batch_size``, ...).

A GPU machine needs only torch, numpy, scipy and pydantic: write the envelope bank and the CPU
results beforehand where the indenter meshes and the CPU simulator are available, e.g.

    python bench/bench_sim_gpu.py --device cpu --operators auto --friction stick --check-n 150 \
        --bank bank.npz --write-reference ref_{friction}.npz --only-reference

and pass ``--bank bank.npz --reference ref_{friction}.npz`` there (how
``bench/results/sim_gpu_h100.json`` was made, with 200 frictionless and 150 sticking contacts).
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

NU = 0.48
RADIUS_MAX_MM = 12.0
DEPTH_MM = (0.2, 1.2)
MU_RANGE = (0.3, 1.5)  # Coulomb contact: friction coefficient per contact, as the evaluation's domain


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def draw_contacts(n: int, n_indenters: int, seed: int, device="cpu", radius_mm=RADIUS_MAX_MM, depth_mm=DEPTH_MM):
    """(index (n,) int64, poses (n, 4) float64: x_mm, y_mm, theta_deg, depth_mm) on ``device``:
    an indenter uniformly, origin uniform in a disc of ``radius_mm``, rotation uniform, depth
    uniform in ``depth_mm`` (low, high)."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    index = torch.randint(n_indenters, (n,), generator=g)
    r = radius_mm * torch.sqrt(torch.rand(n, generator=g, dtype=torch.float64))
    phi = 2 * torch.pi * torch.rand(n, generator=g, dtype=torch.float64)
    theta = 360.0 * torch.rand(n, generator=g, dtype=torch.float64)
    depth = depth_mm[0] + (depth_mm[1] - depth_mm[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    poses = torch.stack([r * torch.cos(phi), r * torch.sin(phi), theta, depth], dim=1)
    return index.to(device), poses.to(device)


def draw_mu(friction: str, n: int, seed: int, device="cpu"):
    """Friction coefficients (n,) float64 uniform in MU_RANGE for Coulomb contact, else None."""
    if friction != "coulomb":
        return None
    g = torch.Generator(device="cpu").manual_seed(seed + 7919)
    return (MU_RANGE[0] + (MU_RANGE[1] - MU_RANGE[0]) * torch.rand(n, generator=g, dtype=torch.float64)).to(device)


def build_bank(names_arg: str, bank_path: str | None, device):
    from tactile_deploy.training.simulation.batched import EnvelopeBank

    if bank_path and Path(bank_path).exists():
        return EnvelopeBank.load_npz(bank_path, device)
    from tactile_deploy.indenters import get_indenter, list_indenters

    names = list_indenters(None if names_arg == "all" else names_arg)
    bank = EnvelopeBank.from_indenters([get_indenter(n) for n in names], device)
    if bank_path:
        bank.save_npz(bank_path)
    return bank


# ----------------------------------------------------------------------------------- reference
def cpu_reference(mesh, material, bank, index, poses, mu=None) -> dict:
    """Results of the CPU path (ContactSimulator or CoulombSimulator with ``mu`` (n,) per
    contact, + DepthCamera) for the given contacts."""
    from tactile_deploy.camera.depth import DepthCamera
    from tactile_deploy.fem.contact import ContactSolveError
    from tactile_deploy.fem.coulomb import CoulombSimulator, CoulombSolveError
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.indenters import ContactPose, get_indenter

    coulomb = material.friction == "coulomb"
    sim = ContactSimulator(mesh, material.model_copy(update={"friction": "stick"}) if coulomb else material)
    sim.prepare()
    stick_sim = sim
    cam = DepthCamera()
    out = {k: [] for k in ("u", "forces", "mask", "force_n", "depth", "solved")}
    for j, (i, p) in enumerate(zip(index.tolist(), poses.tolist())):
        pose = ContactPose(x_mm=p[0], y_mm=p[1], theta_deg=p[2], depth_mm=p[3])
        if coulomb:
            sim = CoulombSimulator.sharing(stick_sim, material.model_copy(update={"mu": float(mu[j])}))
        try:
            r = sim.solve(get_indenter(bank.names[i]), pose)
        except (ContactSolveError, CoulombSolveError):  # the CPU path raises: an iteration that does not settle
            r = sim.solve_intrusion(np.full(mesh.n_plane, -np.inf))
            out["solved"].append(False)
        else:
            out["solved"].append(True)
        out["u"].append(r.displacements_mm.astype(np.float32))
        out["forces"].append(r.contact_forces_n)
        out["mask"].append(r.contact_mask)
        out["force_n"].append(r.force_n)
        out["depth"].append(cam.render(mesh, r.vertices_mm).depth_mm)
    ref = {k: np.asarray(v) for k, v in out.items()}
    if mu is not None:
        ref["mu"] = np.asarray(mu, np.float64)
    b = sim.block
    ref["C_stride"] = np.int64(5 * b)
    ref["C_sub"] = sim.compliance[:: 5 * b, :: 5 * b]
    ref["G_stride"] = np.int64(50)
    ref["G_sub"] = sim.greens[::50]
    return ref


def compare(res, ref: dict, E_mpa: float) -> dict:
    """Max differences of a batched result against reference arrays (numpy), over the contacts
    the CPU path solves (it raises for the others; the batched path must flag the same ones)."""
    ok = ref["solved"] if "solved" in ref else np.ones(len(ref["u"]), bool)
    solved = res.solved.cpu().numpy()
    ref = {k: (v[ok] if k in ("u", "forces", "mask", "force_n", "depth") else v) for k, v in ref.items()}
    u = res.displacements_mm.double().cpu().numpy()[ok]
    f = res.contact_forces_n.double().cpu().numpy()[ok]
    m = res.contact_mask.cpu().numpy()[ok]
    d = res.depth_mm.double().cpu().numpy()[ok]
    mism = (m != ref["mask"]).sum(axis=1)
    return {
        "n_samples": int(len(ok)),
        "unsolved_by_cpu": int((~ok).sum()),
        "unsolved_flags_equal": bool(np.array_equal(solved, ok)),
        "max_abs_displacement_mm": float(np.abs(u - ref["u"]).max()),
        "max_displacement_mm": float(np.abs(ref["u"]).max()),
        "max_abs_force_n": float(np.abs(f - ref["forces"]).max()),
        "max_nodal_force_n": float(np.abs(ref["forces"]).max()),
        "max_rel_total_force": float(np.max(np.abs(res.force_n.double().cpu().numpy()[ok] - ref["force_n"])
                                            / np.maximum(np.abs(ref["force_n"]), 1e-12))),
        "contact_mask_mismatched_nodes": int(mism.sum()),
        "samples_with_mask_mismatch": int((mism > 0).sum()),
        "max_abs_depth_mm": float(np.abs(d - ref["depth"]).max()),
        "host_fallback_samples": int(res.stats["n_contact_fallback"]),
        "E_mpa": E_mpa,
    }


# ----------------------------------------------------------------------------------- timing
def solve_in_batches(sim, bank, index, poses, batch: int, mu=None):
    """Run the whole pipeline over all contacts; returns per-stage seconds and counters."""
    device = sim.device
    stages = {"intrusion": 0.0, "contact": 0.0, "volume": 0.0, "depth": 0.0}
    counts = {"samples": 0, "samples_in_contact": 0, "contact_fallback": 0, "unsolved": 0,
              "max_active_set_iterations": 0, "max_candidate_rounds": 0,
              "max_pixels_per_triangle": 0}
    checksum = torch.zeros((), dtype=torch.float64, device=device)
    for s in range(0, len(index), batch):
        t0 = time.perf_counter()
        delta = sim.intrusion(bank, index[s : s + batch], poses[s : s + batch])
        sync(device)
        stages["intrusion"] += time.perf_counter() - t0
        res = sim.solve_intrusion(delta, stage_seconds=stages, mu=None if mu is None else mu[s : s + batch])
        ok = res.solved
        checksum += res.depth_mm[ok].sum(dtype=torch.float64)
        checksum += res.displacements_mm[ok, 0].sum(dtype=torch.float64)
        st = res.stats
        counts["samples"] += len(delta)
        counts["samples_in_contact"] += st["samples_in_contact"] - st["n_unsolved"]
        counts["contact_fallback"] += st["n_contact_fallback"]
        counts["unsolved"] += st["n_unsolved"]
        counts["max_active_set_iterations"] = max(counts["max_active_set_iterations"],
                                                  st["max_active_set_iterations"])
        counts["max_candidate_rounds"] = max(counts["max_candidate_rounds"], st["max_candidate_rounds"])
        counts["max_pixels_per_triangle"] = max(counts["max_pixels_per_triangle"],
                                                st["render_pixels_per_triangle"])
    assert torch.isfinite(checksum)
    return stages, counts


def throughput(sim, bank, n: int, batch: int, seed: int, max_seconds: float, radius_mm: float) -> dict:
    device = sim.device
    index, poses = draw_contacts(n, len(bank), seed, device, radius_mm)
    mu = draw_mu(sim.material.friction, n, seed, device)
    solve_in_batches(sim, bank, index[: min(batch, n)], poses[: min(batch, n)], batch,
                     None if mu is None else mu[: min(batch, n)])  # warm-up
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
    stages = {}
    counts = {}
    done = 0
    start = time.perf_counter()
    while done < n and time.perf_counter() - start < max_seconds:
        part = slice(done, min(n, done + 8 * batch))
        st, ct = solve_in_batches(sim, bank, index[part], poses[part], batch, None if mu is None else mu[part])
        for k, v in st.items():
            stages[k] = stages.get(k, 0.0) + v
        for k, v in ct.items():
            counts[k] = max(counts.get(k, 0), v) if k.startswith("max_") else counts.get(k, 0) + v
        done = part.stop
    sync(device)
    seconds = time.perf_counter() - start
    out = {
        "batch_size": batch,
        "n_samples": done,
        "seconds": seconds,
        "samples_per_s": done / seconds,
        "contact_samples_per_s": counts["samples_in_contact"] / seconds,  # solved, touching
        "fraction_in_contact": counts["samples_in_contact"] / max(done, 1),
        "stage_seconds": stages,
        "contact_host_fallback_samples": counts["contact_fallback"],
        "unsolved_samples": counts["unsolved"],
        "max_active_set_iterations": counts["max_active_set_iterations"],
        "max_candidate_rounds": counts["max_candidate_rounds"],
        "max_pixels_per_triangle": counts["max_pixels_per_triangle"],
    }
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device)
        out["peak_memory_mb"] = peak / 1e6
        out["memory_per_sample_kb"] = (peak - base) / batch / 1e3
        out["memory_per_sample_incl_operators_kb"] = peak / batch / 1e3
    return out


# ----------------------------------------------------------------------------------- main
def run_friction(args, friction: str, mesh, bank, device, results: dict, out_path) -> None:
    from tactile_deploy.training.simulation.batched import BatchedContactSimulator, compute_operators_torch
    from tactile_deploy.fem.material import Material

    material = Material(nu=NU, friction=friction)
    block = 1 if friction == "frictionless" else 3
    entry: dict = {"friction": friction}
    results["frictions"][friction] = entry

    # Operators.
    sync(device)
    t0 = time.perf_counter()
    if args.operators == "torch":
        C, G = compute_operators_torch(mesh, NU, block, device=device)
        ops = (C, G)
        source = "torch dense Cholesky on the device"
    else:
        ops = "auto"
        source = "auto"
    sim64 = BatchedContactSimulator(mesh, material, device, torch.float64, operators=ops)
    sync(device)
    entry["operators"] = {"source": source if args.operators == "torch" else sim64.operator_source,
                          "seconds": time.perf_counter() - t0,
                          "C_shape": list(sim64.C.shape), "G_mb_float32": sim64.G.numel() * 4 / 1e6}
    log(f"{friction}: operators in {entry['operators']['seconds']:.1f} s")
    sim32 = BatchedContactSimulator(mesh, material, device, torch.float32,
                                    operators=(sim64.C, sim64.G.reshape(-1, mesh.n_nodes, 3)))

    # Equality with the CPU path.
    ref = None
    ref_file = Path(args.reference.format(friction=friction)) if args.reference else None
    if ref_file is not None and ref_file.exists():
        with np.load(ref_file) as f:
            ref = {k: f[k] for k in f.files}
        index = torch.as_tensor(ref["index"], device=device)
        poses = torch.as_tensor(ref["poses"], device=device)
        mu = torch.as_tensor(ref["mu"], device=device) if "mu" in ref else None
        if "depth" not in ref:
            from tactile_deploy.camera.depth import DepthCamera

            cam = DepthCamera()
            ref["depth"] = np.stack([cam.render(mesh, mesh.vertices + u.astype(np.float64)).depth_mm
                                     for u in ref["u"]])
        entry["reference"] = f"{ref_file.name} (CPU path run elsewhere; displacements stored in float32)"
    elif args.check_n > 0:
        index, poses = draw_contacts(args.check_n, len(bank), args.seed + 1, device, args.radius)
        mu = draw_mu(friction, args.check_n, args.seed + 1, device)
        ref = cpu_reference(mesh, material, bank, index.cpu(), poses.cpu(),
                            None if mu is None else mu.cpu().numpy())
        entry["reference"] = "CPU path in this run"
        if args.write_reference:
            from tactile_deploy.atomic import write_npz

            path = Path(args.write_reference.format(friction=friction))
            keep = {k: v for k, v in ref.items() if k != "depth"}
            write_npz(path, index=index.cpu().numpy(), poses=poses.cpu().numpy(), **keep)
            log(f"wrote {path}")
    if args.only_reference:
        return
    if ref is not None:
        s = int(ref["C_stride"])
        C_sub = sim64.C[::s, ::s].cpu().numpy()
        G_sub = sim64.G.reshape(-1, mesh.n_nodes, 3)[:: int(ref["G_stride"])].cpu().numpy()
        entry["operators"]["C_max_rel_diff_vs_cpu"] = float(np.abs(C_sub - ref["C_sub"]).max()
                                                            / np.abs(ref["C_sub"]).max())
        entry["operators"]["G_max_rel_diff_vs_cpu_float32"] = float(np.abs(G_sub - ref["G_sub"]).max()
                                                                    / np.abs(ref["G_sub"]).max())
        eq = {}
        for name, sim in (("float64", sim64), ("float32", sim32)):
            res = sim.solve(bank, index, poses, mu=mu)
            eq[name] = compare(res, ref, material.E_mpa)
        entry["equality_with_cpu"] = eq
        log(f"{friction}: equality {json.dumps(eq)}")

    # float32 against float64 on a larger subset.
    index, poses = draw_contacts(args.f32_n, len(bank), args.seed + 2, device, args.radius)
    mu = draw_mu(friction, args.f32_n, args.seed + 2, device)
    a = sim64.solve(bank, index, poses, mu=mu)
    b = sim32.solve(bank, index, poses, mu=mu)
    both = a.solved & b.solved
    a, b = (type(r)(**{k: (getattr(r, k)[both] if k != "stats" and getattr(r, k) is not None else getattr(r, k))
                       for k in r.__dataclass_fields__}) for r in (a, b))
    entry["float32_vs_float64"] = {
        "n_samples": args.f32_n,
        "unsolved_float64": int(args.f32_n - int(both.sum())) if bool(both.all()) is False else 0,
        "max_abs_displacement_mm": float((b.displacements_mm.double() - a.displacements_mm).abs().max()),
        "max_abs_depth_mm": float((b.depth_mm.double() - a.depth_mm).abs().max()),
        "max_abs_force_n": float((b.contact_forces_n.double() - a.contact_forces_n).abs().max()),
        "contact_mask_mismatched_nodes": int((a.contact_mask != b.contact_mask).sum()),
        "samples_with_mask_mismatch": int((a.contact_mask != b.contact_mask).any(dim=1).sum()),
        "host_fallback_samples_float32": int(b.stats["n_contact_fallback"]),
    }
    log(f"{friction}: float32 vs float64 {json.dumps(entry['float32_vs_float64'])}")
    del sim64, a, b
    write(results, out_path)

    # Throughput in float32: short trial of each batch size (and, on CUDA, of the MAGMA
    # backend for the batched Cholesky factorisations), then the full run.
    trials = {}
    for batch in args.batch_sizes:
        try:
            r = throughput(sim32, bank, 2 * batch, batch, args.seed + 3, 60.0, args.radius)
        except torch.cuda.OutOfMemoryError:
            if device.type == "cuda":
                torch.cuda.empty_cache()
            trials[str(batch)] = "out of memory"
            continue
        trials[str(batch)] = r["samples_per_s"]
        entry.setdefault("batch_trials_stage_seconds", {})[str(batch)] = r["stage_seconds"]
        log(f"{friction}: batch {batch}: {r['samples_per_s']:.0f} samples/s {r['stage_seconds']}")
    entry["batch_trials_samples_per_s"] = trials
    best = max((int(k) for k, v in trials.items() if isinstance(v, float)), key=lambda k: trials[str(k)])
    entry["linalg_backend"] = "default"
    if device.type == "cuda" and args.try_magma:
        default = torch.backends.cuda.preferred_linalg_library()
        try:
            torch.backends.cuda.preferred_linalg_library("magma")
            r = throughput(sim32, bank, 2 * best, best, args.seed + 3, 60.0, args.radius)
            entry["magma_trial_samples_per_s"] = r["samples_per_s"]
            log(f"{friction}: MAGMA, batch {best}: {r['samples_per_s']:.0f} samples/s")
            if r["samples_per_s"] > trials[str(best)]:
                entry["linalg_backend"] = "magma"
            else:
                torch.backends.cuda.preferred_linalg_library(default)
        except RuntimeError as err:
            torch.backends.cuda.preferred_linalg_library(default)
            entry["magma_trial_samples_per_s"] = f"unavailable: {err}"
    n = args.n if friction == args.friction[0] else args.n_other
    entry["throughput_float32"] = throughput(sim32, bank, n, best, args.seed + 4, args.max_seconds,
                                             args.radius)
    log(f"{friction}: {json.dumps(entry['throughput_float32'])}")
    if device.type == "cuda":
        torch.backends.cuda.preferred_linalg_library("default")
    write(results, out_path)


def write(results: dict, out_path) -> None:
    if out_path is None:
        return
    from tactile_deploy.atomic import write_json

    head = results["frictions"].get(results["headline_friction"], {}).get("throughput_float32")
    if head:
        for key in ("samples_per_s", "contact_samples_per_s", "n_samples", "batch_size",
                    "memory_per_sample_kb", "peak_memory_mb"):
            if key in head:
                results[key] = head[key]
    out_path.parent.mkdir(parents=True, exist_ok=True)
    write_json(out_path, results)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--n", type=int, default=200_000, help="contacts timed (first friction law)")
    parser.add_argument("--n-other", type=int, default=50_000, help="contacts timed (other laws)")
    parser.add_argument("--max-seconds", type=float, default=120.0, help="stop timing after this")
    parser.add_argument("--friction", default="frictionless,stick")
    parser.add_argument("--batch-sizes", default="4096,8192,16384")
    parser.add_argument("--indenters", default="primitive", help="primitive | novel | all")
    parser.add_argument("--pad", default="shipped", choices=["shipped", "small"],
                        help="the shipped pad, or a 10 mm radius pad (quick runs)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")
    parser.add_argument("--bank", default=None, help="envelope bank .npz (read, or written here)")
    parser.add_argument("--operators", default="torch", choices=["torch", "auto"],
                        help="torch: dense Cholesky on the device; auto: the CPU cache if present")
    parser.add_argument("--check-n", type=int, default=200, help="contacts compared with the CPU path")
    parser.add_argument("--f32-n", type=int, default=1000, help="contacts for float32 vs float64")
    parser.add_argument("--reference", default=None, help="CPU results .npz, '{friction}' in the name")
    parser.add_argument("--write-reference", default=None, help="write the CPU results computed here")
    parser.add_argument("--only-reference", action="store_true",
                        help="stop after writing the CPU results (--write-reference)")
    parser.add_argument("--try-magma", action="store_true",
                        help="also time MAGMA for the batched Cholesky (CUDA) and keep the faster")
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--small", action="store_true", help="quick CPU run (small counts)")
    parser.add_argument("--out", default=None, help="JSON results path")
    args = parser.parse_args(argv)
    args.friction = [f.strip() for f in args.friction.split(",") if f.strip()]
    args.batch_sizes = [int(b) for b in str(args.batch_sizes).split(",")]
    if args.small:
        args.device, args.pad, args.operators = "cpu", "small", "auto"
        args.n, args.n_other, args.check_n, args.f32_n = 64, 32, 8, 16
        args.batch_sizes = [32]
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    torch.backends.cuda.matmul.allow_tf32 = False  # float32 GEMMs in full float32
    if args.pad == "small":
        from tactile_deploy.pad.geometry import PadGeometry
        from tactile_deploy.pad.mesh import build_pad_mesh

        mesh = build_pad_mesh(PadGeometry(name="small", radius_mm=10.0, edge_mm=1.0))
        args.radius = 5.0
    else:
        from tactile_deploy.pad.asset import load_pad

        mesh = load_pad()
        args.radius = RADIUS_MAX_MM
    bank = build_bank(args.indenters, args.bank, device)
    results = {
        "benchmark": "bench/bench_sim_gpu.py",
        "command": " ".join(sys.argv),
        "device": str(device),
        "device_name": (torch.cuda.get_device_name(device) if device.type == "cuda"
                        else platform.processor() or platform.machine()),
        "torch_version": torch.__version__,
        "cpu_threads": torch.get_num_threads(),
        "host_cpu_count": __import__("os").cpu_count(),
        "dtype_timed": "float32",
        "pad": args.pad,
        "mesh": {"n_nodes": mesh.n_nodes, "n_sensing_nodes": mesh.n_plane, "hash": mesh.content_hash[:16]},
        "contacts": {"indenters": bank.names, "radius_max_mm": args.radius, "depth_mm": list(DEPTH_MM),
                     "nu": NU, "E_mpa": 0.3},
        "headline_friction": args.friction[0],
        "frictions": {},
        "measured": time.strftime("%Y-%m-%d"),
    }
    out_path = Path(args.out) if args.out else None
    for friction in args.friction:
        run_friction(args, friction, mesh, bank, device, results, out_path)
    write(results, out_path)
    print(json.dumps({k: results.get(k) for k in ("device_name", "samples_per_s", "batch_size",
                                                     "memory_per_sample_kb")}, indent=1))
    return results


if __name__ == "__main__":
    main()
