"""Resolved contact solver throughput on the CPU (`tactile-deploy bench sim-resolved`).

    python bench/bench_sim_resolved.py [--n 6] [--workers 2] [--newton-budget 80]

Random primitive contacts (the library's primitives, 0.3-1.0 mm deep, within 8 mm of the
centre) solved by :class:`tactile_deploy.fem.truth.TruthSolver` on the shipped pad, in
``--workers`` processes, for five settings measured in the same run: the pad-mesh path of
datasets (``simulate_contact``: linear, frictionless, contact at the 5,380-node mesh's nodes; the
baseline), and the resolved solver with the linear gel (frictionless), the neo-Hookean gel
(frictionless; once more with SuperLU factorising its tangents in place of PARDISO where the
``pardiso`` extra is installed) and the neo-Hookean gel with Coulomb friction (mu 0.8). A
resolved contact that does not converge, or not within ``--newton-budget`` Newton steps in all
(:attr:`SolveSettings.max_newton_steps`), is counted, not dropped. Reports contacts/s, seconds
per contact, truth-mesh sizes and solver work, and writes the section ``sim-resolved`` of
BENCHMARKS.md.
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
SUPERLU = "neo-Hookean, frictionless, SuperLU factorisations"
SETTINGS = {  # label: (model, friction, the tangents' direct solver: None = the installed default)
    BASELINE: ("pad-mesh", "frictionless", None),
    "resolved, linear, frictionless": ("linear", "frictionless", None),
    "neo-Hookean, frictionless": ("neo-hookean", "frictionless", None),
    SUPERLU: ("neo-hookean", "frictionless", "superlu"),
    "neo-Hookean, Coulomb mu 0.8": ("neo-hookean", "coulomb", None),
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
    model, friction, linear_solver, budget, (name, x, y, theta, depth) = args
    from threadpoolctl import threadpool_limits

    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.truth import TruthSolver
    from tactile_deploy.indenters import ContactPose, get_indenter
    from tactile_deploy.pad.geometry import PadGeometry

    from tactile_deploy.fem.truth import (
        NewtonBudgetError,
        SolveSettings,
        TruthSolveError,
        indenter_field,
        surface_penetration,
    )

    material = Material(E_mpa=0.3, nu=0.48, friction=friction, mu=0.8)
    pose = ContactPose(x_mm=x, y_mm=y, theta_deg=theta, depth_mm=depth)
    with threadpool_limits(1):
        t0 = time.perf_counter()
        if model == "pad-mesh":
            from tactile_deploy.simulation.contact import simulate_contact

            sample = simulate_contact(get_indenter(name), pose, material)
            return {"seconds": time.perf_counter() - t0, "nodes": sample.metadata["n_nodes"],
                    "penetration_um": float("nan"), "name": name, "depth": depth,
                    "failed": False}
        settings = SolveSettings(max_newton_steps=budget, linear_solver=linear_solver)
        solver = TruthSolver(PadGeometry(), material, model=model, settings=settings)
        try:
            sol = solver.solve(get_indenter(name), pose)
        except TruthSolveError as err:
            return {"seconds": time.perf_counter() - t0, "nodes": 0, "factorizations": 0,
                    "penetration_um": float("nan"), "surface_penetration_um": float("nan"),
                    "load_splits": 0, "name": name, "depth": depth, "failed": True,
                    "error": str(err), "over_budget": isinstance(err, NewtonBudgetError)}
        dt = time.perf_counter() - t0
        # the gel's continuous surface against the indenter, checked every 20 um (the solver's
        # own figure is at its constraint points only)
        surface, _ = surface_penetration(sol, indenter_field(get_indenter(name), pose),
                                         pitch_mm=0.02, geometric=model != "linear")
    return {"seconds": dt, "nodes": sol.info["n_nodes"], "factorizations": sol.info["factorizations"],
            "penetration_um": 1e3 * sol.max_penetration_mm, "surface_penetration_um": 1e3 * surface,
            "load_splits": sol.info["load_splits"], "name": name, "depth": depth, "failed": False,
            "newton_steps": sol.info["newton_steps"]}


def run(n: int = 6, workers: int = 2, seed: int = 5, newton_budget: int = 80) -> dict:
    from tactile_deploy.fem.sparse_solver import sparse_backend

    contacts = _contacts(n, seed)
    _solve(("pad-mesh", "frictionless", None, None, contacts[0]))  # the pad mesh's response cache
    backend = sparse_backend()
    out = {}
    for label, (model, friction, linear_solver) in SETTINGS.items():
        if label == SUPERLU and backend == "superlu":
            continue  # the row above is SuperLU already
        t0 = time.perf_counter()
        with ProcessPoolExecutor(workers) as pool:
            rows = list(pool.map(_solve, [(model, friction, linear_solver, newton_budget, c)
                                          for c in contacts]))
        wall = time.perf_counter() - t0
        out[label] = {"contacts_per_s": n / wall, "rows": rows, "wall_s": wall}
    return {"n": n, "workers": workers, "settings": out, "load": os.getloadavg()[0],
            "backend": backend, "newton_budget": newton_budget}


BACKEND_NAMES = {"pardiso": "Intel MKL PARDISO (the `pardiso` extra)",
                 "superlu": "SuperLU (scipy; the `pardiso` extra is not installed)"}


def _failure(row: dict) -> str:
    """A failed contact's cell: over the Newton budget, or not converged (seconds spent)."""
    what = "budget spent" if row.get("over_budget") else "not converged"
    return f"{what} ({row['seconds']:.0f} s)"


def _mean_converged(rows: list[dict], key: str) -> str:
    values = [x[key] for x in rows if not x["failed"] and key in x]
    return f"{sum(values) / len(values):.1f}" if values else "-"


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
        f"nu 0.48; load average {result['load']:.1f} on the machine's 2 cores when finished. "
        f"Tangents factorised by {BACKEND_NAMES[result.get('backend', 'superlu')]} unless the "
        f"setting says otherwise; a contact not converged within {result.get('newton_budget')} "
        "Newton steps in all counts as not converged.",
        "",
        "| setting | contacts/s | vs baseline | median s per contact | median truth nodes | "
        "Newton steps per converged contact | "
        "factorisations per converged contact (modified Newton reuses them) | largest penetration at constraint points (um) | largest penetration of the continuous surface (um) | not converged |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, r in result["settings"].items():
        rows = r["rows"]
        lines.append(
            f"| {label} | {r['contacts_per_s']:.3f} | {r['contacts_per_s'] / base:.2f}x | "
            f"{np.median([x['seconds'] for x in rows]):.1f} | {np.median([x['nodes'] for x in rows]):.0f} | "
            f"{_mean_converged(rows, 'newton_steps')} | "
            f"{_mean_converged(rows, 'factorizations')} | "
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
            cells.append(_failure(x) if x["failed"] else
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
    parser.add_argument("--newton-budget", type=int, default=80,
                        help="Newton steps per contact at most (every load step and retry)")
    parser.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = parser.parse_args(argv)
    result = run(args.n, args.workers, newton_budget=args.newton_budget)
    text = markdown(result)
    print(text)
    if not args.no_write:
        from bench.report import write_section

        write_section("sim-resolved", text)
    return result


if __name__ == "__main__":
    main()
