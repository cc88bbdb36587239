"""Coulomb friction between a rigid indenter and the pad, on the sensing surface's compliance.

Notation as in :mod:`tactile_deploy.fem.contact` (sensor frame, mm, N at E = 1 MPa), with three
contact dofs (x, y, z) per candidate sensing node i:

* ``f_i`` (N): force of the indenter on node i; ``p_i = -f_z,i`` the compressive normal force,
  ``t_i = (f_x,i, f_y,i)`` the tangential (friction) force;
* ``u = C f`` (mm): displacements of the contact dofs, ``C`` the dense surface compliance
  (:attr:`ContactSimulator.compliance` with three dofs per node, the one sticking contact uses);
* gap ``g_i = -delta_i - u_z,i >= 0`` (the same gap as frictionless and sticking contact);
* slip ``s_i = u_t,i - r_i`` (mm): the node's tangential displacement relative to the point of
  the indenter it touches; ``r_i = 0`` for one load step from rest (the indenter moves along
  -z only), the node's previous tangential displacement plus the indenter's tangential move in
  a load history (:meth:`CoulombSimulator.solve` with ``press_steps`` or ``slide_mm``).

Conditions at every candidate node (Signorini contact and Coulomb's law, ``mu >= 0``):

* free: ``f_i = 0``, ``g_i >= 0``;
* stick: ``g_i = 0``, ``p_i >= 0``, ``s_i = 0``, ``|t_i| <= mu p_i``;
* slip: ``g_i = 0``, ``p_i >= 0``, ``t_i = -mu p_i s_i / |s_i|`` (friction opposes the slip).

``mu = 0`` is frictionless contact; ``mu`` above the largest ``|t_i| / p_i`` of the sticking
solution gives the sticking solution (:class:`ContactSimulator` with friction "stick"), since it
satisfies all conditions above.

Solver: the conditions written as the non-smooth equations of Alart and Curnier,
``p - max(0, p - c_n g) = 0`` and ``max(eta, |z|) t - eta z = 0`` with ``z = t - c_t s``,
``eta = mu max(0, p - c_n g)``, solved by a semi-smooth Newton method (the primal-dual active
set method of Hueber, Stadler and Wohlmuth, SIAM J. Sci. Comput. 30 (2008) 572-596, with their
cone-projected tangential force in the slip linearisation): each step sorts the nodes into
free, stick and slip sets from the last iterate and solves one dense linear system on the
nodes in contact (3 rows each: the gap, and the slip or the linearised friction law). It stops
when the natural residual ``max_i |p_i - max(0, p_i - c_n g_i)|`` and
``|t_i - proj_{|.| <= eta_i}(z_i)|`` is at most ``TOL = 1e-10`` times the largest normal force
(a force tolerance, relative); it raises :class:`CoulombSolveError` naming the contact when it
does not within ``MAX_ITER`` steps. ``c_n``, ``c_t`` are the inverse diagonal compliances
(N/mm), which make forces and displacements comparable.

The sensor effect ``friction`` (:mod:`tactile_deploy.sensors.effects._coulomb`) solves the
same discrete problem by a different algorithm (fixed point on the slip bound, projected
gradients); the tests compare the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as la

from tactile_deploy.fem.material import Material
from tactile_deploy.fem.simulator import ContactResult, ContactSimulator
from tactile_deploy.pad.mesh import PadMesh

#: Natural residual of the contact and friction conditions at which the Newton steps stop,
#: relative to the largest normal force of the contact.
TOL = 1e-10
#: Newton steps allowed for one load step.
MAX_ITER = 100


class CoulombSolveError(RuntimeError):
    """The semi-smooth Newton iteration did not settle (the message gives the contact's figures)."""


@dataclass(frozen=True)
class CoulombSolution:
    """Coulomb contact on candidate nodes.

    forces : (k, 3) float64, N at E = 1 (x, y, z; indenter on gel)
    active : (k,) bool, nodes in contact; stick : (k,) bool, nodes in contact that stick
    iterations : Newton steps; residual : final natural residual relative to the largest p
    """

    forces: np.ndarray
    active: np.ndarray
    stick: np.ndarray
    iterations: int
    residual: float


def _natural_residual(p, t, g, s, mu, c_n, c_t) -> float:
    """max over nodes of the Alart-Curnier residuals (N at E = 1)."""
    rn = p - np.maximum(0.0, p - c_n * g)
    eta = mu * np.maximum(0.0, p - c_n * g)
    z = t - c_t[:, None] * s
    nz = np.linalg.norm(z, axis=1)
    proj = z * np.minimum(1.0, eta / np.maximum(nz, 1e-300))[:, None]
    rt = np.linalg.norm(t - proj, axis=1)
    return float(max(np.max(np.abs(rn)), np.max(rt)))


def solve_coulomb_ssn(C: np.ndarray, delta: np.ndarray, mu: float, ref: np.ndarray | None = None,
                      tol: float = TOL, max_iter: int = MAX_ITER) -> CoulombSolution:
    """Coulomb contact on candidate nodes by semi-smooth Newton (module docstring).

    Parameters
    ----------
    C : (3k, 3k) float64, mm/N at E = 1 — compliance of the candidates' x, y, z dofs,
        node-major; symmetric positive definite.
    delta : (k,) float64, mm — indenter intrusion at each candidate node.
    mu : friction coefficient, >= 0.
    ref : (k, 2) float64, mm — tangential position of the indenter point each node would stick
        to (``r_i``; zero: one load step from rest).
    """
    k = len(delta)
    if ref is None:
        ref = np.zeros((k, 2))
    zi = np.arange(k) * 3 + 2
    diag = np.diag(C)
    c_n = 1.0 / diag[zi]
    c_t = 2.0 / (diag[zi - 2] + diag[zi - 1])
    # Start from sticking contact where the indenter reaches (the first step is its solution).
    active = delta > 0
    stick = active.copy()
    f = np.zeros((k, 3))
    u = np.zeros((k, 3))
    res = np.inf
    for it in range(1, max_iter + 1):
        A = np.flatnonzero(active)
        f_new = np.zeros((k, 3))
        if len(A):
            dofs = (A[:, None] * 3 + np.arange(3)).ravel()
            CA = C[dofs][:, dofs]  # (3a, 3a): u of the active dofs from their forces
            m = len(A)
            M = np.empty((3 * m, 3 * m))
            rhs = np.empty(3 * m)
            # normal rows: g = 0  ->  u_z = -delta
            M[2::3] = CA[2::3]
            rhs[2::3] = -delta[A]
            st = stick[A]
            rows_st = np.flatnonzero(st)
            for j in (0, 1):  # stick rows: s = 0  ->  u_t = r
                M[3 * rows_st + j] = CA[3 * rows_st + j]
                rhs[3 * rows_st + j] = ref[A[rows_st], j]
            rows_sl = np.flatnonzero(~st)
            if len(rows_sl):
                nodes = A[rows_sl]
                if mu == 0.0:  # frictionless: t = 0
                    for j in (0, 1):
                        M[3 * rows_sl + j] = 0.0
                        M[3 * rows_sl + j, 3 * rows_sl + j] = 1.0
                        rhs[3 * rows_sl + j] = 0.0
                else:
                    _slip_rows(M, rhs, CA, rows_sl, f[nodes], u[nodes], delta[nodes], ref[nodes],
                               mu, c_n[nodes], c_t[nodes])
            try:
                fa = la.solve(M, rhs, check_finite=False)
            except la.LinAlgError as e:
                raise CoulombSolveError(
                    f"Coulomb contact (mu = {mu:g}): singular Newton system at step {it} "
                    f"({k} candidate nodes, {len(A)} in contact): {e}") from None
            f_new[A] = fa.reshape(m, 3)
            u_new = (C[:, dofs] @ fa).reshape(k, 3)
        else:
            u_new = np.zeros((k, 3))
        f, u = f_new, u_new
        p, t = -f[:, 2], f[:, :2]
        g = -delta - u[:, 2]
        s = u[:, :2] - ref
        scale = max(float(np.max(p)), 1e-300)
        res = _natural_residual(p, t, g, s, mu, c_n, c_t) / scale
        pt = p - c_n * g
        new_active = pt > 0
        z = t - c_t[:, None] * s
        new_stick = new_active & (np.linalg.norm(z, axis=1) < mu * np.maximum(pt, 0.0))
        if res <= tol and np.array_equal(new_active, active):
            return CoulombSolution(f, active, stick & active, it, res)
        active, stick = new_active, new_stick
    raise CoulombSolveError(
        f"Coulomb contact (mu = {mu:g}) did not settle in {max_iter} Newton steps: residual "
        f"{res:.3g} of the largest normal force (tolerance {tol:g}); {k} candidate nodes, "
        f"{int(active.sum())} in contact, max intrusion {float(np.max(delta)):.4g} mm")


def _slip_rows(M, rhs, CA, rows, f, u, delta, ref, mu, c_n, c_t) -> None:
    """Fill the tangential rows of slipping nodes: the Newton linearisation of
    ``|z| t - eta z = 0`` at the last iterate (``z = t - c_t s``, ``eta = mu p`` with the node
    on the indenter), the tangential force in the derivative of ``|z|`` projected onto the
    friction cone (Hueber-Stadler-Wohlmuth)."""
    p_k = -f[:, 2]
    g_k = -delta - u[:, 2]
    eta_k = mu * np.maximum(0.0, p_k - c_n * g_k)
    t_k = f[:, :2]
    z_k = t_k - c_t[:, None] * (u[:, :2] - ref)
    nz = np.linalg.norm(z_k, axis=1)
    nz = np.maximum(nz, 1e-300)
    n = z_k / nz[:, None]
    nt = np.linalg.norm(t_k, axis=1)
    t_hat = t_k * np.minimum(1.0, eta_k / np.maximum(nt, 1e-300))[:, None]
    for q, r in enumerate(rows):
        # z = Z f_A + c_t ref, Z = E_t - c_t CA[t rows]
        Z = -c_t[q] * CA[3 * r: 3 * r + 2]
        Z[0, 3 * r] += 1.0
        Z[1, 3 * r + 1] += 1.0
        B = np.outer(t_hat[q], n[q]) - eta_k[q] * np.eye(2)
        row = B @ Z
        row[0, 3 * r] += nz[q]
        row[1, 3 * r + 1] += nz[q]
        row[:, 3 * r + 2] += mu * z_k[q]  # -eta z_k with eta = -mu f_z
        M[3 * r: 3 * r + 2] = row
        rhs[3 * r: 3 * r + 2] = nz[q] * t_hat[q] - eta_k[q] * z_k[q] - B @ (c_t[q] * ref[q])


def coulomb_surface_forces(C: np.ndarray, delta: np.ndarray, mu: float, ref: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray, int]:
    """Coulomb contact over all contact nodes: forces (k, 3) N at E = 1, stick flags (k,) and the
    Newton steps taken, for intrusions ``delta`` (k,) mm and stick references ``ref`` (k, 2) mm
    (zero: from rest), on the compliance ``C`` (3k, 3k) mm/N at E = 1 (node-major x, y, z).

    Candidates as for frictionless contact (intrusion above minus the largest one), grown by
    every node found penetrating until none does; each round is :func:`solve_coulomb_ssn` on the
    candidates. Raises :class:`CoulombSolveError` when a round does not settle or the candidates
    do not settle in 20 rounds.
    """
    k = len(delta)
    forces = np.zeros((k, 3))
    stick = np.zeros(k, bool)
    if ref is None:
        ref = np.zeros((k, 2))
    if not np.any(delta > 0):
        return forces, stick, 0
    reach = float(np.max(delta))
    cand = np.flatnonzero(delta > -reach)
    iterations = 0
    for _ in range(20):
        dofs = (cand[:, None] * 3 + np.arange(3)).ravel()
        sol = solve_coulomb_ssn(C[np.ix_(dofs, dofs)], delta[cand], mu, ref[cand])
        iterations += sol.iterations
        forces[:] = 0.0
        stick[:] = False
        forces[cand] = sol.forces
        stick[cand] = sol.stick
        act = cand[sol.active]
        adofs = (act[:, None] * 3 + np.arange(3)).ravel()
        u_normal = C[2::3][:, adofs] @ forces[act].ravel()
        penetrating = np.flatnonzero(-delta - u_normal < -1e-9 * reach)
        missing = np.setdiff1d(penetrating, cand)
        if len(missing) == 0:
            return forces, stick, iterations
        cand = np.union1d(cand, missing)
    raise CoulombSolveError("contact candidate set did not settle in 20 rounds "
                            f"(mu = {mu:g}, max intrusion {reach:.4g} mm)")


def _check_coulomb(material: Material) -> None:
    if material.friction != "coulomb":
        raise ValueError(f"CoulombSimulator solves friction 'coulomb', got material.friction="
                         f"{material.friction!r}; use ContactSimulator for it")


class CoulombSimulator(ContactSimulator):
    """Linear-elastic pad + rigid indenter with Coulomb friction of coefficient ``material.mu``.

    The pad model, supports, operators and result are those of :class:`ContactSimulator` with
    three contact dofs per sensing node (its "stick" operators, shared on disk); only the
    tangential law differs (module docstring). ``method`` is "surface" only.

    :meth:`solve` presses the indenter in ``press_steps`` equal depth increments (1: one load
    step from rest, the formulation of the "stick" path) and then, when ``slide_mm`` is not
    zero, moves it that far along the surface (sensor frame x, y, mm) in ``slide_steps``
    increments; each increment is a Coulomb problem whose slip is measured from the end of the
    last one. The result's ``stick_mask`` marks the nodes in contact that stick.
    """

    def __init__(self, mesh: PadMesh, material: Material = Material(friction="coulomb"), **options):
        """``options``: those of :class:`ContactSimulator` (supports, assembly, formulation,
        contact_nodes, use_cache; ``method`` "surface" only)."""
        _check_coulomb(material)
        method = options.get("method", "surface")
        if method != "surface":
            raise ValueError(f"CoulombSimulator solves on the surface compliance: method must be "
                             f"'surface', got {method!r}")
        super().__init__(mesh, material.model_copy(update={"friction": "stick"}), **options)
        self.material = material
        self.last_iterations = 0

    @classmethod
    def sharing(cls, stick: ContactSimulator, material: Material) -> "CoulombSimulator":
        """A Coulomb simulator using the operators of the sticking-contact simulator ``stick``
        (same mesh, nu, supports and contact nodes); no copy is made."""
        if stick.block != 3:
            raise ValueError("sharing needs a simulator with three contact dofs per node "
                             f"(friction 'stick'), got friction {stick.material.friction!r}")
        if stick.material.nu != material.nu:
            raise ValueError(f"material.nu={material.nu} differs from the shared simulator's "
                             f"nu={stick.material.nu}")
        _check_coulomb(material)
        stick.prepare()
        sim = cls.__new__(cls)
        sim.__dict__.update(stick.__dict__)  # dof map, contact nodes, areas, operators: shared
        sim.method = "surface"
        sim.material = material
        sim.last_iterations = 0
        return sim

    def solve(self, indenter, pose, press_steps: int = 1, slide_mm: tuple[float, float] = (0.0, 0.0),
              slide_steps: int = 8) -> ContactResult:
        """Contact of ``indenter`` pressed to ``pose`` in ``press_steps`` increments, then slid by
        ``slide_mm`` (x, y, sensor frame, mm) in ``slide_steps`` increments."""
        if press_steps < 1 or slide_steps < 1:
            raise ValueError(f"press_steps and slide_steps must be >= 1, got {press_steps}, "
                             f"{slide_steps}")
        slide = np.asarray(slide_mm, np.float64)
        ut = np.zeros((len(self.contact_nodes), 2))   # tangential displacement after the last load
        loads = [(pose.model_copy(update={"depth_mm": pose.depth_mm * (j + 1) / press_steps}),
                  np.zeros(2)) for j in range(press_steps)]
        if np.any(slide != 0):
            for j in range(slide_steps):
                off = slide * (j + 1) / slide_steps
                loads.append((pose.model_copy(update={"x_mm": pose.x_mm + float(off[0]),
                                                      "y_mm": pose.y_mm + float(off[1])}),
                              slide / slide_steps))
        for p, move in loads:   # press_steps >= 1: at least one load
            delta = self.intrusion(indenter, p)
            ref = ut + move
            forces, stick = self.surface_forces_coulomb(delta[self.contact_nodes], ref)
            ut = self._tangential(forces)
        u = self.displacements_from_forces(forces)
        return self._coulomb_result(delta, forces, u, stick)

    def solve_intrusion(self, delta: np.ndarray) -> ContactResult:
        """Coulomb contact for an intrusion field ``delta`` (n_plane,) mm, one load step from rest."""
        delta = np.asarray(delta, dtype=np.float64)
        if delta.shape != (self.mesh.n_plane,):
            raise ValueError(f"delta must have shape ({self.mesh.n_plane},), got {delta.shape}")
        forces, stick = self.surface_forces_coulomb(delta[self.contact_nodes])
        return self._coulomb_result(delta, forces, self.displacements_from_forces(forces), stick)

    def _tangential(self, forces: np.ndarray) -> np.ndarray:
        """Tangential displacements (k, 2) mm of every contact node from forces (k, 3) at E = 1."""
        nz = np.flatnonzero(np.any(forces != 0, axis=1))
        if len(nz) == 0:
            return np.zeros((len(forces), 2))
        dofs = (nz[:, None] * 3 + np.arange(3)).ravel()
        u = self.compliance[:, dofs] @ forces[nz].ravel()
        return u.reshape(-1, 3)[:, :2]

    def surface_forces_coulomb(self, delta: np.ndarray, ref: np.ndarray | None = None
                               ) -> tuple[np.ndarray, np.ndarray]:
        """Forces (k, 3) N at E = 1 and stick flags (k,) for intrusions ``delta`` (k,) mm at
        ``contact_nodes`` and stick references ``ref`` (k, 2) mm (zero: from rest).

        Candidates as for frictionless contact (intrusion above minus the largest one), grown
        by every node found penetrating until none does.
        """
        forces, stick, self.last_iterations = coulomb_surface_forces(self.compliance, delta,
                                                                     float(self.material.mu), ref)
        return forces, stick

    def _coulomb_result(self, delta, forces, u, stick) -> ContactResult:
        res = self._result(delta, forces, u)
        mask = np.zeros(self.mesh.n_plane, bool)
        mask[self.contact_nodes] = stick
        return ContactResult(**{**res.__dict__, "stick_mask": mask & res.contact_mask})
