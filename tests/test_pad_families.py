"""Pad families as data: the GelSight Mini and DIGIT pads from their published dimensions, frozen
with hash and card; box grading; fixed sides; the physics lift of any pad against the FEM."""

from __future__ import annotations

import numpy as np
import pytest

from tactile_deploy.pad import asset as asset_mod
from tactile_deploy.pad.family import FAMILIES, PadFamily, SensingArea, depth_grid_over
from tactile_deploy.pad.geometry import PadGeometry
from tactile_deploy.pad.mesh import build_pad_mesh
from tactile_deploy.pad.meshing import box_axis_coords
from tactile_deploy.pad.quality import quality_report

NEW = ("gelsight_mini", "digit")


@pytest.mark.parametrize("name", NEW)
def test_family_pad_is_frozen_with_hash_and_card(name):
    mesh = asset_mod.load_pad(name)
    card = asset_mod.load_pad_card(name)
    fresh = asset_mod.regenerate_shipped(name)
    assert fresh.content_hash == mesh.content_hash == card.content_hash
    fam = FAMILIES[name]
    assert card.family == fam and card.n_nodes == mesh.n_nodes
    # the card cites its sources and states what had to be assumed
    assert len(card.family.sources) >= 2 and all(s.reference for s in card.family.sources)
    assert card.family.assumptions
    q = quality_report(mesh.vertices, mesh.tets)
    assert q.n_inverted == 0 and q.n_slivers == 0


@pytest.mark.parametrize("name", NEW)
def test_sensing_area_spacing_and_outline_match_the_published_numbers(name):
    fam = FAMILIES[name]
    mesh = asset_mod.load_pad(name)
    v = mesh.vertices
    # outline and thickness as published (mm)
    assert np.ptp(v[:, 0]) == pytest.approx(fam.width_mm, abs=1e-9)
    assert np.ptp(v[:, 1]) == pytest.approx(fam.length_mm, abs=1e-9)
    assert v[mesh.backplate_nodes, 2] == pytest.approx(-fam.thickness_mm)
    assert v[: mesh.n_plane, 2].max() == pytest.approx(0.0, abs=1e-3)   # the apex
    assert v[: mesh.n_plane, 2].min() == pytest.approx(
        -fam.crown_mm * (1 + (fam.width_mm / fam.length_mm) ** 2 if fam.crown_mm else 0),
        rel=0.05, abs=1e-9)
    # every sensing-surface cell inside the sensing area is at most 0.5 mm across
    spacing = asset_mod.sensing_spacing_mm(mesh, fam)
    assert spacing <= 0.5
    assert asset_mod.load_pad_card(name).sensing_spacing_mm == pytest.approx(spacing, abs=1e-4)
    # the depth grid covers the sensing area with square cells
    g, a = fam.depth_grid, fam.sensing_area
    assert g.pitch_x_mm == pytest.approx(g.pitch_y_mm)
    assert g.x_min_mm <= a.x_min_mm and g.x_max_mm >= a.x_max_mm
    assert g.y_min_mm <= a.y_min_mm and g.y_max_mm >= a.y_max_mm
    assert g.pitch_x_mm < 0.5 * fam.sensing_spacing_mm


def test_published_dimensions_of_the_two_sensors():
    mini, digit = FAMILIES["gelsight_mini"], FAMILIES["digit"]
    # GelSight Mini datasheet: field of view 18.6 x 14.3 mm; gel pad model 25.25 x 20.75 x 4 mm
    assert (mini.sensing_area.width_mm, mini.sensing_area.length_mm) == pytest.approx((18.6, 14.3))
    assert (mini.width_mm, mini.length_mm, mini.thickness_mm) == (25.25, 20.75, 4.0)
    # DIGIT (FOTS's unit D00001): gel 18.35 x 24.90 mm, 240 x 320 px at 19.58 px/mm
    assert (digit.width_mm, digit.length_mm) == (18.35, 24.9)
    assert digit.sensing_area.width_mm == pytest.approx(240 / 19.58, abs=0.05)
    assert digit.sensing_area.length_mm == pytest.approx(320 / 19.58, abs=0.05)


