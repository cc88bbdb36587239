"""``tactile-deploy reference --sensor NAME [--plugins-dir DIR] [--source SRC] [--frames N]``."""

from __future__ import annotations

from pathlib import Path

import typer

from tactile_deploy.cli.common import console, fail


def reference_command(
    sensor: str = typer.Option(..., "--sensor", help="Sensor plugin name or folder."),
    source: str | None = typer.Option(
        None, "--source", help="Frames of the sensor with nothing touching it: camera index "
        "(0) or /dev/videoN | image folder | image file's folder | video | recording.npz. "
        "Default: the plugin's default source."),
    frames: int = typer.Option(16, "--frames", min=1, help="Frames averaged."),
    plugins_dir: list[Path] | None = typer.Option(None, "--plugins-dir", help="Folder of "
                                                  "plugin folders to search first."),
) -> None:
    """Re-take the sensor's no-contact frame (nothing may touch the gel) and update the plugin."""
    from tactile_deploy.runtime.plugin_dirs import add_plugin_dirs
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin, validate_plugin
    from tactile_deploy.runtime.reference import retake_reference
    from tactile_deploy.runtime.sources.base import SourceError
    from tactile_deploy.runtime.sources.config import SourceSpecError, parse_source
    from tactile_deploy.runtime.sources.factory import make_source

    try:
        add_plugin_dirs(plugins_dir)
        plugin = SensorPlugin.load(sensor)
        if source is None:
            config, from_manifest = plugin.manifest.default_source, True
        else:
            config, from_manifest = parse_source(source), False
        src = make_source(config, plugin, from_manifest=from_manifest)
        result = retake_reference(plugin, src, frames)
    except (PluginError, SourceError, SourceSpecError, FileNotFoundError) as e:
        fail(str(e))
    report = validate_plugin(result.plugin, check_model=False)
    if not report.ok:
        fail("the updated plugin does not validate: " + "; ".join(report.problems), code=1)
    off = ", ".join(f"{v:+.1f}" for v in result.offset_grey)
    console.print(f"new no-contact frame of {plugin.name}: {result.reference_file.name} (mean of "
                  f"{result.n_frames} frames; illumination offset against the previous R, G, B "
                  f"{off} grey levels; colour edges {result.edge_score:.2f} against "
                  f"{result.previous_edge_score:.2f})")
    console.print(f"no-contact depth: {result.noise_file.name}; plugin.json updated")
