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
    pad: Optional[str] = typer.Option(None, "--pad", help="With --presses: the sensor's pad "
                                      "family (gelslim, gelsight_mini, digit)."),
    presses: Optional[Path] = typer.Option(
        None, "--presses", help="A folder of recorded ball presses (and a no-contact frame): "
        "calibrate from it in one command, no prompts (docs/calibration.md)."),
    reference: Optional[Path] = typer.Option(
        None, "--reference", help="With --presses: the no-contact frame (default: picked from "
        "the recording)."),
    annotations: Optional[Path] = typer.Option(
        None, "--annotations", help="With --presses: contact circles, CSV "
        "img_names,center_x,center_y,radius (px); default: detected."),
    ball_radius_mm: Optional[float] = typer.Option(
        None, "--ball-radius-mm", help="With --presses: the ball's RADIUS, mm."),
    mm_per_px: Optional[float] = typer.Option(
        None, "--mm-per-px", help="With --presses: the frames' scale, mm per pixel (default: "
        "the frame spans the family's sensing area)."),
    plugins_dir: Optional[Path] = typer.Option(
        None, "--plugins-dir", help="With --presses: write the plugin into this folder of "
        "plugins (DIR/NAME), where `run --plugins-dir DIR --sensor NAME` finds it."),
    folds: int = typer.Option(5, "--folds", help="With --presses: held-out check, k-fold over "
                              "the presses (0: none)."),
    shallow_presses: bool = typer.Option(
        False, "--shallow-presses", help="With --presses: the ball radius is right although "
        "every contact stays within half of it (skips the diameter check)."),
    readout: Optional[Path] = typer.Option(
        None, "--readout", help="With --presses: a learned read-out (.onnx) of the pad family's "
        "design (e.g. exported/gelsight_mini_readout.onnx) reads the depth instead of the fitted "
        "shading model; its depth gain is calibrated from the ball's curvature."),
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
    recording_only = [n for n, v in (("--pad", pad), ("--reference", reference),
                                     ("--annotations", annotations),
                                     ("--ball-radius-mm", ball_radius_mm),
                                     ("--mm-per-px", mm_per_px), ("--plugins-dir", plugins_dir),
                                     ("--readout", readout))
                      if v is not None]
    if presses is not None:
        wizard_only = [n for n, v in (("--rig", rig), ("--gauge", gauge), ("--config", config),
                                      ("--work", work), ("--redo", redo), ("--model", model))
                       if v is not None] + (["--restart"] if restart else [])
        if wizard_only:
            _fail(f"{', '.join(wizard_only)} belong to the wizard, not to a calibration from "
                  "recorded presses (--presses)")
        from tactile_deploy.calibration.recording.cli import calibrate_from_recording

        calibrate_from_recording(sensor, pad, presses, ball_radius_mm, reference, annotations,
                                 mm_per_px, plugins_dir, out, overwrite, folds, shallow_presses,
                                 readout)
        return
    if recording_only:
        _fail(f"{', '.join(recording_only)} go with --presses DIR (a calibration from recorded "
              "presses); the wizard takes --source and --config")

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
