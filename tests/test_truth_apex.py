"""The resolved solver at a sharp tip, at large deformation: the 90-degree cone pressed 0.8 mm
into the neo-Hookean gel (the default model), checked against the indenter's own surface (its
envelope), not against the solver. In a module of its own so that its solve (about 2.5 min on
one core) runs beside the other truth tests."""

from __future__ import annotations

import numpy as np
import pytest

from tactile_deploy.fem.material import Material
from tactile_deploy.fem.truth import TruthSolver, indenter_field, surface_penetration
from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.pad.geometry import PadGeometry
from contact_checks import check_resolved_contact

SMALL_PAD = PadGeometry(name="small", radius_mm=8.0, thickness_mm=3.0)


@pytest.fixture(scope="module")
def neo_hookean_cone():
    """The 90-degree cone pressed 0.8 mm into the neo-Hookean gel (the default model), off
    the pad's centre: (solution, intrusion field)."""
    ind = get_indenter("cone")
    pose = ContactPose(x_mm=0.3, y_mm=-0.2, theta_deg=0.0, depth_mm=0.8)
    solver = TruthSolver(SMALL_PAD, Material(E_mpa=0.3, nu=0.48))
    return solver.solve(ind, pose), indenter_field(ind, pose)


@pytest.mark.slow
def test_neo_hookean_cone_holds_its_apex_and_reaches_its_depth(neo_hookean_cone):
    """At large deformation the gel wraps the cone's sharp apex. The sensing node there is
    held at the tip (the tip's force on it stays inside the flanks' normal cone, so it is
    never released), and the solve converges (it did not: measured as a face contact, that
    node's normal flipped from flank to flank as it moved across the apex by a micrometre).
    The deepest surface point is at the commanded depth, no traction is tensile, gap and force
    are complementary at every loaded node. Measured: force 0.192229 N in 8 depth increments
    of 0.1 mm, none halved, 64 Newton steps (0.192217 N in 16 of 0.05 mm: the path moves the
    answer by 6e-5 of it)."""
    sol, field = neo_hookean_cone
    assert sol.info["apex_node"] >= 0
    apex = sol.mesh.vertices[sol.info["apex_node"]] + sol.displacements_mm[sol.info["apex_node"]]
    assert np.hypot(apex[0] - 0.3, apex[1] + 0.2) < 1e-6  # held at the tip
    _, tip_depth = check_resolved_contact(sol, field, geometric=True, label="neo-Hookean cone",
                                          max_penetration_mm=None)
    assert tip_depth >= 0.78
    assert tip_depth == pytest.approx(0.8, abs=1e-6)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
    "the gel's surface triangles next to the apex stretch as the gel wraps the tip, and their "
    "chords across the flanks cut into the cone by up to 30.1 um (0.09 mm from the apex; more "
    "than 10 um within 0.04-0.17 mm of it); finer triangles there fold under the apex; docs/fem.md"))
def test_neo_hookean_cone_stays_outside_the_cone_within_10um(neo_hookean_cone):
    sol, field = neo_hookean_cone
    pen, _ = surface_penetration(sol, field, pitch_mm=0.01, geometric=True)
    print(f"neo-Hookean cone: largest penetration {pen * 1e3:.2f} um")
    assert pen <= 10e-3
