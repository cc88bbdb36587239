"""Build the shipped sensor plugins ``gelslim1`` and ``gelslim2`` from the virtual sensors.

    python plugins/build_shipped.py [--only gelslim2] [--model exported/gelslim_mesh.onnx]
                                    [--overwrite]
    python plugins/build_shipped.py --relink-model     # after the family model is re-exported

The calibration wizard (``tactile-deploy calibrate --sensor NEW``, docs/calibration.md) makes the
same files from a real sensor; this script makes them from the shipped virtual sensors of the same
names (``tactile_deploy.sensors``: the contact
FEM of the pad, RGB optics, the unit's effects and noise). What is taken from the virtual sensor
and what is calibrated:

* **Camera mapping**: the virtual camera's own lens and homography (a real sensor's comes from
  ``tactile-deploy calibrate camera``). Its imaging grid is the largest box of whole model-grid
  cells (+-17.5 mm, 128 x 128, 0.273 mm) that the camera sees, trimmed to fast transform sizes:
  the GelSlim cameras see about 24 x 18 mm of the 35 mm pad (90 x 64 cells); the pipeline puts
  that depth into the model grid and leaves the unseen cells at 0. (Half the pitch, 180 x 128
  cells, was measured too: the same depth error on held-out presses, 3 x the imaging time.)
* **Reference frame**: the mean of 16 noisy no-contact frames.
* **Shading model**: fitted as on a real sensor (``calibration.shading.fit``) on 80 presses of a
  3 mm ball at random places and depths in the view, rectified by the runtime's own stages; the
  circles come from the ball centre the sensor reached and the FEM contact area (sensing nodes
  within 10 um of the ball). 16 more presses are
  held out: their depth error against the virtual sensor's true surface (area-averaged onto the
  model grid) is recorded in the manifest's provenance.
* **Noise reference**: the mean model-grid depth of 16 noisy no-contact frames (``subtract``).
* **Material**: the E and nu the virtual sensor's FEM uses.
* **Demo clip**: 60 frames (2 s at 30 fps) of an indenter pressing, sliding (and turning) and
  lifting, stored as MJPEG (``demo.avi``, a few kB per frame); the depth error the compression
  adds is recorded in the provenance.
* **Model**: the family's ONNX model (``--model``), referenced by relative path and sha256; the
  topology file is the pad's.

Everything is seeded: the same code and sensors give the same plugins. An existing plugin is only
replaced with ``--overwrite``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

HERE = Path(__file__).resolve().parent
DEFAULT_MODEL = ROOT / "exported" / "gelslim_mesh.onnx"
BALL_RADIUS_MM = 3.0
BALL_DEPTH_MM = (0.3, 0.9)
N_CALIBRATION = 80
N_HELD_OUT = 16
#: Imaging grid pitch = model pitch / this (2 was measured: same accuracy, 3 x slower).
PITCH_DIVISOR = 1
N_DEMO = 60
#: Shading fit settings (``calibration.shading.fit.ShadingFitConfig``): a coarser position grid
#: and fewer colour bins than the defaults keep the table (and the plugin) to a few MB.
SHADING_BINS = 32
SHADING_NODE_SPACING_MM = 3.0


@dataclass(frozen=True)
class DemoMove:
    """A demo clip: ``indenter`` pressed to ``depth_mm`` at ``start_mm``, slid (and turned) to
    ``end_mm``, lifted (sensor frame, mm, degrees)."""

    indenter: str
    start_mm: tuple[float, float]
    end_mm: tuple[float, float]
    depth_mm: float
    theta_deg: tuple[float, float] = (0.0, 0.0)


DEMOS = {
    "gelslim1": DemoMove("cross", (-4.0, 2.0), (4.0, -2.0), 0.6, (0.0, 45.0)),
    "gelslim2": DemoMove("sphere_r6", (-5.0, 2.5), (5.0, -2.0), 0.9),
}
SEEDS = {"gelslim1": 11, "gelslim2": 12}


# ------------------------------------------------------------------------------------ geometry
def imaging_grid(camera, divisor: int = PITCH_DIVISOR, margin_px: float = 2.0):
    """See :func:`calibration.camera.imaging_grid.imaging_grid` (shared with the wizard)."""
    from calibration.camera.imaging_grid import imaging_grid as _imaging_grid

    return _imaging_grid(camera, divisor, margin_px)


def with_grid(camera, grid):
    """The camera mapping with another output grid (validated)."""
    from calibration.camera.imaging_grid import with_grid as _with_grid

    return _with_grid(camera, grid)


# ------------------------------------------------------------------------------------ presses
class Truth:
    """The virtual sensor's true surface, area-averaged onto the model grid."""

    def __init__(self, sensor):
        from tactile_deploy.imaging.camera_mapping import OutputGrid
        from tactile_deploy.runtime.pipeline import GridResampler

        self.to_model = GridResampler(sensor.renderer.grid, OutputGrid())

    def __call__(self, frame) -> np.ndarray:
        return self.to_model(np.asarray(frame.surface_depth_mm, np.float32))


