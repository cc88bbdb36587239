"""A folder of recorded ball presses: its frames, its no-contact frame, its circles.

Data flow of :func:`load_recording`::

    every image of the folder --read_colour_image (RGB, colour, one size)--> frames
    --contact_edge_score--> which frames show a contact
    --the no-contact frame: --reference if given (checked), else the frame without a contact
    --annotations (CSV) name the presses; without them every frame with a contact is a press

A frame's *contact edge score* is the 99.5th percentile of its colour-gradient magnitude (grey
levels per px, after a 2 px Gaussian): a ball press draws a disc of steep colour edges, a
no-contact frame is smooth (measured on the real GelSight presses: 1.4 for the no-contact frame,
4.7-5.9 for all 42 presses). A frame scoring less than half the presses' median is taken as
no contact.

Frames are (H, W, 3) uint8 RGB, raw camera pixels; circles (column, row, radius) raw px.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tactile_deploy.calibration.recording.errors import PlausibilityError
from tactile_deploy.calibration.shading.presses import IMAGE_SUFFIXES, PressDataError, read_annotations
from tactile_deploy.runtime.reference import contact_edge_score

#: A frame scoring below this fraction of the presses' median contact-edge score has no contact.
NO_CONTACT_FRACTION = 0.5


def read_colour_image(path: str | os.PathLike) -> np.ndarray:
    """An image file as (H, W, 3) uint8 RGB, refusing what is not a colour camera frame: a
    greyscale image (one channel, or three identical ones), 16-bit images, unreadable files."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise PressDataError(f"image {path} not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise PressDataError(f"{path}: not a readable image")
    if img.dtype != np.uint8:
        raise PlausibilityError(f"{path}: {img.dtype} pixels; the calibration reads the camera's "
                                "8-bit RGB frames: save the frames as 8-bit colour images")
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        raise PlausibilityError(
            f"{path}: a greyscale image (1 channel), expected the sensor's RGB frames (3 "
            "channels): shading needs the colours of the LEDs; record colour frames (not a grey "
            "preview or a single channel)")
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise PlausibilityError(f"{path}: {img.shape[2] if img.ndim == 3 else img.ndim} "
                                "channels, expected 3 (RGB) (or 4 with alpha)")
    rgb = np.ascontiguousarray(img[..., 2::-1])
    spread = max(int(np.abs(rgb[..., 0].astype(np.int16) - rgb[..., 1]).max()),
                 int(np.abs(rgb[..., 1].astype(np.int16) - rgb[..., 2]).max()))
    if spread <= 2:
        raise PlausibilityError(
            f"{path}: its three channels are identical (a greyscale image saved as RGB); the "
            "shading calibration needs the sensor's colour frames: record them in colour")
    return rgb


