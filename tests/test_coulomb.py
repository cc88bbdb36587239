"""Coulomb friction on the pad mesh (:class:`tactile_deploy.fem.coulomb.CoulombSimulator`): its
limits are the simulator's frictionless and sticking solutions, its solution satisfies the
contact and friction conditions node by node, it agrees with the sensor effect's solver of the
same discrete problem (a different algorithm: fixed point on the slip bound with projected
gradients), and a slid indenter reaches Amontons' gross sliding ``Q = mu P``."""

from __future__ import annotations

import numpy as np
import pytest

from tactile_deploy.fem.material import Material
from tactile_deploy.indenters import ContactPose, get_indenter

CASES = {
    "sphere_r4": ContactPose(x_mm=1.0, depth_mm=0.8),
    "cylinder_side": ContactPose(x_mm=0.5, y_mm=-1.0, theta_deg=30.0, depth_mm=0.8),
    "flat_punch": ContactPose(x_mm=1.0, depth_mm=0.8),
}


def coulomb(stick, mu):
    from tactile_deploy.fem.coulomb import CoulombSimulator

    return CoulombSimulator.sharing(stick, Material(nu=stick.material.nu, friction="coulomb", mu=mu))


@pytest.mark.parametrize("indenter", list(CASES))
def test_limits_are_frictionless_and_sticking_contact(sims, indenter):
    free_sim, stick = sims
    delta = free_sim.intrusion(get_indenter(indenter), CASES[indenter])
    free = free_sim.solve_intrusion(delta)
    held = stick.solve_intrusion(delta)
    zero = coulomb(stick, 0.0).solve_intrusion(delta)
    # mu = 0: the frictionless solution to round-off (the solver's tolerance is 1e-10 of the
    # largest nodal force; both are exact active-set solutions)
    np.testing.assert_allclose(zero.displacements_mm, free.displacements_mm, rtol=0, atol=1e-10)
    assert zero.force_n == pytest.approx(free.force_n, rel=1e-10)
    assert not zero.stick_mask.any()
    # the sticking solution satisfies Coulomb's law for mu above its largest |t| / p: there the
    # Coulomb solution is the sticking one to round-off, and just below it is not
    ratio = np.linalg.norm(held.contact_forces_n[:, :2], axis=1)[held.contact_mask] / (
        -held.contact_forces_n[held.contact_mask, 2])
    mu_stick = float(ratio.max())
    grip = coulomb(stick, 1.001 * mu_stick).solve_intrusion(delta)
    np.testing.assert_allclose(grip.displacements_mm, held.displacements_mm, rtol=0, atol=1e-10)
    assert grip.force_n == pytest.approx(held.force_n, rel=1e-10)
    assert np.array_equal(grip.stick_mask, held.contact_mask)
    below = coulomb(stick, 0.9 * mu_stick).solve_intrusion(delta)
    assert np.max(np.abs(below.displacements_mm - held.displacements_mm)) > 1e-4
    assert not np.array_equal(below.stick_mask, below.contact_mask)


