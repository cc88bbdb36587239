"""Gain gradient: the depth read-out's gain varies across the field (optical, readout stage).

Physics. A shading calibration (colour -> slope table) made under one illumination reads slopes
too large or too small once the illumination has drifted, and unevenly when the drift differs
across the view (an LED aging, a diffuser thicker on one side): the slopes, and with them the
integrated depth, are scaled by a gain that varies smoothly across the pad. To first order the
reported depth is ``depth * (1 + gain + gain_per_mm_x x + gain_per_mm_y y)`` (x, y of the map's
pixel, sensor frame, mm).

Signature: the residual is the map itself times a plane: largest where contacts are deepest,
growing across the pad along one direction, the same law for every indenter; null value
``gain = gain_per_mm_x = gain_per_mm_y = 0`` reproduces the nominal sensor exactly.

Residual it leaves: gain that varies with the slope's direction or colour (a change of the
shading table itself, not a gain) and higher orders across the field.

Realistic range: gain -0.1 to 0.1, |gain_per_mm_x|, |gain_per_mm_y| up to 0.02 per mm (+-30 %
across a 15 mm view).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class GainGradientParams(EffectParams):
    gain: float = Field(0.0, ge=-0.5, le=0.5, description="Relative depth gain at the pad "
                        "centre, dimensionless; 0 = none (null).")
    gain_per_mm_x: float = Field(0.0, ge=-0.1, le=0.1, description="Change of the relative gain "
                                 "per mm along sensor +x, 1/mm.")
    gain_per_mm_y: float = Field(0.0, ge=-0.1, le=0.1, description="Change of the relative gain "
                                 "per mm along sensor +y, 1/mm.")


class GainGradient(Effect):
    __doc__ = __doc__
    name = "gain_gradient"
    kind = "optical"
    stage = "readout"
    Params = GainGradientParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {
        "gain": (-0.1, 0.1), "gain_per_mm_x": (-0.02, 0.02), "gain_per_mm_y": (-0.02, 0.02)}

    def readout_map(self, depth_mm, xy_mm):
        p = self.params
        if self.is_null:
            return depth_mm
        g = 1.0 + p.gain + p.gain_per_mm_x * xy_mm[..., 0] + p.gain_per_mm_y * xy_mm[..., 1]
        return np.asarray(depth_mm, np.float64) * g
