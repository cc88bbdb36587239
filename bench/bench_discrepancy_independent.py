"""The discrepancy workflow on effects made by code outside the product: confusion matrix,
naming accuracy, false positives, parameter recovery.

    tactile-deploy bench discrepancy --independent [--seeds 5] [--contacts 40] [--null 4]
        [--effects a,b,...] [--no-write]
    tactile-deploy bench discrepancy --independent --seed-list 3 --effects blur --null 0 \
        --results part.json      # one part of the run (parts run in parallel processes)
    tactile-deploy bench discrepancy --independent --summarise part1.json part2.json ...

Every dataset draws its parameters and noise from its own generator, seeded by (seed, dataset):
a part run alone gives the datasets the whole run gives, so a run can be split over processes
or machines and its parts summarised together.

Measured data: per seed, commanded contacts of five of the shared indenter meshes
(``../shared/data/indenters``: sphere, sphere2, cylinder_side, prism, hexagon), within 8 mm of the
centre, 0.3-0.9 mm deep; their clean ``simulate`` output (the shipped sensor's pad and material,
no effects); each effect applied in its textbook form by ``tests/independent_effects.py`` (numpy,
scipy and OpenCV only), at parameters drawn at random from what real sensors show; 4 um white
pixel noise, 1 % force noise. The sensor model given to the workflow is the shipped one
(``gelslim1``). The response tables of a contact set are made once and shared by its datasets.

Targets: >= 90 % of the in-library effects named, their parameters within tolerance, <= 5 %
false positives on effect-free data, out-of-library effects (banding, dust) ``unexplained``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import independent_effects as ind  # noqa: E402

SHARED_INDENTERS = ("sphere", "sphere2", "cylinder_side", "prism", "hexagon")
NOISE_MM = 0.004
#: Effects of the full run (every key of independent_effects.EXPECTED).
EFFECTS = tuple(ind.EXPECTED)
#: Parameter tolerances: scalar parameters (absolute), view displacement fields (RMS over the
#: pad within 9 mm of the centre, mm, or this share of the true field's RMS when larger), gain
#: fields (RMS over the same region).
TOLERANCE = {"offset_mm": 0.002, "scale": 0.003, "dx_mm": 0.03, "dy_mm": 0.03,
             "dtheta_deg": 1.0, "height_mm": 0.03, "delta_nu": 0.003, "sigma_mm": 0.03,
             "max_slope_rel": 0.1, "view_mm": 0.01, "view_rel": 0.1, "gain": 0.01,
             "mu_min": 0.8}


def shared_indenter(name: str) -> str:
    path = ROOT.parent / "shared" / "data" / "indenters" / f"{name}.stl"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: the independent benchmark presses the shared "
                                "indenter meshes (../shared/data/indenters beside the checkout)")
    return str(path)


def random_contacts(n: int, seed: int, indenters, radius_mm: float = 8.0,
                    depth_range_mm=(0.3, 0.9)) -> list:
    rng = np.random.default_rng([seed, 0x696E64])
    out = []
    for i in range(n):
        r = radius_mm * np.sqrt(rng.uniform())
        a = rng.uniform(0.0, 2 * np.pi)
        out.append(ind.Contact(indenters[i % len(indenters)], float(r * np.cos(a)),
                               float(r * np.sin(a)), float(rng.uniform(0.0, 180.0)),
                               float(rng.uniform(*depth_range_mm))))
    return out


def clean_simulator(sensor):
    """simulate(contacts, material) -> (maps, forces): the clean ``simulate`` output of the
    sensor's pad and material (another Poisson ratio or sticking contact on request)."""
    from tactile_deploy.indenters import ContactPose, get_indenter
    from tactile_deploy.simulation.contact import get_simulator, simulate_contact

    base = sensor.config.material

    def simulate(contacts, material=None):
        mat = base
        if material and "delta_nu" in material:
            mat = base.model_copy(update={"nu": base.nu + material["delta_nu"]})
        if material and "friction" in material:
            mat = base.model_copy(update={"friction": material["friction"]})
        sim = sensor.simulator if mat == base else get_simulator(mat, sensor.config.pad)
        maps, forces = [], []
        for c in contacts:
            try:
                s = simulate_contact(get_indenter(c.indenter),
                                     ContactPose(x_mm=c.x_mm, y_mm=c.y_mm, theta_deg=c.theta_deg,
                                                 depth_mm=c.depth_mm), mat, simulator=sim)
            except RuntimeError:  # the solver did not settle: that contact is left out
                maps.append(np.full((128, 128), np.nan))
                forces.append(np.nan)
                continue
            maps.append(s.depth_mm.astype(np.float64))
            forces.append(s.force_n)
        return np.stack(maps), np.array(forces)

    return simulate


