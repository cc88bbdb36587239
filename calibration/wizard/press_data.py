"""The ball presses of a work folder, for the steps after ``presses``, the FEM fit command and
the benchmarks: the kept set, their FEM depth profiles, and the contacts matched for the FEM
fit. Sensor frame, mm; imaging-grid pixels where said."""

from __future__ import annotations

import numpy as np

from tactile_deploy.calibration.fem_fit.fit import MatchedContact
from tactile_deploy.calibration.shading.press_profile import BallPressModel
from tactile_deploy.calibration.shading.presses import PressSet
from tactile_deploy.calibration.wizard.config import WizardConfig
from tactile_deploy.calibration.wizard.context import StepError
from tactile_deploy.calibration.wizard.state import WorkFolder
from tactile_deploy.calibration.wizard.station import Ball
from tactile_deploy.calibration.wizard.work_data import load_camera, load_npz, load_reference
from tactile_deploy.imaging.shading import load_shading
from tactile_deploy.indenters import ContactPose
from tactile_deploy.runtime.pipeline import ImagingPipeline


def grid_px(grid, xy_mm) -> np.ndarray:
    """Sensor-frame points (k, 2) mm -> imaging-grid (column, row) px."""
    xy = np.asarray(xy_mm, np.float64).reshape(-1, 2)
    return np.c_[(xy[:, 0] - grid.x_min_mm) / grid.pitch_x_mm - 0.5,
                 (grid.y_max_mm - xy[:, 1]) / grid.pitch_y_mm - 0.5]


def press_set(work: WorkFolder):
    """The kept presses of ``work`` as a :class:`~tactile_deploy.calibration.shading.presses.PressSet`, and the
    arrays of ``presses.npz``."""
    d = load_npz(work, "presses.npz")
    keep = d["keep"]
    if keep.sum() < 3:
        raise StepError(f"only {int(keep.sum())} presses have a circle: redo the presses")
    return PressSet(d["reference_r"], d["rectified"][keep], [str(n) for n in d["names"][keep]],
                    d["circles"][keep]), d


def press_profiles(config: WizardConfig, presses_npz: dict, camera, reach_radii: float,
                   depth_offset_mm: float = 0.0, nu: float | None = None) -> list:
    """FEM depth profiles (:class:`~tactile_deploy.calibration.shading.press_profile.PressProfile`) of the
    kept presses, out to ``reach_radii`` contact radii: the ball on the family's pad at the rig's
    contact (sensor frame) pressed its intrusion plus ``depth_offset_mm`` (the rig's zero
    offset, once the FEM step has fitted it), or, for hand presses, at the circle's centre and
    the depth whose FEM contact radius is the circle's. ``nu``: the gel's Poisson ratio (None:
    the FEM settings' prior)."""
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


def contacts_from_work(work: WorkFolder, config: WizardConfig) -> list:
    """The kept ball presses of a work folder as :class:`~tactile_deploy.calibration.fem_fit.fit.MatchedContact`:
    depth maps on the model grid from its shading model, the rig's contact (sensor frame, read
    back) and force when a rig pressed them (else None: estimated from the map / unknown)."""
    d = load_npz(work, "presses.npz")
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
