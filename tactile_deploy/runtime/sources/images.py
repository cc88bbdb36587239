"""A folder of still images (PNG, JPEG, ...), read in name order, BGR converted to RGB.

An unreadable image is logged and skipped (counted in ``stats.unreadable``); timestamps assume
the configured frame rate.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from tactile_deploy.runtime.sources.base import Frame, FrameSource, SourceError

log = logging.getLogger(__name__)


class ImageFolderSource(FrameSource):
    """Images matching ``pattern`` in ``folder``, sorted by name."""

    def __init__(self, folder: str | os.PathLike, pattern: str = "*.png", fps: float = 30.0,
                 loop: bool = False, name: str | None = None):
        super().__init__()
        self.folder = Path(folder)
        self.name = name or f"image folder {self.folder}"
        self.pattern = pattern
        self.fps = float(fps)
        self.finite = not loop
        self._loop = bool(loop)
        self._files: list[Path] = []
        self._i = 0
        self._t = 0

    def _open(self) -> None:
        if not self.folder.is_dir():
            raise SourceError(f"{self.name}: folder not found")
        self._files = sorted(p for p in self.folder.glob(self.pattern) if p.is_file())
        if not self._files:
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
                log.warning("%s: cannot read %s as an image; skipped", self.name, path.name)
                continue
            t = int(round(self._t * 1e9 / self.fps))
            self._t += 1
            return self._frame(np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)), t)
        if self._files and self.stats.delivered == 0 and self.stats.unreadable >= len(self._files):
            raise SourceError(f"{self.name}: none of the {len(self._files)} files is a readable "
                              "image")
        return None