def test_gelslim_family_is_the_shipped_gelslim_pad():
    assert FAMILIES["gelslim"].geometry() == asset_mod.SHIPPED_PADS["gelslim"][1]


def test_box_axis_grading():
    x = box_axis_coords(20.0, 6.0, 0.5, 1.25, 1.3)
    d = np.diff(x)
    assert x[0] == pytest.approx(-10.0) and x[-1] == pytest.approx(10.0)
    np.testing.assert_allclose(x, -x[::-1], atol=1e-12)
    inside = (x[:-1] >= -6 - 1e-9) & (x[1:] <= 6 + 1e-9)
    assert d[inside].max() <= 0.5 + 1e-12 and inside.sum() == 24
    assert d.max() <= 1.25 * 1.35            # the outer spacing (stretched at most a little)
    assert np.all(d[~inside] >= 0.49)          # coarsens outward
    # no core: uniform, as the box meshes before grading
    np.testing.assert_allclose(box_axis_coords(30.0, 0.0, 0.1, 1.0, 1.2), np.linspace(-15, 15, 31))


def test_family_validation_names_the_problem():
    base = dict(name="t", description="t", outline="rectangle", width_mm=10.0, length_mm=8.0,
                thickness_mm=3.0, sensing_spacing_mm=0.5, outer_spacing_mm=1.0, n_layers=3,
                depth_grid=depth_grid_over(SensingArea(x_min_mm=-4, x_max_mm=4, y_min_mm=-3,
                                                       y_max_mm=3), 0.2))
    with pytest.raises(ValueError, match="does not lie inside"):
        PadFamily(**base, sensing_area=SensingArea(x_min_mm=-6, x_max_mm=6, y_min_mm=-3,
                                                   y_max_mm=3))
    with pytest.raises(ValueError, match="crown_mm"):
        PadFamily(**base, crown_mm=3.0, sensing_area=SensingArea(x_min_mm=-4, x_max_mm=4,
                                                                 y_min_mm=-3, y_max_mm=3))
    with pytest.raises(ValueError, match="does not fit"):
        PadGeometry(shape="box", width_mm=10, length_mm=8, core_half_width_mm=6,
                    core_half_length_mm=3)


def test_depth_lift_reproduces_the_contact_fem():
    """The physics lift given the FEM's own sensing-surface u_z returns the FEM's whole
    displacement field and contact forces (frictionless contact: u_z on the surface fixes it)."""
    from tactile_deploy.fem.depth_lift import DepthLift
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.indenters import AnalyticSphere, ContactPose

    mesh = build_pad_mesh(PadGeometry(name="small", radius_mm=6.0, edge_mm=0.8, n_layers=3))
    sim = ContactSimulator(mesh, Material(nu=0.45, E_mpa=0.3), use_cache=False, assembly="numpy")
    res = sim.solve(AnalyticSphere(2.0), ContactPose(x_mm=0.5, y_mm=-0.3, depth_mm=0.4))
    lift = DepthLift(mesh, 0.45, 0.3)
    u, f = lift.solve_uz(res.displacements_mm[: mesh.n_plane, 2])
    scale = np.abs(res.displacements_mm).max()
    assert np.abs(u - res.displacements_mm).max() < 1e-6 * scale
    assert f.sum() == pytest.approx(res.force_n, rel=1e-6)
    np.testing.assert_allclose(f, -res.contact_forces_n[:, 2], atol=1e-6 * res.force_n)


def _box_pad_and_grid():
    """A small box pad (8 x 8 x 3 mm) and a 0.1 mm depth grid over its central 6 x 6 mm."""
    geo = PadGeometry(name="b", shape="box", width_mm=8.0, length_mm=8.0, thickness_mm=3.0,
                      edge_mm=1.0, core_edge_mm=0.5, core_half_width_mm=3.0,
                      core_half_length_mm=3.0, n_layers=3)
    grid = depth_grid_over(SensingArea(x_min_mm=-3, x_max_mm=3, y_min_mm=-3, y_max_mm=3), 0.1)
    return build_pad_mesh(geo), grid


