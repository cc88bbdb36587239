"""Build the shipped sensor plugins ``gelslim1`` and ``gelslim2``: the calibration wizard on the
virtual sensors of the same names, plus a demo clip.

    python plugins/build_shipped.py [--only gelslim2] [--model exported/gelslim_mesh.onnx]
                                    [--overwrite] [--work DIR]
    python plugins/build_shipped.py --relink-model     # after the family model is re-exported
    python plugins/build_shipped.py --shading-model    # plugins that read frames with the
                                                       # shading model instead of the learned
                                                       # read-out (faster, less accurate)

Each plugin is made by ``tactile-deploy calibrate`` (:func:`tactile_deploy.calibration.wizard.wizard.run_wizard`,
docs/calibration.md), run non-interactively with the committed config ``plugins/wizard/NAME.json``
on the virtual sensor ``NAME`` (``tactile_deploy.sensors``: the contact FEM of the pad, RGB
optics, the unit's effects and noise) pressed by the simulated rig over pseudo-terminals, exactly
as it calibrates a real sensor on a rig:

* **reference** and **noise reference**: 16 no-contact frames averaged; their mean depth;
* **camera mapping**: fitted from the pressed dot target (9 x 7 pins at 2.5 mm), and the imaging
  grid (the largest box of whole model-grid cells the camera sees: 90 x 64 cells for the
  GelSlim cameras);
* **shading model**: fitted on 80 ball presses (3 mm ball, 0.3-0.9 mm deep) over the view,
  cross-validated;
* **learned read-out**: the GelSlim design's network (``exported/gelslim_readout.onnx``, the
  configs' ``readout``; not fine-tuned: ``readout_steps`` 0) reads the frames, with the unit's
  depth gain from the rig's presses; the shading model stays in the plugin (``--shading-model``
  builds plugins that read frames with it);
* **material**: E from the rig's forces (nu fixed at 0.48), with the rig's depth zero error;
* **model**: the family's ONNX model (``--model``), referenced by relative path and sha256
  (``copy_model: false``: one copy in ``exported/`` for every shipped plugin); the topology file
  is the pad's; the wizard's report is in ``calibration/`` (its pictures with a 256-colour
  palette, to keep the plugin near 2 MB).

What this script adds to the wizard's folder:

* **demo clip**: 60 frames (2 s at 30 fps) of an indenter pressing, sliding (and turning) and
  lifting (:data:`DEMOS`), stored as MJPEG (``demo.avi``), replacing the wizard's clip of the
  calibration presses; it is the plugin's default source, so ``tactile-deploy run --sensor
  gelslim2`` works without a sensor. The depth error the compression adds is recorded;
* **held-out check**: 16 new ball presses (places, depths and noise the wizard never saw) through
  the plugin's own imaging pipeline against the virtual sensor's true surface on the model grid
  (area-averaged), recorded in the manifest's ``provenance`` with the demo clip's depth error.

Everything is seeded (the configs' ``presses.seed``, :data:`SEEDS`): the same code and sensors
give the same plugins. The plugin is assembled beside its target (``plugins/.NAME-build``) and
renamed into place after it validates; an existing plugin is only replaced with ``--overwrite``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import json
import math
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

HERE = Path(__file__).resolve().parent
DEFAULT_MODEL = ROOT / "exported" / "gelslim_mesh.onnx"
#: The wizard config of each shipped plugin.
WIZARD_CONFIGS = HERE / "wizard"
BALL_RADIUS_MM = 3.0
BALL_DEPTH_MM = (0.3, 0.9)
N_HELD_OUT = 16
N_DEMO = 60


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
#: Seeds of the held-out presses and the demo clip.
SEEDS = {"gelslim1": 11, "gelslim2": 12}


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
def run_wizard_on_virtual(name: str, out: Path, work: Path, model: Path,
                          readout: Path | None = None, shading_only: bool = False) -> None:
    """``tactile-deploy calibrate --sensor NAME --source virtual:NAME --rig simulated --yes
    --config plugins/wizard/NAME.json --out OUT --work WORK --model MODEL --overwrite``, the
    config's ``readout`` set to ``readout`` when given, or removed with ``shading_only``."""
    from tactile_deploy.calibration.wizard.config import load_wizard_config
    from tactile_deploy.calibration.wizard.ui import AutoUI
    from tactile_deploy.calibration.wizard.wizard import EXIT_OK, run_wizard

    config = load_wizard_config(WIZARD_CONFIGS / f"{name}.json")
    if shading_only:
        config = config.model_copy(update={"readout": None})
    elif readout is not None:   # recorded relative to the checkout (the wizard runs from there)
        config = config.model_copy(update={"readout": Path(os.path.relpath(readout, ROOT)).as_posix()})
    with contextlib.chdir(ROOT):
        code = run_wizard(name, source=f"virtual:{name}", rig="simulated", gauge=None,
                          config=config, out=out.resolve(), work=work.resolve(), ui=AutoUI(),
                          overwrite=True, model=model)
    if code != EXIT_OK:
        raise SystemExit(f"the calibration wizard failed on virtual:{name} (exit code {code}); "
                         f"its work folder is {work}")