def measured_data(contacts, maps, forces, rng, source: str):
    from tactile_deploy.calibration.discrepancy.measured import MeasuredData

    n = len(contacts)
    return MeasuredData(
        depth_mm=np.asarray(maps, np.float32), frames=None,
        indenter=[c.indenter for c in contacts],
        x_mm=np.array([c.x_mm for c in contacts]), y_mm=np.array([c.y_mm for c in contacts]),
        theta_deg=np.array([c.theta_deg for c in contacts]),
        depth_cmd_mm=np.array([c.depth_mm for c in contacts]),
        force_n=np.asarray(forces) * (1.0 + 0.01 * rng.standard_normal(n)),
        contact_id=np.arange(n), source=source)


def label(v) -> str:
    return v.effect if v.verdict == "effect" else v.verdict


def parameter_check(effect: str, truth: dict, named: str, p: dict,
                    camera_mapping) -> tuple[bool, dict]:
    """Whether the parameters ``p`` of the named candidate ``named`` match the truth of the
    independent ``effect`` (TOLERANCE), and the errors."""
    from tactile_deploy.sensors.effects import get_effect

    region = ind.PAD & (np.hypot(ind.X_MM, ind.Y_MM) <= 9.0)
    if effect in ("radial_map", "radial_image", "pixel_scale_iso", "pixel_scale_axis"):
        tx, ty = ind.view_displacement(effect, truth, camera_mapping.model_dump())
        fx = get_effect(named, p)
        pts = np.stack([ind.X_MM[region], ind.Y_MM[region]], axis=1)
        q = fx.view_points(pts, camera_mapping)
        err = np.sqrt(np.mean((q[:, 0] - pts[:, 0] - tx[region]) ** 2
                              + (q[:, 1] - pts[:, 1] - ty[region]) ** 2))
        size = np.sqrt(np.mean(tx[region] ** 2 + ty[region] ** 2))
        tol = max(TOLERANCE["view_mm"], TOLERANCE["view_rel"] * size)
        return bool(err <= tol), {"view_rms_mm": float(err), "true_view_rms_mm": float(size),
                                  "tolerance_mm": float(tol)}
    if effect == "gain_gradient":
        true = truth["g0"] + truth["g_x"] * ind.X_MM + truth["g_y"] * ind.Y_MM
        fit = p["gain"] + p["gain_per_mm_x"] * ind.X_MM + p["gain_per_mm_y"] * ind.Y_MM
        err = float(np.sqrt(np.mean((fit - true)[region] ** 2)))
        return err <= TOLERANCE["gain"], {"gain_rms": err}
    if effect == "saturation":
        c = p.get("inverse_max_slope", 0.0)
        rel = abs(1.0 / c - truth["max_slope"]) / truth["max_slope"] if c > 0 else np.inf
        return bool(rel <= TOLERANCE["max_slope_rel"]), {"max_slope_rel": float(rel)}
    if effect == "friction":
        return bool(p["mu"] >= TOLERANCE["mu_min"]), {"mu": float(p["mu"])}
    key = {"blur": ("sigma_mm", "sigma_mm"), "poisson": ("delta_nu", "delta_nu")}
    pairs = [key[effect]] if effect in key else [(k, k) for k in truth]
    errors = {k: float(p.get(k, np.nan) - truth[t]) for t, k in pairs}
    return bool(all(abs(e) <= TOLERANCE[k] for k, e in errors.items())), errors


def run_dataset(sensor, tables, contacts, clean, clean_forces, effect, params, simulate, camera,
                rng, opts) -> dict:
    """One dataset through the workflow: the record of its verdict."""
    from tactile_deploy.calibration.discrepancy.workflow import find_discrepancy

    import tempfile

    with tempfile.TemporaryDirectory() as work:
        maps, forces = ind.measured_maps(effect, params, contacts, clean, simulate,
                                         camera.model_dump() if camera is not None else None,
                                         NOISE_MM, rng, Path(work))
    forces = clean_forces if forces is None else forces
    ok = np.flatnonzero(np.all(np.isfinite(maps), axis=(1, 2)))
    data = measured_data([contacts[i] for i in ok], maps[ok], np.asarray(forces)[ok], rng,
                         f"independent {effect}")
    if len(ok) < len(contacts):
        tables = tables.subset(ok)
    t0 = time.perf_counter()
    v = find_discrepancy(sensor, data, opts, tables=tables).verdict
    entry = {"effect": effect, "truth": params, "label": label(v),
             "expected": ind.EXPECTED.get(effect, "none"), "parameters": v.parameters,
             "gap_before_mm": v.gap_before_mm, "gap_after_mm": v.gap_after_mm,
             "explained": v.explained_fraction, "time_s": time.perf_counter() - t0,
             "contacts_left_out": len(contacts) - len(ok),
             "static": v.fingerprint.get("static_structure")}
    if v.verdict == "effect" and effect in ind.EXPECTED and v.effect == ind.EXPECTED[effect]:
        entry["parameters_ok"], entry["errors"] = parameter_check(effect, params, v.effect,
                                                                  v.parameters, camera)
    return entry


