"""Frame-source configurations: plain pydantic models that import no camera or video library.

Each kind of source has a config here and an implementation in its own module of this package
(``camera.py``, ``video.py``, ``images.py``, ``npz.py``, ``virtual.py``, ``demo.py``);
:func:`tactile_deploy.runtime.sources.factory.make_source` builds the source from its config.
A plugin manifest stores one of these as its default source, and ``tactile-deploy run --source
TEXT`` parses TEXT into one with :func:`parse_source`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from tactile_deploy.fileformat import StrictModel


class DemoSourceConfig(StrictModel):
    """The plugin's recorded demo clip (works on a machine without a sensor)."""

    kind: Literal["demo"] = Field("demo", description="Source kind.")
    loop: bool = Field(False, description="Start again at the first frame after the last.")


class CameraSourceConfig(StrictModel):
    """A live camera through OpenCV (V4L2 on Linux), by index, device path or serial number."""

    kind: Literal["camera"] = Field("camera", description="Source kind.")
    device: int | str = Field(
        0, description="Camera index (0, 1, ...), device path (/dev/video2, or a stable link "
        "/dev/v4l/by-id/...), or serial:SERIAL (the USB serial number; `tactile-deploy "
        "cameras` lists them).")
    width_px: int | None = Field(None, gt=0, description="Requested frame width, px (None: the "
                                 "camera's default; the plugin's camera mapping must match).")
    height_px: int | None = Field(None, gt=0, description="Requested frame height, px.")
    fps: float | None = Field(None, gt=0, description="Requested frame rate, frames per second.")
    fourcc: str | None = Field(None, pattern=r"^[ -~]{4}$",
                               description="Requested pixel format, e.g. 'MJPG' or 'YUYV'.")
    exposure: Literal["auto", "lock"] | float | None = Field(
        None, description="Exposure: 'auto' (the camera's automatic exposure), 'lock' (automatic "
        "for settle_s, then fixed at the value it chose), a number (manual, in the driver's "
        "units: V4L2 exposure_time_absolute, 100 us), or None (leave the camera as it is).")
    white_balance: Literal["auto", "lock"] | float | None = Field(
        None, description="White balance: 'auto', 'lock' (automatic for settle_s, then fixed), "
        "a colour temperature in K (manual), or None (leave the camera as it is).")
    settle_s: float = Field(1.0, ge=0, description="How long automatic exposure and white "
                            "balance run before 'lock' fixes them, s.")
    reconnect_timeout_s: float = Field(
        10.0, ge=0, description="How long to keep trying to reopen a camera that disappeared "
        "before giving up, s (0: give up at once).")
    max_backoff_s: float = Field(2.0, gt=0, description="Longest wait between reopening "
                                 "attempts, s (waits double from 0.1 s up to this).")


class VideoSourceConfig(StrictModel):
    """A video file (any container and codec the installed OpenCV reads)."""

    kind: Literal["video"] = Field("video", description="Source kind.")
    path: str = Field(description="Video file (relative paths: to the current folder, or to "
                      "the plugin folder when stored in a manifest).")
    loop: bool = Field(False, description="Start again at the first frame after the last.")


class ImageFolderSourceConfig(StrictModel):
    """A folder of still images, read in name order."""

    kind: Literal["images"] = Field("images", description="Source kind.")
    path: str = Field(description="Folder of images.")
    pattern: str | None = Field(
        None, description="Glob of the files to read, e.g. '*.jpg' (None: every file with an "
        "image suffix: .png, .jpg, .jpeg, .bmp, .tif, .tiff, any case).")
    fps: float = Field(30.0, gt=0, description="Frame rate the timestamps assume, frames/s.")
    loop: bool = Field(False, description="Start again at the first frame after the last.")


class NpzSourceConfig(StrictModel):
    """A recording in tactile-deploy's .npz clip format (see docs/runtime.md)."""

    kind: Literal["npz"] = Field("npz", description="Source kind.")
    path: str = Field(description="Recorded clip (.npz with 'frames' and 'timestamps_ns').")
    loop: bool = Field(False, description="Start again at the first frame after the last.")


class VirtualSourceConfig(StrictModel):
    """A virtual sensor: simulated presses rendered as camera frames."""

    kind: Literal["virtual"] = Field("virtual", description="Source kind.")
    sensor: str | None = Field(None, description="Virtual sensor name (None: the plugin's name).")
    n_frames: int = Field(60, ge=1, description="Number of frames to render.")
    seed: int = Field(0, ge=0, description="Seed of the random presses.")
    loop: bool = Field(False, description="Start again at the first frame after the last.")


SourceConfig = Annotated[
    DemoSourceConfig | CameraSourceConfig | VideoSourceConfig | ImageFolderSourceConfig | NpzSourceConfig | VirtualSourceConfig,
    Field(discriminator="kind"),
]

#: Source kinds and what their command-line text looks like.
SOURCE_FORMS = {
    "demo": "demo",
    "camera": "0 | 1 | /dev/video2 | /dev/v4l/by-id/... | serial:SERIAL | camera:0",
    "video": "clip.mp4 | clip.avi | clip.mkv",
    "images": "path/to/folder/ (png/jpg/jpeg/bmp/tif/tiff files)",
    "npz": "recording.npz",
    "virtual": "virtual | virtual:gelslim2",
}

#: Suffixes an image folder reads when no pattern is given (compared in lower case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".mjpg", ".mjpeg")


class SourceSpecError(ValueError):
    """A --source text that names no known kind of frame source."""


def parse_source(text: str, *, loop: bool = False):
    """Frame-source config from a command-line text (see :data:`SOURCE_FORMS`).

    ``demo``; ``virtual`` or ``virtual:NAME``; a camera index (``0``), ``camera:INDEX|PATH`` or
    a device path under ``/dev``; a folder (images); a file ending in ``.npz`` (recording) or a
    video suffix. Raises :class:`SourceSpecError` listing the accepted forms otherwise.
    """
    t = text.strip()
    if t == "demo":
        return DemoSourceConfig(loop=loop)
    if t == "virtual" or t.startswith("virtual:"):
        name = t.split(":", 1)[1] if ":" in t else None
        return VirtualSourceConfig(sensor=name or None, loop=loop)
    if t.startswith("camera:"):
        dev = t.split(":", 1)[1]
        return CameraSourceConfig(device=int(dev) if dev.isdigit() else dev)
    if re.fullmatch(r"\d+", t):
        return CameraSourceConfig(device=int(t))
    if t.startswith("/dev/"):
        return CameraSourceConfig(device=t)
    if t.startswith("serial:") and len(t) > len("serial:"):
        return CameraSourceConfig(device=t)
    path = Path(t).expanduser()
    if path.is_dir():
        return ImageFolderSourceConfig(path=str(path), loop=loop)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return NpzSourceConfig(path=str(path), loop=loop)
    if suffix in VIDEO_SUFFIXES:
        return VideoSourceConfig(path=str(path), loop=loop)
    forms = "\n".join(f"  {k:8s} {v}" for k, v in SOURCE_FORMS.items())
    raise SourceSpecError(
        f"--source {text!r} is not a frame source tactile-deploy knows (no such folder, and not "
        f"a .npz or video file name). Accepted forms:\n{forms}"
    )
