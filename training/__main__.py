"""Command line: ``python -m tactile_deploy.training {train,export} ...``.

    python -m tactile_deploy.training train --config runs/small.json [--device cuda]
    torchrun --nproc_per_node 8 -m tactile_deploy.training train --config runs/big.json --device cuda
    python -m tactile_deploy.training export --run runs/small --out exported/gelslim_mesh.onnx [--variant fused-int8] [--overwrite]
    python -m tactile_deploy.training report-coarsening --data DATA.npz [--png FIGURE.png]
    python -m tactile_deploy.training ood-score [--onnx exported/gelslim_mesh.onnx] [--bundle exported/gelslim_mesh.pt]
    python -m tactile_deploy.training export-adapt --bundle MODEL.pt [--onnx exported/gelslim_mesh.onnx] [--out DIR]
    python -m tactile_deploy.training envelope-bank --out .device/bank_primitive.npz [--indenters primitive]
    python -m tactile_deploy.training heldout --run out/predictor/gpu_h100 [--n 512] [--seed 1007]
    python -m tactile_deploy.training evaluate --model exported/gelslim_mesh.onnx --out docs/results/evaluation.json [--n 256]
    python -m tactile_deploy.training experiments --config training/configs/experiments_h100.json --out out/experiments [--only latent,kl,scratch]

A mistake in a config, option or input file ends the command with one ``error: ...`` message and
exit status 2 (:mod:`tactile_deploy.training.errors`); nothing is written then.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tactile_deploy.training.errors import UsageError, run_command


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return run_command(lambda: _main(argv))


def _check_output_json(path: str, option: str) -> Path:
    """``path`` may be written as a JSON file (its folder exists, it is not a folder); an existing
    file is replaced (:func:`tactile_deploy.outputs.check_output_file`)."""
    from tactile_deploy.outputs import OutputPathError, check_output_file

    try:
        return check_output_file(path, option, overwrite=True, suffixes=(".json",))
    except OutputPathError as e:
        raise UsageError(str(e)) from None


def _card_of(card_path: Path, model: Path) -> dict:
    """The model card at ``card_path`` if it describes ``model`` (same sha256), else UsageError."""
    import hashlib
    import json

    if not card_path.is_file():
        raise UsageError(f"--card {card_path}: no such file; give the model card written by python -m tactile_deploy.training export")
    card = json.loads(card_path.read_text())
    sha = hashlib.sha256(model.read_bytes()).hexdigest()
    if card.get("files", {}).get("onnx_sha256") != sha:
        raise UsageError(f"--card {card_path} describes another graph than {model} (sha256 differs): give the card "
                         "exported with the first --model")
    return card


def _run_folder(path: str, option: str = "--run") -> Path:
    run = Path(path)
    if not run.is_dir():
        raise UsageError(f"{option} {run}: no such folder; give the run_dir of a training run")
    if not (run / "config.json").is_file():
        raise UsageError(f"{option} {run} holds no config.json: not a training run folder (python -m tactile_deploy.training train "
                         "--config CONFIG.json makes one)")
    return run


def _main(argv: list[str]) -> int:
    if argv[:1] == ["export-adapt"]:
        from tactile_deploy.training.adaptation.export import main as export_adapt

        return export_adapt(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m tactile_deploy.training", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_train = sub.add_parser("train", help="pre-train both VAEs, then the latent projection")
    p_train.add_argument("--config", required=True, help="TrainConfig JSON file")
    p_train.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N, auto)")
    p_train.add_argument("--run-dir", help="override the config's run_dir")
    p_train.add_argument("--time-budget", action="append", default=[], metavar="STAGE=SECONDS",
                         help="override a stage's time_budget_s (repeatable), e.g. surface=120")
    p_export = sub.add_parser("export", help="export a trained run to ONNX with its model card")
    p_export.add_argument("--run", required=True, help="run folder holding model.pt and heldout.npz")
    p_export.add_argument(
        "--out", default="exported/gelslim_mesh.onnx",
        help="ONNX file to write, relative to the current folder (default: %(default)s); its model card "
        "<stem>.json and <stem>.md and, for int8 variants, the fp32 graph <stem>_fp32.onnx go beside it",
    )
    p_export.add_argument("--variant", default=None,
                          help="export variant (default: the shipped one, hybrid-int8-fastood, which needs the surface "
                               "decoder; a run with the latent decoders only: e.g. lean-int8-fastood; docs/predictor.md)")
    p_export.add_argument("--overwrite", action="store_true", help="replace an existing --out and its files")
    p_export.add_argument("--bundle", default=None,
                          help="weights to export (default: RUN/model.pt; e.g. its slim bundle exported/gelslim_mesh.pt)")
    sub.add_parser("export-adapt", help="export the adaptation step of a bundle (--help for its options)")
    p_rep = sub.add_parser("report-coarsening", help="reconstruction errors of the coarsening hierarchy")
    p_rep.add_argument("--data", required=True, help="npz with displacement_mm (S, n, 3): e.g. a run's heldout.npz")
    p_rep.add_argument("--png", help="also draw one contact projected down and up")
    p_rep.add_argument("--n", type=int, default=200, help="contacts used")
    p_slim = sub.add_parser("slim-bundle", help="a training bundle with the trained modules' weights only (float16 by "
                            "default), for committing; export from it")
    p_slim.add_argument("--bundle", required=True, help="model.pt of a training run")
    p_slim.add_argument("--out", required=True, help="bundle to write (e.g. exported/gelslim_mesh.pt)")
    p_slim.add_argument("--dtype", default="float16", choices=["float16", "float32"])
    p_bank = sub.add_parser(
        "envelope-bank",
        help="write the indenters' envelope grids to an .npz (data.synthetic.envelope_bank, for machines without trimesh)",
    )
    p_bank.add_argument("--out", required=True, help=".npz file to write")
    p_bank.add_argument("--indenters", default="primitive", help="'primitive' or comma-separated names")
    p_exp = sub.add_parser("experiments", help="latent sizes, KL weights, pre-training vs scratch (training/experiments.py)")
    p_exp.add_argument("--config", required=True, help="ExperimentConfig JSON file")
    p_exp.add_argument("--out", required=True, help="folder for experiments.json and scratch checkpoints")
    p_exp.add_argument("--only", default="latent,kl,scratch", help="comma-separated groups: latent, kl, scratch")
    p_ood = sub.add_parser(
        "ood-score", help="replace an exported graph's ood_score (and its fp32 twin's) by the size-normalised score "
        "(training/ood_score.py), with its threshold in the metadata and the model card")
    p_ood.add_argument("--onnx", default="exported/gelslim_mesh.onnx", help="the exported *-fastood graph")
    p_ood.add_argument("--bundle", default="exported/gelslim_mesh.pt", help="its training bundle (the generator)")
    p_held = sub.add_parser(
        "heldout", help="simulate fresh held-out contacts of a run's training distribution into RUN/heldout.npz (CPU)"
    )
    p_held.add_argument("--run", required=True, help="run folder holding config.json")
    p_held.add_argument("--n", type=int, default=512, help="contacts")
    p_held.add_argument("--seed", type=int, default=1007, help="generator seed (not the training seed)")
    p_eval = sub.add_parser("evaluate", help="models against the physics lift, domain by domain (training/evaluation.py)")
    p_eval.add_argument("--model", action="append", default=None,
                        help="ONNX model, or LABEL=PATH; repeat to compare models (default: exported/gelslim_mesh.onnx)")
    p_eval.add_argument("--out", required=True, help="JSON report to write")
    p_eval.add_argument("--n", type=int, default=256, help="contacts per domain (large_strain: n / 8)")
    p_eval.add_argument("--seed", type=int, default=2024)
    p_eval.add_argument("--domains", default=None, help="comma-separated subset of the domains")
    p_eval.add_argument("--shared", default="../shared/data/indenters", help="folder of the shared STL indenters")
    p_eval.add_argument("--gel", choices=("linear", "neo-hookean"), default="linear",
                        help="gel law of the frictionless domains' truth (primitives, noisy, unseen_shapes; "
                             "large_strain is neo-Hookean under either; the friction domains need linear)")
    p_eval.add_argument("--card", default=None,
                        help="model card (<model>.json) of the first --model: its 'evaluation' section and markdown "
                             "are rewritten with this report's table (the card must describe that very file)")
    args = parser.parse_args(argv)

    if args.command == "evaluate":
        from tactile_deploy.atomic import write_json
        from tactile_deploy.training.evaluation import ALL_DOMAINS, DOMAINS, EvaluationReport, run_evaluation

        domains = tuple(args.domains.split(",")) if args.domains else DOMAINS
        unknown = [d for d in domains if d not in ALL_DOMAINS]
        if unknown:
            raise UsageError(f"--domains: unknown {', '.join(map(repr, unknown))}; choose among {', '.join(ALL_DOMAINS)}")
        if args.n < 1:
            raise UsageError(f"--n must be >= 1 (contacts per domain), got {args.n}")
        if any(d.startswith("unseen_shapes") for d in domains) and not Path(args.shared).is_dir():
            raise UsageError(f"--shared {args.shared}: no such folder (the unseen_shapes domain reads its STL indenters "
                             "there); give the folder, or leave unseen_shapes out of --domains")
        out = _check_output_json(args.out, "--out")
        models = {}
        for spec in args.model or ["exported/gelslim_mesh.onnx"]:
            label, sep, path = spec.partition("=") if "=" in spec and not Path(spec).is_file() else ("", "", spec)
            model = Path(path)
            label = label or (model.stem if args.model and len(args.model) > 1 else "model")
            if not model.is_file():
                raise UsageError(f"--model {model}: no such file; give an exported ONNX model (python -m tactile_deploy.training export)")
            if label in models:
                raise UsageError(f"--model {spec}: the label {label!r} is given twice; name them LABEL=PATH")
            from tactile_deploy.runtime.predictor import MeshPredictor, ModelContractError

            try:
                MeshPredictor(model, warmup=0)
            except ModelContractError as e:
                raise UsageError(f"--model {model}: {e}") from None
            models[label] = model
        from tactile_deploy.training.evaluation import markdown_table

        card_path = Path(args.card) if args.card else None
        if card_path is not None:
            card = _card_of(card_path, next(iter(models.values())))
        report = run_evaluation(models, args.n, args.seed, domains, Path(args.shared), gel=args.gel)
        EvaluationReport.model_validate(report)  # the committed format (training/evaluation_report.schema.json)
        write_json(out, report)
        print(markdown_table(report))
        print(f"wrote {out}")
        if card_path is not None:
            from tactile_deploy.training.card import write_card

            label = next(iter(models))
            card["evaluation"] = {
                "command": "python -m tactile_deploy.training evaluate " + " ".join(map(str, argv[1:])),
                "seed": args.seed, "report": str(out), "table": markdown_table(report, label)}
            write_card(card, card_path, card_path.with_suffix(".md"))
            print(f"wrote the evaluation into {card_path} and {card_path.with_suffix('.md')}")
        return 0

    if args.command == "slim-bundle":
        from tactile_deploy.training.train import slim_bundle

        if Path(args.out).resolve() == Path(args.bundle).resolve():
            raise UsageError(f"--out {args.out} is the --bundle itself: write the slim bundle elsewhere")
        info = slim_bundle(args.bundle, args.out, args.dtype)
        print(f"wrote {args.out}: {info['tensors']} tensors, {info['numbers']:,} numbers ({info['dtype']}), "
              f"{info['bytes'] / 2**20:.1f} MiB")
        return 0

    if args.command == "ood-score":
        from tactile_deploy.training.ood_score import apply_to_export

        for option, f in (("--onnx", args.onnx), ("--bundle", args.bundle)):
            if not Path(f).is_file():
                raise UsageError(f"{option} {f}: no such file")
        try:
            out = apply_to_export(Path(args.onnx), Path(args.bundle))
        except ValueError as e:
            raise UsageError(str(e)) from None
        print(json.dumps(out, indent=2))
        return 0

    if args.command == "heldout":
        import numpy as np

        from tactile_deploy.atomic import write_npz
        from tactile_deploy.training.config import TrainConfig
        from tactile_deploy.training.data import fresh_contacts

        run = _run_folder(args.run)
        cfg = TrainConfig.load(run / "config.json")
        if cfg.data.synthetic is None:
            raise UsageError(f"--run {run}: the run reads a dataset folder; its held-out split is already on disk")
        if args.n < 1:
            raise UsageError(f"--n must be >= 1 (contacts), got {args.n}")
        if args.seed == cfg.data.synthetic.seed or args.seed < 0:
            raise UsageError(f"--seed {args.seed}: choose a seed >= 0 other than the training seed "
                             f"{cfg.data.synthetic.seed}, so that no contact is shared")
        data = fresh_contacts(cfg.data.synthetic, args.n, args.seed)
        write_npz(run / "heldout.npz", depth_mm=data.depth_mm, displacement_mm=data.displacement_mm,
                  indenter=data.indenter, source=np.array(data.source), seed=np.array(args.seed),
                  contact_mask=data.contact_mask)
        print(f"wrote {args.run}/heldout.npz: {len(data)} contacts ({data.source})")
        return 0

    if args.command == "experiments":
        from tactile_deploy.training.experiments import ExperimentConfig, run_experiments

        run_experiments(ExperimentConfig.load(args.config), args.out, tuple(args.only.split(",")))
        return 0

    if args.command == "envelope-bank":
        from tactile_deploy.training.simulation.batched import EnvelopeBank
        from tactile_deploy.indenters import get_indenter, list_indenters

        names = list_indenters("primitive") if args.indenters == "primitive" else args.indenters.split(",")
        EnvelopeBank.from_indenters([get_indenter(n) for n in names]).save_npz(args.out)
        print(f"wrote {args.out}: {len(names)} indenters")
        return 0

    if args.command == "report-coarsening":
        import numpy as np

        from tactile_deploy.training.reports import coarsening_figure, coarsening_table, markdown_table, pick_contacts

        with np.load(args.data) as d:
            disp = d["displacement_mm"][: args.n]
        print(markdown_table(coarsening_table(disp)))
        if args.png:
            coarsening_figure([disp[k] for k in pick_contacts(disp)], args.png)
        return 0

    if args.command == "train":
        from tactile_deploy.training.config import TrainConfig, check_device
        from tactile_deploy.training.train import STAGES

        cfg = TrainConfig.load(args.config)
        if args.device:
            try:
                check_device(args.device)
            except ValueError as e:
                raise UsageError(f"--device: {e}") from None
            cfg = cfg.model_copy(update={"device": args.device})
        if args.run_dir:
            cfg = cfg.model_copy(update={"run_dir": args.run_dir})
        for item in args.time_budget:
            stage, _, value = item.partition("=")
            current = getattr(cfg, stage, None) if stage in STAGES else None
            try:
                seconds = float(value)
            except ValueError:
                seconds = -1.0
            if current is None or not seconds > 0:
                raise UsageError(f"--time-budget {item}: expected STAGE=SECONDS with a stage of the config "
                                 f"({', '.join(s for s in STAGES if getattr(cfg, s, None) is not None)}) and seconds > 0")
            cfg = cfg.model_copy(update={stage: current.model_copy(update={"time_budget_s": seconds})})
        from tactile_deploy.training.train import train

        try:
            train(cfg)
        except UsageError as e:  # the config's settings: name the file
            raise UsageError(f"{args.config}: {e}") from None
        except KeyboardInterrupt:
            print("interrupted; rerun the same command to resume", file=sys.stderr)
            return 130
        return 0
    from tactile_deploy.training.export import SHIPPED_VARIANT, check_export, export_run

    variant = args.variant or SHIPPED_VARIANT
    out = Path(args.out)
    check_export(args.run, out, variant, args.overwrite)
    if args.bundle is not None and not Path(args.bundle).is_file():
        raise UsageError(f"--bundle {args.bundle}: no such file; give a training bundle (model.pt or its slim bundle)")
    card = export_run(args.run, out, variant=variant, overwrite=args.overwrite, bundle_path=args.bundle)
    par = card["parity"]
    files = [out, *([out.with_name(par["graph"])] if par["graph"] != out.name else []),
             out.with_suffix(".json"), out.with_suffix(".md")]
    print(f"wrote {', '.join(map(str, files))} (variant {variant})")
    which = "the fp32 graph" if par["graph"] != out.name else "the shipped fp32 graph"
    print(f"parity of {which} {par['graph']} vs torch on {par['n_inputs']} held-out maps: max |difference| "
          f"{par['max_abs_diff_mm']:.2e} mm, ood_score {par['ood_max_abs_diff_mm']:.2e} mm")
    if "shipped_vs_fp32_max_abs_diff_mm" in par:
        print(f"shipped int8 graph {out.name} vs {par['graph']}: max |difference| "
              f"{par['shipped_vs_fp32_max_abs_diff_mm']:.2e} mm, RMS {par['shipped_vs_fp32_rms_diff_mm']:.2e} mm, "
              f"ood_score {par['shipped_vs_fp32_ood_max_abs_diff_mm']:.2e} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
