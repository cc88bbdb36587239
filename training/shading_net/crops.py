"""Training crops of the read-out: compact windows of the presses around each contact, and their
file (numpy only, so that a crop file can be trained on where the project is not installed).

A crop keeps the press's 8-bit rectified frame in a ``size`` x ``size``-cell window (clipped to
the grid) around its deepest cell (jittered by up to ``JITTER_CELLS``), its illumination offset,
its true depth, and which unit and where in the unit's grid it came from; the units' reference
frames and cell positions are stored once per unit. :meth:`Crops.features` builds the read-out's
input of any subset (:func:`.data.readout_features`).

File (``.npz``, compressed): ``frames_delta`` (N, h, w, 3) uint8, the frame minus the unit's
reference modulo 256 (lossless, and small differences compress well); ``offsets`` (N, 3)
float32; ``depth_um`` (N, h, w) int16, depth in um; ``unit``, ``row0``, ``col0`` (N,)
int32; ``references`` (U, H, W, 3) uint8; ``xy_mm`` (U, 2, H, W) float32; ``kinds`` (N,) str;
``pitch_mm``; ``spec``: JSON of the settings the crops were made with.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .data import UnitPresses, readout_features

#: Largest jitter of a crop's window around the contact's deepest cell, cells.
JITTER_CELLS = 8
#: Depth stored in these units, mm (1 um, below the read-out's error by an order of magnitude).
DEPTH_UNIT_STORED_MM = 1e-3


class CropFileError(ValueError):
    """A crop file is unreadable or was made with other settings."""


@dataclass
class Crops:
    """Crops of presses of several units (see the module docstring for the fields)."""

    frames: np.ndarray        # (N, h, w, 3) uint8
    offsets: np.ndarray       # (N, 3) float32
    depth_mm: np.ndarray      # (N, h, w) float32
    unit: np.ndarray          # (N,) int32
    row0: np.ndarray          # (N,) int32
    col0: np.ndarray          # (N,) int32
    references: np.ndarray    # (U, H, W, 3) uint8
    xy_mm: np.ndarray         # (U, 2, H, W) float32
    kinds: np.ndarray         # (N,) str
    pitch_mm: float

    def __len__(self) -> int:
        return len(self.frames)

    def features(self, index=None) -> np.ndarray:
        """(n, 11, h, w) float32 read-out features of the crops at ``index`` (default: all)."""
        idx = np.arange(len(self)) if index is None else np.asarray(index)
        h, w = self.frames.shape[1:3]
        out = np.empty((len(idx), 11, h, w), np.float32)
        for k, i in enumerate(idx):
            u, r, c = int(self.unit[i]), int(self.row0[i]), int(self.col0[i])
            out[k] = readout_features(self.frames[i:i + 1], self.offsets[i:i + 1],
                                      self.references[u, r:r + h, c:c + w],
                                      self.xy_mm[u, :, r:r + h, c:c + w])[0]
        return out

    @staticmethod
    def concatenate(parts: list[Crops]) -> Crops:
        """Crops of several units in one (their unit indices renumbered in order)."""
        shapes = {p.references.shape[1:] for p in parts}
        if len(shapes) != 1:
            raise ValueError(f"units with imaging grids of different sizes: {sorted(shapes)}")
        base = np.cumsum([0] + [len(p.references) for p in parts])[:-1]
        return Crops(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                       ("frames", "offsets", "depth_mm")),
                     np.concatenate([p.unit + b for p, b in zip(parts, base)]).astype(np.int32),
                     *(np.concatenate([getattr(p, f) for p in parts]) for f in
                       ("row0", "col0", "references", "xy_mm", "kinds")),
                     parts[0].pitch_mm)


def contact_crops(presses: UnitPresses, rng: np.random.Generator, size: int) -> Crops:
    """``size`` x ``size`` crops (clipped to the grid) of one unit's presses around each press's
    deepest cell, jittered by up to :data:`JITTER_CELLS`."""
    n, h, w = presses.depth_mm.shape
    size_h, size_w = min(size, h), min(size, w)
    r0s, c0s = np.zeros(n, np.int32), np.zeros(n, np.int32)
    for k in range(n):
        r, c = np.unravel_index(int(np.argmax(presses.depth_mm[k])), (h, w))
        r0s[k] = np.clip(r - size_h // 2 + rng.integers(-JITTER_CELLS, JITTER_CELLS + 1), 0, h - size_h)
        c0s[k] = np.clip(c - size_w // 2 + rng.integers(-JITTER_CELLS, JITTER_CELLS + 1), 0, w - size_w)
    frames = np.stack([presses.images[k, r:r + size_h, c:c + size_w] for k, (r, c) in
                       enumerate(zip(r0s, c0s))])
    depth = np.stack([presses.depth_mm[k, r:r + size_h, c:c + size_w] for k, (r, c) in
                      enumerate(zip(r0s, c0s))])
    return Crops(frames, presses.offsets.astype(np.float32), depth.astype(np.float32),
                 np.zeros(n, np.int32), r0s, c0s, presses.reference[None],
                 presses.xy_mm[None].astype(np.float32), presses.kinds, float(presses.pitch_mm))


def save_crops(path: Path, crops: Crops, spec: dict) -> None:
    """Write ``crops`` and the settings they were made with (``spec``) to ``path`` (atomic)."""
    from tactile_deploy.atomic import atomic_path

    refs = crops.references[crops.unit]
    h, w = crops.frames.shape[1:3]
    ref_windows = np.stack([refs[k, r:r + h, c:c + w] for k, (r, c) in
                            enumerate(zip(crops.row0, crops.col0))])
    delta = (crops.frames.astype(np.int16) - ref_windows).astype(np.uint8)    # modulo 256
    depth = np.round(crops.depth_mm / DEPTH_UNIT_STORED_MM)
    if np.abs(depth).max(initial=0) > np.iinfo(np.int16).max:
        raise ValueError("depth beyond +-32 mm cannot be stored")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, frames_delta=delta, offsets=crops.offsets,
                                depth_um=depth.astype(np.int16), unit=crops.unit, row0=crops.row0,
                                col0=crops.col0, references=crops.references, xy_mm=crops.xy_mm,
                                kinds=crops.kinds.astype(str), pitch_mm=np.float64(crops.pitch_mm),
                                spec=np.array(json.dumps(spec, sort_keys=True)))


def read_spec(path: Path) -> dict | None:
    """The settings a crop file was made with (None if it holds none)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return json.loads(str(z["spec"])) if "spec" in z.files else None
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise CropFileError(f"{path} is not a readable crop file ({type(e).__name__}: {e})") from None


def load_crops(path: Path) -> Crops:
    """The :class:`Crops` of a file written by :func:`save_crops`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise CropFileError(f"{path} is not a readable crop file ({type(e).__name__}: {e})") from None
    missing = {"frames_delta", "offsets", "depth_um", "unit", "row0", "col0", "references",
               "xy_mm", "kinds", "pitch_mm"} - set(d)
    if missing:
        raise CropFileError(f"{path}: not a crop file of this version (missing {sorted(missing)}); "
                            "delete it, it is made again")
    h, w = d["frames_delta"].shape[1:3]
    refs = d["references"][d["unit"]]
    ref_windows = np.stack([refs[k, r:r + h, c:c + w] for k, (r, c) in
                            enumerate(zip(d["row0"], d["col0"]))])
    frames = (d["frames_delta"].astype(np.int16) + ref_windows).astype(np.uint8)
    return Crops(frames, d["offsets"].astype(np.float32),
                 d["depth_um"].astype(np.float32) * np.float32(DEPTH_UNIT_STORED_MM),
                 d["unit"].astype(np.int32), d["row0"].astype(np.int32), d["col0"].astype(np.int32),
                 d["references"], d["xy_mm"].astype(np.float32), d["kinds"], float(d["pitch_mm"]))
