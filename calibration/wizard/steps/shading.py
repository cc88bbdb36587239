"""Step 4, shading: the shading model fitted on the presses, cross-validated, and the depth of
four presses against the ball's sphere."""

from __future__ import annotations

import numpy as np

from tactile_deploy.calibration.shading.evaluate import cross_validate, fit_sphere, summarise
from tactile_deploy.calibration.shading.fit import fit_shading
from tactile_deploy.calibration.wizard.config import shading_fit_config
from tactile_deploy.calibration.wizard.context import Context, Outcome, StepError
from tactile_deploy.calibration.wizard.figures import cross_validation_figure, shading_figure
from tactile_deploy.calibration.wizard.press_data import press_profiles, press_set
from tactile_deploy.calibration.wizard.work_data import load_camera
from tactile_deploy.imaging.shading import DepthFromShading, save_shading


def step_shading(ctx: Context) -> Outcome:
    """Fit the shading model on the presses; cross-validate it; show depth vs the sphere."""
    cfg = ctx.config
    presses, d = press_set(ctx.work)
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
