"""Command line of the indentation rig: ``simulate`` and ``press``.

``rig_app`` is a typer sub-app; it also runs on its own: ``python -m tactile_deploy.calibration.rig.cli --help``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from tactile_deploy.calibration.rig.config import (
    RigConfig,
    load_rig_config,
    rig_config_from_dict,
    save_rig_config,
)
from tactile_deploy.calibration.rig.errors import RigConfigError, RigError
from tactile_deploy.calibration.rig.indent import IndentationRig, check_press_depth

rig_app = typer.Typer(
    help="Indentation rig: a G-code stage and a force gauge on serial ports.",
    no_args_is_help=True,
    add_completion=False,
)

#: Exit code of ``press`` when the force limit stopped the press.
EXIT_FORCE_LIMITED = 3


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(1)


@rig_app.command()
def simulate(
    stiffness: float = typer.Option(
        0.7, help="k of the simulated force F = k * indentation^1.5, N/mm^1.5."
    ),
    noise_n: float = typer.Option(0.0, help="Standard deviation of the gauge noise, N."),
    offset_n: float = typer.Option(0.0, help="Zero offset of the simulated gauge, N."),
    seed: int = typer.Option(0, help="Seed of the gauge noise."),
    config: Optional[Path] = typer.Option(
        None, help="Rig config whose stage frame places the virtual sensor (default frame if "
        "omitted)."
    ),
    write_config: Optional[Path] = typer.Option(
        None, help="Write a rig config pointing at the simulated ports to this JSON file."
    ),
    duration_s: float = typer.Option(
        0.0, min=0.0, help="Stop after this many seconds (0: run until Ctrl-C)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing "
                                   "--write-config file."),
) -> None:
    """Start a simulated rig on two pseudo-terminals, print their names, run until Ctrl-C."""
    from tactile_deploy.outputs import OutputPathError, check_output_file
    from tactile_deploy.calibration.rig.simulated import HertzForce, SimulatedRig

    if write_config is not None:
        try:
            check_output_file(write_config, "--write-config", overwrite=overwrite,
                              inputs=[config])
        except OutputPathError as exc:
            _fail(str(exc))
    base = None
    if config is not None:
        try:
            base = load_rig_config(config)
        except RigConfigError as exc:
            _fail(str(exc))
    sim = SimulatedRig(
        HertzForce(stiffness),
        frame=base.stage.frame if base is not None else None,
        noise_std_n=noise_n,
        offset_n=offset_n,
        seed=seed,
    )
    with sim:
        if base is not None:
            data = base.model_dump()
            data["stage"]["port"] = sim.stage_port
            data["gauge"]["port"] = sim.gauge_port
            sim_config = rig_config_from_dict(data, source=str(config))
        else:
            sim_config = sim.rig_config()
        typer.echo(f"stage port: {sim.stage_port}")
        typer.echo(f"gauge port: {sim.gauge_port}")
        if write_config is not None:
            save_rig_config(sim_config, write_config)
            typer.echo(f"rig config: {write_config}")
        ports = (f"--config {write_config}" if write_config is not None else
                 (f"--config {config} " if config is not None else "")
                 + f"--stage {sim.stage_port} --gauge {sim.gauge_port}")
        typer.echo(f"try: tactile-deploy rig press {ports} --x-mm 0 --y-mm 0 --depth-mm 1")
        typer.echo("simulated rig running; Ctrl-C to stop" if duration_s == 0 else
                   f"simulated rig running for {duration_s:g} s")
        try:
            if duration_s > 0:
                time.sleep(duration_s)
            else:
                while True:
                    time.sleep(0.5)
        except KeyboardInterrupt:
            pass
    typer.echo("simulated rig stopped")


def _press_config(config: Optional[Path], stage: Optional[str], gauge: Optional[str]) -> RigConfig:
    if config is not None:
        data = load_rig_config(config).model_dump()
        source = str(config)
    else:
        if stage is None or gauge is None:
            raise RigConfigError(
                "give --stage PORT and --gauge PORT, or --config FILE with both ports"
            )
        data = {"stage": {}, "gauge": {}}
        source = "command line"
        typer.echo(
            "warning: no --config, using the default stage frame (that of the simulated rig); "
            "pass --config with the calibrated frame for real hardware",
            err=True,
        )
    if stage is not None:
        data["stage"]["port"] = stage
    if gauge is not None:
        data["gauge"]["port"] = gauge
    return rig_config_from_dict(data, source=source)


@rig_app.command()
def press(
    x_mm: float = typer.Option(..., help="Contact x, sensor frame, mm."),
    y_mm: float = typer.Option(..., help="Contact y, sensor frame, mm."),
    depth_mm: float = typer.Option(..., min=0.0, help="Depth below the gel surface, mm."),
    stage: Optional[str] = typer.Option(None, help="Stage port (overrides the config)."),
    gauge: Optional[str] = typer.Option(None, help="Force gauge port (overrides the config)."),
    config: Optional[Path] = typer.Option(None, help="Rig config JSON (see docs/rig.md)."),
    surface_z_mm: float = typer.Option(
        0.0, help="Sensor-frame z of the gel surface at (x, y), mm (0 for a flat pad)."
    ),
    home: bool = typer.Option(True, help="Home the stage (G28) before pressing."),
    json_output: bool = typer.Option(False, "--json", help="Print the press record as JSON."),
) -> None:
    """Press once at a sensor-frame contact and print the force.

    Exit code 1 on a rig or config error, 3 when the force limit stopped the press.
    """
    try:
        check_press_depth(depth_mm)
    except ValueError as exc:
        _fail(f"--depth-mm: {exc}")
    try:
        cfg = _press_config(config, stage, gauge)
        with IndentationRig(cfg) as rig:
            if home:
                rig.home()
            record = rig.press(x_mm, y_mm, depth_mm, surface_z_mm=surface_z_mm)
    except (RigError, RigConfigError, ValueError) as exc:
        _fail(str(exc))
    if json_output:
        typer.echo(record.model_dump_json(indent=2))
    else:
        sx, sy, sz = record.stage_readback_mm
        typer.echo(
            f"force {record.force_n:.3f} N at sensor (x, y) = ({x_mm:.3f}, {y_mm:.3f}) mm, depth "
            f"{record.reached_depth_mm:.3f} mm; stage read-back X={sx:.3f} Y={sy:.3f} "
            f"Z={sz:.3f} mm"
        )
    if record.force_limited:
        typer.echo(
            f"force limit: {record.max_force_n:.3f} N > force_limit_n={cfg.force_limit_n:g} N at "
            f"depth {record.reached_depth_mm:.3f} of {depth_mm:.3f} mm; the stage backed off",
            err=True,
        )
        raise typer.Exit(EXIT_FORCE_LIMITED)


if __name__ == "__main__":
    rig_app()
