"""Deterministic builders of closed triangle meshes (mm) for procedural indenters.

Plain functions returning ``trimesh.Trimesh`` solids with outward normals. Curved surfaces are
faceted so that the chord error of every sampled curve (profile, circle) is at most
``facet_error_mm`` (default :data:`FACET_ERROR_MM`); a triangle of a doubly curved surface (sphere)
then lies at most about twice that inside the true surface.

Two-dimensional regions are given as ``(vertices (n, 2), triangles (k, 3), loops)``: triangles
counter-clockwise seen from +z, ``loops`` the boundary cycles as vertex-index arrays with the
region on their left (outer boundary counter-clockwise, holes clockwise).
"""

from __future__ import annotations

import math

import numpy as np

#: Default largest chord (facet) error of curved surfaces, mm.
FACET_ERROR_MM = 1e-3


def sections_for(radius_mm: float, facet_error_mm: float = FACET_ERROR_MM, minimum: int = 16) -> int:
    """Number of equal segments (a multiple of 8) of a circle of ``radius_mm`` whose chord
    error ``r (1 - cos(pi / n))`` is at most ``facet_error_mm``."""
    if facet_error_mm >= radius_mm:
        return minimum
    n = math.ceil(math.pi / math.acos(1.0 - facet_error_mm / radius_mm))
    return max(minimum, 8 * math.ceil(n / 8))


def revolved(profile_rz, sections: int):
    """Solid of revolution about the z axis.

    profile_rz : (n, 2) float, mm: (radius, z) from a point on the axis at the bottom, outwards
        and up, to a point on the axis at the top.
    """
    import trimesh

    profile = np.asarray(profile_rz, dtype=np.float64)
    mesh = trimesh.creation.revolve(profile, sections=int(sections))
    return closed_solid(mesh, "solid of revolution")


