"""Rotation offset: the indenter is turned about the pressing axis against the commanded angle
(mechanical, contact stage).

Physics. The indenter's angular zero in its holder (a flat on a shaft, a keyway, a tool-changer
pin) is off, so a commanded angle ``theta_deg`` is reached as ``theta_deg + dtheta_deg``
(counter-clockwise about +z seen from above, sensor frame). The FEM solves the contact at the
angle reached.

Signature: indenters that are bodies of revolution (spheres, round punches, rings) do not change
at all; for the others the depth residual sits at the contact's edges and corners, antisymmetric
under the indenter's symmetry (a quadrupole around a lying cylinder or a knife edge), the same
angle for every contact. Null value ``dtheta_deg = 0`` reproduces the nominal sensor exactly.

Residual it leaves: an angle that depends on the commanded angle (a holder that slips under
torque) and wobble of the indenter's axis (a tilt).

Realistic range: -5 to 5 degrees (an indenter aligned by eye in its holder; 1 degree with a
keyed mount).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class RotationOffsetParams(EffectParams):
    dtheta_deg: float = Field(0.0, ge=-90.0, le=90.0, description="Error of the indenter's "
                              "angle about +z, degrees counter-clockwise; 0 = none (null).")


class RotationOffset(Effect):
    __doc__ = __doc__
    name = "rotation_offset"
    kind = "mechanical"
    stage = "contact"
    Params = RotationOffsetParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"dtheta_deg": (-5.0, 5.0)}

    def contact_pose(self, pose):
        d = self.params.dtheta_deg
        if d == 0.0:
            return pose
        return pose.model_copy(update={"theta_deg": pose.theta_deg + d})
