"""``tactile-deploy calibrate --sensor NAME --pad FAMILY --presses DIR ... --yes``: the command.

The ``calibrate`` group's callback (calibration/wizard/cli.py) hands over here when ``--presses``
is given: a recording becomes a plugin without questions (``--yes`` states that none are asked;
without it the same happens, as nothing needs answering).
"""

from __future__ import annotations

from pathlib import Path

import typer


def _fail(message: str, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def calibrate_from_recording(sensor: str, pad: str | None, presses: Path,
                             ball_radius_mm: float | None, reference: Path | None,
                             annotations: Path | None, mm_per_px: float | None,
                             plugins_dir: Path | None, out: Path | None, overwrite: bool,
                             folds: int, shallow_presses: bool = False,
                             readout: Path | None = None) -> None:
    """Run :func:`tactile_deploy.calibration.recording.build.calibrate_recording` and print what it did."""
    from tactile_deploy.calibration.recording.build import calibrate_recording
    from tactile_deploy.calibration.recording.errors import PlausibilityError
    from tactile_deploy.calibration.shading.presses import PressDataError
    from tactile_deploy.pad.family import FAMILIES
    from tactile_deploy.runtime.plugins import PluginError

    if pad is None:
        _fail(f"--presses needs --pad FAMILY, the sensor's pad family: one of "
              f"{', '.join(sorted(FAMILIES))}")
    if ball_radius_mm is None:
        _fail("--presses needs --ball-radius-mm R: the radius (not the diameter) of the "
              "calibration ball, mm")
    try:
        result = calibrate_recording(
            sensor, pad, presses, ball_radius_mm=ball_radius_mm, reference=reference,
            annotations=annotations, mm_per_px=mm_per_px, out=out, plugins_dir=plugins_dir,
            overwrite=overwrite, folds=folds, shallow_presses=shallow_presses, readout=readout,
            say=lambda m: typer.echo(m, err=True))
    except (PlausibilityError, PressDataError, PluginError) as e:
        _fail(str(e))
    for note in result.notes:
        typer.echo(f"note: {note}")
    for key, value in result.metrics.items():
        typer.echo(f"  {key}: {value:.4g}" if isinstance(value, float) else f"  {key}: {value}")
    if result.held_out:
        worst = max(result.held_out, key=lambda r: r.shape_um)
        typer.echo(f"  worst held-out press: {worst.name} ({worst.shape_um:.1f} um, radius "
                   f"{100 * worst.radius_error:+.1f} %, {worst.centre_distance_px:.0f} px from "
                   "the image centre)")
    typer.echo(f"wrote plugin {result.plugin}")
    where = f" --plugins-dir {plugins_dir}" if plugins_dir is not None else ""
    name = sensor if plugins_dir is not None else str(result.plugin)
    typer.echo(f"use it: tactile-deploy run --sensor {name}{where} --source FRAMES_DIR "
               "--format npz --out OUT")
