"""The surface of a ball press (sensor frame, mm): the ball's sphere cap inside the contact circle
and the gel's sinking around it, scaled from an elastic half-space (Hertz)."""

from __future__ import annotations

import math

import numpy as np

from tactile_deploy.calibration.optics_fit.parameters import OpticsFitError


def hertz_exterior_shape(r_mm: np.ndarray, a_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Shape of the Hertz (half-space) surface outside a contact of radius a, normalised to 1
    at the rim, and its radial derivative (1/mm): ``phi(r) = u(r) / u(a)`` with
    ``u(r) = (2 a^2 - r^2) asin(a / r) + a sqrt(r^2 - a^2)`` (Johnson, Contact Mechanics, 3.42).
    Valid for r >= a."""
    r = np.maximum(np.asarray(r_mm, np.float64), a_mm)
    root = np.sqrt(np.maximum(r * r - a_mm * a_mm, 0.0))
    asn = np.arcsin(np.clip(a_mm / r, -1.0, 1.0))
    u = (2 * a_mm**2 - r * r) * asn + a_mm * root
    du = -2.0 * r * asn + 2.0 * a_mm * root / r
    ua = 0.5 * math.pi * a_mm**2
    return u / ua, du / ua

def sphere_press_surface(xy_mm: np.ndarray, centre_mm, a_mm: float, ball_radius_mm: float,
                         sinking_scale: float):
    """Surface of a gel pressed by a ball whose contact circle has radius ``a_mm``.

    Inside the circle the gel follows the ball (sphere cap); outside it sinks like the exterior
    of a Hertz contact, with the sinking at the rim ``w_a = sinking_scale * a^2 / (2 R)``
    (``sinking_scale = 1``: elastic half-space, C1 at the rim; 0: no sinking). Tip depth
    ``d = R - sqrt(R^2 - a^2) + w_a``.

    xy_mm : (k, 2) sensor frame. Returns ``(z, dz/dx, dz/dy)``, each (k,) float64 (mm, -, -),
    z = 0 far away, negative pushed in.
    """
    big = float(ball_radius_mm)
    if not 0 < a_mm < big:
        raise OpticsFitError(f"contact radius a_mm={a_mm} must lie in (0, {big}) (ball radius)")
    d = np.asarray(xy_mm, np.float64) - np.asarray(centre_mm, np.float64)
    r = np.hypot(d[:, 0], d[:, 1])
    w_a = sinking_scale * a_mm**2 / (2.0 * big)
    cap_a = big - math.sqrt(big**2 - a_mm**2)
    depth = cap_a + w_a
    inside = r <= a_mm
    rin = np.minimum(r, a_mm)
    root = np.sqrt(big**2 - rin * rin)
    phi, dphi = hertz_exterior_shape(r, a_mm)
    z = np.where(inside, -(depth - (big - root)), -w_a * phi)
    dz_dr = np.where(inside, rin / root, -w_a * dphi)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(r > 0, d[:, 0] / r, 0.0)
        uy = np.where(r > 0, d[:, 1] / r, 0.0)
    return z, dz_dr * ux, dz_dr * uy
