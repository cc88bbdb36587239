"""``tactile-deploy adapt --sensor NAME [--frames DIR | --source ...] [--steps N] [--device cpu|cuda]``."""

from __future__ import annotations

import re
from pathlib import Path

import typer

from tactile_deploy.cli.common import console, err_console, fail


def _refuse_installed_plugin(plugin) -> None:
    """Adapted versions are written into the plugin's folder: not into an installed package
    (a wheel's shipped plugins), where the next upgrade or uninstall would lose them."""
    from tactile_deploy.shipped import installed, plugins_dir

    if plugin.origin == "shipped" and installed() and plugin.folder.resolve().is_relative_to(plugins_dir().resolve()):
        fail(f"plugin {plugin.name!r} is shipped inside the installed package ({plugin.folder}), where adapted "
             f"versions would be lost at the next upgrade; adapt a copy of it: tactile-deploy plugins copy "
             f"{plugin.name} ./{plugin.name} && tactile-deploy adapt --sensor ./{plugin.name} ...")


def adapt_command(
    sensor: str = typer.Option("gelslim2", "--sensor", help="Sensor plugin name or folder (`tactile-deploy plugins list`)."),
    frames: Path | None = typer.Option(None, "--frames", help="Folder of the sensor's camera frames (images)."),
    pattern: str | None = typer.Option(None, "--pattern", help="Which files of --frames to read "
                                       "(default: every .png/.jpg/.jpeg/.bmp/.tif/.tiff file)."),
    source: str | None = typer.Option(
        None, "--source", help="Or a frame source: demo | camera index (0) | video | recording.npz | virtual[:NAME] "
        "(as in `tactile-deploy run`). Default: the plugin's default source."),
    max_frames: int | None = typer.Option(200, "--max-frames", min=2, help="Frames to collect (a camera: required)."),
    steps: int = typer.Option(200, "--steps", min=1, help="Adam steps."),
    batch_size: int = typer.Option(16, "--batch", min=1, help="Depth maps per step."),
    lr: float = typer.Option(1e-4, "--lr", min=0.0, help="Adam learning rate."),
    held_out: float = typer.Option(0.2, "--held-out", help="Share of frames kept aside to judge the adaptation "
                                   "(0.01 to 0.9)."),
    device: str = typer.Option("cpu", "--device", help="cpu | cuda (torch device)."),
    use_filter: bool | None = typer.Option(
        None, "--filter/--no-filter", help="Adapt towards the image VAE's reconstruction of each depth map (--filter, "
        "the paper's target) or towards the depth map itself (--no-filter). Default: the model's design: the "
        "surface-anchored graphs (the shipped GelSlim model) towards the map itself, the latent design towards VAE."),
    from_family: bool = typer.Option(False, "--from-family", help="Start from the family model, not the active "
                                     "adapted one."),
    step_dir: Path | None = typer.Option(None, "--step", help="Adaptation step folder (default: <family model>_adapt "
                                         "beside the family model)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the held-out split and the batch order."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="torch CPU threads (default: torch's)."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Measure only: write nothing to the plugin (with "
                                 "--rollback or --activate: say what they would do)."),
    rollback: bool = typer.Option(False, "--rollback", help="Make the previous adapted version (or the plugin's "
                                  "own model) active again, and stop."),
    activate: int | None = typer.Option(None, "--activate", help="Make kept version N active again (checked: its "
                                        "model file, and that it was adapted from the plugin's family model), and "
                                        "stop; --rollback then returns to the one active before."),
) -> None:
    """Adapt a plugin's model to its sensor from unlabelled frames (self-supervised); writes a new
    version into the plugin's adapted/ folder only when the held-out error improves (the plugin's
    own files are never changed)."""
    from tactile_deploy.adapt.card import CardError
    from tactile_deploy.adapt.weights import AdaptationUnavailable
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin
    from tactile_deploy.runtime.sources.base import SourceError
    from tactile_deploy.runtime.sources.config import ImageFolderSourceConfig, SourceSpecError, parse_source

    try:
        plugin = SensorPlugin.load(sensor)
    except PluginError as e:
        fail(str(e))
    if plugin.manifest.model is None:
        fail(f"plugin {plugin.name!r} has no learned model to adapt (pad "
             f"{plugin.manifest.family.pad}): its meshes come from the pad's physics lift, which "
             "reads the depth map directly; nothing to adapt")
    if not dry_run:
        _refuse_installed_plugin(plugin)
    if rollback or activate is not None:
        _switch_version(plugin, rollback, activate, dry_run)
        return
    if frames is not None and source is not None:
        fail("give --frames or --source, not both")
    if not re.fullmatch(r"cpu|cuda(:\d+)?", device):
        fail(f"--device must be cpu, cuda or cuda:N (N: the index of a CUDA device), got {device!r}")
    if not 0.01 <= held_out <= 0.9:
        fail(f"--held-out must be a share of the frames from 0.01 to 0.9, got {held_out:g}; e.g. --held-out 0.2 "
             "keeps a fifth of them aside")
    try:
        if frames is not None:
            if not frames.is_dir():
                fail(f"--frames {frames} is not a folder of images")
            config, from_manifest = ImageFolderSourceConfig(path=str(frames), pattern=pattern), False
        elif source is not None:
            config, from_manifest = parse_source(source), False
        else:
            config, from_manifest = plugin.manifest.default_source, True
        from tactile_deploy.adapt.step import require_torch
        from tactile_deploy.adapt.weights import require_onnx

        torch = require_torch()
        require_onnx()
        if threads is not None:
            torch.set_num_threads(threads)
        from tactile_deploy.adapt.workflow import (AdaptOptions, adapt_plugin, collect_depths, prepare_adaptation,
                                                   summary_lines)

        options = AdaptOptions(steps=steps, batch_size=batch_size, lr=lr, held_out=held_out, use_filter=use_filter,
                               device=device, seed=seed, start="family" if from_family else "active", write=not dry_run)
        step = prepare_adaptation(plugin, options, step_dir)  # every check that needs no frames, first
        depth, info = collect_depths(plugin, config, from_manifest, max_frames, log=err_console.print)
        err_console.print(f"{info['frames']} frames from {info['source']}" + (f" ({info['refused']} refused)" if info["refused"] else ""))
        with _loss_progress(steps) as progress:
            result = adapt_plugin(plugin, depth, options, step, progress=progress, log=err_console.print,
                                  source=info)
    except (typer.Exit, typer.Abort):  # fail() above: already said
        raise
    except (PluginError, CardError, AdaptationUnavailable, SourceSpecError, SourceError, ValueError,
            FileNotFoundError, PermissionError, RuntimeError) as e:
        fail(str(e))
    for line in summary_lines(result):
        console.print(line)
    if result.version is not None:
        console.print(f"[bold green]new version {result.version.version}[/] of {plugin.name}: {result.version.model} "
                      f"(active; `tactile-deploy adapt --sensor {plugin.sensor_option} --rollback` returns to the "
                      f"previous one); figure: {result.figure}")
    elif dry_run:
        console.print("dry run: nothing written; " + ("the adapted model is better: a version would have been written"
                                                    if result.improved else result.verdict))
    else:
        console.print(f"not written: {result.verdict}; {plugin.name} keeps its current model")


def _switch_version(plugin, rollback: bool, activate: int | None, dry_run: bool) -> None:
    """--rollback or --activate N (with --dry-run: say what it would do)."""
    from tactile_deploy.runtime.plugins.versions import activate as do_activate
    from tactile_deploy.runtime.plugins.versions import rollback as do_rollback

    if rollback and activate is not None:
        fail(f"give --rollback or --activate, not both (got --activate {activate} with --rollback)")
    if activate is not None and activate < 1:
        fail(f"--activate takes the number of a kept version (1 or more), got {activate}; --rollback returns to the "
             "plugin's own model")
    try:
        if rollback:
            was, now = do_rollback(plugin, dry_run=dry_run, warn=lambda m: err_console.print(f"warning: {m}"))
        else:
            was, now = do_activate(plugin, activate, dry_run=dry_run)
    except (ValueError, FileNotFoundError, PermissionError) as e:
        fail(str(e))
    name = {None: "the plugin's own model"}
    change = f"{name.get(was, f'version {was}')} -> {name.get(now, f'version {now}')}"
    if dry_run:
        console.print(f"dry run: {plugin.name} would go {change}; nothing written")
    elif was == now and not rollback:
        console.print(f"{plugin.name}: version {now} is already active; nothing changed")
    else:
        console.print(f"{plugin.name}: {change} (active now; all versions kept in {plugin.folder / 'adapted'}; "
                      f"`tactile-deploy adapt --sensor {plugin.sensor_option} --rollback` goes back)")


class _loss_progress:
    """Progress bar of the Adam steps with the live loss (RMS, um)."""

    def __init__(self, total: int):
        self.total = total

    def __enter__(self):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(TextColumn("[bold]adapting"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("loss {task.fields[loss]} um RMS"), TimeElapsedColumn(),
                                 console=err_console)
        self.progress.__enter__()
        self.task = self.progress.add_task("adapt", total=self.total, loss="-")

        def advance(k: int, loss_mm2: float) -> None:
            self.progress.update(self.task, completed=k, loss=f"{loss_mm2 ** 0.5 * 1e3:.2f}")

        return advance

    def __exit__(self, *exc):
        return self.progress.__exit__(*exc)
