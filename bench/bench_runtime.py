"""Runtime speed and memory: one 640 x 480 RGB frame to a 5,380-node mesh on one CPU thread.

    python bench/bench_runtime.py [--plugin gelslim2] [--frames 3000] [--memory-frames 100000]
                                  [--small] [--no-write]      (or: tactile-deploy bench runtime)

Measures, in one run on this machine, with one thread everywhere (onnxruntime intra-op 1,
OpenCV 1, BLAS 1):

* end to end: frame -> mesh (:func:`tactile_deploy.runtime.pipeline.frame_to_mesh`), p50 and
  p95 over ``--frames`` frames of the plugin's demo clip, and each stage's share;
* reference paths, side by side with ratios: the imaging stages against the straightforward
  path (``cv2.undistort`` of the whole frame, ``cv2.warpPerspective`` onto the grid, then the
  plugin's read-out: its learned read-out if it has one, else the shading module's
  ``DepthFromShading``); the onnxruntime model stage against the same network
  evaluated by torch (eager, one thread) when the training bundle named in the model's metadata
  is present; forces (total only vs per-node pressure);
* memory: the ``run`` loop (frames -> mesh -> forces -> status) over ``--memory-frames`` frames,
  RSS at the start (after warm-up) and the end, and its largest value.

Targets: p50 <= 4 ms end to end (>= 250 Hz); RSS flat over 100,000 frames.
Results go to BENCHMARKS.md (section ``runtime``) unless ``--no-write``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TARGET_P50_MS = 4.0


def rss_mb() -> float:
    """Resident set size of this process now, MiB (Linux /proc; ru_maxrss elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def pct(values, q):
    import numpy as np

    return float(np.percentile(np.asarray(values, float), q))


def time_calls(fn, args_list, repeat_min_s: float = 0.0):
    """Per-call wall times (ms) of ``fn(*args)`` over ``args_list``."""
    out = []
    for args in args_list:
        t0 = time.perf_counter_ns()
        fn(*args)
        out.append((time.perf_counter_ns() - t0) / 1e6)
    return out


def reference_imaging(plugin):
    """The straightforward imaging path: full-frame undistort, perspective warp to the grid,
    then the shading module (as a calibration script would do it)."""
    import cv2
    import numpy as np

    from tactile_deploy.imaging.shading import DepthFromShading

    m = plugin.manifest
    cam = m.camera
    g = cam.grid
    k, d = cam.camera_matrix, cam.dist_coeffs
    # grid pixel (col, row) -> sensor mm -> undistorted px: the inverse homography
    a = np.array([[g.pitch_x_mm, 0, g.x_min_mm + 0.5 * g.pitch_x_mm],
                  [0, -g.pitch_y_mm, g.y_max_mm - 0.5 * g.pitch_y_mm], [0, 0, 1.0]])
    px_from_grid = np.linalg.inv(cam.homography) @ a
    size = (g.nx, g.ny)
    ref_u = cv2.undistort(plugin.reference_frame, k, d)
    ref = cv2.warpPerspective(ref_u, px_from_grid, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    if plugin.readout is not None:     # the plugin reads frames with its learned read-out
        from tactile_deploy.imaging.learned_readout import FeatureMaker

        features = FeatureMaker(ref, g, plugin.readout.saturation_level)
        gain = m.readout_depth_gain

        def read(rect):
            return plugin.readout.depth_mm(features(rect)) * gain
    else:
        read = DepthFromShading(plugin.shading_model, ref).depth

    def depth(frame):
        und = cv2.undistort(frame, k, d)
        rect = cv2.warpPerspective(und, px_from_grid, size,
                                   flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        return read(rect)

    return depth


def _fp32_twin(model_path: Path, meta: dict) -> Path | None:
    """The fp32 ONNX graph of the same weights, named by the model card (or None)."""
    import json

    card = Path(model_path).parent / meta.get("model_card", "")
    if not card.is_file():
        return None
    twin = json.loads(card.read_text()).get("files", {}).get("reference_fp32")
    return Path(model_path).parent / twin if twin else None


def torch_reference(model_path, bundle: Path | None = None):
    """The same network in torch (eager, fp32, one thread): ``(callable, description)``, or
    ``(None, reason)``. The training bundle (``model.pt``) is ``bundle``, else the one committed
    beside the model (``<model>.pt``) or among ``out/predictor/*/model.pt`` of this checkout
    whose torch module reproduces the model's fp32 ONNX twin (named by its model card) to
    1e-4 mm, or the ONNX model itself to 0.1 mm (int8) when there is no twin."""
    try:
        import numpy as np
        import torch
    except ImportError as e:
        return None, f"torch not installed ({e})"
    from tactile_deploy.onnx_runtime.session import make_session

    meta = make_session(model_path, providers="cpu").get_modelmeta().custom_metadata_map
    try:
        from tactile_deploy.training.export import deploy_module
        from tactile_deploy.training.train import load_bundle
    except ImportError as e:
        return None, f"training package not importable ({e})"
    torch.set_num_threads(1)
    variant = meta.get("variant", "lean")
    twin = _fp32_twin(Path(model_path), meta)
    target, tol = (twin, 1e-4) if twin is not None and twin.is_file() else (Path(model_path), 0.1)
    probe = np.zeros((2, 1, 128, 128), np.float32)
    probe[0, 0, 50:70, 50:70] = 0.5
    probe[1, 0, 30:40, 80:100] = 0.8
    want = make_session(target, providers="cpu").run(["displacement"], {"depth": probe})[0]
    committed = [p for p in (Path(model_path).with_suffix(".pt"),) if p.is_file()]
    candidates = [bundle] if bundle is not None else committed + sorted(
        (ROOT / "out" / "predictor").glob("*/model.pt"), key=lambda p: -p.stat().st_mtime)
    for path in candidates:
        try:
            model, info = load_bundle(path)
            module = deploy_module(model, variant)
        except Exception:  # noqa: BLE001 - bundles of other architectures or versions
            continue
        with torch.no_grad():
            got = module(torch.as_tensor(probe))[1].numpy()
        if got.shape == want.shape and float(np.abs(got - want).max()) <= tol:
            @torch.no_grad()
            def run(depth, module=module):
                return module(torch.as_tensor(depth))

            shown = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
            return run, f"{shown}, {variant} in fp32"
    return None, (f"no training bundle reproduces {target.name} (looked at "
                  f"{', '.join(str(c) for c in candidates) or 'out/predictor/*/model.pt'}; "
                  "--torch-bundle PATH)")


#: Presses of the force check; the first 12 (same seed, same draws) were its whole sample before:
#: their median is reported beside the whole sample's.
FORCE_PRESSES = 48
FORCE_PRESSES_BEFORE = 12


def force_check(plugin, predictor, estimator, n: int = FORCE_PRESSES, seed: int = 7) -> dict:
    """Total normal force from the predicted mesh of new virtual-sensor frames (balls and a
    punch at random places and depths) against the force of the sensor's FEM; also the force
    from the sensor's own FEM mesh (the inverse's exactness). Needs the virtual sensor of the
    plugin's name."""
    import numpy as np

    try:
        from tactile_deploy.indenters import ContactPose
        from tactile_deploy.sensors import load_sensor
        from tactile_deploy.sensors.catalog import UnknownSensorError
    except ImportError as e:
        return {"skipped": f"virtual sensors not importable ({e})"}
    try:
        sensor = load_sensor(plugin.name)
    except UnknownSensorError:
        return {"skipped": f"no virtual sensor named {plugin.name!r}"}
    g = plugin.manifest.camera.grid
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        ind = ("sphere_r4", "sphere_r6", "flat_punch")[i % 3]
        pose = ContactPose(x_mm=float(rng.uniform(g.x_min_mm + 5, g.x_max_mm - 5)),
                           y_mm=float(rng.uniform(g.y_min_mm + 5, g.y_max_mm - 5)),
                           depth_mm=float(rng.uniform(0.3, 0.9)))
        out = sensor.press(ind, pose, np.random.default_rng([seed, i]))
        pred = predictor.predict_frame(out.frame)
        every_node = estimator.with_contact_fraction(None)  # the exact inverse of the FEM
        f_pred = estimator.estimate(pred.vertices_mm, pressure=False).total_normal_force_n
        f_all = every_node.estimate(pred.vertices_mm, pressure=False).total_normal_force_n
        f_mesh = every_node.estimate(out.vertices_mm.astype(np.float64), pressure=False).total_normal_force_n
        f_mesh_patch = estimator.estimate(out.vertices_mm.astype(np.float64), pressure=False).total_normal_force_n
        rows.append((out.force_n, f_pred, f_mesh, f_all, f_mesh_patch))
    a = np.array(rows)
    rel = np.abs(a[:, 1:] - a[:, :1]) / a[:, :1]
    return {"n": n, "force_range_n": [float(a[:, 0].min()), float(a[:, 0].max())],
            "contact_fraction": estimator.contact_fraction,
            "predicted_rel_error_median": float(np.median(rel[:, 0])),
            "predicted_rel_error_median_first": [min(n, FORCE_PRESSES_BEFORE),
                                                 float(np.median(rel[:FORCE_PRESSES_BEFORE, 0]))],
            "predicted_rel_error_quartiles": [float(np.quantile(rel[:, 0], 0.25)),
                                              float(np.quantile(rel[:, 0], 0.75))],
            "predicted_rel_error_max": float(rel[:, 0].max()),
            "predicted_every_node_rel_error_median": float(np.median(rel[:, 2])),
            "predicted_every_node_rel_error_max": float(rel[:, 2].max()),
            "fem_mesh_rel_error_max": float(rel[:, 1].max()),
            "fem_mesh_patch_rel_error_max": float(rel[:, 3].max())}


def run(plugin_name: str, frames: int, memory_frames: int, torch_bundle: Path | None = None) -> dict:
    import cv2
    import numpy as np
    from threadpoolctl import threadpool_limits

    from tactile_deploy.runtime.forces import ForceEstimator
    from tactile_deploy.runtime.pipeline import Laps, frame_to_mesh
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.runtime.predictor import MeshPredictor
    from tactile_deploy.runtime.run import Runner, RunOptions
    from tactile_deploy.runtime.sources.base import ArrayPlayback
    from tactile_deploy.runtime.sources.factory import open_clip

    cv2.setNumThreads(1)
    limits = threadpool_limits(1)
    plugin = SensorPlugin.load(plugin_name)
    predictor = MeshPredictor.from_plugin(plugin, threads=1, providers="cpu", warmup=5)
    with open_clip(plugin.demo_clip_path()) as src:
        clip = [f.image for f in src]
    h, w = clip[0].shape[:2]
    pipe = predictor.pipeline
    res: dict = {"plugin": plugin.name, "frame": f"{w}x{h}", "n_frames": frames,
                 "model_file": predictor.model_path.name, "providers": predictor.providers}

    # -- end to end, stage by stage
    for i in range(50):
        frame_to_mesh(clip[i % len(clip)], pipe, predictor)
    totals, stages = [], {}
    for i in range(frames):
        laps = Laps().start()
        t0 = time.perf_counter_ns()
        frame_to_mesh(clip[i % len(clip)], pipe, predictor, laps)
        totals.append((time.perf_counter_ns() - t0) / 1e6)
        for k, v in laps.times_ns.items():
            stages.setdefault(k, []).append(v / 1e6)
    res["e2e_p50_ms"] = pct(totals, 50)
    res["e2e_p95_ms"] = pct(totals, 95)
    res["e2e_mean_ms"] = float(np.mean(totals))
    res["stages"] = {k: {"p50_ms": pct(v, 50), "mean_ms": float(np.mean(v)),
                         "share": float(np.mean(v) / np.mean(totals))} for k, v in stages.items()}

    # -- imaging: ours vs the straightforward path
    ref_depth = reference_imaging(plugin)
    sample = [(clip[i % len(clip)],) for i in range(min(frames, 600))]
    ours = time_calls(pipe.imaging_depth, sample)
    theirs = time_calls(ref_depth, sample)
    diff = max(float(np.abs(pipe.imaging_depth(f) - ref_depth(f)).max()) for (f,) in sample[:20])
    res["imaging"] = {"read_out": ("the same learned read-out" if plugin.readout is not None
                                   else "DepthFromShading"),
                      "ours_p50_ms": pct(ours, 50), "reference_p50_ms": pct(theirs, 50),
                      "ratio": pct(theirs, 50) / pct(ours, 50), "max_depth_difference_mm": diff}

    # -- the optional learned read-out on the same frames (a plugin that names one)
    readout_path = ROOT / "exported" / "gelslim_readout.onnx"
    if plugin.readout is None and readout_path.is_file():
        from tactile_deploy.imaging.learned_readout import LearnedReadout
        from tactile_deploy.runtime.pipeline import ImagingPipeline

        m = plugin.manifest
        learned = ImagingPipeline(m.camera, plugin.shading_model, plugin.reference_frame,
                                  plugin.noise_reference, m.noise_reference.handling,
                                  m.depth_grid, plugin.hooks, readout=LearnedReadout(readout_path))
        lr_ms = time_calls(learned.imaging_depth, sample)
        res["imaging"]["learned_readout_p50_ms"] = pct(lr_ms, 50)

    # -- model: onnxruntime vs torch
    depths = [(pipe.frame_to_depth(f)[None, None],) for (f,) in sample[:200]]
    ort_ms = time_calls(predictor.infer, depths)
    res["model"] = {"onnxruntime_p50_ms": pct(ort_ms, 50)}
    ref_fn, info = torch_reference(predictor.model_path, torch_bundle)
    if ref_fn is None:
        res["model"]["torch"] = f"not measured: {info}"
    else:
        for d in depths[:10]:
            ref_fn(d[0])
        t_ms = time_calls(ref_fn, depths)
        # same network? compare the displacements of the two paths on these depth maps
        diff = max(float(np.abs(ref_fn(d[0])[1].numpy() - predictor.infer(d[0]).displacement_mm).max())
                   for d in depths[:20])
        res["model"].update({"torch_p50_ms": pct(t_ms, 50), "ratio": pct(t_ms, 50) / pct(ort_ms, 50),
                             "torch_bundle": info, "max_displacement_difference_mm": diff})

    # -- forces
    estimator = ForceEstimator.for_plugin(plugin)
    verts = [(predictor.infer(d[0]).vertices_mm[0],) for d in depths[:100]]
    total_only = time_calls(lambda v: estimator.estimate(v, pressure=False), verts)
    full = time_calls(lambda v: estimator.estimate(v), verts)
    res["forces"] = {"total_p50_ms": pct(total_only, 50), "pressure_p50_ms": pct(full, 50)}

    # -- forces from predicted meshes vs the virtual sensor's FEM forces
    res["force_check"] = force_check(plugin, predictor, estimator)

    # -- memory over a long run (the real loop, no file output)
    src = ArrayPlayback(clip, np.arange(len(clip)) * 33_333_333, "demo clip (looped)", loop=True)
    warm = Runner(predictor, src, RunOptions(max_frames=min(1000, memory_frames), forces=False),
                  forces=estimator)
    warm.run()
    src = ArrayPlayback(clip, np.arange(len(clip)) * 33_333_333, "demo clip (looped)", loop=True)
    samples = []
    rss0 = rss_mb()
    t0 = time.perf_counter()

    def status(_line):
        samples.append(rss_mb())

    runner = Runner(predictor, src, RunOptions(max_frames=memory_frames,
                                               status_every_s=max(1.0, memory_frames / 2e4)),
                    forces=estimator, status=status)
    summary = runner.run()
    res["memory"] = {"frames": summary.frames, "rss_start_mb": rss0, "rss_end_mb": rss_mb(),
                     "rss_max_mb": max(samples + [rss0]), "seconds": time.perf_counter() - t0,
                     "loop_fps": summary.fps, "loop_latency_p50_ms": summary.latency_p50_ms}
    limits.restore_original_limits()
    return res


def markdown(r: dict) -> str:
    from bench.report import machine_line

    p50 = r["e2e_p50_ms"]
    met = "met" if p50 <= TARGET_P50_MS else f"not met: {p50 / TARGET_P50_MS:.1f} x the budget"
    lines = [
        "## Runtime: camera frame to mesh (`tactile-deploy bench runtime`)",
        "",
        f"{machine_line()}; one thread (onnxruntime, OpenCV, BLAS); plugin `{r['plugin']}`, "
        f"{r['frame']} RGB frames of its demo clip, model `{r['model_file']}`, {r['n_frames']} frames.",
        "",
        "| end to end (frame -> 5,380-node mesh) | p50 | p95 | rate at p50 | target |",
        "|---|---:|---:|---:|---|",
        f"| measured | {p50:.2f} ms | {r['e2e_p95_ms']:.2f} ms | {1e3 / p50:.0f} Hz | "
        f"p50 <= {TARGET_P50_MS:g} ms (>= 250 Hz): {met} |",
        "",
        "| stage | p50 (ms) | mean (ms) | share of the mean |",
        "|---|---:|---:|---:|",
    ]
    for k, s in r["stages"].items():
        lines.append(f"| {k} | {s['p50_ms']:.3f} | {s['mean_ms']:.3f} | {100 * s['share']:.1f} % |")
    im = r["imaging"]
    md = r["model"]
    lines += [
        "",
        "| path, side by side | ours p50 | reference p50 | ratio (reference / ours) |",
        "|---|---:|---:|---:|",
        f"| imaging: frame -> depth on the imaging grid (reference: full-frame cv2.undistort + "
        f"warpPerspective, point-sampling each cell instead of averaging it, then "
        f"{im['read_out']}; "
        f"max depth difference {1e3 * im['max_depth_difference_mm']:.1f} um) "
        f"| {im['ours_p50_ms']:.3f} ms | {im['reference_p50_ms']:.3f} ms | {im['ratio']:.1f} x |",
    ]
    if "learned_readout_p50_ms" in im:
        lines.append(f"| imaging with the optional learned read-out (`exported/gelslim_readout.onnx`, "
                     f"instead of the shading table and integration; docs/shading.md) vs the "
                     f"plugin's shading model | {im['learned_readout_p50_ms']:.3f} ms | "
                     f"{im['ours_p50_ms']:.3f} ms | {im['ours_p50_ms'] / im['learned_readout_p50_ms']:.2f} x |")
    if "torch_p50_ms" in md:
        lines.append(f"| model: onnxruntime ({r['model_file']}) vs torch eager ({md['torch_bundle']}), "
                     f"one thread; displacements agree to {1e3 * md['max_displacement_difference_mm']:.0f} um "
                     f"| {md['onnxruntime_p50_ms']:.3f} ms"
                     f" | {md['torch_p50_ms']:.3f} ms | {md['ratio']:.1f} x |")
    else:
        lines.append(f"| model: onnxruntime | {md['onnxruntime_p50_ms']:.3f} ms | {md['torch']} | - |")
    f = r["forces"]
    lines.append(f"| forces: total normal force only vs per-node pressure (dense 1,076 x 1,076) | "
                 f"{f['total_p50_ms']:.3f} ms | {f['pressure_p50_ms']:.3f} ms | "
                 f"{f['pressure_p50_ms'] / max(f['total_p50_ms'], 1e-9):.0f} x |")
    fc = r.get("force_check", {})
    if "skipped" in fc:
        lines += ["", f"Forces from predicted meshes: not checked ({fc['skipped']})."]
    elif fc:
        lines += [
            "",
            f"Forces, {fc['n']} new virtual-sensor presses ({fc['force_range_n'][0]:.2f}-"
            f"{fc['force_range_n'][1]:.2f} N; balls of 4 and 6 mm, a 3 mm punch): total normal "
            f"force from the **predicted** mesh vs the sensor's FEM force, summed over the contact patch "
            f"(nodes above {fc['contact_fraction']:g} of the largest nodal force, as `run` reports it): median "
            f"error {100 * fc['predicted_rel_error_median']:.1f} % (quartiles "
            f"{100 * fc['predicted_rel_error_quartiles'][0]:.1f}-{100 * fc['predicted_rel_error_quartiles'][1]:.1f} %; "
            f"the first {fc['predicted_rel_error_median_first'][0]}, this check's earlier sample: "
            f"{100 * fc['predicted_rel_error_median_first'][1]:.1f} %), worst {100 * fc['predicted_rel_error_max']:.0f} %"
            f" (target: median <= 5 %); summed over every node: median "
            f"{100 * fc['predicted_every_node_rel_error_median']:.0f} %, worst "
            f"{100 * fc['predicted_every_node_rel_error_max']:.0f} %; from the sensor's own FEM mesh (the inverse "
            f"FEM alone): worst {100 * fc['fem_mesh_rel_error_max']:.1g} % over every node, "
            f"{100 * fc['fem_mesh_patch_rel_error_max']:.1g} % over the contact patch.",
        ]
    m = r["memory"]
    drift = m["rss_end_mb"] - m["rss_start_mb"]
    lines += [
        "",
        f"Memory, the `run` loop (frame -> mesh -> total force -> status) over {m['frames']:,} "
        f"frames ({m['seconds']:.0f} s, {m['loop_fps']:.0f} fps, latency p50 "
        f"{m['loop_latency_p50_ms']:.2f} ms): RSS {m['rss_start_mb']:.1f} MiB at the start "
        f"(after 1,000 warm-up frames), {m['rss_end_mb']:.1f} MiB at the end ({drift:+.1f} MiB), "
        f"largest {m['rss_max_mb']:.1f} MiB.",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plugin", default="gelslim2")
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--memory-frames", type=int, default=100_000)
    ap.add_argument("--torch-bundle", type=Path, default=None,
                    help="training bundle (model.pt) of the model, for the torch reference")
    ap.add_argument("--small", action="store_true", help="a quick run (300 frames, 2,000 for memory)")
    ap.add_argument("--no-write", action="store_true", help="print, do not update BENCHMARKS.md")
    args = ap.parse_args(argv)
    if args.small:
        args.frames, args.memory_frames = 300, 2000
    import json

    res = run(args.plugin, args.frames, args.memory_frames, args.torch_bundle)
    print(json.dumps(res, indent=2))
    md = markdown(res)
    print(md)
    if not args.no_write and not args.small:
        from bench.report import write_section

        write_section("runtime", md)
        print("updated BENCHMARKS.md (section runtime)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
