"""The resolved contact solver against an independent FEM library (scikit-fem).

``tests/independent_fem.py`` solves a rigid frictionless sphere pressed into the bonded
cylindrical layer with scikit-fem (axisymmetric, quadratic triangles, the same compressible
neo-Hookean strain energy, contact in the current configuration, primal-dual active-set
Newton), written without the product's code. Here:

* it imports nothing of the product;
* at small depth it reproduces the bonded thin-layer solution of Dimitriadis et al. 2002
  (Biophys. J. 82:2798), which checks its elasticity, supports and contact;
* at 1.0 mm (a 2 mm sphere, 3 mm layer of radius 8 mm, E 0.3 MPa, nu 0.48: strains of tens of
  per cent) the resolved solver's force is within 2 % of it and its deformed surface within
  10 um (vertical position of the surface at a given distance from the sphere's axis, current
  configuration, sensor frame): the requirement, not yet met at the automatic truth mesh
  (x1.025, 12.1 um), so that test is a strict expected failure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import independent_fem as ref
from contact_checks import check_resolved_contact
from references import dimitriadis_force, imports_beyond

E_MPA, NU = 0.3, 0.48
PAD_RADIUS_MM, THICKNESS_MM = 8.0, 3.0
BALL_RADIUS_MM, BALL_DEPTH_MM = 2.0, 1.0


def test_independent_fem_uses_no_product_code():
    outside, product = imports_beyond(Path(__file__).parent / "independent_fem.py",
                                      {"numpy", "scipy", "skfem"})
    assert not outside, outside
    assert not product, product


def test_independent_fem_matches_the_thin_layer_solution_at_small_depth():
    # 2 mm sphere, 0.05 mm: contact radius 0.32 mm (a / h = 0.11), resolved by 0.02 mm P2
    # triangles (measured x0.990; the same at 0.01 mm, x0.994 at 0.02 mm depth)
    sol = ref.press_sphere(PAD_RADIUS_MM, THICKNESS_MM, E_MPA, NU, sphere_radius_mm=2.0,
                           depth_mm=0.05, h_fine_mm=0.02, fine_r_mm=0.6, fine_depth_mm=0.2,
                           steps=1)
    expected = dimitriadis_force(E_MPA, NU, 2.0, 0.05, THICKNESS_MM)
    print(f"independent FEM {sol.force_n:.6f} N, Dimitriadis {expected:.6f} N, "
          f"ratio {sol.force_n / expected:.4f}")
    assert sol.force_n == pytest.approx(expected, rel=0.02)
    assert sol.max_penetration_mm < 1e-9


def surface_profile_mm(sol, rho_mm: np.ndarray, azimuths_deg) -> np.ndarray:
    """Height z (mm, sensor frame) of the resolved solution's deformed sensing surface at
    distance ``rho_mm`` (k,) from the z axis along each azimuth: (azimuths, k). The surface is
    the truth mesh's sensing triangles at their current positions (piecewise linear)."""
    from tactile_deploy.fem.truth import locate_in_triangles

    n = sol.mesh.n_plane
    cur = sol.vertices_mm[:n]
    tri = sol.mesh.plane_triangles
    out = []
    for phi in np.deg2rad(np.asarray(azimuths_deg, float)):
        pts = np.stack([rho_mm * np.cos(phi), rho_mm * np.sin(phi)], 1)
        t, bary = locate_in_triangles(pts, cur[tri][:, :, :2])
        assert bary.min() > -1e-9  # every sample lies on the deformed surface
        out.append((cur[tri[t]][:, :, 2] * bary).sum(1))
    return np.array(out)


@pytest.fixture(scope="module")
def ball_at_1mm():
    """The resolved solver's 2 mm sphere pressed 1.0 mm at the centre of the layer (neo-Hookean,
    frictionless, automatic truth mesh) and its intrusion field: (solution, field)."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.truth import IntrusionField, TruthSolver
    from tactile_deploy.pad.geometry import PadGeometry

    def intrusion(xy):
        r2 = (xy**2).sum(1)
        cap = BALL_RADIUS_MM - np.sqrt(np.maximum(BALL_RADIUS_MM**2 - r2, 0.0))
        return np.where(r2 < BALL_RADIUS_MM**2, BALL_DEPTH_MM - cap, -np.inf)

    pad = PadGeometry(name="small", radius_mm=PAD_RADIUS_MM, thickness_mm=THICKNESS_MM)
    solver = TruthSolver(pad, Material(E_mpa=E_MPA, nu=NU), model="neo-hookean")
    field = IntrusionField(intrusion)
    return solver.solve_field(field), field


@pytest.mark.slow
def test_ball_pressed_1mm_stays_on_the_indenters_surface(ball_at_1mm):
    """No penetration anywhere on the continuous surface (measured 6.43 um, near the apex,
    where the gel's surface triangles are stretched from ~0.23 to ~0.3 mm), no tensile
    traction, gap and force complementary; the apex reaches the commanded depth."""
    sol, field = ball_at_1mm
    _, tip_depth = check_resolved_contact(sol, field, geometric=True, label="2 mm ball, 1.0 mm")
    assert tip_depth == pytest.approx(BALL_DEPTH_MM, abs=1e-3)


@pytest.fixture(scope="module")
def independent_ball_at_1mm():
    """The independent FEM's solution of the same press: 0.1 mm P2 triangles (0.05 % in force
    and 2.5 um in the surface from the twice finer mesh)."""
    return ref.press_sphere(PAD_RADIUS_MM, THICKNESS_MM, E_MPA, NU,
                            sphere_radius_mm=BALL_RADIUS_MM, depth_mm=BALL_DEPTH_MM,
                            h_fine_mm=0.1, steps=20)


@pytest.mark.slow
def test_sphere_at_1mm_has_the_independent_fems_surface(ball_at_1mm, independent_ball_at_1mm):
    """The deformed sensing surface within 10 um of the independent FEM's everywhere (24
    azimuths, every 5 um in radius). Measured 7.17 um at the contact edge (12.1 um before the
    truth mesh followed the ball's curvature at its steep rim)."""
    expected = independent_ball_at_1mm
    sol, _ = ball_at_1mm
    rho = np.arange(0.0, PAD_RADIUS_MM - 0.5, 0.005)
    ours = surface_profile_mm(sol, rho, np.arange(0.0, 360.0, 15.0))
    theirs = np.interp(rho, expected.profile_r_mm, expected.profile_z_mm)
    diff = np.abs(ours - theirs[None])
    worst = np.unravel_index(diff.argmax(), diff.shape)
    print(f"surface: largest difference {diff.max() * 1e3:.2f} um at r = {rho[worst[1]]:.3f} mm; "
          f"contact radius {expected.contact_radius_mm:.3f} mm")
    assert diff.max() <= 10e-3


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
    "at the automatic truth mesh (fine spacing 0.173 mm, bulk growing to 2 mm) the resolved "
    "solver's force is 2.5 % above the converged independent FEM; it meets 2 % on a finer mesh "
    "(fine spacing 0.124 mm, bulk at most 0.5 mm: x1.017), not at the default one; docs/fem.md"))
def test_sphere_at_1mm_has_the_independent_fems_force(ball_at_1mm, independent_ball_at_1mm):
    expected = independent_ball_at_1mm
    sol, _ = ball_at_1mm
    print(f"force {sol.force_n:.5f} N vs independent FEM {expected.force_n:.5f} N "
          f"(x{sol.force_n / expected.force_n:.4f})")
    assert sol.force_n == pytest.approx(expected.force_n, rel=0.02)
