"""The real FOTS GelSight ball presses (``../shared/data/real/fots_gelsight_ballpress``): reading
them, their samples with the surface built from the hand-labelled circles, and the fit of the
optics model to them (:func:`fit_fots`)."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile_deploy.calibration.optics_fit.fit import OpticsFit, SurfaceParameters, fit_optics, predict
from tactile_deploy.calibration.optics_fit.parameters import OpticsFitError
from tactile_deploy.calibration.optics_fit.press_surface import sphere_press_surface
from tactile_deploy.calibration.optics_fit.samples import ShadingSamples, frame_offsets, usable
from tactile_deploy.imaging.camera_mapping import CameraMapping, pixels_to_sensor_mm
from tactile_deploy.optics.model import Light, OpticsModel, simple_camera

#: The source checkout (the real presses are in ../shared/data beside it).
ROOT = Path(__file__).resolve().parents[2]
#: The real ball presses (FOTS project, MIT licence), beside the checkout.
FOTS_FOLDER = ROOT.parent / "shared" / "data" / "real" / "fots_gelsight_ballpress"
#: Ball radius of the FOTS presses, mm, and their image scale, px per mm.
FOTS_BALL_RADIUS_MM = 2.35
FOTS_PX_PER_MM = 19.58


def fem_sinking_scale(depths_mm=(0.6, 0.9, 1.2), ball_radius_mm: float = FOTS_BALL_RADIUS_MM,
                      nu: float = 0.48) -> dict:
    """The sinking around a pressed ball on our flat 3 mm pad, as a ``sinking_scale``.

    For each tip depth, the FEM solution (frictionless, ``nu``) at the sensing nodes is fitted by
    :func:`sphere_press_surface` with the contact radius and the sinking scale free (least
    squares on the nodal heights, nodes within 3 ball radii). Returns the per-depth fits and
    their median scale.
    """
    from scipy.optimize import least_squares

    from tactile_deploy.fem.material import Material
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.simulation.contact import get_simulator

    sim = get_simulator(Material(nu=nu))
    ball = AnalyticSphere(ball_radius_mm)
    xy = sim.mesh.vertices[sim.mesh.sensing_nodes, :2]
    near = np.hypot(xy[:, 0], xy[:, 1]) < 3.0 * ball_radius_mm
    fits = []
    for d in depths_mm:
        res = sim.solve(ball, ContactPose(depth_mm=float(d)))
        uz = res.displacements_mm[sim.mesh.sensing_nodes, 2][near]

        def resid(p, uz=uz):
            a, s = p
            z, _, _ = sphere_press_surface(xy[near], (0.0, 0.0), a, ball_radius_mm, s)
            return z - uz

        a0 = math.sqrt(ball_radius_mm * d) * 0.9
        sol = least_squares(resid, [min(a0, 0.95 * ball_radius_mm), 0.5],
                            bounds=([0.05, 0.0], [0.99 * ball_radius_mm, 3.0]))
        a, s = sol.x
        fits.append({"depth_mm": float(d), "contact_radius_mm": float(a), "sinking_scale":
                     float(s), "rms_um": float(1e3 * np.sqrt(np.mean(sol.fun**2)))})
    return {"fits": fits, "sinking_scale": float(np.median([f["sinking_scale"] for f in fits]))}

@dataclass
class PressFrames:
    """Ball presses of one sensor: ``reference`` (H, W, 3) uint8 RGB, ``frames`` (N, H, W, 3)
    uint8 RGB, ``names``, ``circles`` (N, 3) px (column, row, contact radius)."""

    reference: np.ndarray
    frames: np.ndarray
    names: list[str]
    circles: np.ndarray

def read_rgb(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise OpticsFitError(f"{path}: missing or not a readable image")
    return np.ascontiguousarray(img[..., ::-1])

def load_fots(folder: Path = FOTS_FOLDER) -> PressFrames:
    """The FOTS ball presses: background.png, NNNN.png and annotate.csv (circles in px)."""
    folder = Path(folder)
    ann = folder / "annotate.csv"
    if not ann.is_file():
        raise OpticsFitError(f"{ann} not found: the real ball presses must be in {folder} "
                             "(../shared/data beside the checkout)")
    names, circles = [], []
    with open(ann, newline="", encoding="utf-8") as f:
        for line, row in enumerate(csv.DictReader(f), start=2):
            try:
                circles.append([float(row["center_x"]), float(row["center_y"]),
                                float(row["radius"])])
            except (KeyError, TypeError, ValueError):
                raise OpticsFitError(f"{ann}, line {line}: expected numeric center_x, center_y, "
                                     f"radius (px), got {row}") from None
            names.append(row["img_names"].strip())
    reference = read_rgb(folder / "background.png")
    frames = np.stack([read_rgb(folder / n) for n in names])
    if frames.shape[1:] != reference.shape:
        raise OpticsFitError(f"{folder}: press frames are {frames.shape[1:]}, the background "
                             f"{reference.shape}")
    return PressFrames(reference, frames, names, np.array(circles))

def fots_camera(width_px: int = 240, height_px: int = 320) -> CameraMapping:
    """The FOTS sensor's camera: 19.58 px/mm, image centre over the sensor origin, columns
    along +x, rows along -y, no lens distortion (the frames are already rectified)."""
    return simple_camera(width_px, height_px, 1.0 / FOTS_PX_PER_MM)

def press_samples(press: PressFrames, camera: CameraMapping, indices: Sequence[int], *,
                  sinking_scale: float, stride: int = 3, near_factor: float = 3.0,
                  near_stride: int = 1, include_reference: bool = True,
                  far_factor: float = 3.5, ball_radius_mm: float = FOTS_BALL_RADIUS_MM
                  ) -> ShadingSamples:
    """Samples of the presses ``indices`` (and the reference frame as a flat surface, frame 0).

    Contact circles (px) become mm with the camera's mean mm per px at the image centre (a
    distortion-free camera looking straight at the pad, as for the FOTS frames).
    Every ``stride``-th pixel (rows and columns) of each frame, and every ``near_stride``-th
    pixel within ``near_factor`` contact radii of the circle's centre; weights make every
    sample stand for the pixel area it represents. Far-field pixels (for the per-frame offsets):
    beyond ``far_factor`` contact radii.
    """
    h, w = press.reference.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    uv_all = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    xy_all = pixels_to_sensor_mm(uv_all, camera)
    scale = 0.5 * (camera.mm_per_px_x + camera.mm_per_px_y)  # contact radius px -> mm
    grid_sel = ((v % stride == 0) & (u % stride == 0)).ravel()
    near_grid = ((v % near_stride == 0) & (u % near_stride == 0)).ravel()
    parts = []
    items = [(-1, None)] if include_reference else []
    items += [(int(i), press.circles[int(i)]) for i in indices]
    for f, (i, circle) in enumerate(items):
        frame = press.reference if i < 0 else press.frames[i]
        obs = frame.reshape(-1, 3).astype(np.float64)
        if circle is None:
            sel = grid_sel
            z = fx = fy = np.zeros(int(sel.sum()))
            far = np.ones(int(sel.sum()), bool)
            weight = np.full(int(sel.sum()), float(stride * stride))
        else:
            cu, cv, rp = circle
            dist = np.hypot(uv_all[:, 0] - cu, uv_all[:, 1] - cv)
            near = (dist <= near_factor * rp) & near_grid
            sel = grid_sel | near
            centre = pixels_to_sensor_mm(np.array([[cu, cv]]), camera)[0]
            z, fx, fy = sphere_press_surface(xy_all[sel], centre, rp * scale,
                                             ball_radius_mm, sinking_scale)
            far = dist[sel] > far_factor * rp
            weight = np.where(near[sel], float(near_stride**2), float(stride * stride))
        part = ShadingSamples(uv_all[sel], xy_all[sel], z, fx, fy, obs[sel],
                              np.full(int(sel.sum()), f), far, weight)
        circ = [np.nan] * 3 if circle is None else [*centre, circle[2] * scale]
        part.circle_mm = np.tile(np.array(circ, float), (len(z), 1))
        parts.append(part)
    return ShadingSamples.concatenate(parts)

def fots_initial_model(camera: CameraMapping | None = None) -> OpticsModel:
    """Starting point of the FOTS fit: red light from +y, green from -y, blue from -x (as the
    colour changes around a press show), 30 degrees elevation, neutral ambient."""
    cam = camera or fots_camera()
    lights = (
        Light(name="red", azimuth_deg=90.0, elevation_deg=30.0, colour_grey=(120.0, 30.0, 30.0)),
        Light(name="green", azimuth_deg=270.0, elevation_deg=30.0, colour_grey=(30.0, 120.0, 30.0)),
        Light(name="blue", azimuth_deg=180.0, elevation_deg=30.0, colour_grey=(30.0, 30.0, 120.0)),
    )
    return OpticsModel(camera=cam, lights=lights, ambient_grey=(80.0, 80.0, 100.0))

FOTS_FREE = ("ambient_grey", "vignetting.k2", "lights.*.azimuth_deg", "lights.*.elevation_deg",
             "lights.*.colour_grey", "lights.*.falloff_per_mm")

#: Presses the FOTS fit trains on (every fourth); the others are held out.
FOTS_TRAIN = tuple(range(0, 42, 4))

@dataclass
class FotsReport:
    """Outcome of :func:`fit_fots`: the fitted model, the surface parameter, error figures."""

    model: OpticsModel
    sinking_scale: float
    fem: dict
    rows: dict
    train: list[int]
    test: list[int]
    fit: OpticsFit

def _held_out_errors(model: OpticsModel, press: PressFrames, camera, test, sinking_scale):
    """Per-channel RMSE (grey) on the held-out presses: whole frame and within 2 contact radii,
    for the model, the model added to the real reference frame (difference mode) and the real
    reference frame alone (baseline). Per-frame offsets from the far field (> 3.5 radii)."""
    s = press_samples(press, camera, test, sinking_scale=sinking_scale, stride=1,
                      near_factor=2.0, include_reference=False)
    flat = ShadingSamples(s.uv_px, s.xy_mm, np.zeros_like(s.z_mm), np.zeros_like(s.fx),
                          np.zeros_like(s.fy), s.observed, s.frame, s.far, s.weight)
    pred = predict(model, s)
    pred_flat = predict(model, flat)
    _h, w = press.reference.shape[:2]
    idx = (s.uv_px[:, 1] * w + s.uv_px[:, 0]).astype(int)
    ref = press.reference.reshape(-1, 3).astype(np.float64)[idx]
    ok = usable(s.observed)
    circles = press.circles[np.asarray(test)][s.frame]
    near = np.hypot(*(s.uv_px - circles[:, :2]).T) < 2.0 * circles[:, 2]
    out = {}
    for name, p in (("model", pred), ("model on real reference", ref + pred - pred_flat),
                    ("real reference only (baseline)", ref)):
        r = p - s.observed
        off = frame_offsets(r[ok], s.frame[ok], s.far[ok], len(test))
        r = r - off[s.frame]
        out[name] = {
            "frame_rmse_grey": [float(v) for v in np.sqrt((r[ok] ** 2).mean(axis=0))],
            "contact_rmse_grey": [float(v) for v in np.sqrt((r[ok & near] ** 2).mean(axis=0))],
        }
    return out

def fit_fots(press: PressFrames | None = None, train: Sequence[int] = FOTS_TRAIN,
             max_evaluations: int = 400) -> FotsReport:
    """Fit the optics of the FOTS sensor on ``train`` presses (+ its reference frame), with the
    sinking scale of the true surface free, and evaluate on the other presses; also with the
    sinking scale fixed to our FEM's value."""
    press = press or load_fots()
    camera = fots_camera(press.reference.shape[1], press.reference.shape[0])
    test = [i for i in range(len(press.frames)) if i not in set(train)]
    model0 = fots_initial_model(camera)
    samples = press_samples(press, camera, train, sinking_scale=1.0, stride=6, near_factor=2.5,
                            near_stride=3)
    surf = SurfaceParameters(["sinking_scale"], np.array([1.0]), np.array([0.0]),
                             np.array([4.0]),
                             lambda x: samples.press_surface(float(x[0]), FOTS_BALL_RADIUS_MM))
    fit = fit_optics(model0, samples, FOTS_FREE, surface=surf, max_evaluations=max_evaluations)
    scale = fit.extra["sinking_scale"]
    rows = {f"{k} (fitted sinking {scale:.2f})": v for k, v in
            _held_out_errors(fit.model, press, camera, test, scale).items()}
    fem = fem_sinking_scale()
    s_fem = press_samples(press, camera, train, sinking_scale=fem["sinking_scale"], stride=6,
                          near_factor=2.5, near_stride=3)
    fit_fem = fit_optics(model0, s_fem, FOTS_FREE, max_evaluations=max_evaluations)
    rows[f"model (FEM sinking {fem['sinking_scale']:.2f})"] = _held_out_errors(
        fit_fem.model, press, camera, test, fem["sinking_scale"])["model"]
    return FotsReport(fit.model, scale, fem, rows, list(train), test, fit)

