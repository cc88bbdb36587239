"""Ball-press recordings: a no-contact reference frame, press frames, optional labelled circles.

Images are held as (H, W, 3) uint8 **RGB** arrays (files are read with OpenCV and converted
from BGR). Circles are in image pixels: ``(centre column, centre row, contact radius)``.

Annotation files are CSV with the header ``img_names,center_x,center_y,radius`` (pixels; one
row per press frame, as in the FOTS ball-press data).
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
ANNOTATION_COLUMNS = ("img_names", "center_x", "center_y", "radius")


class PressDataError(ValueError):
    """A press recording (images or annotation file) is missing or malformed."""


@dataclass
class PressSet:
    """Ball presses of one sensor.

    reference : (H, W, 3) uint8 RGB, nothing touching the sensor.
    frames : (N, H, W, 3) uint8 RGB, one ball press each.
    names : N file names (no folder).
    circles : (N, 3) float64 px ``(column, row, radius)`` of the contact circles, or None.
    profiles : N modelled depth profiles around the contact centres
        (:class:`~tactile_deploy.calibration.shading.press_profile.PressProfile`, None where there is none):
        training targets for the gel outside the contact; or None.
    """

    reference: np.ndarray
    frames: np.ndarray
    names: list[str]
    circles: np.ndarray | None = None
    profiles: list | None = None

    def __post_init__(self):
        ref = np.asarray(self.reference)
        fr = np.asarray(self.frames)
        if ref.dtype != np.uint8 or ref.ndim != 3 or ref.shape[2] != 3:
            raise PressDataError(f"reference must be (H, W, 3) uint8 RGB, got {ref.shape} "
                                 f"{ref.dtype}")
        if fr.dtype != np.uint8 or fr.ndim != 4 or fr.shape[1:] != ref.shape:
            raise PressDataError(f"frames must be (N, {ref.shape[0]}, {ref.shape[1]}, 3) uint8, "
                                 f"got {fr.shape} {fr.dtype}")
        if len(self.names) != len(fr):
            raise PressDataError(f"{len(self.names)} names for {len(fr)} frames")
        if self.circles is not None:
            c = np.asarray(self.circles, np.float64)
            if c.shape != (len(fr), 3):
                raise PressDataError(f"circles must be ({len(fr)}, 3), got {c.shape}")
            if not np.all(np.isfinite(c)) or np.any(c[:, 2] <= 0):
                raise PressDataError("circles must be finite with positive radii")
            self.circles = c
        if self.profiles is not None and len(self.profiles) != len(fr):
            raise PressDataError(f"{len(self.profiles)} profiles for {len(fr)} frames")

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the frames, px."""
        return self.reference.shape[:2]

    def __len__(self) -> int:
        return len(self.frames)

    def subset(self, index) -> PressSet:
        """The presses at ``index`` (indices or boolean mask), same reference."""
        idx = np.arange(len(self))[index]
        return PressSet(self.reference, self.frames[idx], [self.names[i] for i in idx],
                        None if self.circles is None else self.circles[idx],
                        None if self.profiles is None else [self.profiles[i] for i in idx])


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB; PressDataError naming the file if unreadable."""
    import cv2

    path = Path(path)
    if path.is_dir():
        raise PressDataError(f"{path} is a folder, not an image: give image files "
                             f"({', '.join(IMAGE_SUFFIXES)})")
    if not path.is_file():
        raise PressDataError(f"image {path} not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise PressDataError(f"{path}: not a readable image")
    if img.dtype != np.uint8:
        raise PressDataError(f"{path}: expected 8-bit colour, got dtype {img.dtype}")
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise PressDataError(f"{path}: expected a 3-channel colour image, got shape {img.shape}")
    return np.ascontiguousarray(img[..., 2::-1])


def read_annotations(path: str | os.PathLike) -> dict[str, tuple[float, float, float]]:
    """Labelled circles from a CSV ``img_names,center_x,center_y,radius`` (pixels).

    Returns {file name: (column, row, radius)}. Raises PressDataError naming the file, line and
    field of any problem.
    """
    path = Path(path)
    if not path.is_file():
        raise PressDataError(f"annotation file {path} not found")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            header = tuple(h.strip() for h in (reader.fieldnames or ()))
            if header != ANNOTATION_COLUMNS:
                raise PressDataError(f"{path}: header must be {','.join(ANNOTATION_COLUMNS)}, "
                                     f"got {','.join(header) or '(empty)'}")
            reader.fieldnames = list(header)   # "img_names, center_x, ..." reads the same
            rows = list(reader)
    except UnicodeDecodeError:
        raise PressDataError(f"{path}: not a text file (expected a CSV with the header "
                             f"{','.join(ANNOTATION_COLUMNS)})") from None
    out: dict[str, tuple[float, float, float]] = {}
    for line, row in enumerate(rows, start=2):
        name = (row["img_names"] or "").strip()
        if not name:
            raise PressDataError(f"{path}, line {line}: field 'img_names' is empty")
        vals = []
        for key in ANNOTATION_COLUMNS[1:]:
            text = (row[key] or "").strip()
            try:
                v = float(text)
            except ValueError:
                raise PressDataError(f"{path}, line {line}: field '{key}' must be a number "
                                     f"(pixels), got {text!r}") from None
            if not np.isfinite(v):
                raise PressDataError(f"{path}, line {line}: field '{key}' must be finite, "
                                     f"got {text!r}")
            vals.append(v)
        if vals[2] <= 0:
            raise PressDataError(f"{path}, line {line}: field 'radius' must be > 0 px, got "
                                 f"{vals[2]}")
        if name in out:
            raise PressDataError(f"{path}, line {line}: image {name!r} is listed twice")
        out[name] = (vals[0], vals[1], vals[2])
    if not out:
        raise PressDataError(f"{path}: no annotation rows")
    return out


def load_presses(reference: str | os.PathLike, presses: str | os.PathLike,
                 annotations: str | os.PathLike | None = None) -> PressSet:
    """Load a reference image and every image of the ``presses`` folder (sorted by name).

    The reference file is skipped if it lies in that folder. With ``annotations`` (CSV), every
    press image must have a row and every row an image; circles are then set.
    """
    reference = Path(reference)
    presses = Path(presses)
    if not presses.is_dir():
        raise PressDataError(f"press folder {presses} not found")
    ref = read_rgb(reference)
    files = sorted(p for p in presses.iterdir()
                   if p.suffix.lower() in IMAGE_SUFFIXES and p.resolve() != reference.resolve())
    if not files:
        raise PressDataError(f"{presses}: no images ({', '.join(IMAGE_SUFFIXES)})")
    frames = []
    for p in files:
        img = read_rgb(p)
        if img.shape != ref.shape:
            raise PressDataError(f"{p}: size {img.shape[1]}x{img.shape[0]} px differs from the "
                                 f"reference {reference} ({ref.shape[1]}x{ref.shape[0]} px)")
        frames.append(img)
    names = [p.name for p in files]
    circles = None
    if annotations is not None:
        ann = read_annotations(annotations)
        missing = [n for n in names if n not in ann]
        if missing:
            raise PressDataError(f"{annotations}: no circle for image(s) {', '.join(missing[:5])}"
                                 f"{' ...' if len(missing) > 5 else ''} of {presses}")
        extra = sorted(set(ann) - set(names))
        if extra:
            raise PressDataError(f"{annotations}: rows for image(s) not in {presses}: "
                                 f"{', '.join(extra[:5])}{' ...' if len(extra) > 5 else ''}")
        circles = np.array([ann[n] for n in names], np.float64)
    return PressSet(ref, np.stack(frames), names, circles)
