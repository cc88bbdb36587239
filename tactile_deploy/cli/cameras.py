"""``tactile-deploy cameras``: the video devices of this computer, to choose ``--source``."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from tactile_deploy.cli.common import console


def cameras_command(
    as_json: bool = typer.Option(False, "--json", help="Print the list as JSON."),
    sysfs: Path = typer.Option(Path("/sys/class/video4linux"), "--sysfs", hidden=True),
    dev: Path = typer.Option(Path("/dev"), "--dev", hidden=True),
) -> None:
    """List cameras (Linux V4L2): index, device path, name, USB serial and stable by-id path."""
    from rich.table import Table

    from tactile_deploy.runtime.sources.devices import describe, list_cameras

    cams = list_cameras(sysfs, dev)
    if as_json:
        console.print_json(json.dumps([c.as_dict() for c in cams]))
        return
    if not cams:
        console.print(f"no video devices found (read {sysfs}); on systems without V4L2 give "
                      "the camera's index: --source 0")
        return
    table = Table("index", "path", "name", "stream", "serial", "USB id", "by-id path")
    for row in describe(cams):
        table.add_row(*row)
    console.print(table)
    console.print("use it with --source INDEX, --source /dev/v4l/by-id/... (stable across "
                  "reboots and ports) or --source serial:SERIAL; 'metadata?' nodes carry no image")