def sphere(radius_mm: float, facet_error_mm: float = FACET_ERROR_MM):
    """Sphere of ``radius_mm`` with a vertex at its lowest point (0, 0, 0) (centre at z = R)."""
    n = sections_for(radius_mm, facet_error_mm)
    a = np.linspace(-0.5 * math.pi, 0.5 * math.pi, n // 2 + 1)
    profile = np.stack([radius_mm * np.cos(a), radius_mm * (1.0 + np.sin(a))], axis=1)
    profile[[0, -1], 0] = 0.0
    return revolved(profile, n)


def ellipsoid(semi_axes_mm, facet_error_mm: float = FACET_ERROR_MM):
    """Ellipsoid with semi-axes (a, b, c) along x, y, z (mm), lowest point at (0, 0, 0)."""
    axes = np.asarray(semi_axes_mm, dtype=np.float64)
    mesh = sphere(1.0, facet_error_mm / axes.max())
    mesh.apply_scale(axes)
    return mesh


def paraboloid(tip_radius_mm: float, height_mm: float, facet_error_mm: float = FACET_ERROR_MM):
    """Solid bounded by ``z = r^2 / (2 R)`` below and the plane ``z = height_mm`` above."""
    r_top = math.sqrt(2.0 * tip_radius_mm * height_mm)
    # Chord error of the profile ~ step^2 * curvature / 8; curvature <= 1 / R.
    step = math.sqrt(8.0 * facet_error_mm * tip_radius_mm)
    r = np.linspace(0.0, r_top, max(16, math.ceil(r_top / step)) + 1)
    profile = np.concatenate([np.stack([r, r * r / (2 * tip_radius_mm)], axis=1), [[0.0, height_mm]]])
    return revolved(profile, sections_for(r_top, facet_error_mm))


def disc_prism(radius_mm: float, z0_mm: float, z1_mm: float, facet_error_mm: float = FACET_ERROR_MM):
    """Circular cylinder about the z axis from z0 to z1 (mm)."""
    profile = [[0.0, z0_mm], [radius_mm, z0_mm], [radius_mm, z1_mm], [0.0, z1_mm]]
    return revolved(profile, sections_for(radius_mm, facet_error_mm))


def box(lo_mm, hi_mm):
    """Axis-aligned box between corners ``lo_mm`` and ``hi_mm`` (each (3,), mm)."""
    import trimesh

    lo = np.asarray(lo_mm, dtype=np.float64)
    hi = np.asarray(hi_mm, dtype=np.float64)
    mesh = trimesh.creation.box(extents=hi - lo)
    mesh.apply_translation((lo + hi) / 2)
    return mesh


def convex_solid(points_mm):
    """Convex hull of points (n, 3) mm."""
    import trimesh

    return closed_solid(trimesh.convex.convex_hull(np.asarray(points_mm, dtype=np.float64)), "convex hull")


def regular_polygon(n_sides: int, circumradius_mm: float, phase_rad: float = 0.0) -> np.ndarray:
    """Vertices (n_sides, 2) mm of a regular polygon centred at the origin, counter-clockwise."""
    a = phase_rad + 2.0 * math.pi * np.arange(n_sides) / n_sides
    return circumradius_mm * np.stack([np.cos(a), np.sin(a)], axis=1)


def convex_prism(polygon_xy_mm, z0_mm: float, z1_mm: float):
    """Straight prism over a convex polygon (n, 2) mm from z0 to z1."""
    p = np.asarray(polygon_xy_mm, dtype=np.float64)
    return convex_solid(np.concatenate([np.c_[p, np.full(len(p), z0_mm)], np.c_[p, np.full(len(p), z1_mm)]]))


def prism(vertices_xy_mm, triangles, loops, z0_mm: float, z1_mm: float):
    """Straight prism from z0 to z1 (mm) over a triangulated planar region (see module doc)."""
    import trimesh

    v2 = np.asarray(vertices_xy_mm, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    n = len(v2)
    vertices = np.concatenate([np.c_[v2, np.full(n, z0_mm)], np.c_[v2, np.full(n, z1_mm)]])
    faces = [tri[:, ::-1], tri + n]  # bottom faces down, top faces up
    for loop in loops:
        i = np.asarray(loop, dtype=np.int64)
        j = np.roll(i, -1)
        faces.append(np.stack([i, j, j + n], axis=1))
        faces.append(np.stack([i, j + n, i + n], axis=1))
    mesh = trimesh.Trimesh(vertices, np.concatenate(faces), process=True)
    return closed_solid(mesh, "prism")


def polar_region(phi_rad, r_outer_mm, r_inner_mm=None):
    """Planar region between two star-shaped curves sampled at the same increasing angles.

    phi_rad : (s,) increasing angles covering one turn; r_outer_mm, r_inner_mm : (s,) radii (mm)
    (``r_inner_mm`` None: the region reaches the origin). Returns (vertices, triangles, loops).
    """
    phi = np.asarray(phi_rad, dtype=np.float64)
    ro = np.broadcast_to(np.asarray(r_outer_mm, dtype=np.float64), phi.shape)
    s = len(phi)
    outer = np.stack([ro * np.cos(phi), ro * np.sin(phi)], axis=1)
    k = np.arange(s)
    if r_inner_mm is None:
        vertices = np.concatenate([[[0.0, 0.0]], outer])
        triangles = np.stack([np.zeros(s, np.int64), 1 + k, 1 + (k + 1) % s], axis=1)
        return vertices, triangles, [1 + k]
    ri = np.broadcast_to(np.asarray(r_inner_mm, dtype=np.float64), phi.shape)
    inner = np.stack([ri * np.cos(phi), ri * np.sin(phi)], axis=1)
    vertices = np.concatenate([outer, inner])
    o, o1, i, i1 = k, (k + 1) % s, s + k, s + (k + 1) % s
    triangles = np.concatenate([np.stack([o, o1, i1], axis=1), np.stack([o, i1, i], axis=1)])
    return vertices, triangles, [k, (s + k)[::-1]]


def strip_region(x_mm, lower_mm, upper_mm):
    """Planar region between two chains over the same increasing abscissae.

    x_mm, lower_mm, upper_mm : (n,) with lower < upper. Returns (vertices, triangles, loops) in
    the (x, second coordinate) plane.
    """
    x = np.asarray(x_mm, dtype=np.float64)
    n = len(x)
    vertices = np.concatenate([np.c_[x, lower_mm], np.c_[x, upper_mm]])
    k = np.arange(n - 1)
    lo, lo1, up, up1 = k, k + 1, n + k, n + k + 1
    triangles = np.concatenate([np.stack([lo, lo1, up1], axis=1), np.stack([lo, up1, up], axis=1)])
    loop = np.concatenate([np.arange(n), np.arange(2 * n - 1, n - 1, -1)])
    return vertices, triangles, [loop]


def xz_profile_solid(x_mm, z_lower_mm, z_upper_mm, thickness_y_mm: float):
    """Solid whose cross-section in the x-z plane lies between ``z_lower(x)`` and ``z_upper(x)``,
    extruded symmetrically along y over ``thickness_y_mm`` (a blade seen edge-on)."""
    v, t, loops = strip_region(x_mm, z_lower_mm, z_upper_mm)
    mesh = prism(v, t, loops, -0.5 * thickness_y_mm, 0.5 * thickness_y_mm)
    # Rotation (u, v, w) -> (u, -w, v): the profile plane becomes x-z, the extrusion y.
    rot = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
    mesh.apply_transform(rot)
    return mesh


def heightfield_solid(x_mm, y_mm, height_mm, top_mm: float):
    """Solid over the rectangle spanned by grid lines x (nx,) and y (ny,) (mm) whose lower face
    is ``z = height_mm`` (ny, nx) and whose upper face is the plane ``z = top_mm``."""
    import trimesh

    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    h = np.asarray(height_mm, dtype=np.float64)
    nx, ny = len(x), len(y)
    if h.shape != (ny, nx) or np.any(h >= top_mm):
        raise ValueError(f"height_mm must be (ny, nx) = {(ny, nx)} below top_mm={top_mm}")
    gx, gy = np.meshgrid(x, y, indexing="xy")
    bottom = np.stack([gx, gy, h], axis=-1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = [np.stack([a, c, b], axis=1), np.stack([a, d, c], axis=1)]  # facing down
    # Boundary loop, counter-clockwise from above, and a matching top cap.
    loop = np.concatenate([idx[0, :-1], idx[:-1, -1], idx[-1, :0:-1], idx[:0:-1, 0]])
    m = len(loop)
    top = np.c_[bottom[loop, :2], np.full(m, top_mm)]
    centre = len(bottom) + m
    t = len(bottom) + np.arange(m)
    t1 = np.roll(t, -1)
    j = np.roll(loop, -1)
    faces += [np.stack([loop, j, t1], axis=1), np.stack([loop, t1, t], axis=1),
              np.stack([t, t1, np.full(m, centre)], axis=1)]
    vertices = np.concatenate([bottom, top, [[x.mean(), y.mean(), top_mm]]])
    return closed_solid(trimesh.Trimesh(vertices, np.concatenate(faces), process=True), "heightfield solid")


def union(parts):
    """Assemble closed parts (which may overlap) into one mesh without merging vertices."""
    import trimesh

    return trimesh.util.concatenate(list(parts))


def closed_solid(mesh, what: str):
    """``mesh`` checked to be closed and consistently wound, turned inside out if needed so that
    its normals point outwards (positive volume); ``what`` names it in the error."""
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        raise RuntimeError(f"{what}: mesh is not closed ({len(mesh.faces)} faces)")
    if mesh.volume <= 0:
        mesh.invert()
    return mesh
