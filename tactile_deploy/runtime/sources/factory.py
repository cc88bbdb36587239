"""Build a frame source from its config (:mod:`.config`); the plugin resolves relative paths,
supplies the demo clip and may provide its own sources through :class:`PluginHooks`.

    make_source(parse_source("0"), plugin)          # camera 0
    make_source(DemoSourceConfig(), plugin)         # the plugin's demo clip
"""

from __future__ import annotations

import os
from pathlib import Path

from tactile_deploy.runtime.sources.base import FrameSource, SourceError
from tactile_deploy.runtime.sources.camera import OpenCVCamera
from tactile_deploy.runtime.sources.config import (
    SOURCE_FORMS,
    VIDEO_SUFFIXES,
    CameraSourceConfig,
    DemoSourceConfig,
    ImageFolderSourceConfig,
    NpzSourceConfig,
    VideoSourceConfig,
    VirtualSourceConfig,
)
from tactile_deploy.runtime.sources.images import ImageFolderSource
from tactile_deploy.runtime.sources.npz import NpzSource
from tactile_deploy.runtime.sources.video import VideoSource
from tactile_deploy.runtime.sources.virtual import VirtualSensorSource


def open_clip(path: str | os.PathLike, loop: bool = False, name: str | None = None) -> FrameSource:
    """A recorded clip: ``.npz`` (clip format) or a video file, chosen by suffix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":

        return NpzSource(path, loop=loop, name=name)
    if suffix in VIDEO_SUFFIXES:

        return VideoSource(path, loop=loop, name=name)
    raise SourceError(f"{path}: a clip must be a .npz recording or a video "
                      f"({', '.join(VIDEO_SUFFIXES)}), got {suffix or 'no suffix'!r}")


def _resolve(path: str, plugin, from_manifest: bool) -> Path:
    p = Path(path).expanduser()
    if from_manifest and plugin is not None and not p.is_absolute():
        return plugin.folder / p
    return p


def make_source(config, plugin=None, from_manifest: bool = False, **kwargs) -> FrameSource:
    """The frame source of ``config``.

    plugin : the :class:`~tactile_deploy.runtime.plugins.SensorPlugin` (needed by ``demo`` and
        ``virtual``; its hooks may supply the source).
    from_manifest : the config came from the plugin's manifest (relative paths are then relative
        to the plugin folder, else to the current folder).
    kwargs : passed to the source class (tests pass ``capture_factory`` and ``sleep``).
    """
    if plugin is not None:
        custom = plugin.hooks.open_source(config)
        if custom is not None:
            return custom
    if isinstance(config, DemoSourceConfig):
        if plugin is None:
            raise SourceError("the demo source plays a plugin's demo clip: pass --sensor NAME")
        return open_clip(plugin.demo_clip_path(), loop=config.loop,
                         name=f"demo clip of {plugin.name!r}")
    if isinstance(config, CameraSourceConfig):
        return OpenCVCamera(config, **kwargs)
    if isinstance(config, VideoSourceConfig):
        return VideoSource(_resolve(config.path, plugin, from_manifest), loop=config.loop,
                           **kwargs)
    if isinstance(config, ImageFolderSourceConfig):
        return ImageFolderSource(_resolve(config.path, plugin, from_manifest), config.pattern,
                                 config.fps, config.loop)
    if isinstance(config, NpzSourceConfig):
        return NpzSource(_resolve(config.path, plugin, from_manifest), loop=config.loop)
    if isinstance(config, VirtualSourceConfig):
        name = config.sensor or (_virtual_sensor_of(plugin) if plugin is not None else None)
        if name is None:
            raise SourceError("a virtual source needs a sensor name: --source virtual:NAME or "
                              "--sensor NAME")

        return VirtualSensorSource(name, n_frames=config.n_frames, seed=config.seed,
                                   loop=config.loop)
    forms = ", ".join(SOURCE_FORMS)
    raise SourceError(f"unknown frame source config {config!r}; known kinds: {forms}")


def _virtual_sensor_of(plugin) -> str:
    """The virtual sensor a plugin was calibrated on (its provenance ``source``,
    ``virtual:NAME``), else the plugin's own name (a copy under another name keeps its sensor)."""
    source = str(plugin.manifest.provenance.get("source", ""))
    return source.split(":", 1)[1] if source.startswith("virtual:") else plugin.name