def held_out_errors(plugin, sensor, seed: int) -> dict:
    """:func:`depth_errors_um` of :data:`N_HELD_OUT` new ball presses through the plugin's
    imaging pipeline."""
    from tactile_deploy.runtime.pipeline import ImagingPipeline

    grid = plugin.manifest.camera.grid
    raw, circ, true = ball_presses(sensor, grid, N_HELD_OUT, seed + 1000, Truth(sensor))
    pipeline = ImagingPipeline.from_plugin(plugin)
    centres = np.stack([grid.x_min_mm + (circ[:, 0] + 0.5) * grid.pitch_x_mm,
                        grid.y_max_mm - (circ[:, 1] + 0.5) * grid.pitch_y_mm], 1)
    return depth_errors_um([pipeline.frame_to_depth(f) for f in raw], true, centres,
                           circ[:, 2] * grid.pitch_x_mm)


def add_demo_clip(plugin, sensor, move: DemoMove, seed: int, path: Path) -> dict:
    """Write the demo clip (MJPEG) to ``path``; returns its depth error and what the
    compression adds (um), measured through the plugin's imaging pipeline."""
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.sources.factory import open_clip
    from tactile_deploy.runtime.sources.video import write_video

    pipeline = ImagingPipeline.from_plugin(plugin)
    frames, true = demo_frames(sensor, move, seed)
    depth = [pipeline.frame_to_depth(f) for f in frames]
    deep = int(np.argmax(true.max(axis=(1, 2))))
    write_video(path, frames, fps=sensor.config.fps, fourcc="MJPG")
    with open_clip(path) as src:
        decoded = np.stack([f.image for f in src])
    codec = [np.sqrt(np.mean((pipeline.frame_to_depth(a) - d) ** 2)) * 1e3
             for a, d in zip(decoded, depth)]
    return {"rmse_um_worst": float(max(np.sqrt(np.mean((d - t) ** 2)) * 1e3
                                       for d, t in zip(depth, true))),
            "deepest_true_mm": float(true[deep].max()),
            "deepest_estimated_mm": float(depth[deep].max()),
            "codec_rmse_um_worst": float(max(codec))}


def compact_report_pictures(folder: Path) -> None:
    """Re-encode the report's PNG pictures (``folder``) with a 256-colour palette: about a third
    of the size, keeping each shipped plugin near 2 MB."""
    from PIL import Image

    from tactile_deploy.atomic import atomic_path

    for path in sorted(folder.glob("*.png")):
        with Image.open(path) as im:
            small = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT,
                                               dither=Image.Dither.NONE)
        with atomic_path(path) as tmp:
            small.save(tmp, format="PNG", optimize=True)


