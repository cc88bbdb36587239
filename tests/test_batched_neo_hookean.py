"""Batched neo-Hookean contact (torch) against the numpy reference and against equilibrium.

CPU torch, float64, on a 10 mm pad (347 sensing nodes). The reference is
:func:`tactile_deploy.sensors.effects.hyperelastic.solve_neo_hookean` (numpy/scipy: sparse
factor, its own contact solver); the equilibrium check needs neither: the assembled neo-Hookean
internal forces of the batched solution must balance its contact forces.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import tactile_deploy.sensors.effects.hyperelastic as hyperelastic  # noqa: E402
from tactile_deploy.fem.hyperelastic import NeoHookeanGel  # noqa: E402
from tactile_deploy.fem.material import Material  # noqa: E402
from tactile_deploy.fem.simulator import ContactSimulator  # noqa: E402
from tactile_deploy.indenters import ContactPose, get_indenter  # noqa: E402
from tactile_deploy.pad.geometry import PadGeometry  # noqa: E402
from tactile_deploy.pad.mesh import build_pad_mesh  # noqa: E402
from tactile_deploy.training.simulation.batched import BatchedContactSimulator  # noqa: E402
from tactile_deploy.training.simulation.batched_neo_hookean import (  # noqa: E402
    BatchedNeoHookean,
    TorchNeoHookean,
)

SMALL = PadGeometry(name="small", radius_mm=10.0, edge_mm=1.0)
# Deep presses (0.6-1.0 mm of the 3 mm pad: strains of 30-50 %), off centre, rotated.
CONTACTS = (("sphere_r4", ContactPose(x_mm=0.5, y_mm=-0.3, depth_mm=1.0)),
            ("flat_punch", ContactPose(x_mm=-1.0, theta_deg=20.0, depth_mm=0.6)),
            ("sphere_r2", ContactPose(x_mm=1.0, y_mm=1.0, depth_mm=0.9)),
            ("parallel_lines", ContactPose(theta_deg=45.0, depth_mm=0.8)))


@pytest.fixture(scope="module")
def small():
    """(CPU simulator, batched linear simulator in float64, intrusions (4, n_plane))."""
    mesh = build_pad_mesh(SMALL)
    sim = ContactSimulator(mesh, Material(nu=0.48, E_mpa=0.3), assembly="numpy", use_cache=False)
    sim.prepare()
    linear = BatchedContactSimulator(mesh, sim.material, dtype=torch.float64,
                                     operators=(sim.compliance, sim.greens))
    delta = np.stack([sim.intrusion(get_indenter(n), p) for n, p in CONTACTS])
    return sim, linear, torch.from_numpy(delta)


def test_batched_forces_equal_the_numpy_gel(small):
    sim, _, _ = small
    gel = NeoHookeanGel(sim.mesh.vertices, sim.mesh.tets, 1.0, 0.48)
    u = 0.05 * np.random.default_rng(0).standard_normal((3, sim.mesh.n_nodes, 3))
    f, ok = TorchNeoHookean(gel).forces(torch.from_numpy(u))
    ref = np.stack([gel.forces(x) for x in u])
    assert bool(ok.all())
    assert np.abs(f.numpy() - ref).max() <= 1e-12 * np.abs(ref).max()
    # an inverted tet flags its sample, not the others
    bad = u.copy()
    bad[1] = -3.0 * (sim.mesh.vertices - sim.mesh.vertices.mean(axis=0))
    _, ok = TorchNeoHookean(gel).forces(torch.from_numpy(bad))
    assert ok.tolist() == [True, False, True]


@pytest.mark.parametrize("tol_mm", [1e-6, 1e-10])
def test_batch_equals_the_numpy_reference(small, tol_mm, monkeypatch):
    """Same fixed point, same path: displacements equal to round-off at the reference's
    tolerance (same iteration counts) and at a tolerance near round-off."""
    sim, linear, delta = small
    monkeypatch.setattr(hyperelastic, "TOLERANCE_MM", tol_mm)
    res, stats = BatchedNeoHookean(linear, tol_mm=tol_mm).solve_intrusion(delta, render=False)
    assert stats.unsolved == 0 and bool(res.solved.all())
    for i, (name, _) in enumerate(CONTACTS):
        ref, info = hyperelastic.solve_neo_hookean(sim, delta[i].numpy(), 1.0, backend="numpy")
        du = np.abs(res.displacements_mm[i].numpy() - ref.displacements_mm).max()
        df = np.abs(res.contact_forces_n[i].numpy() - ref.contact_forces_n).max()
        print(f"{name}: {info['iterations']} iterations, force {ref.force_n:.6f} N, |du| {du:.1e} mm, |df| {df:.1e} N")
        assert du <= 1e-10
        assert df <= 1e-10 * ref.force_n
        assert float(res.force_n[i]) == pytest.approx(ref.force_n, rel=1e-10)


def test_batch_is_in_equilibrium_and_stiffer_than_linear_at_depth(small):
    """Reference-free: at the batched solution the neo-Hookean internal forces balance the
    contact forces (free dofs), the contact forces push only (no tension), and the neo-Hookean
    gel needs more force than the linear one at these depths (it stiffens in compression)."""
    sim, linear, delta = small
    res, _ = BatchedNeoHookean(linear, tol_mm=1e-10).solve_intrusion(delta, render=False)
    gel = NeoHookeanGel(sim.mesh.vertices, sim.mesh.tets, sim.material.E_mpa, 0.48)
    T = sim.dofs.T
    lin = linear.solve_intrusion(delta, render=False)
    for i in range(len(CONTACTS)):
        u = res.displacements_mm[i].numpy()
        f_c = np.zeros((sim.mesh.n_nodes, 3))
        f_c[: sim.mesh.n_plane] = res.contact_forces_n[i].numpy()
        residual = T.T @ (gel.forces(u) - f_c).ravel()   # internal = external on the free dofs
        print(f"{CONTACTS[i][0]}: largest residual {np.abs(residual).max():.1e} N, "
              f"largest contact force {np.abs(f_c).max():.2e} N")
        assert np.abs(residual).max() <= 1e-6 * np.abs(f_c).max()   # measured at most 1.7e-7 (parallel_lines)
        assert res.contact_forces_n[i, :, 2].max() <= 0.0     # compressive only (force on the gel is -z)
        assert float(res.force_n[i]) > float(lin.force_n[i])


def test_zero_strength_is_the_linear_solution(small):
    _, linear, delta = small
    res, stats = BatchedNeoHookean(linear, strength=0.0).solve_intrusion(delta, render=False)
    lin = linear.solve_intrusion(delta, render=False)
    assert stats.iterations == 1
    assert torch.allclose(res.displacements_mm, lin.displacements_mm, rtol=0, atol=1e-12)


def test_rejects_what_it_does_not_solve(small):
    sim, linear, _ = small
    stick = BatchedContactSimulator(sim.mesh, Material(nu=0.48, friction="stick"), dtype=torch.float64,
                                    operators=(np.eye(3 * sim.mesh.n_plane),
                                               np.zeros((3 * sim.mesh.n_plane, sim.mesh.n_nodes, 3))))
    with pytest.raises(ValueError, match="frictionless"):
        BatchedNeoHookean(stick)
    single = BatchedContactSimulator(sim.mesh, sim.material, dtype=torch.float32,
                                     operators=(sim.compliance, sim.greens))
    with pytest.raises(ValueError, match="float64"):
        BatchedNeoHookean(single)
    with pytest.raises(ValueError, match="strength"):
        BatchedNeoHookean(linear, strength=-1.0)


# ------------------------------------------------------------------------------ training data
def test_gel_law_is_checked_against_the_friction_laws():
    from pydantic import ValidationError

    from tactile_deploy.training.config import SyntheticData

    with pytest.raises(ValidationError, match="frictionless contact only"):
        SyntheticData(n_samples=1, friction=["frictionless", "stick"], gel=["linear", "neo-hookean"])
    with pytest.raises(ValidationError, match="one per friction law"):
        SyntheticData(n_samples=1, friction=["frictionless", "stick"], gel=["linear", "linear", "neo-hookean"])
    assert SyntheticData(n_samples=1, gel="neo-hookean").gel == "neo-hookean"


def test_generated_neo_hookean_presses_are_neo_hookean_equilibria():
    """The CPU generator with a linear + neo-Hookean mixture: the neo-Hookean presses balance the
    neo-Hookean gel's internal forces (every free dof but the contact nodes' z is unloaded); the
    linear presses do not (their second-order terms are unbalanced)."""
    from contact_checks import neo_hookean_imbalance

    from tactile_deploy.training.config import SyntheticData
    from tactile_deploy.training.data import generate

    spec = SyntheticData(n_samples=2, seed=3, indenters=["sphere_r4"], radius_max_mm=2.0, depth_min_mm=0.8,
                         depth_max_mm=1.0, contact_radius_mm=6.0, friction=["frictionless", "frictionless"],
                         gel=["linear", "neo-hookean"])
    data = generate(spec)
    imbalance = [neo_hookean_imbalance(u, touching, spec.nu)
                 for u, touching in zip(data.displacement_mm, data.contact_mask)]
    print(f"largest unbalanced force / contact force: linear {imbalance[0]:.1e}, neo-Hookean {imbalance[1]:.1e}")
    assert imbalance[1] < 1e-5     # measured 1.7e-7 (the displacements are stored in float32)
    assert imbalance[0] > 1e-2     # measured 4.7e-2


def test_contact_solve_does_not_depend_on_its_starting_active_sets(small):
    """The fixed point warm-starts each contact solve from the previous map's active sets; the
    contact problem's solution is unique, so any start gives the same forces."""
    _, linear, delta = small
    cold, active, _ = linear.contact.solve(delta)
    rng = np.random.default_rng(4)
    for start in (torch.zeros_like(active), ~active, torch.from_numpy(rng.random(active.shape) < 0.5)):
        warm, warm_active, _ = linear.contact.solve(delta, start)
        assert torch.equal(warm_active, active)
        assert torch.allclose(warm, cold, rtol=0, atol=1e-12)
