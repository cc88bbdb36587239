"""Command line of the indentation rig: ``simulate``, ``press`` and ``collect``.

``rig_app`` is a typer sub-app; it also runs on its own: ``python -m calibration.rig.cli --help``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional

import typer

from calibration.rig.config import (
    RigConfig,
    load_rig_config,
    rig_config_from_dict,
    save_rig_config,
)
from calibration.rig.errors import RigConfigError, RigError
from calibration.rig.indent import IndentationRig, check_press_depth

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
    from calibration.rig.simulated import HertzForce, SimulatedRig

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


@rig_app.command()
def collect(
    out: Path = typer.Option(..., help="The measured-data .npz to write (docs/discrepancy.md)."),
    indenter: str = typer.Option(..., help="Indenter on the rig: library name (`tactile-deploy "
                                 "indenters list`) or mesh path."),
    source: str = typer.Option(..., help="Frame source of the sensor's camera: camera:INDEX, a "
                               "device, video or folder; virtual:NAME with --simulated."),
    simulated: bool = typer.Option(False, "--simulated", help="Press a virtual sensor "
                                   "(--source virtual:NAME) with a simulated rig on "
                                   "pseudo-terminals."),
    config: Optional[Path] = typer.Option(None, help="Rig config JSON (see docs/rig.md)."),
    stage: Optional[str] = typer.Option(None, help="Stage port (overrides the config)."),
    gauge: Optional[str] = typer.Option(None, help="Force gauge port (overrides the config)."),
    plan: Optional[Path] = typer.Option(None, help="CSV of contacts: x_mm, y_mm, depth_mm "
                                        "(sensor frame); default: --n random ones."),
    n: int = typer.Option(24, min=1, help="Random contacts (without --plan)."),
    radius_mm: float = typer.Option(7.0, min=0.0, help="Random contacts within this radius of "
                                    "the centre, mm."),
    depth_range: str = typer.Option("0.3,0.9", help="Random contacts' depths: min,max, mm."),
    seed: int = typer.Option(0, min=0, help="Seed of the random contacts."),
    theta_deg: float = typer.Option(0.0, help="The indenter's angle about z on the tool "
                                    "holder, sensor frame, degrees."),
    plugin: Optional[str] = typer.Option(None, help="The unit's plugin: its imaging pipeline "
                                         "adds depth maps (and measures their noise)."),
    frames_per_press: int = typer.Option(1, min=1, help="Frames grabbed at each press."),
    reference_frames: int = typer.Option(8, min=0, help="No-contact frames grabbed first (the "
                                         "depth maps' noise)."),
    keep_frames: bool = typer.Option(True, "--keep-frames/--no-frames", help="Store the frames "
                                     "(--no-frames: depth maps only, needs --plugin)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out."),
) -> None:
    """Press a plan of contacts and record frames (and depth maps), commanded contacts and
    forces as measured data for ``tactile-deploy discrepancy``."""
    from calibration.discrepancy.collect import (
        collect_presses,
        load_plan,
        plan_contacts,
        save_collection,
    )
    from tactile_deploy.outputs import OutputPathError, check_output_file

    try:
        check_output_file(out, "--out", overwrite=overwrite, inputs=[plan, config])
    except OutputPathError as exc:
        _fail(str(exc))
    if out.suffix != ".npz":
        _fail(f"--out {out}: measured data are an .npz file")
    try:
        if plan is not None:
            contacts = load_plan(plan)
        else:
            parts = [float(v) for v in depth_range.split(",")]
            if len(parts) != 2:
                raise ValueError(f"--depth-range {depth_range!r}: expected min,max in mm")
            contacts = plan_contacts(n, radius_mm, (parts[0], parts[1]), seed)
    except (ValueError, FileNotFoundError) as exc:
        _fail(str(exc))
    pipeline = None
    if plugin is not None:
        from tactile_deploy.runtime.pipeline import ImagingPipeline
        from tactile_deploy.runtime.plugins import PluginError, SensorPlugin

        try:
            pipeline = ImagingPipeline.from_plugin(SensorPlugin.load(plugin))
        except PluginError as exc:
            _fail(f"--plugin {plugin}: {exc}")
    elif not keep_frames:
        _fail("--no-frames needs --plugin (the depth maps come from its imaging pipeline)")
    from tactile_deploy.indenters import get_indenter

    try:
        get_indenter(indenter)
    except (ValueError, OSError) as exc:
        _fail(f"--indenter {indenter}: {exc}")

    def run(rig, grab, retract=None):
        with typer.progressbar(length=len(contacts), label="pressing", file=sys.stderr) as bar:
            return collect_presses(rig, grab, contacts, indenter, theta_deg=theta_deg,
                                   frames_per_press=frames_per_press,
                                   reference_frames=reference_frames, pipeline=pipeline,
                                   source=source, plugin=plugin, keep_frames=keep_frames,
                                   retract=retract, progress=bar.update)

    try:
        if simulated:
            from calibration.rig.virtual_bench import VirtualPressBench
            from tactile_deploy.sensors.catalog import UnknownSensorError, load_sensor

            if not source.startswith("virtual:"):
                _fail(f"--simulated presses a virtual sensor: give --source virtual:NAME, got "
                      f"{source!r}")
            try:
                sensor = load_sensor(source.split(":", 1)[1])
            except (UnknownSensorError, FileNotFoundError) as exc:
                _fail(f"--source {source}: {exc}")
            if config is not None or stage is not None or gauge is not None:
                _fail("--simulated runs its own rig: leave out --config, --stage and --gauge")
            with VirtualPressBench(sensor, indenter, theta_deg, seed) as bench:
                data, log = run(bench.rig, bench.grab)
        else:
            if source.startswith("virtual"):
                _fail("a virtual sensor is pressed by a simulated rig: add --simulated")
            from calibration.wizard.station import CameraStation
            from tactile_deploy.runtime.sources.base import SourceError
            from tactile_deploy.runtime.sources.config import SourceSpecError, parse_source

            try:
                station = CameraStation(parse_source(source), _press_config(config, stage,
                                                                            gauge))
            except (SourceSpecError, SourceError) as exc:
                _fail(f"--source {source}: {exc}")
            try:
                data, log = run(station.rig, station.grab)
            finally:
                station.close()
    except (RigError, RigConfigError, ValueError) as exc:
        _fail(str(exc))
    save_collection(out, data, log)
    kept = len(log.recorded)
    typer.echo(f"{kept} of {len(contacts)} presses recorded ({data.n} samples"
               + (", frames" if data.frames is not None else "")
               + (", depth maps" if data.depth_mm is not None else "") + f") in {out}"
               + (f"; depth noise {1e3 * log.noise_mm:.2f} um" if log.noise_mm else ""))
    if kept < len(contacts):
        typer.echo(f"{len(contacts) - kept} presses stopped at the force limit and were not "
                   "recorded (see rig_log in the file)", err=True)


if __name__ == "__main__":
    rig_app()
