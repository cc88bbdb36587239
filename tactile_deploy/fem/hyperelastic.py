"""Compressible neo-Hookean gel on linear tets: energy, internal forces and tangent stiffness.

Strain energy (total Lagrangian; reference = rest mesh; mm, MPa, so energies in N mm)::

    Pi(u) = sum_t V_t mu/2 (J_t^(-2/3) I1_t - 3)  +  sum_n V_n kappa/2 (J_n - 1)^2
            (+ the collapse barrier of tets with J_t < 0.5, below)

    F_t = I + sum_a u_a (x) g_a,  J_t = det F_t,  I1_t = tr(F_t' F_t)   (per tet t)
    J_n = v_n / V_n,  v_n = sum_(t ∋ n) V_t J_t / 4,  V_n = sum_(t ∋ n) V_t / 4   (per node n)

i.e. the continuum law ``W(F) = mu/2 (J^(-2/3) I1 - 3) + kappa/2 (J - 1)^2`` (shear modulus mu,
bulk modulus kappa = lambda + 2 mu / 3, both from E and nu) with the volumetric part evaluated on
the volume change of each node's patch (an averaged-nodal-pressure / F-bar-type formulation that
does not lock at nu -> 0.5). Its Hessian at u = 0 is exactly the locking-free ``nodal_pressure``
linear stiffness of :func:`tactile_deploy.fem.elasticity.assemble_stiffness_numpy`, so small-
strain linear elasticity (:class:`LinearGel`) is its small-strain limit.

Collapse barrier. Averaged over a node's patch, the volume change of one tet costs next to
nothing when its neighbours make up for it, so a tet can collapse while every J_n stays near 1 (a
spurious mode of nodal-pressure formulations). Below a sharp tip it does: under the 90-degree
cone pressed into the GelSlim pad (nu 0.45) tets below the apex were crushed to J < 0 at 0.46 of
0.8 mm, and the solve stopped. Each tet therefore also carries::

    V_t kappa J0^2 b(J_t / J0),  b(s) = s - 1 - ln s - (s - 1)^2 / 2 for s < 1, 0 for s >= 1

(J0 = :data:`COLLAPSE_BARRIER_J` = 0.5): zero with its first two derivatives at J0 and above, so
the law is unchanged wherever every tet keeps half its volume (the closed-form compression to
40 % strain, J 0.6, and the small-strain limit: exact), and infinite as J_t -> 0. Its pressure
kappa J0 (2 - s - 1/s) joins pbar_t below; its curvature adds
V_t kappa (1/s^2 - 1) J_t^2 (H g_a)(H g_b)' to the tangent. On that cone 35 of 27,248 tets end below
J0 (smallest J 0.11), holding 0.06 % of the stored energy.

Forces and tangent (first Piola stress P, H = F^-T)::

    P_dev = mu J^(-2/3) (F - I1/3 H),         f_a += V_t (P_dev + pbar_t J_t H) g_a,
    pbar_t = mean over the tet's nodes of kappa (J_n - 1)

    dP_dev/dF [ij, mn] = mu J^(-2/3) (d_im d_jn - 2/3 H_ij F_mn - 2/3 F_ij H_mn
                                      + 2/9 I1 H_ij H_mn + I1/3 H_in H_mj)
    K = sum_t V_t g' (dP_dev/dF + pbar_t J (H_ij H_mn - H_in H_mj)) g  +  B' diag(kappa / V_n) B,
    B[n, (b, m)] = dv_n / du_bm = sum_(t ∋ n, b) V_t / 4 J_t (H_t g_b)_m

Deviatoric part on faces (``deviatoric="face"``, the resolved solver's choice). Constant-strain
tets are too stiff in shear: on the graded truth meshes the force of a sphere pressed into the
bonded layer came out 4-5 % above a converged quadratic FEM. With ``"face"`` the deviatoric
energy is integrated over face-based smoothing cells instead of tets (the face-based smoothed
FEM, FS-FEM-T4: Nguyen-Thoi, Liu, Lam, Zhang 2009, Int. J. Numer. Meth. Eng. 78:324)::

    sum_f V_f mu/2 (J_f^(-2/3) I1_f - 3),   F_f = (V_1 F_1 + V_2 F_2) / (V_1 + V_2)

for every face f shared by tets 1 and 2 (V_f = (V_1 + V_2) / 4; a boundary face: its one tet,
V_f = V_1 / 4), so the cells tile the mesh. F_f depends on the face's 3 nodes and the two
opposite vertices (5 "slots", gradients G_f (5, 3)); a homogeneous deformation is still
represented exactly (patch tests hold), and the smoothed gradient removes most of the tets'
excess shear stiffness. The volumetric part stays on the nodal patches above. The formulas
above hold cell by cell with (g, V_t, F_t) -> (G_f, V_f, F_f) for the deviatoric terms.

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


#: Tets whose volume ratio J falls below this carry the collapse barrier (module docstring).
COLLAPSE_BARRIER_J = 0.5


class InvertedElementError(ValueError):
    """A displacement field inverts (J <= 0) at least one tet."""


def _scatter_pattern(nodes: np.ndarray):
    """Global (row, col) of every entry of cell matrices (c, 3k, 3k) of cells ``nodes`` (c, k)."""
    k = 3 * nodes.shape[1]
    dofs = (3 * nodes[:, :, None] + np.arange(3)[None, None, :]).reshape(-1, k)
    rows = np.repeat(dofs, k, axis=1).ravel()
    cols = np.tile(dofs, (1, k)).ravel()
    return rows, cols


def face_cells(tets: np.ndarray, grads: np.ndarray, volumes: np.ndarray):
    """Face-based smoothing cells of a tet mesh: (nodes (f, 5), G (f, 5, 3) 1/mm, V (f,) mm^3).

    One cell per face: slots 0-2 its nodes, 3 and 4 the vertices opposite it in its two tets
    (a boundary face: slot 4 repeats slot 3 with a zero gradient). ``G`` are the gradients of
    the smoothed deformation ``F_f = I + sum_a u_a (x) G_a`` (volume-weighted mean of the two
    tets' gradients), ``V`` the cells' volumes (a quarter of each adjacent tet)."""
    tets = np.asarray(tets, np.int64)
    m = len(tets)
    local = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])  # face k: opposite vertex k
    loc = np.broadcast_to(local, (m, 4, 3))
    glob = tets[:, local]  # (m, 4, 3)
    order = np.argsort(glob, axis=2)
    glob = np.take_along_axis(glob, order, 2).reshape(-1, 3)
    loc = np.take_along_axis(loc, order, 2).reshape(-1, 3)
    _, inverse, count = np.unique(glob, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if count.max() > 2:
        raise ValueError(f"a face is shared by {int(count.max())} tets (a valid mesh has at most 2)")
    by_face = np.argsort(inverse, kind="stable")
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    h1 = by_face[start]  # half-faces (tet * 4 + k)
    h2 = np.where(count == 2, by_face[np.minimum(start + 1, len(by_face) - 1)], h1)
    t1, k1, t2, k2 = h1 // 4, h1 % 4, h2 // 4, h2 % 4
    inner = count == 2
    v1, v2 = volumes[t1], np.where(inner, volumes[t2], 0.0)
    w1, w2 = v1 / (v1 + v2), v2 / (v1 + v2)
    G = np.empty((len(count), 5, 3))
    G[:, :3] = (w1[:, None, None] * grads[t1[:, None], loc[h1]]
                + w2[:, None, None] * grads[t2[:, None], loc[h2]])
    G[:, 3] = w1[:, None] * grads[t1, k1]
    G[:, 4] = w2[:, None] * grads[t2, k2]
    nodes = np.concatenate([glob[h1], tets[t1, k1][:, None], tets[t2, k2][:, None]], axis=1)
    return nodes, G, 0.25 * (v1 + v2)


class NeoHookeanGel:
    """Neo-Hookean energy of ``vertices`` (n, 3) mm / ``tets`` (m, 4) at E (MPa) and nu.

    ``deviatoric``: ``"element"`` (the deviatoric energy per tet) or ``"face"`` (per face-based
    smoothing cell, module docstring); the volumetric energy is per node either way."""

    model = "neo-hookean"

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float,
                 deviatoric: str = "element"):
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.tets = np.ascontiguousarray(tets, np.int64)
        self.grads, self.volumes = shape_gradients(self.vertices, self.tets)
        if deviatoric == "element":
            self.cell_nodes, self.cell_grads, self.cell_volumes = self.tets, self.grads, self.volumes
        elif deviatoric == "face":
            self.cell_nodes, self.cell_grads, self.cell_volumes = face_cells(
                self.tets, self.grads, self.volumes)
        else:
            raise ValueError(f"deviatoric must be 'element' or 'face', got {deviatoric!r}")
        self.deviatoric = deviatoric
        lam, mu = lame_parameters(E_mpa, nu)
        self.mu = mu
        self.kappa = lam + 2.0 * mu / 3.0
        self.n_nodes = len(self.vertices)
        self.nodal_volumes = np.bincount(self.tets.ravel(), np.repeat(self.volumes / 4.0, 4),
                                         minlength=self.n_nodes)
        m = len(self.tets)
        # Pattern of B (node n of tet t, dof (b, c) of tet t).
        self._b_rows = np.broadcast_to(self.tets[:, :, None, None], (m, 4, 4, 3)).ravel()
        self._b_cols = np.broadcast_to(
            (3 * self.tets[:, None, :, None] + np.arange(3)[None, None, None, :]), (m, 4, 4, 3)
        ).ravel()
        self._patterns = {}

    def _assemble(self, ke: np.ndarray, nodes: np.ndarray) -> sp.csr_matrix:
        """Sum cell matrices (c, 3k, 3k) of cells with ``nodes`` (c, k) into the global CSR
        (each pattern built once: its entries sorted by row, then column, are CSR's order)."""
        key_ = nodes.shape[1]
        n3 = 3 * self.n_nodes
        if key_ not in self._patterns:
            rows, cols = _scatter_pattern(nodes)
            uniq, inverse = np.unique(rows * n3 + cols, return_inverse=True)
            indptr = np.searchsorted(uniq // n3, np.arange(n3 + 1))
            self._patterns[key_] = (uniq % n3, indptr, inverse.ravel())
        indices, indptr, inverse = self._patterns[key_]
        data = np.bincount(inverse, ke.ravel(), minlength=len(indices))
        return sp.csr_matrix((data, indices, indptr), shape=(n3, n3))

    # ----------------------------------------------------------------------------- kinematics
    def _kinematics(self, u: np.ndarray):
        """Per tet: F, J, H = F^-T; per node: J_n; per deviatoric cell: F_c, J_c, H_c."""
        F = np.eye(3) + np.einsum("mai,maj->mij", u[self.tets], self.grads)
        J, H = _determinant_and_inverse_transpose(F, "tets")
        Jn = np.bincount(self.tets.ravel(), np.repeat(self.volumes * J / 4.0, 4),
                         minlength=self.n_nodes) / self.nodal_volumes
        if self.deviatoric == "element":
            return F, J, H, Jn, (F, J, H)
        Fc = np.eye(3) + np.einsum("mai,maj->mij", u[self.cell_nodes], self.cell_grads)
        Jc, Hc = _determinant_and_inverse_transpose(Fc, "face cells")
        return F, J, H, Jn, (Fc, Jc, Hc)

    def _barrier(self, J: np.ndarray, order: int) -> np.ndarray:
        """The collapse barrier of tets with J (m,) below :data:`COLLAPSE_BARRIER_J` (module
        docstring): its energy density (MPa), first or second derivative in J (``order`` 0, 1, 2)."""
        j0 = COLLAPSE_BARRIER_J
        s = np.minimum(J / j0, 1.0)
        c = self.kappa * j0**2
        if order == 0:
            return c * (s - 1.0 - np.log(s) - 0.5 * (s - 1.0) ** 2)
        if order == 1:
            return c / j0 * (2.0 - s - 1.0 / s)
        return c / j0**2 * (1.0 / s**2 - 1.0)

    def energy(self, u: np.ndarray) -> float:
        """Stored energy (N mm) of displacements u (n, 3) mm; +inf if a tet inverts."""
        try:
            _, J, _, Jn, (Fc, Jc, _) = self._kinematics(np.asarray(u, np.float64))
        except InvertedElementError:
            return np.inf
        i1 = np.einsum("mij,mij->m", Fc, Fc)
        w_dev = 0.5 * self.mu * (Jc ** (-2.0 / 3.0) * i1 - 3.0)
        return float(self.cell_volumes @ w_dev
                     + 0.5 * self.kappa * self.nodal_volumes @ (Jn - 1.0) ** 2
                     + self.volumes @ self._barrier(J, 0))

    def forces(self, u: np.ndarray) -> np.ndarray:
        """Internal forces dPi/du, (n, 3) N."""
        return self._forces(*self._kinematics(np.asarray(u, np.float64)))

    def _scatter_forces(self, fe: np.ndarray, nodes: np.ndarray, out: np.ndarray) -> None:
        for c in range(3):
            out[:, c] += np.bincount(nodes.ravel(), fe[:, :, c].ravel(), minlength=self.n_nodes)

    def _forces(self, F, J, H, Jn, cell):
        Fc, Jc, Hc = cell
        i1 = np.einsum("mij,mij->m", Fc, Fc)
        P = self.mu * (Jc ** (-2.0 / 3.0))[:, None, None] * (Fc - (i1 / 3.0)[:, None, None] * Hc)
        out = np.zeros((self.n_nodes, 3))
        fe = self.cell_volumes[:, None, None] * np.einsum("mij,maj->mai", P, self.cell_grads)
        self._scatter_forces(fe, self.cell_nodes, out)
        pbar = (self.kappa * (Jn - 1.0))[self.tets].mean(axis=1) + self._barrier(J, 1)
        P = (pbar * J)[:, None, None] * H
        fe = self.volumes[:, None, None] * np.einsum("mij,maj->mai", P, self.grads)
        self._scatter_forces(fe, self.tets, out)
        return out

    def forces_and_stiffness(self, u: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        """Internal forces (n, 3) N and tangent stiffness (3n, 3n) CSR N/mm at u (n, 3) mm."""
        F, J, H, Jn, cell = self._kinematics(np.asarray(u, np.float64))
        f = self._forces(F, J, H, Jn, cell)
        # deviatoric, per cell (k slots): entries [a i, b m] of the formulas in the docstring
        Fc, Jc, Hc = cell
        g = self.cell_grads
        m, k = g.shape[:2]
        i1 = np.einsum("mij,mij->m", Fc, Fc)
        c = self.mu * Jc ** (-2.0 / 3.0)
        hg = (g @ Hc.transpose(0, 2, 1)).reshape(m, 3 * k)  # H g_a, flattened (a, i)
        fg = (g @ Fc.transpose(0, 2, 1)).reshape(m, 3 * k)  # F g_a
        hh = hg[:, :, None] * hg[:, None, :]  # (m, 3k, 3k): (H g_a)_i (H g_b)_m
        hf = hg[:, :, None] * fg[:, None, :]
        ke = _per_cell(2.0 / 9.0 * c * i1) * hh
        ke -= _per_cell(2.0 / 3.0 * c) * (hf + hf.transpose(0, 2, 1))
        ke += _per_cell(c * i1 / 3.0) * _swap_components(hh, k)
        ke5 = ke.reshape(m, k, 3, k, 3)
        cgg = _per_cell(c) * (g @ g.transpose(0, 2, 1))  # c g_a . g_b
        for d in range(3):
            ke5[:, :, d, :, d] += cgg
        ke *= _per_cell(self.cell_volumes)
        K = self._assemble(ke, self.cell_nodes)
        # volumetric, per tet: the pressure's geometric term and the barrier's curvature ...
        pbar = (self.kappa * (Jn - 1.0))[self.tets].mean(axis=1) + self._barrier(J, 1)
        hg = self.grads @ H.transpose(0, 2, 1)  # (m, 4, 3): H g_a
        hgf = hg.reshape(len(self.tets), 12)
        hh = hgf[:, :, None] * hgf[:, None, :]
        ke = _per_cell(pbar * J * self.volumes) * (hh - _swap_components(hh, 4))
        ke += _per_cell(self._barrier(J, 2) * J**2 * self.volumes) * hh
        K = K + self._assemble(ke, self.tets)
        # ... and the coupling through the nodal volumes: B' diag(kappa / V_n) B.
        vals = ((self.volumes * J / 4.0)[:, None, None, None] * hg[:, None, :, :])
        vals = np.broadcast_to(vals, (len(self.tets), 4, 4, 3)).ravel()
        B = sp.coo_matrix((vals, (self._b_rows, self._b_cols)),
                          shape=(self.n_nodes, 3 * self.n_nodes)).tocsr()
        K = K + B.T @ sp.diags(self.kappa / self.nodal_volumes) @ B
        return f, K.tocsr()


def _per_cell(values: np.ndarray) -> np.ndarray:
    """(m,) -> (m, 1, 1): a factor per cell matrix."""
    return values[:, None, None]


def _swap_components(block: np.ndarray, k: int) -> np.ndarray:
    """Cell matrices (m, 3k, 3k) with entries [a i, b m] -> [a m, b i] (the two components
    exchanged between the slots a and b)."""
    m = len(block)
    return block.reshape(m, k, 3, k, 3).transpose(0, 1, 4, 3, 2).reshape(m, 3 * k, 3 * k)


def _determinant_and_inverse_transpose(F: np.ndarray, what: str):
    """det F (m,) and F^-T (m, 3, 3) of 3 x 3 matrices F (m, 3, 3), by cofactors (row i of the
    cofactor matrix is row i+1 x row i+2 of F, and F^-T = cofactors / det). Raises
    :class:`InvertedElementError` naming ``what`` where det F <= 0 (or is not finite)."""
    a, b, c = F[:, 0], F[:, 1], F[:, 2]
    cof = np.empty_like(F)
    cof[:, 0] = np.cross(b, c)
    cof[:, 1] = np.cross(c, a)
    cof[:, 2] = np.cross(a, b)
    det = np.einsum("mj,mj->m", a, cof[:, 0])
    if np.any(det <= 0.0) or not np.all(np.isfinite(det)):
        raise InvertedElementError(f"{int(np.sum(~(det > 0)))} {what} inverted (J <= 0)")
    return det, cof / det[:, None, None]


class LinearGel:
    """Small-strain linear elasticity, the small-strain limit of :class:`NeoHookeanGel` with
    the same ``deviatoric`` integration (``Pi = 1/2 u' K u``): for ``"element"`` the locking-free
    ``nodal_pressure`` stiffness of :mod:`tactile_deploy.fem.elasticity`, for ``"face"`` the
    neo-Hookean tangent at u = 0."""

    model = "linear"

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float,
                 deviatoric: str = "element"):
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.tets = np.ascontiguousarray(tets, np.int64)
        self.n_nodes = len(self.vertices)
        if deviatoric == "element":
            self.K = assemble_stiffness_numpy(self.vertices, self.tets, E_mpa, nu,
                                              "nodal_pressure")
        else:
            gel = NeoHookeanGel(self.vertices, self.tets, E_mpa, nu, deviatoric)
            self.K = gel.forces_and_stiffness(np.zeros_like(self.vertices))[1]

    def energy(self, u: np.ndarray) -> float:
        x = np.asarray(u, np.float64).ravel()
        return float(0.5 * x @ (self.K @ x))

    def forces(self, u: np.ndarray) -> np.ndarray:
        return (self.K @ np.asarray(u, np.float64).ravel()).reshape(-1, 3)

    def forces_and_stiffness(self, u: np.ndarray):
        return self.forces(u), self.K


def gel_model(name: str, vertices, tets, E_mpa: float, nu: float, deviatoric: str = "element"):
    """``"neo-hookean"`` -> :class:`NeoHookeanGel`, ``"linear"`` -> :class:`LinearGel`, with
    the deviatoric energy integrated per tet (``"element"``) or per face cell (``"face"``)."""
    if name == "neo-hookean":
        return NeoHookeanGel(vertices, tets, E_mpa, nu, deviatoric)
    if name == "linear":
        return LinearGel(vertices, tets, E_mpa, nu, deviatoric)
    raise ValueError(f"model must be 'neo-hookean' or 'linear', got {name!r}")
