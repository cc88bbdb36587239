"""Pose of an indenter over the pad, and the map from sensor frame to indenter frame.

Frames (mm): the **sensor frame** has its origin at the centre of the sensing (top) surface,
z up and out of the gel; the **indenter frame** has its origin at the indenter's reference point,
z up, and the lowest point of its pressing surface at z = 0.

A pose places the indenter origin at (x_mm, y_mm) in the sensor frame, rotated by theta_deg about
+z (counter-clockwise seen from above), with its lowest point depth_mm below the rest sensing
surface z = 0. A sensor-frame point p maps to the indenter-frame point
``q = R(-theta) (p - (x_mm, y_mm))``, and an indenter-frame point (q, z) maps to the sensor-frame
point ``(R(theta) q + (x_mm, y_mm), z - depth_mm)``.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class ContactPose(BaseModel):
    """Where and how deep an indenter presses (sensor frame, mm and degrees)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

    x_mm: float = Field(0.0, description="Indenter origin x in the sensor frame, mm.")
    y_mm: float = Field(0.0, description="Indenter origin y in the sensor frame, mm.")
    theta_deg: float = Field(
        0.0, description="Rotation of the indenter about +z, degrees, counter-clockwise from above."
    )
    depth_mm: float = Field(
        0.0,
        description="Depth of the pressing surface's lowest point below the rest sensing surface "
        "z = 0, mm (> 0 means pressed in).",
    )


def sensor_to_indenter_xy(points_xy_mm, pose: ContactPose) -> np.ndarray:
    """Map sensor-frame points to the indenter frame: ``q = R(-theta) (p - (x, y))``.

    points_xy_mm : (k, 2) float, mm, sensor frame.
    Returns (k, 2) float64, mm, indenter frame.
    """
    p = np.asarray(points_xy_mm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points_xy_mm must have shape (k, 2), got {p.shape}")
    c, s = math.cos(math.radians(pose.theta_deg)), math.sin(math.radians(pose.theta_deg))
    dx = p[:, 0] - pose.x_mm
    dy = p[:, 1] - pose.y_mm
    return np.stack([c * dx + s * dy, c * dy - s * dx], axis=1)


def indenter_to_sensor(points_mm, pose: ContactPose) -> np.ndarray:
    """Map indenter-frame points (k, 3) mm to the sensor frame (k, 3) float64 mm."""
    q = np.asarray(points_mm, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"points_mm must have shape (k, 3), got {q.shape}")
    m = pose_matrix(pose)
    return q @ m[:3, :3].T + m[:3, 3]


def pose_matrix(pose: ContactPose) -> np.ndarray:
    """(4, 4) float64 homogeneous transform from the indenter frame to the sensor frame."""
    c, s = math.cos(math.radians(pose.theta_deg)), math.sin(math.radians(pose.theta_deg))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = [pose.x_mm, pose.y_mm, -pose.depth_mm]
    return m
