"""Triangle rasteriser against an independent ray caster and analytic surfaces."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

import tactile_deploy.raster as raster
from tactile_deploy.raster import RasterGrid, rasterize_triangles


def _vertical_ray_hits(triangles: np.ndarray, xy: np.ndarray):
    """Möller–Trumbore intersection of downward vertical rays with every triangle.

    Independent of the rasteriser (3-D ray/triangle algebra, no edge functions, no grid).
    Returns hit z (k, m) with NaN where ray k misses triangle m.
    """
    top = triangles[:, :, 2].max() + 10.0
    origin = np.concatenate([xy, np.full((len(xy), 1), top)], axis=1)[:, None, :]  # (k, 1, 3)
    direction = np.array([0.0, 0.0, -1.0])
    v0, v1, v2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    pvec = np.cross(direction, e2)
    det = np.einsum("mi,mi->m", e1, pvec)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - v0[None]  # (k, m, 3)
    u = np.einsum("kmi,mi->km", tvec, pvec) * inv
    qvec = np.cross(tvec, e1[None])
    v = np.einsum("i,kmi->km", direction, qvec) * inv
    t = np.einsum("mi,kmi->km", e2, qvec) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    return np.where(hit, top - t, np.nan)


def _random_closed_meshes(seed: int = 0) -> np.ndarray:
    """A tilted sphere, a rotated box and a small cone, overlapping, as triangles (m, 3, 3)."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=3.0)
    sphere.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    sphere.apply_translation([0.7, -0.4, 1.0])
    box = trimesh.creation.box(extents=[4.0, 2.5, 1.5])
    box.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    box.apply_translation([-2.5, 1.5, 0.5])
    cone = trimesh.creation.cone(radius=1.2, height=2.0, sections=24)
    cone.apply_translation([2.5, 2.5, -1.0])
    return np.concatenate([sphere.triangles, box.triangles, cone.triangles])


@pytest.mark.parametrize("reduce", ["min", "max"])
def test_matches_vertical_ray_casting(reduce):
    tri = _random_closed_meshes()
    grid = RasterGrid.covering([-6.0, -4.0], [5.0, 5.0], 0.037)
    r = rasterize_triangles(tri, grid, reduce=reduce, return_face_index=True, return_barycentric=True)
    rng = np.random.default_rng(1)
    iy = rng.integers(0, grid.ny, 400)
    ix = rng.integers(0, grid.nx, 400)
    xy = np.stack([grid.x_mm[ix], grid.y_mm[iy]], axis=1)
    hits = _vertical_ray_hits(tri, xy)
    any_hit = ~np.all(np.isnan(hits), axis=1)
    assert any_hit.sum() > 150 and (~any_hit).sum() > 20  # both cases are exercised
    expect = np.full(len(xy), np.nan)
    red = np.nanmin if reduce == "min" else np.nanmax
    expect[any_hit] = red(hits[any_hit], axis=1)
    got = r.z_mm[iy, ix]
    np.testing.assert_array_equal(np.isnan(got), ~any_hit)
    np.testing.assert_allclose(got[any_hit], expect[any_hit], atol=1e-9)
    # The reported face is hit by the ray at the reported z, and its barycentric weights
    # reproduce the pixel centre and z.
    face = r.face_index[iy, ix]
    assert np.all((face >= 0) == any_hit)
    f = face[any_hit]
    np.testing.assert_allclose(hits[np.flatnonzero(any_hit), f], got[any_hit], atol=1e-9)
    w = r.barycentric[iy[any_hit], ix[any_hit]]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    assert w.min() > -1e-9
    recon = np.einsum("ki,kij->kj", w, tri[f])
    np.testing.assert_allclose(recon[:, :2], xy[any_hit], atol=1e-9)
    np.testing.assert_allclose(recon[:, 2], got[any_hit], atol=1e-9)


def test_tilted_plane_is_exact_and_coverage_is_the_square():
    # Two triangles over [-2, 3] x [-1, 2] carrying z = 0.3 x - 0.7 y + 1.1.
    def plane(x, y):
        return 0.3 * x - 0.7 * y + 1.1

    corners = np.array([[-2.0, -1.0], [3.0, -1.0], [3.0, 2.0], [-2.0, 2.0]])
    xyz = np.concatenate([corners, plane(corners[:, 0], corners[:, 1])[:, None]], axis=1)
    tri = xyz[np.array([[0, 1, 2], [0, 2, 3]])]
    grid = RasterGrid(-3.0, -2.0, 0.1, 71, 51)  # centres on multiples of 0.1
    r = rasterize_triangles(tri, grid)
    centres = grid.pixel_centres_mm()
    x, y = centres[..., 0], centres[..., 1]
    inside = (x >= -2 - 1e-9) & (x <= 3 + 1e-9) & (y >= -1 - 1e-9) & (y <= 2 + 1e-9)
    np.testing.assert_array_equal(r.covered, inside)  # boundary centres included, no crack
    np.testing.assert_allclose(r.z_mm[inside], plane(x, y)[inside], atol=1e-12)


