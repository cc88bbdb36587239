"""Adaptation targets against the FEM truth of a virtual sensor.

    python bench/bench_adapt_truth.py [--domain gelslim1] [--n 200] [--n-adapt 140] [--steps 200]

The shipped graph and its committed adaptation step (``exported/gelslim_mesh_adapt``), adapted
through the runtime's own code (:mod:`tactile_deploy.adapt.step`, as ``tactile-deploy adapt``) on
the first ``--n-adapt`` presses of a virtual-sensor domain
(:mod:`tactile_deploy.training.adaptation.domains`: its RGB frames through its plugin, with the
sensor's FEM mesh as truth), once towards the measured map I and once towards the image VAE's
reconstruction VAE(I), each from the family model; measured on the other presses. Figures:
per-node Euclidean error (um) against the FEM mesh, RMS over the sensing nodes pressed more than
50 um and over every node; beside them, the depth maps' own error against the true depth over the
contact and the shipped graph's error from the true maps (how much is the read-out). Complements ``bench/bench_predictor_real.py`` (real presses, the ball
as reference, no mesh truth). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PRESSED_MM = 0.05


def main(argv=None) -> int:
    from tactile_deploy.adapt.step import AdaptSettings, StepProgram, adapt, adaptation_target
    from tactile_deploy.adapt.weights import write_adapted_onnx
    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.pad.asset import load_pad
    from tactile_deploy.training.adaptation.domains import load_or_make

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--domain", default="gelslim1", help="a virtual domain of training/adaptation/domains.py")
    ap.add_argument("--n", type=int, default=200, help="presses in all")
    ap.add_argument("--n-adapt", type=int, default=140, help="presses adapted on; the rest are measured")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--onnx", default=str(ROOT / "exported" / "gelslim_mesh.onnx"))
    ap.add_argument("--step", default=str(ROOT / "exported" / "gelslim_mesh_adapt"))
    args = ap.parse_args(argv)
    if not 0 < args.n_adapt < args.n:
        ap.error(f"--n-adapt must be between 1 and --n - 1 ({args.n - 1}), got {args.n_adapt}")

    domain = load_or_make(args.domain, args.n, 0, ROOT / "out" / "adapt")
    if domain.vertices_mm is None:
        ap.error(f"domain {args.domain!r} has no mesh truth: choose a virtual-sensor domain")
    pad = load_pad()
    m = pad.n_plane
    depth = domain.depth_mm.astype(np.float32)
    ev = slice(args.n_adapt, None)
    true = domain.vertices_mm[ev] - pad.vertices  # (K, n, 3) mm
    pressed = true[:, :m, 2] < -PRESSED_MM

    def errors(onnx_path, maps=depth[ev]) -> tuple[float, float]:
        pred = make_session(onnx_path, providers="cpu").run(["vertices"], {"depth": maps[:, None]})[0]
        e = np.linalg.norm(pred - pad.vertices - true, axis=-1)
        return 1e3 * float(np.sqrt((e[:, :m][pressed] ** 2).mean())), 1e3 * float(np.sqrt((e**2).mean()))

    step = StepProgram.load(args.step)
    rows = {"shipped graph": errors(args.onnx)}
    # how much of it is the depth map: the read-out's error over the contact, and the graph on the true maps
    true_maps = domain.true_depth_mm[ev].astype(np.float32)
    contact = (true_maps > PRESSED_MM) & (domain.weight > 0.5)
    readout_um = 1e3 * float(np.sqrt(((depth[ev] - true_maps)[contact] ** 2).mean()))
    on_true = errors(args.onnx, true_maps)
    family = step.weights()
    settings = AdaptSettings(steps=args.steps, batch_size=16, lr=args.lr)
    with tempfile.TemporaryDirectory() as work:
        for name, use_filter in (("adapted towards I (fp32)", False), ("adapted towards VAE(I) (fp32)", True)):
            step.load_weights(family)  # each adaptation starts from the family model
            target, _ = adaptation_target(step, depth, use_filter)
            adapt(step, depth[: args.n_adapt], target[: args.n_adapt], domain.weight, settings)
            path = write_adapted_onnx(step.card, step.card.path(step.folder, "fp32_model"), step.weights(),
                                      Path(work) / "adapted.onnx", {"adapted": "true"})
            rows[name] = errors(path)
    print(f"Domain {args.domain}: {args.n_adapt} presses adapted on, {args.n - args.n_adapt} measured "
          f"({pressed.sum(1).mean():.1f} sensing nodes pressed > {PRESSED_MM * 1e3:.0f} um per press); {args.steps} "
          f"Adam steps, lr {args.lr:g}, batch 16. Error against the FEM mesh, um.\n")
    print("| mesh | pressed sensing nodes um | all nodes um |\n|---|---|---|")
    for name, (p, a) in rows.items():
        print(f"| {name} | {p:.1f} | {a:.1f} |")
    print(f"\nThe depth maps themselves: {readout_um:.1f} um RMS off the true depth over the contact pixels (true depth "
          f"> {PRESSED_MM * 1e3:.0f} um); the shipped graph on the true depth maps: {on_true[0]:.1f} um on the pressed "
          f"sensing nodes, {on_true[1]:.1f} um over all nodes.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
