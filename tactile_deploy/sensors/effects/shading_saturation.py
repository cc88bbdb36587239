"""Shading saturation: steep slopes read as a limit slope (optical, readout stage).

Physics. A shading pipeline reads each pixel's colour as a surface slope. Where the shading
saturates (pixels at full well on slopes facing an LED, or past the end of the calibrated
colour -> slope table) a steeper slope reads the same colour: the slope magnitude read is
``min(|g|, 1 / inverse_max_slope)`` in the slope's direction (|g| the surface's slope, mm/mm).
The pipeline integrates these clipped slopes, so every contact whose gel slopes exceed the
limit is reported shallower, most where it is steepest.

Signature: nothing changes until a contact's steepest slope passes the limit; beyond it the
residual is negative at the contact's centre, with the rim of the steep region pulled in, and
it grows with the depth and the sharpness of the indenter (small spheres and punch edges
first); null value ``inverse_max_slope = 0`` (no limit) reproduces the nominal sensor exactly.

Residual it leaves: a soft knee (slopes compressed before they clip) and saturation that depends
on the slope's direction (one LED saturating alone).

Realistic range: inverse_max_slope 0-3 (slopes clip at 0.33 mm/mm and above; a 4 mm ball 1 mm
deep reaches 0.8 at its contact edge).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class ShadingSaturationParams(EffectParams):
    inverse_max_slope: float = Field(0.0, ge=0.0, le=20.0, description="1 / the surface slope "
                                     "(mm/mm) beyond which slopes read as that slope; 0 = no "
                                     "limit (null).")


class ShadingSaturation(Effect):
    __doc__ = __doc__
    name = "shading_saturation"
    kind = "optical"
    stage = "readout"
    Params = ShadingSaturationParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"inverse_max_slope": (0.0, 3.0)}

    def readout_map(self, depth_mm, xy_mm):
        c = self.params.inverse_max_slope
        if c == 0.0:
            return depth_mm
        from tactile_deploy.imaging.poisson import integrate_gradients

        pitch = float(abs(xy_mm[0, 1, 0] - xy_mm[0, 0, 0]))
        z = np.asarray(depth_mm, np.float64)
        # slopes of the surface (mm/mm) on the pixel grid; the surface moves in by the depth
        g_col = np.gradient(z, axis=1) / pitch
        g_row = np.gradient(z, axis=0) / pitch
        mag = np.hypot(g_col, g_row)
        limit = 1.0 / c
        factor = np.where(mag > limit, limit / np.maximum(mag, 1e-300), 1.0)
        if np.all(factor == 1.0):
            return z
        # integrate only the change of the slopes: the map keeps its level far from contacts
        d_col = (g_col * (factor - 1.0)) * pitch
        d_row = (g_row * (factor - 1.0)) * pitch
        return z + integrate_gradients(d_col, d_row, "dirichlet").astype(np.float64)
