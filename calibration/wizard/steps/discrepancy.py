"""Step 7, discrepancy: the unit's sensor model, and rig presses for the discrepancy workflow.

After the plugin is written this step

1. writes the unit's sensor model into the plugin folder (``sensor_model.json``,
   :func:`tactile_deploy.calibration.discrepancy.sensor_model.unit_sensor_model`: the unit's camera mapping,
   E and nu, the family's lights), so that ``tactile-deploy discrepancy --sensor <plugin>``
   runs;
2. with a rig, presses the calibration ball at a plan of commanded contacts across the pad
   (``discrepancy.n_presses`` of them, 0: none), grabs the frames with the ball held, reads the
   forces, turns the frames into depth with the new plugin, and writes it all as measured data
   (``discrepancy_presses.npz`` in the work folder,
   :func:`tactile_deploy.calibration.discrepancy.collect.collect_presses`; the same as ``tactile-deploy rig
   collect``);

and reports the command that looks for what the model misses.
"""

from __future__ import annotations

from tactile_deploy.calibration.discrepancy.collect import collect_presses, plan_contacts, save_collection
from tactile_deploy.calibration.discrepancy.sensor_model import MODEL_FILE, SensorModelError, unit_sensor_model
from tactile_deploy.calibration.wizard.context import Context, Outcome, StepError
from tactile_deploy.calibration.wizard.station import Ball
from tactile_deploy.calibration.wizard.work_data import load_camera, load_fitted_material
from tactile_deploy.runtime.pipeline import ImagingPipeline
from tactile_deploy.runtime.plugins import SensorPlugin
from tactile_deploy.sensors.config import save_sensor_config

PRESSES_FILE = "discrepancy_presses.npz"


def step_discrepancy(ctx: Context) -> Outcome:
    """The unit's sensor model and, with a rig, presses for ``tactile-deploy discrepancy``."""
    cfg = ctx.config
    out = ctx.out
    if not (out / "plugin.json").is_file():
        raise StepError(f"the plugin folder {out} is missing: redo the plugin step "
                        "(--redo plugin)")
    material = load_fitted_material(ctx.work)
    try:
        model = unit_sensor_model(ctx.sensor, cfg.family, load_camera(ctx.work),
                                  material.E_mpa, material.nu)
    except SensorModelError as e:
        raise StepError(str(e)) from None
    save_sensor_config(model, out / MODEL_FILE)
    metrics = {"sensor model": str(out / MODEL_FILE), "E (MPa)": material.E_mpa,
               "nu": material.nu}
    notes = [f"the unit's sensor model: {out / MODEL_FILE} (--sensor {out})"]
    settings = cfg.discrepancy
    station = ctx.station
    if settings.n_presses == 0 or station.rig is None:
        why = ("discrepancy.n_presses is 0" if settings.n_presses == 0 else
               "there is no rig: record presses later with `tactile-deploy rig collect`")
        notes.append(f"no presses recorded ({why})")
        notes.append(f"then: tactile-deploy discrepancy --sensor {out} --measured PRESSES.npz")
        return Outcome(metrics, [], notes)
    presses, log = record_presses(ctx)
    metrics.update({"presses recorded": len(log.recorded),
                    "presses stopped at the force limit": len(log.presses) - len(log.recorded),
                    "depth noise (um)": (1e3 * log.noise_mm if log.noise_mm else None)})
    notes.append(f"measured data: {presses}")
    notes.append(f"look for what the model misses: tactile-deploy discrepancy --sensor {out} "
                 f"--measured {presses} --report {ctx.work.folder / 'discrepancy'}")
    return Outcome(metrics, [], notes)


def record_presses(ctx: Context):
    """Press the plan with the rig (module docstring): ``(path, CollectionLog)``."""
    s = ctx.config.discrepancy
    ball = Ball(ctx.config.presses.ball_radius_mm)
    station = ctx.station
    station.mount(ball, ctx.ui)
    plan = plan_contacts(s.n_presses, s.radius_mm, tuple(s.depth_range_mm), s.seed)
    pipeline = ImagingPipeline.from_plugin(SensorPlugin.load(ctx.out))
    ctx.ui.say(f"pressing {ball.describe()} at {len(plan)} places for the discrepancy workflow")
    try:
        data, log = collect_presses(station.rig, station.grab, plan, ball.indenter_name,
                                    frames_per_press=s.frames_per_press,
                                    reference_frames=s.reference_frames, pipeline=pipeline,
                                    source=ctx.state.source, plugin=str(ctx.out))
    except ValueError as e:
        raise StepError(f"discrepancy presses: {e}") from None
    path = ctx.work.path(PRESSES_FILE)
    save_collection(path, data, log)
    return path, log
