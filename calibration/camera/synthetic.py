"""Frames of planar calibration targets seen through a known camera (virtual-sensor frames).

The estimators of this package take plain images, so these frames stand in for real ones (tests,
the documentation figure) and the virtual sensor's own renders can replace them unchanged.

Rendering is by inverse mapping, so every raw pixel is sampled exactly once::

    raw px --(cv2.undistortPoints, iterated to 1e-12)--> normalised --K--> undistorted px
           --plane_from_undistorted (3x3)--> plane mm --target_from_plane (3x3)--> target px
           --cv2.remap (bilinear)--> value

with the target first low-passed (a Gaussian of half a camera pixel, in target pixels) against
aliasing, optionally ``supersample x supersample`` samples per raw pixel averaged, then a Gaussian
blur (optics) and Gaussian noise (sensor). The lens inverse uses OpenCV's own iteration,
independent of the Newton solver in :mod:`tactile_deploy.imaging.camera_mapping`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from tactile_deploy.calibration.camera.charuco import CharucoBoardSpec, board_image


@dataclass(frozen=True)
class VirtualCamera:
    """A pinhole camera with OpenCV lens distortion.

    image_size : (width, height) px. camera_matrix : (3, 3) px.
    dist_coeffs : (5,) k1 k2 p1 p2 k3.
    """

    image_size: tuple[int, int]
    camera_matrix: tuple[tuple[float, ...], ...]
    dist_coeffs: tuple[float, ...]

    @classmethod
    def from_arrays(cls, image_size, camera_matrix, dist_coeffs) -> "VirtualCamera":
        k = np.asarray(camera_matrix, dtype=np.float64)
        return cls(
            image_size=(int(image_size[0]), int(image_size[1])),
            camera_matrix=tuple(tuple(float(v) for v in row) for row in k),
            dist_coeffs=tuple(float(v) for v in np.asarray(dist_coeffs, dtype=np.float64).ravel()),
        )

    @property
    def k(self) -> np.ndarray:
        """(3, 3) float64 camera matrix, px."""
        return np.array(self.camera_matrix)

    @property
    def d(self) -> np.ndarray:
        """(5,) float64 distortion coefficients."""
        return np.array(self.dist_coeffs)

    def project(self, plane_to_undistorted: np.ndarray, xy_mm: np.ndarray) -> np.ndarray:
        """Plane points (N, 2) mm -> raw px (N, 2), through ``cv2.projectPoints``."""
        xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        q = xy @ plane_to_undistorted[:, :2].T + plane_to_undistorted[:, 2]
        und = q[:, :2] / q[:, 2:3]
        k = self.k
        rays = np.stack([(und[:, 0] - k[0, 2]) / k[0, 0], (und[:, 1] - k[1, 2]) / k[1, 1],
                         np.ones(len(und))], axis=1)
        uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k, self.d)
        return uv.reshape(-1, 2)

    def undistort(self, uv_raw_px: np.ndarray) -> np.ndarray:
        """Raw px (N, 2) -> undistorted px (N, 2), through ``cv2.undistortPoints``."""
        return _undistort(self, np.asarray(uv_raw_px, dtype=np.float64).reshape(-1, 2))


def _undistort(camera: VirtualCamera, uv: np.ndarray) -> np.ndarray:
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-15)
    k = camera.k
    n = cv2.undistortPoints(uv.reshape(-1, 1, 2), k, camera.d, criteria=crit).reshape(-1, 2)
    return np.stack([n[:, 0] * k[0, 0] + k[0, 2], n[:, 1] * k[1, 1] + k[1, 2]], axis=1)


@lru_cache(maxsize=4)
def _sample_grid(camera: VirtualCamera, supersample: int) -> np.ndarray:
    """Undistorted px of the raw sample positions: (s*s, H, W, 2) float64."""
    width, height = camera.image_size
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    out = []
    for dv in offsets:
        for du in offsets:
            pts = np.stack([(u + du).ravel(), (v + dv).ravel()], axis=1)
            out.append(_undistort(camera, pts).reshape(height, width, 2))
    return np.stack(out)


def render_plane_image(
    target: np.ndarray,
    target_from_plane: np.ndarray,
    plane_from_undistorted: np.ndarray,
    camera: VirtualCamera,
    *,
    supersample: int = 1,
    background: float = 0.0,
) -> np.ndarray:
    """Image of a planar target through ``camera`` (no blur, no noise).

    target : (Ht, Wt) or (Ht, Wt, C) float32, the target's appearance in the plane.
    target_from_plane : (3, 3), plane mm -> target image px (column, row; pixel-centre convention).
    plane_from_undistorted : (3, 3), undistorted camera px -> plane mm.
    background : value outside the target image.
    Returns (H, W[, C]) float32, raw camera pixels.
    """
    m = np.asarray(target_from_plane, dtype=np.float64) @ np.asarray(
        plane_from_undistorted, dtype=np.float64)
    # Target pixels per camera pixel at the image centre -> anti-alias pre-filter.
    width, height = camera.image_size
    c = np.array([(width - 1) / 2.0, (height - 1) / 2.0, 1.0])
    q0, qu, qv = m @ c, m @ (c + [1.0, 0, 0]), m @ (c + [0, 1.0, 0])
    step = max(np.hypot(*(qu[:2] / qu[2] - q0[:2] / q0[2])),
               np.hypot(*(qv[:2] / qv[2] - q0[:2] / q0[2])))
    target = target.astype(np.float32)
    if step / supersample > 1.0:
        target = cv2.GaussianBlur(target, (0, 0), 0.5 * step / supersample)
    acc = None
    for und in _sample_grid(camera, supersample):
        q = und @ m[:, :2].T + m[:, 2]
        w = q[..., 2]
        if not (np.all(w > 0) or np.all(w < 0)):
            raise ValueError("the plane's horizon crosses the image (W changes sign)")
        mx = (q[..., 0] / w).astype(np.float32)
        my = (q[..., 1] / w).astype(np.float32)
        s = cv2.remap(target, mx, my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=background)
        acc = s if acc is None else acc + s
    return acc / supersample**2


def finish_frame(image: np.ndarray, *, blur_sigma_px: float, noise_sigma: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Optics blur + sensor noise, then quantise: (H, W[, C]) float -> uint8."""
    out = image.astype(np.float32)
    if blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma_px)
    out = out + rng.normal(0.0, noise_sigma, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------ targets
def board_to_sensor(spec: CharucoBoardSpec, board_faces_camera: bool = True) -> np.ndarray:
    """(3, 3): board mm (origin top-left, x right, y down as printed) -> sensor mm.

    The board is centred on the pad with its printed x axis along sensor +x. Printed side facing
    the camera (lying face down on a clear gel): printed "down" is sensor +y; facing outwards
    (seen through a transparent sheet): printed "down" is sensor -y.
    """
    sy = 1.0 if board_faces_camera else -1.0
    return np.array([[1.0, 0.0, -spec.board_width_mm / 2.0],
                     [0.0, sy, -sy * spec.board_height_mm / 2.0],
                     [0.0, 0.0, 1.0]])


def charuco_target(spec: CharucoBoardSpec, px_per_mm: float = 25.0, margin_mm: float = 3.0):
    """The board as a plane image: ``(image, target_from_board)``.

    image : (Ht, Wt) float32 in [0, 255], board plus a white paper margin.
    target_from_board : (3, 3), board mm -> image px.
    """
    img = board_image(spec, px_per_mm).astype(np.float32)
    m = int(round(margin_mm * px_per_mm))
    img = cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255.0)
    ppm_x = (img.shape[1] - 2 * m) / spec.board_width_mm
    ppm_y = (img.shape[0] - 2 * m) / spec.board_height_mm
    t = np.array([[ppm_x, 0.0, m - 0.5], [0.0, ppm_y, m - 0.5], [0.0, 0.0, 1.0]])
    return img, t


