"""``tactile-deploy``: the command-line entry point.

Commands of this package are defined in the modules of :mod:`tactile_deploy.cli`; command groups
of the ``tactile_deploy.calibration`` and ``tactile_deploy.training`` packages register themselves
through the ``tactile_deploy.cli`` entry-point group (``name = "module:attribute"``, a Typer app or
a plain function), so the runtime never imports them.

A command that needs a library of an extra the install does not have (matplotlib, questionary,
torch, ...) ends with the ``pip install`` that brings it, exit status 2.
"""

from __future__ import annotations

import sys
from importlib.metadata import entry_points

import typer

from tactile_deploy.cli import adapt, bench, cameras, pad, plugins, reference, run, simulate

app = typer.Typer(
    name="tactile-deploy",
    help="Volumetric FEM meshes of tactile sensor pads from camera frames.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(show: bool) -> None:
    if show:
        from tactile_deploy.version import version_text

        typer.echo(version_text())
        raise typer.Exit()


@app.callback()
def _options(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                          help="Print the version, the code's sha256 and the library "
                                               "versions, and exit.")) -> None:
    """Volumetric FEM meshes of tactile sensor pads from camera frames."""


app.command("simulate")(simulate.simulate_command)
app.add_typer(pad.pad_app, name="pad")
app.add_typer(pad.indenters_app, name="indenters")
app.add_typer(bench.bench_app, name="bench")
app.command("run")(run.run_command)
app.add_typer(plugins.plugins_app, name="plugins")
app.command("adapt")(adapt.adapt_command)
app.command("cameras")(cameras.cameras_command)
app.command("reference")(reference.reference_command)


def _register_entry_points() -> None:
    for ep in entry_points(group="tactile_deploy.cli"):
        try:
            obj = ep.load()
        except Exception as exc:  # a broken optional package must not break the runtime CLI
            print(f"warning: command group '{ep.name}' ({ep.value}) failed to load: {exc}", file=sys.stderr)
            continue
        if isinstance(obj, typer.Typer):
            app.add_typer(obj, name=ep.name)
        else:
            app.command(ep.name)(obj)


_register_entry_points()


#: Import name of an optional library -> the extra that installs it (pyproject.toml).
EXTRA_OF = {
    "matplotlib": "figures", "questionary": "calibrate", "serial": "calibrate", "warp": "sim",
    "torch": "adapt", "onnx": "adapt", "onnxscript": "train", "mcap": "ros", "rosbags": "ros",
    "rerun": "view",
}


def missing_extra_message(exc: ModuleNotFoundError) -> str | None:
    """The line that tells which extra brings the missing module, or None when it is not one of
    an extra's (a defect, not an install choice)."""
    top = (exc.name or "").split(".")[0]
    extra = EXTRA_OF.get(top)
    if extra is None:
        return None
    return (f"error: this command needs {top}, which is not installed; install it with "
            f"pip install 'tactile-deploy[{extra}]'")


def main() -> None:
    try:
        app()
    except ModuleNotFoundError as exc:
        message = missing_extra_message(exc)
        if message is None:
            raise
        print(message, file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
