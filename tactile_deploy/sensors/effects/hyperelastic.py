"""Hyperelastic: neo-Hookean large-deformation response of the gel (mechanical, material stage).

Physics. The nominal model is small-strain linear elasticity; at indentations of a third of the
3 mm pad the strains under the indenter reach 30-50 %, where a silicone gel (neo-Hookean to good
approximation) departs from it: geometric nonlinearity (equilibrium in the deformed shape) and
material nonlinearity (stiffening in compression, volume conservation exact rather than
linearised). This effect solves the pad as a compressible neo-Hookean solid
(:class:`tactile_deploy.fem.hyperelastic.NeoHookeanGel`, the resolved solver's model: isochoric
neo-Hookean energy per tet plus a bulk energy on the nodal patch volumes, whose small-strain
limit is exactly the nominal locking-free stiffness) with frictionless contact against the indenter, by fixed-point
iterations on the nominal model's factorised stiffness::

    K u_(k+1) = f_contact - s r(u_k),    r(u) = f_int(u) - K u  (the large-deformation terms)

each step solved exactly with the contact constraints on the pad's surface compliance (the
pre-displacement ``-K^-1 s r`` shifts the indenter's intrusion; the exact active set follows),
until the displacements change by less than ``TOLERANCE_MM``. ``strength`` s scales the
large-deformation terms: 0 is the linear model (null), 1 neo-Hookean, > 1 a gel that stiffens
faster than neo-Hookean (Gent- or Mooney-Rivlin-like at large strain). The internal forces run as
warp kernels when warp is installed (:mod:`tactile_deploy.fem.hyperelastic_warp`; numpy
otherwise).

Signature: against the nominal sensor the residual (depth map, force) grows faster than linearly
with the indentation depth: the large-deformation terms are of second order in the strain, so
the residual is about quadratic in depth (x 4 for twice the depth) where the nominal error
budget is linear. Null value ``strength = 0`` reproduces the nominal sensor exactly.

Residual it leaves: the contact is linearised (gap measured along z at the nodes' rest
positions, frictionless forces along z), and the mesh is the nominal 1 mm tet mesh (no
remeshing); Coulomb friction is not combined with it.

Realistic range: strength 0.5-1.5 (silicones between Mooney-Rivlin with softening and Gent
stiffening); 1 for a neo-Hookean gel.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.fem.simulator import ContactResult, surface_contact_forces
from tactile_deploy.fem.hyperelastic import InvertedElementError, NeoHookeanGel
from tactile_deploy.fem.hyperelastic_warp import NeoHookeanForces
from tactile_deploy.sensors.effects.base import Effect, EffectParams

#: Convergence tolerance of the fixed-point iterations, mm (largest nodal change).
TOLERANCE_MM = 1e-6
#: Most iterations before the solve is declared not converged.
MAX_ITERATIONS = 200


class HyperelasticParams(EffectParams):
    strength: float = Field(0.0, ge=0.0, le=3.0, description="Scale of the neo-Hookean "
                            "large-deformation terms, dimensionless: 0 = linear (null), 1 = "
                            "neo-Hookean.")


class HyperelasticConvergenceError(RuntimeError):
    """The large-deformation iterations did not converge (too deep a contact for this gel)."""


def _pad_model(simulator):
    """Neo-Hookean internal forces of the simulator's mesh at E = 1 MPa (cached on the
    simulator): ``_pad_model(sim)(u, backend)`` (n, 3), ``.gel`` the
    :class:`~tactile_deploy.fem.hyperelastic.NeoHookeanGel`."""

    cached = getattr(simulator, "_neo_hookean_pad", None)
    if cached is None:
        cached = NeoHookeanForces(NeoHookeanGel(simulator.mesh.vertices, simulator.mesh.tets,
                                                1.0, simulator.material.nu))
        simulator._neo_hookean_pad = cached
    return cached


def solve_neo_hookean(simulator, delta_mm: np.ndarray, strength: float = 1.0,
                      backend: str = "auto", initial=None, anderson: int = 10):
    """Frictionless contact of the neo-Hookean pad for intrusions ``delta_mm`` (n_plane,) mm.

    ``simulator``: a frictionless :class:`~tactile_deploy.fem.simulator.ContactSimulator` with
    the ``nodal_pressure`` formulation (its operators and factor are reused). Returns
    ``(ContactResult, info)`` with info = {"iterations", "change_mm"}. Anderson acceleration
    (history ``anderson``; mixing 0.5, then 0.2 if that breaks down) makes the iterations
    converge where the plain fixed point diverges (strains of 50 %).
    """

    if simulator.block != 1:
        raise ValueError("the hyperelastic effect solves frictionless contact only; build the "
                         "sensor with friction='frictionless'")
    if simulator.formulation != "nodal_pressure":
        raise ValueError("the hyperelastic effect needs the 'nodal_pressure' formulation "
                         f"(its small-strain limit), got {simulator.formulation!r}")
    mesh = simulator.mesh
    delta = np.asarray(delta_mm, np.float64)
    if delta.shape != (mesh.n_plane,):
        raise ValueError(f"delta_mm must have shape ({mesh.n_plane},), got {delta.shape}")
    pad = _pad_model(simulator)
    T = simulator.dofs.T
    K = simulator.K_q
    factor = simulator.factor
    C = simulator.compliance
    nodes = simulator.contact_nodes
    d = delta[nodes]

    def step(u: np.ndarray):
        """One fixed-point map: displacements (n, 3) -> (new displacements, forces)."""
        uq = T.T @ u.ravel()
        try:
            f_int = pad(u, backend)
        except InvertedElementError:
            raise _Breakdown from None   # as non-finite forces: the iterations broke down
        r = T.T @ f_int.ravel() - K @ uq
        ub = (T @ factor.solve(-strength * r)).reshape(-1, 3)
        d_eff = d + ub[nodes, 2]
        if np.any(d_eff > 0):
            forces = surface_contact_forces(C, d_eff, 1)
        else:
            forces = np.zeros((len(d), 1))
        return ub + simulator.displacements_from_forces(forces), forces

    if initial is None:
        initial = simulator.solve_intrusion(delta).displacements_mm
    u0 = np.asarray(initial, np.float64)
    for depth, beta in ((anderson, 0.5), (anderson, 0.2)):
        try:
            u, forces, it, change = _iterate(step, u0, depth, beta)
            break
        except _Breakdown:
            continue
    else:
        raise HyperelasticConvergenceError(
            f"neo-Hookean contact did not converge in {MAX_ITERATIONS} iterations: the contact is "
            f"too deep for strength={strength} (elements invert or the iterations stall); press "
            f"less deep")
    n_plane = mesh.n_plane
    f3 = np.zeros((n_plane, 3))
    f3[nodes, 2] = forces[:, 0] * simulator.material.E_mpa
    fn = -f3[:, 2]
    areas = mesh.sensing_nodal_areas_mm2()
    result = ContactResult(
        rest_vertices_mm=mesh.vertices, displacements_mm=u, contact_mask=fn > 0,
        contact_forces_n=f3, pressure_kpa=1e3 * fn / areas, force_n=float(fn.sum()),
        intrusion_mm=delta)
    return result, {"iterations": it, "change_mm": change}


class _Breakdown(Exception):
    pass


def _iterate(step, u, depth: int, beta: float):
    """Anderson-accelerated fixed-point iterations of ``u <- step(u)`` with mixing ``beta``
    (history ``depth``; the update is ``x + beta f`` corrected over the last differences)."""
    xs, fs = [], []
    for it in range(1, MAX_ITERATIONS + 1):
        with np.errstate(all="ignore"):
            g, forces = step(u)
        f = (g - u).ravel()
        change = float(np.abs(f).max())
        if not np.isfinite(change):
            raise _Breakdown
        if change < TOLERANCE_MM:
            return g, forces, it, change
        xs = (xs + [u.ravel().copy()])[-(depth + 1):]
        fs = (fs + [f])[-(depth + 1):]
        if len(xs) > 1 and depth > 0:
            dF = np.diff(np.stack(fs, axis=1), axis=1)
            dX = np.diff(np.stack(xs, axis=1), axis=1)
            try:  # least squares through the small normal equations (40 x faster than a
                # tall SVD); singular values below 1e-7 of the largest are dropped
                gamma = np.linalg.lstsq(dF.T @ dF, dF.T @ fs[-1], rcond=1e-14)[0]
            except np.linalg.LinAlgError:
                raise _Breakdown from None
            u = (xs[-1] + beta * fs[-1] - (dX + beta * dF) @ gamma).reshape(-1, 3)
        else:
            u = u + beta * (g - u)
    raise _Breakdown


class Hyperelastic(Effect):
    __doc__ = __doc__
    name = "hyperelastic"
    kind = "mechanical"
    stage = "material"
    Params = HyperelasticParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"strength": (0.5, 1.5)}

    def correct_contact(self, simulator, delta_mm, result):
        if self.params.strength == 0.0:
            return result
        out, _ = solve_neo_hookean(simulator, delta_mm, self.params.strength,
                                   initial=result.displacements_mm)
        return out
