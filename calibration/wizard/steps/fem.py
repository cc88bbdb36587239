"""Step 5, fem: nu from the depth maps of the presses, E from the rig's forces."""

from __future__ import annotations

import math

import numpy as np

from tactile_deploy.calibration.fem_fit.fit import fit_fem_parameters, render_contact
from tactile_deploy.calibration.fem_fit.operator_bank import OperatorBank
from tactile_deploy.calibration.fem_fit.result import FemResult, write_fem_result
from tactile_deploy.calibration.wizard.context import Context, Outcome, StepError
from tactile_deploy.calibration.wizard.figures import fem_figure
from tactile_deploy.calibration.wizard.press_data import contacts_from_work
from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.indenters import get_indenter
from tactile_deploy.pad.asset import load_pad


def step_fem(ctx: Context) -> Outcome:
    """nu from the depth maps of the presses (the shading model just fitted), E from the rig's
    forces; without forces E is reported as not identifiable and the prior is kept."""
    cfg = ctx.config.fem
    if not cfg.enabled:
        write_fem_result(ctx.work.path("fem.json"), FemResult(
            E_mpa=cfg.prior_E_mpa, nu=cfg.prior_nu, source="prior (FEM fit off in the config)"))
        return Outcome({"E (MPa)": cfg.prior_E_mpa, "nu": cfg.prior_nu},
                       [], ["FEM fit off (fem.enabled = false): the prior goes into the plugin"])

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
    write_fem_result(ctx.work.path("fem.json"), FemResult(
        E_mpa=E, nu=res.nu, source=source, nu_std=_finite(res.nu_std),
        E_std_mpa=_finite(res.E_std_mpa), E_note=res.E_note, nu_note=res.nu_note,
        friction=res.friction, friction_note=res.friction_note,
        depth_gap_um=_finite(1e3 * res.rmse_mm), depth_offset_mm=res.depth_offset_mm,
        method=res.method, evaluations=res.evaluations, n_contacts=len(contacts),
        forces_measured_n=[float(f) for f in fm], forces_fitted_n=[float(f) for f in fs]))
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


def _finite(x: float | None) -> float | None:
    """``x``, or None when it is not a finite number (not measured)."""
    return None if x is None or not math.isfinite(x) else float(x)
