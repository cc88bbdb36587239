"""Matched measured data: depth maps (or RGB frames) with the contacts that made them.

Two layouts hold the same content (N samples, one row per sample):

* **.npz**: ``depth`` (N, 128, 128) float32, mm pushed in, on the standard depth grid (row 0 =
  largest y, +-17.5 mm, sensor frame) and/or ``frames`` (N, H, W, 3) uint8 RGB, raw camera
  pixels; per sample ``indenter`` (N,) str (library name or mesh path), ``x_mm``, ``y_mm``,
  ``theta_deg``, ``depth_mm`` (N,) float: the commanded contact (sensor frame), NaN where not
  known; ``force_n`` (N,) float, measured total normal force, NaN where not known. Optional:
  ``contact_id`` (N,) int (samples of one physical contact, e.g. several frames of one press,
  share it; default: every sample its own contact), ``noise_mm`` (scalar, the depth noise of one
  pixel, one sigma, when it is known), ``header_json`` (scalar str: a :class:`MeasuredHeader`,
  written by :func:`save_measured`; when present, :func:`load_measured` checks the arrays against
  it: sample and contact counts, which maps, frame size, noise).
* **a folder** with ``contacts.csv``: columns ``indenter, x_mm, y_mm, theta_deg, depth_mm,
  force_n`` (empty cell = not known), ``depth_file`` (a .npy (128, 128) map, mm) or
  ``frame_file`` (an RGB image), optional ``contact_id``; paths relative to the folder.

A contact is **known** when ``x_mm``, ``y_mm`` and ``depth_mm`` are given (``theta_deg`` missing
counts as 0); otherwise the workflow estimates it from the map. The three are given together or
not at all (a sample with some of them is refused). Commanded depths and maps are mm pushed into
the gel (> 0), shallower than the pad's thickness; ``noise_mm`` is > 0. :func:`load_measured`
checks everything and names the file, field, expected and actual value of any problem;
:func:`save_measured` writes the .npz atomically.
"""

from __future__ import annotations

import csv
import hashlib
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from typing import Literal

from pydantic import Field, ValidationError

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.indenters import ContactPose
from tactile_deploy.jsonfile import validation_error_text
from tactile_deploy.pad.geometry import PadGeometry

#: Depth grid of the measured maps (the standard grid of docs: 128 x 128 over +-17.5 mm).
DEPTH_SHAPE = (128, 128)
PER_SAMPLE = ("x_mm", "y_mm", "theta_deg", "depth_mm", "force_n")
#: Gel pad thickness, mm: no depth (commanded or in a map) reaches it.
PAD_THICKNESS_MM = PadGeometry().thickness_mm
#: The fields of a commanded contact's position, given together or not at all (field names).
POSE_FIELDS = (("x_mm", "x_mm"), ("y_mm", "y_mm"), ("depth_cmd_mm", "depth_mm"))


class MeasuredDataError(ValueError):
    """Measured data that cannot be used (the message names the file and field)."""


#: Units of the .npz layout's arrays (``header_json["units"]``).
MEASURED_UNITS = {"depth": "mm pushed in along -z", "frames": "RGB uint8, raw camera pixels",
                  "x_mm": "mm", "y_mm": "mm", "theta_deg": "deg", "depth_mm": "mm",
                  "force_n": "N", "noise_mm": "mm"}
MEASURED_FRAME = "sensor: origin at the centre of the sensing surface, z up out of the gel"
MEASURED_DEPTH_GRID = ("128 x 128 pixels over x, y in [-17.5, 17.5] mm; row 0 = largest y, "
                       "column 0 = smallest x")


