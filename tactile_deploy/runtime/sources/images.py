"""A folder of still images (PNG, JPEG, BMP, TIFF), read in name order, BGR converted to RGB.

Without a pattern every file with an image suffix (:data:`IMAGE_SUFFIXES`, any case) is read.
An unreadable image is logged and skipped (counted in ``stats.unreadable``, its name kept once in
``unreadable_files``); timestamps assume the configured frame rate, except in a folder written by
``run --record``: its ``timestamps.csv`` gives the order and each frame's recorded time.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from tactile_deploy.runtime.sources.base import Frame, FrameSource, SourceError
from tactile_deploy.runtime.sources.config import IMAGE_SUFFIXES

log = logging.getLogger(__name__)


class ImageFolderSource(FrameSource):
    """Images matching ``pattern`` (None: any image suffix) in ``folder``, sorted by name.

    unreadable_files : names of the files skipped because they are not readable images, each
        listed once (in the order met).
    """

    def __init__(self, folder: str | os.PathLike, pattern: str | None = None, fps: float = 30.0,
                 loop: bool = False, name: str | None = None):
        super().__init__()
        self.folder = Path(folder)
        self.name = name or f"image folder {self.folder}"
        self.pattern = pattern
        self.fps = float(fps)
        self.finite = not loop
        self._loop = bool(loop)
        self._files: list[Path] = []
        self.unreadable_files: list[str] = []
        self._i = 0
        self._t = 0
        self._times_ns: list[int] | None = None

    @property
    def frame_count(self) -> int | None:
        return None if self._loop or not self._files else len(self._files)

    def _open(self) -> None:
        if not self.folder.is_dir():
            raise SourceError(f"{self.name}: folder not found")
        if self.pattern is None:
            found = (p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        else:
            found = self.folder.glob(self.pattern)
        self._files = sorted(p for p in found if p.is_file())
        self._times_ns = None
        if self.pattern is None:
            from tactile_deploy.runtime.record import read_timestamps

            recorded = read_timestamps(self.folder)
            if recorded:
                by_name = {p.name: p for p in self._files}
                kept = [(by_name[n], t) for n, t in recorded if n in by_name]
                self._files = [p for p, _ in kept]
                t0 = kept[0][1] if kept else 0
                self._times_ns = [t - t0 for _, t in kept]
        if not self._files:
            if self.pattern is None:
                raise SourceError(f"{self.name}: no image files ({', '.join(IMAGE_SUFFIXES)}) in "
                                  "it; pass the folder that holds the frames")
            raise SourceError(f"{self.name}: no files match {self.pattern!r}; pass another "
                              "pattern or folder")

    def _read(self) -> Frame | None:
        import cv2

        tries = 0
        while tries < len(self._files):
            if self._i >= len(self._files):
                if not self._loop:
                    return None
                self._i = 0
            path = self._files[self._i]
            self._i += 1
            tries += 1
            img = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if img is None:
                self.stats.unreadable += 1
                if path.name not in self.unreadable_files:
                    self.unreadable_files.append(path.name)
                log.warning("%s: cannot read %s as an image; skipped", self.name, path.name)
                continue
            if self._times_ns is not None:
                t = self._times_ns[self._i - 1]
            else:
                t = int(round(self._t * 1e9 / self.fps))
            self._t += 1
            return self._frame(np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)), t,
                               label=path.name)
        if self._files and self.stats.delivered == 0 and self.stats.unreadable >= len(self._files):
            raise SourceError(f"{self.name}: none of the {len(self._files)} files is a readable "
                              "image")
        return None