def dataset_rng(seed: int, effect: str, null_index: int = 0) -> np.random.Generator:
    """The generator of one dataset: the effect's parameters, its noise and the force noise.
    Seeded by the contact set, the effect's place in EFFECTS (effect-free datasets after them)
    and the effect-free dataset's number: the same wherever and with whatever else it runs."""
    k = EFFECTS.index(effect) if effect != "none" else len(EFFECTS) + null_index
    return np.random.default_rng([seed, k, 0x62656E63])


def run(sensor_name: str, seeds, n_contacts: int, n_null: int, effects, log=print,
        workers: int = 2, checkpoint=None) -> dict:
    """Every effect (and ``n_null`` effect-free datasets) on the contact sets ``seeds`` (a list
    of seeds, or a count: seeds 0..n-1) of ``n_contacts``; ``checkpoint(results)`` is called
    after each dataset with the results so far (a run stopped early can still be summarised)."""
    from tactile_deploy.calibration.discrepancy.workflow import DiscrepancyOptions, prepare_tables
    from tactile_deploy.sensors import load_sensor

    seeds = list(range(seeds)) if isinstance(seeds, int) else [int(s) for s in seeds]
    sensor = load_sensor(sensor_name)
    sensor.simulator.prepare()
    simulate = clean_simulator(sensor)
    camera = sensor.config.optics.camera
    opts = DiscrepancyOptions(workers=workers)
    indenters = [shared_indenter(n) for n in SHARED_INDENTERS]
    runs, t_start = [], time.perf_counter()
    for done, seed in enumerate(seeds):
        contacts = random_contacts(n_contacts, seed, indenters)
        clean, clean_forces = simulate(contacts)
        t0 = time.perf_counter()
        tables = prepare_tables(sensor, measured_data(
            contacts, clean, clean_forces, np.random.default_rng([seed, 0x7461626C]), "clean"),
            opts)
        log(f"contact set {seed}: {n_contacts} contacts tabulated in "
            f"{time.perf_counter() - t0:.0f} s")
        for effect, null_index in [*((e, 0) for e in effects), *(("none", j) for j in range(n_null))]:
            rng = dataset_rng(seed, effect, null_index)
            params = ind.draw(effect, rng) if effect != "none" else {}
            entry = run_dataset(sensor, tables, contacts, clean, clean_forces, effect, params,
                                simulate, camera, rng, opts)
            entry["seed"] = seed
            runs.append(entry)
            log(f"[{time.perf_counter() - t_start:6.0f} s] seed {seed} {effect} "
                f"{json.dumps(params, default=float)} -> {entry['label']} "
                f"{json.dumps(entry['parameters'], default=float)} explained "
                f"{entry['explained']} params ok {entry.get('parameters_ok')} "
                f"({entry['time_s']:.0f} s)")
            if checkpoint is not None:
                checkpoint(_results(runs, sensor_name, seeds[: done + 1], n_contacts, effects,
                                    t_start, complete=False))
    return _results(runs, sensor_name, seeds, n_contacts, effects, t_start, complete=True)


def _results(runs, sensor_name, seeds, n_contacts, effects, t_start, complete) -> dict:
    import os

    from bench.report import machine_line

    return {"runs": runs, "sensor": sensor_name, "seeds": len(seeds), "seed_list": list(seeds),
            "contacts": n_contacts, "effects": list(effects),
            "wall_s": time.perf_counter() - t_start, "load_average": os.getloadavg(),
            "machine": machine_line(), "processes": 1, "complete": complete}


