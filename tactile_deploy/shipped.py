"""Where the data that ships with tactile-deploy is found: the one place that knows.

- Assets of the package (pad meshes, virtual-sensor configs, committed JSON Schemas) are package
  data of :mod:`tactile_deploy`, found through :mod:`importlib.resources`.
- The shipped sensor plugins and exported models are folders of the installed package,
  ``tactile_deploy/plugins/`` and ``tactile_deploy/exported/`` (the wheel maps the repository's
  ``plugins/`` and ``exported/`` there, see setup.py). In a source checkout (and an editable
  install of one) they are the repository's ``plugins/`` and ``exported/`` beside the package.
  Both layouts keep the two folders side by side, so a plugin's relative model path
  (``../../exported/gelslim_mesh.onnx``) resolves in either.

Every path returned is a real folder or file on disk (tactile-deploy is not run from a zip
archive).
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

#: The shipped data folders, by name in both layouts.
PLUGINS = "plugins"
MODELS = "exported"


def package_root() -> Path:
    """The folder of the installed :mod:`tactile_deploy` package."""
    root = files("tactile_deploy")
    if not isinstance(root, Path):
        raise RuntimeError(f"tactile_deploy is imported from {root}, not from files on disk; "
                           "install it as files (pip install tactile-deploy)")
    return root


def installed() -> bool:
    """True when the shipped plugins and models are inside the installed package (a wheel
    install), False in a source checkout."""
    return (package_root() / PLUGINS).is_dir()


def shipped_root() -> Path:
    """The folder holding ``plugins/`` and ``exported/``: the package itself when installed from
    a wheel, else the source checkout's root."""
    root = package_root()
    return root if installed() else root.parent


def asset_dir(kind: str) -> Path:
    """Folder of the shipped assets of one kind: ``"pads"`` (meshes and their cards) or
    ``"sensors"`` (virtual-sensor configs)."""
    return package_root() / "assets" / kind


def plugins_dir() -> Path:
    """Folder of the shipped sensor plugins (one sub-folder per plugin)."""
    return shipped_root() / PLUGINS


def models_dir() -> Path:
    """Folder of the exported models (ONNX graphs, adaptation steps, their model cards)."""
    return shipped_root() / MODELS


def model_path(name: str) -> Path:
    """A shipped model file by name, e.g. ``"gelslim_mesh.onnx"``."""
    return models_dir() / name
