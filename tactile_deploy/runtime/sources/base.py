"""The common base of frame sources: ``connect`` / ``read`` / ``disconnect``, usable with ``with``.

A :class:`Frame` is one camera image in **RGB** channel order (OpenCV's BGR is converted where a
source reads it), (H, W, 3) uint8, with its timestamps:

* ``t_wall_ns``: wall-clock time of capture, ns since the UNIX epoch (``time.time_ns()``), for
  other processes and logs;
* ``t_mono_ns``: the same instant on this process's monotonic clock (``time.monotonic_ns()``),
  for latencies;
* ``t_source_ns``: the frame's own time in a recording (ns from the first frame), or None for a
  live camera.

``read()`` returns the next frame, or None when a finite source is exhausted; it raises
:class:`SourceError` (or a subclass) when the source fails for good. ``stats`` counts frames
delivered and frames dropped: captured by the device but never delivered (a camera whose frames
arrive faster than they are read, gaps in the camera's frame counter or timestamps).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


class SourceError(RuntimeError):
    """A frame source cannot deliver frames (the message says which source and what to do)."""


class SourceDisconnectedError(SourceError):
    """A live source vanished and did not come back within its reconnection timeout."""


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    image : (H, W, 3) uint8, RGB, raw camera pixels (row 0 at the top of the camera image).
    index : position in the stream, counted from 0 over delivered frames.
    t_wall_ns : capture time, ns since the UNIX epoch.
    t_mono_ns : capture time on ``time.monotonic_ns()``.
    t_source_ns : time within a recording, ns from its first frame (None for live sources).
    label : where in the source the frame came from, when it says (an image folder: the file's
        name), else None.
    """

    image: np.ndarray
    index: int
    t_wall_ns: int
    t_mono_ns: int
    t_source_ns: int | None = None
    label: str | None = None


@dataclass
class SourceStats:
    """Counters of a source: frames delivered, dropped, reconnections, unreadable frames."""

    delivered: int = 0
    dropped: int = 0
    reconnects: int = 0
    unreadable: int = 0
    extra: dict = field(default_factory=dict)


def now_ns() -> tuple[int, int]:
    """``(time.time_ns(), time.monotonic_ns())`` taken together."""
    return time.time_ns(), time.monotonic_ns()


class FrameSource:
    """Base class. Subclasses implement ``_open``, ``_read`` and ``_close``; ``name`` describes
    the source in messages ("camera /dev/video2", "clip demo.mp4")."""

    name: str = "frame source"
    #: True for a source that ends (a file); False for a live device or a looped recording.
    finite: bool = True
    #: True for a device that captures whether or not it is read (a camera): the loop must not
    #: wait for slow outputs; False for recordings, which lose nothing by waiting.
    live: bool = False

    def __init__(self) -> None:
        self.stats = SourceStats()
        self._connected = False

    # -- public API
    def connect(self) -> FrameSource:
        if not self._connected:
            self._open()
            self._connected = True
        return self

    def read(self) -> Frame | None:
        """The next frame, or None at the end of a finite source."""
        if not self._connected:
            raise SourceError(f"{self.name}: read() before connect(); use `with source:` or "
                              "call connect() first")
        frame = self._read()
        if frame is not None:
            self.stats.delivered += 1
        return frame

    def disconnect(self) -> None:
        if self._connected:
            self._connected = False
            self._close()

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def frame_count(self) -> int | None:
        """Frames this source delivers in all (known for a finite recording once connected;
        None for a camera or a looped recording): progress and ETA."""
        return None

    def __enter__(self) -> FrameSource:
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.disconnect()

    def __iter__(self):
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame

    # -- for subclasses
    def _open(self) -> None:  # pragma: no cover - trivial default
        pass

    def _read(self) -> Frame | None:
        raise NotImplementedError

    def _close(self) -> None:  # pragma: no cover - trivial default
        pass

    def _frame(self, image: np.ndarray, t_source_ns: int | None = None,
               stamp: tuple[int, int] | None = None, label: str | None = None) -> Frame:
        wall, mono = stamp if stamp is not None else now_ns()
        return Frame(image=image, index=self.stats.delivered, t_wall_ns=wall, t_mono_ns=mono,
                     t_source_ns=t_source_ns, label=label)


class ArrayPlayback(FrameSource):
    """Play frames held in memory (RGB uint8) with their recorded timestamps; base of the
    file sources. ``frames`` is anything indexable giving (H, W, 3) uint8 arrays."""

    def __init__(self, frames, timestamps_ns, name: str, loop: bool = False) -> None:
        super().__init__()
        self.name = name
        self._frames = frames
        self._t = np.asarray(timestamps_ns, dtype=np.int64)
        self._loop = bool(loop)
        self._i = 0
        self.finite = not loop
        if len(self._t) != len(frames):
            raise SourceError(f"{name}: {len(frames)} frames but {len(self._t)} timestamps")

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def frame_count(self) -> int | None:
        return None if self._loop else len(self._frames)

    def _read(self) -> Frame | None:
        n = len(self._frames)
        if n == 0:
            return None
        if self._i >= n:
            if not self._loop:
                return None
            self._i = 0
        i = self._i
        self._i += 1
        return self._frame(np.asarray(self._frames[i]), int(self._t[i]))
