"""Dome: a pre-curved sensing surface, domed (crowned) or dished (mechanical, geometry stage).

Physics. The gel is moulded with a paraboloid cap: at rest the sensing surface lies at
``z = -height_mm * r^2 / radius_mm^2`` below the plane z = 0 through its apex (sensor frame, r
the distance from the apex at ``(centre_x_mm, centre_y_mm)``, the pad centre by default). A
negative height is a dished gel (its rim higher than the centre: shrinkage of a gel cast in a
frame). Indentation depths are measured from the plane z = 0, so an indenter at radius r meets
the gel ``height_mm r^2 / radius_mm^2`` later: its intrusion into the gel at every
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

Realistic range: -0.3 to 0.5 mm over the 17.5 mm GelSlim pad (flat moulds sag or dish 0-0.1 mm
from shrinkage); domed fingertip gels reach 1 mm; the apex within 2 mm of the pad centre.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class DomeParams(EffectParams):
    height_mm: float = Field(0.0, ge=-1.5, le=1.5, description="Sag from the apex to radius_mm, "
                             "mm; 0 = flat (null), < 0 = dished (the rim higher).")
    radius_mm: float = Field(17.5, gt=0.0, le=50.0, description="Radius at which the sag equals "
                             "height_mm, mm (the pad rim).")
    centre_x_mm: float = Field(0.0, ge=-10.0, le=10.0, description="Apex x, sensor frame, mm.")
    centre_y_mm: float = Field(0.0, ge=-10.0, le=10.0, description="Apex y, sensor frame, mm.")


class Dome(Effect):
    __doc__ = __doc__
    name = "dome"
    kind = "mechanical"
    stage = "geometry"
    Params = DomeParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"height_mm": (-0.3, 0.5)}

    @property
    def is_null(self) -> bool:
        return self.params.height_mm == 0.0

    def rest_height_mm(self, xy_mm: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy_mm, np.float64)
        p = self.params
        if p.height_mm == 0.0:
            return np.zeros(len(xy))
        dx, dy = xy[:, 0] - p.centre_x_mm, xy[:, 1] - p.centre_y_mm
        return -p.height_mm * (dx**2 + dy**2) / p.radius_mm**2