class MeasuredHeader(StrictModel):
    """``header_json`` of a measured-data .npz: what the arrays hold, checked on reading."""

    format_version: Literal[1] = Field(1, description="Version of this format.")
    n_samples: int = Field(ge=0, description="Samples (rows of every per-sample array).")
    n_contacts: int = Field(ge=0, description="Distinct physical contacts (contact_id values).")
    n_known: int = Field(ge=0, description="Samples whose commanded contact (x_mm, y_mm, "
                         "depth_mm) is given.")
    maps: list[Literal["depth", "frames"]] = Field(min_length=1, description="Which of the "
                                                   "maps the file holds.")
    frames_shape: list[int] | None = Field(None, min_length=3, max_length=3, description=""
                                           "(H, W, 3) of each RGB frame, when frames are held.")
    noise_mm: float | None = Field(None, gt=0, description="Depth noise of one pixel, one "
                                   "sigma, mm (also the array noise_mm), when known.")
    source: str = Field(description="Where the samples came from when they were written.")
    units: dict[str, str] = Field(default_factory=lambda: dict(MEASURED_UNITS),
                                  description="Unit of each array.")
    frame: str = Field(MEASURED_FRAME, description="Coordinate frame of the positions.")
    depth_grid: str = Field(MEASURED_DEPTH_GRID, description="Pixel geometry of 'depth'.")


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
        self.contact_id = self._contact_ids(np.asarray(self.contact_id))
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
            deep = d.reshape(n, -1).max(axis=1) if n else np.zeros(0)
            if np.any(deep > PAD_THICKNESS_MM):
                i = int(np.argmax(deep > PAD_THICKNESS_MM))
                raise MeasuredDataError(
                    f"{self.source}: field 'depth' reaches {deep[i]:g} mm in {self._sample(i)}, "
                    f"deeper than the {PAD_THICKNESS_MM:g} mm gel pad: maps must be in mm "
                    "pushed in (maps in um: divide them by 1000)")
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
        given = np.array([np.isfinite(getattr(self, name)) for name, _ in POSE_FIELDS])
        partly = given.any(axis=0) & ~given.all(axis=0)
        if partly.any():
            i = int(np.argmax(partly))
            missing = [f for (_, f), g in zip(POSE_FIELDS, given[:, i]) if not g]
            present = [f for (_, f), g in zip(POSE_FIELDS, given[:, i]) if g]
            raise MeasuredDataError(
                f"{self.source}: {self._sample(i)} has {', '.join(present)} but no "
                f"{', '.join(missing)} (NaN or empty): a commanded contact needs x_mm, y_mm and "
                "depth_mm all given; give the missing value, or leave all three empty to have "
                "the contact estimated from the map")
        for i, v in enumerate(self.depth_cmd_mm):
            if np.isfinite(v) and not 0 < v < PAD_THICKNESS_MM:
                raise MeasuredDataError(
                    f"{self.source}: field 'depth_mm' of {self._sample(i)} is {v:g} mm, expected a "
                    f"depth in mm pushed into the gel, > 0 and below the {PAD_THICKNESS_MM:g} mm "
                    "pad: " + ("depth is positive into the gel; flip the sign of depths "
                               "recorded as negative z" if v <= 0 else
                               "depths in um: divide them by 1000"))
        f = self.force_n[np.isfinite(self.force_n)]
        if np.any(f < 0):
            raise MeasuredDataError(f"{self.source}: field 'force_n' has negative forces "
                                    f"({f.min():g} N); forces are compressive, > 0")
        if self.noise_mm is not None and not (np.isfinite(self.noise_mm) and self.noise_mm > 0):
            raise MeasuredDataError(f"{self.source}: field 'noise_mm' must be > 0 mm (the pixel "
                                    f"noise, one sigma; it sets the null threshold), got "
                                    f"{self.noise_mm}; give the noise measured on repeated "
                                    "no-contact maps (e.g. 0.005 for 5 um), or leave the field "
                                    "out to have it estimated from the residual")

    def _sample(self, i: int) -> str:
        """Sample ``i`` as a message names it (with its row of contacts.csv for a folder)."""
        row = self.metadata.get("csv_rows")
        return f"sample {i}" + (f" (contacts.csv row {row[i]})" if row else "")

    def _contact_ids(self, ids: np.ndarray) -> np.ndarray:
        """``contact_id`` as int64, or MeasuredDataError when its values are not integers."""
        if ids.dtype.kind in "iu":
            return ids.astype(np.int64)
        if ids.dtype.kind == "f":
            whole = np.isfinite(ids) & (ids == np.round(ids))
            if whole.all():
                return ids.astype(np.int64)
            bad = int(np.argmin(whole))
        else:
            bad = 0
        raise MeasuredDataError(
            f"{self.source}: field 'contact_id' must be integers (one number per physical contact, "
            f"shared by its samples), got {ids.dtype} values such as {ids[bad].item()!r} in "
            f"{self._sample(bad)}; number the contacts 0, 1, 2, ..., or leave the field out "
            "(every sample its own contact)")

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
        metadata = dict(self.metadata)
        metadata.pop("header", None)   # the header of the file describes all its samples
        if "csv_rows" in metadata:
            metadata["csv_rows"] = [metadata["csv_rows"][i] for i in idx]
        return MeasuredData(
            None if self.depth_mm is None else self.depth_mm[idx],
            None if self.frames is None else self.frames[idx],
            [self.indenter[i] for i in idx], self.x_mm[idx], self.y_mm[idx],
            self.theta_deg[idx], self.depth_cmd_mm[idx], self.force_n[idx],
            self.contact_id[idx], self.noise_mm, self.source, metadata)


