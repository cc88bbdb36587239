"""warp.fem stiffness assembly against the vectorised numpy assembly and closed-form checks.

Units: mm, MPa, N/mm. The first run in a process with an empty warp kernel cache compiles the
warp.fem kernels (15-30 s on a 2-core CPU); later runs load them from the cache.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("warp")

from tactile_deploy.fem.elasticity import assemble_stiffness, assemble_stiffness_numpy  # noqa: E402
from tactile_deploy.fem.elasticity_warp import assemble_stiffness_warp  # noqa: E402
from tactile_deploy.pad.asset import load_pad  # noqa: E402
from tactile_deploy.pad.geometry import PadGeometry  # noqa: E402
from tactile_deploy.pad.mesh import build_pad_mesh  # noqa: E402

E_MPA = 0.3
NU = 0.45
# Both assemblies are float64 and differ only in summation order: round-off, ~1e-15 relative.
REL_TOL = 1e-12


def rel_max_abs(A, B) -> float:
    """max |A - B| / max |B| over all entries of two sparse matrices."""
    return float(abs(A - B).max() / abs(B).max())


def rigid_modes(vertices: np.ndarray) -> np.ndarray:
    """(3n, 6) rigid-body displacements: 3 translations, 3 infinitesimal rotations (mm)."""
    n = len(vertices)
    x = vertices - vertices.mean(axis=0)
    modes = np.zeros((n, 3, 6))
    for c in range(3):
        modes[:, c, c] = 1.0
        axis = np.eye(3)[c]
        modes[:, :, 3 + c] = np.cross(axis, x)
    return modes.reshape(3 * n, 6)


def total_volume(vertices: np.ndarray, tets: np.ndarray) -> float:
    """Mesh volume, mm^3."""
    p = vertices[tets]
    return float(np.abs(np.linalg.det(p[:, 1:] - p[:, :1])).sum() / 6.0)


@pytest.fixture(scope="module")
def small_mesh():
    mesh = build_pad_mesh(PadGeometry(radius_mm=5.0, edge_mm=1.0, n_layers=2))
    return mesh.vertices, mesh.tets


@pytest.fixture(scope="module")
def small_K(small_mesh):
    vertices, tets = small_mesh
    return (
        assemble_stiffness_warp(vertices, tets, E_MPA, NU),
        assemble_stiffness_numpy(vertices, tets, E_MPA, NU),
    )


@pytest.fixture(scope="module")
def pad_mesh():
    pad = load_pad()
    return pad.vertices, pad.tets


@pytest.fixture(scope="module")
def pad_K(pad_mesh):
    vertices, tets = pad_mesh
    return (
        assemble_stiffness_warp(vertices, tets, E_MPA, NU),
        assemble_stiffness_numpy(vertices, tets, E_MPA, NU),
    )


@pytest.mark.parametrize("which", ["small", "pad"])
def test_matches_numpy_assembly(which, request):
    vertices, _ = request.getfixturevalue(f"{which}_mesh")
    K_warp, K_np = request.getfixturevalue(f"{which}_K")
    n = len(vertices)
    assert K_warp.shape == (3 * n, 3 * n)
    assert K_warp.dtype == np.float64
    # Same sparsity pattern, then same values.
    K_np = K_np.copy()
    K_np.sort_indices()
    np.testing.assert_array_equal(K_warp.indptr, K_np.indptr)
    np.testing.assert_array_equal(K_warp.indices, K_np.indices)
    assert rel_max_abs(K_warp, K_np) <= REL_TOL


@pytest.mark.parametrize("which", ["small", "pad"])
def test_symmetric_with_rigid_null_space(which, request):
    vertices, _ = request.getfixturevalue(f"{which}_mesh")
    K, _ = request.getfixturevalue(f"{which}_K")
    k_max = abs(K).max()
    assert abs(K - K.T).max() <= 1e-14 * k_max
    R = rigid_modes(vertices)
    # Forces of a rigid motion, relative to the force scale of a unit-amplitude displacement.
    assert np.abs(K @ R).max() <= 1e-12 * k_max * np.abs(R).max()


def test_null_space_is_exactly_rigid(small_K):
    """Six zero eigenvalues (rigid motions) and no spurious zero-energy modes."""
    K, _ = small_K
    eig = np.linalg.eigvalsh(K.toarray())
    scale = eig[-1]
    assert np.all(np.abs(eig[:6]) <= 1e-12 * scale)
    assert eig[6] >= 1e-4 * scale


@pytest.mark.parametrize("which", ["small", "pad"])
def test_uniform_strain_energy(which, request):
    """u = G x: P1 is exact, so u^T K u = V (lambda tr(eps)^2 + 2 mu eps:eps)."""
    vertices, tets = request.getfixturevalue(f"{which}_mesh")
    K, _ = request.getfixturevalue(f"{which}_K")
    G = np.random.default_rng(7).normal(scale=0.01, size=(3, 3))  # displacement gradient, mm/mm
    u = (vertices @ G.T).ravel()
    eps = 0.5 * (G + G.T)
    lam = E_MPA * NU / ((1 + NU) * (1 - 2 * NU))
    mu = E_MPA / (2 * (1 + NU))
    energy2 = total_volume(vertices, tets) * (lam * np.trace(eps) ** 2 + 2 * mu * np.sum(eps * eps))
    assert u @ (K @ u) == pytest.approx(energy2, rel=1e-10)


def test_p1_nodes_are_vertices(small_mesh):
    """warp's P1 node i sits on vertex i, so no DOF permutation is needed."""
    import warp as wp
    import warp.fem as fem

    vertices, tets = small_mesh
    geo = fem.Tetmesh(
        wp.array(tets.astype(np.int32), dtype=int), wp.array(vertices, dtype=wp.vec3d)
    )
    space = fem.make_polynomial_space(geo, degree=1, dtype=wp.vec3d)
    assert space.node_count() == len(vertices)
    np.testing.assert_array_equal(space.node_positions().numpy(), vertices)