def pressed_dots_signal(
    pitch_mm: float,
    shape: tuple[int, int],
    *,
    dot_sigma_mm: float = 0.35,
    depth_mm: float = 0.25,
    gain: float = 160.0,
    extent_mm: float = 22.0,
    px_per_mm: float = 20.0,
):
    """Change of a three-light shading when a grid of rounded pins dents the gel.

    Each pin leaves a Gaussian dent (pins at least 7 ``dot_sigma_mm`` apart, so that each point
    feels only its nearest pin) ``h = -depth exp(-r^2 / (2 sigma^2))``; channel c of the image
    changes by ``gain (n . l_c - l_c,z)`` with ``n`` the dent's unit normal and ``l_c`` three
    lights 120 degrees apart in azimuth, 45 degrees in elevation (a GelSight-style rig). The grid
    is ``shape = (columns, rows)`` dots of ``pitch_mm``, centred on the sensor origin.

    Returns ``(signal, target_from_sensor)``: (Ht, Wt, 3) float32 (grey levels, signed) over
    +-``extent_mm``, and the (3, 3) map sensor mm -> signal image px (row 0 at the largest y).
    """
    n = int(round(2 * extent_mm * px_per_mm))
    coords = (np.arange(n) + 0.5) / px_per_mm - extent_mm
    x, y = np.meshgrid(coords, -coords)
    cols, rows = shape
    # Dents are > 7 sigma apart, so each point only feels the nearest pin.
    ix = np.clip(np.rint(x / pitch_mm + (cols - 1) / 2.0), 0, cols - 1)
    iy = np.clip(np.rint(y / pitch_mm + (rows - 1) / 2.0), 0, rows - 1)
    dx = x - (ix - (cols - 1) / 2.0) * pitch_mm
    dy = y - (iy - (rows - 1) / 2.0) * pitch_mm
    h = -depth_mm * np.exp(-(dx * dx + dy * dy) / (2 * dot_sigma_mm**2))
    gx = -dx / dot_sigma_mm**2 * h  # dh/dx
    gy = -dy / dot_sigma_mm**2 * h
    norm = np.sqrt(1.0 + gx * gx + gy * gy)
    nx, ny, nz = -gx / norm, -gy / norm, 1.0 / norm
    out = []
    for az in np.deg2rad([90.0, 210.0, 330.0]):
        lx, ly, lz = np.cos(az) / np.sqrt(2), np.sin(az) / np.sqrt(2), 1 / np.sqrt(2)
        out.append(gain * (nx * lx + ny * ly + nz * lz - lz))
    signal = np.stack(out, axis=-1).astype(np.float32)
    t = np.array([[px_per_mm, 0.0, extent_mm * px_per_mm - 0.5],
                  [0.0, -px_per_mm, extent_mm * px_per_mm - 0.5],
                  [0.0, 0.0, 1.0]])
    return signal, t