def test_upper_envelope_of_mesh_sphere_within_facet_error():
    radius = 5.0
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    # An inscribed polyhedron lies inside the sphere and within its facet sagitta of it.
    centres = sphere.triangles_center
    sagitta = radius - np.linalg.norm(centres, axis=1).min()
    grid = RasterGrid.covering([-6.0, -6.0], [6.0, 6.0], 0.05)
    r = rasterize_triangles(sphere.triangles, grid, reduce="max")
    c = grid.pixel_centres_mm()
    rho2 = c[..., 0] ** 2 + c[..., 1] ** 2
    inner = rho2 < (0.9 * radius) ** 2
    cap = np.sqrt(radius**2 - rho2[inner])
    err = r.z_mm[inner] - cap
    assert np.all(err <= 1e-9)
    # Vertical error is the normal sagitta divided by the cosine of the surface slope.
    assert np.all(err >= -sagitta * radius / cap - 1e-9)
    assert not np.any(r.covered[rho2 > (radius + 1e-6) ** 2])


def test_pixel_centres_on_shared_edges_and_vertices_leave_no_crack():
    # A triangulated heightfield whose vertices are pixel centres and whose diagonals run
    # through pixel centres: every centre of the covered square lies on an edge or vertex.
    n = 12
    xs = np.arange(n + 1) * 0.5
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    gz = np.sin(gx) * np.cos(gy)
    v = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
    k = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    quads = np.stack([k, k + 1, k + n + 2, k + n + 1], axis=1)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    grid = RasterGrid(0.0, 0.0, 0.25, 2 * n + 1, 2 * n + 1)
    for reduce in ("min", "max"):
        r = rasterize_triangles(v[faces], grid, reduce=reduce)
        assert r.covered.all()
        # Values at the vertices are the vertex heights exactly.
        np.testing.assert_allclose(r.z_mm[::2, ::2], gz, atol=1e-12)


def test_ties_go_to_the_lowest_face_index():
    t = np.array([[[0, 0, 1.0], [2, 0, 1.0], [0, 2, 1.0]]])
    tri = np.concatenate([t, t, t])
    grid = RasterGrid(0.25, 0.25, 0.5, 2, 2)
    r = rasterize_triangles(tri[::-1].copy(), grid, return_face_index=True)
    assert np.all(r.face_index[r.covered] == 0)
    assert r.covered.sum() == 4


def test_chunked_equals_unchunked(monkeypatch):
    tri = _random_closed_meshes(seed=3)
    grid = RasterGrid.covering([-6.0, -4.0], [5.0, 5.0], 0.05)
    ref = rasterize_triangles(tri, grid, return_face_index=True)
    monkeypatch.setattr(raster, "_CHUNK_PIXELS", 500)
    got = rasterize_triangles(tri, grid, return_face_index=True)
    np.testing.assert_array_equal(got.z_mm, ref.z_mm)
    np.testing.assert_array_equal(got.face_index, ref.face_index)


def test_vertical_walls_and_steep_slivers_do_not_extrapolate():
    # A box: its vertical walls have zero xy area. A nearly vertical sliver rising from z = 0
    # to 5 over 1e-6 mm must give its bottom edge's z on that edge, not an extrapolation.
    box = trimesh.creation.box(extents=[2.0, 2.0, 1.0])
    sliver = np.array([[[1.5, -1.0, 0.0], [1.5, 1.0, 0.0], [1.5 + 1e-6, 0.0, 5.0]]])
    grid = RasterGrid(-1.5, -1.5, 0.5, 7, 7)
    r = rasterize_triangles(np.concatenate([box.triangles, sliver]), grid, reduce="min")
    assert np.nanmin(r.z_mm[:, :6]) == pytest.approx(-0.5)
    np.testing.assert_allclose(r.z_mm[1:6, 6], 0.0, atol=1e-6)
    assert not r.covered[0, 6] and not r.covered[6, 6]
    rmax = rasterize_triangles(box.triangles, grid, reduce="max")
    np.testing.assert_array_equal(rmax.covered[1:6, 1:6], True)
    np.testing.assert_allclose(rmax.z_mm[1:6, 1:6], 0.5)
    assert not rmax.covered[0].any() and not rmax.covered[:, 0].any()


