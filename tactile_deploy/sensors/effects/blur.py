"""Blur: the depth read-out loses fine detail (optical, readout stage).

Physics. A soft focus, a thick membrane coating or a diffuse reflective layer lowers the
modulation transfer function of the optics: the slopes a shading pipeline reads are those of a
smoothed surface, and so is the depth it integrates. To first order the reported depth is the
surface's map convolved with a Gaussian of standard deviation ``sigma_mm`` (its MTF
``exp(-2 pi^2 sigma^2 f^2)``; 0.5 at ``f = 0.19 / sigma``).

Signature: contact edges and peaks are smoothed: the residual is ``(sigma^2 / 2)`` times the
map's Laplacian to first order: negative at the deepest points, positive around the contact
edges, largest for sharp indenters (punch edges, small spheres), the same at every place on the
pad; null value ``sigma_mm = 0`` reproduces the nominal sensor exactly.

Residual it leaves: MTF shapes other than Gaussian (a defocus disc, anisotropic blur) beyond
their second moment.

Realistic range: 0-0.4 mm (about 1.5 pixels of the standard 0.27 mm depth grid).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field
from scipy.ndimage import gaussian_filter

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class BlurParams(EffectParams):
    sigma_mm: float = Field(0.0, ge=0.0, le=2.0, description="Standard deviation of the "
                            "Gaussian blur of the depth map, mm; 0 = none (null).")


class Blur(Effect):
    __doc__ = __doc__
    name = "blur"
    kind = "optical"
    stage = "readout"
    Params = BlurParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"sigma_mm": (0.0, 0.4)}

    def readout_map(self, depth_mm, xy_mm):
        s = self.params.sigma_mm
        if s == 0.0:
            return depth_mm
        pitch = float(abs(xy_mm[0, 1, 0] - xy_mm[0, 0, 0]))
        return gaussian_filter(np.asarray(depth_mm, np.float64), s / pitch, mode="constant",
                               truncate=4.0)
