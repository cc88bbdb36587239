"""Tilt: the gel surface is tilted against the indenter's axis of motion (mechanical, contact).

Physics. A sensor mounted with its sensing surface tilted by ``angle_deg`` against the plane
perpendicular to the rig's (or robot's) pressing axis, the surface descending along the in-plane
direction ``azimuth_deg`` (sensor frame, counter-clockwise from +x). To first order in the angle
the indenter meets a surface that recedes by ``tan(angle) * s`` at in-plane distance s (along the
azimuth) from the indenter's origin, where the commanded depth is reached: the intrusion at every
point becomes ``delta - tan(angle) * ((p - c) . e)``. The FEM solves the contact with that
intrusion (exact active set on the surface compliance), and the optics see the resulting shape.

Signature: against the nominal sensor, a flat-faced indenter leaves a depth residual that is a
plane across the contact with slope ``-tan(angle)`` along the azimuth (one side pressed less,
the other more); null value ``angle_deg = 0`` reproduces the nominal sensor exactly.

Residual it leaves: second-order terms (the indenter's foreshortening by cos(angle), the sideways
travel ``depth * tan(angle)`` of a tilted approach, shear from the oblique load).

Realistic range: 0-2 degrees (mounting tolerance of a finger on a gripper or a sensor on a rig).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class TiltParams(EffectParams):
    angle_deg: float = Field(0.0, ge=0.0, le=10.0, description="Tilt of the sensing surface "
                             "against the pressing axis, degrees; 0 = none (null).")
    azimuth_deg: float = Field(0.0, ge=-360.0, le=360.0, description="In-plane direction in "
                               "which the surface recedes, degrees counter-clockwise from "
                               "sensor +x.")


class Tilt(Effect):
    __doc__ = __doc__
    name = "tilt"
    kind = "mechanical"
    stage = "contact"
    Params = TiltParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"angle_deg": (0.0, 2.0)}

    def intrusion_mm(self, delta_mm, xy_mm, pose):
        p = self.params
        if p.angle_deg == 0.0:
            return delta_mm
        slope = math.tan(math.radians(p.angle_deg))
        ex, ey = math.cos(math.radians(p.azimuth_deg)), math.sin(math.radians(p.azimuth_deg))
        xy = np.asarray(xy_mm, np.float64)
        s = (xy[:, 0] - pose.x_mm) * ex + (xy[:, 1] - pose.y_mm) * ey
        return delta_mm - slope * s
