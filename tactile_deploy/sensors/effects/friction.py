"""Friction: Coulomb friction between the indenter and the gel (mechanical, material stage).

Physics. The nominal pad model's contact is frictionless (the gel slides freely under the
indenter). Silicone gels grip: the gel under a pressing indenter is held where the friction
force ``mu fn`` can hold it and slips where the gel's tendency to spread outward exceeds it.
This effect solves the contact with Coulomb friction of coefficient ``mu``
(:mod:`tactile_deploy.sensors.effects._coulomb`: stick/slip active sets on the compliance of
the sensing surface's three dofs per node, one load step from rest), replacing the model's
frictionless solution.

Signature: the gel under the contact is held back from spreading outward: the surface inside
the contact is pushed in more uniformly, contact edges are sharper, and the force rises (a
4 mm sphere 0.8 mm deep: the map differs from frictionless by up to 56 um and the force by
7 % when the gel sticks); the change grows with mu up to the sticking limit (mu about 1 for a
sphere on this gel) and then stops; null value ``mu = 0`` reproduces the nominal
(frictionless) sensor exactly.

Residual it leaves: the history of a press (loading path, rate effects; a press ramped in
steps slips differently from one load step), friction that depends on pressure, and the
indenter's lateral compliance.

Realistic range: mu 0.3-2 (silicone on steel or 3D-printed plastic; coated gels lower).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.sensors.effects.base import Effect, EffectParams


class FrictionParams(EffectParams):
    mu: float = Field(0.0, ge=0.0, le=20.0, description="Coulomb friction coefficient between "
                      "indenter and gel, dimensionless; 0 = frictionless (null).")


class Friction(Effect):
    __doc__ = __doc__
    name = "friction"
    kind = "mechanical"
    stage = "material"
    Params = FrictionParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"mu": (0.3, 2.0)}

    @classmethod
    def prepare(cls, simulator) -> None:
        from tactile_deploy.sensors.effects._coulomb import coulomb_solver

        solver = coulomb_solver(simulator)
        _ = solver.C3, simulator.factor

    def correct_contact(self, simulator, delta_mm, result):
        mu = self.params.mu
        if mu == 0.0:
            return result
        from tactile_deploy.fem.simulator import ContactResult
        from tactile_deploy.sensors.effects._coulomb import coulomb_solver

        solver = coulomb_solver(simulator)
        delta = np.asarray(delta_mm, np.float64)
        nodes = simulator.contact_nodes
        forces = solver.forces(delta[nodes], mu)
        u = solver.displacements(forces)
        mesh = simulator.mesh
        f3 = np.zeros((mesh.n_plane, 3))
        f3[nodes] = forces * simulator.material.E_mpa
        fn = -f3[:, 2]
        return ContactResult(rest_vertices_mm=mesh.vertices, displacements_mm=u,
                             contact_mask=fn > 0, contact_forces_n=f3,
                             pressure_kpa=1e3 * fn / mesh.sensing_nodal_areas_mm2(),
                             force_n=float(fn.sum()), intrusion_mm=delta)