def merge_results(parts: list[dict]) -> dict:
    """The parts of one run (same sensor and contacts per seed), run side by side, as one
    result: their datasets together, the longest part's wall time."""
    first = parts[0]
    for p in parts[1:]:
        for key in ("sensor", "contacts"):
            if p[key] != first[key]:
                raise ValueError(f"results to merge differ in {key!r}: {first[key]!r} and "
                                 f"{p[key]!r}; summarise parts of one run only")
    runs = [r for p in parts for r in p["runs"]]
    seeds = sorted({r["seed"] for r in runs})
    effects = [e for e in EFFECTS if any(e in p["effects"] for p in parts)]
    return {"runs": runs, "sensor": first["sensor"], "seeds": len(seeds), "seed_list": seeds,
            "contacts": first["contacts"], "effects": effects,
            "wall_s": max(p["wall_s"] for p in parts),
            "load_average": [max(p["load_average"][i] for p in parts) for i in range(3)],
            "machine": first.get("machine"), "processes": sum(p.get("processes", 1) for p in parts),
            "complete": all(p.get("complete", True) for p in parts)}


def _coverage(res: dict) -> str:
    """Which effects ran, and whether the run finished (a stopped run is summarised as far as it
    went)."""
    runs = res["runs"]
    n_null = sum(r["effect"] == "none" for r in runs)
    full = set(res["effects"]) == set(EFFECTS)
    text = (f"Effects: {'all ' + str(len(EFFECTS)) if full else ', '.join(res['effects'])}"
            f" ({len(runs)} datasets, {n_null} effect-free)")
    if res.get("complete", True):
        return text + "."
    return text + f"; the run was stopped after {len(runs)} datasets."


def summarise(res: dict) -> tuple[str, dict]:
    from bench.report import machine_line
    from tactile_deploy.sensors.catalog import sensor_config

    runs = res["runs"]
    machine = res.get("machine") or machine_line()
    processes = res.get("processes", 1)
    where = "" if processes == 1 else f" as {processes} processes side by side"
    camera = sensor_config(res["sensor"]).optics.camera
    for r in runs:  # parameter checks with the tolerances of this file
        if r["label"] == r["expected"] and r["expected"] not in ("none", "unexplained"):
            r["parameters_ok"], r["errors"] = parameter_check(r["effect"], r["truth"],
                                                              r["label"], r["parameters"], camera)
    library = [r for r in runs if r["expected"] not in ("none", "unexplained")]
    outside = [r for r in runs if r["expected"] == "unexplained"]
    null = [r for r in runs if r["effect"] == "none"]
    named = sum(r["label"] == r["expected"] for r in library)
    params_ok = sum(bool(r.get("parameters_ok")) for r in library)
    fp = sum(r["label"] != "none" for r in null)
    unexplained = sum(r["label"] == "unexplained" for r in outside)
    rows = [e for e in res["effects"]] + ["none"]
    labels = sorted({r["label"] for r in runs} | {"none", "unexplained"},
                    key=lambda s: (s in ("none", "unexplained", "ambiguous"), s))
    head = "| made outside \\ verdict | " + " | ".join(labels) + " |"
    lines = [head, "|---" * (len(labels) + 1) + "|"]
    for e in rows:
        rr = [r for r in runs if r["effect"] == e]
        if rr:
            exp = rr[0]["expected"]
            lines.append(f"| **{e}** (-> {exp}) | " + " | ".join(
                str(sum(r['label'] == lab for r in rr)) for lab in labels) + " |")
    per = ["| effect (textbook form) | runs | named | parameters within tolerance | gap before "
           "-> after, um (median) | time per run, s (median) |", "|---|---:|---:|---:|---|---:|"]
    for e in rows:
        rr = [r for r in runs if r["effect"] == e]
        if not rr:
            continue
        ok = sum(r["label"] == r["expected"] for r in rr)
        pok = sum(bool(r.get("parameters_ok")) for r in rr)
        after = [r["gap_after_mm"] for r in rr if r["gap_after_mm"] is not None]
        per.append(f"| {e} | {len(rr)} | {ok} | {pok if rr[0]['expected'] not in ('none', 'unexplained') else '-'} | "
                   f"{1e3 * np.median([r['gap_before_mm'] for r in rr]):.2f} -> "
                   f"{f'{1e3 * np.median(after):.2f}' if after else '-'} | "
                   f"{np.median([r['time_s'] for r in rr]):.0f} |")
    n_lib = max(len(library), 1)
    acc = named / n_lib
    fpr = fp / max(len(null), 1)
    text = f"""## Discrepancy workflow on effects made outside the product (`tactile-deploy bench discrepancy --independent`)

{machine}; whole benchmark {res['wall_s'] / 60:.0f} min{where}, load average
{res['load_average'][2]:.1f} over its last 15 min. Sensor model
`{res['sensor']}` (5,380-node pad); per seed {res['contacts']} commanded contacts of five shared
indenter meshes (sphere, sphere2, cylinder_side, prism, hexagon; within 8 mm of the centre,
0.3-0.9 mm deep), their clean `simulate` output with one effect applied by
`tests/independent_effects.py` (numpy, scipy, OpenCV; none of the product's effect code), 4 um
pixel noise, 1 % force noise; {res['seeds']} seeds, parameters drawn at random per seed from
what real sensors show (either sign where both occur). {_coverage(res)}

| measure | result | target |
|---|---|---|
| in-library effects named | {named} / {len(library)} = {100 * acc:.0f} % | >= 90 %: {'met' if acc >= 0.9 else 'NOT met'} |
| named with parameters within tolerance | {params_ok} / {named} | all |
| false positives on effect-free data | {fp} / {len(null)} = {100 * fpr:.0f} % | <= 5 %: {'met' if fpr <= 0.05 else 'NOT met'} |
| out-of-library effects (banding, dust) reported as unexplained | {unexplained} / {len(outside)} | all |
| contacts left out (the clean simulation did not settle) | {sum(r.get('contacts_left_out', 0) for r in runs)} in {sum(bool(r.get('contacts_left_out')) for r in runs)} datasets | - |

Confusion matrix (rows: the effect applied outside and the candidate that should name it;
columns: the verdict):

{chr(10).join(lines)}

{chr(10).join(per)}

Tolerances: offsets 2 um, depth scale 0.003, position 0.03 mm, rotation 1 degree, dome 0.03 mm,
Poisson ratio 0.003,
blur 0.03 mm, saturation slope 10 %; views (radial distortion of the map or of the image,
pixel scale) by their displacement field over the pad within 9 mm of the centre: RMS error
<= 0.01 mm or 10 % of the true field's RMS; gain fields: RMS error <= 0.01; sticking gel: a
friction coefficient >= 0.8 (the sticking limit).
"""
    return text, {"accuracy": acc, "false_positive_rate": fpr, "named": named,
                  "library_runs": len(library), "parameters_ok": params_ok,
                  "unexplained": unexplained, "outside_runs": len(outside)}