def save_measured(path: str | os.PathLike, data: MeasuredData) -> None:
    """Write ``data`` as the .npz layout (atomic)."""
    from tactile_deploy.atomic import write_npz

    write_npz(path, **measured_arrays(data))


def measured_arrays(data: MeasuredData) -> dict[str, np.ndarray]:
    """The arrays of the .npz layout of ``data``."""
    arrays = {"indenter": np.array(data.indenter, dtype=str), "x_mm": data.x_mm,
              "y_mm": data.y_mm, "theta_deg": data.theta_deg, "depth_mm": data.depth_cmd_mm,
              "force_n": data.force_n, "contact_id": data.contact_id,
              "header_json": np.array(measured_header(data).model_dump_json())}
    if data.depth_mm is not None:
        arrays["depth"] = data.depth_mm.astype(np.float32)
    if data.frames is not None:
        arrays["frames"] = data.frames
    if data.noise_mm is not None:
        arrays["noise_mm"] = np.float64(data.noise_mm)
    return arrays


def measured_header(data: MeasuredData) -> MeasuredHeader:
    """The header that describes ``data``'s arrays."""
    return MeasuredHeader(
        n_samples=data.n, n_contacts=len(np.unique(data.contact_id)),
        n_known=sum(data.known(i) for i in range(data.n)),
        maps=[m for m, a in (("depth", data.depth_mm), ("frames", data.frames)) if a is not None],
        frames_shape=None if data.frames is None else list(data.frames.shape[1:]),
        noise_mm=data.noise_mm, source=data.source)


def _check_header(path: Path, text: str, data: MeasuredData) -> MeasuredHeader:
    """``header_json`` of the file at ``path`` validated, and the arrays checked against it."""
    try:
        header = MeasuredHeader.model_validate_json(text)
    except ValidationError as e:
        raise MeasuredDataError(validation_error_text(
            f"{path}: field 'header_json'", e, "measured-data header",
            "the format is measured_header.schema.json in calibration/discrepancy/")) from None
    got = measured_header(data)
    for name in ("n_samples", "n_contacts", "n_known", "maps", "frames_shape", "noise_mm"):
        expected, actual = getattr(header, name), getattr(got, name)
        if expected != actual:
            raise MeasuredDataError(
                f"{path}: field 'header_json.{name}': the header says {expected!r}, the arrays "
                f"hold {actual!r}; the arrays were changed after the file was written (write it "
                "again with save_measured, or remove header_json)")
    return header


