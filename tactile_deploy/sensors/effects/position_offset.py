"""Position offset: the indenter lands beside the commanded point (mechanical, contact stage).

Physics. The rig's (or robot's) origin is registered to the sensor's centre only to within a
fraction of a millimetre (by eye, with a touch probe, from a CAD mount): every commanded contact
point ``(x_mm, y_mm)`` is reached at ``(x_mm + dx_mm, y_mm + dy_mm)`` (sensor frame). The FEM
solves the contact where the indenter really is.

Signature: the depth residual against the nominal sensor is the contact map's derivative along
the offset, ``-(dx, dy) . grad(depth)``: a dipole across every contact with the same direction and
size anywhere on the pad and for every indenter (a tilt gives a sphere of radius R the same
dipole as an offset of ``R tan(angle)``, so spheres of one radius alone do not tell the two
apart: a flat punch or spheres of other radii do). Null value ``dx_mm = dy_mm = 0`` reproduces
the nominal sensor exactly.

Residual it leaves: an offset that changes over the workspace (a scale or rotation error of the
rig's axes) and one that changes with the pressing depth (an axis not perpendicular to the pad:
see the tilt).

Realistic range: -0.3 to 0.3 mm per axis (registration by touch probe 0.05-0.1 mm, by eye or from
a CAD mount 0.2-0.3 mm).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class PositionOffsetParams(EffectParams):
    dx_mm: float = Field(0.0, ge=-3.0, le=3.0, description="Offset of the reached contact point "
                         "along sensor +x, mm; 0 = none (null).")
    dy_mm: float = Field(0.0, ge=-3.0, le=3.0, description="Offset along sensor +y, mm.")


class PositionOffset(Effect):
    __doc__ = __doc__
    name = "position_offset"
    kind = "mechanical"
    stage = "contact"
    Params = PositionOffsetParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"dx_mm": (-0.3, 0.3),
                                                                 "dy_mm": (-0.3, 0.3)}

    def contact_pose(self, pose):
        p = self.params
        if p.dx_mm == 0.0 and p.dy_mm == 0.0:
            return pose
        return pose.model_copy(update={"x_mm": pose.x_mm + p.dx_mm, "y_mm": pose.y_mm + p.dy_mm})
