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
   intensity-weighted centroid. Components touching the border are dropped. Then
   :func:`refine_to_apex` moves each centroid to its pin's apex: the LEDs light one flank of a
   dent more than the other and clip channels there, so the centroid of the change is off the
   pin (on the virtual GelSlim 2 by 1.5 px typically, up to 10 px near the image corners: 0.1
   mm on average and up to 0.3 mm of error in the fitted mapping). The apex is flat: there every
   channel is back at the reference's colour (darkened a little by the depth), and around it
   each channel changes linearly with position, in opposite directions on opposite flanks.
2. :func:`assign_grid_indices`: lattice indices by growing from a dot near the centre whose four
   neighbours are where its lattice vectors predict: each step predicts the neighbour at
   ``p +- a``, ``p +- b`` with ``a, b`` the local lattice vectors, updated from each accepted step,
   so the prediction follows the lens distortion. Blobs off the lattice stay unassigned; the dots
   beyond a missing one are reached around it. Orientation: the lattice vector closest to the
   image direction of sensor +x (from ``u_axis``/``v_axis``, the sensor axes that image right and
   down point along) is index +x. The index origin is the centre of the detected extent, checked
   against ``grid_shape`` when given.
3. :func:`tactile_deploy.calibration.camera.fitting.fit_plane_mapping` on one view: homography + principal point
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

from tactile_deploy.calibration.camera.charuco import TargetNotFoundError
from tactile_deploy.calibration.camera.fitting import (
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

    centres_px : (N, 2) float64, raw px (u, v): the pins' apexes (:func:`refine_to_apex`), the
        centroid where a blob is not a ring of change around an unchanged centre.
    areas_px : (N,) int, pixels above threshold per blob.
    strength : (H, W) float32, the smoothed change magnitude the blobs were cut from.
    threshold : float, the level used (same units as ``strength``).
    centroids_px : (N, 2) float64, raw px: the blobs' intensity-weighted centroids.
    at_apex : (N,) bool, whether ``centres_px`` is the refined apex (else the centroid).
    """

    centres_px: np.ndarray
    areas_px: np.ndarray
    strength: np.ndarray
    threshold: float
    centroids_px: np.ndarray | None = None
    at_apex: np.ndarray | None = None


def detect_dots(frame: np.ndarray, reference: np.ndarray | None = None, *,
                blur_sigma_px: float = 2.5, min_area_px: int = 8, refine: bool = True,
                name: str = "frame") -> DotDetections:
    """Centres of the pressed dots.

    frame : (H, W) or (H, W, C) raw camera frame (any numeric dtype) with the grid pressed, or an
        already reference-subtracted frame when ``reference`` is None.
    reference : same shape, the unpressed gel.
    blur_sigma_px : smoothing before thresholding, px; about half a dot's radius in the image.
    refine : move the centroids to the pins' apexes (:func:`refine_to_apex`; needs a colour
        frame and at least two dots); False keeps the centroids.
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
    centroids = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    apexes, at_apex = centroids, np.zeros(len(centroids), bool)
    if refine and f.ndim == 3 and len(centroids) >= 2:
        raw = np.asarray(frame, np.float32) if reference is not None else None
        apexes, at_apex = refine_to_apex(f, centroids, raw_frame=raw,
                                         raw_reference=None if reference is None else r)
    return DotDetections(
        centres_px=apexes,
        areas_px=np.asarray(areas, dtype=int),
        strength=s,
        threshold=threshold,
        centroids_px=centroids,
        at_apex=at_apex,
    )


#: Expected radius of a pin's contact disc as a fraction of the lattice pitch (0.75 mm pins
#: pressed 0.35 mm on a 2.5 mm pitch: 0.63 mm = 0.25 pitch).
DOT_RADIUS_PER_PITCH = 0.25
#: Raw grey levels at or beyond which a channel counts as clipped (dark or saturated).
CLIP_LOW, CLIP_HIGH = 3.0, 252.0


