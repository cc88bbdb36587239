"""Linear-elastic stiffness of a linear-tetrahedron mesh (vectorised numpy assembly).

Small-strain isotropic elasticity, sigma = lambda tr(eps) I + 2 mu eps. For a linear tet the
shape-function gradients g_a (a = 0..3) are constant, and the element stiffness is

    K_e[a i, b j] = V_e (lambda g_a,i g_b,j + mu g_a,j g_b,i + mu delta_ij g_a . g_b).

Degrees of freedom are node-major: dof ``3 * node + c`` for component c in (x, y, z).
Units: vertices in mm, E in MPa -> K in N/mm.

:mod:`tactile_deploy.fem.elasticity_warp` assembles the same matrix with warp.fem integrands;
the two agree to round-off (tested).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def shape_gradients(vertices: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape-function gradients and volumes of linear tets.

    Returns ``(grads (m, 4, 3) 1/mm, volumes (m,) mm^3)``.
    """
    p = vertices[tets]
    J = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # (m,3,3)
    volumes = np.linalg.det(J) / 6.0
    Jinv = np.linalg.inv(J)  # rows: gradients of barycentric coordinates 1..3
    g123 = Jinv  # (m, 3, 3): g[a-1, :] = grad N_a
    g0 = -g123.sum(axis=1, keepdims=True)
    return np.concatenate([g0, g123], axis=1), volumes


def element_stiffness(grads: np.ndarray, volumes: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """Element stiffness matrices, (m, 12, 12) N/mm, dofs ordered (node a, component i)."""
    gg = np.einsum("mai,mbj->maibj", grads, grads)
    dot = np.einsum("mai,mbi->mab", grads, grads)
    eye = np.eye(3)
    ke = lam * gg + mu * gg.transpose(0, 1, 4, 3, 2)  # mu g_a,j g_b,i
    ke = ke + mu * dot[:, :, None, :, None] * eye[None, None, :, None, :]
    return (volumes[:, None, None, None, None] * ke).reshape(len(grads), 12, 12)


def lame_parameters(E_mpa: float, nu: float) -> tuple[float, float]:
    """(lambda, mu) in MPa from Young's modulus (MPa) and Poisson's ratio."""
    return E_mpa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), E_mpa / (2.0 * (1.0 + nu))


def _scatter_element_matrices(ke: np.ndarray, tets: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    dofs = (3 * np.asarray(tets)[:, :, None] + np.arange(3)[None, None, :]).reshape(-1, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    n = 3 * n_nodes
    K = sp.coo_matrix((ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    K.sum_duplicates()
    return K


def nodal_divergence_operator(vertices: np.ndarray, tets: np.ndarray):
    """Weak divergence onto nodes and the lumped nodal volumes.

    Returns ``(D (n, 3n) CSR mm^2, V (n,) mm^3)`` with ``D[a] . u = integral N_a div(u) dV`` and
    ``V[a] = integral N_a dV``, so ``(D u) / V`` is the volume-averaged dilatation at each node.
    """
    grads, volumes = shape_gradients(np.asarray(vertices, float), np.asarray(tets))
    tets = np.asarray(tets)
    n = len(vertices)
    m = len(tets)
    # Row: test node a; column: dof (b, i). Entry V_e / 4 * dN_b/dx_i, the same for every a.
    vals = np.broadcast_to((volumes[:, None, None, None] / 4.0) * grads[:, None, :, :], (m, 4, 4, 3))
    rows = np.repeat(tets[:, :, None, None], 4, axis=2).repeat(3, axis=3)
    cols = 3 * tets[:, None, :, None] + np.arange(3)[None, None, None, :]
    cols = np.broadcast_to(cols, rows.shape)
    D = sp.coo_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(n, 3 * n)).tocsr()
    V = np.zeros(n)
    np.add.at(V, tets.ravel(), np.repeat(volumes / 4.0, 4))
    return D, V


def assemble_stiffness_numpy(
    vertices: np.ndarray,
    tets: np.ndarray,
    E_mpa: float,
    nu: float,
    formulation: str = "standard",
) -> sp.csr_matrix:
    """Global stiffness K, (3n, 3n) CSR float64, N/mm.

    ``formulation``:

    * ``"standard"``: displacement-only linear tets. They lock volumetrically as nu -> 0.5
      (too stiff); see docs/fem.md for the measured error.
    * ``"nodal_pressure"``: the bulk term acts on the dilatation averaged over each node's
      patch (a mixed u-p formulation with continuous P1 pressure and lumped pressure mass,
      condensed): ``K = K_dev + kappa D' diag(1/V) D`` with ``kappa = lambda + 2 mu / 3``. It
      passes the same patch tests and does not lock.
    """
    lam, mu = lame_parameters(E_mpa, nu)
    vertices = np.asarray(vertices, float)
    grads, volumes = shape_gradients(vertices, np.asarray(tets))
    if formulation == "standard":
        return _scatter_element_matrices(element_stiffness(grads, volumes, lam, mu), tets, len(vertices))
    if formulation == "nodal_pressure":
        kappa = lam + 2.0 * mu / 3.0
        K_dev = _scatter_element_matrices(
            element_stiffness(grads, volumes, -2.0 * mu / 3.0, mu), tets, len(vertices)
        )
        D, V = nodal_divergence_operator(vertices, tets)
        K_vol = (D.T @ sp.diags(kappa / V) @ D).tocsr()
        return (K_dev + K_vol).tocsr()
    raise ValueError(f"formulation must be 'standard' or 'nodal_pressure', got {formulation!r}")


def assemble_stiffness(
    vertices: np.ndarray,
    tets: np.ndarray,
    E_mpa: float,
    nu: float,
    backend: str = "auto",
    formulation: str = "standard",
) -> sp.csr_matrix:
    """Global stiffness matrix with the chosen backend.

    ``backend``: ``"numpy"`` (vectorised, no extra dependency), ``"warp"`` (warp.fem integrands on
    the CPU or CUDA device), or ``"auto"`` (warp when importable, else numpy).
    """
    if backend == "numpy":
        return assemble_stiffness_numpy(vertices, tets, E_mpa, nu, formulation)
    if backend in ("warp", "auto"):
        try:
            import warp

            warp.config.log_level = warp.LOG_ERROR  # no banner or per-kernel load lines
            from tactile_deploy.fem.elasticity_warp import assemble_stiffness_warp
        except ImportError:
            if backend == "warp":
                raise
            return assemble_stiffness_numpy(vertices, tets, E_mpa, nu, formulation)
        return assemble_stiffness_warp(vertices, tets, E_mpa, nu, formulation=formulation)
    raise ValueError(f"backend must be 'auto', 'numpy' or 'warp', got {backend!r}")
