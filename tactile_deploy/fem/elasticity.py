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


def assemble_stiffness_numpy(
    vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float
) -> sp.csr_matrix:
    """Global stiffness K, (3n, 3n) CSR float64, N/mm."""
    lam = E_mpa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = E_mpa / (2.0 * (1.0 + nu))
    grads, volumes = shape_gradients(np.asarray(vertices, float), np.asarray(tets))
    ke = element_stiffness(grads, volumes, lam, mu)
    dofs = (3 * np.asarray(tets)[:, :, None] + np.arange(3)[None, None, :]).reshape(-1, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    n = 3 * len(vertices)
    K = sp.coo_matrix((ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    K.sum_duplicates()
    return K


def assemble_stiffness(
    vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float, backend: str = "auto"
) -> sp.csr_matrix:
    """Global stiffness matrix with the chosen backend.

    ``backend``: ``"numpy"`` (vectorised, no extra dependency), ``"warp"`` (warp.fem integrands on
    the CPU or CUDA device), or ``"auto"`` (warp when importable, else numpy).
    """
    if backend == "numpy":
        return assemble_stiffness_numpy(vertices, tets, E_mpa, nu)
    if backend in ("warp", "auto"):
        try:
            from tactile_deploy.fem.elasticity_warp import assemble_stiffness_warp
        except ImportError:
            if backend == "warp":
                raise
            return assemble_stiffness_numpy(vertices, tets, E_mpa, nu)
        return assemble_stiffness_warp(vertices, tets, E_mpa, nu)
    raise ValueError(f"backend must be 'auto', 'numpy' or 'warp', got {backend!r}")
