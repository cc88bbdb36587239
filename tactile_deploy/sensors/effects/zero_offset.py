"""Zero offset: the indentation depth is measured from a wrong zero (mechanical, contact stage).

Physics. The pressing axis' zero (where depth 0 is assumed to touch the gel) is off by
``offset_mm``: a commanded depth d presses the indenter to ``d + offset_mm`` (positive: deeper).
Typical causes: the touch-off detected by a force threshold, thermal growth of the rig, a gel
thickness tolerance, or the sensor's mount. The FEM solves the contact at the true depth.

Signature: for a smooth indenter the depth map's peak is deeper by exactly ``offset_mm`` (the
intrusion is shifted uniformly), the force by the corresponding amount of the force-depth curve;
null value ``offset_mm = 0`` reproduces the nominal sensor exactly. A commanded contact that the
offset lifts off the gel gives the no-contact frame.

Residual it leaves: none for a constant offset; a zero that drifts during a recording is not
modelled (use one instance per offset).

Realistic range: -0.05 to +0.05 mm (touch-off by force threshold on a 0.3 MPa gel).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class ZeroOffsetParams(EffectParams):
    offset_mm: float = Field(0.0, ge=-1.0, le=1.0, description="Error of the depth zero, mm: "
                             "the indenter goes this much deeper than commanded; 0 = none (null).")


class ZeroOffset(Effect):
    __doc__ = __doc__
    name = "zero_offset"
    kind = "mechanical"
    stage = "contact"
    Params = ZeroOffsetParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"offset_mm": (-0.05, 0.05)}

    def contact_pose(self, pose):
        if self.params.offset_mm == 0.0:
            return pose
        return pose.model_copy(update={"depth_mm": pose.depth_mm + self.params.offset_mm})
