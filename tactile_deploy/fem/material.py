"""Material and friction parameters of the gel.

Units: Young's modulus ``E_mpa`` in MPa (= N/mm^2), so with lengths in mm the stiffness matrix
is in N/mm, forces in N and displacements in mm.

Silicone gels of vision-based tactile sensors have E of about 0.1-0.6 MPa and a Poisson ratio of
0.45-0.49. The paper's calibrated 145 MPa is outside that range: under displacement control (an
indenter pushed to a commanded depth) the displacement field does not depend on E at all, only the
forces do, so a fit of depth maps alone cannot identify E; it needs measured forces.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

FrictionModel = Literal["frictionless", "stick", "coulomb"]

#: Largest Poisson ratio the linear-tet pad model is validated for (see docs/fem.md, locking).
NU_MAX_VALIDATED = 0.49


class Material(BaseModel):
    """Linear-elastic gel with a friction law for the indenter contact."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    E_mpa: float = Field(0.3, gt=0, le=1e4, description="Young's modulus, MPa.")
    nu: float = Field(0.45, ge=0.0, lt=0.5, description="Poisson's ratio, dimensionless.")
    mu: float = Field(1.0, ge=0.0, description="Coulomb friction coefficient gel/indenter.")
    friction: FrictionModel = Field(
        "frictionless",
        description="Tangential contact law: frictionless (slip freely), stick (no slip), "
        "or coulomb (slip once |tangential| > mu * normal force).",
    )

    @property
    def lame_mpa(self) -> tuple[float, float]:
        """Lame parameters (lambda, mu_shear) in MPa."""
        lam = self.E_mpa * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        shear = self.E_mpa / (2.0 * (1.0 + self.nu))
        return lam, shear
