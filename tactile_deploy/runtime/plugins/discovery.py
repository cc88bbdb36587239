"""Where sensor plugins are found (first found wins; a later plugin of the same name is reported
as shadowed by ``tactile-deploy plugins list``):

1. the folders listed in ``$TACTILE_DEPLOY_PLUGIN_PATH`` (``os.pathsep``-separated), each either a
   plugin folder or a folder of plugin folders;
2. packages that register entry points in the group ``tactile_deploy.plugins``: the entry point
   (``name = "package.module:attribute"``) loads to a :class:`PluginEntry` (folder plus optional
   :class:`PluginHooks`), a folder path, or a function returning either;
3. the shipped plugins (:func:`tactile_deploy.shipped.plugins_dir`).

Only entry-point plugins can bring code (:class:`PluginHooks`): a plugin folder on its own is
data, and loading it never runs code from it.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np

from tactile_deploy.runtime.plugins.manifest import MANIFEST_NAME, PluginError
from tactile_deploy.shipped import plugins_dir

log = logging.getLogger(__name__)

#: Entry-point group through which installed packages register plugins.
ENTRY_POINT_GROUP = "tactile_deploy.plugins"
#: Environment variable with extra plugin folders.
PLUGIN_PATH_ENV = "TACTILE_DEPLOY_PLUGIN_PATH"


# ------------------------------------------------------------------------------------ hooks
class PluginHooks:
    """Code a third-party sensor package may add (override what you need; defaults do nothing).

    Hooks are called by :class:`tactile_deploy.runtime.pipeline.ImagingPipeline` and the source
    factory; they must keep the documented shapes, dtypes and units.
    """

    def preprocess_frame(self, frame: np.ndarray) -> np.ndarray:
        """Raw camera frame (H, W, 3) uint8 RGB -> the same shape and dtype (e.g. colour
        correction, own demosaicing), before rectification."""
        return frame

    def postprocess_depth(self, depth_mm: np.ndarray) -> np.ndarray:
        """Depth map (128, 128) float32 mm on the model grid -> the same, before the model."""
        return depth_mm

    def open_source(self, config) -> object | None:
        """A :class:`~tactile_deploy.runtime.sources.base.FrameSource` for ``config`` (e.g. the
        sensor's own camera driver), or None to use the built-in sources."""
        return None


@dataclass(frozen=True)
class PluginEntry:
    """What an entry point of the group ``tactile_deploy.plugins`` provides."""

    folder: Path
    hooks: PluginHooks | None = None


@dataclass(frozen=True)
class PluginLocation:
    """A plugin found by the registry: its name, folder, where it came from, its hooks."""

    name: str
    folder: Path
    origin: str
    hooks: PluginHooks | None = None


# ------------------------------------------------------------------------------------ registry
def _folder_plugins(root: Path, origin: str) -> list[PluginLocation]:
    if (root / MANIFEST_NAME).is_file():
        return [PluginLocation(root.name, root, origin)]
    if not root.is_dir():
        return []
    return [PluginLocation(p.name, p, origin) for p in sorted(root.iterdir())
            if (p / MANIFEST_NAME).is_file()]


def _entry_point_plugins() -> list[PluginLocation]:
    out = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
            if callable(obj) and not isinstance(obj, (PluginEntry, str, os.PathLike)):
                obj = obj()
            if isinstance(obj, (str, os.PathLike)):
                obj = PluginEntry(Path(obj))
            if not isinstance(obj, PluginEntry):
                raise TypeError(f"expected a PluginEntry or a folder path, got {type(obj).__name__}")
        except Exception as exc:  # a broken third-party package must not break the others
            log.warning("plugin entry point '%s' (%s) failed to load: %s", ep.name, ep.value, exc)
            continue
        dist = getattr(ep, "dist", None)
        origin = f"entry point {ep.value}" + (f" ({dist.name})" if dist is not None else "")
        out.append(PluginLocation(ep.name, Path(obj.folder), origin, obj.hooks))
    return out


def search_path() -> list[Path]:
    """Folders named by ``$TACTILE_DEPLOY_PLUGIN_PATH``, in order."""
    text = os.environ.get(PLUGIN_PATH_ENV, "")
    return [Path(p).expanduser() for p in text.split(os.pathsep) if p.strip()]


def discover_plugins() -> tuple[dict[str, PluginLocation], list[PluginLocation]]:
    """All plugins: ``(by name, shadowed)`` in the search order of the module docstring."""
    found: list[PluginLocation] = []
    for root in search_path():
        found += _folder_plugins(root, f"${PLUGIN_PATH_ENV}")
    found += _entry_point_plugins()
    found += _folder_plugins(plugins_dir(), "shipped")
    by_name: dict[str, PluginLocation] = {}
    shadowed = []
    for loc in found:
        if loc.name in by_name:
            shadowed.append(loc)
        else:
            by_name[loc.name] = loc
    return by_name, shadowed


def find_plugin(name_or_path: str | os.PathLike) -> PluginLocation:
    """A plugin by registered name, or by the path of its folder or manifest."""
    text = str(name_or_path)
    path = Path(text).expanduser()
    if os.sep in text or text.startswith(".") or path.is_dir() or path.suffix == ".json":
        folder = path.parent if path.suffix == ".json" else path
        if not (folder / MANIFEST_NAME).is_file():
            raise PluginError(f"{folder} is not a plugin folder (no {MANIFEST_NAME} in it)")
        return PluginLocation(folder.name, folder, "path")
    by_name, _ = discover_plugins()
    if text not in by_name:
        known = ", ".join(sorted(by_name)) or "none"
        raise PluginError(f"unknown sensor plugin {text!r}; installed plugins: {known} (run "
                          "`tactile-deploy plugins list`, or pass the path of a plugin folder)")
    return by_name[text]
