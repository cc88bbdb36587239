"""Deterministic tetrahedral meshing of a pad by layered extrusion.

Data flow: ``PadGeometry`` -> in-plane points (rings for a disc, a grid for a box) -> 2-D
Delaunay triangles -> one copy of the points per node layer, top (sensing surface) first ->
each prism between two layers split into three tetrahedra.

The prism split uses the global 2-D node numbers: the quad face between 2-D nodes a < b is
always cut along the diagonal from a's upper node to b's lower node. Both prisms sharing a quad
face then cut it the same way, so the mesh is conforming, and the three diagonals of one prism
are never cyclic, so every prism splits into exactly three tetrahedra.

Node order (the contract of every exported model): node ``layer * n_plane + i`` is 2-D point
``i`` on layer ``layer``; layer 0 is the sensing surface, the last layer the backplate.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import Delaunay

from tactile_deploy.pad.geometry import PadGeometry

# Ring k of a disc is rotated by k times this fraction of its own node pitch. An irrational
# value avoids co-circular point quadruples, whose Delaunay triangulation would be ambiguous.
_RING_PHASE = (math.sqrt(5.0) - 1.0) / 2.0


def _ring_radii(geometry: PadGeometry) -> np.ndarray:
    """Radii (mm) of the node rings of a disc, centre excluded, outer rim last."""
    radius = geometry.radius_mm
    if geometry.core_radius_mm <= 0:
        n_rings = max(1, round(radius / geometry.edge_mm))
        return radius * np.arange(1, n_rings + 1) / n_rings
    radii = []
    r = 0.0
    h = geometry.core_edge_mm
    while True:
        if r + 0.5 * h >= geometry.core_radius_mm:
            h = min(h * geometry.edge_growth, geometry.edge_mm)
        r_next = r + h
        if r_next >= radius - 0.5 * h:
            break
        radii.append(r_next)
        r = r_next
    radii.append(radius)
    return np.asarray(radii)


def box_axis_coords(extent_mm: float, core_half_mm: float, core_edge_mm: float,
                    edge_mm: float, growth: float) -> np.ndarray:
    """Node coordinates (mm, ascending, symmetric about 0) along one side of a box.

    Without a core (``core_half_mm`` = 0): uniform, as close to ``edge_mm`` as divides the side.
    With one: uniform at most ``core_edge_mm`` inside +-``core_half_mm``, then each interval
    ``growth`` times the previous one, at most ``edge_mm``, out to the side's ends (the last
    intervals scaled together so that they end exactly at the side).
    """
    half = 0.5 * extent_mm
    if core_half_mm <= 0:
        n = max(1, round(extent_mm / edge_mm))
        return np.linspace(-half, half, n + 1)
    core_half = min(core_half_mm, half)
    n_core = max(1, math.ceil(2.0 * core_half / core_edge_mm - 1e-9))
    core = np.linspace(-core_half, core_half, n_core + 1)
    h = 2.0 * core_half / n_core
    margin = half - core_half
    if margin <= 1e-9:
        return core
    steps = []
    while sum(steps) < margin:
        h = min(h * growth, edge_mm)
        steps.append(h)
    # n or n - 1 growing intervals, stretched or shrunk to end exactly at the side
    options = [steps] + ([steps[:-1]] if len(steps) > 1 else [])
    best = min(options, key=lambda st: abs(np.log(margin / sum(st))))
    right = core_half + np.cumsum(np.asarray(best) * (margin / sum(best)))
    right[-1] = half
    return np.concatenate([-right[::-1], core, right])


def _box_axes(geometry: PadGeometry) -> tuple[np.ndarray, np.ndarray]:
    g = geometry
    xs = box_axis_coords(g.width_mm, g.core_half_width_mm, g.core_edge_mm, g.edge_mm,
                         g.edge_growth)
    ys = box_axis_coords(g.length_mm, g.core_half_length_mm, g.core_edge_mm, g.edge_mm,
                         g.edge_growth)
    return xs, ys


def plane_points(geometry: PadGeometry) -> np.ndarray:
    """In-plane node positions of one layer, (n_plane, 2) float64, mm (sensor frame x, y)."""
    if geometry.shape == "box":
        xs, ys = _box_axes(geometry)
        gx, gy = np.meshgrid(xs, ys, indexing="xy")
        return np.stack([gx.ravel(), gy.ravel()], axis=1)
    points = [np.zeros((1, 2))]
    radii = _ring_radii(geometry)
    previous = 0.0
    for k, r in enumerate(radii, start=1):
        spacing = r - previous
        previous = r
        if geometry.sector_deg == 360.0:
            n = max(6, round(2.0 * math.pi * r / spacing))
            phase = (k * _RING_PHASE) % 1.0
            angles = 2.0 * math.pi * (np.arange(n) + phase) / n
        else:  # quarter: both straight edges carry nodes (symmetry planes)
            n = max(1, round(0.5 * math.pi * r / spacing))
            angles = 0.5 * math.pi * np.arange(n + 1) / n
        points.append(np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1))
    return np.concatenate(points, axis=0)


def plane_triangles(points_xy: np.ndarray, geometry: PadGeometry) -> np.ndarray:
    """Counter-clockwise triangles (n_tri, 3) int64 over the in-plane points."""
    if geometry.shape == "box":
        xs, ys = _box_axes(geometry)
        nx, ny = len(xs) - 1, len(ys) - 1
        idx = np.arange((nx + 1) * (ny + 1)).reshape(ny + 1, nx + 1)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    else:
        tris = Delaunay(points_xy, qhull_options="Qbb Qc Qz Q12").simplices.astype(np.int64)
    p = points_xy[tris]
    cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (
        p[:, 1, 1] - p[:, 0, 1]
    ) * (p[:, 2, 0] - p[:, 0, 0])
    tris[cross < 0] = tris[cross < 0][:, [0, 2, 1]]
    # Canonical order, independent of the triangulator's internal numbering.
    first = np.argmin(tris, axis=1)
    tris = np.stack([np.roll(t, -f) for t, f in zip(tris, first)]) if len(tris) else tris
    order = np.lexsort((tris[:, 2], tris[:, 1], tris[:, 0]))
    return tris[order]


def layer_fractions(geometry: PadGeometry) -> np.ndarray:
    """Depth fraction s in [0, 1] of each node layer, top (0) to backplate (1)."""
    n = geometry.n_layers
    if geometry.top_layer_mm <= 0 or geometry.layer_growth == 1.0:
        return np.linspace(0.0, 1.0, n + 1)
    thickness = geometry.top_layer_mm * geometry.layer_growth ** np.arange(n)
    s = np.concatenate([[0.0], np.cumsum(thickness)])
    return s / s[-1]


def extrude(points_xy: np.ndarray, triangles: np.ndarray, geometry: PadGeometry):
    """Stack the plane into node layers and split each prism into three tetrahedra.

    Returns ``(vertices (n, 3) float64 mm, tets (m, 4) int64)`` with positive tet volumes.
    """
    n_plane = len(points_xy)
    s = layer_fractions(geometry)
    z_top = np.broadcast_to(
        geometry.top_height_mm(points_xy[:, 0], points_xy[:, 1]), (n_plane,)
    )
    z_bottom = -geometry.thickness_mm
    vertices = np.concatenate(
        [
            np.column_stack([points_xy, (1.0 - f) * z_top + f * z_bottom])
            for f in s
        ]
    )
    tri = np.sort(triangles, axis=1)  # a < b < c, the rule that makes the split conforming
    tets = []
    for layer in range(geometry.n_layers):
        up = tri + layer * n_plane
        lo = tri + (layer + 1) * n_plane
        a, b, c = up.T
        qa, qb, qc = lo.T
        tets.append(np.stack([a, b, c, qc], 1))
        tets.append(np.stack([a, b, qb, qc], 1))
        tets.append(np.stack([a, qa, qb, qc], 1))
    tets = np.concatenate(tets)
    vol = signed_volumes(vertices, tets)
    flip = vol < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return vertices, tets


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron, (m,) mm^3 (positive = right-handed)."""
    p = vertices[tets]
    return np.einsum(
        "ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]
    ) / 6.0