def gel_reference(camera: VirtualCamera, rng: np.random.Generator) -> np.ndarray:
    """A smooth, coloured, vignetted image of an unpressed gel: (H, W, 3) float32, 0..255."""
    width, height = camera.image_size
    u, v = np.meshgrid(np.linspace(-1, 1, width), np.linspace(-1, 1, height))
    base = 150.0 - 45.0 * (u * u + v * v)
    chans = [base + 25.0 * u, base + 25.0 * v, base - 20.0 * u * v]
    img = np.stack(chans, axis=-1).astype(np.float32)
    texture = cv2.GaussianBlur(rng.normal(0, 6.0, (height, width)).astype(np.float32), (0, 0), 3)
    return img + texture[..., None]


# ------------------------------------------------------------------------------- scenes
def render_charuco_frame(
    spec: CharucoBoardSpec,
    camera: VirtualCamera,
    board_to_undistorted: np.ndarray,
    rng: np.random.Generator,
    *,
    blur_sigma_px: float = 0.8,
    noise_sigma: float = 2.0,
    background: float = 128.0,
) -> np.ndarray:
    """A (H, W) uint8 frame of the board through ``camera``.

    board_to_undistorted : (3, 3), board mm (origin top-left, x right, y down as printed) ->
        undistorted camera px; for the board on the sensor plane use
        ``sensor_to_undistorted @ board_to_sensor(spec, faces_camera)``.
    """
    target, target_from_board = charuco_target(spec)
    img = render_plane_image(target, target_from_board, np.linalg.inv(board_to_undistorted),
                             camera, background=background)
    return finish_frame(img, blur_sigma_px=blur_sigma_px, noise_sigma=noise_sigma, rng=rng)


def render_dot_press(
    camera: VirtualCamera,
    sensor_to_undistorted: np.ndarray,
    pitch_mm: float,
    shape: tuple[int, int],
    rng: np.random.Generator,
    *,
    blur_sigma_px: float = 0.8,
    noise_sigma: float = 2.0,
) -> tuple[np.ndarray, np.ndarray]:
    """``(pressed, reference)``: (H, W, 3) uint8 frames of a gel with and without a dot grid
    (:func:`pressed_dots_signal`) pressed in; independent noise in each."""
    reference = gel_reference(camera, rng)
    signal, target_from_sensor = pressed_dots_signal(pitch_mm, shape)
    change = render_plane_image(signal, target_from_sensor, np.linalg.inv(sensor_to_undistorted),
                                camera)
    pressed = finish_frame(reference + change, blur_sigma_px=blur_sigma_px,
                           noise_sigma=noise_sigma, rng=rng)
    ref = finish_frame(reference, blur_sigma_px=blur_sigma_px, noise_sigma=noise_sigma, rng=rng)
    return pressed, ref