def refine_to_apex(diff: np.ndarray, centres_px: np.ndarray, *, raw_frame: np.ndarray | None = None,
                   raw_reference: np.ndarray | None = None, fit_fraction: float = 0.3,
                   iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Move blob centres to the apexes of the pins that made them.

    diff : (H, W, C) float32, frame minus reference (grey levels). centres_px : (N, 2) raw px,
    first estimates (the blobs' centroids; N >= 2: the lattice pitch is the distance to the
    nearest other blob). raw_frame, raw_reference : (H, W, C) the frames themselves, to leave
    out channels clipped at either end (None: every channel is used).

    Each pin's disc of contact (radius ``DOT_RADIUS_PER_PITCH`` x the local pitch, r) changes the
    colours in a ring around an unchanged apex. Start: within 0.8 r of the centroid, the pixel
    whose smoothed change magnitude is lowest against the mean on a circle of 0.6 r around it.
    Then, ``iterations`` times: within ``fit_fraction`` x r, a plane per unclipped channel,
    ``diff_c = a_c + b_c . (p - c)``, and the point where every channel equals its reference
    darkened by a common factor k, ``a_c + b_c . dp = -k ref_c`` (least squares in dp and k,
    k = 0 with fewer than three channels). Returns ``(centres (N, 2) px, at_apex (N,) bool)``;
    a blob whose ring is not at least twice as changed as its centre, or whose iterations leave
    the disc, keeps its first estimate (at_apex False).
    """
    d = np.asarray(diff, np.float32)
    centres = np.asarray(centres_px, np.float64).reshape(-1, 2)
    out, at_apex = centres.copy(), np.zeros(len(centres), bool)
    if len(centres) < 2 or d.ndim != 3:
        return out, at_apex
    n_ch = d.shape[2]
    smooth = np.stack([cv2.GaussianBlur(d[..., c], (0, 0), 1.0) for c in range(n_ch)], -1)
    mag = np.linalg.norm(np.stack([cv2.GaussianBlur(d[..., c], (0, 0), 1.5)
                                   for c in range(n_ch)], -1), axis=-1)
    usable = np.ones(d.shape, bool)
    for img in (raw_frame, raw_reference):
        if img is not None:
            usable &= (img > CLIP_LOW) & (img < CLIP_HIGH)
    ref = (np.asarray(raw_reference, np.float32) if raw_reference is not None
           else np.zeros(d.shape, np.float32))
    pitch = cKDTree(centres).query(centres, 2)[0][:, 1]
    radius = DOT_RADIUS_PER_PITCH * pitch
    # ring contrast: mean change magnitude on a circle of 0.6 r minus the change at the pixel
    ring_r = 0.6 * float(np.median(radius))
    k = int(np.ceil(ring_r)) + 1
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
    ring = (np.abs(np.hypot(xx, yy) - ring_r) < 0.5).astype(np.float32)
    contrast = cv2.filter2D(mag, -1, ring / ring.sum(), borderType=cv2.BORDER_REPLICATE) - mag
    for i, (c0, r) in enumerate(zip(centres, radius)):
        start = _ring_centre(contrast, mag, c0, 0.8 * r)
        if start is None:
            continue
        c = _apex_iterations(smooth, usable, ref, start, fit_fraction * r, iterations)
        if c is not None and np.hypot(*(c - start)) <= 0.5 * r:
            out[i], at_apex[i] = c, True
    return out, at_apex


def _ring_centre(contrast, mag, c0, reach):
    """The pixel within ``reach`` of ``c0`` with the highest ring contrast, or None when its
    ring is not at least twice as changed as the pixel itself."""
    h, w = mag.shape
    u0, v0 = int(round(c0[0])), int(round(c0[1]))
    k = int(np.ceil(reach))
    v_lo, v_hi, u_lo, u_hi = max(v0 - k, 0), min(v0 + k + 1, h), max(u0 - k, 0), min(u0 + k + 1, w)
    if v_lo >= v_hi or u_lo >= u_hi:
        return None
    vv, uu = np.mgrid[v_lo:v_hi, u_lo:u_hi]
    win = np.where(np.hypot(uu - c0[0], vv - c0[1]) <= reach, contrast[v_lo:v_hi, u_lo:u_hi],
                   -np.inf)
    j = np.unravel_index(int(np.argmax(win)), win.shape)
    v, u = v_lo + j[0], u_lo + j[1]
    if not contrast[v, u] >= mag[v, u]:          # ring mean >= 2 x the centre's change
        return None
    return np.array([u, v], np.float64)


def _apex_iterations(smooth, usable, ref, start, fit_radius, iterations):
    """Newton-like steps to where the channels' planes meet (see :func:`refine_to_apex`);
    None when fewer than two channels are usable or a step leaves the image."""
    h, w, n_ch = smooth.shape
    c = np.array(start, np.float64)
    rho = max(float(fit_radius), 2.0)
    k = int(np.ceil(rho)) + 1
    for _ in range(iterations):
        u0, v0 = int(round(c[0])), int(round(c[1]))
        vv, uu = np.mgrid[v0 - k:v0 + k + 1, u0 - k:u0 + k + 1]
        inside = ((np.hypot(uu - c[0], vv - c[1]) <= rho) & (uu >= 0) & (vv >= 0)
                  & (uu < w) & (vv < h))
        uu, vv = uu[inside], vv[inside]
        if len(uu) < 6:
            return None
        rows, rhs = [], []
        for ch in range(n_ch):
            ok = usable[vv, uu, ch]
            if ok.sum() < 0.6 * len(ok):
                continue
            a = np.stack([np.ones(int(ok.sum())), uu[ok] - c[0], vv[ok] - c[1]], 1)
            coef = np.linalg.lstsq(a, smooth[vv[ok], uu[ok], ch], rcond=None)[0]
            rows.append([coef[1], coef[2], ref[v0, u0, ch]])
            rhs.append(-coef[0])
        if len(rows) < 2:
            return None
        m, b = np.asarray(rows), np.asarray(rhs)
        if len(rows) < 3 or not np.any(m[:, 2]):
            m = m[:, :2]
        step = np.linalg.lstsq(m, b, rcond=None)[0][:2]
        if not np.all(np.isfinite(step)):
            return None
        c = c + step
        if not (0 <= c[0] < w and 0 <= c[1] < h):
            return None
        if np.hypot(*step) < 0.01:
            break
    return c


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
    refine: bool = True,
    grid: OutputGrid | None = None,
    name: str = "pressed frame",
) -> tuple[PlaneFit, DotDetections]:
    """Camera mapping from a pressed dot grid (one press; several frames of it are averaged).

    frames : one (H, W[, C]) frame or a sequence of frames of the same press, raw camera pixels.
    reference : the unpressed gel, same shape (None if ``frames`` are already subtracted).
    pitch_mm : lattice pitch, mm. grid_shape : (columns, rows), checked when given.
    refine : fit the pins' apexes (:func:`refine_to_apex`, the default) rather than the blobs'
    centroids. Returns the fit and the detections.
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
    det = detect_dots(frame, reference, blur_sigma_px=blur_sigma_px, refine=refine, name=name)
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