def build(name: str, folder: Path, model: Path, overwrite: bool, work: Path | None = None,
          readout: Path | None = None, shading_only: bool = False) -> dict:
    """Make the shipped plugin ``name`` in ``folder`` (see the module docstring); ``readout``
    replaces the config's learned read-out, ``shading_only`` drops it."""
    from tactile_deploy.atomic import replace_folder
    from tactile_deploy.runtime.plugins import (
        MANIFEST_NAME,
        SensorPlugin,
        validate_plugin,
        write_plugin,
    )
    from tactile_deploy.sensors import load_sensor

    if (folder / MANIFEST_NAME).exists() and not overwrite:
        raise SystemExit(f"{folder / MANIFEST_NAME} exists; pass --overwrite to rebuild it")
    if not model.is_file():
        raise SystemExit(f"the family model {model} does not exist: export it first "
                         "(python -m tactile_deploy.training export ...) or pass --model")
    t0 = time.perf_counter()
    # assembled beside the target: the model's relative path stays valid after the rename
    staging = folder.parent / f".{folder.name}-build"
    if staging.exists():
        shutil.rmtree(staging)
    with tempfile.TemporaryDirectory(prefix=f"{name}-calibration-") as tmp:
        run_wizard_on_virtual(name, staging, work or Path(tmp) / "work", model, readout,
                              shading_only)
    try:
        plugin = SensorPlugin.load(staging)
        sensor = load_sensor(name)
        sensor.prepare()
        seed = SEEDS[name]
        held = held_out_errors(plugin, sensor, seed)
        move = DEMOS[name]
        demo = add_demo_clip(plugin, sensor, move, seed, staging / "demo.avi")
        compact_report_pictures(staging / "calibration")

        m = plugin.manifest
        fields = m.model_dump(mode="json", exclude=set(m.files()) | {"noise_reference"})
        fields["noise_handling"] = m.noise_reference.handling
        fields["default_source"] = {"kind": "demo"}
        prov = dict(m.provenance)
        prov.update({
            "made_by": (f"tactile-deploy calibrate (the calibration wizard) on the virtual sensor "
                        f"{name} with the simulated rig, config plugins/wizard/{name}.json, run by "
                        "plugins/build_shipped.py, which adds the demo clip and the held-out "
                        "check"),
            "date": _dt.date.today().isoformat(),
            "sensor": repr(sensor),
            "held_out_depth_error": (
                f"{held['n']} new presses against the true surface on the model grid: whole "
                f"frame RMSE <= {held['whole_rmse_um_worst']:.1f} um, within 1.5 contact radii "
                f"<= {held['near_rmse_um_worst']:.1f} um (mean {held['near_rmse_um_mean']:.1f}), "
                f"peak <= {held['peak_error_um_worst']:.1f} um"),
            "demo_clip": (f"{N_DEMO} frames, {move.indenter} pressed {move.depth_mm} mm, slid "
                          f"{move.start_mm} -> {move.end_mm} mm; MJPEG adds depth RMSE <= "
                          f"{demo['codec_rmse_um_worst']:.1f} um per frame"),
            "demo_depth_error": (f"frame RMSE <= {demo['rmse_um_worst']:.1f} um; deepest frame "
                                 f"{demo['deepest_estimated_mm']:.3f} mm estimated, "
                                 f"{demo['deepest_true_mm']:.3f} mm true"),
        })
        fields["provenance"] = prov
        files = {k: plugin.path_of(k) for k in m.files()}
        files["demo_clip"] = staging / "demo.avi"
        write_plugin(staging, fields, files, overwrite=True)
        report = validate_plugin(staging)
        if not report.ok:
            raise SystemExit(f"built plugin {staging} does not validate:\n"
                             + "\n".join(report.problems))
        replace_folder(staging, folder)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    return {"plugin": name, "seconds": round(time.perf_counter() - t0, 1), "held_out": held,
            "demo": demo, "material": json.loads(m.material.model_dump_json()),
            "imaging_grid": [m.camera.grid.nx, m.camera.grid.ny],
            "size_mb": round(size / 1e6, 2)}


def relink_model(folder: Path, model: Path) -> dict:
    """Point an existing plugin at a re-exported family model: check the model's contract and
    mesh hash, then record its path and sha256 in ``plugin.json`` (nothing else changes)."""
    from tactile_deploy.atomic import write_json
    from tactile_deploy.runtime.plugins import MANIFEST_NAME, PluginManifest, load_manifest
    from tactile_deploy.checksums import file_sha256
    from tactile_deploy.onnx_runtime.contract import check_model_contract

    manifest = load_manifest(folder)
    check_model_contract(model, manifest.family.mesh_hash, what=f"model for {manifest.name}")
    doc = json.loads((folder / MANIFEST_NAME).read_text())
    doc["model"] = {"path": Path(os.path.relpath(model, folder.resolve())).as_posix(),
                    "sha256": file_sha256(model)}
    write_json(folder / MANIFEST_NAME, PluginManifest.model_validate(doc).model_dump(mode="json"))
    return {"plugin": manifest.name, "model": doc["model"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Build the shipped sensor plugins with the "
                                 "calibration wizard on the virtual sensors of the same names.")
    ap.add_argument("--only", choices=sorted(DEMOS), help="build one plugin")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="the family ONNX model")
    ap.add_argument("--out", type=Path, default=HERE, help="folder of plugin folders")
    ap.add_argument("--overwrite", action="store_true", help="replace existing plugins")
    ap.add_argument("--work", type=Path, help="keep the wizard's work folders here "
                    "(WORK/NAME.calibration; default: a temporary folder)")
    read = ap.add_mutually_exclusive_group()
    read.add_argument("--readout", type=Path, default=None,
                      help="another learned read-out file than the configs' "
                      "(exported/gelslim_readout.onnx)")
    read.add_argument("--shading-model", action="store_true",
                      help="read frames with the shading model (no learned read-out): faster, "
                      "less accurate (docs/shading.md)")
    ap.add_argument("--relink-model", action="store_true",
                    help="only point existing plugins at --model (after a re-export)")
    args = ap.parse_args(argv)
    for name in ([args.only] if args.only else sorted(DEMOS)):
        if args.relink_model:
            print(json.dumps(relink_model(args.out / name, args.model.resolve()), indent=2))
            continue
        work = args.work / f"{name}.calibration" if args.work else None
        readout = None if args.readout is None else args.readout.resolve()
        if readout is not None and not readout.is_file():
            raise SystemExit(f"the learned read-out {readout} does not exist: train it "
                             "(python -m tactile_deploy.training.shading_net)")
        info = build(name, args.out / name, args.model.resolve(), args.overwrite, work, readout,
                     args.shading_model)
        print(json.dumps(info, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
