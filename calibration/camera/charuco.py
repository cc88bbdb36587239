"""Camera mapping from frames of a ChArUco board (OpenCV ``cv2.aruco``).

The board
---------
Default: 14 x 14 squares of 3.0 mm (42 x 42 mm), ArUco markers of 2.25 mm from
``DICT_4X4_100`` (98 markers). The 13 x 13 = 169 inner chessboard corners are the calibration
points; they reach +-18 mm, so the whole +-17.5 mm output grid is measured rather than
extrapolated (the board is larger than a 35 mm pad on purpose; corners outside the camera's view
are simply not detected), and the centre corner is the board's centre. Each marker bit is
0.375 mm: 9 printer dots at 600 dpi, about 5 camera pixels at 0.07 mm/px, enough for detection.
Board coordinates (OpenCV's): origin at the board's top-left corner as printed, x to the right,
y down, mm.

Placement and the sensor frame
------------------------------
The board is centred on the pad, its printed x axis along sensor +x, in the plane of the sensing
surface. ``board_faces_camera=True`` (default): the printed side faces the camera, e.g. lying face
down on a clear gel before coating; printed "down" is then sensor +y. ``False``: the printed
side faces outwards (a transparency seen through from below); printed "down" is sensor -y.

Frames and what they determine
------------------------------
* **One frame** (the board on the sensor plane): a single-view fit (:mod:`tactile_deploy.calibration.camera.
  fitting`): homography + principal point + k1, k2, p1, p2, with fx = fy = ``focal_px`` assumed.
  The raw pixel -> mm mapping is fully determined; the focal length, and hence the coefficients
  on their own, are not.
* **Three or more frames** at different tilts (20-40 degrees; the board off the sensor, held in
  front of the camera) plus the sensor-plane frame: ``cv2.calibrateCamera`` on all of them
  determines fx, fy, cx, cy, k1, k2, p1, p2 (k3 on request); the homography then comes from the
  sensor-plane frame with the lens held fixed.
"""

from __future__ import annotations

import warnings
from functools import lru_cache
from pathlib import Path
from typing import Literal, Sequence

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from tactile_deploy.calibration.camera.fitting import (
    CalibrationError,
    PlaneFit,
    fit_plane_mapping,
    single_view_camera_matrix,
)
from tactile_deploy.atomic import atomic_path, write_text
from tactile_deploy.imaging.camera_mapping import OutputGrid

#: Fewest detected corners for a frame to be used.
MIN_CORNERS = 12

_DICTIONARIES = {
    "DICT_4X4_50": 50, "DICT_4X4_100": 100, "DICT_4X4_250": 250, "DICT_4X4_1000": 1000,
    "DICT_5X5_50": 50, "DICT_5X5_100": 100, "DICT_5X5_250": 250, "DICT_5X5_1000": 1000,
    "DICT_6X6_50": 50, "DICT_6X6_100": 100, "DICT_6X6_250": 250, "DICT_6X6_1000": 1000,
}


class TargetNotFoundError(ValueError):
    """No usable calibration target was found in a frame (the message says what to try)."""