def markdown_table(report: FotsReport) -> str:
    lines = [("| prediction of the held-out presses | RMSE whole frame R / G / B | "
             "RMSE within 2 contact radii R / G / B |"), "|---|---|---|"]
    for name, v in report.rows.items():
        f = " / ".join(f"{x:.1f}" for x in v["frame_rmse_grey"])
        c = " / ".join(f"{x:.1f}" for x in v["contact_rmse_grey"])
        lines.append(f"| {name} | {f} | {c} |")
    return "\n".join(lines)

def fots_figure(report: FotsReport, press: PressFrames, path: Path, show=(1, 5, 13)) -> None:
    """Side by side: real held-out presses, simulated (fitted optics, renderer), difference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tactile_deploy.atomic import atomic_path
    from tactile_deploy.optics.render import OpticsRenderer, grid_centres

    model = report.model
    renderer = OpticsRenderer(model)
    x, y = grid_centres(renderer.grid)
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    picks = [report.test[i] for i in show if i < len(report.test)]
    fig, axes = plt.subplots(3, len(picks) + 1, figsize=(2.6 * (len(picks) + 1), 9.6))
    cols = [("reference", None)] + [(press.names[i], i) for i in picks]
    for k, (name, i) in enumerate(cols):
        real = press.reference if i is None else press.frames[i]
        if i is None:
            height = renderer.flat_height()
        else:
            cu, cv, rp = press.circles[i]
            centre = pixels_to_sensor_mm(np.array([[cu, cv]]), model.camera)[0]
            z, _, _ = sphere_press_surface(xy, centre, rp / FOTS_PX_PER_MM, FOTS_BALL_RADIUS_MM,
                                           report.sinking_scale)
            height = z.reshape(x.shape).astype(np.float32)
        sim = renderer.render(height)
        # Same per-frame drift correction as the error figures (far field, > 3.5 radii).
        diff = real.astype(np.float64) - sim
        if i is not None:
            vv, uu = np.mgrid[0:real.shape[0], 0:real.shape[1]]
            far = np.hypot(uu - cu, vv - cv) > 3.5 * rp
            sim = np.clip(sim + diff[far].mean(axis=0), 0, 255).astype(np.uint8)
            diff = real.astype(np.float64) - sim
        rmse = np.sqrt((diff**2).mean(axis=(0, 1)))
        axes[0, k].imshow(real)
        axes[0, k].set_title(f"real {name}", fontsize=8)
        axes[1, k].imshow(sim)
        axes[1, k].set_title("simulated", fontsize=8)
        axes[2, k].imshow(np.clip(128 + 2 * diff, 0, 255).astype(np.uint8))
        axes[2, k].set_title("2 x (real - sim) + 128\nRMSE R/G/B " +
                             "/".join(f"{v:.1f}" for v in rmse), fontsize=8)
        for a in axes[:, k]:
            a.set_xticks([])
            a.set_yticks([])
    fig.suptitle("FOTS GelSight ball presses (held out) vs the fitted optics model", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)

def fots_sensor_config(report: FotsReport):
    """The ``gelsight_fots`` virtual sensor: the fitted optics with assumed sensor noise, a
    domed gel and the large-deformation effects that set it apart from the GelSlim units."""
    from tactile_deploy.optics.model import SensorNoise
    from tactile_deploy.sensors.config import EffectSpec, VirtualSensorConfig

    optics = report.model.model_copy(update={
        "noise": SensorNoise(read_noise_grey=1.5, conversion_gain_grey_per_e=0.03),
        "blur_sigma_px": 0.5})
    optics = OpticsModel.model_validate(optics.model_dump() | {"camera": optics.camera})
    return VirtualSensorConfig(
        name="gelsight_fots", family="gelsight",
        description=("GelSight-class sensor fitted to the real FOTS ball presses: 240 x 320 px "
                     "portrait frames at 19.58 px/mm, three directional RGB lights from the fit "
                     f"(sinking scale {report.sinking_scale:.2f}), assumed noise; a 0.3 mm dome "
                     "and over-exposure set it apart from the GelSlim units."),
        optics=optics, fps=30.0, seed=3,
        effects=(EffectSpec(name="dome", params={"height_mm": 0.3}),
                 EffectSpec(name="saturation", params={"exposure_factor": 1.15})))