def test_backend_dispatch_and_explicit_cpu(small_mesh, small_K):
    vertices, tets = small_mesh
    K_warp, _ = small_K
    K_cpu = assemble_stiffness_warp(vertices, tets, E_MPA, NU, device="cpu")
    K_dispatch = assemble_stiffness(vertices, tets, E_MPA, NU, backend="warp")
    assert abs(K_cpu - K_warp).max() <= REL_TOL * abs(K_warp).max()
    assert abs(K_dispatch - K_warp).max() <= REL_TOL * abs(K_warp).max()


def test_rejects_bad_input(small_mesh):
    vertices, tets = small_mesh
    flipped = tets.copy()
    flipped[3, [0, 1]] = flipped[3, [1, 0]]
    with pytest.raises(ValueError, match="inverted or degenerate"):
        assemble_stiffness_warp(vertices, flipped, E_MPA, NU)
    with pytest.raises(ValueError, match="vertices"):
        assemble_stiffness_warp(vertices[:, :2], tets, E_MPA, NU)
    with pytest.raises(ValueError, match="tets"):
        assemble_stiffness_warp(vertices, tets[:, :3], E_MPA, NU)
    with pytest.raises(ValueError, match="outside"):
        assemble_stiffness_warp(vertices, tets + len(vertices), E_MPA, NU)
    with pytest.raises(ValueError, match="nu"):
        assemble_stiffness_warp(vertices, tets, E_MPA, 0.5)
    with pytest.raises(ValueError, match="E_mpa"):
        assemble_stiffness_warp(vertices, tets, -1.0, NU)


def test_package_imports_without_warp():
    """Importing the package and the numpy assembly must not pull in warp."""
    code = (
        "import sys, tactile_deploy, tactile_deploy.fem.elasticity, tactile_deploy.pad.asset; "
        "sys.exit('warp' in sys.modules)"
    )
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
