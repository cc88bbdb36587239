"""Video files through OpenCV (``cv2.VideoCapture``), frames converted from BGR to RGB."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.runtime.sources.base import Frame, FrameSource, SourceError


class VideoSource(FrameSource):
    """Play a video file. Timestamps come from the container (``CAP_PROP_POS_MSEC``), or from
    the frame rate when the container has none."""

    def __init__(self, path: str | os.PathLike, loop: bool = False, name: str | None = None,
                 capture_factory=None):
        super().__init__()
        self.path = Path(path)
        self.name = name or f"video {self.path}"
        self.finite = not loop
        self._loop = bool(loop)
        self._factory = capture_factory
        self._cap = None
        self._fps = 0.0
        self._n = 0
        self._pos = 0

    @property
    def frame_count(self) -> int | None:
        return None if self._loop or not self._n else self._n

    def _open(self) -> None:
        import cv2

        if not self.path.is_file():
            raise SourceError(f"{self.name}: file not found (looked for {self.path.resolve()}); "
                              "check the path, or give a camera index (--source 0)")
        self._cap = (self._factory or cv2.VideoCapture)(str(self.path))
        if not self._cap.isOpened():
            raise SourceError(f"{self.name}: OpenCV cannot open it (unknown container or codec); "
                              "convert it to .mp4 (mp4v) or record a .npz clip instead")
        self._fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self._n = max(int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 0)   # container's count
        self._pos = 0

    def _read(self) -> Frame | None:
        import cv2

        ok, img = self._cap.read()
        if not ok or img is None:
            if self._loop and self._pos > 0:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                self._pos = 0
                ok, img = self._cap.read()
            if not ok or img is None:
                return None
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        pos_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0)
        if pos_ms <= 0 and self._pos > 0 and self._fps > 0:
            pos_ms = 1e3 * self._pos / self._fps
        self._pos += 1
        return self._frame(np.ascontiguousarray(img), int(round(pos_ms * 1e6)))

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def write_video(path: str | os.PathLike, frames, fps: float = 30.0, fourcc: str = "mp4v") -> Path:
    """Write RGB frames (N, H, W, 3) uint8 as a video file (atomic). Returns the path."""
    import cv2

    frames = np.asarray(frames)
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must be (N, H, W, 3) uint8 RGB, got {frames.shape} {frames.dtype}")
    path = Path(path)
    h, w = frames.shape[1:3]
    with atomic_path(path) as tmp:
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*fourcc), float(fps), (w, h))
        if not writer.isOpened():
            raise SourceError(f"{path}: OpenCV cannot write {fourcc!r} video here")
        try:
            for f in frames:
                writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
        finally:
            writer.release()
    return path
