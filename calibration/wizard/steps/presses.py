"""Step 3, presses: the ball pressed over the view (by the rig or by hand), each contact circle
detected on the imaging grid; circles can be corrected or presses dropped by hand."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tactile_deploy.calibration.shading.circles import ContactNotFoundError, detect_contact_circle
from tactile_deploy.calibration.shading.presses import PressDataError, read_annotations
from tactile_deploy.calibration.wizard.context import Context, Outcome, StepError
from tactile_deploy.calibration.wizard.figures import circles_figure
from tactile_deploy.calibration.wizard.press_data import grid_px
from tactile_deploy.calibration.wizard.station import Ball, rig_press_frames
from tactile_deploy.calibration.wizard.work_data import (
    load_camera,
    load_npz,
    load_reference,
    mean_frame,
    rectifier_for,
)
from tactile_deploy.atomic import write_npz


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


def step_presses(ctx: Context) -> Outcome:
    """Press the ball over the view, detect each contact circle on the imaging grid."""
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
            frames, rec = rig_press_frames(st, ball, contact, cfg.frames_per_press)
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
        raw.append(mean_frame(frames))
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
                detected[i] = [*grid_px(grid, tips_a[i, :2])[0], a_mm / grid.pitch_x_mm]
                notes.append(f"{names[i]}: {e}; circle taken from the rig's position")
            else:
                notes.append(f"{names[i]}: {e}; left out (correct it by hand to keep it)")
    circles = detected.copy()
    if cfg.annotations:

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
    d = load_npz(ctx.work, "presses.npz")
    camera = load_camera(ctx.work)
    grid = camera.grid
    pitch = grid.pitch_x_mm
    keep, circles = d["keep"], d["circles"]
    has_rig = bool(np.all(np.isfinite(d["tip_mm"][:, 0]))) if len(d["tip_mm"]) else False
    rig_px = grid_px(grid, d["tip_mm"][:, :2]) if has_rig else None
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
    d = load_npz(ctx.work, "presses.npz")
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
    d = load_npz(ctx.work, "presses.npz")
    i = _ask_press(ctx, len(d["names"]), "drop")
    d["keep"][i] = False
    write_npz(ctx.work.path("presses.npz"), **d)
    return presses_outcome(ctx, [f"{d['names'][i]} dropped"])
