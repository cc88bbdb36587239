"""Camera mapping from a grid of dots of known pitch pressed into the gel.

The target: a plate of rounded pins on a square lattice of ``pitch_mm`` (for example 13 x 13 pins
at 2.5 mm), centred on the pad with its rows along sensor x, pressed a fraction of a millimetre
into the gel. In the frame minus a reference frame of the unpressed gel each pin is a blob (for a
photometric rig a ring of shading change around the dent; the per-pixel norm over the colour
channels makes it one blob after smoothing).

Steps
-----
1. :func:`detect_dots`: ``|frame - reference|`` (norm over channels), Gaussian smoothing, a
   threshold well above the noise (and at least Otsu's), connected components; each component's
   centre is its intensity-weighted centroid. Components touching the border are dropped.
2. :func:`assign_grid_indices`: lattice indices by growing from a dot near the centre whose four
   neighbours are where its lattice vectors predict: each step predicts the neighbour at
   ``p +- a``, ``p +- b`` with ``a, b`` the local lattice vectors, updated from each accepted step,
   so the prediction follows the lens distortion. Blobs off the lattice stay unassigned; the dots
   beyond a missing one are reached around it. Orientation: the lattice vector closest to the
   image direction of sensor +x (from ``u_axis``/``v_axis``, the sensor axes that image right and
   down point along) is index +x. The index origin is the centre of the detected extent, checked
   against ``grid_shape`` when given.
3. :func:`calibration.camera.fitting.fit_plane_mapping` on one view: homography + principal point
   + k1, k2, p1, p2 with fx = fy assumed (what one view determines: see that module). The mapping
   is measured where the dots are; use a grid that spans the sensing area.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree

from calibration.camera.charuco import TargetNotFoundError
from calibration.camera.fitting import (
    CalibrationError,
    PlaneFit,
    fit_plane_mapping,
    single_view_camera_matrix,
)
from tactile_deploy.imaging.camera_mapping import OutputGrid

#: Fewest dots for a calibration (homography + 4 distortion coefficients, with redundancy).
MIN_DOTS = 16

_AXES = {"+x": (0, 1.0), "-x": (0, -1.0), "+y": (1, 1.0), "-y": (1, -1.0)}


@dataclass(frozen=True)
class DotDetections:
    """Blobs found in a reference-subtracted frame.

    centres_px : (N, 2) float64, raw px (u, v): intensity-weighted centroids.
    areas_px : (N,) int, pixels above threshold per blob.
    strength : (H, W) float32, the smoothed change magnitude the blobs were cut from.
    threshold : float, the level used (same units as ``strength``).
    """

    centres_px: np.ndarray
    areas_px: np.ndarray
    strength: np.ndarray
    threshold: float


def detect_dots(frame: np.ndarray, reference: np.ndarray | None = None, *,
                blur_sigma_px: float = 2.5, min_area_px: int = 8,
                name: str = "frame") -> DotDetections:
    """Centres of the pressed dots.

    frame : (H, W) or (H, W, C) raw camera frame (any numeric dtype) with the grid pressed, or an
        already reference-subtracted frame when ``reference`` is None.
    reference : same shape, the unpressed gel.
    blur_sigma_px : smoothing before thresholding, px; about half a dot's radius in the image.
    """
    f = np.asarray(frame, dtype=np.float32)
    if f.ndim not in (2, 3):
        raise ValueError(f"{name}: expected an (H, W) or (H, W, C) image, got shape {f.shape}")
    if reference is not None:
        r = np.asarray(reference, dtype=np.float32)
        if r.shape != f.shape:
            raise ValueError(f"{name}: reference frame has shape {r.shape}, frame has {f.shape}")
        f = f - r
    mag = np.sqrt(np.sum(f * f, axis=2)) if f.ndim == 3 else np.abs(f)
    if not np.all(np.isfinite(mag)):
        raise ValueError(f"{name}: frame contains NaN or inf")
    s = cv2.GaussianBlur(mag, (0, 0), blur_sigma_px)
    med = float(np.median(s))
    # noise of the smoothed magnitude: pixel noise from the high-pass residual (robust when
    # the dots cover much of the frame, unlike the spread of ``s`` itself) times the Gaussian's
    # white-noise gain 1 / (2 sqrt(pi) sigma)
    high = mag - cv2.GaussianBlur(mag, (0, 0), 1.0)
    pixel_noise = 1.4826 * float(np.median(np.abs(high - np.median(high))))
    noise = pixel_noise / (2.0 * np.sqrt(np.pi) * max(blur_sigma_px, 0.5))
    peak = float(np.max(s))
    scaled = np.clip((s - med) * (255.0 / max(peak - med, 1e-12)), 0, 255).astype(np.uint8)
    otsu, _ = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    threshold = max(med + 8.0 * noise, med + otsu * (peak - med) / 255.0)
    mask = (s > threshold).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    height, width = s.shape
    w = np.maximum(s - threshold, 0.0)
    centres, areas = [], []
    for i in range(1, n):
        x0, y0, bw, bh, area = stats[i]
        if area < min_area_px or x0 == 0 or y0 == 0 or x0 + bw == width or y0 + bh == height:
            continue
        sub = (labels[y0:y0 + bh, x0:x0 + bw] == i) * w[y0:y0 + bh, x0:x0 + bw]
        total = float(sub.sum())
        vv, uu = np.mgrid[y0:y0 + bh, x0:x0 + bw]
        centres.append(((sub * uu).sum() / total, (sub * vv).sum() / total))
        areas.append(area)
    return DotDetections(
        centres_px=np.asarray(centres, dtype=np.float64).reshape(-1, 2),
        areas_px=np.asarray(areas, dtype=int),
        strength=s,
        threshold=threshold,
    )


def _axis_direction(axis_of_u: str, axis_of_v: str, sensor_axis: int) -> np.ndarray:
    """Image direction (du, dv) of sensor +x (sensor_axis 0) or +y (1)."""
    out = np.zeros(2)
    for k, name in enumerate((axis_of_u, axis_of_v)):
        ax, sign = _AXES[name]
        if ax == sensor_axis:
            out[k] = sign
    return out


def assign_grid_indices(centres_px: np.ndarray, *, u_axis: str = "+x", v_axis: str = "+y",
                        tolerance: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice indices of dot centres.

    centres_px : (N, 2) float, raw px.
    u_axis, v_axis : sensor axis ("+x", "-x", "+y", "-y") that image right (+u) and image down
        (+v) point along, to within 45 degrees. Default: a camera looking straight up at the
        gel, image right = sensor +x, image down = sensor +y (the mirrored view).
    tolerance : accepted distance of a neighbour from its prediction, fraction of the pitch.
    Returns ``(indices, assigned)``: (N, 2) int (ix along sensor +x, iy along +y; arbitrary
    origin) and (N,) bool; unassigned rows of ``indices`` are 0.
    """
    for label, value in (("u_axis", u_axis), ("v_axis", v_axis)):
        if value not in _AXES:
            raise ValueError(f"{label}={value!r}: expected one of {sorted(_AXES)}")
    if _AXES[u_axis][0] == _AXES[v_axis][0]:
        raise ValueError(f"u_axis={u_axis!r} and v_axis={v_axis!r} must name different axes")
    pts = np.asarray(centres_px, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    indices = np.zeros((n, 2), dtype=int)
    assigned = np.zeros(n, dtype=bool)
    if n < 5:
        return indices, assigned
    tree = cKDTree(pts)
    nn_dist, _ = tree.query(pts, k=2)
    pitch_px = float(np.median(nn_dist[:, 1]))

    # Seeds: dots near the centre of the detections, nearest first. A seed must see all four
    # lattice neighbours where its basis predicts them (so a stray blob cannot seed); the
    # growth from the first seed that reaches half of the blobs (else the best) is kept.
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    best = (indices, assigned)
    for seed in np.argsort(np.linalg.norm(pts - centre, axis=1))[:12]:
        basis = _seed_basis(tree, pts, int(seed), pitch_px, u_axis, v_axis, tolerance)
        if basis is None:
            continue
        result = _grow_lattice(tree, pts, int(seed), basis, tolerance)
        if result[1].sum() > best[1].sum():
            best = result
        if best[1].sum() >= 0.5 * n:
            break
    return best


def _seed_basis(tree, pts, seed, pitch_px, u_axis, v_axis, tolerance):
    """Lattice vectors (a: sensor +x, b: +y) at ``seed``, or None if it is not a lattice site."""
    d, j = tree.query(pts[seed], k=min(9, len(pts)))
    vecs = pts[j[1:]] - pts[seed]
    ok = (d[1:] > 0.6 * pitch_px) & (d[1:] < 1.5 * pitch_px)
    vecs = vecs[ok]
    if len(vecs) < 4:
        return None
    basis = []
    for sensor_axis in (0, 1):
        want = _axis_direction(u_axis, v_axis, sensor_axis)
        cos = vecs @ want / np.linalg.norm(vecs, axis=1)
        k = int(np.argmax(cos))
        if cos[k] < np.cos(np.deg2rad(40.0)):
            return None
        basis.append(vecs[k].copy())
    for vec in (basis[0], -basis[0], basis[1], -basis[1]):
        dist, _ = tree.query(pts[seed] + vec)
        if dist > tolerance * np.linalg.norm(vec):
            return None
    return basis


def _grow_lattice(tree, pts, seed, basis, tolerance):
    """Breadth-first assignment of lattice indices from ``seed`` (index (0, 0))."""
    n = len(pts)
    indices = np.zeros((n, 2), dtype=int)
    assigned = np.zeros(n, dtype=bool)
    local = {seed: (basis[0], basis[1])}
    assigned[seed] = True
    owner = {(0, 0): seed}
    queue = deque([seed])
    steps = ((0, +1), (0, -1), (1, +1), (1, -1))
    while queue:
        p = queue.popleft()
        a, b = local[p]
        for axis, sign in steps:
            step = sign * (a if axis == 0 else b)
            dist, q = tree.query(pts[p] + step)
            if dist > tolerance * np.linalg.norm(step) or assigned[q]:
                continue
            idx = indices[p].copy()
            idx[axis] += sign
            key = (int(idx[0]), int(idx[1]))
            if key in owner:  # two blobs claim one lattice site: keep the first
                continue
            actual = sign * (pts[q] - pts[p])
            local[q] = (actual, b) if axis == 0 else (a, actual)
            indices[q] = idx
            assigned[q] = True
            owner[key] = q
            queue.append(q)
    return indices, assigned


def dot_grid_positions_mm(indices: np.ndarray, pitch_mm: float,
                          grid_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Sensor-frame positions (N, 2) mm of lattice ``indices`` for a grid centred on the origin.

    grid_shape : (columns, rows) of the physical grid; when given, the detected index extent
        must match it (every edge dot seen), otherwise the origin would be ambiguous.
    """
    idx = np.asarray(indices)
    lo, hi = idx.min(axis=0), idx.max(axis=0)
    extent = hi - lo + 1
    if grid_shape is not None and (extent[0] != grid_shape[0] or extent[1] != grid_shape[1]):
        raise CalibrationError(
            f"the detected dots span {extent[0]} x {extent[1]} lattice positions but the grid "
            f"has {grid_shape[0]} x {grid_shape[1]}: some edge dots are missing or extra blobs "
            "joined the lattice, so the grid's centre is ambiguous; press the whole grid inside "
            "the view, or check --dot-grid"
        )
    mid = 0.5 * (lo + hi)
    return (idx - mid) * pitch_mm


def calibrate_dots(
    frames: Sequence[np.ndarray] | np.ndarray,
    reference: np.ndarray | None,
    pitch_mm: float,
    *,
    grid_shape: tuple[int, int] | None = None,
    u_axis: str = "+x",
    v_axis: str = "+y",
    focal_px: float | None = None,
    free_lens: tuple[str, ...] = ("cx", "cy", "k1", "k2", "p1", "p2"),
    blur_sigma_px: float = 2.5,
    grid: OutputGrid | None = None,
    name: str = "pressed frame",
) -> tuple[PlaneFit, DotDetections]:
    """Camera mapping from a pressed dot grid (one press; several frames of it are averaged).

    frames : one (H, W[, C]) frame or a sequence of frames of the same press, raw camera pixels.
    reference : the unpressed gel, same shape (None if ``frames`` are already subtracted).
    pitch_mm : lattice pitch, mm. grid_shape : (columns, rows), checked when given.
    Returns the fit and the detections.
    """
    if not pitch_mm > 0:
        raise ValueError(f"pitch_mm must be positive, got {pitch_mm}")
    if isinstance(frames, np.ndarray):
        frames = [frames]
    stack = [np.asarray(f) for f in frames]
    if not stack:
        raise CalibrationError("no pressed frames given")
    shape = stack[0].shape
    for i, f in enumerate(stack):
        if f.shape != shape:
            raise ValueError(f"{name} {i} has shape {f.shape}, the first has {shape}")
    frame = stack[0] if len(stack) == 1 else np.mean([f.astype(np.float32) for f in stack], axis=0)
    det = detect_dots(frame, reference, blur_sigma_px=blur_sigma_px, name=name)
    hint = ("check that the reference frame shows the unpressed gel and the other frames the "
            "pressed grid, that the press is deep enough to see, and try --blur-px near half a "
            "dot's radius in pixels")
    if len(det.centres_px) < MIN_DOTS:
        raise TargetNotFoundError(
            f"{name}: found {len(det.centres_px)} dots in the reference-subtracted frame, need at "
            f"least {MIN_DOTS}; {hint}"
        )
    idx, ok = assign_grid_indices(det.centres_px, u_axis=u_axis, v_axis=v_axis)
    if ok.sum() < MIN_DOTS:
        raise TargetNotFoundError(
            f"{name}: {len(det.centres_px)} blobs found but only {int(ok.sum())} form a square "
            f"lattice (need {MIN_DOTS}); {hint}; and that --u-axis/--v-axis ({u_axis}, {v_axis}) "
            "describe the camera's orientation to within 45 degrees"
        )
    xy = dot_grid_positions_mm(idx[ok], pitch_mm, grid_shape)
    image_size = (shape[1], shape[0])
    k = single_view_camera_matrix(image_size, focal_px)
    fit = fit_plane_mapping(
        det.centres_px[ok], xy, image_size, k, None, free_lens,
        method="dots-single-view", n_frames=len(stack), focal_assumed=True, grid=grid,
    )
    return fit, det
