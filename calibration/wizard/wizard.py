"""The calibration wizard: from a new sensor to a plugin the runtime loads.

    tactile-deploy calibrate --sensor NEW [--source SRC] [--rig PORT --gauge PORT | --rig simulated]
        [--config wizard.json] [--out DIR] [--work DIR] [--yes] [--redo STEP] [--restart]

Data flow of :func:`run_wizard` (each step in :mod:`tactile_deploy.calibration.wizard.steps`)::

    reference frame -> camera mapping + imaging grid -> ball presses + contact circles
        -> shading model (cross-validated) -> FEM material (optional) -> plugin folder + report

After each step the person sees its figures of merit and pictures and accepts it, corrects it
(circles), redoes it, or stops; an accepted step is recorded in the work folder's state file, so
that the same command resumes after an interruption. ``--yes`` accepts every default answer.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from tactile_deploy.calibration.wizard.config import WizardConfig, wizard_config_from_dict
from tactile_deploy.calibration.wizard.context import Context, Outcome, StepError
from tactile_deploy.calibration.wizard.state import (
    STEP_TITLES,
    STEPS,
    WizardState,
    WizardStateError,
    WorkFolder,
    now_iso,
)
from tactile_deploy.calibration.wizard.station import Station, StationError
from tactile_deploy.calibration.wizard.steps import STEP_FUNCTIONS

#: Exit codes: done, bad input or a failed step, stopped by the person (resumable).
EXIT_OK, EXIT_ERROR, EXIT_STOPPED = 0, 1, 130

_NAME = re.compile(r"^[a-z0-9][a-z0-9_\-]*$")


class WizardError(ValueError):
    """Bad arguments or a work folder that does not fit them (the message says what to do)."""


def default_work_folder(out: Path) -> Path:
    """Where the steps' data live: beside the plugin folder, ``<out>.calibration``."""
    return out.parent / f"{out.name}.calibration"


def open_station(source: str, rig: str | None, gauge: str | None,
                 config: WizardConfig) -> Station:
    """The station for ``--source``, ``--rig`` and ``--gauge`` (see the module docstring)."""
    from tactile_deploy.calibration.rig import RigConfigError, load_rig_config, rig_config_from_dict
    from tactile_deploy.calibration.wizard.station import CameraStation, VirtualStation
    from tactile_deploy.runtime.sources.config import (
        SourceSpecError,
        VirtualSourceConfig,
        parse_source,
    )

    try:
        src = parse_source(source)
    except SourceSpecError as e:
        raise WizardError(str(e)) from None
    overrides = config.rig.overrides()
    if isinstance(src, VirtualSourceConfig):
        if not src.sensor:
            raise WizardError("--source virtual needs a sensor name: --source virtual:gelslim2 "
                              "(see `tactile-deploy sensors list`)")
        if rig not in (None, "simulated"):
            raise WizardError(f"--rig {rig}: a virtual sensor cannot see a rig on a serial port; "
                              "use --rig simulated (a simulated rig that presses the virtual "
                              "sensor) or no rig")
        from tactile_deploy.sensors.catalog import list_sensors

        if src.sensor not in list_sensors():
            raise WizardError(f"--source virtual:{src.sensor}: no such virtual sensor; known: "
                              f"{', '.join(list_sensors())}")
        return VirtualStation(src.sensor, simulated_rig=rig == "simulated",
                              seed=config.presses.seed, rig_overrides=overrides)
    if rig == "simulated":
        raise WizardError("--rig simulated presses a virtual sensor: use it with --source "
                          "virtual:NAME")
    rig_config = None
    if rig is not None or config.rig_config is not None:
        if config.rig_config is not None:
            try:
                data = load_rig_config(config.rig_config).model_dump()
            except RigConfigError as e:
                raise WizardError(str(e)) from None
        else:
            data = {"stage": {}, "gauge": {}}
        if rig is not None:
            data["stage"]["port"] = rig
        if gauge is not None:
            data["gauge"]["port"] = gauge
        if not data["gauge"].get("port"):
            raise WizardError("--rig PORT needs --gauge PORT (the force gauge's serial port), "
                              "or a rig_config with both ports")
        data.update(overrides)
        try:
            rig_config = rig_config_from_dict(data, source=config.rig_config or "command line")
        except RigConfigError as e:
            raise WizardError(str(e)) from None
    return CameraStation(src, rig_config)