def measured_sha256(path: str | os.PathLike) -> str:
    """sha256 (hex) of measured data: an .npz file's bytes; for a folder, of every file in it
    (its path relative to the folder and its bytes' sha256, in sorted order)."""
    from tactile_deploy.checksums import file_sha256

    path = Path(path)
    if path.is_file():
        return file_sha256(path)
    h = hashlib.sha256()
    for p in sorted(q for q in path.rglob("*") if q.is_file()):
        h.update(p.relative_to(path).as_posix().encode("utf-8") + b"\0")
        h.update(bytes.fromhex(file_sha256(p)))
    return h.hexdigest()


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

        def read(name):
            # the arrays load lazily: a field that cannot be read fails here, not at np.load
            try:
                return z[name]
            except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as e:
                # object arrays (pickles), truncated or corrupt members
                raise MeasuredDataError(
                    f"{path}: field {name!r} cannot be read ({' '.join(str(e).split())}); save "
                    "it as a plain array of numbers or strings (no Python objects: "
                    "np.array(names, dtype=str) for indenter names)") from None

        if "indenter" not in keys:
            raise MeasuredDataError(f"{path}: field 'indenter' is missing (one library name or "
                                    "mesh path per sample)")
        names = np.atleast_1d(read("indenter"))
        if names.dtype.kind not in "US" or names.ndim != 1:
            raise MeasuredDataError(f"{path}: field 'indenter' must be (N,) strings (one library "
                                    f"name or mesh path per sample), got {names.shape} "
                                    f"{names.dtype}; save it as np.array(names, dtype=str)")
        indenter = [s.decode() if isinstance(s, bytes) else str(s) for s in names.tolist()]
        n = len(indenter)

        def per_sample(name, default=np.nan):
            if name not in keys:
                return np.full(n, default)
            arr = read(name)
            try:
                return np.asarray(arr, np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise MeasuredDataError(f"{path}: field {name!r} must be numbers (NaN where not "
                                        f"known), got dtype {arr.dtype}") from None

        noise = None
        if "noise_mm" in keys:
            arr = read("noise_mm")
            if arr.size != 1 or arr.dtype.kind not in "iuf":
                raise MeasuredDataError(f"{path}: field 'noise_mm' must be one number (the pixel "
                                        f"noise, one sigma, mm), got shape {arr.shape} "
                                        f"{arr.dtype}; save one value for all samples, or leave "
                                        "the field out to have it estimated")
            noise = float(arr.reshape(-1)[0])
        data = MeasuredData(
            depth_mm=read("depth") if "depth" in keys else None,
            frames=read("frames") if "frames" in keys else None, indenter=indenter,
            x_mm=per_sample("x_mm"), y_mm=per_sample("y_mm"), theta_deg=per_sample("theta_deg"),
            depth_cmd_mm=per_sample("depth_mm"), force_n=per_sample("force_n"),
            contact_id=(np.asarray(read("contact_id")).reshape(-1) if "contact_id" in keys
                        else np.arange(n)),
            noise_mm=noise, source=str(path))
        if "header_json" in keys:
            header = _check_header(path, str(read("header_json")), data)
            data.metadata["header"] = header
        return data


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

    def contact_id(row, k):
        value = number(row, k, "contact_id")
        if not (np.isfinite(value) and value == round(value)):
            raise MeasuredDataError(f"{table}, row {k + 2}: column 'contact_id' must be an "
                                    f"integer, got {(row.get('contact_id') or '').strip()!r}; "
                                    "give every sample its contact's number, or leave out the "
                                    "column (every sample its own contact)")
        return int(value)

    ids = (np.array([contact_id(r, k) for k, r in enumerate(rows)])
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
        contact_id=ids, source=str(folder), metadata={"csv_rows": list(range(2, n + 2))})
