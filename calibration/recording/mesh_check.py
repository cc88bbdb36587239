"""Is the mesh's sensing surface the ball? Sphere fits to the displaced sensing nodes of a press.

For a press of a ball of known radius R with its contact circle (a camera-frame circle, through
the plugin's camera mapping into the sensor frame, mm), take the displaced sensing nodes that
lie within ``region`` (0.8) contact radii of the circle's centre (where the ball is: the gel
slides along a frictionless ball, so the nodes inside the contact now are not those that were
there at rest), and fit

* a sphere of radius R, centre free: the RMS distance of the nodes from it is the **shape
  error** (um);
* a sphere with the radius free too: its radius against R is the **radius error**.

This is the mesh-level counterpart of :mod:`tactile_deploy.calibration.shading.evaluate` (which fits the depth
map) and needs nothing but the mesh, the circle and the mapping: an independent check of
calibration + depth + physics lift on real presses, whose true surface inside the contact is the
ball. Units: mm, um for RMS; sensor frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares


@dataclass(frozen=True)
class MeshSphereFit:
    """Sphere fits of one press's displaced sensing nodes (module docstring)."""

    name: str
    n_nodes: int
    shape_um: float          # RMS distance from the sphere of the known radius
    radius_mm: float         # radius of the free sphere
    radius_error: float      # radius_mm / R - 1
    centre_mm: tuple[float, float]
    contact_radius_mm: float


def fit_sphere_points(points: np.ndarray, radius_mm: float | None = None):
    """Least-squares sphere through 3-D points (k, 3) mm lying on its lower cap: returns
    ``(centre (3,), radius, rms (mm))``; ``radius_mm`` fixes the radius."""
    p = np.asarray(points, np.float64)
    lowest = p[np.argmin(p[:, 2])]
    r0 = radius_mm if radius_mm is not None else 2.0 * np.ptp(p[:, 0]) + 1e-3
    x0 = [lowest[0], lowest[1], lowest[2] + r0] + ([] if radius_mm is not None else [r0])

    def fun(q):
        r = radius_mm if radius_mm is not None else q[3]
        return np.linalg.norm(p - q[:3], axis=1) - r

    sol = least_squares(fun, x0, x_scale="jac")
    r = radius_mm if radius_mm is not None else float(sol.x[3])
    return sol.x[:3], float(r), float(np.sqrt(np.mean(sol.fun ** 2)))


def press_mesh_fit(name: str, vertices_mm: np.ndarray, rest_vertices_mm: np.ndarray,
                   sensing_nodes: np.ndarray, centre_mm, contact_radius_mm: float,
                   ball_radius_mm: float, region: float = 0.8) -> MeshSphereFit:
    """The two sphere fits of one press (module docstring)."""
    rest = np.asarray(rest_vertices_mm, np.float64)[sensing_nodes]
    moved = np.asarray(vertices_mm, np.float64)[sensing_nodes]
    d = np.hypot(moved[:, 0] - centre_mm[0], moved[:, 1] - centre_mm[1])
    sel = d < region * contact_radius_mm
    if sel.sum() < 8:
        raise ValueError(f"press {name}: only {int(sel.sum())} sensing nodes within "
                         f"{region} contact radii ({contact_radius_mm:.2f} mm) of "
                         f"({centre_mm[0]:.2f}, {centre_mm[1]:.2f}) mm")
    pts = moved[sel]
    _, _, rms = fit_sphere_points(pts, ball_radius_mm)
    c, r, _ = fit_sphere_points(pts, None)
    return MeshSphereFit(name, int(sel.sum()), 1e3 * rms, r, r / ball_radius_mm - 1.0,
                         (float(c[0]), float(c[1])), float(contact_radius_mm))


def circles_to_sensor_mm(circles_px: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame circles (column, row, radius px) -> centres (k, 2) mm and radii (k,) mm,
    sensor frame, through a :class:`~tactile_deploy.imaging.camera_mapping.CameraMapping`."""
    from tactile_deploy.imaging.camera_mapping import pixels_to_sensor_mm

    c = np.asarray(circles_px, np.float64)
    centres = pixels_to_sensor_mm(c[:, :2], camera)
    edge = pixels_to_sensor_mm(c[:, :2] + np.c_[c[:, 2], np.zeros(len(c))], camera)
    return centres, np.linalg.norm(edge - centres, axis=1)
