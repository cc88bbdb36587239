"""``tactile-deploy calibrate ...``: every calibration step as a plain command.

Registered with the ``tactile-deploy`` command through the ``tactile_deploy.cli`` entry-point
group (see pyproject.toml), so the runtime package never imports ``calibration``.
"""

from __future__ import annotations

import typer

from calibration.camera.cli import camera_app
from calibration.shading.cli import shading_app

calibrate_app = typer.Typer(
    help="Calibrate a sensor: camera mapping, shading model, FEM parameters.",
    no_args_is_help=True,
)
calibrate_app.add_typer(camera_app)  # merges `camera` and `make-board` into `calibrate`
calibrate_app.add_typer(shading_app)  # `calibrate shading`
