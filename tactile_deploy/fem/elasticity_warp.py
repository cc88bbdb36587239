"""Linear-elastic stiffness of a linear-tetrahedron mesh, assembled with warp.fem integrands.

Small-strain isotropic elasticity on the pad volume Omega (mm), displacement u in mm:

    a(u, v) = int_Omega  lambda div(u) div(v) + 2 mu eps(u) : eps(v)  dV,
    eps(u) = (grad u + grad u^T) / 2,

with the Lame parameters lambda = E nu / ((1 + nu)(1 - 2 nu)) and mu = E / (2 (1 + nu)) in MPa
(= N/mm^2), so K is in N/mm. Displacements live in the vector-valued P1 space of a ``fem.Tetmesh``;
the bilinear form is integrated to a 3x3-block BSR matrix and returned as a scipy CSR matrix in
the same node-major DOF order as :func:`tactile_deploy.fem.elasticity.assemble_stiffness_numpy`
(dof ``3 * node + c`` for component c in (x, y, z)); the two agree to round-off.

Node numbering: warp's P1 space on a Tetmesh has one node per vertex, and node ``i`` is vertex
``i`` (``TetmeshSpaceTopology.element_node_index`` returns ``tet_vertex_indices[cell][k]``), so
block row ``i`` of warp's matrix is already our node ``i`` and no permutation is needed. The test
suite checks this against the space's node positions.

Precision: float64 throughout (``wp.vec3d`` positions, ``wp.float64`` Lame parameters and
output).

Kernels: the kernels are compiled on first use per device (warp prints a "Module ... load"
line for each unless ``warp.config.quiet`` is set) and kept in warp's kernel cache
(``~/.cache/warp/<version>``, or ``$WARP_CACHE_PATH``); later processes load them from there, and
a new mesh, E or nu reuses them. Measured for the 5,380-node, 24,444-tet pad: on a 2-core CPU,
~14 s with an empty kernel cache, 0.6 s for the first call of a process with a filled cache and
0.35 s after that (``import warp`` costs another ~1.4 s); on an H100 (``device="cuda:0"``), 8 s
cold and 17 ms warm. Both devices agree with the numpy assembly to 6e-16 relative.

This module imports warp at import time; import it lazily (see
:func:`tactile_deploy.fem.elasticity.assemble_stiffness`) so that ``tactile_deploy`` runs without
warp installed.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import warp as wp
import warp.fem as fem

# Assembly needs no adjoint kernels; not generating them makes the cold compile of the integrand
# and dispatch kernels about 4x faster.
_KERNEL_OPTIONS = {"enable_backward": False}


@fem.integrand
def elasticity_form(s: fem.Sample, u: fem.Field, v: fem.Field, lame: wp.vec2d):
    """lambda div(u) div(v) + 2 mu eps(u) : eps(v), with lame = (lambda, mu) in MPa."""
    return lame[0] * fem.div(u, s) * fem.div(v, s) + wp.float64(2.0) * lame[1] * wp.ddot(
        fem.D(u, s), fem.D(v, s)
    )


@fem.integrand
def divergence_form(s: fem.Sample, u: fem.Field, q: fem.Field):
    """q div(u): weak divergence of a P1 displacement onto P1 nodal (pressure) functions."""
    return q(s) * fem.div(u, s)


@fem.integrand
def volume_form(s: fem.Sample, q: fem.Field):
    """q: integrated, the lumped nodal volumes V_a = int N_a dV."""
    return q(s)


def _check_inputs(
    vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float
) -> tuple[np.ndarray, np.ndarray]:
    """Convert and validate; returns ``(vertices (n, 3) float64 mm, tets (m, 4) int32)``."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"vertices must have shape (n, 3) with n > 0, got {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("vertices contain NaN or inf")
    tets_in = np.asarray(tets)
    if tets_in.ndim != 2 or tets_in.shape[1] != 4 or len(tets_in) == 0:
        raise ValueError(f"tets must have shape (m, 4) with m > 0, got {tets_in.shape}")
    if not np.issubdtype(tets_in.dtype, np.integer):
        raise ValueError(f"tets must be integer vertex indices, got dtype {tets_in.dtype}")
    if tets_in.min() < 0 or tets_in.max() >= len(vertices):
        raise ValueError(
            f"tets index vertices outside [0, {len(vertices)}): "
            f"min {tets_in.min()}, max {tets_in.max()}"
        )
    tets_i32 = np.ascontiguousarray(tets_in, dtype=np.int32)
    if not (np.isfinite(E_mpa) and E_mpa > 0.0):
        raise ValueError(f"E_mpa must be a positive finite modulus in MPa, got {E_mpa}")
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"nu must lie in (-1, 0.5), got {nu}")
    # warp.fem integrates with |det J|, the numpy reference with the signed volume; both are the
    # same (and physical) only for positively oriented tets.
    p = vertices[tets_i32]
    e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    signed6 = np.einsum("mi,mi->m", e1, np.cross(e2, e3))  # 6 x signed volume, mm^3
    bad = np.flatnonzero(~(signed6 > 0.0))
    if len(bad):
        raise ValueError(
            f"{len(bad)} tets are inverted or degenerate (signed volume <= 0), "
            f"first {bad[:5].tolist()}; tets must be positively oriented"
        )
    return vertices, tets_i32


