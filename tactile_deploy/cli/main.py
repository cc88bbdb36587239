"""``tactile-deploy``: the command-line entry point.

Commands of this package are defined in the modules of :mod:`tactile_deploy.cli`; command groups
of the ``calibration`` and ``training`` packages register themselves through the
``tactile_deploy.cli`` entry-point group (``name = "module:attribute"``, a Typer app or a plain
function), so the runtime never imports them.
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


def main() -> None:
    app()


if __name__ == "__main__":
    main()
