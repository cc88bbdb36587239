"""Command line: ``python -m tactile_deploy.training {train,export} ...``.

    python -m tactile_deploy.training train --config runs/small.json [--device cuda]
    torchrun --nproc_per_node 8 -m tactile_deploy.training train --config runs/big.json --device cuda
    python -m tactile_deploy.training export --run runs/small --out exported/gelslim_mesh.onnx [--variant fused-int8] [--overwrite]
    python -m tactile_deploy.training report-coarsening --data DATA.npz [--png FIGURE.png]
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
    p_export = sub.add_parser("export", help="export a trained run to ONNX with its model card")
    p_export.add_argument("--run", required=True, help="run folder holding model.pt and heldout.npz")
    p_export.add_argument(
        "--out", default="exported/gelslim_mesh.onnx",
        help="ONNX file to write, relative to the current folder (default: %(default)s); its model card "
        "<stem>.json and <stem>.md and, for int8 variants, the fp32 graph <stem>_fp32.onnx go beside it",
    )
    p_export.add_argument("--variant", default=None,
                          help="export variant (default: the shipped one, lean-int8-fastood; see docs/predictor.md)")
    p_export.add_argument("--overwrite", action="store_true", help="replace an existing --out and its files")
    sub.add_parser("export-adapt", help="export the adaptation step of a bundle (--help for its options)")
    p_rep = sub.add_parser("report-coarsening", help="reconstruction errors of the coarsening hierarchy")
    p_rep.add_argument("--data", required=True, help="npz with displacement_mm (S, n, 3): e.g. a run's heldout.npz")
    p_rep.add_argument("--png", help="also draw one contact projected down and up")
    p_rep.add_argument("--n", type=int, default=200, help="contacts used")
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
    p_held = sub.add_parser(
        "heldout", help="simulate fresh held-out contacts of a run's training distribution into RUN/heldout.npz (CPU)"
    )
    p_held.add_argument("--run", required=True, help="run folder holding config.json")
    p_held.add_argument("--n", type=int, default=512, help="contacts")
    p_held.add_argument("--seed", type=int, default=1007, help="generator seed (not the training seed)")
    p_eval = sub.add_parser("evaluate", help="the model against the physics baseline on five domains (training/evaluation.py)")
    p_eval.add_argument("--model", default="exported/gelslim_mesh.onnx", help="ONNX model")
    p_eval.add_argument("--out", required=True, help="JSON report to write")
    p_eval.add_argument("--n", type=int, default=256, help="contacts per domain (large_strain: n / 8)")
    p_eval.add_argument("--seed", type=int, default=2024)
    p_eval.add_argument("--domains", default=None, help="comma-separated subset of the domains")
    p_eval.add_argument("--shared", default="../shared/data/indenters", help="folder of the shared STL indenters")
    args = parser.parse_args(argv)

    if args.command == "evaluate":
        from tactile_deploy.atomic import write_json
        from tactile_deploy.training.evaluation import DOMAINS, run_evaluation

        domains = tuple(args.domains.split(",")) if args.domains else DOMAINS
        unknown = [d for d in domains if d not in DOMAINS]
        if unknown:
            raise UsageError(f"--domains: unknown {', '.join(map(repr, unknown))}; choose among {', '.join(DOMAINS)}")
        if args.n < 1:
            raise UsageError(f"--n must be >= 1 (contacts per domain), got {args.n}")
        if "shared_stl" in domains and not Path(args.shared).is_dir():
            raise UsageError(f"--shared {args.shared}: no such folder (the shared_stl domain reads its STL indenters "
                             "there); give the folder, or leave shared_stl out of --domains")
        out = _check_output_json(args.out, "--out")
        model = Path(args.model)
        if not model.is_file():
            raise UsageError(f"--model {model}: no such file; give an exported ONNX model (python -m tactile_deploy.training export)")
        from tactile_deploy.runtime.predictor import MeshPredictor, ModelContractError

        try:
            MeshPredictor(model, warmup=0)
        except ModelContractError as e:
            raise UsageError(f"--model {model}: {e}") from None
        report = run_evaluation(model, args.n, args.seed, domains, Path(args.shared))
        write_json(out, report)
        print(f"wrote {out}")
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
                  indenter=data.indenter, source=np.array(data.source), seed=np.array(args.seed))
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

        cfg = TrainConfig.load(args.config)
        if args.device:
            try:
                check_device(args.device)
            except ValueError as e:
                raise UsageError(f"--device: {e}") from None
            cfg = cfg.model_copy(update={"device": args.device})
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
    card = export_run(args.run, out, variant=variant, overwrite=args.overwrite)
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
