"""The predicted mesh against a real ball, before and after self-supervised adaptation.

    python bench/bench_predictor_real.py [--onnx exported/gelslim_mesh.onnx]
        [--step exported/gelslim_mesh_adapt] [--steps 200] [--lr 1e-4] [--json out.json] [--no-write]

The 42 real GelSight ball presses of ``../shared/data/real/fots_gelsight_ballpress`` (a steel ball
of radius 2.35 mm; each frame's contact circle labelled by hand) through a plugin calibrated on
them (:func:`tactile_deploy.calibration.shading.real_gelsight.real_gelsight_plugin`: shading model, Poisson
integration, the image centred on the sensor origin at 0.05107 mm per pixel). The reference is
independent of any model: inside the labelled contact circle (radius a) the gel surface lies on
the ball, ``z(r) = z0 - (sqrt(R^2 - r^2) - sqrt(R^2 - a^2))`` with r the distance from the circle's
centre; the ball's height z0 (how far the contact rim itself sank) is not labelled, so it is fitted
per press (least squares) and the figures are of the shape:

* **ball surface RMSE** (um): the predicted sensing nodes whose deformed (x, y) lie inside the
  contact circle, RMS of z_pred - z(r) after the fitted z0, over the presses measured;
* **cap depth error** (%): the predicted depth of the contact centre below the contact rim
  (interpolated from the sensing nodes) against the ball's cap ``R - sqrt(R^2 - a^2)``, mean of
  the signed and of the absolute per-press errors.

Adaptation as ``tactile-deploy adapt`` does it (the committed step, Adam on the label-free loss
towards the design's target over the camera's view: the measured map I for the surface-anchored
graphs, the image VAE's reconstruction VAE(I) for the latent design) on the first 30 presses, and
once more towards the other target, each from the family model; the figures are of the other 12,
for the shipped model before and after, and for the physics lift of the same depth maps
(:mod:`tactile_deploy.training.evaluation`) beside them. Writes the ``predictor-real``
section of BENCHMARKS.md unless ``--no-write``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

N_ADAPT = 30


def ball_errors(vertices_mm, rest_mm, n_plane: int, centres_mm, a_mm, radius_mm: float) -> dict:
    """Shape errors of predicted meshes (N, n, 3) mm against balls with contact circles of centres
    (N, 2) mm and radii (N,) mm (module docstring)."""
    import numpy as np
    from scipy.interpolate import griddata

    sq, caps = [], []
    for v, c, a in zip(vertices_mm, centres_mm, a_mm):
        top = v[:n_plane]
        r = np.hypot(top[:, 0] - c[0], top[:, 1] - c[1])
        inside = r < a
        if inside.sum() < 3:
            continue
        shape = -(np.sqrt(radius_mm**2 - np.minimum(r[inside], radius_mm) ** 2) - np.sqrt(radius_mm**2 - a**2))
        z0 = float(np.mean(top[inside, 2] - shape))  # the ball's fitted height (its rim's sink)
        sq.append((top[inside, 2] - z0 - shape) ** 2)
        ring = c + a * np.stack([np.cos(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
                                 np.sin(np.linspace(0, 2 * np.pi, 24, endpoint=False))], 1)
        z = griddata(top[:, :2], top[:, 2], np.vstack([c[None], ring]), method="linear")
        cap_pred = float(np.nanmean(z[1:]) - z[0])
        cap_true = radius_mm - np.sqrt(radius_mm**2 - a**2)
        caps.append((cap_pred - cap_true) / cap_true * 100.0)
    sq = np.concatenate(sq)
    caps = np.asarray(caps)
    return {"ball_surface_rmse_um": float(np.sqrt(sq.mean()) * 1e3), "nodes": int(len(sq)),
            "cap_depth_error_pct": {"mean": float(caps.mean()), "mean_abs": float(np.abs(caps).mean())},
            "presses": int(len(caps))}


def main(argv=None) -> int:
    import numpy as np

    from tactile_deploy.calibration.shading.real_gelsight import REAL_BALL_RADIUS_MM, REAL_MM_PER_PX, real_gelsight_plugin
    from tactile_deploy.adapt.step import AdaptSettings, StepProgram, adapt, adaptation_target, evaluate
    from tactile_deploy.adapt.weights import write_adapted_onnx
    from tactile_deploy.adapt.workflow import view_weight
    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.pad.asset import load_pad
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.training.evaluation import physics_lift

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--onnx", default=str(ROOT / "exported" / "gelslim_mesh.onnx"), help="the family model")
    ap.add_argument("--step", default=str(ROOT / "exported" / "gelslim_mesh_adapt"), help="its adaptation step")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--json", help="also write the results to this JSON file")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="bench_predictor_real_"))
    plugin, presses = real_gelsight_plugin(work / "fots-gelsight")
    pipe = ImagingPipeline.from_plugin(plugin)
    depth = np.stack([pipe.frame_to_depth(f) for f in presses.frames]).astype(np.float32)
    h, w = presses.shape
    s = REAL_MM_PER_PX
    circles = np.asarray(presses.circles, np.float64)  # (column, row, radius) px
    centres = np.stack([s * (circles[:, 0] - (w - 1) / 2), -s * (circles[:, 1] - (h - 1) / 2)], 1)
    a = circles[:, 2] * s
    pad = load_pad()
    weight = view_weight(plugin)
    step = StepProgram.load(args.step)
    target, filtered = adaptation_target(step, depth)  # the design's own target, as `tactile-deploy adapt`
    other, _ = adaptation_target(step, depth, not filtered)
    ev = slice(N_ADAPT, None)

    def mesh_of(onnx_path):
        session = make_session(onnx_path, providers="cpu")
        return session.run(["vertices"], {"depth": depth[:, None]})[0]

    rows = {}
    before = mesh_of(args.onnx)
    rows["shipped model"] = ball_errors(before[ev], pad.vertices, pad.n_plane, centres[ev], a[ev], REAL_BALL_RADIUS_MM)
    rows["shipped model"]["label_free_rmse_um"] = evaluate(step, depth[ev], target[ev], weight).rmse_mm * 1e3
    settings = AdaptSettings(steps=args.steps, batch_size=16, lr=args.lr)
    family = step.weights()
    name_of = {True: "towards VAE(I)", False: "towards I"}
    for name, tgt in (("adapted (fp32)", target), (f"adapted {name_of[not filtered]} (fp32)", other)):
        step.load_weights(family)  # each adaptation starts from the family model
        hist = adapt(step, depth[:N_ADAPT], tgt[:N_ADAPT], weight, settings)
        if name == "adapted (fp32)":
            loss = (hist.loss_mm2[0], hist.loss_mm2[-1])
        adapted_path = write_adapted_onnx(step.card, step.card.path(step.folder, "fp32_model"), step.weights(),
                                          work / "adapted.onnx", {"adapted": "true"})
        after = mesh_of(adapted_path)
        rows[name] = ball_errors(after[ev], pad.vertices, pad.n_plane, centres[ev], a[ev], REAL_BALL_RADIUS_MM)
        rows[name]["label_free_rmse_um"] = evaluate(step, depth[ev], tgt[ev], weight).rmse_mm * 1e3
    lift = physics_lift(depth[ev]) + pad.vertices
    rows["physics lift"] = ball_errors(lift, pad.vertices, pad.n_plane, centres[ev], a[ev], REAL_BALL_RADIUS_MM)

    lines = [
        f"The 42 real GelSight ball presses (`../shared/data/real`, ball radius {REAL_BALL_RADIUS_MM} mm, contact "
        f"circles labelled by hand) through a plugin calibrated on them; adaptation ({args.steps} Adam steps, lr "
        f"{args.lr:g}, batch 16, the committed step) on {N_ADAPT} presses, figures on the other "
        f"{len(depth) - N_ADAPT}. Ball surface: RMS of the predicted sensing nodes inside the contact circle "
        "against the ball (its height fitted per press), um; cap depth: the contact centre's depth below the rim "
        "against the ball's cap, % (signed mean / mean of |.|); label-free: the adaptation's loss (rendered mesh vs "
        f"its target), um. `adapted (fp32)`: as `tactile-deploy adapt` does it, {name_of[filtered]} (the target of "
        f"this design; the label-free figure of the shipped model is against it too); the other row {name_of[not filtered]}.",
        "",
        "| mesh | ball surface RMSE um | cap depth error % | label-free RMSE um |",
        "|---|---|---|---|",
    ]
    for name, r in rows.items():
        c = r["cap_depth_error_pct"]
        lf = r.get("label_free_rmse_um")
        lines.append(f"| {name} | {r['ball_surface_rmse_um']:.1f} | {c['mean']:+.1f} / {c['mean_abs']:.1f} | "
                     + (f"{lf:.1f}" if lf is not None else "-") + " |")
    lines += ["", f"Adaptation loss ({name_of[filtered]}) {loss[0] * 1e6:.0f} -> {loss[1] * 1e6:.0f} um^2; whole run "
              f"{time.perf_counter() - t0:.0f} s."]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        from bench.report import machine_line, write_section

        write_section("predictor-real", "## The predicted mesh against a real ball (`bench/bench_predictor_real.py`)"
                      f"\n\n{machine_line()}; model {Path(args.onnx).name}.\n\n" + text)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
