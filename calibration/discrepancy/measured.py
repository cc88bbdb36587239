"""Matched measured data: depth maps (or RGB frames) with the contacts that made them.

Two layouts hold the same content (N samples, one row per sample):

* **.npz**: ``depth`` (N, 128, 128) float32, mm pushed in, on the standard depth grid (row 0 =
  largest y, +-17.5 mm, sensor frame) and/or ``frames`` (N, H, W, 3) uint8 RGB, raw camera
  pixels; per sample ``indenter`` (N,) str (library name or mesh path), ``x_mm``, ``y_mm``,
  ``theta_deg``, ``depth_mm`` (N,) float: the commanded contact (sensor frame), NaN where not
  known; ``force_n`` (N,) float, measured total normal force, NaN where not known. Optional:
  ``contact_id`` (N,) int (samples of one physical contact, e.g. several frames of one press,
  share it; default: every sample its own contact), ``noise_mm`` (scalar, the depth noise of one
  pixel, one sigma, when it is known).
* **a folder** with ``contacts.csv``: columns ``indenter, x_mm, y_mm, theta_deg, depth_mm,
  force_n`` (empty cell = not known), ``depth_file`` (a .npy (128, 128) map, mm) or
  ``frame_file`` (an RGB image), optional ``contact_id``; paths relative to the folder.

A contact is **known** when ``x_mm``, ``y_mm`` and ``depth_mm`` are given (``theta_deg`` missing
counts as 0); otherwise the workflow estimates it from the map. :func:`load_measured` checks
everything and names the file, field, expected and actual value of any problem;
:func:`save_measured` writes the .npz atomically.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tactile_deploy.indenters import ContactPose

#: Depth grid of the measured maps (the standard grid of docs: 128 x 128 over +-17.5 mm).
DEPTH_SHAPE = (128, 128)
PER_SAMPLE = ("x_mm", "y_mm", "theta_deg", "depth_mm", "force_n")


class MeasuredDataError(ValueError):
    """Measured data that cannot be used (the message names the file and field)."""


@dataclass
class MeasuredData:
    """N measured samples (see the module docstring for units and frames).

    depth_mm : (N, 128, 128) float32 or None; frames : (N, H, W, 3) uint8 or None;
    indenter : N names; x_mm, y_mm, theta_deg, depth_cmd_mm, force_n : (N,) float64, NaN =
    unknown; contact_id : (N,) int64; noise_mm : known pixel noise (mm) or None; source : where
    it was read from.
    """

    depth_mm: np.ndarray | None
    frames: np.ndarray | None
    indenter: list[str]
    x_mm: np.ndarray
    y_mm: np.ndarray
    theta_deg: np.ndarray
    depth_cmd_mm: np.ndarray
    force_n: np.ndarray
    contact_id: np.ndarray
    noise_mm: float | None = None
    source: str = "<memory>"
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        n = len(self.indenter)
        for name in ("x_mm", "y_mm", "theta_deg", "depth_cmd_mm", "force_n", "contact_id"):
            arr = np.asarray(getattr(self, name))
            if arr.shape != (n,):
                raise MeasuredDataError(f"{self.source}: field {name!r} must have shape ({n},) "
                                        f"(one value per sample), got {arr.shape}")
        for name in ("x_mm", "y_mm", "theta_deg", "depth_cmd_mm", "force_n"):
            setattr(self, name, np.asarray(getattr(self, name), np.float64))
        self.contact_id = np.asarray(self.contact_id, np.int64)
        if self.depth_mm is None and self.frames is None:
            raise MeasuredDataError(f"{self.source}: no 'depth' maps and no 'frames'; give at "
                                    "least one of them")
        if self.depth_mm is not None:
            d = np.asarray(self.depth_mm, np.float32)
            if d.shape != (n, *DEPTH_SHAPE):
                raise MeasuredDataError(
                    f"{self.source}: field 'depth' must have shape ({n}, 128, 128) (mm on the "
                    f"standard depth grid), got {d.shape}; resample the maps onto that grid")
            bad = ~np.isfinite(d)
            if bad.any():
                i = int(np.argwhere(bad.any(axis=(1, 2)))[0, 0])
                raise MeasuredDataError(f"{self.source}: field 'depth' has {int(bad.sum())} NaN "
                                        f"or infinite values (first in sample {i}); replace them "
                                        "(0 where the gel is not pushed in)")
            self.depth_mm = d
        if self.frames is not None:
            f = np.asarray(self.frames)
            if f.dtype != np.uint8 or f.ndim != 4 or f.shape[0] != n or f.shape[3] != 3:
                raise MeasuredDataError(f"{self.source}: field 'frames' must be (N={n}, H, W, 3) "
                                        f"uint8 RGB, got {f.shape} {f.dtype}")
        for i, name in enumerate(self.indenter):
            if not isinstance(name, str) or not name:
                raise MeasuredDataError(f"{self.source}: field 'indenter' of sample {i} must be "
                                        f"a library name or mesh path, got {name!r}")
        f = self.force_n[np.isfinite(self.force_n)]
        if np.any(f < 0):
            raise MeasuredDataError(f"{self.source}: field 'force_n' has negative forces "
                                    f"({f.min():g} N); forces are compressive, > 0")
        if self.noise_mm is not None and not (np.isfinite(self.noise_mm) and self.noise_mm >= 0):
            raise MeasuredDataError(f"{self.source}: field 'noise_mm' must be >= 0, got "
                                    f"{self.noise_mm}")

    @property
    def n(self) -> int:
        return len(self.indenter)

    def known(self, i: int) -> bool:
        """Whether sample i's commanded contact is given."""
        return bool(np.isfinite(self.x_mm[i]) and np.isfinite(self.y_mm[i])
                    and np.isfinite(self.depth_cmd_mm[i]))

    def pose(self, i: int) -> ContactPose | None:
        """Commanded contact of sample i (sensor frame), or None when not known."""
        if not self.known(i):
            return None
        theta = float(self.theta_deg[i]) if np.isfinite(self.theta_deg[i]) else 0.0
        return ContactPose(x_mm=float(self.x_mm[i]), y_mm=float(self.y_mm[i]), theta_deg=theta,
                           depth_mm=float(self.depth_cmd_mm[i]))

    def subset(self, index) -> MeasuredData:
        """The samples ``index`` (array of ints) as new measured data."""
        idx = np.asarray(index, np.int64)
        return MeasuredData(
            None if self.depth_mm is None else self.depth_mm[idx],
            None if self.frames is None else self.frames[idx],
            [self.indenter[i] for i in idx], self.x_mm[idx], self.y_mm[idx],
            self.theta_deg[idx], self.depth_cmd_mm[idx], self.force_n[idx],
            self.contact_id[idx], self.noise_mm, self.source, dict(self.metadata))