def _paraboloid(grid, x0_mm: float, radius_mm: float, depth_mm: float) -> np.ndarray:
    """Depth map (mm) of a paraboloid of ``radius_mm`` at (x0, 0) pressed ``depth_mm``."""
    x = grid.x_min_mm + (np.arange(grid.nx) + 0.5) * grid.pitch_x_mm
    y = grid.y_max_mm - (np.arange(grid.ny) + 0.5) * grid.pitch_y_mm
    r2 = (x[None, :] - x0_mm) ** 2 + y[:, None] ** 2
    return np.clip(depth_mm - r2 / (2 * radius_mm), 0, None)


def test_depth_lift_puts_each_node_on_the_depth_surface_and_fixed_sides_hold():
    """Nodes end where the depth map says the surface is (after sliding sideways); fixed side
    walls stay put."""
    from tactile_deploy.fem.constraints import Supports
    from tactile_deploy.fem.depth_lift import DepthLift, sample_depth_grid

    mesh, grid = _box_pad_and_grid()
    depth = _paraboloid(grid, 0.0, 2.0, 0.5)          # a 2 mm paraboloid 0.5 mm deep
    lift = DepthLift(mesh, 0.48, 0.3, Supports(side="fixed"))
    v, f = lift.from_depth(depth, grid)
    top = v[: mesh.n_plane]
    assert np.abs(top[:, :2] - mesh.vertices[: mesh.n_plane, :2]).max() > 0.02   # it slid
    np.testing.assert_allclose(-top[:, 2], sample_depth_grid(depth, grid, top[:, :2]), atol=3e-3)
    assert np.abs(v[mesh.side_nodes] - mesh.vertices[mesh.side_nodes]).max() == 0.0
    assert f.sum() > 0


def test_depth_lift_lateral_operator_gives_the_solves_numbers_and_is_cached(tmp_path, monkeypatch):
    """The fixed point's lateral steps from the cached dense operator equal those of a sparse
    solve of the whole mesh per step; a second lift of the same pad and material reads the
    operator back from the cache folder, another nu does not."""
    from tactile_deploy.fem.depth_lift import DepthLift

    monkeypatch.setenv("TACTILE_DEPLOY_CACHE_DIR", str(tmp_path))
    mesh, grid = _box_pad_and_grid()
    depth = _paraboloid(grid, 0.4, 1.5, 0.6)
    lift = DepthLift(mesh, 0.48, 0.3)
    v_op, f_op = lift.from_depth(depth, grid)
    v_solve, f_solve = lift.from_depth(depth, grid, lateral="solve")
    assert np.abs(v_op - mesh.vertices).max() > 0.3
    np.testing.assert_allclose(v_op, v_solve, rtol=0, atol=1e-10)
    np.testing.assert_allclose(f_op, f_solve, rtol=0, atol=1e-10 * np.abs(f_solve).max())
    assert lift.lateral_cache_path.is_file()
    again = DepthLift(mesh, 0.48, 0.3)
    assert again.lateral_cache_path == lift.lateral_cache_path
    np.testing.assert_array_equal(np.load(again.lateral_cache_path), lift.lateral_operator())
    assert DepthLift(mesh, 0.45, 0.3).lateral_cache_path != lift.lateral_cache_path
    for bad in (np.zeros((3, 3)), np.full_like(lift.lateral_operator(), np.nan)):   # recomputed
        np.save(lift.lateral_cache_path, bad)
        np.testing.assert_allclose(DepthLift(mesh, 0.48, 0.3).lateral_operator(), lift.lateral_operator(),
                                   rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.load(lift.lateral_cache_path), lift.lateral_operator(),
                                   rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="lateral must be 'operator' or 'solve'"):
        lift.from_depth(depth, grid, lateral="dense")
