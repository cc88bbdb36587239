"""Poisson drift: the gel's Poisson ratio differs from the calibrated one (mechanical, material
stage).

Physics. Silicone gels are nearly incompressible, but their effective Poisson ratio moves with
the batch (mixing ratio, plasticiser content), with ageing (oil bleeding out of the gel) and with
temperature; a sensor calibrated at one value is then simulated with the wrong volumetric
stiffness. The contact is solved exactly (surface Green's functions, exact active set) on the same
pad mesh, supports and contact law with ``nu + delta_nu`` (E unchanged); the simulator at that
ratio is built on first use and kept on the nominal simulator (its operators go to the disk
cache like every simulator's).

Signature: under displacement control the contact region itself hardly changes (the indenter
prescribes it); what changes is how the gel sinks around it: a lower ratio lets the surface
outside the contact edge sink further (a residual ring that grows with the depth: 2 / 8 um just
outside a 4 mm ball pressed 0.3 / 0.6 mm, for -0.03), and the force drops by about 4 % per 0.01.
Null value ``delta_nu = 0`` reproduces the nominal sensor exactly.

Residual it leaves: a Poisson ratio that varies through the gel (a skin on the surface) and
rate effects (viscoelastic relaxation of the bulk modulus). It replaces the linear solution, so it
is not combined with the hyperelastic effect (whose solve uses the nominal ratio).

Realistic range: -0.03 to 0.01 (nu 0.45-0.49 against a calibrated 0.48: the linear-tet pad model
is validated up to nu = 0.49).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from tactile_deploy.fem.material import NU_MAX_VALIDATED
from tactile_deploy.fem.simulator import ContactSimulator
from tactile_deploy.sensors.effects.base import Effect, EffectParams

#: Simulators at drifted ratios kept per nominal simulator (each holds its surface operators).
MAX_CACHED_SIMULATORS = 4


class PoissonDriftParams(EffectParams):
    delta_nu: float = Field(0.0, ge=-0.2, le=0.05, description="Change of the gel's Poisson "
                            "ratio against the simulator's, dimensionless; 0 = none (null).")


def drifted_simulator(simulator, delta_nu: float):
    """The simulator of ``simulator``'s pad at ``nu + delta_nu`` (built once, cached on it)."""

    nu = simulator.material.nu + delta_nu
    if not 0.0 <= nu <= NU_MAX_VALIDATED:
        raise ValueError(f"poisson_drift: nu = {simulator.material.nu:g} + {delta_nu:g} = {nu:g} "
                         f"is outside [0, {NU_MAX_VALIDATED}], where the linear-tet pad model is "
                         "validated; use a smaller delta_nu")
    cache = simulator.__dict__.setdefault("_poisson_drift_simulators", {})
    key = round(nu, 9)
    if key not in cache:
        while len(cache) >= MAX_CACHED_SIMULATORS:
            cache.pop(next(iter(cache)))
        cache[key] = ContactSimulator(
            simulator.mesh, simulator.material.model_copy(update={"nu": nu}),
            supports=simulator.supports, method=simulator.method, assembly=simulator.assembly,
            formulation=simulator.formulation, contact_nodes=simulator.contact_nodes,
            use_cache=simulator._use_cache)
    return cache[key]


class PoissonDrift(Effect):
    __doc__ = __doc__
    name = "poisson_drift"
    kind = "mechanical"
    stage = "material"
    Params = PoissonDriftParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"delta_nu": (-0.03, 0.01)}

    def correct_contact(self, simulator, delta_mm, result):
        if self.params.delta_nu == 0.0:
            return result
        return drifted_simulator(simulator, self.params.delta_nu).solve_intrusion(delta_mm)
