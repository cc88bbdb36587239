"""Depth scale: the pressing axis travels a different distance than commanded (mechanical,
contact stage).

Physics. A stage whose steps per millimetre are off (lead-screw pitch, microstepping, a belt or
gear ratio), or a robot whose kinematic calibration is off along the pressing axis, reaches the
depth ``depth_mm * (1 + scale)`` for a commanded depth ``depth_mm`` counted from the touch-off.
The FEM solves the contact at the depth reached.

Signature: the depth residual against the nominal sensor grows in proportion to the commanded
depth (a zero offset is the same at every depth; large-strain stiffening grows about with its
square); at every depth the peak moves by ``scale * depth_mm``; the force follows the force-depth
curve at the scaled depth. Null value ``scale = 0`` reproduces the nominal sensor exactly.

Residual it leaves: an axis error that varies along the travel (backlash, a periodic lead-screw
error) and one that differs between approach directions.

Realistic range: -0.05 to 0.05 (lead screws and microstepping 0.5-3 %; a robot arm without a
calibrated tool axis up to 5 %).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class DepthScaleParams(EffectParams):
    scale: float = Field(0.0, ge=-0.5, le=0.5, description="Relative error of the travel along "
                         "the pressing axis, dimensionless: the indenter reaches depth * (1 + "
                         "scale); 0 = none (null).")


class DepthScale(Effect):
    __doc__ = __doc__
    name = "depth_scale"
    kind = "mechanical"
    stage = "contact"
    Params = DepthScaleParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"scale": (-0.05, 0.05)}

    def contact_pose(self, pose):
        if self.params.scale == 0.0:
            return pose
        return pose.model_copy(update={"depth_mm": pose.depth_mm * (1.0 + self.params.scale)})