@pytest.mark.parametrize("indenter,mu", [("sphere_r4", 0.3), ("cylinder_side", 0.3), ("flat_punch", 0.3)])
def test_contact_and_friction_conditions_hold_at_every_node(sims, indenter, mu):
    from tactile_deploy.sensors.effects._coulomb import coulomb_solver

    free_sim, stick = sims
    sim = coulomb(stick, mu)
    delta = free_sim.intrusion(get_indenter(indenter), CASES[indenter])
    res = sim.solve_intrusion(delta)
    nodes = sim.contact_nodes
    f = res.contact_forces_n[nodes] / sim.material.E_mpa  # N at E = 1
    u = (sim.compliance @ f.ravel()).reshape(-1, 3)
    # the volume's displacements (float32 Green's functions) at the contact nodes
    np.testing.assert_allclose(res.displacements_mm[sim.mesh.sensing_nodes[nodes]], u, atol=1e-7)
    p, t = -f[:, 2], f[:, :2]
    tn = np.linalg.norm(t, axis=1)
    scale = p.max()
    gap = -delta[nodes] - u[:, 2]
    reach = delta.max()
    assert np.all(p >= -1e-10 * scale)  # no tensile pressure
    assert np.all(gap >= -1e-9 * reach)  # no penetration
    on = p > 1e-10 * scale
    assert np.all(np.abs(gap[on]) <= 1e-9 * reach)  # pressed nodes touch the indenter
    # inside the friction cone: the residuals bound the excess by (1 + mu) * TOL * max p
    assert np.all(tn <= mu * p + (1 + mu) * 1e-10 * scale)
    assert np.all(tn[~on] <= 1e-10 * scale)
    st = res.stick_mask[nodes]
    slip = on & ~st
    assert st.sum() >= 3 and slip.sum() >= 3, (st.sum(), slip.sum())  # both regimes occur
    ut = np.linalg.norm(u[:, :2], axis=1)
    assert np.all(ut[st] <= 1e-9 * reach)  # sticking nodes do not move sideways
    # slipping nodes: on the cone, the friction force opposite to the slip
    np.testing.assert_allclose(tn[slip], mu * p[slip], rtol=1e-8)
    moving = slip & (ut > 1e-6)
    cos = np.sum(t[moving] * u[moving, :2], axis=1) / (tn[moving] * ut[moving])
    assert np.all(cos < -1 + 1e-8)
    # the sensor effect's solver of the same discrete problem, a different algorithm
    other = coulomb_solver(free_sim).forces(delta[nodes], mu)
    assert np.max(np.abs(other - f)) <= 1e-6 * scale


def test_press_then_slide_reaches_gross_sliding(sims):
    """A sphere pressed in 4 steps and slid along x: a slide of 0.2 mm leaves a stick zone and a
    tangential force well below mu P (partial slip); one of 1 mm slips every node in contact,
    each at the friction cone, the friction forces dragging the gel along the slide, and the
    tangential force reaches mu times the normal force (Amontons) up to the spread of the
    nodes' slip directions."""
    _, stick = sims
    mu = 0.5
    sim = coulomb(stick, mu)
    ind, pose = get_indenter("sphere_r4"), CASES["sphere_r4"]
    pressed = sim.solve(ind, pose, press_steps=4)
    short = sim.solve(ind, pose, press_steps=4, slide_mm=(0.2, 0.0), slide_steps=8)
    slid = sim.solve(ind, pose, press_steps=4, slide_mm=(1.0, 0.0), slide_steps=8)
    for res in (pressed, short, slid):
        f = res.contact_forces_n
        tn = np.linalg.norm(f[:, :2], axis=1)
        assert np.all(tn <= mu * -f[:, 2] + (1 + mu) * 1e-10 * res.force_n)
    q_pressed = np.linalg.norm(pressed.contact_forces_n[:, :2].sum(0))
    assert q_pressed < 0.02 * mu * pressed.force_n  # a normal press: friction forces cancel
    q_short = short.contact_forces_n[:, 0].sum()
    assert 0.2 * mu * short.force_n < q_short < 0.5 * mu * short.force_n  # measured 0.33
    assert 5 <= short.stick_mask.sum() < short.contact_mask.sum()
    f = slid.contact_forces_n
    on = slid.contact_mask
    assert not slid.stick_mask.any() and on.sum() >= 10
    np.testing.assert_allclose(np.linalg.norm(f[on, :2], axis=1), -mu * f[on, 2], rtol=1e-8)
    assert f[on, 0].min() > 0
    assert 0.99 * mu * slid.force_n < f[:, 0].sum() <= mu * slid.force_n  # measured 0.998
    assert abs(f[:, 1].sum()) < 0.02 * mu * slid.force_n


def test_each_simulator_names_the_one_for_its_friction_law():
    from tactile_deploy.fem.coulomb import CoulombSimulator
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.pad.geometry import PadGeometry
    from tactile_deploy.pad.mesh import build_pad_mesh

    with pytest.raises(ValueError, match="CoulombSimulator"):
        ContactSimulator(build_pad_mesh(PadGeometry(name="tiny", radius_mm=4.0, edge_mm=1.0,
                                                    n_layers=2)), Material(friction="coulomb"))
    with pytest.raises(ValueError, match="friction 'coulomb'"):
        CoulombSimulator(build_pad_mesh(PadGeometry(name="tiny", radius_mm=4.0, edge_mm=1.0,
                                                    n_layers=2)), Material(friction="stick"))
