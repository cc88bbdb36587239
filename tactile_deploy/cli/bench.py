"""``tactile-deploy bench NAME``: run a benchmark script of ``bench/`` (source checkout)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path
from typing import List, Optional

import typer

from tactile_deploy.cli.common import fail

bench_app = typer.Typer(help="Benchmarks; results go to BENCHMARKS.md.", no_args_is_help=True)

BENCH_DIR = Path(__file__).resolve().parents[2] / "bench"

#: benchmark name -> script in bench/
BENCHMARKS = {
    "sim": "bench_sim.py",
    "sim-gpu": "bench_sim_gpu.py",
    "sim-resolved": "bench_sim_resolved.py",
    "shading": "bench_shading.py",
    "optics": "bench_optics.py",
    "predictor": "bench_predictor.py",
    "runtime": "bench_runtime.py",
    "adapt": "bench_adapt.py",
    "adapt-tables": "bench_adapt_tables.py",
    "discrepancy": "bench_discrepancy.py",
    "recording": "bench_recording.py",
    "families": "bench_families.py",
}


def _run_script(name: str, args: list[str]) -> None:
    script = BENCH_DIR / BENCHMARKS[name]
    if not script.exists():
        fail(f"benchmark script {script} not found: benchmarks run from a source checkout of tactile-deploy")
    sys.argv = [str(script), *args]
    runpy.run_path(str(script), run_name="__main__")


def _make(name: str):
    def command(
        ctx: typer.Context,
        args: Optional[List[str]] = typer.Argument(None, help="Options passed to the script (see --help after --)."),
    ) -> None:
        _run_script(name, list(args or []))

    command.__doc__ = f"Run bench/{BENCHMARKS[name]} (pass its options after --)."
    return command


for _name in BENCHMARKS:
    bench_app.command(_name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(_make(_name))
