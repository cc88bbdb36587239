"""Saturation: an over-exposed camera clips the bright shading (optical, optics stage).

Physics. The exposure (shutter time x analogue gain) is set higher than the nominal model's by
``exposure_factor``; every radiance is multiplied by it before noise, and whatever exceeds the
sensor's full well (``saturation_grey``, 255 for 8-bit) clips. Bright slopes facing an LED lose
their gradient information, which a shading model cannot recover.

Signature: unsaturated pixels scale by ``exposure_factor``; the fraction of pixels at the
saturation level grows with it, first on the slopes facing the LEDs; null value
``exposure_factor = 1`` reproduces the nominal sensor exactly.

Residual it leaves: blooming (charge spilling into neighbours) and a soft knee of the response
near full well.

Realistic range: 1.0-1.6 (auto-exposure settling on a dark scene, or a user-set gain).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class SaturationParams(EffectParams):
    exposure_factor: float = Field(1.0, ge=0.5, le=4.0, description="Exposure relative to the "
                                   "nominal model, dimensionless; 1 = nominal (null).")


class Saturation(Effect):
    __doc__ = __doc__
    name = "saturation"
    kind = "optical"
    stage = "optics"
    Params = SaturationParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"exposure_factor": (1.0, 1.6)}

    def optics(self, model):
        f = self.params.exposure_factor
        if f == 1.0:
            return model
        return model.model_copy(update={"exposure_gain": model.exposure_gain * f})
