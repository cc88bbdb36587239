"""Compressible neo-Hookean gel on linear tets: energy, internal forces and tangent stiffness.

Strain energy (total Lagrangian; reference = rest mesh; mm, MPa, so energies in N mm)::

    Pi(u) = sum_t V_t mu/2 (J_t^(-2/3) I1_t - 3)  +  sum_n V_n kappa/2 (J_n - 1)^2

    F_t = I + sum_a u_a (x) g_a,  J_t = det F_t,  I1_t = tr(F_t' F_t)   (per tet t)
    J_n = v_n / V_n,  v_n = sum_(t ∋ n) V_t J_t / 4,  V_n = sum_(t ∋ n) V_t / 4   (per node n)

i.e. the continuum law ``W(F) = mu/2 (J^(-2/3) I1 - 3) + kappa/2 (J - 1)^2`` (shear modulus mu,
bulk modulus kappa = lambda + 2 mu / 3, both from E and nu) with the volumetric part evaluated on
the volume change of each node's patch (an averaged-nodal-pressure / F-bar-type formulation that
does not lock at nu -> 0.5). Its Hessian at u = 0 is exactly the locking-free ``nodal_pressure``
linear stiffness of :func:`tactile_deploy.fem.elasticity.assemble_stiffness_numpy`, so small-
strain linear elasticity (:class:`LinearGel`) is its small-strain limit.

Forces and tangent (first Piola stress P, H = F^-T)::

    P_dev = mu J^(-2/3) (F - I1/3 H),         f_a += V_t (P_dev + pbar_t J_t H) g_a,
    pbar_t = mean over the tet's nodes of kappa (J_n - 1)

    dP_dev/dF [ij, mn] = mu J^(-2/3) (d_im d_jn - 2/3 H_ij F_mn - 2/3 F_ij H_mn
                                      + 2/9 I1 H_ij H_mn + I1/3 H_in H_mj)
    K = sum_t V_t g' (dP_dev/dF + pbar_t J (H_ij H_mn - H_in H_mj)) g  +  B' diag(kappa / V_n) B,
    B[n, (b, m)] = dv_n / du_bm = sum_(t ∋ n, b) V_t / 4 J_t (H_t g_b)_m

Degrees of freedom are node-major (``3 * node + component``); displacements u (n, 3) mm.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from tactile_deploy.fem.elasticity import (
    assemble_stiffness_numpy,
    lame_parameters,
    shape_gradients,
)


class InvertedElementError(ValueError):
    """A displacement field inverts (J <= 0) at least one tet."""


def _scatter_pattern(tets: np.ndarray):
    dofs = (3 * tets[:, :, None] + np.arange(3)[None, None, :]).reshape(-1, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    return rows, cols


class NeoHookeanGel:
    """Neo-Hookean energy of ``vertices`` (n, 3) mm / ``tets`` (m, 4) at E (MPa) and nu."""

    model = "neo-hookean"

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float):
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.tets = np.ascontiguousarray(tets, np.int64)
        self.grads, self.volumes = shape_gradients(self.vertices, self.tets)
        lam, mu = lame_parameters(E_mpa, nu)
        self.mu = mu
        self.kappa = lam + 2.0 * mu / 3.0
        self.n_nodes = len(self.vertices)
        self.nodal_volumes = np.bincount(self.tets.ravel(), np.repeat(self.volumes / 4.0, 4),
                                         minlength=self.n_nodes)
        self._rows, self._cols = _scatter_pattern(self.tets)
        m = len(self.tets)
        # Pattern of B (node n of tet t, dof (b, c) of tet t).
        self._b_rows = np.broadcast_to(self.tets[:, :, None, None], (m, 4, 4, 3)).ravel()
        self._b_cols = np.broadcast_to(
            (3 * self.tets[:, None, :, None] + np.arange(3)[None, None, None, :]), (m, 4, 4, 3)
        ).ravel()

    def _assemble(self, ke: np.ndarray) -> sp.csr_matrix:
        """Sum element matrices (m, 12, 12) into the global CSR (pattern built once)."""
        if not hasattr(self, "_pattern"):
            n3 = 3 * self.n_nodes
            key = self._rows * n3 + self._cols
            uniq, inverse = np.unique(key, return_inverse=True)
            self._pattern = (uniq // n3, uniq % n3, inverse.ravel(), n3)
        rows, cols, inverse, n3 = self._pattern
        data = np.bincount(inverse, ke.ravel(), minlength=len(rows))
        return sp.csr_matrix((data, (rows, cols)), shape=(n3, n3))

    # ----------------------------------------------------------------------------- kinematics
    def _kinematics(self, u: np.ndarray):
        F = np.eye(3) + np.einsum("mai,maj->mij", u[self.tets], self.grads)
        J = np.linalg.det(F)
        if np.any(J <= 0.0) or not np.all(np.isfinite(J)):
            raise InvertedElementError(f"{int(np.sum(~(J > 0)))} tets inverted (J <= 0)")
        H = np.transpose(np.linalg.inv(F), (0, 2, 1))
        Jn = np.bincount(self.tets.ravel(), np.repeat(self.volumes * J / 4.0, 4),
                         minlength=self.n_nodes) / self.nodal_volumes
        return F, J, H, Jn

    def energy(self, u: np.ndarray) -> float:
        """Stored energy (N mm) of displacements u (n, 3) mm; +inf if a tet inverts."""
        try:
            F, J, _, Jn = self._kinematics(np.asarray(u, np.float64))
        except InvertedElementError:
            return np.inf
        i1 = np.einsum("mij,mij->m", F, F)
        w_dev = 0.5 * self.mu * (J ** (-2.0 / 3.0) * i1 - 3.0)
        return float(self.volumes @ w_dev + 0.5 * self.kappa * self.nodal_volumes @ (Jn - 1.0) ** 2)

    def forces(self, u: np.ndarray) -> np.ndarray:
        """Internal forces dPi/du, (n, 3) N."""
        F, J, H, Jn = self._kinematics(np.asarray(u, np.float64))
        return self._forces(F, J, H, Jn)

    def _forces(self, F, J, H, Jn):
        i1 = np.einsum("mij,mij->m", F, F)
        P = self.mu * (J ** (-2.0 / 3.0))[:, None, None] * (F - (i1 / 3.0)[:, None, None] * H)
        pbar = (self.kappa * (Jn - 1.0))[self.tets].mean(axis=1)
        P = P + (pbar * J)[:, None, None] * H
        fe = self.volumes[:, None, None] * np.einsum("mij,maj->mai", P, self.grads)
        out = np.zeros((self.n_nodes, 3))
        for c in range(3):
            out[:, c] = np.bincount(self.tets.ravel(), fe[:, :, c].ravel(), minlength=self.n_nodes)
        return out

    def forces_and_stiffness(self, u: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        """Internal forces (n, 3) N and tangent stiffness (3n, 3n) CSR N/mm at u (n, 3) mm."""
        F, J, H, Jn = self._kinematics(np.asarray(u, np.float64))
        f = self._forces(F, J, H, Jn)
        i1 = np.einsum("mij,mij->m", F, F)
        c = self.mu * J ** (-2.0 / 3.0)
        pbar = (self.kappa * (Jn - 1.0))[self.tets].mean(axis=1)
        pJ = pbar * J
        hg = np.einsum("tij,taj->tai", H, self.grads)  # (m, 4, 3): H g_a
        fg = np.einsum("tij,taj->tai", F, self.grads)  # F g_a
        gg = np.einsum("taj,tbj->tab", self.grads, self.grads)

        def outer(x, y):  # (m, 4, 3) x (m, 4, 3) -> (m, 4, 3, 4, 3): x_ai y_bm
            return x[:, :, :, None, None] * y[:, None, None, :, :]

        s = lambda v: v[:, None, None, None, None]  # noqa: E731
        ke = s(c) * gg[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
        ke += s(-2.0 / 3.0 * c) * (outer(hg, fg) + outer(fg, hg))
        ke += s(2.0 / 9.0 * c * i1 + pJ) * outer(hg, hg)
        ke += s(c * i1 / 3.0 - pJ) * np.transpose(outer(hg, hg), (0, 3, 2, 1, 4))
        ke *= s(self.volumes)
        K = self._assemble(ke)
        # Volumetric coupling through the nodal volumes: B' diag(kappa / V_n) B.
        vals = ((self.volumes * J / 4.0)[:, None, None, None] * hg[:, None, :, :])
        vals = np.broadcast_to(vals, (len(self.tets), 4, 4, 3)).ravel()
        B = sp.coo_matrix((vals, (self._b_rows, self._b_cols)),
                          shape=(self.n_nodes, 3 * self.n_nodes)).tocsr()
        K = K + B.T @ sp.diags(self.kappa / self.nodal_volumes) @ B
        return f, K.tocsr()


class LinearGel:
    """Small-strain linear elasticity with the same locking-free ``nodal_pressure`` stiffness:
    the small-strain limit of :class:`NeoHookeanGel` (``Pi = 1/2 u' K u``)."""

    model = "linear"

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float):
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.tets = np.ascontiguousarray(tets, np.int64)
        self.n_nodes = len(self.vertices)
        self.K = assemble_stiffness_numpy(self.vertices, self.tets, E_mpa, nu, "nodal_pressure")

    def energy(self, u: np.ndarray) -> float:
        x = np.asarray(u, np.float64).ravel()
        return float(0.5 * x @ (self.K @ x))

    def forces(self, u: np.ndarray) -> np.ndarray:
        return (self.K @ np.asarray(u, np.float64).ravel()).reshape(-1, 3)

    def forces_and_stiffness(self, u: np.ndarray):
        return self.forces(u), self.K


def gel_model(name: str, vertices, tets, E_mpa: float, nu: float):
    """``"neo-hookean"`` -> :class:`NeoHookeanGel`, ``"linear"`` -> :class:`LinearGel`."""
    if name == "neo-hookean":
        return NeoHookeanGel(vertices, tets, E_mpa, nu)
    if name == "linear":
        return LinearGel(vertices, tets, E_mpa, nu)
    raise ValueError(f"model must be 'neo-hookean' or 'linear', got {name!r}")
