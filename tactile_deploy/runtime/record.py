"""``tactile-deploy run --record``: the raw camera frames, kept losslessly with their times.

Into ``<out>/frames/``: ``frame_<index, 6 digits>.png`` (the frame exactly as the camera
delivered it, RGB, 8 bit, PNG: lossless) and ``timestamps.csv`` with ``frame_index``, ``file``,
``t_capture_ns`` (wall clock, ns since the UNIX epoch), ``t_mono_ns`` (monotonic clock) and
``t_source_ns`` (time within a recording, empty for a camera), one row per frame kept. Each PNG
is written atomically; ``timestamps.csv`` under a temporary name, renamed at the end.

The folder is a frame source itself: ``run --source <out>/frames`` replays it in order, and its
frames keep their recorded times (``--realtime`` plays them at the recorded pace).

PNG encoding (~10 ms per 640 x 480 frame at compression level 1) runs in a background thread:
from a live camera frames that arrive while the queue is full are dropped, counted and warned
about; from a recording every frame is kept.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tactile_deploy.runtime.sinks import BackgroundSink

TIMESTAMPS = "timestamps.csv"
HEADER = "frame_index,file,t_capture_ns,t_mono_ns,t_source_ns"


class RawFrameRecorder(BackgroundSink):
    """Keep every processed frame's raw image (module docstring) in ``folder``."""

    name = "raw frame recorder"

    def __init__(self, folder: str | os.PathLike, png_compression: int = 1, queue_size: int = 16):
        super().__init__(queue_size)
        self.folder = Path(folder)
        self.png_compression = int(png_compression)
        self._tmp = self.folder / f".{TIMESTAMPS}.partial"

    def setup(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        self._csv = open(self._tmp, "w", encoding="utf-8")
        self._csv.write(HEADER + "\n")

    def handle(self, result) -> None:
        import cv2

        from tactile_deploy.atomic import atomic_path

        f = result.frame
        name = f"frame_{int(f.index):06d}.png"
        bgr = cv2.cvtColor(np.ascontiguousarray(f.image), cv2.COLOR_RGB2BGR)
        with atomic_path(self.folder / name) as tmp:
            if not cv2.imwrite(str(tmp), bgr, [cv2.IMWRITE_PNG_COMPRESSION, self.png_compression]):
                raise OSError(f"OpenCV could not write {self.folder / name}")
        t_src = "" if f.t_source_ns is None else str(int(f.t_source_ns))
        self._csv.write(f"{f.index},{name},{f.t_wall_ns},{f.t_mono_ns},{t_src}\n")
        self._csv.flush()

    def teardown(self) -> None:
        csv = getattr(self, "_csv", None)
        if csv is not None:
            csv.close()
            os.replace(self._tmp, self.folder / TIMESTAMPS)

    def report(self) -> dict:
        return {**super().report(), "file": str(self.folder)}


def read_timestamps(folder: Path) -> list[tuple[str, int]] | None:
    """``[(file name, t_capture_ns)]`` of a ``--record`` folder in frame order, or None when the
    folder has no ``timestamps.csv``."""
    import csv

    path = Path(folder) / TIMESTAMPS
    if not path.is_file():
        return None
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return [(r["file"], int(r["t_capture_ns"])) for r in rows]
