"""Recorded clips in tactile-deploy's ``.npz`` format, and the source that plays them.

Clip format (``save_clip`` writes it atomically, ``load_clip`` checks it):

* ``frames``: (N, H, W, 3) uint8, RGB, raw camera pixels;
* ``timestamps_ns``: (N,) int64, ns from the first frame (starts at 0, strictly increasing);
* ``metadata_json`` (optional): a JSON object as a 0-d string array (sensor, how it was made).
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import write_npz
from tactile_deploy.runtime.sources.base import ArrayPlayback, SourceError


class ClipFormatError(SourceError):
    """A recorded clip is missing, unreadable, or not in the clip format."""


def save_clip(path: str | os.PathLike, frames, timestamps_ns, metadata: dict | None = None) -> None:
    """Write a clip (see the module docstring). frames (N, H, W, 3) uint8 RGB; timestamps (N,) ns."""
    frames = np.asarray(frames)
    t = np.asarray(timestamps_ns, dtype=np.int64)
    _check(Path(path), frames, t)
    arrays = {"frames": frames, "timestamps_ns": t}
    if metadata is not None:
        arrays["metadata_json"] = np.array(json.dumps(metadata))
    write_npz(path, **arrays)


def _check(path: Path, frames: np.ndarray, t: np.ndarray) -> None:
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
        raise ClipFormatError(f"{path}: array 'frames' must be (N, H, W, 3) uint8 RGB, got "
                              f"{frames.shape} {frames.dtype}")
    if t.shape != (len(frames),):
        raise ClipFormatError(f"{path}: array 'timestamps_ns' must have shape ({len(frames)},) "
                              f"(one per frame), got {t.shape}")
    if len(t) and (t[0] != 0 or np.any(np.diff(t) <= 0)):
        raise ClipFormatError(f"{path}: 'timestamps_ns' must start at 0 and increase strictly "
                              f"(got first {t[:3].tolist()}...)")


def load_clip(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read and check a clip: ``(frames (N, H, W, 3) uint8, timestamps_ns (N,) int64, metadata)``."""
    path = Path(path)
    if not path.is_file():
        raise ClipFormatError(f"recorded clip {path} not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            files = set(z.files)
            missing = {"frames", "timestamps_ns"} - files
            if missing:
                raise ClipFormatError(f"{path}: array(s) {sorted(missing)} missing (has "
                                      f"{sorted(files)}); is this a tactile-deploy clip?")
            frames = z["frames"]
            t = z["timestamps_ns"].astype(np.int64)
            meta_text = str(z["metadata_json"]) if "metadata_json" in files else "{}"
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise ClipFormatError(f"{path}: not a readable .npz file ({e}); re-record or re-copy "
                              "it") from None
    _check(path, frames, t)
    try:
        meta = json.loads(meta_text)
    except json.JSONDecodeError as e:
        raise ClipFormatError(f"{path}: 'metadata_json' is not valid JSON ({e.msg})") from None
    return frames, t, meta if isinstance(meta, dict) else {}


class NpzSource(ArrayPlayback):
    """Play a recorded ``.npz`` clip."""

    def __init__(self, path: str | os.PathLike, loop: bool = False, name: str | None = None):
        self.path = Path(path)
        frames, t, self.metadata = load_clip(self.path)
        super().__init__(frames, t, name or f"recording {self.path}", loop)