def _open_station(source: str, rig: str | None, gauge: str | None,
                  config: WizardConfig) -> Station:
    """:func:`open_station`; a source or rig that cannot be opened is a :class:`WizardError`."""
    from tactile_deploy.calibration.rig import RigError
    from tactile_deploy.runtime.sources.base import SourceError

    try:
        return open_station(source, rig, gauge, config)
    except (SourceError, RigError, StationError) as e:
        raise WizardError(f"--source {source}" + (f" --rig {rig}" if rig else "")
                          + f": {e}") from None


def _prepare_state(work: WorkFolder, sensor: str, source: str, rig: str | None,
                   config: WizardConfig, config_given: bool, redo: str | None, restart: bool,
                   ui) -> tuple[WizardState, WizardConfig]:
    """Start a calibration or pick up the one in ``work`` (see the module docstring)."""
    if work.exists() and restart:
        shutil.rmtree(work.folder)
    if work.exists():
        state = work.load()
        if (state.sensor, state.source, state.rig) != (sensor, source, rig):
            raise WizardError(
                f"{work.folder} holds a calibration of {state.sensor!r} from --source "
                f"{state.source} (rig {state.rig}), not of {sensor!r} from {source} (rig {rig}): "
                "use another --work folder, or --restart to start over")
        stored = wizard_config_from_dict(state.config, str(work.state_path))
        if config_given and stored != config:
            changed = sorted(k for k in type(config).model_fields
                             if getattr(config, k) != getattr(stored, k))
            if redo is None:
                raise WizardError(
                    f"{work.folder} was started with another config (different: "
                    f"{', '.join(changed)}); pass --redo STEP to redo from a step with the new "
                    "config, or --restart to start over")
            state.config = config.model_dump(mode="json")
            work.save(state)
        else:
            config = stored
        done = [s for s in STEPS if state.done(s)]
        ui.say(f"Resuming the calibration of [bold]{sensor}[/] in {work.folder} (started "
               f"{state.started}; done: {', '.join(done) or 'nothing yet'}).")
        if ui.interactive and done and redo is None:
            choices = [("resume", f"Resume at {state.first_pending() or 'the end'}")]
            choices += [(s, f"Redo from '{s}'") for s in done]
            choices += [("restart", "Start over")]
            pick = ui.choose("Resume?", choices, "resume")
            if pick == "restart":
                shutil.rmtree(work.folder)
                return _prepare_state(work, sensor, source, rig, config, config_given, None,
                                      False, ui)
            if pick != "resume":
                redo = pick
        if redo is not None:
            gone = work.forget_from(state, redo)
            if gone:
                ui.say(f"Redoing from '{redo}': {', '.join(gone)} will run again.")
        return state, config
    state = WizardState(sensor=sensor, source=source, rig=rig,
                        config=config.model_dump(mode="json"), started=now_iso())
    return work.create(state), config


def _open_pictures(ui, figures) -> None:
    """Open the figures in the desktop's image viewer (or say where they are)."""
    import typer

    for f in figures:
        try:
            failed = typer.launch(str(f)) != 0
        except OSError:
            failed = True
        if failed:
            ui.say(f"could not open {f} here: open it in an image viewer")


