"""Physics baseline: depth map -> whole pad and inverse-FEM forces, against the forward simulator."""

from __future__ import annotations

import numpy as np
import pytest

from tactile_deploy.fem.surface_to_volume import SurfaceToVolume, sample_depth_at
from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.simulation.contact import simulate_contact


@pytest.fixture(scope="module")
def s2v(pad_sim):
    return SurfaceToVolume(pad_sim)


@pytest.mark.parametrize("name", ["sphere_r4", "flat_punch", "cross", "coin"])
def test_exact_surface_displacement_gives_the_exact_volume_and_force(s2v, pad_sim, name):
    s = simulate_contact(get_indenter(name), ContactPose(x_mm=1, y_mm=2, theta_deg=10, depth_mm=0.9), pad_sim.material, simulator=pad_sim)
    uz = (s.vertices_mm - s.rest_vertices_mm)[: pad_sim.mesh.n_plane, 2]
    np.testing.assert_allclose(s2v.displacements(uz), s.vertices_mm - s.rest_vertices_mm, atol=1e-5)
    forces = s2v.forces_n(uz)
    assert forces.sum() == pytest.approx(s.force_n, rel=1e-6)
    # nodes off the contact carry no force (to the solver's round-off)
    assert np.abs(forces[~s.contact_mask]).max() < 1e-6 * s.force_n


def test_operator_equals_a_direct_sparse_solve_with_the_surface_prescribed(s2v, pad_sim):
    """A second method: the pad's sparse stiffness solved directly, every sensing node's u_z
    prescribed (x, y free), for a field no contact made (two bumps and a tilt): displacements
    and the reactions at the prescribed dofs (the forces)."""
    from scipy.sparse.linalg import spsolve

    mesh = pad_sim.mesh
    xy = mesh.vertices[mesh.sensing_nodes, :2]
    r1 = np.linalg.norm(xy - [3.0, -2.0], axis=1)
    r2 = np.linalg.norm(xy - [-6.0, 5.0], axis=1)
    uz = -0.6 * np.exp(-((r1 / 2.5) ** 2)) - 0.3 * np.exp(-((r2 / 4.0) ** 2)) + 0.004 * xy[:, 0]

    K = pad_sim.K_q.tocsc()
    presc = pad_sim.dofs.z_col[mesh.sensing_nodes]
    free = np.setdiff1d(np.arange(K.shape[0]), presc)
    uq = np.zeros(K.shape[0])
    uq[presc] = uz
    uq[free] = spsolve(K[free][:, free], -(K[free][:, presc] @ uz))
    u_direct = (pad_sim.dofs.T @ uq).reshape(-1, 3)
    reaction_n = pad_sim.material.E_mpa * (K @ uq)[presc]  # force the surface needs, + = along +z

    np.testing.assert_allclose(s2v.displacements(uz), u_direct, atol=2e-5 * np.abs(uz).max())
    np.testing.assert_allclose(s2v.forces_n(uz), -reaction_n, atol=1e-6 * np.abs(reaction_n).max() + 1e-9, rtol=1e-5)


@pytest.mark.parametrize("name", ["sphere_r4", "flat_punch"])
def test_volume_from_a_rendered_depth_map(s2v, pad_sim, name):
    s = simulate_contact(get_indenter(name), ContactPose(x_mm=1, y_mm=2, theta_deg=10, depth_mm=0.9), pad_sim.material, simulator=pad_sim)
    v = s2v.vertices_from_depth(s.depth_mm)
    rmse = np.sqrt(((v - s.vertices_mm) ** 2).sum(1).mean())
    print(f"{name}: vertex RMSE from the depth map {rmse * 1e3:.1f} um")
    assert rmse < 0.01


def test_depth_sampling_follows_the_image_convention():
    # a ramp in x, rows with y decreasing: value = x + 2 y at pixel centres
    n, h = 128, 17.5
    c = -h + (np.arange(n) + 0.5) * 2 * h / n
    img = c[None, :] + 2 * c[::-1, None]
    pts = np.array([[0.0, 0.0], [3.3, -7.1], [-10.0, 12.5]])
    np.testing.assert_allclose(sample_depth_at(img, pts), pts[:, 0] + 2 * pts[:, 1], atol=1e-9)
