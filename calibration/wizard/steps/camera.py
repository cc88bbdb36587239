"""Step 2, camera: the camera mapping from a target (crop, pressed dots or a ChArUco board) and
the imaging grid (what the camera sees)."""

from __future__ import annotations

import dataclasses

import numpy as np

from tactile_deploy.calibration.camera.charuco import CharucoBoardSpec, calibrate_charuco, load_board_spec
from tactile_deploy.calibration.camera.dots import calibrate_dots
from tactile_deploy.calibration.camera.figure import plot_fit
from tactile_deploy.calibration.camera.fitting import CalibrationError
from tactile_deploy.calibration.wizard.context import Context, Outcome, StepError
from tactile_deploy.calibration.wizard.figures import crop_figure
from tactile_deploy.calibration.wizard.station import PinPlate, rig_press_frames
from tactile_deploy.calibration.wizard.work_data import load_reference, mean_frame
from tactile_deploy.atomic import write_npz
from tactile_deploy.imaging.camera_mapping import crop_camera_mapping, save_mapping
from tactile_deploy.imaging.imaging_grid import imaging_grid, with_grid


def step_camera(ctx: Context) -> Outcome:
    """Camera mapping from the target, and the imaging grid (what the camera sees)."""
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
            frames, record = rig_press_frames(st, plate, (0.0, 0.0, cfg.press_depth_mm), cfg.n_frames)
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

        try:
            fit, det = calibrate_dots(list(frames), ref, cfg.pitch_mm, grid_shape=tuple(cfg.grid),
                                      u_axis=cfg.u_axis, v_axis=cfg.v_axis,
                                      blur_sigma_px=cfg.blur_px, free_lens=tuple(cfg.free_lens),
                                      name="target frame")
        except (CalibrationError, ValueError) as e:
            raise StepError(f"dot target: {e}") from None
        shown = mean_frame(frames)
    else:

        spec = load_board_spec(cfg.board) if cfg.board else CharucoBoardSpec()
        st.release(ctx.ui)
        ctx.ui.wait(f"Lay the ChArUco board ({spec.describe()}) flat on the sensing surface")
        frames = st.grab(cfg.n_frames)
        shown = mean_frame(frames)
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
