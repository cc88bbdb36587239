"""Coulomb friction between indenter and gel (the ``friction`` effect): its limits are the
simulator's own frictionless and sticking solutions (independent solvers), and in between the
solution satisfies Coulomb's law node by node."""

from __future__ import annotations

import numpy as np
import pytest

from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.sensors.effects import get_effect


@pytest.mark.parametrize("indenter", ["sphere_r4", "flat_punch"])
def test_friction_limits_are_frictionless_and_sticking_contact(sims, indenter):
    sim, stick = sims
    delta = sim.intrusion(get_indenter(indenter), ContactPose(x_mm=1.0, depth_mm=0.8))
    free = sim.solve_intrusion(delta)
    held = stick.solve_intrusion(delta)
    assert held.force_n > 1.03 * free.force_n  # the gel held back: stiffer
    grip = get_effect("friction", {"mu": 20.0}).correct_contact(sim, delta, free)
    np.testing.assert_allclose(grip.displacements_mm, held.displacements_mm, atol=1e-6)
    assert grip.force_n == pytest.approx(held.force_n, rel=1e-6)
    slip = get_effect("friction", {"mu": 1e-4}).correct_contact(sim, delta, free)
    assert slip.force_n == pytest.approx(free.force_n, rel=1e-3)
    assert np.max(np.abs(slip.displacements_mm - free.displacements_mm)) < 2e-3


def test_intermediate_friction_satisfies_coulombs_law_at_every_node(sims):
    from tactile_deploy.sensors.effects._coulomb import coulomb_solver

    sim, _ = sims
    mu = 0.3
    delta = sim.intrusion(get_indenter("cylinder_side"),
                          ContactPose(x_mm=0.5, y_mm=-1.0, theta_deg=30.0, depth_mm=0.8))
    solver = coulomb_solver(sim)
    nodes = sim.contact_nodes
    f = solver.forces(delta[nodes], mu)
    u = (solver.C3 @ f.ravel()).reshape(-1, 3)
    fn = -f[:, 2]
    ft = np.linalg.norm(f[:, :2], axis=1)
    ut = u[:, :2]
    scale = fn.max()
    gap = -delta[nodes] - u[:, 2]
    assert np.all(fn >= -1e-9 * scale) and np.all(gap >= -1e-7)
    active = fn > 1e-6 * scale
    assert np.all(np.abs(gap[active]) < 1e-7)  # in contact: on the indenter
    assert np.all(ft <= mu * fn * (1 + 1e-6) + 1e-9 * scale)  # inside the cone
    sticking = active & (ft < (1 - 1e-3) * mu * fn)
    slipping = active & ~sticking
    assert sticking.sum() > 5 and slipping.sum() > 5  # both regimes occur
    assert np.max(np.linalg.norm(ut[sticking], axis=1)) < 1e-6
    # slipping nodes: friction opposes the slip
    moving = slipping & (np.linalg.norm(ut, axis=1) > 1e-5)
    cos = np.sum(f[moving, :2] * ut[moving], axis=1) / (ft[moving] * np.linalg.norm(ut[moving],
                                                                                   axis=1))
    assert np.all(cos < -0.999)
    # the volume's displacements agree with the surface compliance at the sensing nodes
    disp = solver.displacements(f)
    np.testing.assert_allclose(disp[nodes], u, atol=1e-8)
