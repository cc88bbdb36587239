"""The resolved solver at a sharp tip, at large deformation: the 90-degree cone pressed 0.8 mm
into the neo-Hookean gel (the default model) at the centre of the GelSlim pad with the default
material, as ``tactile-deploy simulate --indenter cone --depth 0.8`` presses it, checked against
the indenter's own surface (its envelope), not against the solver. In a module of its own so
that its solve (about 3.5 min on one core) runs beside the other truth tests."""

from __future__ import annotations

import numpy as np
import pytest

from tactile_deploy.fem.material import Material
from tactile_deploy.fem.truth import TruthSolver, indenter_field, surface_penetration
from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.pad.geometry import PadGeometry
from contact_checks import check_resolved_contact


@pytest.fixture(scope="module")
def neo_hookean_cone():
    """The 90-degree cone pressed 0.8 mm into the neo-Hookean gel (the default model) at the
    centre of the GelSlim pad, E 0.3 MPa, nu 0.45 (the defaults): (solution, intrusion field)."""
    ind = get_indenter("cone")
    pose = ContactPose(x_mm=0.0, y_mm=0.0, theta_deg=0.0, depth_mm=0.8)
    solver = TruthSolver(PadGeometry(), Material())
    return solver.solve(ind, pose), indenter_field(ind, pose)


@pytest.mark.slow
def test_neo_hookean_cone_holds_its_apex_and_reaches_its_depth(neo_hookean_cone):
    """At large deformation the gel wraps the cone's sharp apex. The sensing node there is
    held at the tip (the tip's force on it stays inside the flanks' normal cone, so it is
    never released), and the solve converges (it did not: measured as a face contact, that
    node's normal flipped from flank to flank as it moved across the apex by a micrometre).
    Below the apex tets are crushed; before the collapse barrier (tactile_deploy.fem.hyperelastic)
    one inverted at 0.46 of the 0.8 mm and the solve stopped, every halving of the increment
    failing again. The deepest surface point is at the commanded depth, no traction is tensile,
    gap and force are complementary at every loaded node. Measured: force 0.191313 N in 9 depth
    increments of 0.089 mm, none halved, 63 Newton steps, 31 factorisations (5,705 nodes); 35
    tets end below half their volume (the smallest J 0.11)."""
    sol, field = neo_hookean_cone
    assert sol.info["apex_node"] >= 0
    assert sol.info["load_splits"] == 0
    apex = sol.mesh.vertices[sol.info["apex_node"]] + sol.displacements_mm[sol.info["apex_node"]]
    assert np.hypot(apex[0], apex[1]) < 1e-6  # held at the tip
    _, tip_depth = check_resolved_contact(sol, field, geometric=True, label="neo-Hookean cone",
                                          max_penetration_mm=None)
    assert tip_depth >= 0.78
    assert tip_depth == pytest.approx(0.8, abs=1e-6)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
    "the gel's surface triangles next to the apex stretch as the gel wraps the tip, and their "
    "chords across the flanks cut into the cone by up to 30.3 um near the apex; docs/fem.md"))
def test_neo_hookean_cone_stays_outside_the_cone_within_10um(neo_hookean_cone):
    sol, field = neo_hookean_cone
    pen, _ = surface_penetration(sol, field, pitch_mm=0.01, geometric=True)
    print(f"neo-Hookean cone: largest penetration {pen * 1e3:.2f} um")
    assert pen <= 10e-3
