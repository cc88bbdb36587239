"""The paper's Table 2 on our domains, in one command.

    tactile-deploy bench adapt-tables -- --aug out/predictor/shipped_aug [--clean exported/gelslim_mesh.pt] \
        [--steps 200] [--lr 1e-4] [--n-adapt 200] [--n-eval 100] [--transfer clean|aug] [--write docs/adaptation.md]

Two models: one trained on clean simulated depth maps (default: the shipped bundle with its ONNX
model and committed step), one with augmentation (a training run folder, e.g. the augmented twin
of :mod:`tactile_deploy.training.adaptation.augmented_twin`). A run folder without its exports gets the ONNX
graph and the adaptation step exported into ``out/adapt/models/<clean|aug>/`` (the runtime's
files, as ``tactile-deploy adapt`` uses them). Every adaptation runs through the runtime's own code
(:mod:`tactile_deploy.adapt.step`): ``n_adapt`` depth maps of the target domain to adapt on,
``n_eval`` maps of *other* presses to measure on.

Figures per row, on the evaluation maps (mm in the data, um in the tables):

* **label-free RMSE** (the paper's metric): rendered predicted mesh vs the model's own VAE
  reconstruction of the input, over the pixels the sensor sees;
* **depth RMSE vs truth**: rendered predicted mesh vs the clean simulated depth map of the same
  contact (virtual domains only);
* **vertex RMSE vs truth**: predicted vs the virtual sensor's FEM mesh, all 5,380 nodes and axes
  (what the paper could not measure).

Rows: Table 2a (ablation on Real-Prim = virtual gelslim1): adapt + aug., neither, aug. only,
adapt only, adapt + aug. without the VAE filter. Table 2b (transfers, the ``--transfer`` model):
Sim -> Real-Prim, Sim -> Real-Prim-2 (gelslim2), Real-Prim -> Real-Prim-2, Real-Prim ->
Real-Novel (the shared STL indenters on gelslim1), Sim -> Real-Novel, Sim -> real ball presses
(../shared/data/real, label-free only); and Sim-Prim, the simulator's own held-out maps. Each
virtual row also gives LF*, the label-free figure the true mesh would get (true depth vs VAE(I)).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.report import write_section  # noqa: E402
from tactile_deploy.calibration.shading.real_gelsight import real_gelsight_plugin  # noqa: E402
from tactile_deploy.training.adaptation.domains import (  # noqa: E402
    REAL_PLUGIN_FOLDER,
    Domain,
    load_or_make,
    rmse_mm,
)

WORK = ROOT / "out" / "adapt"


def export_model(run: Path, out: Path, log=print) -> tuple[Path, Path]:
    """Shipped ONNX graph (+ fp32 twin, card) and adaptation step of a training run, into
    ``out``; reused when present. A bundle ``NAME.pt`` with ``NAME.onnx`` and its step
    ``NAME_adapt/`` beside it (``exported/gelslim_mesh.pt``) is used as it is. Returns (onnx, step folder)."""
    from tactile_deploy.training.adaptation.export import export_step
    from tactile_deploy.training.export import export_run

    if run.suffix == ".pt":
        onnx, step = run.with_suffix(".onnx"), run.with_name(run.stem + "_adapt")
        if not (onnx.is_file() and (step / "card.json").is_file()):
            raise FileNotFoundError(f"{run}: {onnx} or {step}/card.json is missing; export them (python -m tactile_deploy.training "
                                    f"export-adapt --bundle {run} --onnx {onnx})")
        return onnx, step
    if (run / "gelslim_mesh.onnx").is_file() and (run / "gelslim_mesh_adapt" / "card.json").is_file():
        return run / "gelslim_mesh.onnx", run / "gelslim_mesh_adapt"
    out.mkdir(parents=True, exist_ok=True)
    onnx = out / "gelslim_mesh.onnx"
    step = out / "gelslim_mesh_adapt"
    if not onnx.is_file():
        log(f"exporting {run} -> {onnx}")
        export_run(run, onnx)
    if not (step / "card.json").is_file():
        log(f"exporting the adaptation step -> {step}")
        export_step(run / "model.pt", onnx, step, log=log)
    return onnx, step


class Model:
    """A model under test: its step program (weights reset per experiment) and filter."""

    def __init__(self, name: str, step_folder: Path):
        from tactile_deploy.adapt.step import StepProgram

        self.name = name
        self.program = StepProgram.load(step_folder)
        self.family = self.program.weights()

    def targets(self, domain: Domain, use_filter: bool = True) -> np.ndarray:
        from tactile_deploy.adapt.step import adaptation_target

        return adaptation_target(self.program, domain.depth_mm, use_filter)[0]


def measure(model: Model, domain: Domain, weights: dict) -> dict:
    """Figures of ``weights`` on the evaluation maps of ``domain`` (module docstring), mm."""
    from tactile_deploy.adapt.step import evaluate

    model.program.load_weights(weights)
    target = model.targets(domain)
    ev = evaluate(model.program, domain.depth_mm, target, domain.weight, keep=("rendered", "displacement"))
    out = {"label_free_rmse_mm": ev.rmse_mm, "overflow": ev.overflow, "n": len(domain)}
    if domain.true_depth_mm is not None:
        out["depth_vs_truth_rmse_mm"] = rmse_mm(ev.rendered_mm, domain.true_depth_mm, domain.weight)
        # the label-free figure the true mesh would get: how far the target VAE(I) is from the truth
        out["truth_label_free_rmse_mm"] = rmse_mm(domain.true_depth_mm, target, domain.weight)
        from tactile_deploy.pad.asset import load_pad

        rest = load_pad().vertices.astype(np.float32)
        true_disp = domain.vertices_mm - rest[None]
        out["vertex_rmse_mm"] = float(np.sqrt(np.mean((ev.displacement_mm.astype(np.float64) - true_disp) ** 2)))
        out["vertex_rmse_sensing_mm"] = float(np.sqrt(np.mean(
            (ev.displacement_mm[:, :1076].astype(np.float64) - true_disp[:, :1076]) ** 2)))
    return out


def run_adaptation(model: Model, domain: Domain, start: dict, steps: int, use_filter: bool = True,
                   lr: float = 1e-4, batch: int = 16, seed: int = 0) -> tuple[dict, dict]:
    """Adapt from weights ``start`` on ``domain`` (all its maps); (adapted weights, info)."""
    from tactile_deploy.adapt.step import AdaptSettings, adapt

    model.program.load_weights(start)
    target = model.targets(domain, use_filter)
    hist = adapt(model.program, domain.depth_mm, target, domain.weight,
                 AdaptSettings(steps=steps, batch_size=batch, lr=lr, seed=seed))
    return model.program.weights(), {"seconds": hist.seconds, "steps": steps, "lr": lr, "batch": batch,
                                     "use_filter": use_filter, "loss_first_mm2": hist.loss_mm2[0],
                                     "loss_last_mm2": hist.loss_mm2[-1]}


def tune_lr(model: Model, domain: Domain, lrs: list[float], steps: int, n_valid: int = 40, log=print) -> dict:
    """Label-free choice of the learning rate, as a device could make it: adapt on the first
    maps of ``domain`` (its adaptation part), measure the label-free RMSE on its last
    ``n_valid`` maps; returns {lr: rmse_mm} (and the start)."""
    from tactile_deploy.adapt.step import evaluate

    fit, valid = domain.split(len(domain) - n_valid)
    target = model.targets(valid)
    model.program.load_weights(model.family)
    out = {"start": evaluate(model.program, valid.depth_mm, target, valid.weight).rmse_mm}
    log(f"start: {out['start'] * 1e3:.2f} um")
    for lr in lrs:
        weights, info = run_adaptation(model, fit, model.family, steps, lr=lr)
        model.program.load_weights(weights)
        out[lr] = evaluate(model.program, valid.depth_mm, target, valid.weight).rmse_mm
        log(f"lr {lr:g}: {out[lr] * 1e3:.2f} um ({info['seconds']:.0f} s)")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clean", type=Path, default=ROOT / "exported" / "gelslim_mesh.pt",
                    help="model trained without augmentation: a training run, or a bundle with its ONNX model and "
                    "step beside it (default: the shipped model)")
    ap.add_argument("--aug", type=Path, required=True, help="its augmented twin (a run folder)")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--n-adapt", type=int, default=200)
    ap.add_argument("--n-eval", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=WORK)
    ap.add_argument("--write", type=Path, default=None, help="write the tables into this markdown file's section")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--tune-lr", type=float, nargs="+", default=None,
                    help="only choose the learning rate (label-free, on gelslim1's adaptation maps) and stop")
    ap.add_argument("--tune-model", choices=["clean", "aug"], default="clean")
    ap.add_argument("--transfer", choices=["clean", "aug"], default="clean",
                    help="model of Table 2b (default: the clean one, i.e. the shipped model)")
    ap.add_argument("--batch", type=int, default=16)
    args = ap.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    n = args.n_adapt + args.n_eval
    domains_dir = args.work / "domains"
    dom = {name: load_or_make(name, n, args.seed, domains_dir) for name in ("gelslim1", "gelslim2", "gelslim1-novel")}
    split = {k: d.split(args.n_adapt) for k, d in dom.items()}
    if not (domains_dir / REAL_PLUGIN_FOLDER / "plugin.json").is_file():
        real_gelsight_plugin(domains_dir / REAL_PLUGIN_FOLDER)
    balls = load_or_make("real-balls", 42, 0, domains_dir)
    split["real-balls"] = balls.split(30)
    sim = load_or_make("sim", args.n_eval, 1000 + args.seed, domains_dir)
    runs = {"clean": args.clean, "aug": args.aug}
    if args.tune_lr:
        _, step = export_model(runs[args.tune_model], args.work / "models" / args.tune_model)
        print(json.dumps(tune_lr(Model(args.tune_model, step), split["gelslim1"][0], args.tune_lr, args.steps), indent=1))
        return 0
    models = {}
    for key, run in runs.items():
        _, step = export_model(run, args.work / "models" / key)
        models[key] = Model(key, step)
    results: dict = {"settings": vars(args) | {"clean": str(args.clean), "aug": str(args.aug),
                                                "work": str(args.work), "write": str(args.write)},
                     "rows": {}}

    def row(name, model_key, domain_key, start, adapt_on=None, use_filter=True):
        model = models[model_key]
        adapt_d, eval_d = split[domain_key] if domain_key in split else (None, sim)
        before = measure(model, eval_d, start)
        entry = {"model": model_key, "domain": domain_key, "before": before}
        weights = start
        if adapt_on is not None:
            weights, info = run_adaptation(model, adapt_on, start, args.steps, use_filter, args.lr, args.batch,
                                           seed=args.seed)
            entry["after"] = measure(model, eval_d, weights)
            entry["adaptation"] = info
        results["rows"][name] = entry
        print(f"{name}: {json.dumps(entry, default=float)[:400]}", flush=True)
        return weights

    aug, clean = models["aug"].family, models["clean"].family
    m = args.transfer  # the model of Table 2b
    start = models[m].family
    row("sim-prim (aug)", "aug", "sim", aug)
    row("sim-prim (clean)", "clean", "sim", clean)
    g1 = {}
    for key in ("aug", "clean"):
        g1[key] = row(f"{key}: sim -> gelslim1", key, "gelslim1", models[key].family, split["gelslim1"][0])
    row("aug, no filter: sim -> gelslim1", "aug", "gelslim1", aug, split["gelslim1"][0], use_filter=False)
    row(f"{m}: sim -> gelslim2", m, "gelslim2", start, split["gelslim2"][0])
    row(f"{m}: gelslim1 -> gelslim2", m, "gelslim2", g1[m], split["gelslim2"][0])
    row(f"{m}: gelslim1 -> gelslim1-novel", m, "gelslim1-novel", g1[m], split["gelslim1-novel"][0])
    row(f"{m}: sim -> gelslim1-novel", m, "gelslim1-novel", start, split["gelslim1-novel"][0])
    row(f"{m}: sim -> real-balls", m, "real-balls", start, split["real-balls"][0])
    results["seconds"] = time.perf_counter() - t0
    from tactile_deploy.atomic import write_json

    args.work.mkdir(parents=True, exist_ok=True)
    write_json(args.work / "tables.json", results)
    md = tables_markdown(results)
    print(md)
    if args.write is not None:
        write_section("adaptation-tables", md, args.write)
    return 0


def _um(x) -> str:
    return "-" if x is None else f"{x * 1e3:.1f}"


def tables_markdown(results: dict) -> str:
    rows = results["rows"]
    s = results["settings"]

    def fig(name, when, key):
        e = rows[name].get(when)
        return None if e is None else e.get(key)

    def rel(path: str) -> str:
        p = Path(path)
        return p.relative_to(ROOT).as_posix() if p.is_absolute() and p.is_relative_to(ROOT) else path

    s = s | {"clean": rel(s["clean"]), "aug": rel(s["aug"])}
    lines = [
        f"Models: clean `{s['clean']}`, augmented `{s['aug']}` (docs/adaptation.md says how they were trained). "
        f"Adaptation: {s['steps']} Adam steps, lr {s['lr']:g}, batch {s.get('batch', 16)}, on {s['n_adapt']} maps of the target "
        f"domain; figures on {s['n_eval']} maps of other presses (real balls: 30 / 12). um; "
        "LF = label-free RMSE (rendered mesh vs the model's VAE(I), the paper's metric), "
        "D = rendered mesh vs the true clean depth map, V = vertex RMSE vs the true FEM mesh (all nodes).",
        "",
        "**Table 2a** (Real-Prim: virtual gelslim1, primitive indenters; LF* = the LF the true mesh gets)",
        "",
        "| setting | LF | D | V | LF* |",
        "|---|---|---|---|---|",
    ]
    ablation = [
        ("Adapt + Aug.", "aug: sim -> gelslim1", "after"),
        ("No Aug. No Adapt", "clean: sim -> gelslim1", "before"),
        ("Only Aug.", "aug: sim -> gelslim1", "before"),
        ("Only Adapt", "clean: sim -> gelslim1", "after"),
        ("Adapt + Aug. w/o VAE", "aug, no filter: sim -> gelslim1", "after"),
    ]
    for label, name, when in ablation:
        lines.append(f"| {label} | {_um(fig(name, when, 'label_free_rmse_mm'))} | "
                     f"{_um(fig(name, when, 'depth_vs_truth_rmse_mm'))} | {_um(fig(name, when, 'vertex_rmse_mm'))} | "
                     f"{_um(fig(name, 'before', 'truth_label_free_rmse_mm'))} |")
    lines += [
        "",
        f"**Table 2b** ({'clean' if s.get('transfer', 'aug') == 'clean' else 'augmented'} model `{s[s.get('transfer', 'aug')]}`; "
        "before -> after adaptation)",
        "",
        "| source -> target | LF | ratio | D | V | ratio V | LF* |",
        "|---|---|---|---|---|---|---|",
    ]
    m = s.get("transfer", "aug")
    transfers = [
        ("Sim-Prim (held-out simulation, no adaptation)", f"sim-prim ({m})"),
        ("Sim-Prim -> Real-Prim (gelslim1)", f"{m}: sim -> gelslim1"),
        ("Sim-Prim -> Real-Prim-2 (gelslim2)", f"{m}: sim -> gelslim2"),
        ("Real-Prim -> Real-Prim-2", f"{m}: gelslim1 -> gelslim2"),
        ("Real-Prim -> Real-Novel (STL indenters, gelslim1)", f"{m}: gelslim1 -> gelslim1-novel"),
        ("Sim-Prim -> Real-Novel", f"{m}: sim -> gelslim1-novel"),
        ("Sim-Prim -> real ball presses (GelSight)", f"{m}: sim -> real-balls"),
    ]
    for label, name in transfers:
        b, a = rows[name]["before"], rows[name].get("after")

        def pair(key):
            if a is None:
                return _um(b.get(key))
            return f"{_um(b.get(key))} -> {_um(a.get(key))}" if b.get(key) is not None else "-"

        def ratio(key):
            if a is None or b.get(key) is None:
                return "-"
            return f"{b[key] / a[key]:.2f}x"

        lines.append(f"| {label} | {pair('label_free_rmse_mm')} | {ratio('label_free_rmse_mm')} | "
                     f"{pair('depth_vs_truth_rmse_mm')} | {pair('vertex_rmse_mm')} | {ratio('vertex_rmse_mm')} | "
                     f"{_um(b.get('truth_label_free_rmse_mm'))} |")
    secs = [r["adaptation"]["seconds"] for r in rows.values() if "adaptation" in r]
    lines += ["", f"Adaptation time per row: {min(secs):.0f}-{max(secs):.0f} s for {s['steps']} steps on this "
                  f"machine (shared, loaded); whole run {results['seconds'] / 60:.0f} min."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    from tactile_deploy.training.errors import run_command

    raise SystemExit(run_command(main))
