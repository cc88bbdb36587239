"""Build the shipped sensor plugins ``gelslim1`` and ``gelslim2`` from virtual sensors.

    python plugins/build_shipped.py [--only gelslim2] [--model exported/gelslim_mesh.onnx]
                                    [--overwrite] [--check-only]

What is simulated and what is calibrated, per plugin:

* **The sensor** is virtual: the contact FEM of the GelSlim pad (``ContactSimulator``, the
  sensor's E and nu) deforms the gel under an indenter; the surface seen by the camera is the
  deformed pad rendered at 0.1 mm by the depth camera, with the indenter's non-penetration floor
  restoring what the 1 mm mesh smooths (``depth_detail`` of the simulator); the RGB optics
  (``tactile_deploy.optics``: three coloured LEDs, ambient light, vignetting, gel texture, blur,
  shot and read noise, 8-bit) turn it into 640 x 480 camera frames through the sensor's lens and
  homography. The two sensors differ in lens, scale, rotation, mirror, lights, noise and E.
* **The camera mapping** is the virtual camera's own (the calibration wizard estimates it with a
  ChArUco board or pressed dots, docs/camera_mapping.md).
* **The shading model** is fitted as on a real sensor (``calibration.shading.fit``): 80 presses
  of a 4 mm ball at random places and depths, rectified onto the 128 x 128 model grid, with the
  ball's known centre and the FEM contact radius as circles. 16 more presses are held out: their
  depth error against the true surface is recorded in the manifest's provenance.
* **The noise reference** is the mean depth of 16 noisy no-contact frames (``subtract``).
* **The demo clip** is 60 frames of a simulated indenter pressing, sliding and lifting, stored
  as MJPEG (``demo.avi``, about 7 kB per frame); the depth error the compression adds is
  recorded in the provenance.
* **The model** is the family's ONNX model (``--model``, default ``exported/gelslim_mesh.onnx``),
  referenced by relative path and checksum; the topology file is the pad's.

Everything is seeded: the same code gives the same plugins. A folder that already holds a
plugin is only replaced with ``--overwrite``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

HERE = Path(__file__).resolve().parent
DEFAULT_MODEL = ROOT / "exported" / "gelslim_mesh.onnx"
#: Calibration ball (the 4 mm sphere of the indenter library), its presses.
BALL = "sphere_r4"
BALL_RADIUS_MM = 4.0
N_CALIBRATION = 80
N_HELD_OUT = 16
#: Grid of the surface the optics shade: +-24 mm at 0.1 mm (covers the camera's view).
SURFACE_HALF_MM = 24.0
SURFACE_RES = 480


@dataclass(frozen=True)
class DemoMove:
    """One demo clip: an indenter pressed to ``depth_mm`` at ``start``, slid to ``end``."""

    indenter: str
    start_mm: tuple[float, float]
    end_mm: tuple[float, float]
    depth_mm: float
    theta_deg: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class VirtualSensor:
    """Parameters of one virtual GelSlim (lengths mm, angles degrees, intensities grey levels)."""

    name: str
    description: str
    mm_per_px: float
    k1: float
    rotation_deg: float
    mirrored: bool
    light_azimuths_deg: tuple[float, float, float]
    light_elevation_deg: float
    light_grey: float
    ambient_grey: float
    vignetting_k2: float
    blur_sigma_px: float
    read_noise_grey: float
    conversion_gain: float
    texture_rms: float
    E_mpa: float
    nu: float
    seed: int
    demo: DemoMove
    extra: dict = field(default_factory=dict)


SENSORS = {
    "gelslim1": VirtualSensor(
        name="gelslim1", description="GelSlim-class sensor, virtual unit 1 (barrel lens, "
        "0.075 mm/px, one fold mirror)",
        mm_per_px=0.075, k1=-0.08, rotation_deg=1.5, mirrored=False,
        light_azimuths_deg=(90.0, 210.0, 330.0), light_elevation_deg=35.0, light_grey=130.0,
        ambient_grey=45.0, vignetting_k2=-0.15, blur_sigma_px=0.6, read_noise_grey=1.0,
        conversion_gain=0.02, texture_rms=0.01, E_mpa=0.30, nu=0.48, seed=1,
        demo=DemoMove("cross", (-5.0, 4.0), (5.0, -3.0), 0.6, (0.0, 60.0))),
    "gelslim2": VirtualSensor(
        name="gelslim2", description="GelSlim-class sensor, virtual unit 2 (stronger lens "
        "distortion, 0.078 mm/px, mirrored view)",
        mm_per_px=0.078, k1=-0.12, rotation_deg=-2.0, mirrored=True,
        light_azimuths_deg=(80.0, 200.0, 320.0), light_elevation_deg=32.0, light_grey=125.0,
        ambient_grey=50.0, vignetting_k2=-0.2, blur_sigma_px=0.7, read_noise_grey=1.2,
        conversion_gain=0.025, texture_rms=0.015, E_mpa=0.25, nu=0.48, seed=2,
        demo=DemoMove("sphere_r6", (-6.0, 3.0), (6.0, -2.0), 0.9)),
}


# ------------------------------------------------------------------------------------ the sensor
class Simulation:
    """A virtual sensor: FEM contact -> fine surface -> RGB frame."""

    def __init__(self, spec: VirtualSensor):
        from tactile_deploy.camera.depth import DepthCamera
        from tactile_deploy.fem.material import Material
        from tactile_deploy.imaging.camera_mapping import OutputGrid
        from tactile_deploy.optics import (
            GelTexture,
            Light,
            OpticsModel,
            OpticsRenderer,
            SensorNoise,
            Vignetting,
            simple_camera,
        )
        from tactile_deploy.simulation.contact import get_simulator

        self.spec = spec
        camera = simple_camera(640, 480, spec.mm_per_px, k1=spec.k1,
                               rotation_deg=spec.rotation_deg, mirrored=spec.mirrored)
        colours = [(1.0, 0.09, 0.06), (0.08, 1.0, 0.12), (0.06, 0.11, 1.0)]
        lights = tuple(
            Light(name=n, azimuth_deg=az, elevation_deg=spec.light_elevation_deg,
                  colour_grey=tuple(spec.light_grey * c for c in col))
            for n, az, col in zip(("red", "green", "blue"), spec.light_azimuths_deg, colours))
        self.optics = OpticsModel(
            camera=camera, lights=lights, ambient_grey=(spec.ambient_grey,) * 3,
            vignetting=Vignetting(k2=spec.vignetting_k2), blur_sigma_px=spec.blur_sigma_px,
            noise=SensorNoise(read_noise_grey=spec.read_noise_grey,
                              conversion_gain_grey_per_e=spec.conversion_gain),
            texture=GelTexture(rms=spec.texture_rms, seed=spec.seed))
        fine = OutputGrid(x_min_mm=-SURFACE_HALF_MM, x_max_mm=SURFACE_HALF_MM,
                          y_min_mm=-SURFACE_HALF_MM, y_max_mm=SURFACE_HALF_MM,
                          nx=SURFACE_RES, ny=SURFACE_RES)
        self.renderer = OpticsRenderer(self.optics, grid=fine, noise_seed=spec.seed)
        self.material = Material(E_mpa=spec.E_mpa, nu=spec.nu)
        self.sim = get_simulator(self.material)
        self.fine_camera = DepthCamera(SURFACE_HALF_MM, SURFACE_RES)
        self.model_camera = DepthCamera(17.5, 128)
        self.rng = np.random.default_rng(spec.seed)

    def _surface(self, camera, indenter, pose, vertices):
        img = camera.render(self.sim.mesh, vertices)
        xy = camera.pixel_centres_mm().reshape(-1, 2)
        floor = np.maximum(indenter.intrusion_mm(xy, pose).reshape(img.depth_mm.shape), 0.0)
        return np.where(img.mask, np.maximum(img.depth_mm, floor), 0.0).astype(np.float32)

    def press(self, indenter, pose):
        """(frame (480, 640, 3) uint8 RGB, true depth (128, 128) mm on the model grid,
        contact result) of ``indenter`` at ``pose``; no contact when pose.depth_mm <= 0."""
        if pose.depth_mm <= 0:
            return self.reference(), np.zeros((128, 128), np.float32), None
        res = self.sim.solve(indenter, pose)
        fine = self._surface(self.fine_camera, indenter, pose, res.vertices_mm)
        truth = self._surface(self.model_camera, indenter, pose, res.vertices_mm)
        return self.renderer.render(-fine, self.rng), truth, res

    def reference(self):
        return self.renderer.reference_frame(self.rng)


# ------------------------------------------------------------------------------------ steps
def calibration_presses(simu: Simulation, n: int, rng, rectify):
    """Ball presses: raw frames, frames rectified by ``rectify`` (the runtime's stages),
    circles (model-grid px), true depths (model grid, mm)."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.indenters import ContactPose, get_indenter

    p = OutputGrid().pitch_x_mm
    ball = get_indenter(BALL)
    areas = simu.sim.mesh.sensing_nodal_areas_mm2()
    frames, circles, truths, raw = [], [], [], []
    for _ in range(n):
        r, th = rng.uniform(0.0, 12.0), rng.uniform(0.0, 2 * np.pi)
        x, y = float(r * np.cos(th)), float(r * np.sin(th))
        pose = ContactPose(x_mm=x, y_mm=y, depth_mm=float(rng.uniform(0.3, 0.9)))
        frame, truth, res = simu.press(ball, pose)
        a_mm = float(np.sqrt((areas * res.contact_mask).sum() / np.pi))
        raw.append(frame)
        frames.append(rectify(frame))
        truths.append(truth)
        circles.append(((x + 17.5) / p - 0.5, (17.5 - y) / p - 0.5, a_mm / p))
    return np.stack(raw), np.stack(frames), np.array(circles), np.stack(truths)


def depth_errors_um(depths, truths, circles) -> dict:
    """The shading calibration's figures: whole-frame RMSE, RMSE within 1.5 contact radii,
    peak depth error (um); worst over the presses."""
    rows, cols = np.mgrid[0:128, 0:128]
    whole, near, peak = [], [], []
    for d, t, c in zip(depths, truths, circles):
        m = np.hypot(cols - c[0], rows - c[1]) < 1.5 * c[2]
        whole.append(np.sqrt(np.mean((d - t) ** 2)) * 1e3)
        near.append(np.sqrt(np.mean((d[m] - t[m]) ** 2)) * 1e3)
        peak.append(abs(float(d.max()) - float(t.max())) * 1e3)
    return {"whole_rmse_um_worst": float(max(whole)), "near_rmse_um_worst": float(max(near)),
            "peak_error_um_worst": float(max(peak)), "n": len(whole)}


def demo_frames(simu: Simulation, n: int = 60):
    """The demo clip: rest, press, slide (and turn), lift, rest."""
    from tactile_deploy.indenters import ContactPose, get_indenter

    mv = simu.spec.demo
    ind = get_indenter(mv.indenter)
    n_rest, n_press, n_lift = 4, 12, 10
    n_slide = n - 2 * n_rest - n_press - n_lift
    poses = []
    for i in range(n):
        if i < n_rest or i >= n - n_rest:
            s, depth = 0.0 if i < n_rest else 1.0, 0.0
        elif i < n_rest + n_press:
            s, depth = 0.0, mv.depth_mm * (i - n_rest + 1) / n_press
        elif i < n_rest + n_press + n_slide:
            s, depth = (i - n_rest - n_press) / max(n_slide - 1, 1), mv.depth_mm
        else:
            k = i - n_rest - n_press - n_slide
            s, depth = 1.0, mv.depth_mm * (1 - (k + 1) / (n_lift + 1))
        x = mv.start_mm[0] + s * (mv.end_mm[0] - mv.start_mm[0])
        y = mv.start_mm[1] + s * (mv.end_mm[1] - mv.start_mm[1])
        th = mv.theta_deg[0] + s * (mv.theta_deg[1] - mv.theta_deg[0])
        poses.append(ContactPose(x_mm=x, y_mm=y, theta_deg=th, depth_mm=depth))
    frames, truths = [], []
    for pose in poses:
        f, t, _ = simu.press(ind, pose)
        frames.append(f)
        truths.append(t)
    return np.stack(frames), np.stack(truths)


def build(spec: VirtualSensor, folder: Path, model: Path, overwrite: bool,
          supersample: int | None = None) -> dict:
    import cv2

    from calibration.shading.fit import fit_shading
    from calibration.shading.presses import PressSet
    from tactile_deploy.atomic import atomic_path
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.imaging.shading import save_shading
    from tactile_deploy.runtime.pipeline import (
        ImagingPipeline,
        Rectifier,
        rectify_frame,
        resample_to_grid,
    )
    from tactile_deploy.runtime.plugins import (
        MANIFEST_NAME,
        SensorPlugin,
        validate_plugin,
        write_plugin,
    )
    from tactile_deploy.runtime.predictor import MeshTopology
    from tactile_deploy.runtime.sources.factory import open_clip
    from tactile_deploy.runtime.sources.video import write_video

    if (folder / MANIFEST_NAME).exists() and not overwrite:
        raise SystemExit(f"{folder / MANIFEST_NAME} exists; pass --overwrite to rebuild it")
    if not model.is_file():
        raise SystemExit(f"the family model {model} does not exist: export it first "
                         "(python -m training export ...) or pass --model")
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    simu = Simulation(spec)
    rng = np.random.default_rng(1000 + spec.seed)
    cam = simu.optics.camera
    rectifier = Rectifier(cam, supersample)

    def rectify(frame):
        return resample_to_grid(rectify_frame(frame, rectifier), rectifier)

    reference = simu.reference()
    ref_rect = rectify(reference)

    # shading: fit on N_CALIBRATION presses, evaluate on N_HELD_OUT others
    raw, frames, circles, truths = calibration_presses(simu, N_CALIBRATION + N_HELD_OUT, rng,
                                                       rectify)
    train = PressSet(ref_rect, frames[:N_CALIBRATION],
                     [f"press_{i:03d}" for i in range(N_CALIBRATION)], circles[:N_CALIBRATION])
    fit = fit_shading(train, BALL_RADIUS_MM, OutputGrid().pitch_x_mm)
    save_shading(fit.model, folder / "shading.npz")
    with atomic_path(folder / "reference.png") as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(reference, cv2.COLOR_RGB2BGR))
    # held-out presses through the whole pipeline, raw frames in (no noise handling)
    plain = ImagingPipeline(cam, fit.model, reference, None, "keep",
                            supersample=rectifier.supersample)
    held = [plain.frame_to_depth(f) for f in raw[N_CALIBRATION:]]
    held_err = depth_errors_um(held, truths[N_CALIBRATION:], circles[N_CALIBRATION:])

    # noise reference: mean depth of 16 noisy no-contact frames
    noise = np.mean([plain.frame_to_depth(simu.reference()) for _ in range(16)], axis=0)
    np.save(folder / "noise_reference.npy", noise.astype(np.float32))

    # demo clip (MJPEG) and the depth error its compression adds
    demo, demo_truth = demo_frames(simu)
    write_video(folder / "demo.avi", demo, fps=30.0, fourcc="MJPG")
    with open_clip(folder / "demo.avi") as src:
        decoded = np.stack([f.image for f in src])
    codec = [np.sqrt(np.mean((plain.frame_to_depth(a) - plain.frame_to_depth(b)) ** 2)) * 1e3
             for a, b in zip(demo, decoded)]
    MeshTopology.from_pad().save(folder / "topology.npz")

    fields = {
        "name": spec.name, "description": spec.description,
        "family": {"name": "gelslim", "pad": "gelslim", "pad_version": 1,
                   "mesh_hash": MeshTopology.from_pad().mesh_hash},
        "camera": json.loads(cam.model_dump_json()),
        "material": {"E_mpa": spec.E_mpa, "nu": spec.nu,
                     "source": "virtual sensor: the E and nu its FEM was run with"},
        "default_source": {"kind": "demo"},
        "noise_handling": "subtract",
        "provenance": {
            "made_by": "plugins/build_shipped.py (virtual sensor; the calibration wizard makes "
                       "the same files from a real sensor)",
            "date": _dt.date.today().isoformat(),
            "sensor": (f"virtual: FEM (E {spec.E_mpa} MPa, nu {spec.nu}) + RGB optics, "
                       f"{spec.mm_per_px} mm/px, k1 {spec.k1}, rotation {spec.rotation_deg} deg, "
                       f"{'mirrored' if spec.mirrored else 'not mirrored'}, seed {spec.seed}"),
            "shading_fit": (f"{N_CALIBRATION} presses of a {BALL_RADIUS_MM:g} mm ball on the "
                            f"128 x 128 model grid; in-sample sphere RMS "
                            f"{fit.model.header.fit_metrics.get('in_sample_sphere_rms_um', float('nan')):.1f} um"),
            "held_out_depth_error": (
                f"{held_err['n']} presses: whole-frame RMSE <= {held_err['whole_rmse_um_worst']:.1f} um, "
                f"within 1.5 contact radii <= {held_err['near_rmse_um_worst']:.1f} um, peak "
                f"<= {held_err['peak_error_um_worst']:.1f} um"),
            "demo_clip": (f"60 frames, {spec.demo.indenter} pressed {spec.demo.depth_mm} mm, slid "
                          f"{spec.demo.start_mm} -> {spec.demo.end_mm} mm; MJPEG adds depth RMSE "
                          f"<= {max(codec):.1f} um per frame"),
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
    SensorPlugin.load(folder)
    return {"plugin": spec.name, "seconds": round(time.perf_counter() - t0, 1),
            "held_out": held_err, "codec_rmse_um_worst": float(max(codec)),
            "size_mb": round(sum(p.stat().st_size for p in folder.iterdir()) / 1e6, 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=sorted(SENSORS), help="build one plugin")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="the family ONNX model")
    ap.add_argument("--out", type=Path, default=HERE, help="folder of plugin folders")
    ap.add_argument("--overwrite", action="store_true", help="replace existing plugins")
    ap.add_argument("--supersample", type=int, default=None,
                    help="rectification samples per grid cell side (default: the runtime's)")
    args = ap.parse_args(argv)
    names = [args.only] if args.only else sorted(SENSORS)
    for name in names:
        info = build(SENSORS[name], args.out / name, args.model.resolve(), args.overwrite,
                     args.supersample)
        print(json.dumps(info, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
