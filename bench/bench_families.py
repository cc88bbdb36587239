"""The GelSight Mini and DIGIT virtual sensors through the one-command calibration: depth and mesh
against the truth, on balls and on shapes the calibration never saw.

For each family's virtual sensor (``tactile_deploy/assets/sensors/<family>.json``):

1. 24 ball presses (1.5 mm ball radius, 0.4-1.1 mm deep, anywhere in the view) are recorded in the
   real recordings' layout (frames, ``background.png``, ``annotate.csv``) and calibrated with
   :func:`tactile_deploy.calibration.recording.build.calibrate_recording` at the virtual camera's scale;
2. new ball presses (8 at least two contact radii inside the view, 8 within 1.2-1.7 of its
   edges) go through the plugin's imaging pipeline: RMSE within 1.5 contact radii against the
   surface the frames were shaded from, on the family's depth grid (the GelSlim check of
   ``bench shading``, target 20 um); and a second sample of 24 + 24 (seed 4048), since 8 presses
   move the mean by several um;
3. the same presses' meshes from the physics lift against the FEM's deformed pad: RMSE of the
   sensing nodes within 1.5 contact radii (um, 3-D distance);
4. 16 presses of the shared indenter meshes (``../shared/data/indenters``, shapes neither the
   calibration nor any training saw; seed 99, one per shape): contact-region RMSE (the true depth
   above 10 um, grown by 4 cells), target 30 um; and a second, larger sample (48 presses, three per
   shape, seed 123) with its mean per shape, since 16 presses move the mean by several um.

    python bench/bench_families.py [--families gelsight_mini,digit] [--no-write]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

INDENTERS = ROOT.parent / "shared" / "data" / "indenters"
BALL_MM = 1.5
#: Presses of the second sample of the shared shapes (three per shape).
SECOND_SHAPE_SAMPLE = 48
#: Presses of the second sample of balls, inside the view and near its edges (each).
SECOND_BALL_SAMPLE = 24


def family_bench(name: str, tmp: Path) -> list[dict]:
    """The family's virtual sensor calibrated twice from the same recording (the fitted shading
    model; the learned read-out ``exported/<family>_readout.onnx`` when it is shipped), each
    measured on the same new presses (module docstring); one result per depth reader."""
    from tactile_deploy.calibration.recording.build import calibrate_recording
    from tactile_deploy.calibration.shading.virtual_check import (
        contact_region_errors,
        near_contact_errors,
        view_mask,
        virtual_ball_presses,
        virtual_shape_presses,
    )
    from tactile_deploy.calibration.virtual_recordings import record_ball_presses
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.pad.family import FAMILIES
    from tactile_deploy.runtime.physics import PhysicsPredictor
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.sensors.catalog import load_sensor
    from tactile_deploy.shipped import model_path

    fam = FAMILIES[name]
    sensor = load_sensor(name)
    t0 = time.perf_counter()
    sensor.prepare()
    t_prepare = time.perf_counter() - t0
    rec = record_ball_presses(sensor, 24, radius_mm=BALL_MM, depth_range_mm=(0.4, 1.1), seed=5)
    folder = tmp / f"{name}_presses"
    rec.save(folder)
    mm_per_px = float(sensor.optics.camera.mm_per_px_x)
    readout = model_path(f"{name}_readout.onnx")
    readers = [("the fitted shading model", None)]
    units = None
    if readout.is_file():
        readers.append((f"learned read-out `exported/{readout.name}`", readout))
        card = readout.with_suffix(".json")
        units = json.loads(card.read_text())["family"]["units"] if card.is_file() else None
    grid = presses = sp = truth_vertices = None
    results = []
    for label, readout_file in readers:
        t0 = time.perf_counter()
        cal = calibrate_recording(f"{name.replace('_', '-')}-virtual", name, folder,
                                  ball_radius_mm=BALL_MM, annotations=folder / "annotate.csv",
                                  shallow_presses=True, mm_per_px=mm_per_px,
                                  out=tmp / f"{name}_plugin_{len(results)}", readout=readout_file,
                                  say=lambda m: None)
        t_cal = time.perf_counter() - t0
        plugin = SensorPlugin.load(cal.plugin)
        predictor = PhysicsPredictor(plugin)
        pipeline = predictor.pipeline
        sens = predictor.lift.mesh.sensing_nodes
        rest = predictor.topology.rest_vertices_mm[sens]
        if presses is None:   # the same new presses for every reader
            grid = plugin.manifest.camera.grid
            presses = virtual_ball_presses(sensor, grid, 8, 8, seed=2024, ball_radius_mm=BALL_MM,
                                           depth_range_mm=(0.4, 1.0), depth_grid=fam.depth_grid)
            presses2 = virtual_ball_presses(sensor, grid, SECOND_BALL_SAMPLE, SECOND_BALL_SAMPLE,
                                            seed=4048, ball_radius_mm=BALL_MM,
                                            depth_range_mm=(0.4, 1.0), depth_grid=fam.depth_grid)
            # meshes against the FEM: the same poses pressed again (noise-free) for the truth
            truth_vertices = [sensor.press(AnalyticSphere(BALL_MM), ContactPose(
                x_mm=c[0], y_mm=c[1], depth_mm=a * a / (2 * BALL_MM))).vertices_mm[sens]
                for c, a in zip(presses.centres_mm, presses.radii_mm)]
            shapes = sorted(INDENTERS.glob("*.stl"))
            margin = min(3.0, 0.25 * min(grid.x_max_mm - grid.x_min_mm, grid.y_max_mm - grid.y_min_mm))
            sp = virtual_shape_presses(sensor, grid, shapes, n=16, seed=99, depth_grid=fam.depth_grid,
                                       margin_mm=margin)
            sp48 = virtual_shape_presses(sensor, grid, shapes, n=SECOND_SHAPE_SAMPLE, seed=123,
                                         depth_grid=fam.depth_grid, margin_mm=margin)
        depths = np.stack([pipeline.frame_to_depth(f) for f in presses.frames])
        ball = near_contact_errors(depths, presses, depth_grid=fam.depth_grid)
        ball2 = near_contact_errors(np.stack([pipeline.frame_to_depth(f) for f in presses2.frames]),
                                    presses2, depth_grid=fam.depth_grid)
        mesh_err = []
        for d, c, a, truth in zip(depths, presses.centres_mm, presses.radii_mm, truth_vertices):
            v = predictor.infer(d[None, None]).vertices_mm[0][sens]
            near = np.hypot(rest[:, 0] - c[0], rest[:, 1] - c[1]) < 1.5 * a
            mesh_err.append(1e3 * np.sqrt(np.mean(np.sum((v[near] - truth[near]) ** 2, axis=1))))
        shape_depths = np.stack([pipeline.frame_to_depth(f) for f in sp.frames])
        view = view_mask(plugin.manifest.camera.grid, fam.depth_grid)
        shape = contact_region_errors(shape_depths, sp.truths, view=view)
        shape48 = contact_region_errors(np.stack([pipeline.frame_to_depth(f) for f in sp48.frames]),
                                        sp48.truths, view=view)
        results.append({"family": name, "reader": label, "ball": ball, "edge": presses.near_edge,
                        "ball2": ball2, "edge2": presses2.near_edge,
                        "mesh": np.array(mesh_err), "shape": shape, "shape_names": sp.names,
                        "shape48": shape48, "shape48_names": sp48.names,
                        "cal": cal.metrics, "t_prepare": t_prepare, "t_cal": t_cal,
                        "view_edge_extension_mm": plugin.manifest.view_edge_extension_mm,
                        "readout_units": units})
    return results


def markdown(results: list[dict]) -> str:
    from bench.report import machine_line

    units_text = ", ".join(f"{r['family']}: {r['readout_units']}" for r in results
                           if r["readout_units"] is not None and r["reader"].startswith("learned"))
    lines = ["## GelSight Mini and DIGIT virtual sensors, one-command calibration "
             "(`tactile-deploy bench families`)", "",
             (f"{machine_line()} (load average {os.getloadavg()[1]:.1f}: a shared "
              "machine). Each family's virtual sensor: 24 ball presses (radius 1.5 mm, "
              "0.4-1.1 mm) recorded in the real recordings' layout and calibrated by the one-command "
              "calibration, once with the fitted shading model and once with the family's learned "
              "read-out (`--readout exported/<family>_readout.onnx`, trained on virtual units "
              f"drawn around the design ({units_text}, its card), never on the nominal unit "
              "measured here; its depth used as trained); new presses: 8 "
              "balls at least two contact radii inside the view, 8 within 1.2-1.7 of its edges "
              "(RMSE within 1.5 contact radii against the surface the frames were shaded from, "
              f"family depth grid) and a second sample of {SECOND_BALL_SAMPLE} + {SECOND_BALL_SAMPLE} "
              "(seed 4048), the first sample's physics-lift meshes against the FEM (sensing nodes "
              "within 1.5 contact radii, 3-D RMSE), 16 presses of the 16 shared indenter meshes "
              "(contact-region RMSE; seed 99, one per shape) and a second sample of 48 (three per shape, "
              "seed 123), and the same over the depth-grid cells inside the camera's imaging grid "
              "(in the view). um. The depth grid follows the sensing area, a little wider than the "
              "camera's view: across that strip the plugins carry the depth at the view's edge "
              "(`view_edge_extension_mm`, set by the calibration to the strip's widest side, "
              "which depends on the imaging grid the depth is read on: "
              + "; ".join(f"{r['family']}, {r['reader'].split(' `')[0]}: {r['view_edge_extension_mm']:.2f} mm"
                          for r in results)
              + "; with depth 0 there, a contact reaching past the view left a cliff at its edge)."),
             "",
             "| family | depth from | balls inside: RMSE near mean (worst) | near the edges | "
             f"second sample ({SECOND_BALL_SAMPLE} + {SECOND_BALL_SAMPLE}): inside / near the edges, "
             "mean (worst) | mesh vs FEM mean (worst) | unseen shapes: contact-region mean (worst) | the same, 48 presses: mean "
             "(worst) | 48 presses, in the view: mean | calibration held-out shape mean / worst | targets |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in results:
        near, edge = r["ball"]["near"], r["edge"]
        near2, edge2 = r["ball2"]["near"], r["edge2"]
        region, region48 = r["shape"]["region"], r["shape48"]["region"]
        ok = [("balls 20 um (both samples)", max(near[~edge].mean(), near2[~edge2].mean()) <= 20),
              ("edges 20 um (both samples)", max(near[edge].mean(), near2[edge2].mean()) <= 20),
              ("shapes 30 um (both samples)", max(np.nanmean(region), np.nanmean(region48)) <= 30)]
        lines.append(
            f"| {r['family']} | {r['reader']} | {near[~edge].mean():.1f} ({near[~edge].max():.1f}) | "
            f"{near[edge].mean():.1f} | {near2[~edge2].mean():.1f} ({near2[~edge2].max():.1f}) / "
            f"{near2[edge2].mean():.1f} ({near2[edge2].max():.1f}) | "
            f"{r['mesh'].mean():.1f} ({r['mesh'].max():.1f}) | "
            f"{np.nanmean(region):.1f} ({np.nanmax(region):.1f}) | "
            f"{np.nanmean(region48):.1f} ({np.nanmax(region48):.1f}) | "
            f"{np.nanmean(r['shape48']['region_in_view']):.1f} | "
            f"{r['cal']['held-out shape error mean (um)']:.1f} / "
            f"{r['cal']['held-out shape error worst (um)']:.1f} | "
            + ", ".join(f"{n}: {'met' if v else '**not met**'}" for n, v in ok) + " |")
    lines += ["", f"Per shape, the {SECOND_SHAPE_SAMPLE}-press sample (contact-region RMSE, mean of the "
              "shape's presses, um; worst four):", ""]
    for r in results:
        per = {}
        for n_, e in zip(r["shape48_names"], r["shape48"]["region"]):
            per.setdefault(n_, []).append(e)
        worst = sorted(((np.nanmean(v), k) for k, v in per.items()), reverse=True)[:4]
        lines.append(f"* {r['family']}, {r['reader']}: "
                     + ", ".join(f"{k} {v:.0f}" for v, k in worst))
    lines += ["", "Time: " + "; ".join(
        f"{r['family']} ({r['reader']}): surface operators {r['t_prepare']:.0f} s (once, cached), "
        f"calibration {r['t_cal']:.0f} s" for r in results) + "."]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", default="gelsight_mini,digit")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.families.split(","):
            results += family_bench(name.strip(), Path(tmp))
            print(markdown(results), flush=True)
    text = markdown(results)
    print(text)
    if not args.no_write:
        from bench.report import write_section

        write_section("families", text)
        print("\nwrote the families section of BENCHMARKS.md")


if __name__ == "__main__":
    main()
