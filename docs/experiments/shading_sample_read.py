"""Shading read per camera sample instead of per imaging-grid cell, on virtual-sensor presses.

    python docs/experiments/shading_sample_read.py [--cache DIR] [--factors 2 3 4]

The runtime rectifies a frame to ``s x s`` samples per imaging-grid cell (0.273 mm on the
GelSlim grid), averages their colours per cell and reads the shading table per cell. Colour is
a strongly non-linear function of slope (point LEDs, channels that clip beyond a slope of about
0.26), so where the slope changes within a cell (the contact edge) the mean colour maps to a
wrong slope. This script measures the alternative: the table fitted at sample resolution (the
wizard's presses rectified to ``s x s`` samples per cell, targets at the samples' positions),
read at every sample, the gradients averaged per cell, integrated on the imaging grid by the
same solver and resampled to the model grid as the runtime does. Beside it, per factor: the
per-cell read of the same factor (colours averaged, table fitted per cell), and oracles: the
true surface's gradients averaged per cell from the samples vs per cell.

Presses and errors as in ``bench/bench_shading.py --only virtual`` (bench set seed 2024, 8 + 8;
second set seed 77, 24 + 8; RMSE within 1.5 contact radii, um). The wizard's presses and the
new presses are cached in ``--cache`` (the first run takes a few minutes).
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]


def wizard_data(cache: Path) -> dict:
    """The wizard's presses on the virtual GelSlim (as ``bench_shading.virtual_accuracy``),
    their FEM profiles, and the two new press sets, cached in ``cache``."""
    path = cache / "data.pkl"
    if path.is_file():
        with open(path, "rb") as f:
            return pickle.load(f)

    from bench.bench_shading import VIRTUAL_SENSOR, VIRTUAL_WIZARD, run_virtual_wizard
    from tactile_deploy.calibration.shading.virtual_check import virtual_ball_presses
    from tactile_deploy.calibration.wizard.config import wizard_config_from_dict
    from tactile_deploy.calibration.wizard.config import shading_fit_config
    from tactile_deploy.calibration.wizard.press_data import press_profiles
    from tactile_deploy.sensors import load_sensor

    config = wizard_config_from_dict(dict(VIRTUAL_WIZARD), "bench_shading.VIRTUAL_WIZARD")
    d, camera, reference, reference_frames = run_virtual_wizard(config, cache)
    fit_cfg = shading_fit_config(config.shading)
    profiles = press_profiles(config, d, camera, fit_cfg.far_factor)
    sensor = load_sensor(VIRTUAL_SENSOR)
    sensor.prepare()
    sets = {"bench": virtual_ball_presses(sensor, camera.grid, 8, 8, keep_surfaces=True),
            "second": virtual_ball_presses(sensor, camera.grid, 24, 8, seed=77,
                                           keep_surfaces=True)}
    out = {"presses": d, "camera": camera, "reference": reference,
           "reference_frames": reference_frames, "fit_cfg": fit_cfg, "profiles": profiles,
           "ball_radius_mm": config.presses.ball_radius_mm, "sets": sets}
    with open(path, "wb") as f:
        pickle.dump(out, f)
    return out


def sample_circles(circles, s: int) -> np.ndarray:
    """Circles (N, 3) in imaging-grid px -> the same circles in px of ``s x s`` samples per
    cell (centre column/row and radius)."""
    c = np.asarray(circles, np.float64).copy()
    c[:, :2] = (c[:, :2] + 0.5) * s - 0.5
    c[:, 2] *= s
    return c


class SampleRead:
    """Frame -> depth with the table read per sample and the gradients averaged per cell."""

    def __init__(self, camera, model, reference_raw, s: int):
        from tactile_deploy.imaging.camera_mapping import OutputGrid
        from tactile_deploy.imaging.poisson import poisson_solver
        from tactile_deploy.runtime.pipeline import (
            GridResampler,
            Rectifier,
            ShadingTables,
            rectify_frame,
        )

        self.s = s
        self.rect = Rectifier(camera, s)
        self.tables = ShadingTables.build(model, rectify_frame(reference_raw, self.rect))
        g = camera.grid
        self.shape = (g.ny, g.nx)
        h = model.header
        self.solver = poisson_solver(self.shape, "dirichlet",
                                     (h.poisson_weight_x, h.poisson_weight_y))
        self.pitch = g.pitch_x_mm
        self.resampler = GridResampler(g, OutputGrid())
        self.noise = None

    def gradients(self, frame):
        from tactile_deploy.runtime.pipeline import (
            rectify_frame,
            shading_gradients,
            subtract_reference,
        )

        samples = rectify_frame(frame, self.rect)
        gc, gr = shading_gradients(subtract_reference(samples, self.tables), samples, self.tables)
        ny, nx = self.shape
        s = self.s
        return (gc.reshape(ny, s, nx, s).mean(axis=(1, 3)),
                gr.reshape(ny, s, nx, s).mean(axis=(1, 3)))

    def depth(self, frame):
        from tactile_deploy.runtime.pipeline import integrate_depth

        gc, gr = self.gradients(frame)
        d = self.resampler(integrate_depth(gc, gr, self.solver, self.pitch))
        return d if self.noise is None else d - self.noise


def fit_at(data: dict, s: int, per_sample: bool, prior_weight: float | None = None,
           bins: int | None = None):
    """The wizard's shading fit on its presses rectified at ``s`` samples per cell: per sample
    (``per_sample``; targets at the samples) or per cell (colours averaged)."""
    from dataclasses import replace

    from tactile_deploy.calibration.shading.fit import fit_shading
    from tactile_deploy.calibration.shading.presses import PressSet
    from tactile_deploy.runtime.pipeline import (
        Rectifier,
        rectify_frame,
        resample_to_grid,
    )

    d, camera = data["presses"], data["camera"]
    keep = d["keep"]
    r = Rectifier(camera, s)
    if per_sample:
        rect = lambda f: rectify_frame(f, r)
    else:
        rect = lambda f: resample_to_grid(rectify_frame(f, r), r)
    k = s if per_sample else 1
    presses = PressSet(rect(data["reference"]), np.stack([rect(f) for f in d["raw"][keep]]),
                       [str(n) for n in d["names"][keep]], sample_circles(d["circles"][keep], k),
                       data["profiles"])
    cfg = data["fit_cfg"]
    if prior_weight is not None:
        cfg = replace(cfg, prior_weight=prior_weight)
    if bins is not None:
        cfg = replace(cfg, bins=bins)
    t0 = time.perf_counter()
    fit = fit_shading(presses, data["ball_radius_mm"], camera.grid.pitch_x_mm / k, cfg)
    return fit.model, time.perf_counter() - t0


def with_noise(run, data: dict, depth_fn):
    run.noise = np.mean([depth_fn(f) for f in data["reference_frames"]], axis=0)


def summary(errors: dict, sets: dict) -> str:
    parts = []
    for name, new in sets.items():
        e = errors[name]
        i, g = ~new.near_edge, new.near_edge
        parts.append(f"{e['near'][i].mean():5.1f} / {e['near'][i].max():5.1f} | "
                     f"{e['near'][g].mean():5.1f} | {np.abs(e['peak'][i]).mean():4.0f}")
    return " | ".join(parts)


def oracle_errors(data: dict, s: int, per_sample: bool) -> dict:
    """True surface gradients (area-averaged onto the ``s x s`` samples, central differences)
    averaged per cell (``per_sample``) or taken per cell from the cell-averaged surface,
    integrated with the isotropic solver, resampled to the model grid."""
    from tactile_deploy.calibration.shading.virtual_check import near_contact_errors
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.imaging.poisson import poisson_solver
    from tactile_deploy.runtime.pipeline import GridResampler

    g = data["camera"].grid
    k = s if per_sample else 1
    fine = g.model_copy(update={"nx": g.nx * k, "ny": g.ny * k})
    solver = poisson_solver((g.ny, g.nx), "dirichlet", (1.0, 1.0))
    to_model = GridResampler(g, OutputGrid())
    out = {}
    for name, new in data["sets"].items():
        to_fine = GridResampler(new.surface_grid, fine)
        depths = []
        for surf in new.surfaces_mm:
            d_row, d_col = np.gradient(to_fine(surf).astype(np.float64))   # per sample px
            d_row = d_row.reshape(g.ny, k, g.nx, k).mean(axis=(1, 3)) * k  # per cell px
            d_col = d_col.reshape(g.ny, k, g.nx, k).mean(axis=(1, 3)) * k
            depths.append(to_model(solver.integrate(d_col.astype(np.float32),
                                                    d_row.astype(np.float32))))
        out[name] = near_contact_errors(depths, new)
    return out


def main(argv=None) -> None:
    from tactile_deploy.calibration.shading.virtual_check import near_contact_errors
    from tactile_deploy.runtime.pipeline import ImagingPipeline

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cache", type=Path, default=Path("/tmp/shading_sample_read"))
    parser.add_argument("--factors", type=int, nargs="+", default=[2, 3, 4])
    parser.add_argument("--prior-weights", type=float, nargs="*", default=[],
                        help="also fit the per-sample tables with these prior weights")
    parser.add_argument("--bins", type=int, nargs="*", default=[],
                        help="also fit the per-sample tables with these numbers of bins")
    parser.add_argument("--no-cell", action="store_true", help="skip the per-cell reads")
    parser.add_argument("--no-oracle", action="store_true")
    parser.add_argument("--timing", action="store_true",
                        help="median frame -> depth time of both reads (one thread)")
    args = parser.parse_args(argv)
    data = wizard_data(args.cache)
    sets = data["sets"]
    print("columns per set: inside mean / worst | near edges mean | inside mean abs peak (um);"
          " bench set, then second set", flush=True)
    if not args.no_oracle:
        for s in args.factors:
            for per_sample in (False, True):
                if not per_sample and s != args.factors[0]:
                    continue
                tag = f"oracle: true gradients {'per sample, averaged' if per_sample else 'per cell'}"
                print(f"{tag:60s} s={s}: {summary(oracle_errors(data, s, per_sample), sets)}",
                      flush=True)
    camera = data["camera"]
    if args.timing:
        import cv2

        cv2.setNumThreads(1)
    for s in args.factors:
        cell_err, cell_run = None, None
        if not args.no_cell:
            model, t = fit_at(data, s, per_sample=False)
            plain = ImagingPipeline(camera, model, data["reference"], None, "keep", supersample=s)
            noise = np.mean([plain.frame_to_depth(f) for f in data["reference_frames"]], axis=0)
            run = ImagingPipeline(camera, model, data["reference"], noise.astype(np.float32),
                                  "subtract", supersample=s)
            err = {n: near_contact_errors([run.frame_to_depth(f) for f in new.frames], new)
                   for n, new in sets.items()}
            tag = f"per cell (colours averaged), w_x {model.header.poisson_weight_x:.3f}"
            print(f"{tag:60s} s={s}: {summary(err, sets)}   fit {t:.1f} s", flush=True)
            cell_err, cell_run = err, run
        variants = ([(None, None)] + [(pw, None) for pw in args.prior_weights]
                    + [(None, b) for b in args.bins])
        for pw, bins in variants:
            model, t = fit_at(data, s, per_sample=True, prior_weight=pw, bins=bins)
            run = SampleRead(camera, model, data["reference"], s)
            with_noise(run, data, run.depth)
            err = {n: near_contact_errors([run.depth(f) for f in new.frames], new)
                   for n, new in sets.items()}
            tag = (f"per sample, gradients averaged, w_x {model.header.poisson_weight_x:.3f}"
                   + ("" if pw is None else f", prior weight {pw:g}")
                   + ("" if bins is None else f", {bins} bins"))
            print(f"{tag:60s} s={s}: {summary(err, sets)}   fit {t:.1f} s", flush=True)
            if cell_err is not None and pw is None and bins is None:
                print(f"    per press, s={s}: {press_changes(cell_err, err, sets)}", flush=True)
            if args.timing and pw is None and bins is None:
                frame = sets["bench"].frames[0]
                cell = f"per cell {median_ms(cell_run.frame_to_depth, frame):.2f} ms, " \
                    if cell_run is not None else ""
                print(f"    frame -> depth (128 x 128, one thread, median), s={s}: {cell}"
                      f"per sample {median_ms(run.depth, frame):.2f} ms", flush=True)


def press_changes(cell: dict, sample: dict, sets: dict) -> str:
    """How many presses the per-sample read improves, and the worst near-edge press."""
    parts = []
    for name, new in sets.items():
        d = sample[name]["near"] - cell[name]["near"]
        edge = np.flatnonzero(new.near_edge)
        w = edge[np.argmax(cell[name]["near"][edge])]
        parts.append(f"{name}: {int((d < 0).sum())} of {len(d)} better (median "
                     f"{np.median(d):+.1f} um), worst near-edge press {cell[name]['near'][w]:.1f}"
                     f" -> {sample[name]['near'][w]:.1f} um")
    return "; ".join(parts)


def median_ms(fn, frame, n: int = 200) -> float:
    fn(frame)
    t = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn(frame)
        t.append(time.perf_counter() - t0)
    return float(np.median(t) * 1e3)


if __name__ == "__main__":
    main()