class CharucoBoardSpec(BaseModel):
    """A printed ChArUco board (the JSON written beside the board image by ``make-board``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    format_version: Literal[1] = Field(1, description="Version of this file format.")
    squares_x: int = Field(14, ge=3, description="Squares along the board's x (printed width).")
    squares_y: int = Field(14, ge=3, description="Squares along the board's y (printed height).")
    square_mm: float = Field(3.0, gt=0, description="Side of a chessboard square, mm.")
    marker_mm: float = Field(2.25, gt=0, description="Side of an ArUco marker, mm.")
    dictionary: Literal[tuple(_DICTIONARIES)] = Field(  # type: ignore[valid-type]
        "DICT_4X4_100", description="OpenCV predefined ArUco dictionary."
    )

    @model_validator(mode="after")
    def _check(self) -> "CharucoBoardSpec":
        if self.marker_mm >= self.square_mm:
            raise ValueError(
                f"marker_mm={self.marker_mm} must be smaller than square_mm={self.square_mm}"
            )
        needed = self.squares_x * self.squares_y // 2
        if needed > _DICTIONARIES[self.dictionary]:
            raise ValueError(
                f"a {self.squares_x}x{self.squares_y} board needs {needed} markers but "
                f"{self.dictionary} has {_DICTIONARIES[self.dictionary]}"
            )
        return self

    @property
    def board_width_mm(self) -> float:
        return self.squares_x * self.square_mm

    @property
    def board_height_mm(self) -> float:
        return self.squares_y * self.square_mm

    def describe(self) -> str:
        return (f"ChArUco {self.squares_x}x{self.squares_y} squares of {self.square_mm:.3f} mm, "
                f"markers {self.marker_mm:.3f} mm, {self.dictionary}")


@lru_cache(maxsize=8)
def cv_board(spec: CharucoBoardSpec) -> cv2.aruco.CharucoBoard:
    """The OpenCV board object (lengths in mm)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    return cv2.aruco.CharucoBoard(
        (spec.squares_x, spec.squares_y), spec.square_mm, spec.marker_mm, dictionary
    )


@lru_cache(maxsize=8)
def _detector(spec: CharucoBoardSpec) -> cv2.aruco.CharucoDetector:
    return cv2.aruco.CharucoDetector(cv_board(spec))


def board_image(spec: CharucoBoardSpec, px_per_mm: float) -> np.ndarray:
    """The board alone, (round(H_mm * px_per_mm), round(W_mm * px_per_mm)) uint8, 0 black."""
    size = (int(round(spec.board_width_mm * px_per_mm)),
            int(round(spec.board_height_mm * px_per_mm)))
    return cv_board(spec).generateImage(size, marginSize=0, borderBits=1)


def print_sheet(spec: CharucoBoardSpec, dpi: int = 600, margin_mm: float = 6.0):
    """A print-ready sheet: the board at true size, a 10 mm scale bar and a caption.

    Returns ``(image, board_size_mm)``: (H, W) uint8 at ``dpi``, and the printed board's
    (width, height) in mm as rendered (pixel counts / dpi).
    """
    ppm = dpi / 25.4
    board = board_image(spec, ppm)
    size_mm = (board.shape[1] / ppm, board.shape[0] / ppm)
    m = int(round(margin_mm * ppm))
    font, scale, thick = cv2.FONT_HERSHEY_SIMPLEX, dpi / 600.0 * 1.1, max(1, int(dpi / 300))
    lines = [
        spec.describe(),
        f"Print at 100 % ({dpi} dpi): board {size_mm[0]:.2f} x {size_mm[1]:.2f} mm. Bar: 10 mm.",
        "Top edge = printed y = 0; x to the right. Centre the board on the pad.",
    ]
    text_w = max(cv2.getTextSize(t, font, scale, thick)[0][0] for t in lines)
    line_h = int(cv2.getTextSize("Ag", font, scale, thick)[0][1] * 1.9)
    bar_h = int(round(8 * ppm))
    width = max(board.shape[1] + 2 * m, text_w + 2 * m)
    height = m + board.shape[0] + bar_h + len(lines) * line_h + m
    sheet = np.full((height, width), 255, np.uint8)
    x0 = (width - board.shape[1]) // 2
    sheet[m:m + board.shape[0], x0:x0 + board.shape[1]] = board
    # 10 mm scale bar with end ticks, under the board.
    y_bar = m + board.shape[0] + int(round(3 * ppm))
    x_end = x0 + int(round(10 * ppm))
    cv2.rectangle(sheet, (x0, y_bar), (x_end - 1, y_bar + int(round(0.6 * ppm))), 0, -1)
    for xt in (x0, x_end - 1):
        cv2.line(sheet, (xt, y_bar - int(round(1.2 * ppm))), (xt, y_bar + int(round(1.8 * ppm))),
                 0, thick)
    y = m + board.shape[0] + bar_h
    for t in lines:
        y += line_h
        cv2.putText(sheet, t, (m, y - line_h // 4), font, scale, 0, thick, cv2.LINE_AA)
    return sheet, size_mm


def save_print_sheet(spec: CharucoBoardSpec, path: str | Path,
                     dpi: int = 600) -> tuple[float, float]:
    """Write the print sheet (PNG with its dpi recorded) and ``<stem>.json`` (the board spec).

    Both files are written atomically. Returns the board's printed size (width, height) in mm.
    """
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"board image must be a .png file, got {path}")
    sheet, size_mm = print_sheet(spec, dpi)
    with atomic_path(path) as tmp:
        Image.fromarray(sheet).save(tmp, dpi=(dpi, dpi))
    write_text(path.with_suffix(".json"), spec.model_dump_json(indent=2) + "\n")
    return size_mm


def load_board_spec(path: str | Path) -> CharucoBoardSpec:
    """Read a board spec JSON written by :func:`save_print_sheet` (clear errors)."""
    from pydantic import ValidationError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"board description {path} not found (written by make-board)")
    try:
        return CharucoBoardSpec.model_validate_json(path.read_text(encoding="utf-8"))
    except ValidationError as e:
        details = "; ".join(
            f"field '{'.'.join(str(p) for p in err['loc']) or '(document)'}': {err['msg']}"
            for err in e.errors()
        )
        raise ValueError(f"{path}: invalid board description: {details}") from None


