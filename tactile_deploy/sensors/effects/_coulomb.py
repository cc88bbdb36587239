"""Coulomb friction between the indenter and the gel, solved on the sensing surface's compliance.

Notation as in :mod:`tactile_deploy.fem.contact`, with three contact dofs per sensing node
(x, y, z): ``f_i`` the force of the indenter on node i, ``fn_i = -f_z,i >= 0`` compressive,
``u_i`` the node's displacement, gap ``g_i = -delta_i - u_z,i >= 0``. The indenter moves straight
down (no lateral motion), so a node in contact slips by its tangential displacement ``u_t,i``.
Coulomb's law, for one load step from the rest state (proportional loading):

* free: ``f_i = 0``, ``g_i >= 0``;
* stick: ``g_i = 0``, ``u_t,i = 0``, ``|f_t,i| <= mu fn_i``;
* slip: ``g_i = 0``, ``f_t,i = -mu fn_i u_t,i / |u_t,i|`` (friction opposes the slip).

``mu = 0`` is frictionless contact, ``mu -> inf`` sticking contact.

Solver: the classic fixed point on the slip bound (Panagiotopoulos). Given the tangential
forces, the normal problem is frictionless contact with the tangential forces' normal
displacement added to the intrusion (primal-dual active sets, as for frictionless contact);
given the normal forces, the tangential forces solve the Tresca problem with the slip bound
``g_i = mu fn_i``: minimise ``1/2 f_t' C_tt f_t + f_t' C_tz f_z`` over ``|f_t,i| <= g_i``
(its optimality conditions are the stick and slip conditions above: the gradient is u_t), by
accelerated projected gradients (FISTA with restarts). The two alternate until the forces
settle. The stiffness is the nominal linear pad's; the compliance of all three dofs of every
sensing node is computed once per pad and Poisson ratio (one sparse solve per dof) and cached on
disk beside the frictionless operators.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as la

from tactile_deploy.fem.contact import solve_contact_pdas

#: Relative change of the forces (and fixed-point residual of the Tresca problem) at which
#: the iterations stop.
FORCE_TOL = 1e-9
MAX_OUTER = 200
MAX_INNER = 20000


class CoulombSolveError(RuntimeError):
    """The friction iterations did not settle."""


def _tresca(A: np.ndarray, b: np.ndarray, g: np.ndarray, x0: np.ndarray, L: float,
            tol: float) -> np.ndarray:
    """argmin 1/2 x'Ax + b'x over |x_i| <= g_i (x: (k, 2) node-major, flat), FISTA with
    gradient restarts."""
    def proj(x):
        v = x.reshape(-1, 2)
        n = np.linalg.norm(v, axis=1)
        scale = np.where(n > g, g / np.maximum(n, 1e-300), 1.0)
        return (v * scale[:, None]).ravel()

    x = proj(x0)
    y, t = x.copy(), 1.0
    for _ in range(MAX_INNER):
        grad = A @ y + b
        x_new = proj(y - grad / L)
        if np.max(np.abs(x_new - x)) <= tol:
            return x_new
        t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
        if (y - x_new) @ (x_new - x) > 0:  # restart when momentum points uphill
            y, t_new = x_new.copy(), 1.0
        else:
            y = x_new + ((t - 1.0) / t_new) * (x_new - x)
        x, t = x_new, t_new
    raise CoulombSolveError(f"the tangential (Tresca) problem did not settle in {MAX_INNER} "
                            "steps")


def solve_coulomb(C3: np.ndarray, delta: np.ndarray, mu: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coulomb contact on candidate nodes (module docstring).

    C3 : (3k, 3k) compliance, node-major (x, y, z), mm/N at E = 1. delta : (k,) mm. mu : >= 0.
    Returns ``(forces (k, 3) N at E = 1, active (k,) bool, slipping (k,) bool)``.
    """
    k = len(delta)
    t_idx = (np.arange(k)[:, None] * 3 + np.arange(2)).ravel()
    z_idx = np.arange(k) * 3 + 2
    Ctt = C3[np.ix_(t_idx, t_idx)]
    Ctz = C3[np.ix_(t_idx, z_idx)]
    Czz = C3[np.ix_(z_idx, z_idx)]
    L = float(np.linalg.eigvalsh(Ctt)[-1])
    ft = np.zeros(2 * k)
    fz = np.zeros(k)
    for _ in range(MAX_OUTER):
        sol = solve_contact_pdas(Czz, delta + Ctz.T @ ft, 1)
        fz_new = sol.forces[:, 0]
        scale = max(float(np.max(np.abs(fz_new))), 1e-300)
        g = mu * np.maximum(-fz_new, 0.0)
        ft_new = _tresca(Ctt, Ctz @ fz_new, g, ft, L, 1e-3 * FORCE_TOL * scale)
        change = max(float(np.max(np.abs(ft_new - ft))), float(np.max(np.abs(fz_new - fz))))
        ft, fz = ft_new, fz_new
        if change <= FORCE_TOL * scale:
            f = np.concatenate([ft.reshape(k, 2), fz[:, None]], axis=1)
            active = -fz > 0
            slipping = active & (np.linalg.norm(f[:, :2], axis=1) >= (1 - 1e-6) * g)
            return f, active, slipping
    raise CoulombSolveError(f"Coulomb contact (mu = {mu:g}) did not settle in {MAX_OUTER} "
                            f"steps ({k} candidate nodes, max intrusion {delta.max():.4g} mm)")


