"""``tactile-deploy rig ...``: the rig's commands (:mod:`tactile_deploy.calibration.rig.cli`: ``simulate``,
``press``) and ``collect``, which presses a plan of contacts and records them as measured data
for the discrepancy workflow (:mod:`tactile_deploy.calibration.discrepancy.collect`), with a camera station of
the wizard (:mod:`tactile_deploy.calibration.wizard.station`) or a virtual sensor on a simulated rig.

Registered with the ``tactile-deploy`` command through the ``tactile_deploy.cli`` entry-point
group (see pyproject.toml).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from tactile_deploy.calibration.discrepancy.collect import (
    collect_presses,
    load_plan,
    plan_contacts,
    save_collection,
)
from tactile_deploy.calibration.rig.cli import _fail, _press_config, rig_app
from tactile_deploy.calibration.rig.errors import RigConfigError, RigError

__all__ = ["rig_app"]


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
            from tactile_deploy.calibration.rig.virtual_bench import VirtualPressBench
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
            from tactile_deploy.calibration.wizard.station import CameraStation
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

