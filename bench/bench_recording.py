"""Real ball presses -> plugin (one command) -> meshes of held-out presses, and what it costs.

The shared real recording (``../shared/data/real/fots_gelsight_ballpress``: 42 presses of a
2.35 mm ball, 240 x 320 px at 19.58 px/mm) is split into the odd- and the even-numbered presses;
each half calibrates a ``gelsight_mini`` plugin with the one-command calibration
(:func:`tactile_deploy.calibration.recording.build.calibrate_recording`, 5-fold held-out check of its own), and
the other half goes through the runtime (imaging pipeline + the pad's physics lift), so that
every press is a held-out press once. Inside each contact, spheres are fitted to the displaced
sensing nodes within 0.8 contact radii (:mod:`tactile_deploy.calibration.recording.mesh_check`): the ball's
radius with the centre free (shape error), and the radius free (radius error). The presses
nearest the image border (in contact radii) are listed on their own. Speed: the physics lift
per frame against the frame -> depth it follows and against the lift with one sparse solve per
fixed-point step instead of the lateral operator (the baseline: the same meshes), same frames,
same run; the start with an empty operator cache (the first half: factor and lateral operator
built) and with the operator cached (the second half).

    python bench/bench_recording.py [--no-write]       # or: tactile-deploy bench recording
"""

from __future__ import annotations

import argparse
import os
import csv
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data" / "real" / "fots_gelsight_ballpress"
BALL_RADIUS_MM = 2.35
MM_PER_PX = 1 / 19.58
N_EDGE = 8


def _labels() -> dict[str, list[float]]:
    with open(DATA / "annotate.csv", newline="") as f:
        return {r["img_names"]: [float(r["center_x"]), float(r["center_y"]), float(r["radius"])]
                for r in csv.DictReader(f)}


def run_half(parity: int, labels: dict, tmp: Path):
    """Calibrate on presses of ``parity`` (1: odd), mesh the others: per-press fits, the
    calibration's figures, and per-frame times (s) of depth and lift."""
    from tactile_deploy.calibration.recording.build import calibrate_recording
    from tactile_deploy.calibration.recording.mesh_check import circles_to_sensor_mm, press_mesh_fit
    from tactile_deploy.calibration.shading.presses import read_rgb
    from tactile_deploy.runtime.physics import PhysicsPredictor
    from tactile_deploy.runtime.plugins import SensorPlugin

    train = tmp / f"train{parity}"
    train.mkdir()
    shutil.copy(DATA / "background.png", train / "background.png")
    rows = ["img_names,center_x,center_y,radius"]
    held = []
    for name, (cx, cy, r) in labels.items():
        if int(Path(name).stem) % 2 == parity:
            shutil.copy(DATA / name, train / name)
            rows.append(f"{name},{cx},{cy},{r}")
        else:
            held.append(name)
    (train / "annotate.csv").write_text("\n".join(rows) + "\n")
    t0 = time.perf_counter()
    result = calibrate_recording(f"half{parity}", "gelsight_mini", train,
                                 ball_radius_mm=BALL_RADIUS_MM,
                                 annotations=train / "annotate.csv", mm_per_px=MM_PER_PX,
                                 out=tmp / f"half{parity}", say=lambda m: None)
    t_cal = time.perf_counter() - t0
    plugin = SensorPlugin.load(result.plugin)
    t0 = time.perf_counter()
    predictor = PhysicsPredictor(plugin)
    t_setup = time.perf_counter() - t0
    topo = predictor.topology
    fits, t_depth, t_lift = [], [], []
    for name in held:
        frame = read_rgb(DATA / name)
        t0 = time.perf_counter()
        depth = predictor.pipeline.frame_to_depth(frame)
        t1 = time.perf_counter()
        pred = predictor.infer(depth[None, None])
        t2 = time.perf_counter()
        baseline, _ = predictor.lift.from_depth(depth, predictor.depth_grid, predictor.iterations,
                                                lateral="solve")
        t3 = time.perf_counter()
        diff = float(np.abs(baseline - pred.vertices_mm[0]).max())
        if diff > 1e-5:   # float32 vertices of the same solution
            raise SystemExit(f"{name}: the lateral operator's mesh is {diff * 1e3:.3f} um from the "
                             "baseline's")
        t_depth.append(t1 - t0)
        t_lift.append((t2 - t1, t3 - t2))
        centre, radius = circles_to_sensor_mm(np.array([labels[name]]), plugin.manifest.camera)
        fits.append(press_mesh_fit(name, pred.vertices_mm[0], topo.rest_vertices_mm,
                                   topo.sensing_nodes, centre[0], radius[0], BALL_RADIUS_MM))
    return fits, result.metrics, t_cal, t_setup, t_depth, t_lift


def border_distance_radii(circle, shape_hw) -> float:
    """Distance (contact radii) from a circle's centre to the nearest image border."""
    h, w = shape_hw
    cx, cy, r = circle
    return min(cx + 0.5, w - 0.5 - cx, cy + 0.5, h - 0.5 - cy) / r