@pytest.mark.parametrize("tilt_rad", [0.0, 1e-12, 1e-4, 1e-2])
def test_centres_on_a_near_vertical_wall_take_the_lower_surface(tilt_rad):
    # A wedge with bottom z = 0.3 x and top z = 1 whose walls y = +-1 pass through pixel
    # centres, tilted about x so the walls are exactly, numerically or slightly not vertical.
    # Wall triangles span z from -0.3 to 1; on the wall line the lower envelope is 0.3 x.
    corners = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (0.3 * x, 1.0)])
    wedge = trimesh.convex.convex_hull(corners)
    wedge.apply_transform(trimesh.transformations.rotation_matrix(tilt_rad, [1, 0, 0]))
    grid = RasterGrid(-1.5, -1.5, 0.25, 13, 13)
    r = rasterize_triangles(wedge.triangles, grid, reduce="min")
    if tilt_rad < 1e-9:
        x = grid.pixel_centres_mm()[..., 0]
        assert r.covered[2:11, 2:11].all() and r.covered.sum() == 81
        np.testing.assert_allclose(r.z_mm[2:11, 2:11], 0.3 * x[2:11, 2:11], atol=1e-9)
    else:
        # Tilted walls have an xy footprint of their own: compare with ray casting, which is
        # unambiguous here because no pixel centre lies exactly on an edge any more.
        hits = _vertical_ray_hits(wedge.triangles, grid.pixel_centres_mm().reshape(-1, 2))
        hit = ~np.all(np.isnan(hits), axis=1)
        expect = np.full(len(hits), np.nan)
        expect[hit] = np.nanmin(hits[hit], axis=1)
        # Unless, at x = 0, the bottom face misses a wall line by only 1 - cos(tilt), less than
        # edge_tolerance_mm: then the raster covers that centre with the bottom face's z = 0 where
        # the ray meets the wall at about tilt / 2 (or misses).
        ambiguous = 1.0 - math.cos(tilt_rad) < raster.EDGE_TOLERANCE_MM
        extra = r.covered.ravel() & ~hit
        assert r.covered.ravel()[hit].all()
        assert extra.sum() == (1 if ambiguous else 0)
        atol = 0.51 * tilt_rad if ambiguous else 1e-9
        np.testing.assert_allclose(r.z_mm.ravel()[hit], expect[hit], atol=atol)


def test_empty_and_offgrid_input():
    grid = RasterGrid(0.0, 0.0, 1.0, 4, 3)
    r = rasterize_triangles(np.zeros((0, 3, 3)), grid, return_face_index=True, return_barycentric=True)
    assert r.z_mm.shape == (3, 4) and np.isnan(r.z_mm).all()
    assert np.all(r.face_index == -1) and r.barycentric.shape == (3, 4, 3)
    far = np.array([[[100.0, 100, 0], [101, 100, 0], [100, 101, 0]]])
    assert np.isnan(rasterize_triangles(far, grid).z_mm).all()


@pytest.mark.parametrize(
    "tri, kwargs, match",
    [
        (np.zeros((2, 3)), {}, r"shape \(m, 3, 3\)"),
        (np.full((1, 3, 3), np.nan), {}, "NaN or inf"),
        (np.zeros((1, 3, 3)), {"reduce": "mean"}, "'min' or 'max'"),
        (np.zeros((1, 3, 3)), {"edge_tolerance_mm": -1.0}, "edge_tolerance_mm"),
    ],
)
def test_bad_input_is_named(tri, kwargs, match):
    with pytest.raises(ValueError, match=match):
        rasterize_triangles(tri, RasterGrid(0.0, 0.0, 1.0, 2, 2), **kwargs)


@pytest.mark.parametrize(
    "args, match",
    [((0.0, 0.0, 0.0, 2, 2), "pitch_mm"), ((0.0, 0.0, 1.0, 0, 2), "nx"), ((np.nan, 0.0, 1.0, 2, 2), "x0_mm")],
)
def test_bad_grid_is_named(args, match):
    with pytest.raises(ValueError, match=match):
        RasterGrid(*args)
