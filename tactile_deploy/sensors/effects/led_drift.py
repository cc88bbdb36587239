"""LED drift: the LEDs' brightness changes from frame to frame (optical, camera stage).

Physics. LED drivers, supply ripple and warm-up make each colour channel's illumination vary in
time; real GelSight-class recordings drift by up to +-30 grey levels against their reference
frame. Every frame, each channel's radiance is multiplied by ``1 + sigma_rel * n_c``, n_c an
independent standard normal deviate drawn from the frame's random generator.

Signature: per-channel frame means scatter around the nominal ones with relative standard
deviation ``sigma_rel``, the same factor over the whole frame; null value ``sigma_rel = 0``
reproduces the nominal sensor exactly.

Residual it leaves: slow drifts (correlated from frame to frame) and spatially varying flicker.

Realistic range: 0-0.08 (relative, one sigma).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class LedDriftParams(EffectParams):
    sigma_rel: float = Field(0.0, ge=0.0, le=0.5, description="Relative per-frame, per-channel "
                             "brightness variation (one sigma); 0 = none (null).")


class LedDrift(Effect):
    __doc__ = __doc__
    name = "led_drift"
    kind = "optical"
    stage = "camera"
    Params = LedDriftParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"sigma_rel": (0.0, 0.08)}

    def frame_gain(self, renderer, rng):
        s = self.params.sigma_rel
        if s == 0.0 or rng is None:
            return None
        return np.maximum(1.0 + s * rng.standard_normal(3), 0.0).astype(np.float32)
