"""Compression set: a permanent dent where the gel has been pressed most (mechanical, geometry
stage).

Physics. Elastomers loaded for a long time do not fully recover (compression set); a sensor
pressed again and again at the same place keeps a shallow dent there. The rest surface is lowered
by ``depth_mm * exp(-|p - c|^2 / (2 width_mm^2))`` around the point c = (x_mm, y_mm) (sensor
frame): an indenter meets the gel later by the local dent depth (the rest-height mechanism, as for
the dome), and the optics see the dimple in the no-contact frame.

Signature: contacts over the dent are shallower by about its local depth and lose the side that
lies over its slope; contacts elsewhere are unchanged; the residual is tied to one place of the
pad, not to the contacts' depth or shape. Null value ``depth_mm = 0`` reproduces the nominal
sensor exactly.

Residual it leaves: the gel's changed stiffness inside the dent (a set gel is slightly stiffer)
and dents that are not round.

Realistic range: 0-0.08 mm deep (a few per cent of a 3 mm gel after long use at one spot), 1-4 mm
wide. It is deliberately not a candidate of the discrepancy workflow (an unknown place: four
parameters): the workflow must report it as structure it cannot name.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class CompressionSetParams(EffectParams):
    depth_mm: float = Field(0.0, ge=0.0, le=0.5, description="Depth of the dent at its centre, "
                            "mm; 0 = none (null).")
    x_mm: float = Field(0.0, ge=-50.0, le=50.0, description="Centre of the dent, sensor x, mm.")
    y_mm: float = Field(0.0, ge=-50.0, le=50.0, description="Centre of the dent, sensor y, mm.")
    width_mm: float = Field(2.0, gt=0.0, le=20.0, description="Gaussian width (one sigma) of "
                            "the dent, mm.")


class CompressionSet(Effect):
    __doc__ = __doc__
    name = "compression_set"
    kind = "mechanical"
    stage = "geometry"
    Params = CompressionSetParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"depth_mm": (0.0, 0.08),
                                                                 "width_mm": (1.0, 4.0)}

    def rest_height_mm(self, xy_mm: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy_mm, np.float64)
        p = self.params
        r2 = (xy[:, 0] - p.x_mm) ** 2 + (xy[:, 1] - p.y_mm) ** 2
        return -p.depth_mm * np.exp(-r2 / (2.0 * p.width_mm**2))
