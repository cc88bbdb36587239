"""Build a frame source from its config (:mod:`.config`); the plugin resolves relative paths,
supplies the demo clip and may provide its own sources through :class:`PluginHooks`.

    make_source(parse_source("0"), plugin)          # camera 0
    make_source(DemoSourceConfig(), plugin)         # the plugin's demo clip
"""

from __future__ import annotations

import os
from pathlib import Path

from tactile_deploy.runtime.sources.base import FrameSource, SourceError
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


def open_clip(path: str | os.PathLike, loop: bool = False, name: str | None = None) -> FrameSource:
    """A recorded clip: ``.npz`` (clip format) or a video file, chosen by suffix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        from tactile_deploy.runtime.sources.npz import NpzSource

        return NpzSource(path, loop=loop, name=name)
    if suffix in VIDEO_SUFFIXES:
        from tactile_deploy.runtime.sources.video import VideoSource

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
        from tactile_deploy.runtime.sources.camera import OpenCVCamera

        if plugin is not None:
            config = camera_config_for_plugin(config, plugin)
        return OpenCVCamera(config, **kwargs)
    if isinstance(config, VideoSourceConfig):
        from tactile_deploy.runtime.sources.video import VideoSource

        return VideoSource(_resolve(config.path, plugin, from_manifest), loop=config.loop,
                           **kwargs)
    if isinstance(config, ImageFolderSourceConfig):
        from tactile_deploy.runtime.sources.images import ImageFolderSource

        return ImageFolderSource(_resolve(config.path, plugin, from_manifest), config.pattern,
                                 config.fps, config.loop)
    if isinstance(config, NpzSourceConfig):
        from tactile_deploy.runtime.sources.npz import NpzSource

        return NpzSource(_resolve(config.path, plugin, from_manifest), loop=config.loop)
    if isinstance(config, VirtualSourceConfig):
        name = config.sensor or (_virtual_sensor_of(plugin) if plugin is not None else None)
        if name is None:
            raise SourceError("a virtual source needs a sensor name: --source virtual:NAME or "
                              "--sensor NAME")
        from tactile_deploy.runtime.sources.virtual import VirtualSensorSource

        return VirtualSensorSource(name, n_frames=config.n_frames, seed=config.seed,
                                   loop=config.loop)
    forms = ", ".join(SOURCE_FORMS)
    raise SourceError(f"unknown frame source config {config!r}; known kinds: {forms}")


def camera_config_for_plugin(config: CameraSourceConfig, plugin) -> CameraSourceConfig:
    """``config`` with what it leaves open taken from the plugin: the frame size of its camera
    mapping, and frame rate, pixel format, exposure and white balance of its default source when
    that is a camera (a camera given as ``--source 0`` is asked for what the plugin expects)."""
    cam = plugin.manifest.camera
    updates = {}
    if config.width_px is None:
        updates["width_px"] = cam.image_width_px
    if config.height_px is None:
        updates["height_px"] = cam.image_height_px
    default = plugin.manifest.default_source
    if isinstance(default, CameraSourceConfig):
        for name in ("fps", "fourcc", "exposure", "white_balance"):
            if getattr(config, name) is None and getattr(default, name) is not None:
                updates[name] = getattr(default, name)
        if "settle_s" not in config.model_fields_set and "settle_s" in default.model_fields_set:
            updates["settle_s"] = default.settle_s
    return config.model_copy(update=updates) if updates else config


def _virtual_sensor_of(plugin) -> str:
    """The virtual sensor a plugin was calibrated on (its provenance ``source``,
    ``virtual:NAME``), else the plugin's own name (a copy under another name keeps its sensor)."""
    source = str(plugin.manifest.provenance.get("source", ""))
    return source.split(":", 1)[1] if source.startswith("virtual:") else plugin.name