def main(argv=None) -> dict:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--independent", action="store_true")
    parser.add_argument("--sensor", default="gelslim1")
    parser.add_argument("--seeds", type=int, default=5, help="contact sets 0..N-1")
    parser.add_argument("--seed-list", default=None,
                        help="comma list of contact sets to run instead of --seeds (one part)")
    parser.add_argument("--contacts", type=int, default=40)
    parser.add_argument("--null", type=int, default=4, help="effect-free datasets per seed")
    parser.add_argument("--effects", default=None,
                        help="comma list (default: all; an empty string: effect-free only)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--results", type=Path, default=None,
                        help="write the results JSON here (a part: BENCHMARKS.md is not touched)")
    parser.add_argument("--summarise", type=Path, nargs="+", default=None,
                        help="summarise the results JSON of an earlier run, or of its parts run "
                             "side by side (no new runs)")
    args = parser.parse_args(argv)
    effects = (EFFECTS if args.effects is None
               else tuple(e for e in args.effects.split(",") if e))
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        parser.error(f"--effects: unknown {', '.join(unknown)}; known: {', '.join(EFFECTS)}")
    seeds = ([int(x) for x in args.seed_list.split(",")] if args.seed_list else args.seeds)
    from tactile_deploy.atomic import write_text

    results_path = args.results or ROOT / "bench" / "results" / "discrepancy-independent.json"

    def save(res):
        results_path.parent.mkdir(parents=True, exist_ok=True)
        write_text(results_path, json.dumps(res, indent=1, default=float) + "\n")

    if args.summarise is not None:
        parts = [json.loads(p.read_text()) for p in args.summarise]
        res = parts[0] if len(parts) == 1 else merge_results(parts)
    else:
        res = run(args.sensor, seeds, args.contacts, args.null, effects,
                  log=lambda m: print(m, flush=True), workers=args.workers,
                  checkpoint=None if args.no_write else save)
    if args.results is not None:
        save(res)
        return {}
    text, summary = summarise(res)
    print(text)
    if not args.no_write:
        from bench.report import write_section

        write_section("discrepancy-independent", text)
        if args.summarise is None or len(args.summarise) > 1:
            results_path = ROOT / "bench" / "results" / "discrepancy-independent.json"
            save(res)
    return summary


if __name__ == "__main__":
    main()
