"""User plugin folders: ``--plugins-dir DIR`` and ``$TACTILE_DEPLOY_PLUGIN_PATH``.

A plugin folder (``DIR/NAME/plugin.json``) is found by name once ``DIR`` is on the search path
(:mod:`tactile_deploy.runtime.plugins`): ``$TACTILE_DEPLOY_PLUGIN_PATH`` lists such folders for
every command (``os.pathsep``-separated); ``--plugins-dir DIR`` puts ``DIR`` ahead of them for
one command (``tactile-deploy calibrate ... --plugins-dir DIR`` writes the new plugin there,
``run``, ``reference``, ``adapt`` ... find it there by name).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from tactile_deploy.runtime.plugins import PLUGIN_PATH_ENV, PluginError


def check_plugins_dir(folder: str | os.PathLike, option: str = "--plugins-dir") -> Path:
    """``folder`` as an absolute path, or a :class:`PluginError` when it is no folder."""
    path = Path(folder).expanduser()
    if path.exists() and not path.is_dir():
        raise PluginError(f"{option} {folder}: is a file; give the folder that holds plugin "
                          "folders (DIR/NAME/plugin.json)")
    if not path.is_dir():
        raise PluginError(f"{option} {folder}: folder not found; create it, or give the folder "
                          "that holds your plugin folders")
    return path.absolute()


def add_plugin_dirs(folders: Iterable[str | os.PathLike] | None) -> list[Path]:
    """Put ``folders`` ahead of ``$TACTILE_DEPLOY_PLUGIN_PATH`` for this process (and the
    processes it starts); returns them as absolute paths."""
    added = [check_plugins_dir(f) for f in (folders or [])]
    if added:
        current = [p for p in os.environ.get(PLUGIN_PATH_ENV, "").split(os.pathsep) if p.strip()]
        os.environ[PLUGIN_PATH_ENV] = os.pathsep.join([str(p) for p in added] + current)
    return added