class CoulombSolver:
    """Coulomb contact on a :class:`~tactile_deploy.fem.simulator.ContactSimulator`'s pad (its
    stiffness, supports and contact nodes; its own friction law is ignored)."""

    def __init__(self, simulator):
        self.sim = simulator
        self._C3 = None

    @property
    def C3(self) -> np.ndarray:
        """(3k, 3k) compliance of the x, y, z dofs of the contact nodes, mm/N at E = 1."""
        if self._C3 is None:
            from tactile_deploy.fem.simulator import cache_dir, load_cached, save_cached

            sim = self.sim
            folder = cache_dir() / f"coulomb_{sim.operator_key}"
            path = folder / "C3.npy"
            cols = self.columns
            C3 = load_cached(path, (len(cols), len(cols)), "Coulomb compliance") if sim._use_cache else None
            if C3 is not None:
                self._C3 = C3
                return C3
            n_q = sim.K_q.shape[0]
            C3 = np.empty((len(cols), len(cols)))
            for start in range(0, len(cols), 256):
                sel = cols[start:start + 256]
                rhs = np.zeros((n_q, len(sel)))
                rhs[sel, np.arange(len(sel))] = 1.0
                C3[:, start:start + len(sel)] = sim.factor.solve(rhs)[cols]
            C3 = 0.5 * (C3 + C3.T)
            if sim._use_cache:
                save_cached(path, C3)
            self._C3 = C3
        return self._C3

    @property
    def columns(self) -> np.ndarray:
        """Reduced dofs (x, y, z) of every contact node, node-major, (3k,)."""
        d = self.sim.dofs
        nodes = self.sim.contact_nodes
        cols = np.concatenate([d.xy_cols[nodes], d.z_col[nodes][:, None]], axis=1)
        if np.any(cols < 0):
            raise ValueError("Coulomb friction needs free x, y and z at every contact node")
        return cols.ravel()

    def forces(self, delta: np.ndarray, mu: float) -> np.ndarray:
        """Contact forces (k, 3) N at E = 1 on the contact nodes for intrusions ``delta`` (k,) mm
        (candidate nodes grown until none penetrates, as for frictionless contact)."""
        C3 = self.C3
        forces = np.zeros((len(delta), 3))
        if not np.any(delta > 0):
            return forces
        reach = float(np.max(delta))
        cand = np.flatnonzero(delta > -reach)
        for _ in range(20):
            dofs = (cand[:, None] * 3 + np.arange(3)).ravel()
            f, _, _ = solve_coulomb(C3[np.ix_(dofs, dofs)], delta[cand], mu)
            forces[:] = 0.0
            forces[cand] = f
            u_normal = C3[2::3][:, dofs] @ f.ravel()
            penetrating = np.flatnonzero(-delta - u_normal < -1e-9 * reach)
            missing = np.setdiff1d(penetrating, cand)
            if len(missing) == 0:
                return forces
            cand = np.union1d(cand, missing)
        raise CoulombSolveError("contact candidate set did not settle")

    def displacements(self, forces: np.ndarray) -> np.ndarray:
        """Nodal displacements (n, 3) mm at E = 1 from contact forces (k, 3) N: one sparse
        solve of the pad."""
        sim = self.sim
        rhs = np.zeros(sim.K_q.shape[0])
        rhs[self.columns] = forces.ravel()
        uq = sim.factor.solve(rhs[:, None])[:, 0]
        return (sim.dofs.T @ uq).reshape(-1, 3)


def coulomb_solver(simulator) -> CoulombSolver:
    """The :class:`CoulombSolver` of ``simulator`` (built once, cached on it)."""
    solver = simulator.__dict__.get("_coulomb_solver")
    if solver is None:
        solver = CoulombSolver(simulator)
        simulator.__dict__["_coulomb_solver"] = solver
    return solver
