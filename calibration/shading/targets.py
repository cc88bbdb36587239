"""True surface of a ball press: the sphere of the ball's radius inside the contact circle.

Inside the contact the gel takes the ball's shape, so its depth follows the sphere of the
**ball's** radius R, whatever the contact radius a (fitting a sphere of radius a, as some public
tools do, gets every gradient wrong). Outside the contact the gel sinks around the ball (the
contact circle is not where the depth is zero); those pixels have no known target.

Image axes: column ``c`` and row ``r`` in pixels; the returned gradients are derivatives of depth
(mm, positive into the gel) per mm along image columns and rows (dimensionless).
"""

from __future__ import annotations

import numpy as np


def sphere_gradients(shape: tuple[int, int], centre_px, ball_radius_px: float,
                     max_radius_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of a ball's depth along image columns and rows, (H, W) float32 each.

    depth(c, r) = d0 + sqrt(R^2 - rho^2) - R with rho the distance from ``centre_px`` (column,
    row), so d depth / d c = -(c - c0) / sqrt(R^2 - rho^2). Pixels beyond ``max_radius_px``
    (default 0.99 R) get the value at that radius along their direction, so the field stays
    finite; mask them out as needed.
    """
    h, w = shape
    rmax = 0.99 * ball_radius_px if max_radius_px is None else float(max_radius_px)
    if not 0 < rmax < ball_radius_px:
        raise ValueError(f"max_radius_px must lie in (0, {ball_radius_px}), got {rmax}")
    dc = np.arange(w, dtype=np.float64)[None, :] - float(centre_px[0])
    dr = np.arange(h, dtype=np.float64)[:, None] - float(centre_px[1])
    rho = np.hypot(dc, dr)
    scale = np.where(rho > rmax, rmax / np.maximum(rho, 1e-12), 1.0)
    dc = dc * scale
    dr = dr * scale
    q = np.sqrt(ball_radius_px ** 2 - (dc ** 2 + dr ** 2))
    return (-dc / q).astype(np.float32), (-dr / q).astype(np.float32)


def sphere_gradients_at(cols, rows, centre_px, ball_radius_px: float) -> np.ndarray:
    """Sphere gradients (N, 2) at pixel positions (N,) inside the ball's footprint."""
    dc = np.asarray(cols, np.float64) - float(centre_px[0])
    dr = np.asarray(rows, np.float64) - float(centre_px[1])
    q2 = ball_radius_px ** 2 - dc ** 2 - dr ** 2
    if np.any(q2 <= 0):
        raise ValueError("positions outside the ball's footprint (distance >= ball radius)")
    q = np.sqrt(q2)
    return np.stack([-dc / q, -dr / q], -1)


def sphere_cap_depth_mm(shape: tuple[int, int], centre_px, contact_radius_px: float,
                        ball_radius_mm: float, mm_per_px: float) -> np.ndarray:
    """Depth (H, W) float64, mm, of a ball pressed until its contact radius is ``contact_radius``.

    The gel is taken as flat outside the contact (no sinking around the ball): a rigid sphere
    cap of depth R - sqrt(R^2 - a^2) at the centre. Used for synthetic presses of known depth.
    """
    h, w = shape
    a_mm = contact_radius_px * mm_per_px
    if not 0 < a_mm < ball_radius_mm:
        raise ValueError(f"contact radius {a_mm:.4f} mm must lie in (0, ball radius "
                         f"{ball_radius_mm} mm)")
    dc = (np.arange(w)[None, :] - float(centre_px[0])) * mm_per_px
    dr = (np.arange(h)[:, None] - float(centre_px[1])) * mm_per_px
    rho2 = dc ** 2 + dr ** 2
    base = np.sqrt(ball_radius_mm ** 2 - a_mm ** 2)
    return np.maximum(np.sqrt(np.maximum(ball_radius_mm ** 2 - rho2, 0.0)) - base, 0.0)
