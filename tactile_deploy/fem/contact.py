"""Exact rigid-indenter contact on the sensing surface, solved on its compliance.

Notation for one sample, on the sensing nodes that may touch (candidates):

* ``delta_i`` (mm): intrusion of the rigid indenter below the rest surface at node i;
* ``u_z,i`` (mm): vertical displacement of node i (negative = pushed in);
* ``f_i`` (N): force the indenter applies to node i; ``fn_i = -f_z,i >= 0`` is compressive;
* gap ``g_i = -delta_i - u_z,i >= 0``: the node stays below the indenter surface.

Contact is a non-penetration constraint, not a penalty: either ``g_i = 0`` and ``fn_i >= 0``
(in contact) or ``g_i >= 0`` and ``f_i = 0`` (free), exactly (linear complementarity).

Tangential law per contact node:

* ``frictionless``: only ``f_z`` acts; the node slides freely.
* ``stick``: a node in contact does not slide (``u_x = u_y = 0``, the indenter moves only
  vertically), with unbounded tangential force.

The problem is solved with a primal-dual active-set method (semi-smooth Newton on the
complementarity conditions), which terminates exactly when the active set repeats. Each step
solves the compliance system restricted to the active nodes. For frictionless contact an
independent Lawson-Hanson solver (``scipy.optimize.nnls``) is the fallback and the test oracle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
from scipy.optimize import nnls


class ContactSolveError(RuntimeError):
    """The active-set iteration did not settle (reported with the sample's figures)."""


@dataclass(frozen=True)
class ContactSolution:
    """Contact forces on candidate nodes.

    ``forces`` : (k, b) float64, N — per candidate node, b = 1 (f_z) or 3 (f_x, f_y, f_z);
    ``active`` : (k,) bool — nodes in contact; ``iterations`` : active-set steps taken.
    """

    forces: np.ndarray
    active: np.ndarray
    iterations: int


def _normal_index(block: int) -> int:
    return 0 if block == 1 else 2


def solve_contact_pdas(
    C: np.ndarray, delta: np.ndarray, block: int, max_iter: int = 100
) -> ContactSolution:
    """Solve the contact complementarity problem by primal-dual active sets.

    Parameters
    ----------
    C : (k * block, k * block) float64, mm/N
        Compliance of the candidate nodes' contact dofs, node-major, the normal (z) dof last
        in each block of 3 (or alone when ``block == 1``). Symmetric positive definite.
    delta : (k,) float64, mm
        Indenter intrusion at each candidate node.
    block : 1 (frictionless) or 3 (stick).
    """
    k = len(delta)
    nz = _normal_index(block)
    normal_dofs = np.arange(k) * block + nz
    c = 1.0 / np.diag(C)[normal_dofs]  # N/mm, makes force and gap comparable
    active = delta > 0
    forces = np.zeros(k * block)
    for it in range(1, max_iter + 1):
        forces[:] = 0.0
        if active.any():
            dofs = (np.flatnonzero(active)[:, None] * block + np.arange(block)[None, :]).ravel()
            target = np.zeros((int(active.sum()), block))
            target[:, nz] = -delta[active]
            sub = C[np.ix_(dofs, dofs)]
            forces[dofs] = la.solve(sub, target.ravel(), assume_a="pos", check_finite=False)
        u_normal = C[normal_dofs] @ forces
        gap = -delta - u_normal
        fn = -forces[normal_dofs]
        new_active = (fn - c * gap) > 0
        if np.array_equal(new_active, active):
            return ContactSolution(forces.reshape(k, block), active, it)
        active = new_active
    raise ContactSolveError(
        f"active set did not settle in {max_iter} steps ({k} candidate nodes, "
        f"max intrusion {delta.max():.4g} mm)"
    )


def solve_frictionless_nnls(C: np.ndarray, delta: np.ndarray) -> ContactSolution:
    """Frictionless contact as non-negative least squares (Lawson-Hanson), an independent method.

    ``min 1/2 fn' C fn - delta' fn, fn >= 0`` equals ``min |L' fn - L^-1 delta|^2`` with
    ``C = L L'``; its KKT conditions are the complementarity conditions above.
    """
    L = la.cholesky(C, lower=True)
    rhs = la.solve_triangular(L, delta, lower=True)
    fn, _ = nnls(L.T, rhs, maxiter=50 * len(delta))
    return ContactSolution(-fn[:, None], fn > 0, 0)


def solve_contact(C: np.ndarray, delta: np.ndarray, block: int) -> ContactSolution:
    """PDAS with the Lawson-Hanson fallback for frictionless contact."""
    try:
        return solve_contact_pdas(C, delta, block)
    except ContactSolveError:
        if block != 1:
            raise
        return solve_frictionless_nnls(C, delta)