def ball_presses(sensor, grid, n: int, seed: int, truth: Truth):
    """``n`` ball presses inside ``grid`` (1.2 contact radii from its edge): raw frames,
    circles in imaging-grid px, true model-grid depths."""
    from tactile_deploy.indenters import AnalyticSphere, ContactPose

    ball = AnalyticSphere(BALL_RADIUS_MM)
    rng = np.random.default_rng([seed, 0x62616C6C])
    a_max = math.sqrt(2 * BALL_RADIUS_MM * BALL_DEPTH_MM[1])
    frames, circles, depths = [], [], []
    for i in range(n):
        pose = ContactPose(x_mm=float(rng.uniform(grid.x_min_mm + 1.2 * a_max, grid.x_max_mm - 1.2 * a_max)),
                           y_mm=float(rng.uniform(grid.y_min_mm + 1.2 * a_max, grid.y_max_mm - 1.2 * a_max)),
                           depth_mm=float(rng.uniform(*BALL_DEPTH_MM)))
        out = sensor.press(ball, pose, np.random.default_rng([seed, 1, i]))
        reached = out.pose_reached
        a_mm = contact_radius_mm(sensor, ball, out)
        frames.append(out.frame)
        circles.append(((reached.x_mm - grid.x_min_mm) / grid.pitch_x_mm - 0.5,
                        (grid.y_max_mm - reached.y_mm) / grid.pitch_y_mm - 0.5,
                        a_mm / grid.pitch_x_mm))
        depths.append(truth(out))
    return np.stack(frames), np.array(circles), np.stack(depths)


#: Gel-to-ball gap (mm) below which a sensing node of the deformed mesh counts as in contact.
CONTACT_GAP_MM = 0.01


def contact_radius_mm(sensor, ball, out, gap_mm: float = CONTACT_GAP_MM) -> float:
    """Equivalent contact radius sqrt(area / pi), mm, of a ball press: the lumped area of the
    sensing nodes of the deformed mesh that lie within ``gap_mm`` of the ball's surface."""
    r = out.pose_reached
    mesh = sensor.simulator.mesh
    nodes = mesh.sensing_nodes
    xy = mesh.vertices[nodes, :2]
    uz = out.vertices_mm[nodes, 2] - mesh.vertices[nodes, 2]
    intr = ball.intrusion_mm(xy, r)                 # ball surface at z = -intr
    touching = np.isfinite(intr) & (-intr - uz < gap_mm)
    return math.sqrt(mesh.sensing_nodal_areas_mm2()[touching].sum() / math.pi)


