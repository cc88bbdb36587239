"""``tactile-deploy calibrate ...``: the calibration wizard and every step as a plain command.

    tactile-deploy calibrate --sensor NEW [--source SRC] [--rig PORT --gauge PORT] ...  (wizard)
    tactile-deploy calibrate camera | make-board | shading | fem ...                     (steps)

Registered with the ``tactile-deploy`` command through the ``tactile_deploy.cli`` entry-point
group (see pyproject.toml), so the runtime package never imports ``calibration``.
"""

from __future__ import annotations

import typer

from tactile_deploy.calibration.camera.cli import camera_app
from tactile_deploy.calibration.fem_command import fem_app
from tactile_deploy.calibration.shading.cli import shading_app
from tactile_deploy.calibration.wizard.cli import calibrate_callback

calibrate_app = typer.Typer(
    help="Calibrate a sensor: the wizard (--sensor NEW), or one step (camera mapping, shading "
    "model, FEM parameters).",
    invoke_without_command=True,
    no_args_is_help=True,
)
calibrate_app.callback()(calibrate_callback)  # `calibrate --sensor NEW ...`: the wizard
calibrate_app.add_typer(camera_app)  # merges `camera` and `make-board` into `calibrate`
calibrate_app.add_typer(shading_app)  # `calibrate shading`
calibrate_app.add_typer(fem_app)  # `calibrate fem`
