"""Illumination gradient: a smooth tilt of the illumination across the pad (optical, camera).

Physics. LEDs that age unevenly, a diffuser or light guide that is thicker on one side, or an
LED board slightly off-centre make the irradiance of the whole pad vary smoothly with position,
on top of the nominal model's per-LED fall-off. To first order the radiance of every channel is
multiplied by ``1 + gain_per_mm_x * x + gain_per_mm_y * y`` (x, y of the pad point each pixel
sees, sensor frame, mm), clipped at 0.

Signature: the ratio of a frame to the nominal frame is a plane over the pad with those slopes;
null value ``gain_per_mm_x = gain_per_mm_y = 0`` reproduces the nominal sensor exactly.

Residual it leaves: colour-dependent and higher-order non-uniformity (one LED fading alone is a
change of that LED's colour and fall-off in the optics model instead).

Realistic range: |gain| up to 0.02 per mm (+-30 % across a 15 mm view).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class IlluminationGradientParams(EffectParams):
    gain_per_mm_x: float = Field(0.0, ge=-0.1, le=0.1, description="Relative radiance change per "
                                 "mm along sensor +x, 1/mm; 0 = none (null).")
    gain_per_mm_y: float = Field(0.0, ge=-0.1, le=0.1, description="Relative radiance change per "
                                 "mm along sensor +y, 1/mm.")


class IlluminationGradient(Effect):
    __doc__ = __doc__
    name = "illumination_gradient"
    kind = "optical"
    stage = "camera"
    Params = IlluminationGradientParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"gain_per_mm_x": (-0.02, 0.02), "gain_per_mm_y": (-0.02, 0.02)}

    def __init__(self, params=None, **kwargs):
        super().__init__(params, **kwargs)
        self._cache: tuple[int, np.ndarray] | None = None

    def frame_gain(self, renderer, rng):
        p = self.params
        if p.gain_per_mm_x == 0.0 and p.gain_per_mm_y == 0.0:
            return None
        if self._cache is None or self._cache[0] != id(renderer):
            xy = renderer.pixel_xy_mm
            g = 1.0 + p.gain_per_mm_x * xy[..., 0] + p.gain_per_mm_y * xy[..., 1]
            self._cache = (id(renderer), np.maximum(g, 0.0).astype(np.float32)[..., None])
        return self._cache[1]