def _run_step(ctx: Context, step: str, index: int) -> bool:
    """Run one step until the person accepts it (True) or stops (False)."""
    ui = ctx.ui
    while True:
        ui.heading(index + 1, len(STEPS), STEP_TITLES[step])
        try:
            outcome: Outcome = STEP_FUNCTIONS[step](ctx)
        except (StepError, StationError) as e:
            ui.say(f"[bold red]step '{step}' failed:[/] {e}")
            if not ui.interactive:
                raise
            if ui.choose("What now?", [("redo", "Redo this step"),
                                       ("quit", "Stop here (resume later)")], "redo") == "quit":
                return False
            continue
        while True:
            ui.show_result(f"{step}: figures of merit", outcome.metrics, outcome.figures,
                           outcome.notes)
            choices = [("accept", "Accept and go on")]
            choices += [(key, label) for key, label, _ in outcome.actions]
            if ui.interactive and outcome.figures:
                choices.append(("view", "Open the pictures"))
            choices += [("redo", "Redo this step"), ("quit", "Stop here (resume later)")]
            pick = ui.choose(f"Step '{step}' done. Next?", choices, "accept")
            if pick == "view":
                _open_pictures(ui, outcome.figures)
                continue
            if pick == "accept":
                ctx.work.finish(ctx.state, step, outcome.metrics, outcome.figures, outcome.notes)
                return True
            if pick == "quit":
                return False
            if pick == "redo":
                break
            action = next(a for k, _, a in outcome.actions if k == pick)
            outcome = action()


def run_wizard(sensor: str, *, source: str, rig: str | None, gauge: str | None,
               config: WizardConfig | None, out: Path, work: Path | None, ui,
               redo: str | None = None, restart: bool = False, overwrite: bool = False,
               model: Path | None = None) -> int:
    """Run (or resume) the calibration; returns an exit code (EXIT_*)."""
    if not _NAME.match(sensor):
        raise WizardError(f"--sensor {sensor!r}: a plugin name is lower case letters, digits, "
                          "'-' and '_', starting with a letter or digit")
    if redo is not None and redo not in STEPS:
        raise WizardError(f"--redo {redo!r}: the steps are {', '.join(STEPS)}")
    config_given = config is not None
    config = config or WizardConfig()
    wf = WorkFolder(work or default_work_folder(out))
    station = None
    if restart or not wf.exists():
        # a new calibration: the source and rig must open before its state is written, so
        # that a mistyped --source leaves nothing behind
        station = _open_station(source, rig, gauge, config)
    try:
        try:
            state, config = _prepare_state(wf, sensor, source, rig, config, config_given, redo,
                                           restart, ui)
        except WizardStateError as e:
            raise WizardError(str(e)) from None
    except BaseException:
        if station is not None:
            station.close()
        raise
    if state.first_pending() is None:
        if station is not None:
            station.close()
        ui.say(f"Every step is done; the plugin is {out}. Pass --redo STEP to redo a step.")
        return EXIT_OK
    ui.say(f"Calibrating [bold]{sensor}[/]: frames from {source}"
           + (f", rig {rig}" if rig else ", presses by hand") + f"; work folder {wf.folder}")
    try:
        if station is None:
            try:
                station = _open_station(source, rig, gauge, config)
            except WizardError as e:  # resuming: what is done stays done
                raise WizardError(f"{e}; the steps done so far are kept in {wf.folder}: fix the "
                                  "source or rig and run the same command again") from None
        ui.say(f"station: {station.description}, {station.image_size[0]} x "
               f"{station.image_size[1]} px")
        ctx = Context(sensor, config, station, wf, ui, state, Path(out), overwrite, model)
        for i, step in enumerate(STEPS):
            if state.done(step):
                ui.say(f"[green]done[/] {step}: {STEP_TITLES[step]} ({state.steps[step].finished})")
                continue
            if not _run_step(ctx, step, i):
                ui.say(f"Stopped. Progress is kept in {wf.folder}: run the same command to go "
                       "on.")
                return EXIT_STOPPED
    except KeyboardInterrupt:
        ui.say(f"\nInterrupted. Progress is kept in {wf.folder} (finished steps only): run the "
               "same command to go on.")
        return EXIT_STOPPED
    except (StepError, StationError) as e:
        ui.say(f"[bold red]error:[/] {e}\nProgress is kept in {wf.folder}.")
        return EXIT_ERROR
    finally:
        if station is not None:
            station.close()
    ui.say(f"[bold green]Done.[/] Plugin {out} (report {Path(out) / 'calibration' / 'report.html'}"
           f"). Run it: tactile-deploy run --sensor {out}")
    return EXIT_OK
