"""On-device adaptation speed: steps per second of the exported step, and adapting a plugin on
200 frames end to end.

    python bench/bench_adapt.py [--plugin gelslim2] [--device cpu|cuda] [--frames 200] [--steps 200]
                                [--threads N] [--small] [--no-write]      (or: tactile-deploy bench adapt)

Measures, in one run:

* **step**: one Adam step (forward + loss + backward + update) of the exported program
  (``exported/gelslim_mesh_adapt/step.pt2``, loaded as the runtime loads it) at batch 16, median
  over repeated steps, as steps/s and maps/s; against the same step of the eager torch module
  rebuilt from the training code and bundle when ``--bundle`` is given (ratio = overhead of the
  exported program), and the renderer's share of the step;
* **renderer**: the step's fixed-shape differentiable renderer (the training module the program
  was captured from) against the batched rasteriser
  of the simulator (:class:`tactile_deploy.training.simulation.depth_torch.TorchDepthCamera`, no gradient,
  variable shapes), forward at batch 16;
* **200 frames**: ``tactile-deploy adapt`` on a copy of the plugin fed ``--frames`` frames of its
  virtual sensor (frames rendered beforehand, not timed): imaging, filter, held-out split,
  ``--steps`` steps, evaluation, adapted ONNX (int8 like the family model), version written;
  wall time against the target of 2 minutes on a 2-core CPU.

Results go to BENCHMARKS.md (section ``adapt``) unless ``--no-write``, with the CUDA results
committed as ``bench/results/adapt_cuda_*.json`` (made on a GPU machine by
``bench/bench_adapt_device.py``, which needs only torch, numpy, onnx, onnxruntime and pydantic);
a run of this script with ``--device cuda`` writes its own section (``adapt-cuda``).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TARGET_200_FRAMES_S = 120.0


def _sync(device):
    import torch

    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def time_steps(program, depth, target, weight, n: int, device) -> list[float]:
    """Seconds per Adam step (forward + backward + update), batch = len(depth)."""
    import torch

    opt = torch.optim.Adam(program.trainable(), lr=1e-5)
    times = []
    for _ in range(n):
        _sync(device)
        t0 = time.perf_counter()
        loss = program(depth, target, weight)[0]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return times


def median_time(fn, n: int, device) -> float:
    out = []
    for _ in range(n):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def virtual_frames(sensor: str, n: int, seed: int = 7) -> list[np.ndarray]:
    """``n`` camera frames of the virtual sensor pressing primitive indenters in its view."""
    from tactile_deploy.indenters import ContactPose, list_indenters
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.sensors import load_sensor

    s = load_sensor(sensor)
    s.prepare()
    g = SensorPlugin.load(sensor).manifest.camera.grid
    rng = np.random.default_rng(seed)
    names = list_indenters("primitive")
    frames = []
    while len(frames) < n:
        pose = ContactPose(x_mm=float(rng.uniform(g.x_min_mm + 2.5, g.x_max_mm - 2.5)),
                           y_mm=float(rng.uniform(g.y_min_mm + 2.5, g.y_max_mm - 2.5)),
                           theta_deg=float(rng.uniform(0, 360)), depth_mm=float(rng.uniform(0.3, 1.1)))
        try:
            frames.append(s.press(names[int(rng.integers(len(names)))], pose,
                                  np.random.default_rng([seed, len(frames)]), truth=False).frame)
        except Exception:  # noqa: BLE001 - a pose the simulator refuses: draw another
            continue
    return frames


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plugin", default="gelslim2")
    ap.add_argument("--step", type=Path, default=None, help="step folder (default: beside the plugin's model)")
    ap.add_argument("--bundle", type=Path, default=None, help="training bundle for the eager baseline")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=20, help="timed steps of the step benchmark")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--small", action="store_true", help="a few steps on the demo clip's frames (tests)")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    if args.small:
        args.frames, args.steps, args.repeat = 30, 3, 3
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    from tactile_deploy.adapt.step import StepProgram, vae_filter
    from tactile_deploy.adapt.workflow import AdaptOptions, adapt_plugin, default_step_folder, view_weight
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin

    plugin = SensorPlugin.load(args.plugin)
    step_dir = args.step or default_step_folder(plugin)
    t_frames = time.perf_counter()
    if args.small:  # the plugin's demo clip: no simulation needed
        from tactile_deploy.runtime.sources.factory import open_clip

        with open_clip(plugin.demo_clip_path()) as src:
            frames = [f.image for f in src][: args.frames]
        origin = "its demo clip"
    elif plugin.name in ("gelslim1", "gelslim2"):
        frames = virtual_frames(plugin.name, args.frames)
        origin = f"the virtual {plugin.name}"
    else:
        raise SystemExit(f"bench adapt renders frames with the virtual sensor of the same name; {plugin.name} has none")
    t_frames = time.perf_counter() - t_frames
    pipe = ImagingPipeline.from_plugin(plugin)
    depth = np.stack([pipe.frame_to_depth(f) for f in frames]).astype(np.float32)
    program = StepProgram.load(step_dir, args.device)
    weight = view_weight(plugin)
    target = vae_filter(program, depth)
    b = min(args.batch, len(depth))
    d, t = depth[:b], target[:b]
    step_s = time_steps(program, d, t, weight, args.repeat + 2, args.device)[2:]
    step_med = statistics.median(step_s)

    # renderer share and the simulator's rasteriser as baseline (forward, no gradient)
    from tactile_deploy.training.simulation.depth_torch import TorchDepthCamera
    from tactile_deploy.pad.asset import load_pad

    pad = load_pad()
    with torch.no_grad():
        disp = program(d, t, weight)[3].to(args.device)
    from tactile_deploy.training.adaptation.render import DepthRenderer

    renderer = DepthRenderer.for_pad(pad, pixels_per_triangle=program.card.pixels_per_triangle).to(args.device)
    with torch.no_grad():
        r_ours = median_time(lambda: renderer(disp[:, :pad.n_plane]), max(3, args.repeat // 2), args.device)
        cam = TorchDepthCamera(pad, device=args.device, dtype=torch.float32)
        r_base = median_time(lambda: cam.render_displacements(disp[:, :pad.n_plane]), max(3, args.repeat // 2),
                             args.device)
    u = disp[:, :pad.n_plane].clone().requires_grad_(True)

    def fwd_bwd():
        renderer(u)[0].square().sum().backward()

    r_grad = median_time(fwd_bwd, max(3, args.repeat // 2), args.device)

    eager = None
    if args.bundle is not None:
        from tactile_deploy.training.adaptation.step import AdaptationStep
        from tactile_deploy.training.train import load_bundle

        model, _ = load_bundle(args.bundle)
        em = AdaptationStep(model).train().to(args.device)

        class Eager:
            def __init__(self, m):
                self.m = m

            def trainable(self):
                names = set(self.m.trainable_names())
                return [p for n, p in self.m.named_parameters() if n in names]

            def __call__(self, dd, tt, ww):
                dev = args.device
                return self.m(torch.as_tensor(dd)[:, None].to(dev), torch.as_tensor(tt).to(dev),
                              torch.as_tensor(ww).to(dev))

        eager = statistics.median(time_steps(Eager(em), d, t, weight, args.repeat + 2, args.device)[2:])

    # 200 frames end to end, on a copy of the plugin
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / plugin.name
        shutil.copytree(plugin.folder, copy, ignore=shutil.ignore_patterns("adapted"))
        _relink(copy, plugin.path_of("model"))
        target_plugin = SensorPlugin.load(copy)
        t0 = time.perf_counter()
        result = adapt_plugin(target_plugin, depth, AdaptOptions(steps=args.steps, batch_size=args.batch,
                                                                 device=args.device),
                              step_dir, log=lambda m: None, source={"source": "virtual frames", "frames": len(depth), "refused": 0})
        imaging = _imaging_time(pipe, frames)
        total = time.perf_counter() - t0 + imaging

    dev_name = _device_name(args.device)
    threads = torch.get_num_threads()
    lines = [
        f"`tactile-deploy bench adapt --device {args.device}`; {dev_name}, torch {torch.__version__}, "
        f"{threads} threads; step program `{Path(step_dir).relative_to(ROOT) if Path(step_dir).is_relative_to(ROOT) else step_dir}`; "
        f"frames: {len(frames)} of {origin} (making them took {t_frames:.0f} s, not counted).",
        "",
        "| measure | value | baseline | ratio |",
        "|---|---|---|---|",
        f"| Adam step, batch {b} (forward + loss + backward + update) | {step_med * 1e3:.0f} ms = **{1 / step_med:.2f} steps/s**, "
        f"{b / step_med:.0f} maps/s | "
        + (f"eager training module {eager * 1e3:.0f} ms | {step_med / eager:.2f} |" if eager else "- | - |"),
        f"| renderer forward, batch {b} | {r_ours * 1e3:.1f} ms | simulator's batched rasteriser {r_base * 1e3:.1f} ms | "
        f"{r_ours / r_base:.2f} |",
        f"| renderer forward + backward, batch {b} | {r_grad * 1e3:.1f} ms ({100 * r_grad / step_med:.0f} % of a step) | - | - |",
        f"| adapt on {len(frames)} frames ({result.n_train} + {result.n_held_out} held out), {args.steps} steps, "
        f"ONNX written | **{total:.0f} s** (imaging {imaging:.1f} s, steps {result.history.seconds:.0f} s) | "
        f"target {TARGET_200_FRAMES_S:.0f} s | {total / TARGET_200_FRAMES_S:.2f} |",
        "",
        f"Held-out label-free RMSE in that run: {result.before.rmse_mm * 1e3:.1f} -> {result.after.rmse_mm * 1e3:.1f} um"
        f" ({'version written' if result.version else 'no improvement, nothing written'}).",
    ]
    lines += ["", *cuda_lines(step_med, b)]
    md = "\n".join(lines)
    print(md)
    if not args.no_write:
        from bench.report import machine_line, write_section

        name = "adapt" if args.device == "cpu" else "adapt-cuda"
        title = "## On-device adaptation (`tactile-deploy bench adapt" + ("" if args.device == "cpu" else f" --device {args.device}") + "`)"
        write_section(name, f"{title}\n\n{machine_line()}\n\n{md}")
    return 0


def cuda_lines(cpu_step_s: float, batch: int) -> list[str]:
    """The committed CUDA results (``bench/results/adapt_cuda_*.json``, written on a GPU machine by
    ``bench/bench_adapt_device.py``) as a table, against this run's CPU step."""
    import json

    files = sorted((ROOT / "bench" / "results").glob("adapt_cuda_*.json"))
    if not files:
        return ["CUDA: not measured yet. On a GPU machine (torch, numpy, onnx, onnxruntime, pydantic suffice): "
                "`python bench/bench_adapt_device.py --device cuda --out bench/results/adapt_cuda_<gpu>.json`, "
                "commit the JSON, run this benchmark again."]
    out = ["CUDA (`bench/bench_adapt_device.py --device cuda`, committed results; synthetic presses, same step "
           "program; the CPU column is this run's step):", "",
           "| GPU | result file | Adam step (batch) | steps/s | vs this CPU | adapt: frames, steps, total |",
           "|---|---|---|---|---|---|"]
    for f in files:
        r = json.loads(f.read_text())
        st, ad = r["step"], r["adapt"]
        same = " (same batch)" if r["batch"] == batch else f" (CPU at batch {batch})"
        out.append(f"| {r['device_name']} | `{f.relative_to(ROOT)}` | {st['median_s'] * 1e3:.1f} ms ({r['batch']}) | "
                   f"**{st['steps_per_s']:.1f}** | {cpu_step_s / st['median_s']:.1f}x{same} | "
                   f"{ad['frames']}, {ad['steps']}, {ad['total_s']:.1f} s |")
    return out


def _relink(folder: Path, model: Path) -> None:
    sys.path.insert(0, str(ROOT / "plugins"))
    from build_shipped import relink_model

    relink_model(folder, model.resolve())


def _imaging_time(pipe, frames) -> float:
    t0 = time.perf_counter()
    for f in frames:
        pipe.frame_to_depth(f)
    return time.perf_counter() - t0


def _device_name(device: str) -> str:
    import torch

    if device.startswith("cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    import platform

    import os

    return f"CPU {platform.processor() or platform.machine()} ({os.cpu_count()} logical CPUs)"


if __name__ == "__main__":
    raise SystemExit(main())
