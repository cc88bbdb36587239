"""Resolved contact solver throughput on the CPU (`tactile-deploy bench sim-resolved`).

    python bench/bench_sim_resolved.py [--n 6] [--workers 2]

Random primitive contacts (the library's primitives, 0.3-1.0 mm deep, within 8 mm of the
centre) solved by :class:`tactile_deploy.fem.truth.TruthSolver` on the shipped pad, in
``--workers`` processes, for four settings measured in the same run: the pad-mesh path of
datasets (``simulate_contact``: linear, frictionless, contact at the 5,380-node mesh's nodes; the
baseline), and the resolved solver with the linear gel (frictionless), the neo-Hookean gel
(frictionless) and the neo-Hookean gel with Coulomb friction (mu 0.8). A resolved contact that
does not converge is counted, not dropped. Reports contacts/s, seconds per contact, truth-mesh sizes and
solver work, and writes the section ``sim-resolved`` of BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

BASELINE = "pad mesh, linear, frictionless (simulate_contact; baseline)"
SETTINGS = {
    BASELINE: ("pad-mesh", "frictionless"),
    "resolved, linear, frictionless": ("linear", "frictionless"),
    "neo-Hookean, frictionless": ("neo-hookean", "frictionless"),
    "neo-Hookean, Coulomb mu 0.8": ("neo-hookean", "coulomb"),
}


def _contacts(n: int, seed: int):
    import numpy as np

    from tactile_deploy.indenters import list_indenters

    rng = np.random.default_rng(seed)
    names = list_indenters("primitive")
    return [(names[int(rng.integers(len(names)))], float(rng.uniform(-8, 8)),
             float(rng.uniform(-8, 8)), float(rng.uniform(0, 360)), float(rng.uniform(0.3, 1.0)))
            for _ in range(n)]


def _solve(args):
    model, friction, (name, x, y, theta, depth) = args
    from threadpoolctl import threadpool_limits

    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.truth import TruthSolver
    from tactile_deploy.indenters import ContactPose, get_indenter
    from tactile_deploy.pad.geometry import PadGeometry

    from tactile_deploy.fem.truth import TruthSolveError, indenter_field, surface_penetration

    material = Material(E_mpa=0.3, nu=0.48, friction=friction, mu=0.8)
    pose = ContactPose(x_mm=x, y_mm=y, theta_deg=theta, depth_mm=depth)
    with threadpool_limits(1):
        t0 = time.perf_counter()
        if model == "pad-mesh":
            from tactile_deploy.simulation.contact import simulate_contact

            sample = simulate_contact(get_indenter(name), pose, material)
            return {"seconds": time.perf_counter() - t0, "nodes": sample.metadata["n_nodes"],
                    "factorizations": 0, "penetration_um": float("nan"), "name": name,
                    "depth": depth, "failed": False}
        solver = TruthSolver(PadGeometry(), material, model=model)
        try:
            sol = solver.solve(get_indenter(name), pose)
        except TruthSolveError as err:
            return {"seconds": time.perf_counter() - t0, "nodes": 0, "factorizations": 0,
                    "penetration_um": float("nan"), "surface_penetration_um": float("nan"),
                    "load_splits": 0, "name": name, "depth": depth, "failed": True,
                    "error": str(err)}
        dt = time.perf_counter() - t0
        # the gel's continuous surface against the indenter, checked every 20 um (the solver's
        # own figure is at its constraint points only)
        surface, _ = surface_penetration(sol, indenter_field(get_indenter(name), pose),
                                         pitch_mm=0.02, geometric=model != "linear")
    return {"seconds": dt, "nodes": sol.info["n_nodes"], "factorizations": sol.info["factorizations"],
            "penetration_um": 1e3 * sol.max_penetration_mm, "surface_penetration_um": 1e3 * surface,
            "load_splits": sol.info["load_splits"], "name": name, "depth": depth, "failed": False}


def run(n: int = 6, workers: int = 2, seed: int = 5) -> dict:
    contacts = _contacts(n, seed)
    _solve(("pad-mesh", "frictionless", contacts[0]))  # the pad mesh's response cache on disk
    out = {}
    for label, (model, friction) in SETTINGS.items():
        t0 = time.perf_counter()
        with ProcessPoolExecutor(workers) as pool:
            rows = list(pool.map(_solve, [(model, friction, c) for c in contacts]))
        wall = time.perf_counter() - t0
        out[label] = {"contacts_per_s": n / wall, "rows": rows, "wall_s": wall}
    return {"n": n, "workers": workers, "settings": out, "load": os.getloadavg()[0]}


def _largest(values) -> str:
    finite = [v for v in values if v == v]
    return f"{max(finite):.3f}" if finite else "n/a"


def _splits(n: int) -> str:
    return "" if not n else f" ({n} split{'s' if n > 1 else ''})"


def markdown(result: dict) -> str:
    import numpy as np

    from bench.report import machine_line

    base = result["settings"][BASELINE]["contacts_per_s"]
    lines = [
        "## Resolved contact solver (`tactile-deploy bench sim-resolved`)",
        "",
        f"CPU: {machine_line()}; {result['workers']} worker processes (one thread each), "
        f"{result['n']} random primitive contacts (0.3-1.0 mm deep) on the GelSlim pad, E 0.3 MPa, "
        f"nu 0.48; load average {result['load']:.1f} on the machine's 2 cores when finished.",
        "",
        "| setting | contacts/s | vs baseline | median s per contact | median truth nodes | "
        "factorisations per contact (modified Newton reuses them) | largest penetration at constraint points (um) | largest penetration of the continuous surface (um) | not converged |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, r in result["settings"].items():
        rows = r["rows"]
        lines.append(
            f"| {label} | {r['contacts_per_s']:.3f} | {r['contacts_per_s'] / base:.2f}x | "
            f"{np.median([x['seconds'] for x in rows]):.1f} | {np.median([x['nodes'] for x in rows]):.0f} | "
            f"{np.mean([x['factorizations'] for x in rows]):.1f} | "
            f"{_largest([x['penetration_um'] for x in rows])} | "
            f"{_largest([x.get('surface_penetration_um', float('nan')) for x in rows])} | "
            f"{sum(x['failed'] for x in rows)} |")
    labels = list(result["settings"])
    first = result["settings"][labels[0]]["rows"]
    lines += ["", "Per contact, seconds (load splits: depth increments halved after a failure):", "",
              "| contact | " + " | ".join(labels) + " |",
              "|---|" + "---:|" * len(labels)]
    for k, row in enumerate(first):
        cells = []
        for label in labels:
            x = result["settings"][label]["rows"][k]
            cells.append("not converged" if x["failed"] else
                         f"{x['seconds']:.1f}" + _splits(x.get("load_splits", 0)))
        lines.append(f"| {row['name']} {row['depth']:.2f} mm | " + " | ".join(cells) + " |")
    lines += ["", "The surface check reads the gel's piecewise-linear surface under a 20 um grid "
              "over the footprint: at a punch's sharp rim the one triangle spanning the rim "
              "cuts its corner (docs/fem.md, Contact).",
              "", "Target: >= 2 contacts/s on 2 CPU cores, resolved, large deformation, Coulomb."]
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=6)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = parser.parse_args(argv)
    result = run(args.n, args.workers)
    text = markdown(result)
    print(text)
    if not args.no_write:
        from bench.report import write_section

        write_section("sim-resolved", text)
    return result


if __name__ == "__main__":
    main()