def depth_errors_um(depths, truths, centres_mm, radii_mm) -> dict:
    """The shading calibration's figures on the model grid: whole-frame RMSE, RMSE within 1.5
    contact radii, peak depth error (um); worst over the presses."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid

    g = OutputGrid()
    x = g.x_min_mm + (np.arange(g.nx) + 0.5) * g.pitch_x_mm
    y = g.y_max_mm - (np.arange(g.ny) + 0.5) * g.pitch_y_mm
    whole, near, peak = [], [], []
    for d, t, c, a in zip(depths, truths, centres_mm, radii_mm):
        m = np.hypot(x[None, :] - c[0], y[:, None] - c[1]) < 1.5 * a
        whole.append(np.sqrt(np.mean((d - t) ** 2)) * 1e3)
        near.append(np.sqrt(np.mean((d[m] - t[m]) ** 2)) * 1e3)
        peak.append(abs(float(d.max()) - float(t.max())) * 1e3)
    return {"whole_rmse_um_worst": float(max(whole)), "near_rmse_um_worst": float(max(near)),
            "peak_error_um_worst": float(max(peak)), "near_rmse_um_mean": float(np.mean(near)),
            "n": len(whole)}


def demo_frames(sensor, move: DemoMove, seed: int, n: int = N_DEMO):
    """Rest, press, slide (and turn), lift, rest; (frames, true model-grid depths)."""
    from tactile_deploy.indenters import ContactPose

    n_rest, n_press, n_lift = 4, 12, 10
    n_slide = n - 2 * n_rest - n_press - n_lift
    truth = Truth(sensor)
    frames, depths = [], []
    for i in range(n):
        if i < n_rest or i >= n - n_rest:
            s, depth = (0.0 if i < n_rest else 1.0), 0.0
        elif i < n_rest + n_press:
            s, depth = 0.0, move.depth_mm * (i - n_rest + 1) / n_press
        elif i < n_rest + n_press + n_slide:
            s, depth = (i - n_rest - n_press) / max(n_slide - 1, 1), move.depth_mm
        else:
            k = i - n_rest - n_press - n_slide
            s, depth = 1.0, move.depth_mm * (1 - (k + 1) / (n_lift + 1))
        pose = ContactPose(x_mm=move.start_mm[0] + s * (move.end_mm[0] - move.start_mm[0]),
                           y_mm=move.start_mm[1] + s * (move.end_mm[1] - move.start_mm[1]),
                           theta_deg=move.theta_deg[0] + s * (move.theta_deg[1] - move.theta_deg[0]),
                           depth_mm=depth)
        out = sensor.press(move.indenter, pose, np.random.default_rng([seed, 2, i]))
        frames.append(out.frame)
        depths.append(truth(out))
    return np.stack(frames), np.stack(depths)


# ------------------------------------------------------------------------------------ build
def build(name: str, folder: Path, model: Path, overwrite: bool) -> dict:
    import cv2

    from calibration.shading.fit import fit_shading
    from calibration.shading.presses import PressSet
    from tactile_deploy.atomic import atomic_path
    from tactile_deploy.imaging.shading import save_shading
    from tactile_deploy.runtime.pipeline import ImagingPipeline, Rectifier, rectify_frame, resample_to_grid
    from tactile_deploy.runtime.plugins import MANIFEST_NAME, validate_plugin, write_plugin
    from tactile_deploy.runtime.predictor import MeshTopology
    from tactile_deploy.runtime.sources.factory import open_clip
    from tactile_deploy.runtime.sources.video import write_video
    from tactile_deploy.sensors import load_sensor

    if (folder / MANIFEST_NAME).exists() and not overwrite:
        raise SystemExit(f"{folder / MANIFEST_NAME} exists; pass --overwrite to rebuild it")
    if not model.is_file():
        raise SystemExit(f"the family model {model} does not exist: export it first "
                         "(python -m training export ...) or pass --model")
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    seed = SEEDS[name]
    sensor = load_sensor(name)
    sensor.prepare()
    grid = imaging_grid(sensor.optics.camera)
    camera = with_grid(sensor.optics.camera, grid)
    rectifier = Rectifier(camera)

    def rectify(frame):
        return resample_to_grid(rectify_frame(frame, rectifier), rectifier)

    reference = sensor.record_reference(seed, n_average=16)
    truth = Truth(sensor)

    # shading: fit on N_CALIBRATION presses, evaluate on N_HELD_OUT others (new places, noise)
    raw, circles, _ = ball_presses(sensor, grid, N_CALIBRATION, seed, truth)
    train = PressSet(rectify(reference), np.stack([rectify(f) for f in raw]),
                     [f"press_{i:03d}" for i in range(N_CALIBRATION)], circles)
    from calibration.shading.fit import ShadingFitConfig

    fit = fit_shading(train, BALL_RADIUS_MM, grid.pitch_x_mm,
                      ShadingFitConfig(bins=SHADING_BINS, node_spacing_mm=SHADING_NODE_SPACING_MM))
    save_shading(fit.model, folder / "shading.npz")
    with atomic_path(folder / "reference.png") as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(reference, cv2.COLOR_RGB2BGR))
    plain = ImagingPipeline(camera, fit.model, reference, None, "keep")
    h_raw, h_circ, h_true = ball_presses(sensor, grid, N_HELD_OUT, seed + 1000, truth)
    centres = np.stack([grid.x_min_mm + (h_circ[:, 0] + 0.5) * grid.pitch_x_mm,
                        grid.y_max_mm - (h_circ[:, 1] + 0.5) * grid.pitch_y_mm], 1)
    held_err = depth_errors_um([plain.frame_to_depth(f) for f in h_raw], h_true, centres,
                               h_circ[:, 2] * grid.pitch_x_mm)

    # noise reference: mean model-grid depth of 16 noisy no-contact frames
    noise = np.mean([plain.frame_to_depth(sensor.reference_frame(np.random.default_rng([seed, 3, i])))
                     for i in range(16)], axis=0)
    np.save(folder / "noise_reference.npy", noise.astype(np.float32))

    # demo clip (MJPEG) and the depth error its compression adds
    move = DEMOS[name]
    demo, demo_truth = demo_frames(sensor, move, seed)
    demo_depth = [plain.frame_to_depth(f) for f in demo]
    deep = int(np.argmax(demo_truth.max(axis=(1, 2))))
    demo_err = {"rmse_um_worst": float(max(np.sqrt(np.mean((d - t) ** 2)) * 1e3
                                           for d, t in zip(demo_depth, demo_truth))),
                "deepest_true_mm": float(demo_truth[deep].max()),
                "deepest_estimated_mm": float(demo_depth[deep].max())}
    write_video(folder / "demo.avi", demo, fps=sensor.config.fps, fourcc="MJPG")
    with open_clip(folder / "demo.avi") as src:
        decoded = np.stack([f.image for f in src])
    codec = [np.sqrt(np.mean((plain.frame_to_depth(a) - plain.frame_to_depth(b)) ** 2)) * 1e3
             for a, b in zip(demo, decoded)]
    topo = MeshTopology.from_pad()
    topo.save(folder / "topology.npz")

    mat = sensor.config.material
    fields = {
        "name": name,
        "description": (sensor.config.description.split(":")[0].strip()
                        + " (the virtual sensor of this name)"),
        "family": {"name": "gelslim", "pad": sensor.config.pad, "pad_version": 1,
                   "mesh_hash": topo.mesh_hash},
        "camera": json.loads(camera.model_dump_json()),
        "material": {"E_mpa": mat.E_mpa, "nu": mat.nu,
                     "source": f"virtual sensor {name}: the E and nu of its FEM"},
        "default_source": {"kind": "demo"},
        "noise_handling": "subtract",
        "provenance": {
            "made_by": "plugins/build_shipped.py from the virtual sensor of the same name "
                       "(the calibration wizard makes these files from a real sensor)",
            "date": _dt.date.today().isoformat(),
            "sensor": repr(sensor),
            "imaging_grid": (f"{grid.nx} x {grid.ny} cells of {grid.pitch_x_mm:.4f} mm over x "
                             f"[{grid.x_min_mm:g}, {grid.x_max_mm:g}], y [{grid.y_min_mm:g}, "
                             f"{grid.y_max_mm:g}] mm (what the camera sees), {rectifier.supersample}"
                             " x supersampled"),
            "shading_fit": (f"{N_CALIBRATION} presses of a {BALL_RADIUS_MM:g} mm ball, depth "
                            f"{BALL_DEPTH_MM[0]}-{BALL_DEPTH_MM[1]} mm; in-sample sphere RMS "
                            f"{fit.model.header.fit_metrics.get('in_sample_sphere_rms_um', float('nan')):.1f} um"),
            "held_out_depth_error": (
                f"{held_err['n']} presses against the true surface on the model grid: whole "
                f"frame RMSE <= {held_err['whole_rmse_um_worst']:.1f} um, within 1.5 contact "
                f"radii <= {held_err['near_rmse_um_worst']:.1f} um (mean "
                f"{held_err['near_rmse_um_mean']:.1f}), peak <= {held_err['peak_error_um_worst']:.1f} um"),
            "demo_clip": (f"{N_DEMO} frames, {move.indenter} pressed {move.depth_mm} mm, slid "
                          f"{move.start_mm} -> {move.end_mm} mm; MJPEG adds depth RMSE <= "
                          f"{max(codec):.1f} um per frame"),
            "demo_depth_error": (f"frame RMSE <= {demo_err['rmse_um_worst']:.1f} um; deepest "
                                 f"frame {demo_err['deepest_estimated_mm']:.3f} mm estimated, "
                                 f"{demo_err['deepest_true_mm']:.3f} mm true"),
        },
    }
    files = {"model": model, "shading": folder / "shading.npz",
             "reference_frame": folder / "reference.png",
             "noise_reference": folder / "noise_reference.npy", "demo_clip": folder / "demo.avi",
             "topology": folder / "topology.npz"}
    write_plugin(folder, fields, files, overwrite=overwrite)
    report = validate_plugin(folder)
    if not report.ok:
        raise SystemExit(f"built plugin {folder} does not validate:\n" + "\n".join(report.problems))
    return {"plugin": name, "seconds": round(time.perf_counter() - t0, 1), "held_out": held_err,
            "demo": demo_err,
            "codec_rmse_um_worst": float(max(codec)), "imaging_grid": [grid.nx, grid.ny],
            "size_mb": round(sum(p.stat().st_size for p in folder.iterdir()) / 1e6, 2)}


def relink_model(folder: Path, model: Path) -> dict:
    """Point an existing plugin at a re-exported family model: check the model's contract and
    mesh hash, then record its path and sha256 in ``plugin.json`` (nothing else changes)."""
    import os

    from tactile_deploy.atomic import write_json
    from tactile_deploy.runtime.plugins import MANIFEST_NAME, PluginManifest, file_sha256, load_manifest
    from tactile_deploy.runtime.predictor import check_model_contract

    manifest = load_manifest(folder)
    check_model_contract(model, manifest.family.mesh_hash, what=f"model for {manifest.name}")
    doc = json.loads((folder / MANIFEST_NAME).read_text())
    doc["model"] = {"path": Path(os.path.relpath(model, folder.resolve())).as_posix(),
                    "sha256": file_sha256(model)}
    write_json(folder / MANIFEST_NAME, PluginManifest.model_validate(doc).model_dump(mode="json"))
    return {"plugin": manifest.name, "model": doc["model"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=sorted(DEMOS), help="build one plugin")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="the family ONNX model")
    ap.add_argument("--out", type=Path, default=HERE, help="folder of plugin folders")
    ap.add_argument("--overwrite", action="store_true", help="replace existing plugins")
    ap.add_argument("--relink-model", action="store_true",
                    help="only point existing plugins at --model (after a re-export)")
    args = ap.parse_args(argv)
    for name in ([args.only] if args.only else sorted(DEMOS)):
        if args.relink_model:
            print(json.dumps(relink_model(args.out / name, args.model.resolve()), indent=2))
            continue
        info = build(name, args.out / name, args.model.resolve(), args.overwrite)
        print(json.dumps(info, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
