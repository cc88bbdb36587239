"""Command line: ``python -m training {train,export} ...``.

    python -m training train --config runs/small.json [--device cuda]
    torchrun --nproc_per_node 8 -m training train --config runs/big.json --device cuda
    python -m training export --run runs/small --out exported/gelslim_mesh.onnx [--variant fused-int8]
    python -m training report-coarsening --data DATA.npz [--png FIGURE.png]
    python -m training export-adapt --bundle MODEL.pt [--onnx exported/gelslim_mesh.onnx] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["export-adapt"]:
        from training.adaptation.export import main as export_adapt

        return export_adapt(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m training", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_train = sub.add_parser("train", help="pre-train both VAEs, then the latent projection")
    p_train.add_argument("--config", required=True, help="TrainConfig JSON file")
    p_train.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N, auto)")
    p_export = sub.add_parser("export", help="export a trained run to ONNX with its model card")
    p_export.add_argument("--run", required=True, help="run folder holding model.pt and heldout.npz")
    p_export.add_argument("--out", default="exported/gelslim_mesh.onnx", help="ONNX file to write")
    p_export.add_argument("--variant", default=None, help="export variant (default: the shipped one)")
    sub.add_parser("export-adapt", help="export the adaptation step of a bundle (--help for its options)")
    p_rep = sub.add_parser("report-coarsening", help="reconstruction errors of the coarsening hierarchy")
    p_rep.add_argument("--data", required=True, help="npz with displacement_mm (S, n, 3): e.g. a run's heldout.npz")
    p_rep.add_argument("--png", help="also draw one contact projected down and up")
    p_rep.add_argument("--n", type=int, default=200, help="contacts used")
    args = parser.parse_args(argv)

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
