"""``tactile-deploy calibrate --sensor NEW ...``: the wizard as the ``calibrate`` group's callback.

Without a subcommand, ``calibrate`` runs the wizard; its subcommands (``camera``, ``shading``,
``fem``, ``make-board``) run single steps on recorded data.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer


def _fail(message: str, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def calibrate_callback(
    ctx: typer.Context,
    sensor: Optional[str] = typer.Option(
        None, "--sensor", help="Name of the new sensor's plugin (lower case, digits, - and _)."),
    source: str = typer.Option(
        "0", "--source", help="Frames: a camera (0, /dev/video2), a video or image folder, or "
        "virtual:NAME for a virtual sensor."),
    rig: Optional[str] = typer.Option(
        None, "--rig", help="Serial port of the rig's G-code stage, or 'simulated' (a simulated "
        "rig pressing a virtual sensor). Without it, presses are made by hand."),
    gauge: Optional[str] = typer.Option(None, "--gauge", help="Serial port of the force gauge."),
    config: Optional[Path] = typer.Option(
        None, "--config", help="Wizard settings (JSON; calibration/wizard/"
        "wizard_config.schema.json). Defaults suit a GelSlim-class sensor."),
    out: Optional[Path] = typer.Option(None, "--out", help="Plugin folder to write (default: "
                                       "./NAME)."),
    work: Optional[Path] = typer.Option(None, "--work", help="Work folder of the steps (default: "
                                        "OUT.calibration beside the plugin); resumes from it."),
    yes: bool = typer.Option(False, "--yes", help="Non-interactive: accept every default "
                             "answer (needs a rig or a virtual sensor for the presses)."),
    redo: Optional[str] = typer.Option(None, "--redo", help="Redo from this step (reference, "
                                       "camera, presses, shading, fem, plugin)."),
    restart: bool = typer.Option(False, "--restart", help="Discard the work folder and start "
                                 "over."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing plugin "
                                   "folder OUT."),
    model: Optional[Path] = typer.Option(None, "--model", help="The family's ONNX model "
                                         "(default: exported/gelslim_mesh.onnx)."),
) -> None:
    """Calibrate a new sensor (the wizard), or run one step with a subcommand."""
    given = [n for n, v in (("--sensor", sensor), ("--rig", rig), ("--gauge", gauge),
                            ("--config", config), ("--out", out), ("--work", work),
                            ("--redo", redo), ("--model", model)) if v is not None]
    if ctx.invoked_subcommand is not None:
        if given:
            _fail(f"{', '.join(given)} belong to the wizard (`calibrate --sensor NAME ...`), not "
                  f"to `calibrate {ctx.invoked_subcommand}`")
        return
    if sensor is None:
        typer.echo(ctx.get_help())
        raise typer.Exit(0 if not given else 2)

    from tactile_deploy.calibration.wizard.config import WizardConfigError, load_wizard_config
    from tactile_deploy.calibration.wizard.ui import AutoUI, InteractiveUI
    from tactile_deploy.calibration.wizard.wizard import WizardError, run_wizard

    if not yes and not sys.stdin.isatty():
        _fail("the wizard asks questions: run it in a terminal, or pass --yes (with --config) "
              "for a non-interactive run")
    try:
        cfg = load_wizard_config(config) if config is not None else None
    except WizardConfigError as e:
        _fail(str(e))
    out = out or Path(sensor)
    if yes and rig is None and not source.startswith("virtual"):
        _fail("--yes cannot wait for hand presses: give a rig (--rig PORT --gauge PORT), or "
              "run without --yes")
    ui = AutoUI() if yes else InteractiveUI()
    try:
        code = run_wizard(sensor, source=source, rig=rig, gauge=gauge, config=cfg, out=out,
                          work=work, ui=ui, redo=redo, restart=restart, overwrite=overwrite,
                          model=model)
    except WizardError as e:
        _fail(str(e))
    raise typer.Exit(code)
