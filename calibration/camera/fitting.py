"""Least-squares fit of lens distortion + homography to one view of a planar target.

Model (see :mod:`tactile_deploy.imaging.camera_mapping`): a target point at sensor-plane
``(x, y)`` mm is seen at raw pixel ``distort(G [x, y, 1])`` where ``G = H^-1`` maps the plane to
undistorted pixels and ``distort`` is OpenCV's lens model with camera matrix ``K``. Unknowns: the 8
degrees of freedom of ``G`` and the lens parameters named in ``free_lens`` (by default the
principal point cx, cy and k1, k2, p1, p2); fx, fy and the rest are held. Cost: squared
reprojection error in raw pixels, minimised with Levenberg-Marquardt from the distortion-free
homography, then points off by more than 5 times the median error are dropped and the fit redone.

What one view determines
------------------------
* The raw-pixel -> plane mapping: fully (to the detection noise), inside the area the target
  covers; outside it the lens model extrapolates.
* The focal length: not at all for a square-on view. It is a gauge: rescaling ``fx = fy`` by
  ``s`` and each coefficient of degree ``n`` in ``r`` by ``s^n`` (k1 by s^2, k2 by s^4, p1, p2 by
  s) gives the same distortion field in pixels. So fx = fy is assumed (``focal_px``) and only the
  field, not the coefficients alone, is meaningful.
* The principal point (the distortion centre): weakly, through the shape of the distortion; it
  trades off against p1, p2 and the homography's perspective terms, which leaves the mapping
  unchanged. Holding it at the image centre instead costs about 1 px at the corners for a lens
  with k2 = 0.1 and a 15 px offset (the r^4 term cannot be re-centred), so it is fitted.
* The split between the lens and the homography: only up to a homography. Compare fields
  modulo a homography, or compare the composite mapping.

Several views at different tilts (``cv2.calibrateCamera``, :mod:`tactile_deploy.calibration.camera.charuco`)
determine fx, fy, cx, cy and the coefficients themselves.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from tactile_deploy.imaging.camera_mapping import (
    CameraMapping,
    FitSummary,
    OutputGrid,
    camera_mapping_from_parameters,
    distort_normalized,
    grid_coverage,
    pixels_to_sensor_mm,
    sensor_mm_to_pixels,
)

#: Names of the OpenCV distortion coefficients, in OpenCV order.
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")
#: Lens parameters a single-view fit may free: the principal point and the distortion.
LENS_NAMES = ("cx", "cy") + DISTORTION_NAMES


class CalibrationError(ValueError):
    """A calibration could not be made from the given frames (the message says what to try)."""


@dataclass(frozen=True)
class PlaneFit:
    """Result of a camera-mapping calibration.

    mapping : the estimated mapping (with its :class:`FitSummary`).
    uv_px : (N, 2) float64, raw px: target points detected in the sensor-plane frame (inliers).
    xy_mm : (N, 2) float64, mm, sensor frame: their known positions.
    residual_px : (N, 2) float64, px: reprojection ``sensor_mm_to_pixels(xy_mm) - uv_px``.
    residual_mm : (N, 2) float64, mm: ``pixels_to_sensor_mm(uv_px) - xy_mm``.
    rejected_uv_px : (M, 2) float64, raw px: detections dropped as outliers.
    """

    mapping: CameraMapping
    uv_px: np.ndarray
    xy_mm: np.ndarray
    residual_px: np.ndarray
    residual_mm: np.ndarray
    rejected_uv_px: np.ndarray


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Similarity (3, 3) taking ``pts`` to zero mean and unit RMS radius."""
    mean = pts.mean(axis=0)
    scale = 1.0 / max(float(np.sqrt(np.mean(np.sum((pts - mean) ** 2, axis=1)))), 1e-12)
    return np.array([[scale, 0.0, -scale * mean[0]], [0.0, scale, -scale * mean[1]], [0, 0, 1.0]])