def assemble_stiffness_warp(
    vertices: np.ndarray,
    tets: np.ndarray,
    E_mpa: float,
    nu: float,
    device: str | None = None,
    formulation: str = "standard",
) -> sp.csr_matrix:
    """Global stiffness K of a linear-tet mesh, assembled with warp.fem.

    ``formulation="nodal_pressure"`` assembles ``K_dev + kappa D' diag(1/V) D`` instead (see
    :func:`tactile_deploy.fem.elasticity.assemble_stiffness_numpy`): the deviatoric part is the
    same elasticity form with lambda = -2 mu / 3, ``D`` the mixed form ``q div(u)`` between the
    vector P1 space and a scalar P1 space, ``V`` the integral of each scalar basis function.

    Parameters
    ----------
    vertices : (n, 3) float64, mm
        Node positions (any frame).
    tets : (m, 4) int
        Vertex indices of each tet, positively oriented (the layout of ``PadMesh.tets``).
    E_mpa : float, MPa
        Young's modulus.
    nu : float
        Poisson's ratio, in (-1, 0.5).
    device : str or None
        Warp device, e.g. ``"cpu"`` or ``"cuda:0"``; ``None`` is warp's default device (the
        first CUDA device when warp sees one, else the CPU).

    Returns
    -------
    K : (3n, 3n) scipy.sparse.csr_matrix, float64, N/mm
        Node-major DOFs, ``3 * node + c``; sorted column indices; same sparsity and values as
        :func:`tactile_deploy.fem.elasticity.assemble_stiffness_numpy` to round-off.
    """
    if formulation not in ("standard", "nodal_pressure"):
        raise ValueError(f"formulation must be 'standard' or 'nodal_pressure', got {formulation!r}")
    vertices, tets_i32 = _check_inputs(vertices, tets, E_mpa, nu)
    lam = E_mpa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = E_mpa / (2.0 * (1.0 + nu))
    kappa = lam + 2.0 * mu / 3.0
    if formulation == "nodal_pressure":
        lam = -2.0 * mu / 3.0  # deviatoric part; the bulk term is added below
    n = len(vertices)

    device = wp.get_device(device)
    with wp.ScopedDevice(device):
        geo = fem.Tetmesh(
            tet_vertex_indices=wp.array(tets_i32, dtype=int),
            positions=wp.array(vertices, dtype=wp.vec3d),
        )
        space = fem.make_polynomial_space(geo, degree=1, dtype=wp.vec3d)
        cells = fem.Cells(geo)
        # P1 strains are constant per tet: the one-point rule integrates the form exactly.
        quadrature = fem.RegularQuadrature(cells, order=0)
        u = fem.make_trial(space, domain=cells)
        v = fem.make_test(space, domain=cells)
        K_bsr = fem.integrate(
            elasticity_form,
            quadrature=quadrature,
            fields={"u": u, "v": v},
            values={"lame": wp.vec2d(lam, mu)},
            output_dtype=wp.float64,
            kernel_options=_KERNEL_OPTIONS,
            device=device,
        )
        nnz = K_bsr.nnz_sync()
        indptr = K_bsr.offsets.numpy()[: n + 1]
        indices = K_bsr.columns.numpy()[:nnz]
        blocks = K_bsr.values.numpy()[:nnz]
        if formulation == "nodal_pressure":
            scalar = fem.make_polynomial_space(geo, degree=1, dtype=wp.float64)
            q = fem.make_test(scalar, domain=cells)
            linear = fem.RegularQuadrature(cells, order=1)  # q div(u) is linear: exact
            D_bsr = fem.integrate(
                divergence_form,
                quadrature=linear,
                fields={"u": u, "q": q},
                output_dtype=wp.float64,
                kernel_options=_KERNEL_OPTIONS,
                device=device,
            )
            V = fem.integrate(
                volume_form,
                quadrature=linear,
                fields={"q": q},
                output_dtype=wp.float64,
                kernel_options=_KERNEL_OPTIONS,
                device=device,
            ).numpy()
            d_nnz = D_bsr.nnz_sync()
            D = sp.bsr_matrix(
                (
                    D_bsr.values.numpy()[:d_nnz].reshape(d_nnz, 1, 3).astype(np.float64),
                    D_bsr.columns.numpy()[:d_nnz],
                    D_bsr.offsets.numpy()[: n + 1],
                ),
                shape=(n, 3 * n),
            ).tocsr()

    if K_bsr.nrow != n or K_bsr.ncol != n or blocks.shape[1:] != (3, 3):
        raise RuntimeError(
            f"warp.fem returned a {K_bsr.nrow}x{K_bsr.ncol} matrix of {blocks.shape[1:]} blocks "
            f"for {n} vertices; expected {n}x{n} of (3, 3)"
        )
    # Block (test node a, trial node b) holds entry [i, j] = a(phi_b e_j, phi_a e_i)
    # = K[3a + i, 3b + j]: a BSR matrix of 3x3 blocks is exactly our node-major layout.
    K = sp.bsr_matrix(
        (blocks.astype(np.float64, copy=False), indices, indptr), shape=(3 * n, 3 * n)
    ).tocsr()
    if formulation == "nodal_pressure":
        K = (K + D.T @ sp.diags(kappa / V) @ D).tocsr()
    K.sort_indices()
    return K