def markdown(fits, metrics, times, labels) -> str:
    from bench.report import machine_line

    shape = np.array([f.shape_um for f in fits])
    err = np.array([f.radius_error for f in fits])
    dist = {f.name: border_distance_radii(labels[f.name], (320, 240)) for f in fits}
    edge = sorted(fits, key=lambda f: dist[f.name])[:N_EDGE]
    t_cal, t_setup, t_depth, t_lift = times
    depth_ms = 1e3 * np.median(t_depth)
    lift_ms, solve_ms = 1e3 * np.median(np.array(t_lift), axis=0)
    checks = [("mesh shape error mean <= 25 um", shape.mean() <= 25, f"{shape.mean():.1f} um"),
              ("free radius within 5 % on every press", np.abs(err).max() <= 0.05,
               f"worst {100 * np.abs(err).max():.1f} %")]
    lines = [
        "## Real presses -> plugin (one command) -> meshes (`tactile-deploy bench recording`)",
        "",
        (f"{machine_line()} (load average {os.getloadavg()[1]:.1f} over the run's last "
         "5 minutes: the machine was shared, times are longer than alone). Data: `../shared/data/real/fots_gelsight_ballpress` (42 presses of "
         "a 2.35 mm ball, 240 x 320 px portrait, 19.58 px/mm). `calibrate --pad gelsight_mini "
         "--presses ... --annotations ... --ball-radius-mm 2.35 --mm-per-px 0.05107` on the odd "
         "presses meshes the even ones and the reverse, so every press is held out once; the "
         "meshes are the runtime's (imaging pipeline, then the pad's physics lift). Inside each "
         "contact, spheres fitted to the displaced sensing nodes within 0.8 labelled contact "
         "radii: shape error = RMS distance from the sphere of the ball's radius (centre free); "
         "radius error = the free sphere's radius against 2.35 mm."),
        "",
        "| held-out presses | n | shape error mean (um) | worst (um) | radius error mean | "
        "worst abs |",
        "|---|---:|---:|---:|---:|---:|",
        (f"| all | {len(fits)} | {shape.mean():.1f} | {shape.max():.1f} | "
         f"{100 * err.mean():+.1f} % | {100 * np.abs(err).max():.1f} % |"),
    ]
    es = np.array([f.shape_um for f in edge])
    ee = np.array([f.radius_error for f in edge])
    lines.append(f"| the {N_EDGE} nearest the image border | {N_EDGE} | {es.mean():.1f} | "
                 f"{es.max():.1f} | {100 * ee.mean():+.1f} % | {100 * np.abs(ee).max():.1f} % |")
    lines += ["", f"The {N_EDGE} presses nearest the image border, each (distance from the "
              "nearest border in contact radii; the recording has no press closer than this):",
              "", "| press | border distance (contact radii) | nodes | shape error (um) | "
              "radius error |", "|---|---:|---:|---:|---:|"]
    for f in edge:
        lines.append(f"| {f.name} | {dist[f.name]:.2f} | {f.n_nodes} | {f.shape_um:.1f} | "
                     f"{100 * f.radius_error:+.1f} % |")
    lines += ["", "The calibrations' own held-out check (5-fold, depth maps on the imaging grid, "
              "as `calibrate` prints it):", "",
              "| calibrated on | shape error mean (um) | worst (um) | fitted radius error worst |",
              "|---|---:|---:|---:|"]
    for label, m in metrics:
        lines.append(f"| {label} presses | {m['held-out shape error mean (um)']:.1f} | "
                     f"{m['held-out shape error worst (um)']:.1f} | "
                     f"{m['held-out fitted radius error worst (%)']:.1f} % |")
    lines += ["", "| target | measured | met |", "|---|---:|---|",
              *[f"| {n} | {v} | {'yes' if ok else '**no**'} |" for n, ok, v in checks], "",
              (f"Cost (medians over the {len(fits)} frames): frame -> depth {depth_ms:.1f} ms, "
               f"physics lift {lift_ms:.0f} ms ({lift_ms / depth_ms:.0f} x the frame -> depth; "
               "the fixed point's steps by the cached lateral operator, one sparse solve of the "
               f"10,716-node pad at the end), against {solve_ms:.0f} ms with a sparse solve per "
               f"step (the same meshes to 0.01 um): {solve_ms / lift_ms:.1f} x faster; its start "
               f"{t_setup[0]:.1f} s with an empty cache (the pad's factor and lateral operator "
               f"built), {t_setup[1]:.1f} s with the operator cached; one calibration (21 presses, "
               f"5-fold check) {np.mean(t_cal):.1f} s.")]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        raise SystemExit(f"{DATA} not found: the benchmark reads ../shared/data beside the checkout")
    labels = _labels()
    fits, metrics, t_cal, t_setup, t_depth, t_lift = [], [], [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["TACTILE_DEPLOY_CACHE_DIR"] = str(Path(tmp) / "cache")   # an empty cache
        for parity, label in ((1, "odd"), (0, "even")):
            f, m, tc, ts, td, tl = run_half(parity, labels, Path(tmp))
            fits += f
            metrics.append((label, m))
            t_cal.append(tc)
            t_setup.append(ts)
            t_depth += td
            t_lift += tl
    text = markdown(fits, metrics, (t_cal, t_setup, t_depth, t_lift), labels)
    print(text)
    if not args.no_write:
        from bench.report import write_section

        write_section("recording-real", text)
        print("\nwrote the recording-real section of BENCHMARKS.md")


if __name__ == "__main__":
    main()