def save_measured(path: str | os.PathLike, data: MeasuredData) -> None:
    """Write ``data`` as the .npz layout (atomic)."""
    from tactile_deploy.atomic import write_npz

    arrays = {"indenter": np.array(data.indenter, dtype=str), "x_mm": data.x_mm,
              "y_mm": data.y_mm, "theta_deg": data.theta_deg, "depth_mm": data.depth_cmd_mm,
              "force_n": data.force_n, "contact_id": data.contact_id}
    if data.depth_mm is not None:
        arrays["depth"] = data.depth_mm.astype(np.float32)
    if data.frames is not None:
        arrays["frames"] = data.frames
    if data.noise_mm is not None:
        arrays["noise_mm"] = np.float64(data.noise_mm)
    write_npz(path, **arrays)


def load_measured(path: str | os.PathLike) -> MeasuredData:
    """Read measured data from an .npz file or a folder with ``contacts.csv``."""
    path = Path(path)
    if path.is_dir():
        return _load_folder(path)
    if not path.is_file():
        raise FileNotFoundError(f"measured data {path} not found: give an .npz file or a folder "
                                "with contacts.csv (docs/discrepancy.md)")
    if path.suffix != ".npz":
        raise MeasuredDataError(f"{path}: measured data must be an .npz file or a folder with "
                                f"contacts.csv, got a {path.suffix or 'suffix-less'} file")
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise MeasuredDataError(f"{path}: not a readable .npz file ({e})") from None
    with z:
        keys = set(z.files)
        if "indenter" not in keys:
            raise MeasuredDataError(f"{path}: field 'indenter' is missing (one library name or "
                                    "mesh path per sample)")
        indenter = [str(s) for s in np.atleast_1d(z["indenter"])]
        n = len(indenter)

        def per_sample(name, default=np.nan):
            if name not in keys:
                return np.full(n, default)
            try:
                return np.asarray(z[name], np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise MeasuredDataError(f"{path}: field {name!r} must be numbers (NaN where not "
                                        f"known), got dtype {z[name].dtype}") from None

        noise = float(z["noise_mm"]) if "noise_mm" in keys else None
        return MeasuredData(
            depth_mm=z["depth"] if "depth" in keys else None,
            frames=z["frames"] if "frames" in keys else None, indenter=indenter,
            x_mm=per_sample("x_mm"), y_mm=per_sample("y_mm"), theta_deg=per_sample("theta_deg"),
            depth_cmd_mm=per_sample("depth_mm"), force_n=per_sample("force_n"),
            contact_id=(np.asarray(z["contact_id"]).reshape(-1) if "contact_id" in keys
                        else np.arange(n)),
            noise_mm=noise, source=str(path))


def _load_folder(folder: Path) -> MeasuredData:
    table = folder / "contacts.csv"
    if not table.is_file():
        raise MeasuredDataError(f"{folder}: contacts.csv not found; a measured-data folder holds "
                                "contacts.csv (one row per sample) and the maps or frames it names")
    with open(table, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise MeasuredDataError(f"{table}: no samples (the header alone)")
    cols = set(rows[0])
    if "indenter" not in cols:
        raise MeasuredDataError(f"{table}: column 'indenter' is missing")
    if not ({"depth_file", "frame_file"} & cols):
        raise MeasuredDataError(f"{table}: needs a column 'depth_file' (.npy maps, mm) or "
                                "'frame_file' (RGB images)")

    def number(row, k, name):
        text = (row.get(name) or "").strip()
        if not text:
            return np.nan
        try:
            return float(text)
        except ValueError:
            raise MeasuredDataError(f"{table}, row {k + 2}: column {name!r} must be a number or "
                                    f"empty, got {text!r}") from None

    depth, frames = [], []
    for k, row in enumerate(rows):
        if "depth_file" in cols:
            p = folder / row["depth_file"].strip()
            try:
                depth.append(np.load(p, allow_pickle=False))
            except (OSError, ValueError) as e:
                raise MeasuredDataError(f"{table}, row {k + 2}: depth_file {p} cannot be read "
                                        f"({e})") from None
            if depth[-1].shape != DEPTH_SHAPE:
                raise MeasuredDataError(f"{p}: a depth map must be (128, 128) mm, got "
                                        f"{depth[-1].shape}")
        if "frame_file" in cols:
            import cv2

            p = folder / row["frame_file"].strip()
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None:
                raise MeasuredDataError(f"{table}, row {k + 2}: frame_file {p} cannot be read "
                                        "as an image")
            frames.append(img[..., ::-1])
    shapes = {f.shape for f in frames}
    if len(shapes) > 1:
        raise MeasuredDataError(f"{table}: frames have different sizes {sorted(shapes)}")
    n = len(rows)
    ids = (np.array([int(number(r, k, "contact_id")) for k, r in enumerate(rows)])
           if "contact_id" in cols else np.arange(n))
    return MeasuredData(
        depth_mm=np.stack(depth).astype(np.float32) if depth else None,
        frames=np.stack(frames) if frames else None,
        indenter=[r["indenter"].strip() for r in rows],
        x_mm=np.array([number(r, k, "x_mm") for k, r in enumerate(rows)]),
        y_mm=np.array([number(r, k, "y_mm") for k, r in enumerate(rows)]),
        theta_deg=np.array([number(r, k, "theta_deg") for k, r in enumerate(rows)]),
        depth_cmd_mm=np.array([number(r, k, "depth_mm") for k, r in enumerate(rows)]),
        force_n=np.array([number(r, k, "force_n") for k, r in enumerate(rows)]),
        contact_id=ids, source=str(folder))
