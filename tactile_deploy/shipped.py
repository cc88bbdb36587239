"""Where the data that ships with tactile-deploy is found: the one place that knows.

- Assets of the package (pad meshes, virtual-sensor configs, committed JSON Schemas) are package
  data of :mod:`tactile_deploy`, found through :mod:`importlib.resources`.
- The shipped sensor plugins (``plugins/``) and exported models (``exported/``) sit beside the
  package in a source checkout or an editable install.

Every path returned is a real folder or file on disk (tactile-deploy is not run from a zip
archive).
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def package_root() -> Path:
    """The folder of the installed :mod:`tactile_deploy` package."""
    root = files("tactile_deploy")
    if not isinstance(root, Path):
        raise RuntimeError(f"tactile_deploy is imported from {root}, not from files on disk; "
                           "install it as files (pip install tactile-deploy)")
    return root


def asset_dir(kind: str) -> Path:
    """Folder of the shipped assets of one kind: ``"pads"`` (meshes and their cards) or
    ``"sensors"`` (virtual-sensor configs)."""
    return package_root() / "assets" / kind


def plugins_dir() -> Path:
    """Folder of the shipped sensor plugins (one sub-folder per plugin)."""
    return package_root().parent / "plugins"


def models_dir() -> Path:
    """Folder of the exported models (ONNX graphs, adaptation steps, their model cards)."""
    return package_root().parent / "exported"


def model_path(name: str) -> Path:
    """A shipped model file by name, e.g. ``"gelslim_mesh.onnx"``."""
    return models_dir() / name
