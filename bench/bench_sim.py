"""Simulator throughput on the CPU: samples/s of the data generator vs a per-sample sparse solve.

    python bench/bench_sim.py [--n 200] [--workers 2] [--small]   (or: tactile-deploy bench sim)

Measures, in one run on this machine:

* the data generator (surface Green's functions + exact active set + depth camera), with
  ``--workers`` processes, in samples/s over ``--n`` random primitive contacts;
* the baseline: the same contacts solved by the full sparse method (active-set iteration that
  re-factors the whole stiffness for every active set), on a few samples;
* memory: operator bytes (shared by the workers), stored bytes per sample, peak RSS;
* the friction laws: the contact solve alone (surface operators loaded, no depth camera), one
  process with one BLAS thread, on the same ``--friction-contacts`` random primitive contacts,
  frictionless, sticking and Coulomb (mu uniform in 0.3-1.5 per contact, one load step).

The GPU figure comes from ``bench/bench_sim_gpu.py`` (results in ``bench/results/``) and is
quoted next to it when present.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def friction_law_rates(n: int, seed: int = 123) -> dict:
    """Contacts/s of the contact solve (``simulator.solve``: forces and the volume's
    displacements) per friction law on the same ``n`` random primitive contacts (nu = 0.48,
    depth 0.2-1.2 mm, within 12 mm of the centre), one process, one BLAS thread."""
    import math

    import numpy as np
    from threadpoolctl import threadpool_limits

    from tactile_deploy.fem.material import Material
    from tactile_deploy.indenters import ContactPose, get_indenter, list_indenters
    from tactile_deploy.simulation.contact import ContactError, check_pose, get_simulator

    names = tuple(list_indenters("primitive"))
    rng = np.random.default_rng([seed, 7])
    mesh = get_simulator(Material(nu=0.48)).mesh
    contacts = []
    while len(contacts) < n:
        ind = get_indenter(names[int(rng.integers(len(names)))])
        r, phi = 12.0 * math.sqrt(rng.random()), 2 * math.pi * rng.random()
        pose = ContactPose(x_mm=r * math.cos(phi), y_mm=r * math.sin(phi),
                           theta_deg=360 * rng.random(), depth_mm=float(rng.uniform(0.2, 1.2)))
        mu = float(rng.uniform(0.3, 1.5))
        try:
            check_pose(mesh, ind, pose)
        except ContactError:
            continue
        contacts.append((ind, pose, mu))
    rates = {}
    for law in ("frictionless", "stick", "coulomb"):
        sims = [get_simulator(Material(nu=0.48, friction=law, mu=mu if law == "coulomb" else 1.0))
                for _, _, mu in contacts]
        sims[0].prepare()
        with threadpool_limits(1):
            t0 = time.perf_counter()
            for (ind, pose, _), sim in zip(contacts, sims):
                sim.solve(ind, pose)
            rates[law] = n / (time.perf_counter() - t0)
    return {"n_contacts": n, "contacts_per_s": rates,
            "coulomb_vs_frictionless": rates["coulomb"] / rates["frictionless"],
            "coulomb_vs_stick": rates["coulomb"] / rates["stick"]}


def run(n: int = 200, workers: int = 2, baseline_samples: int = 2, seed: int = 123,
        friction_contacts: int = 20) -> dict:
    import numpy as np
    from threadpoolctl import threadpool_limits

    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.indenters import ContactPose, get_indenter, list_indenters
    from tactile_deploy.simulation.contact import get_simulator
    from tactile_deploy.simulation.dataset import DatasetSpec, generate_dataset

    material = Material(nu=0.48)
    names = tuple(list_indenters("primitive"))
    sim = get_simulator(material)
    t0 = time.perf_counter()
    sim.prepare()
    prepare_s = time.perf_counter() - t0
    spec = DatasetSpec(n_samples=n, indenters=names, seed=seed, shard_size=max(1, n // (2 * workers)), material=material)
    for name in names:  # build envelope grids before timing (cached on disk after the first run)
        get_indenter(name).envelope_grid()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate_dataset(spec, tmp, workers=workers)
        gen_s = time.perf_counter() - t0
        bytes_per_sample = sum(p.stat().st_size for p in Path(tmp).glob("shard_*.npz")) / n
    rate = n / gen_s

    # Baseline: full sparse solve per sample (same physics, same contacts).
    full = ContactSimulator(sim.mesh, material, method="full", assembly="numpy", use_cache=False)
    rng = np.random.default_rng(seed)
    times, max_diff = [], 0.0
    with threadpool_limits(1):
        for _ in range(baseline_samples):
            ind = get_indenter(names[int(rng.integers(len(names)))])
            pose = ContactPose(x_mm=float(rng.uniform(-5, 5)), y_mm=float(rng.uniform(-5, 5)),
                               theta_deg=float(rng.uniform(0, 360)), depth_mm=float(rng.uniform(0.4, 1.0)))
            t0 = time.perf_counter()
            ref = full.solve(ind, pose)
            times.append(time.perf_counter() - t0)
            fast = sim.solve(ind, pose)
            max_diff = max(max_diff, float(np.abs(ref.displacements_mm - fast.displacements_mm).max()))
    baseline_rate = 1.0 / float(np.mean(times))
    laws = friction_law_rates(friction_contacts, seed) if friction_contacts else None
    operator_bytes = sim.compliance.nbytes + sim.greens.nbytes
    return {
        "n_samples": n,
        "workers": workers,
        "samples_per_s": rate,
        "baseline_samples_per_s": baseline_rate,
        "speedup": rate / baseline_rate,
        "baseline_max_displacement_difference_mm": max_diff,
        "operator_prepare_s": prepare_s,
        "operator_mb": operator_bytes / 1e6,
        "stored_kb_per_sample": bytes_per_sample / 1e3,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
        "formulation": sim.formulation,
        "friction": material.friction,
        "friction_laws": laws,
    }


def markdown(result: dict, gpu: dict | None) -> str:
    from bench.report import machine_line

    lines = [
        "## Simulator throughput: image-mesh pairs per second (`tactile-deploy bench sim`)",
        "",
        f"CPU: {machine_line()}; {result['workers']} worker processes, {result['n_samples']} random "
        f"primitive contacts, {result['friction']} contact, {result['formulation']} tets.",
        "",
        "| path | pairs/s (one contact = depth map + mesh) | vs baseline |",
        "|---|---|---|",
        f"| per-sample sparse direct solve (baseline, 1 process) | {result['baseline_samples_per_s']:.3f} | 1x |",
        f"| Green's functions + exact active set (CPU, {result['workers']} processes) | "
        f"{result['samples_per_s']:.1f} | {result['speedup']:.0f}x |",
    ]
    if gpu:
        lines.append(
            f"| batched torch path ({gpu.get('device_name', 'GPU')}) | {gpu['samples_per_s']:.0f} | "
            f"{gpu['samples_per_s'] / result['baseline_samples_per_s']:.0f}x |"
        )
    lines += [
        "",
        f"Targets: >= 50 samples/s on 2 CPU cores; >= 5,000 samples/s on one H100. "
        f"Baseline and fast path agree to {result['baseline_max_displacement_difference_mm']:.1e} mm "
        f"(max nodal displacement difference).",
        "",
        f"Memory: operators {result['operator_mb']:.0f} MB (computed once per mesh, nu and friction "
        f"in {result['operator_prepare_s']:.1f} s or loaded from the cache, shared by the workers), "
        f"{result['stored_kb_per_sample']:.0f} kB stored per sample (compressed shard), "
        f"peak RSS of the benchmark process {result['peak_rss_mb']:.0f} MB.",
    ]
    if gpu:
        lines.append(
            f"GPU: {gpu.get('device_name')} — {gpu.get('n_samples')} samples, batch {gpu.get('batch_size')}, "
            f"{gpu.get('memory_per_sample_kb', float('nan')):.0f} kB GPU memory per sample in flight "
            f"(`bench/bench_sim_gpu.py`, results in `bench/results/sim_gpu_h100.json`)."
        )
    laws = result.get("friction_laws")
    if laws:
        r = laws["contacts_per_s"]
        lines += [
            "",
            f"Friction laws, the contact solve alone (forces + volume displacements, no depth camera), "
            f"1 process, 1 BLAS thread, the same {laws['n_contacts']} random primitive contacts:",
            "",
            "| friction law | contacts/s | vs frictionless |",
            "|---|---|---|",
            f"| frictionless (exact active set, 1 dof per node) | {r['frictionless']:.1f} | 1x |",
            f"| stick (exact active set, 3 dofs per node) | {r['stick']:.1f} | "
            f"{r['stick'] / r['frictionless']:.2f}x |",
            f"| Coulomb, mu 0.3-1.5 (semi-smooth Newton, `CoulombSimulator`) | {r['coulomb']:.1f} | "
            f"{laws['coulomb_vs_frictionless']:.2f}x ({laws['coulomb_vs_stick']:.2f}x stick) |",
        ]
    gpu_laws = _gpu_friction_rows()
    if gpu_laws:
        lines += [
            "",
            "The batched torch path per friction law on one GPU (`bench/bench_sim_gpu.py`: intrusion, contact, "
            "volume and depth map, float32 fields; Coulomb contact solved in float64), against the CPU path on the "
            "same contacts:",
            "",
            "| friction law | device | contacts/s | GPU memory per sample kB | max force difference vs CPU N "
            "(contacts) | results |",
            "|---|---|---:|---:|---|---|",
        ] + gpu_laws
    nh_rows = _gpu_neo_hookean_rows()
    if nh_rows:
        lines += [
            "",
            "Large deformation: the neo-Hookean gel (frictionless, the pad mesh; the hyperelastic effect's fixed "
            "point, batched: `bench/bench_sim_neo_hookean.py`, contacts as the evaluation's large-strain domain, "
            "0.6-1.2 mm deep; intrusion, linear start, fixed point and depth map in float64), against the linear "
            "batched path in float64 on the same contacts in the same run, and against the numpy reference "
            "(`solve_neo_hookean`) on a subset:",
            "",
            "| device | neo-Hookean contacts/s | linear contacts/s (same run) | fixed-point maps per contact | "
            "GPU memory per sample kB | max displacement / force difference vs numpy (contacts) | results |",
            "|---|---:|---:|---:|---:|---|---|",
        ] + nh_rows
    return "\n".join(lines)


def _gpu_neo_hookean_rows() -> list[str]:
    """Table rows of the committed neo-Hookean GPU results (bench/results/sim_neo_hookean_*.json)."""
    rows = []
    for path in sorted((ROOT / "bench" / "results").glob("sim_neo_hookean_*.json")):
        doc = json.loads(path.read_text())
        nh, lin, chk = doc["neo_hookean"], doc["linear_float64"], doc["check"]
        rows.append(f"| {doc['device']} | {nh['contacts_per_s']:.0f} | {lin['contacts_per_s']:.0f} | "
                    f"{nh['mean_fixed_point_maps']:.1f} | {nh.get('memory_per_sample_kb', float('nan')):.0f} | "
                    f"{chk['max_displacement_difference_mm']:.1e} mm / {chk['max_force_difference_n']:.1e} N "
                    f"({chk['both_solved']}) | `{path.relative_to(ROOT)}` |")
    return rows


def _gpu_friction_rows() -> list[str]:
    """Table rows of the committed GPU results, one per friction law (bench/results/sim_gpu_*.json)."""
    rows = []
    for path in sorted((ROOT / "bench" / "results").glob("sim_gpu_*h100.json")):
        doc = json.loads(path.read_text())
        for law, entry in doc.get("frictions", {}).items():
            t = entry.get("throughput_float32")
            if not t:
                continue
            eq = entry.get("equality_with_cpu", {}).get("float64", {})
            diff = (f"{eq['max_abs_force_n']:.1e} ({eq['n_samples']})" if "max_abs_force_n" in eq else "-")
            rows.append(f"| {law} | {doc.get('device_name', 'GPU')} | {t['samples_per_s']:.0f} | "
                        f"{t.get('memory_per_sample_kb', float('nan')):.0f} | {diff} | `{path.relative_to(ROOT)}` |")
    return rows


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--baseline-samples", type=int, default=2)
    parser.add_argument("--small", action="store_true", help="quick run (40 samples, 1 baseline sample)")
    parser.add_argument("--friction-contacts", type=int, default=20,
                        help="contacts of the friction-law comparison (0: skip it)")
    parser.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = parser.parse_args(argv)
    if args.small:
        args.n, args.baseline_samples = 40, 1
    result = run(args.n, args.workers, args.baseline_samples, friction_contacts=args.friction_contacts)
    gpu_path = ROOT / "bench" / "results" / "sim_gpu_h100.json"
    gpu = json.loads(gpu_path.read_text()) if gpu_path.exists() else None
    text = markdown(result, gpu)
    print(text)
    if not args.no_write and not args.small:
        from bench.report import write_section

        write_section("sim", text)
    return result


if __name__ == "__main__":
    main()
