"""Shared pieces of the command line: consoles, error exits, progress bars."""

from __future__ import annotations

from contextlib import contextmanager

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

console = Console()
err_console = Console(stderr=True)


def fail(message: str, code: int = 2) -> None:
    """Print ``message`` as an error (what went wrong and what to do) and exit."""
    from rich.markup import escape

    err_console.print(f"[bold red]error:[/] {escape(message)}")  # brackets in paths or commands are text
    raise typer.Exit(code)


@contextmanager
def progress_bar(description: str, total: int, unit: str = "items"):
    """A rich progress bar; yields ``advance(n)``."""
    columns = [
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn(f"{{task.fields[rate]}} {unit}/s"),
        TimeElapsedColumn(),
    ]
    with Progress(*columns, console=err_console, transient=False) as progress:
        task = progress.add_task(description, total=total, rate="-")

        def advance(n: int = 1, rate: float | None = None) -> None:
            fields = {} if rate is None else {"rate": f"{rate:.1f}"}
            progress.update(task, advance=n, **fields)

        yield advance


def prepare_simulator(sim) -> None:
    """Load the simulator's operators, with a progress bar when they must be computed."""
    from tactile_deploy.fem.simulator import cache_dir

    folder = cache_dir() / f"surface_{sim.operator_key}"
    if (folder / "C.npy").exists():
        sim.prepare()
        return
    err_console.print(
        f"computing surface operators once for nu={sim.material.nu}, friction={sim.material.friction} "
        f"(cached in {cache_dir()})"
    )
    with progress_bar("Green's functions", sim.n_operator_columns, "columns") as advance:
        sim.prepare(progress=advance)