def _project(g: np.ndarray, xy: np.ndarray, k: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Plane mm -> raw px through homography ``g`` (mm -> undistorted px) and the lens."""
    q = xy @ g[:, :2].T + g[:, 2]
    u = q[:, 0] / q[:, 2]
    v = q[:, 1] / q[:, 2]
    xd, yd, _ = distort_normalized((u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], dist)
    return np.stack([xd * k[0, 0] + k[0, 2], yd * k[1, 1] + k[1, 2]], axis=1)


def _fit_once(uv, xy, lens0, free_idx, focal, g0):
    """One Levenberg-Marquardt fit. lens0: (cx, cy, k1, k2, p1, p2, k3); focal: (fx, fy)."""
    t_px = _normaliser(uv)
    t_mm = _normaliser(xy)
    t_px_inv = np.linalg.inv(t_px)
    g_n = t_px @ g0 @ np.linalg.inv(t_mm)
    g_n = g_n / g_n[2, 2]
    x0 = np.concatenate([g_n.ravel()[:8], lens0[free_idx]])

    def unpack(p):
        g = t_px_inv @ np.append(p[:8], 1.0).reshape(3, 3) @ t_mm
        lens = lens0.copy()
        lens[free_idx] = p[8:]
        k = np.array([[focal[0], 0.0, lens[0]], [0.0, focal[1], lens[1]], [0.0, 0.0, 1.0]])
        return g, k, lens[2:]

    def residual(p):
        g, k, d = unpack(p)
        return (_project(g, xy, k, d) - uv).ravel()

    sol = least_squares(residual, x0, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12)
    return unpack(sol.x)


def fit_plane_mapping(
    uv_px,
    xy_mm,
    image_size: tuple[int, int],
    camera_matrix,
    dist_init=None,
    free_lens: tuple[str, ...] = ("cx", "cy", "k1", "k2", "p1", "p2"),
    *,
    fitted_lens: tuple[str, ...] | None = None,
    method: str,
    n_frames: int = 1,
    focal_assumed: bool = True,
    grid: OutputGrid | None = None,
    reject_factor: float = 5.0,
    min_reject_px: float = 0.5,
) -> PlaneFit:
    """Fit the homography (and the free lens parameters) to one view of a planar target.

    uv_px : (N, 2) float, raw px: detected target points.
    xy_mm : (N, 2) float, mm, sensor frame: the same points' known positions on the plane.
    image_size : (width, height) px. camera_matrix : (3, 3) px, held fixed.
    dist_init : (5,) k1 k2 p1 p2 k3 start values (zeros when None).
    free_lens : lens parameters fitted with the homography, of ``LENS_NAMES`` (cx cy k1 k2 p1 p2
        k3); the others keep their start values (``camera_matrix``, ``dist_init``).
    fitted_lens : what to record as estimated (default ``free_lens``; the multi-view path records
        the intrinsics that ``cv2.calibrateCamera`` estimated).
    method, n_frames, focal_assumed : recorded in the mapping's :class:`FitSummary`.
    reject_factor, min_reject_px : after each fit, points whose reprojection error exceeds
        ``max(reject_factor * median error, min_reject_px)`` are dropped and the fit repeated.
    """
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
    if len(uv) != len(xy):
        raise ValueError(f"uv_px has {len(uv)} points but xy_mm has {len(xy)}")
    unknown = set(free_lens) - set(LENS_NAMES)
    if unknown:
        raise ValueError(f"free_lens: unknown parameters {sorted(unknown)}; "
                         f"choose from {LENS_NAMES}")
    free_idx = np.array([LENS_NAMES.index(n) for n in free_lens], dtype=int)
    n_needed = max(6, 8 + len(free_idx))
    if len(uv) < n_needed:
        raise CalibrationError(
            f"only {len(uv)} target points were found; fitting the homography and "
            f"{len(free_idx)} distortion coefficients needs at least {n_needed}: use a target "
            "that covers more of the image"
        )
    k = np.asarray(camera_matrix, dtype=np.float64)
    dist0 = np.zeros(5) if dist_init is None else np.asarray(dist_init, dtype=np.float64).ravel()
    dist0 = np.concatenate([dist0[:5], np.zeros(max(0, 5 - dist0.size))])

    keep = np.ones(len(uv), dtype=bool)
    g0, _ = cv2.findHomography(xy, uv, 0)
    if g0 is None:
        raise CalibrationError("the target points are degenerate (collinear?): no homography")
    lens0 = np.concatenate([[k[0, 2], k[1, 2]], dist0])
    focal = (k[0, 0], k[1, 1])
    for _ in range(4):
        g, k, dist = _fit_once(uv[keep], xy[keep], lens0, free_idx, focal, g0)
        err = np.linalg.norm(_project(g, xy, k, dist) - uv, axis=1)
        threshold = max(reject_factor * float(np.median(err[keep])), min_reject_px)
        new_keep = err <= threshold
        if np.array_equal(new_keep, keep):
            break
        if new_keep.sum() < n_needed:
            raise CalibrationError(
                f"{int((~new_keep).sum())} of {len(uv)} target points disagree with the fit by "
                f"more than {threshold:.2f} px; the detections are unreliable (check focus, "
                "lighting and the target description)"
            )
        keep = new_keep
        g0 = g

    try:
        provisional = camera_mapping_from_parameters(image_size, k, dist, np.linalg.inv(g),
                                                     grid=grid)
    except ValueError as e:
        raise CalibrationError(
            f"the fitted mapping is unusable ({e}); the target points cover too little of the "
            f"image for the lens model with {', '.join(free_lens) or 'no free terms'}: "
            "use a target that reaches the image corners, or free fewer coefficients"
        ) from None
    res_px = sensor_mm_to_pixels(xy[keep], provisional) - uv[keep]
    res_mm = pixels_to_sensor_mm(uv[keep], provisional) - xy[keep]
    summary = FitSummary(
        method=method,
        n_frames=n_frames,
        n_points=int(keep.sum()),
        n_rejected=int((~keep).sum()),
        rms_px=float(np.sqrt(np.mean(np.sum(res_px**2, axis=1)))),
        max_px=float(np.max(np.linalg.norm(res_px, axis=1))),
        rms_mm=float(np.sqrt(np.mean(np.sum(res_mm**2, axis=1)))),
        fitted_lens=tuple(fitted_lens) if fitted_lens is not None else tuple(free_lens),
        focal_assumed=focal_assumed,
        grid_coverage=grid_coverage(provisional),
    )
    mapping = provisional.model_copy(update={"fit": summary})
    return PlaneFit(
        mapping=mapping,
        uv_px=uv[keep],
        xy_mm=xy[keep],
        residual_px=res_px,
        residual_mm=res_mm,
        rejected_uv_px=uv[~keep],
    )


def single_view_camera_matrix(image_size: tuple[int, int], focal_px: float | None) -> np.ndarray:
    """Start camera matrix of a single-view fit: fx = fy = ``focal_px``, principal point at the
    image centre (the fit moves the principal point, not the focal length).

    focal_px : assumed focal length, px; ``max(width, height)`` when None (about a 53 degree
        field of view across the longer side). It only sets the scale of the coefficients.
    """
    width, height = image_size
    f = float(max(width, height) if focal_px is None else focal_px)
    if not f > 0:
        raise ValueError(f"focal_px must be positive, got {focal_px}")
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