# ---------------------------------------------------------------------------- detection
def to_gray_u8(frame: np.ndarray, name: str = "frame") -> np.ndarray:
    """(H, W) or (H, W, 3|4) BGR(A) image of any numeric dtype -> (H, W) uint8."""
    img = np.asarray(frame)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img[..., :3].astype(np.float32), cv2.COLOR_BGR2GRAY)
    elif img.ndim != 2:
        raise ValueError(f"{name}: expected an (H, W) or (H, W, 3) image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img
    img = img.astype(np.float32)
    lo, hi = float(np.min(img)), float(np.max(img))
    if not np.isfinite(lo + hi):
        raise ValueError(f"{name}: image contains NaN or inf")
    if hi <= 255.0 and lo >= 0.0 and hi > 1.0:
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return np.clip(np.rint((img - lo) * (255.0 / max(hi - lo, 1e-12))), 0, 255).astype(np.uint8)


def detect_charuco(frame: np.ndarray, spec: CharucoBoardSpec, name: str = "frame"):
    """Inner chessboard corners of the board in one frame.

    Returns ``(uv_px, ids)``: (N, 2) float64 raw px (sub-pixel) and (N,) int corner ids
    (row-major over the inner corners). Raises :class:`TargetNotFoundError` when fewer than
    :data:`MIN_CORNERS` corners are found.
    """
    gray = to_gray_u8(frame, name)
    corners, ids, _, marker_ids = _detector(spec).detectBoard(gray)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    n = 0 if ids is None else len(ids)
    if n < MIN_CORNERS:
        raise TargetNotFoundError(
            f"{name}: found {n} ChArUco corners ({n_markers} markers), need {MIN_CORNERS}. "
            "Check that the board is in view, evenly lit and in focus, and that the board "
            f"description matches the print (expected {spec.describe()}; pass --board board.json "
            "from make-board). For a grid pressed into the gel use --target dots."
        )
    return corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(int)


def board_corners_mm(spec: CharucoBoardSpec, ids: np.ndarray) -> np.ndarray:
    """Board coordinates (N, 2) mm of inner-corner ``ids`` (origin top-left, x right, y down)."""
    return np.asarray(cv_board(spec).getChessboardCorners(), dtype=np.float64)[ids, :2]


def board_to_sensor_mm(spec: CharucoBoardSpec, bxy_mm: np.ndarray,
                       board_faces_camera: bool = True) -> np.ndarray:
    """Board coordinates -> sensor frame (N, 2) mm for a board centred on the pad (see module)."""
    b = np.asarray(bxy_mm, dtype=np.float64)
    x = b[:, 0] - spec.board_width_mm / 2.0
    y = b[:, 1] - spec.board_height_mm / 2.0
    return np.stack([x, y if board_faces_camera else -y], axis=1)


# --------------------------------------------------------------------------- estimation
def calibrate_charuco(
    frames: Sequence[np.ndarray],
    spec: CharucoBoardSpec | None = None,
    *,
    plane_index: int = 0,
    board_faces_camera: bool = True,
    focal_px: float | None = None,
    free_lens: tuple[str, ...] = ("cx", "cy", "k1", "k2", "p1", "p2"),
    fit_k3: bool = False,
    grid: OutputGrid | None = None,
    names: Sequence[str] | None = None,
) -> PlaneFit:
    """Camera mapping from ChArUco frames.

    frames : raw camera frames, each (H, W) or (H, W, 3) BGR, all the same size.
        ``frames[plane_index]`` shows the board on the sensor plane (see the module docstring).
        One frame: single-view fit (``focal_px``, ``free_lens`` apply). Several frames:
        ``cv2.calibrateCamera`` on all of them, then the homography from the plane frame.
    names : frame names for messages (file names); indices when None.
    Returns a :class:`PlaneFit` whose residuals are those of the plane frame.
    """
    spec = spec or CharucoBoardSpec()
    if len(frames) == 0:
        raise CalibrationError("no frames given")
    names = list(names) if names is not None else [f"frame {i}" for i in range(len(frames))]
    if not 0 <= plane_index < len(frames):
        raise ValueError(f"plane_index={plane_index} is out of range for {len(frames)} frames")
    shape = np.asarray(frames[0]).shape[:2]
    for f, n in zip(frames, names):
        if np.asarray(f).shape[:2] != shape:
            raise ValueError(f"{n} is {np.asarray(f).shape[1]}x{np.asarray(f).shape[0]} px but "
                             f"{names[0]} is {shape[1]}x{shape[0]} px: all frames must match")
    image_size = (shape[1], shape[0])

    uv_plane, ids_plane = detect_charuco(frames[plane_index], spec, names[plane_index])
    xy_plane = board_to_sensor_mm(spec, board_corners_mm(spec, ids_plane), board_faces_camera)

    if len(frames) == 1:
        k = single_view_camera_matrix(image_size, focal_px)
        return fit_plane_mapping(
            uv_plane, xy_plane, image_size, k, None, free_lens,
            method="charuco-single-view", n_frames=1, focal_assumed=True, grid=grid,
        )

    obj, img, skipped = [], [], []
    for i, (f, n) in enumerate(zip(frames, names)):
        if i == plane_index:
            uv, ids = uv_plane, ids_plane
        else:
            try:
                uv, ids = detect_charuco(f, spec, n)
            except TargetNotFoundError:
                skipped.append(n)
                continue
        b = board_corners_mm(spec, ids)
        obj.append(np.c_[b, np.zeros(len(b))].astype(np.float32))
        img.append(uv.astype(np.float32).reshape(-1, 1, 2))
    if skipped:
        warnings.warn(f"no ChArUco board found in {', '.join(skipped)}; frames skipped",
                      stacklevel=2)
    if len(obj) < 3:
        raise CalibrationError(
            f"a multi-view calibration needs the board in at least 3 frames, found it in "
            f"{len(obj)}: add frames with the board tilted 20-40 degrees, or pass only the "
            "sensor-plane frame for a single-view fit"
        )
    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, k, dist, _, _, std_intr, _, _ = cv2.calibrateCameraExtended(
        obj, img, image_size, None, None, flags=flags, criteria=crit
    )
    std_intr = np.asarray(std_intr).ravel()
    rel = float(max(std_intr[0] / k[0, 0], std_intr[1] / k[1, 1]))
    if rel > 0.02:
        warnings.warn(
            f"the focal length is poorly determined (+-{100 * rel:.1f} %): the views need more "
            "varied tilts; the pixel -> mm mapping of the plane frame is still fitted", stacklevel=2
        )
    fit = fit_plane_mapping(
        uv_plane, xy_plane, image_size, k, np.asarray(dist).ravel()[:5], (),
        method="charuco-multi-view", n_frames=len(obj), focal_assumed=False, grid=grid,
        fitted_lens=("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
        + (("k3",) if fit_k3 else ()),
    )
    return fit