@dataclass
class Recording:
    """Ball presses of one sensor, as found in a folder.

    reference : (H, W, 3) uint8, the no-contact frame; reference_path : its file;
    reference_picked : True when it was picked from the folder (no --reference).
    frames : (N, H, W, 3) uint8 presses; names : their file names.
    circles : (N, 3) raw px from --annotations, or None (detect them).
    no_contact : other frames without contact (K, H, W, 3) (for the noise reference).
    scores : contact-edge score of every file read, by name.
    """

    folder: Path
    reference: np.ndarray
    reference_path: Path
    reference_picked: bool
    frames: np.ndarray
    names: list[str]
    circles: np.ndarray | None
    no_contact: np.ndarray
    scores: dict[str, float] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.reference.shape[:2]


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def load_recording(presses: str | os.PathLike, reference: str | os.PathLike | None = None,
                   annotations: str | os.PathLike | None = None) -> Recording:
    """Read a press folder (module docstring); raises :class:`PlausibilityError` or
    :class:`~tactile_deploy.calibration.shading.presses.PressDataError` naming the file and what to fix."""
    folder = Path(presses)
    if not folder.is_dir():
        raise PressDataError(f"--presses {folder}: folder not found")
    files = _images(folder)
    ref_path = None if reference is None else Path(reference)
    if ref_path is not None and not ref_path.is_file():
        raise PressDataError(f"--reference {ref_path}: file not found")
    ann = read_annotations(annotations) if annotations is not None else None
    if ann is not None:
        missing = sorted(set(ann) - {p.name for p in files})
        if missing:
            raise PressDataError(f"--annotations {annotations}: rows for image(s) not in "
                                 f"{folder}: {', '.join(missing[:5])}"
                                 f"{' ...' if len(missing) > 5 else ''}")
    if ref_path is not None:
        files = [p for p in files if p.resolve() != ref_path.resolve()]
    if not files:
        raise PressDataError(f"--presses {folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    images = {p.name: read_colour_image(p) for p in files}
    shapes = {im.shape for im in images.values()}
    ref_img = read_colour_image(ref_path) if ref_path is not None else None
    if ref_img is not None:
        shapes.add(ref_img.shape)
    if len(shapes) > 1:
        first = files[0]
        for p in files[1:] + ([ref_path] if ref_path is not None else []):
            im = images.get(p.name) if p != ref_path else ref_img
            if im.shape != images[first.name].shape:
                raise PressDataError(
                    f"{p}: size {im.shape[1]}x{im.shape[0]} px differs from {first} "
                    f"({images[first.name].shape[1]}x{images[first.name].shape[0]} px): all "
                    "frames of one recording come from one camera setting")
    scores = {n: contact_edge_score(im) for n, im in images.items()}
    press_names = ([n for n in images if n in ann] if ann is not None else list(images))
    if not press_names:
        raise PressDataError(f"--annotations {annotations}: names none of the images of {folder}")
    typical = float(np.median([scores[n] for n in press_names]))
    limit = NO_CONTACT_FRACTION * typical
    if ref_img is not None:
        s = contact_edge_score(ref_img)
        scores[ref_path.name] = s
        if s > limit:
            raise PlausibilityError(
                f"--reference {ref_path}: this frame shows a contact (its colour edges are "
                f"{s:.1f} grey levels/px, {s / typical:.0%} of a press's {typical:.1f}; a "
                "no-contact frame is smooth): record the reference with nothing touching the "
                "sensor, or leave --reference out to pick the no-contact frame of the recording")
        picked = False
    else:
        candidates = [n for n in images if ann is None or n not in ann]
        if not candidates:
            raise PlausibilityError(
                f"--presses {folder}: every image is a press of --annotations {annotations}; add "
                "a frame with nothing touching the sensor to the folder, or pass --reference FILE")
        best = min(candidates, key=lambda n: scores[n])
        if scores[best] > limit:
            raise PlausibilityError(
                f"--presses {folder}: no frame without contact (the smoothest, {best}, has colour "
                f"edges of {scores[best]:.1f} grey levels/px against {typical:.1f} for a press; "
                "a no-contact frame is smooth): record one with nothing touching the sensor into "
                "the folder, or pass --reference FILE")
        ref_path, ref_img, picked = folder / best, images.pop(best), True
        if best in press_names:
            press_names.remove(best)
    no_contact = [n for n in press_names if scores[n] <= limit and ann is None]
    press_names = [n for n in press_names if n not in no_contact]
    others = [n for n in images if n not in press_names and n not in no_contact
              and scores[n] <= limit]
    if ann is not None:
        flat = [n for n in press_names if scores[n] <= limit]
        if flat:
            raise PlausibilityError(
                f"--annotations {annotations}: {', '.join(flat[:5])} show(s) no contact (colour "
                f"edges {scores[flat[0]]:.1f} against {typical:.1f} grey levels/px for a press); "
                "remove their rows or the frames")
    if len(press_names) < 4:
        raise PlausibilityError(f"--presses {folder}: {len(press_names)} press frame(s); the "
                                "calibration needs at least 4 ball presses (20 or more spread "
                                "over the view calibrate well)")
    circles = None if ann is None else np.array([ann[n] for n in press_names], np.float64)
    nc = [images[n] for n in no_contact + others]
    return Recording(folder, ref_img, ref_path, picked,
                     np.stack([images[n] for n in press_names]), press_names, circles,
                     np.stack(nc) if nc else np.zeros((0, *ref_img.shape), np.uint8), scores)
