"""Dome: a pre-curved sensing surface (mechanical, geometry stage).

Physics. The gel is moulded with a paraboloid cap: at rest the sensing surface lies at
``z = -height_mm * r^2 / radius_mm^2`` below the apex plane z = 0 (sensor frame, r the distance
from the pad centre). Indentation depths are measured from the apex plane, so an indenter at
radius r meets the gel ``height_mm r^2 / radius_mm^2`` later: its intrusion into the gel at every
sensing node is reduced by the sag there (the rest-height mechanism of
:meth:`tactile_deploy.fem.simulator.ContactSimulator.intrusion`, solved on the pad's exact
surface compliance). The camera sees the curved surface: normals tilt outwards by
``atan(2 height r / radius^2)``, so the no-contact frame changes as well.

Signature: the depth-map residual against the nominal sensor grows toward the edge (a press at
radius r is shallower by about the sag there); null value ``height_mm = 0`` reproduces the
nominal sensor exactly.

Residual it leaves: the compliance is that of the flat pad (a shallow shell of sag h is thinner
at the rim by h, so there it is slightly stiffer than modelled, of order h / thickness); the
output mesh and depth maps stay those of the flat pad's displacement field (deformation relative
to the domed rest shape), the rest shape itself is not in the mesh.

Realistic range: 0-0.5 mm over the 17.5 mm GelSlim pad (flat moulds sag 0-0.1 mm from
shrinkage); domed fingertip gels reach 1 mm.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class DomeParams(EffectParams):
    height_mm: float = Field(0.0, ge=0.0, le=1.5, description="Sag from the apex (pad centre) "
                             "to radius_mm, mm; 0 = flat (null).")
    radius_mm: float = Field(17.5, gt=0.0, le=50.0, description="Radius at which the sag equals "
                             "height_mm, mm (the pad rim).")


class Dome(Effect):
    __doc__ = __doc__
    name = "dome"
    kind = "mechanical"
    stage = "geometry"
    Params = DomeParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"height_mm": (0.0, 0.5)}

    def rest_height_mm(self, xy_mm: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy_mm, np.float64)
        p = self.params
        return -p.height_mm * (xy[:, 0] ** 2 + xy[:, 1] ** 2) / p.radius_mm**2
