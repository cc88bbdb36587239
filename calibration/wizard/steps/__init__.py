"""The wizard's steps, one module each, each a function ``step_<name>(ctx) -> Outcome``.

A step reads what earlier steps left in the work folder (:mod:`tactile_deploy.calibration.wizard.work_data`),
talks to the station (frames, rig, person), writes its own data there atomically, and returns
its figures of merit and pictures (:mod:`tactile_deploy.calibration.wizard.context`). It is recorded as done
only when the person accepts it (:mod:`tactile_deploy.calibration.wizard.wizard`).
"""

from __future__ import annotations

from tactile_deploy.calibration.wizard.steps.camera import step_camera
from tactile_deploy.calibration.wizard.steps.fem import step_fem
from tactile_deploy.calibration.wizard.steps.plugin import step_plugin
from tactile_deploy.calibration.wizard.steps.presses import step_presses
from tactile_deploy.calibration.wizard.steps.reference import step_reference
from tactile_deploy.calibration.wizard.steps.shading import step_shading

#: Step functions by name, in order.
STEP_FUNCTIONS = {"reference": step_reference, "camera": step_camera, "presses": step_presses,
                  "shading": step_shading, "fem": step_fem, "plugin": step_plugin}
