"""The wizard's steps, each a function ``step_<name>(ctx) -> Outcome``.

A step reads what earlier steps left in the work folder, talks to the station (frames, rig,
person), writes its own data there atomically, and returns its figures of merit and pictures.
It is recorded as done only when the person accepts it (:mod:`calibration.wizard.wizard`).

Files in the work folder: ``reference.npz`` / ``reference.png`` (step reference),
``camera_mapping.json`` and ``camera.npz`` (camera), ``presses.npz`` (presses; circles are
edited there), ``shading.npz`` (shading), ``fem.json`` (fem), the plugin folder (plugin).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibration.wizard.config import WizardConfig
from calibration.wizard.state import WizardState, WorkFolder
from calibration.wizard.station import Ball, PinPlate, Station
from tactile_deploy.atomic import atomic_path, replace_folder, write_json, write_npz


class StepError(RuntimeError):
    """A step could not be completed (the message says why and what to change)."""


@dataclass
class Context:
    """Everything a step needs."""

    sensor: str
    config: WizardConfig
    station: Station
    work: WorkFolder
    ui: object
    state: WizardState
    out: Path
    overwrite: bool = False
    model_path: Path | None = None


@dataclass
class Outcome:
    """What a step found: figures of merit (names carry units), pictures, notes, and extra
    actions the person may take before accepting (key, label, action returning a new Outcome)."""

    metrics: dict
    figures: list[Path]
    notes: list[str] = field(default_factory=list)
    actions: list[tuple[str, str, Callable[[], Outcome]]] = field(default_factory=list)


# ------------------------------------------------------------------------------------- helpers
def _png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"could not write {path}")


def _mean_frame(frames: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(frames.astype(np.float32).mean(axis=0)), 0, 255).astype(np.uint8)


def _load(work: WorkFolder, name: str) -> dict:
    path = work.path(name)
    if not path.is_file():
        raise StepError(f"{path} is missing: redo the step that writes it")
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def load_reference(work: WorkFolder) -> tuple[np.ndarray, np.ndarray]:
    """(reference (H, W, 3) uint8, the frames averaged into it (n, H, W, 3))."""
    d = _load(work, "reference.npz")
    return d["reference"], d["frames"]


def load_camera(work: WorkFolder):
    from tactile_deploy.imaging.camera_mapping import load_mapping

    return load_mapping(work.path("camera_mapping.json"))


def rectifier_for(camera):
    """``frame -> (ny, nx, 3) uint8`` on the imaging grid, as the runtime rectifies."""
    from tactile_deploy.runtime.pipeline import Rectifier, rectify_frame, resample_to_grid

    r = Rectifier(camera)
    return lambda frame: resample_to_grid(rectify_frame(frame, r), r)


def _rig_press(station: Station, tool, contact, n_frames: int):
    """Press with the rig and grab frames with the tool held: (frames or None, record)."""
    held = []
    x, y, d = contact
    record = station.rig.press(x, y, d, on_pressed=lambda rec: held.append(
        station.grab(n_frames)))
    return (held[0] if held else None), record


# ------------------------------------------------------------------------------------- 1
def step_reference(ctx: Context) -> Outcome:
    """Average frames with nothing touching the sensor."""
    from calibration.wizard.figures import reference_figure

    n = ctx.config.reference.n_frames
    st = ctx.station
    if st.rig is not None:
        st.rig.retract()
    else:
        st.release(ctx.ui)
    frames = st.grab(n)
    ref = _mean_frame(frames)
    write_npz(ctx.work.path("reference.npz"), reference=ref, frames=frames)
    _png(ctx.work.path("reference.png"), ref)
    noise = float(np.median(frames.astype(np.float32).std(axis=0))) if n > 1 else float("nan")
    sat = float(np.mean(np.any(ref >= 254, axis=-1)))
    notes = []
    if n > 1 and noise == 0:
        notes.append("the frames are identical: is the source a still image? The noise "
                     "reference will be zero")
    if sat > 0.05:
        notes.append(f"{100 * sat:.1f} % of the reference pixels are saturated: lower the LED "
                     "brightness or the exposure")
    fig = reference_figure(ctx.work.figures / "reference.png", ref, frames)
    h, w = ref.shape[:2]
    metrics = {"frames averaged": n, "image size (px)": f"{w} x {h}",
               "camera noise, median per-pixel std (grey)": noise,
               "saturated pixels (%)": 100 * sat,
               "mean colour (R, G, B grey)": ", ".join(f"{v:.0f}" for v in
                                                       ref.reshape(-1, 3).mean(0))}
    return Outcome(metrics, [fig], notes)


# ------------------------------------------------------------------------------------- 2
def step_camera(ctx: Context) -> Outcome:
    """Camera mapping from the target, and the imaging grid (what the camera sees)."""
    from calibration.camera.figure import plot_fit
    from calibration.camera.fitting import CalibrationError
    from calibration.camera.imaging_grid import imaging_grid, with_grid
    from calibration.wizard.figures import crop_figure
    from tactile_deploy.imaging.camera_mapping import save_mapping
    from tactile_deploy.runtime.plugins import crop_camera_mapping

    cfg = ctx.config.camera
    ref, _ = load_reference(ctx.work)
    h, w = ref.shape[:2]
    st = ctx.station
    notes: list[str] = []
    if cfg.target == "crop":
        try:
            camera = crop_camera_mapping(w, h, cfg.mm_per_px, cfg.crop)
        except ValueError as e:
            raise StepError(f"camera.crop: {e}") from None
        fig = crop_figure(ctx.work.figures / "camera.png", ref, cfg.crop or (0, 0, w, h))
        save_mapping(camera, ctx.work.path("camera_mapping.json"))
        g = camera.grid
        return Outcome({"target": "none (crop)", "mm per px": cfg.mm_per_px,
                        "imaging grid (cells)": f"{g.nx} x {g.ny}",
                        "imaging grid (mm)": f"x [{g.x_min_mm:.2f}, {g.x_max_mm:.2f}], y "
                                             f"[{g.y_min_mm:.2f}, {g.y_max_mm:.2f}]"}, [fig],
                       ["no lens or perspective correction: the frames are taken as rectified"])
    if cfg.target == "dots":
        plate = PinPlate(cfg.pitch_mm, tuple(cfg.grid), cfg.pin_radius_mm)
        st.mount(plate, ctx.ui)
        if st.rig is not None:
            frames, record = _rig_press(st, plate, (0.0, 0.0, cfg.press_depth_mm), cfg.n_frames)
            if frames is None:
                raise StepError(f"the target press stopped at the force limit "
                                f"({record.max_force_n:.2f} N at "
                                f"{record.reached_depth_mm:.3f} mm): press less deep "
                                "(camera.press_depth_mm) or raise force_limit_n in the rig "
                                "config")
            notes.append(f"target pressed by the rig: {record.force_n:.2f} N at "
                         f"{record.reached_depth_mm:.3f} mm")
        else:
            st.hand_press(plate, (0.0, 0.0, cfg.press_depth_mm), ctx.ui, "target")
            frames = st.grab(cfg.n_frames)
            st.release(ctx.ui)
        from calibration.camera.dots import calibrate_dots

        try:
            fit, det = calibrate_dots(list(frames), ref, cfg.pitch_mm, grid_shape=tuple(cfg.grid),
                                      u_axis=cfg.u_axis, v_axis=cfg.v_axis,
                                      blur_sigma_px=cfg.blur_px, free_lens=tuple(cfg.free_lens),
                                      name="target frame")
        except (CalibrationError, ValueError) as e:
            raise StepError(f"dot target: {e}") from None
        shown = _mean_frame(frames)
    else:
        from calibration.camera.charuco import CharucoBoardSpec, calibrate_charuco, load_board_spec

        spec = load_board_spec(cfg.board) if cfg.board else CharucoBoardSpec()
        st.release(ctx.ui)
        ctx.ui.wait(f"Lay the ChArUco board ({spec.describe()}) flat on the sensing surface")
        frames = st.grab(cfg.n_frames)
        shown = _mean_frame(frames)
        try:
            fit = calibrate_charuco([np.ascontiguousarray(shown[..., ::-1])], spec,
                                    free_lens=tuple(cfg.free_lens))
        except (CalibrationError, ValueError) as e:
            raise StepError(f"ChArUco board: {e}") from None
        ctx.ui.wait("Take the board off the sensor")
    write_npz(ctx.work.path("camera.npz"), frames=frames)
    try:
        grid = imaging_grid(fit.mapping)
    except ValueError as e:
        raise StepError(str(e)) from None
    camera = with_grid(fit.mapping, grid)
    save_mapping(camera, ctx.work.path("camera_mapping.json"))
    fig = ctx.work.figures / "camera.png"
    plot_fit(dataclasses.replace(fit, mapping=camera), shown, fig, dpi=80)
    s = camera.fit
    metrics = {"target": cfg.target, "points used": s.n_points, "points rejected": s.n_rejected,
               "reprojection RMS (px)": s.rms_px, "reprojection max (px)": s.max_px,
               "reprojection RMS (um)": 1e3 * s.rms_mm,
               "mm per px (x, y)": f"{camera.mm_per_px_x:.5f}, {camera.mm_per_px_y:.5f}",
               "image mirrored": str(camera.image_mirrored),
               "imaging grid (cells of 0.273 mm)": f"{grid.nx} x {grid.ny}",
               "imaging grid (mm)": f"x [{grid.x_min_mm:.2f}, {grid.x_max_mm:.2f}], y "
                                    f"[{grid.y_min_mm:.2f}, {grid.y_max_mm:.2f}]"}
    if s.rms_px > 3.0:
        notes.append(f"reprojection RMS {s.rms_px:.2f} px is large: check the target settings")
    return Outcome(metrics, [fig], notes)


# ------------------------------------------------------------------------------------- 3
def plan_presses(grid, ball_radius_mm: float, n: int, depth_range_mm, seed: int,
                 edge_margin: float = 1.2) -> np.ndarray:
    """``n`` contacts (x_mm, y_mm, depth_mm), sensor frame: a jittered lattice over the imaging
    grid (centres ``edge_margin`` contact radii of the deepest press from its edges) so that the
    presses cover the whole view, depths spread evenly over ``depth_range_mm`` in random order."""
    rng = np.random.default_rng([seed, 0x706C616E])
    a_max = math.sqrt(2 * ball_radius_mm * depth_range_mm[1] - depth_range_mm[1] ** 2)
    m = edge_margin * a_max
    x0, x1 = grid.x_min_mm + m, grid.x_max_mm - m
    y0, y1 = grid.y_min_mm + m, grid.y_max_mm - m
    if x1 <= x0 or y1 <= y0:
        raise StepError(f"a {ball_radius_mm} mm ball pressed {depth_range_mm[1]} mm does not fit "
                        f"the imaging grid ({grid.x_max_mm - grid.x_min_mm:.1f} x "
                        f"{grid.y_max_mm - grid.y_min_mm:.1f} mm): use a smaller ball or "
                        "shallower presses")
    aspect = (x1 - x0) / (y1 - y0)
    rows = max(1, int(round(math.sqrt(n / aspect))))
    cols = int(math.ceil(n / rows))
    cells = [(i, j) for i in range(rows) for j in range(cols)]
    pick = sorted(rng.choice(len(cells), size=n, replace=False))
    out = []
    dx, dy = (x1 - x0) / cols, (y1 - y0) / rows
    for k in pick:
        i, j = cells[k]
        out.append((x0 + (j + 0.5 + rng.uniform(-0.3, 0.3)) * dx,
                    y0 + (i + 0.5 + rng.uniform(-0.3, 0.3)) * dy))
    depths = rng.permutation(np.linspace(depth_range_mm[0], depth_range_mm[1], n))
    return np.c_[np.array(out), depths]


def _grid_px(grid, xy_mm) -> np.ndarray:
    """Sensor-frame points (k, 2) mm -> imaging-grid (column, row) px."""
    xy = np.asarray(xy_mm, np.float64).reshape(-1, 2)
    return np.c_[(xy[:, 0] - grid.x_min_mm) / grid.pitch_x_mm - 0.5,
                 (grid.y_max_mm - xy[:, 1]) / grid.pitch_y_mm - 0.5]


def step_presses(ctx: Context) -> Outcome:
    """Press the ball over the view, detect each contact circle on the imaging grid."""
    from calibration.shading.circles import ContactNotFoundError, detect_contact_circle

    cfg = ctx.config.presses
    camera = load_camera(ctx.work)
    grid = camera.grid
    ref, _ = load_reference(ctx.work)
    rect = rectifier_for(camera)
    ref_r = rect(ref)
    plan = plan_presses(grid, cfg.ball_radius_mm, cfg.n_presses, cfg.depth_range_mm, cfg.seed,
                        cfg.edge_margin)
    ball = Ball(cfg.ball_radius_mm)
    st = ctx.station
    st.mount(ball, ctx.ui)
    raw, planned, tips, forces, notes = [], [], [], [], []
    for i, contact in enumerate(plan):
        label = f"press {i + 1}/{len(plan)}"
        if st.rig is not None:
            frames, rec = _rig_press(st, ball, contact, cfg.frames_per_press)
            if frames is None:
                notes.append(f"{label} stopped at the force limit ({rec.max_force_n:.2f} N at "
                             f"{rec.reached_depth_mm:.3f} mm): left out")
                continue
            tips.append((*rec.tip_readback_mm[:2], rec.reached_depth_mm))
            forces.append(rec.force_n)
        else:
            st.hand_press(ball, tuple(contact), ctx.ui, label)
            frames = st.grab(cfg.frames_per_press)
            tips.append((np.nan, np.nan, np.nan))
            forces.append(np.nan)
        raw.append(_mean_frame(frames))
        planned.append(contact)
    if st.rig is not None:
        st.rig.retract()
    else:
        st.release(ctx.ui)
    if len(raw) < 3:
        raise StepError(f"only {len(raw)} presses were recorded: lower the press depths or "
                        "raise the rig's force limit")
    raw = np.stack(raw)
    rect_frames = np.stack([rect(f) for f in raw])
    names = np.array([f"press_{i:03d}.png" for i in range(len(raw))])
    detected = np.full((len(raw), 3), np.nan)
    tips_a = np.array(tips, np.float64).reshape(-1, 3)
    for i, f in enumerate(rect_frames):
        try:
            detected[i] = detect_contact_circle(f, ref_r, min_radius_px=2.5)
        except ContactNotFoundError as e:
            if np.all(np.isfinite(tips_a[i])):
                # the rig knows where it pressed: its centre, and the rigid-sphere contact
                # radius sqrt(R d) (the fit refines centres and re-measures radii)
                a_mm = math.sqrt(cfg.ball_radius_mm * max(tips_a[i, 2], 1e-3))
                detected[i] = [*_grid_px(grid, tips_a[i, :2])[0], a_mm / grid.pitch_x_mm]
                notes.append(f"{names[i]}: {e}; circle taken from the rig's position")
            else:
                notes.append(f"{names[i]}: {e}; left out (correct it by hand to keep it)")
    circles = detected.copy()
    if cfg.annotations:
        from calibration.shading.presses import PressDataError, read_annotations

        try:
            ann = read_annotations(Path(cfg.annotations))
        except (PressDataError, OSError) as e:
            raise StepError(f"presses.annotations: {e}") from None
        for i, n in enumerate(names):
            if n in ann:
                circles[i] = ann[n]
        notes.append(f"circles of {sum(n in ann for n in names)} presses from {cfg.annotations}")
    keep = np.all(np.isfinite(circles), axis=1)
    write_npz(ctx.work.path("presses.npz"), raw=raw, rectified=rect_frames, reference_r=ref_r,
              names=names, planned_mm=np.array(planned, np.float64),
              tip_mm=np.array(tips, np.float64), force_n=np.array(forces, np.float64),
              detected=detected, circles=circles, keep=keep)
    return presses_outcome(ctx, notes)


def presses_outcome(ctx: Context, notes: list[str] | None = None) -> Outcome:
    """Figures of merit and the circles picture of the saved presses, with the manual
    correction actions."""
    from calibration.wizard.figures import circles_figure

    d = _load(ctx.work, "presses.npz")
    camera = load_camera(ctx.work)
    grid = camera.grid
    pitch = grid.pitch_x_mm
    keep, circles = d["keep"], d["circles"]
    has_rig = bool(np.all(np.isfinite(d["tip_mm"][:, 0]))) if len(d["tip_mm"]) else False
    rig_px = _grid_px(grid, d["tip_mm"][:, :2]) if has_rig else None
    fig = circles_figure(ctx.work.figures / "presses.png", d["rectified"], circles, d["names"],
                         keep, rig_px)
    r = circles[keep, 2] * pitch
    metrics = {"presses recorded": len(keep), "presses used": int(keep.sum()),
               "contact radius range (mm)": (f"{r.min():.2f} - {r.max():.2f}" if len(r)
                                             else "-")}
    if has_rig:
        f = d["force_n"][keep]
        off = np.hypot(*(circles[keep, :2] - rig_px[keep]).T) * pitch
        metrics["force range (N)"] = f"{f.min():.2f} - {f.max():.2f}"
        metrics["circle centre vs rig position, mean (mm)"] = float(off.mean())
        metrics["circle centre vs rig position, max (mm)"] = float(off.max())
    actions = [("correct", "Correct a circle by hand", lambda: _correct_circle(ctx)),
               ("drop", "Drop a press", lambda: _drop_press(ctx))]
    return Outcome(metrics, [fig], list(notes or []), actions)


def _ask_press(ctx: Context, n: int, what: str) -> int:
    def valid(t: str):
        return (t.strip().isdigit() and 1 <= int(t) <= n) or f"a press number from 1 to {n}"

    return int(ctx.ui.text(f"Which press to {what}? (1-{n}, see the picture)", "1", valid)) - 1


def _correct_circle(ctx: Context) -> Outcome:
    d = _load(ctx.work, "presses.npz")
    i = _ask_press(ctx, len(d["names"]), "correct")
    cur = d["circles"][i]
    h, w = d["rectified"].shape[1:3]

    def valid(t: str):
        try:
            c, r, rad = (float(v) for v in t.replace(",", " ").split())
        except ValueError:
            return "three numbers: column row radius (px of the imaging grid)"
        return (0 <= c < w and 0 <= r < h and 0 < rad < max(w, h)) or (
            f"column in [0, {w}), row in [0, {h}), radius > 0")

    default = "" if not np.all(np.isfinite(cur)) else f"{cur[0]:.1f} {cur[1]:.1f} {cur[2]:.1f}"
    text = ctx.ui.text(f"Circle of {d['names'][i]}: column row radius (px)", default, valid)
    d["circles"][i] = [float(v) for v in text.replace(",", " ").split()]
    d["keep"][i] = True
    write_npz(ctx.work.path("presses.npz"), **d)
    return presses_outcome(ctx, [f"{d['names'][i]}: circle set by hand to {text}"])


def _drop_press(ctx: Context) -> Outcome:
    d = _load(ctx.work, "presses.npz")
    i = _ask_press(ctx, len(d["names"]), "drop")
    d["keep"][i] = False
    write_npz(ctx.work.path("presses.npz"), **d)
    return presses_outcome(ctx, [f"{d['names'][i]} dropped"])


# ------------------------------------------------------------------------------------- 4
def _press_set(ctx: Context):
    from calibration.shading.presses import PressSet

    d = _load(ctx.work, "presses.npz")
    keep = d["keep"]
    if keep.sum() < 3:
        raise StepError(f"only {int(keep.sum())} presses have a circle: redo the presses")
    return PressSet(d["reference_r"], d["rectified"][keep], [str(n) for n in d["names"][keep]],
                    d["circles"][keep]), d


def press_profiles(config: WizardConfig, presses_npz: dict, camera, reach_radii: float,
                   depth_offset_mm: float = 0.0, nu: float | None = None) -> list:
    """FEM depth profiles (:class:`~calibration.shading.press_profile.PressProfile`) of the
    kept presses, out to ``reach_radii`` contact radii: the ball on the family's pad at the rig's
    contact (sensor frame) pressed its intrusion plus ``depth_offset_mm`` (the rig's zero
    offset, once the FEM step has fitted it), or, for hand presses, at the circle's centre and
    the depth whose FEM contact radius is the circle's. ``nu``: the gel's Poisson ratio (None:
    the FEM settings' prior)."""
    from calibration.shading.press_profile import BallPressModel

    cfg = config
    model = BallPressModel(cfg.family, cfg.presses.ball_radius_mm,
                           cfg.fem.prior_nu if nu is None else float(nu))
    g = camera.grid
    out = []
    for i in np.flatnonzero(presses_npz["keep"]):
        col, row, a_px = presses_npz["circles"][i]
        a_mm = a_px * g.pitch_x_mm
        tip = presses_npz["tip_mm"][i]
        if np.all(np.isfinite(tip)):
            x, y, depth = tip
            depth = depth + depth_offset_mm
        else:
            x = g.x_min_mm + (col + 0.5) * g.pitch_x_mm
            y = g.y_max_mm - (row + 0.5) * g.pitch_y_mm
            depth = model.depth_for_contact_radius(x, y, a_mm)
        out.append(model.profile(x, y, depth, reach_radii * a_mm + 1.0))
    return out


def shading_fit_config(settings):
    """The :class:`~calibration.shading.fit.ShadingFitConfig` of the wizard's shading settings."""
    from calibration.shading.fit import ShadingFitConfig

    return ShadingFitConfig(bins=settings.bins, node_spacing_mm=settings.node_spacing_mm,
                            kernel_sigma_mm=settings.kernel_sigma_mm,
                            ring_stride=settings.ring_stride, prior_model=settings.prior)


def step_shading(ctx: Context) -> Outcome:
    """Fit the shading model on the presses; cross-validate it; show depth vs the sphere."""
    from calibration.shading.evaluate import cross_validate, fit_sphere, summarise
    from calibration.shading.fit import fit_shading
    from calibration.wizard.figures import cross_validation_figure, shading_figure
    from tactile_deploy.imaging.shading import DepthFromShading, save_shading

    cfg = ctx.config
    presses, d = _press_set(ctx)
    camera = load_camera(ctx.work)
    pitch = camera.grid.pitch_x_mm
    radius = cfg.presses.ball_radius_mm
    fit_cfg = shading_fit_config(cfg.shading)
    if cfg.shading.ring_targets == "fem":
        ctx.ui.say("shading: the ball presses solved by the FEM of the pad (targets around the "
                   "contacts; about 20 s the first time)")
        presses.profiles = press_profiles(cfg, d, camera, fit_cfg.far_factor)
    try:
        fit = fit_shading(presses, radius, pitch, fit_cfg)
    except ValueError as e:
        raise StepError(f"shading fit: {e}") from None
    save_shading(fit.model, ctx.work.path("shading.npz"))
    runner = DepthFromShading(fit.model, presses.reference)
    metrics = {"presses": len(presses),
               "targets around the contacts": ("FEM of the pad" if presses.profiles is not None
                                               else "none"),
               "in-sample sphere residual (um)": fit.model.header.fit_metrics[
                   "in_sample_sphere_rms_um"],
               "colour model residual (grey)": fit.colour_model_rms_grey,
               "depth weight x / y": f"{fit.model.header.poisson_weight_x:.3g} / 1",
               "table fallback": cfg.shading.prior}
    figures, notes = [], []
    folds = min(cfg.shading.folds, len(presses))
    if folds >= 2:
        def fitter(train):
            return DepthFromShading(fit_shading(train, radius, pitch, fit_cfg).model,
                                    train.reference)

        res = cross_validate(presses, fitter, radius, pitch, folds)
        s = summarise(res)
        metrics.update({
            f"held-out shape error mean ({folds}-fold CV, um)": s.shape_mean_um,
            "held-out shape error worst (um)": s.shape_worst_um,
            "held-out fitted radius error mean (%)": 100 * s.radius_error_mean,
            "held-out fitted radius error worst abs (%)": 100 * s.radius_error_worst,
            "held-out fitted radius error, centre half mean (%)": 100 * s.radius_error_centre,
            "held-out fitted radius error, edge half mean (%)": 100 * s.radius_error_edge})
        figures.append(cross_validation_figure(ctx.work.figures / "shading_cv.png", res, radius,
                                               pitch))
        if s.shape_mean_um > 20 or s.shape_worst_um > 40 or s.radius_error_worst > 0.05:
            a_px = presses.circles[:, 2]
            notes.append(f"held-out figures miss the targets set on real presses (shape error "
                         f"<= 20 um mean, <= 40 um worst; radius within 5 %): check the circles, "
                         f"add presses or press deeper. Here the contacts span {a_px.min():.0f}-"
                         f"{a_px.max():.0f} px of the imaging grid: below ~10 px the fitted "
                         "radius of a cap is poorly conditioned")
    # four presses: nearest to the centre, farthest from it, deepest, shallowest
    h, w = presses.shape
    dist = np.hypot(presses.circles[:, 0] - (w - 1) / 2, presses.circles[:, 1] - (h - 1) / 2)
    show = list(dict.fromkeys([int(np.argmin(dist)), int(np.argmax(dist)),
                               int(np.argmax(fit.circles[:, 2])),
                               int(np.argmin(fit.circles[:, 2]))]))
    depths = [runner.depth(presses.frames[i]) for i in show]
    spheres = [fit_sphere(dm, presses.circles[i], pitch, radius) for dm, i in zip(depths, show)]
    figures.insert(0, shading_figure(ctx.work.figures / "shading.png", depths,
                                     [presses.circles[i] for i in show],
                                     [f"{presses.names[i]} (in sample)" for i in show], spheres,
                                     pitch, radius))
    return Outcome(metrics, figures, notes)


# ------------------------------------------------------------------------------------- 5
def contacts_from_work(work: WorkFolder, config: WizardConfig) -> list:
    """The kept ball presses of a work folder as :class:`~calibration.fem_fit.fit.MatchedContact`:
    depth maps on the model grid from its shading model, the rig's contact (sensor frame, read
    back) and force when a rig pressed them (else None: estimated from the map / unknown)."""
    from calibration.fem_fit.fit import MatchedContact
    from tactile_deploy.imaging.shading import load_shading
    from tactile_deploy.indenters import ContactPose
    from tactile_deploy.runtime.pipeline import ImagingPipeline

    d = _load(work, "presses.npz")
    camera = load_camera(work)
    ref, _ = load_reference(work)
    pipeline = ImagingPipeline(camera, load_shading(work.path("shading.npz")), ref, None, "keep")
    ball = Ball(config.presses.ball_radius_mm)
    contacts = []
    for i in np.flatnonzero(d["keep"]):
        depth = pipeline.frame_to_depth(d["raw"][i]).astype(np.float64)
        tip, force = d["tip_mm"][i], d["force_n"][i]
        pose = (ContactPose(x_mm=tip[0], y_mm=tip[1], depth_mm=tip[2])
                if np.all(np.isfinite(tip)) else None)
        contacts.append(MatchedContact(depth, ball.indenter_name, pose,
                                       float(force) if np.isfinite(force) else None))
    return contacts


def step_fem(ctx: Context) -> Outcome:
    """nu from the depth maps of the presses (the shading model just fitted), E from the rig's
    forces; without forces E is reported as not identifiable and the prior is kept."""
    cfg = ctx.config.fem
    if not cfg.enabled:
        write_json(ctx.work.path("fem.json"), {"E_mpa": cfg.prior_E_mpa, "nu": cfg.prior_nu,
                                               "source": "prior (FEM fit off in the config)"})
        return Outcome({"E (MPa)": cfg.prior_E_mpa, "nu": cfg.prior_nu},
                       [], ["FEM fit off (fem.enabled = false): the prior goes into the plugin"])
    from calibration.fem_fit.fit import fit_fem_parameters, render_contact
    from calibration.fem_fit.operator_bank import OperatorBank
    from calibration.wizard.figures import fem_figure
    from tactile_deploy.camera.depth import DepthCamera
    from tactile_deploy.indenters import get_indenter
    from tactile_deploy.pad.asset import load_pad

    contacts = contacts_from_work(ctx.work, ctx.config)
    ctx.ui.say(f"FEM fit: surface operators at nu = {', '.join(f'{v:g}' for v in cfg.nu_grid)} "
               "(about 20 s each the first time, then cached)")
    bank = OperatorBank(load_pad(ctx.config.family), grid_nu=tuple(cfg.nu_grid))
    cam = DepthCamera()
    try:
        res = fit_fem_parameters(contacts, bank, cam, method=cfg.method, bootstrap=cfg.bootstrap,
                                 fit_depth_offset=cfg.fit_depth_offset)
    except ValueError as e:  # contacts the FEM cannot reproduce (e.g. no force at a contact)
        raise StepError(f"FEM fit: {e}; redo the presses step (--redo presses)") from None
    E = res.E_mpa if res.E_mpa is not None else cfg.prior_E_mpa
    source = (f"calibrated by tactile-deploy calibrate: nu {res.nu_note}; E {res.E_note}"
              if res.E_mpa is not None else
              f"calibrated by tactile-deploy calibrate: nu {res.nu_note}; E = prior "
              f"{cfg.prior_E_mpa} MPa ({res.E_note})")
    fm, fs = [], []
    for c, p in zip(contacts, res.poses):
        if c.force_n is not None and res.E_mpa is not None:
            fm.append(c.force_n)
            fs.append(res.E_mpa * render_contact(bank, res.nu, cam, get_indenter(c.indenter),
                                                 p)[1])
    write_json(ctx.work.path("fem.json"), {
        "E_mpa": E, "nu": res.nu, "source": source, "nu_std": res.nu_std,
        "E_std_mpa": res.E_std_mpa, "E_note": res.E_note, "nu_note": res.nu_note,
        "friction_note": res.friction_note, "depth_gap_um": 1e3 * res.rmse_mm,
        "depth_offset_mm": res.depth_offset_mm,
        "forces_measured_n": fm, "forces_fitted_n": fs})
    fig = fem_figure(ctx.work.figures / "fem.png", res.objective_curve, res.nu, fm, fs)
    metrics = {"contacts": len(contacts), "nu": res.nu,
               "nu bootstrap std": (res.nu_std if math.isfinite(res.nu_std)
                                    and len(cfg.nu_grid) > 1 else "-"),
               "E (MPa)": E if res.E_mpa is not None else f"{E} (prior: not identifiable)",
               "E bootstrap std (MPa)": (res.E_std_mpa if res.E_std_mpa is not None else "-"),
               "depth-map gap RMS at the optimum (um)": 1e3 * res.rmse_mm}
    if res.depth_offset_mm is not None:
        metrics["rig depth zero offset, fitted (um)"] = 1e3 * res.depth_offset_mm
    if fm:
        err = np.abs(np.array(fs) / np.array(fm) - 1)
        metrics["force fit, median |error| (%)"] = float(100 * np.median(err))
    return Outcome(metrics, [fig], [f"nu: {res.nu_note}", f"E: {res.E_note}"])


# ------------------------------------------------------------------------------------- 6
def default_model() -> Path:
    """The family model of a source checkout (exported/gelslim_mesh.onnx)."""
    return Path(__file__).resolve().parents[2] / "exported" / "gelslim_mesh.onnx"


def step_plugin(ctx: Context) -> Outcome:
    """Write the plugin folder (validated by the runtime's loader) with its report, atomically:
    everything goes to a hidden folder beside the target, which is renamed into place last."""
    import os
    import shutil

    from calibration.wizard.figures import plugin_figure
    from calibration.wizard.report import write_report
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin

    out = Path(ctx.out)
    ours = ctx.state.plugin_written == str(out.resolve())
    if out.exists() and not (ctx.overwrite or ours):
        raise StepError(f"{out} exists: pass --overwrite to replace it, or choose another --out")
    if not out.parent.is_dir():
        raise StepError(f"--out: folder {out.parent} does not exist")
    model = Path(ctx.model_path or ctx.config.model or default_model())
    if not model.is_file():
        raise StepError(f"the family model {model} does not exist: pass --model PATH (an ONNX "
                        "model exported by `python -m training export`)")
    tmp = (out.parent / f".{out.name}.partial-{os.getpid()}").resolve()
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        manifest, notes = _build_plugin(ctx, tmp, model)
        report = validate_plugin(tmp)
        if not report.ok:
            raise StepError("the written plugin does not validate:\n  "
                            + "\n  ".join(report.problems))
        plugin = SensorPlugin.load(tmp)
        pipeline = ImagingPipeline.from_plugin(plugin)
        d = _load(ctx.work, "presses.npz")
        i = int(np.argmax(d["planned_mm"][:, 2])) if len(d["planned_mm"]) else 0
        depth = pipeline.frame_to_depth(d["raw"][i])
        fig = plugin_figure(ctx.work.figures / "plugin.png", d["raw"][i], depth,
                            manifest.depth_grid)
        size_mb = sum(p.stat().st_size for p in tmp.rglob("*") if p.is_file()) / 1e6
        metrics = {"plugin": str(out), "checks passed": len(report.checked),
                   "size (MB)": size_mb,
                   "deepest press, plugin depth max (mm)": float(depth.max())}
        write_report(ctx, tmp / "calibration", {"plugin": metrics}, [fig])
        replace_folder(tmp, out)
        ctx.state.plugin_written = str(out.resolve())
        ctx.work.save(ctx.state)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    notes.append(f"report: {out / 'calibration' / 'report.html'}")
    notes.append(f"use it: tactile-deploy run --sensor {out}")
    return Outcome(metrics, [fig], notes)


def _build_plugin(ctx: Context, folder: Path, model: Path):
    """Files and manifest of the plugin in ``folder``; returns (manifest, notes)."""
    import shutil

    from tactile_deploy.imaging.shading import load_shading
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import write_plugin
    from tactile_deploy.runtime.predictor import MeshTopology
    from tactile_deploy.runtime.sources.video import write_video

    cfg = ctx.config
    camera = load_camera(ctx.work)
    ref, ref_frames = load_reference(ctx.work)
    shading = load_shading(ctx.work.path("shading.npz"))
    shutil.copyfile(ctx.work.path("shading.npz"), folder / "shading.npz")
    _png(folder / "reference.png", ref)
    d = _load(ctx.work, "presses.npz")
    material = json.loads(ctx.work.path("fem.json").read_text())
    readout, tune_note = None, None
    if cfg.readout is not None:
        from tactile_deploy.imaging.learned_readout import LearnedReadout, ReadoutError

        try:
            readout = LearnedReadout(cfg.readout)
        except ReadoutError as e:
            raise StepError(f"config field 'readout': {e}") from None
        if cfg.readout_steps > 0:
            readout, tune_note = _finetune_readout(ctx, camera, shading, ref, ref_frames,
                                                   readout, d, material, folder)
    plain = ImagingPipeline(camera, shading, ref, None, "keep", readout=readout)
    noise = np.mean([plain.frame_to_depth(f) for f in ref_frames], axis=0).astype(np.float32)
    gain, gain_note = 1.0, None
    if readout is not None:
        gain, gain_note = _readout_gain(camera, shading, ref, noise, readout, d, material)
        if tune_note is not None:
            gain_note = f"{gain_note}; {tune_note}"
        noise = noise * np.float32(gain)
    np.save(folder / "noise_reference.npy", noise)
    demo = np.concatenate([ref_frames[:4], d["raw"][d["keep"]]])
    write_video(folder / "demo.avi", demo, fps=10.0, fourcc="MJPG")
    topo = MeshTopology.from_pad(cfg.family)
    topo.save(folder / "topology.npz")
    if cfg.copy_model:
        shutil.copyfile(model, folder / model.name)
        model = folder / model.name
    steps = ctx.state.steps
    prov = {"made_by": "tactile-deploy calibrate (the calibration wizard)",
            "date": ctx.state.started[:10], "source": ctx.state.source,
            "rig": ctx.state.rig or "none (hand presses)",
            "report": "calibration/report.html"}
    for name in ("camera", "shading", "fem"):
        if name in steps:
            prov[f"{name}_figures"] = "; ".join(
                f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                for k, v in steps[name].metrics.items())
    fields = {
        "name": ctx.sensor,
        "description": cfg.description or f"{ctx.sensor}, calibrated from {ctx.state.source}",
        "family": {"name": cfg.family, "pad": cfg.family, "pad_version": 1,
                   "mesh_hash": topo.mesh_hash},
        "camera": json.loads(camera.model_dump_json()),
        "material": {"E_mpa": float(material["E_mpa"]), "nu": float(material["nu"]),
                     "source": material["source"]},
        "default_source": _default_source(ctx),
        "noise_handling": "subtract",
        "provenance": prov,
    }
    if readout is not None:
        fields["readout_depth_gain"] = gain
        prov["readout"] = gain_note
    files = {"model": model, "shading": folder / "shading.npz",
             "reference_frame": folder / "reference.png",
             "noise_reference": folder / "noise_reference.npy", "demo_clip": folder / "demo.avi",
             "topology": folder / "topology.npz"}
    if readout is not None:
        files["readout"] = readout.path.resolve()
    manifest = write_plugin(folder, fields, files)
    return manifest, [f"model: {'copied into the plugin' if cfg.copy_model else model}"]


def _finetune_readout(ctx: Context, camera, shading, ref, ref_frames, readout, d, material,
                      folder: Path):
    """:func:`finetune_readout_on_presses` in the plugin step, its progress on the UI."""
    from calibration.shading.readout_finetune import FinetuneUnavailable

    ctx.ui.say(f"fine-tuning the learned read-out on {int(d['keep'].sum())} presses "
               f"({ctx.config.readout_steps} steps)")

    def log(step, steps, loss, seconds):
        ctx.ui.say(f"  step {step}/{steps}: loss {loss:.3g} ({seconds:.0f} s)")

    try:
        return finetune_readout_on_presses(ctx.config, camera, shading, ref, ref_frames, readout,
                                           d, material, folder / "readout.onnx", ctx.sensor, log)
    except FinetuneUnavailable as e:
        raise StepError(str(e)) from None


def finetune_readout_on_presses(config: WizardConfig, camera, shading, ref, ref_frames, readout,
                                presses_npz: dict, material: dict, out: Path, unit: str,
                                log=None):
    """The design's ``readout`` fine-tuned on the kept presses of ``presses_npz`` and the
    no-contact ``ref_frames`` (:mod:`calibration.shading.readout_finetune`; targets: the
    presses' FEM depth profiles at the rig's intrusion plus the FEM step's zero offset, with its
    nu), ``config.readout_steps`` steps, written to ``out``: ``(LearnedReadout of it, a line for
    the provenance)``."""
    from calibration.shading.readout_finetune import finetune_unit_readout
    from tactile_deploy.imaging.learned_readout import LearnedReadout
    from tactile_deploy.runtime.pipeline import ImagingPipeline

    d = presses_npz
    keep = d["keep"]
    if not keep.any():
        raise StepError("no kept presses to fine-tune the learned read-out on: redo the presses "
                        "step, or set readout_steps to 0 in the config")
    offset = material.get("depth_offset_mm")
    nu = material.get("nu", config.fem.prior_nu)
    profiles = press_profiles(config, d, camera, 4.0, offset or 0.0, nu)
    depths = np.stack([p.depth_map(camera.grid) for p in profiles])
    pipeline = ImagingPipeline(camera, shading, ref, None, "keep", readout=readout)
    result = finetune_unit_readout(pipeline, d["raw"][keep], depths, ref_frames, out, unit,
                                   steps=config.readout_steps, log=log)
    source = (f"depth targets at the rig's intrusion plus its zero offset {1e3 * offset:+.1f} um"
              if offset is not None
              else "depth targets at the rig's intrusion (no zero offset known: FEM fit off)")
    return LearnedReadout(result.path), f"{result.summary()} ({source}, nu {nu:.3g})"


def _readout_gain(camera, shading, ref, noise, readout, d, material) -> tuple[float, str]:
    """The unit's depth gain of the learned read-out from the rig's presses
    (:mod:`calibration.shading.readout_gain`), and a line for the provenance."""
    from calibration.shading.readout_gain import readout_depth_gain
    from tactile_deploy.runtime.pipeline import ImagingPipeline

    tips = d["tip_mm"]
    use = d["keep"] & np.all(np.isfinite(tips), axis=1)
    what = f"{readout.path.name} (design {readout.metadata.get('design', '?')})"
    if not use.any():
        return 1.0, (f"{what}; depth gain not calibrated (1): no rig presses of known depth")
    offset = material.get("depth_offset_mm")
    pipeline = ImagingPipeline(camera, shading, ref, noise, "subtract", readout=readout)
    gain, ratios = readout_depth_gain(pipeline, d["raw"][use], tips[use, 2], offset or 0.0)
    source = (f"the rig's zero offset {1e3 * offset:+.1f} um from the FEM step"
              if offset is not None else "no zero offset known (FEM fit off): taken as 0")
    return gain, (f"{what}; depth gain {gain:.4f} = median over {len(ratios)} rig presses of the "
                  f"intrusion over the read-out's deepest cell (p10-p90 {np.percentile(ratios, 10):.3f}"
                  f"-{np.percentile(ratios, 90):.3f}), {source}")


def _default_source(ctx: Context) -> dict:
    src = getattr(ctx.station, "source_config", None)
    if src is not None and src.kind == "camera":
        return src.model_dump()
    sensor = getattr(getattr(ctx.station, "sensor", None), "name", None)
    if sensor is not None:
        return {"kind": "virtual", "sensor": sensor}
    return {"kind": "demo"}


from calibration.wizard.step_discrepancy import step_discrepancy  # noqa: E402

#: Step functions by name, in order.
STEP_FUNCTIONS = {"reference": step_reference, "camera": step_camera, "presses": step_presses,
                  "shading": step_shading, "fem": step_fem, "plugin": step_plugin,
                  "discrepancy": step_discrepancy}
