"""Command line: ``python -m training {train,export} ...``.

    python -m training train --config runs/small.json [--device cuda]
    torchrun --nproc_per_node 8 -m training train --config runs/big.json --device cuda
    python -m training export --run runs/small --out exported/gelslim_mesh.onnx [--variant fused-int8]
    python -m training report-coarsening --data DATA.npz [--png FIGURE.png]
    python -m training envelope-bank --out .device/bank_primitive.npz [--indenters primitive]
    python -m training heldout --run out/predictor/gpu_h100 [--n 512] [--seed 1007]
    python -m training evaluate --model exported/gelslim_mesh.onnx --out docs/results/evaluation.json [--n 256]
    python -m training experiments --config training/configs/experiments_h100.json --out out/experiments [--only latent,kl,scratch]
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_train = sub.add_parser("train", help="pre-train both VAEs, then the latent projection")
    p_train.add_argument("--config", required=True, help="TrainConfig JSON file")
    p_train.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N, auto)")
    p_export = sub.add_parser("export", help="export a trained run to ONNX with its model card")
    p_export.add_argument("--run", required=True, help="run folder holding model.pt and heldout.npz")
    p_export.add_argument("--out", default="exported/gelslim_mesh.onnx", help="ONNX file to write")
    p_export.add_argument("--variant", default=None, help="export variant (default: the shipped one)")
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
        from pathlib import Path

        from tactile_deploy.atomic import write_json
        from training.evaluation import DOMAINS, run_evaluation

        domains = tuple(args.domains.split(",")) if args.domains else DOMAINS
        report = run_evaluation(args.model, args.n, args.seed, domains, Path(args.shared))
        write_json(args.out, report)
        print(f"wrote {args.out}")
        return 0

    if args.command == "heldout":
        from pathlib import Path

        import numpy as np

        from tactile_deploy.atomic import write_npz
        from training.config import TrainConfig
        from training.data import fresh_contacts

        cfg = TrainConfig.load(Path(args.run) / "config.json")
        if cfg.data.synthetic is None:
            raise SystemExit(f"{args.run}: the run reads a dataset folder; its held-out split is already on disk")
        try:
            data = fresh_contacts(cfg.data.synthetic, args.n, args.seed)
        except ValueError as exc:
            raise SystemExit(f"--seed: {exc}") from None
        write_npz(Path(args.run) / "heldout.npz", depth_mm=data.depth_mm, displacement_mm=data.displacement_mm,
                  indenter=data.indenter, source=np.array(data.source))
        print(f"wrote {args.run}/heldout.npz: {len(data)} contacts ({data.source})")
        return 0

    if args.command == "experiments":
        from training.experiments import ExperimentConfig, run_experiments

        run_experiments(ExperimentConfig.load(args.config), args.out, tuple(args.only.split(",")))
        return 0

    if args.command == "envelope-bank":
        from tactile_deploy.fem.batched import EnvelopeBank
        from tactile_deploy.indenters import get_indenter, list_indenters

        names = list_indenters("primitive") if args.indenters == "primitive" else args.indenters.split(",")
        EnvelopeBank.from_indenters([get_indenter(n) for n in names]).save_npz(args.out)
        print(f"wrote {args.out}: {len(names)} indenters")
        return 0

    if args.command == "report-coarsening":
        import numpy as np

        from training.reports import coarsening_figure, coarsening_table, markdown_table, pick_contacts

        with np.load(args.data) as d:
            disp = d["displacement_mm"][: args.n]
        print(markdown_table(coarsening_table(disp)))
        if args.png:
            coarsening_figure([disp[k] for k in pick_contacts(disp)], args.png)
        return 0

    if args.command == "train":
        from training.config import TrainConfig
        from training.train import train

        cfg = TrainConfig.load(args.config)
        if args.device:
            cfg = cfg.model_copy(update={"device": args.device})
        train(cfg)
        return 0
    from training.export import export_run

    card = export_run(args.run, args.out, variant=args.variant)
    print(f"wrote {args.out}: parity {card['parity']['max_abs_diff_mm']:.2e} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
