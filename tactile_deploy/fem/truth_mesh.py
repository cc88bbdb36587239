"""Truth meshes: a pad mesh refined around one contact and graded away from it.

The frozen output mesh of a pad (~1 mm between sensing nodes) cannot resolve a contact smaller
than ~2 mm. The truth solver meshes the pad anew for every contact with gmsh: fine
(``h_fine_mm``, at most the depth-pixel pitch 0.27 mm and smaller for small contacts) over the
region of the sensing surface the indenter can touch, growing linearly with the 3-D distance
from that region (in plane, and more slowly towards the backplate) up to ``h_coarse_mm``. The number of
nodes therefore grows with the contact region, not with the pad.

Data flow of :func:`build_truth_mesh`::

    PadGeometry (disc or box, flat) + refinement region (points on the sensing surface, mm)
        --> size field s(p) = min(h_coarse, h_fine + |((growth - 1) d, (depth_growth - 1) z)|),
            d the in-plane distance from the region, z the depth below the sensing surface
        --> gmsh: OpenCASCADE solid, Frontal-Delaunay surfaces, Delaunay volume, optimised
        --> TruthMesh: sensing-surface nodes first (0 .. n_plane - 1), node sets by surface

Everything is in the sensor frame, mm. The mesh is deterministic for the same inputs (one
meshing thread).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from tactile_deploy.pad.geometry import PadGeometry
from tactile_deploy.pad.mesh import PadMesh

#: Default growth of the edge length away from the contact region, in plane (1 + mm per mm).
BULK_GROWTH = 1.2
#: Default growth of the edge length with depth below the contact region (1 + mm per mm). Under
#: a contact the bulk tets of a nearly incompressible gel are too stiff when coarse: a 2 mm
#: sphere pressed 1.0 mm into the 3 mm layer (nu 0.48) gives x1.025 the independent FEM's force
#: with the edges growing by 0.2 per mm in every direction (0.77 mm tets at the backplate, 3,380
#: nodes), x1.0175 when they grow by 0.15 per mm with depth (0.62 mm there, 4,205 nodes) and
#: x1.011 by 0.1 (5,071 nodes); by 0.15 in every direction (x1.016, 4,971 nodes) the
#: neo-Hookean cone's solve failed (elements folded below its apex), with depth alone it
#: converges (docs/fem.md).
DEPTH_GROWTH = 1.15


@dataclass(frozen=True, eq=False)
class TruthMesh(PadMesh):
    """A truth mesh: like :class:`PadMesh` (sensing nodes first, ``plane_triangles`` = the
    sensing-surface triangles, counter-clockwise from +z) but unstructured below the surface,
    with its own backplate and side node sets."""

    n_sensing: int = 0
    bottom_nodes: np.ndarray | None = None
    wall_nodes: np.ndarray | None = None

    @property
    def n_plane(self) -> int:
        return self.n_sensing

    @property
    def backplate_nodes(self) -> np.ndarray:
        return self.bottom_nodes

    @cached_property
    def side_nodes(self) -> np.ndarray:
        return self.wall_nodes


def build_truth_mesh(geometry: PadGeometry, region_xy: np.ndarray, h_fine_mm: float,
                     h_coarse_mm: float = 2.0, growth: float = BULK_GROWTH,
                     surface_nodes_xy: np.ndarray | None = None,
                     point_sizes: list[tuple[float, float, float]] = (),
                     curvature_sizes: np.ndarray | None = None,
                     curvature_growth: float = 1.5,
                     depth_growth: float = DEPTH_GROWTH) -> TruthMesh:
    """A pad mesh refined over ``region_xy`` (k, 2) mm (points where contact can occur).

    ``h_fine_mm``: edge length over the region; ``h_coarse_mm``: the largest edge length;
    ``growth``: 1 + the increase of the edge length per mm of in-plane distance from the
    region; ``depth_growth``: the same per mm of depth below the sensing surface (the two add as
    the components of a vector);
    ``surface_nodes_xy`` (k, 2): points of the sensing surface that must be nodes (an
    indenter's tip); ``point_sizes``: (x, y, size) triples, finer spots on the sensing surface
    (around a sharp tip) whose size grows by ``growth`` from there; ``curvature_sizes`` (k, 3):
    more such (x, y, size) spots, many (where a curved indenter needs shorter chords), whose
    size grows by ``curvature_growth`` - 1 per mm. The centres of the sensing surface and of the backplate are always nodes
    (so that a uniform expansion leaves the centre in place: the pins of rolling supports).
    """
    import gmsh

    if geometry.sector_deg != 360.0 or geometry.dome_height_mm != 0.0:
        raise ValueError("truth meshes support full flat pads (disc or box); got "
                         f"sector_deg={geometry.sector_deg}, dome_height_mm={geometry.dome_height_mm}")
    region = np.asarray(region_xy, float).reshape(-1, 2)
    tree = cKDTree(region) if len(region) else None
    h = geometry.thickness_mm
    spots = np.zeros((0, 3)) if curvature_sizes is None else np.asarray(curvature_sizes, float)
    spot_tree = cKDTree(spots[:, :2]) if len(spots) else None
    spot_reach = float((h_fine_mm - spots[:, 2].min()) / (curvature_growth - 1.0)) if len(spots) else 0.0

    def size(dim, tag, x, y, z, lc):
        if tree is None:
            return h_coarse_mm
        d, _ = tree.query((x, y))
        d = max(d - 0.5 * h_fine_mm, 0.0)
        out = min(h_coarse_mm, h_fine_mm + (((growth - 1.0) * d) ** 2
                                            + ((depth_growth - 1.0) * z) ** 2) ** 0.5)
        for px, py, ps in point_sizes:
            dp = ((x - px) ** 2 + (y - py) ** 2 + z * z) ** 0.5
            out = min(out, ps + (growth - 1.0) * dp)
        if spot_tree is not None and -z < spot_reach:
            near = spot_tree.query_ball_point((x, y), spot_reach)
            if near:
                q = spots[near]
                dp = np.sqrt((q[:, 0] - x) ** 2 + (q[:, 1] - y) ** 2 + z * z)
                out = min(out, float(np.min(q[:, 2] + (curvature_growth - 1.0) * dp)))
        return out

    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("truth")
        occ = gmsh.model.occ
        if geometry.shape == "disc":
            occ.addCylinder(0, 0, -h, 0, 0, h, geometry.radius_mm)
        else:
            occ.addBox(-0.5 * geometry.width_mm, -0.5 * geometry.length_mm, -h,
                       geometry.width_mm, geometry.length_mm, h)
        occ.synchronize()
        top_tag = bottom_tag = None
        for dim, tag in gmsh.model.getEntities(2):
            _, _, z0, _, _, z1 = gmsh.model.getBoundingBox(dim, tag)
            if abs(z0) < 1e-4 * h and abs(z1) < 1e-4 * h:
                top_tag = tag
            elif abs(z0 + h) < 1e-4 * h and abs(z1 + h) < 1e-4 * h:
                bottom_tag = tag
        geo = gmsh.model.geo
        # The surface's centre and the requested nodes, each once: two points closer than
        # 1e-3 of the fine spacing (a centred indenter's tip found at -3e-14 mm) made gmsh
        # build degenerate and duplicated tets between them.
        top_xy = [(0.0, 0.0)]
        for x, y in ([] if surface_nodes_xy is None else np.reshape(surface_nodes_xy, (-1, 2))):
            if min(np.hypot(x - px, y - py) for px, py in top_xy) > 1e-3 * h_fine_mm:
                top_xy.append((float(x), float(y)))
        top_points = [occ.addPoint(x, y, 0.0) for x, y in top_xy]
        bottom_points = [occ.addPoint(0.0, 0.0, -h)]
        occ.synchronize()
        gmsh.model.mesh.embed(0, top_points, 2, top_tag)
        gmsh.model.mesh.embed(0, bottom_points, 2, bottom_tag)
        del geo
        gmsh.model.mesh.setSizeCallback(size)
        for name, value in (("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.MeshSizeFromPoints", 0),
                            ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.Algorithm", 6),
                            ("Mesh.Algorithm3D", 1), ("Mesh.Optimize", 1),
                            ("Mesh.MaxNumThreads1D", 1), ("Mesh.MaxNumThreads2D", 1),
                            ("Mesh.MaxNumThreads3D", 1)):
            gmsh.option.setNumber(name, value)
        gmsh.model.mesh.generate(3)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        xyz = xyz.reshape(-1, 3)
        index = np.zeros(int(tags.max()) + 1, np.int64)
        index[tags.astype(np.int64)] = np.arange(len(tags))
        _, conn = gmsh.model.mesh.getElementsByType(4)
        tets = index[conn.astype(np.int64)].reshape(-1, 4)
        top_tris, bottom, wall = [], [], []
        for dim, tag in gmsh.model.getEntities(2):
            x0, y0, z0, x1, y1, z1 = gmsh.model.getBoundingBox(dim, tag)
            node_tags, _, _ = gmsh.model.mesh.getNodes(dim, tag, includeBoundary=True)
            nodes = index[node_tags.astype(np.int64)]
            if abs(z0) < 1e-4 * h and abs(z1) < 1e-4 * h:
                _, tri = gmsh.model.mesh.getElementsByType(2, tag)
                top_tris.append(index[tri.astype(np.int64)].reshape(-1, 3))
            elif abs(z0 + h) < 1e-4 * h and abs(z1 + h) < 1e-4 * h:
                bottom.append(nodes)
            else:
                wall.append(nodes)
    finally:
        gmsh.finalize()
    top_tris = np.concatenate(top_tris)
    # Snap the surfaces exactly (gmsh's coordinates carry round-off).
    top = np.unique(top_tris)
    xyz[top, 2] = 0.0
    # Every node on the backplate plane (embedded points are not listed with the surface).
    bottom = np.unique(np.concatenate(bottom + [np.flatnonzero(np.abs(xyz[:, 2] + h) < 1e-6 * h)]))
    xyz[bottom, 2] = -h
    wall = np.unique(np.concatenate(wall))
    # Renumber: sensing nodes first, the others in gmsh's order.
    order = np.concatenate([top, np.setdiff1d(np.arange(len(xyz)), top)])
    new = np.empty(len(order), np.int64)
    new[order] = np.arange(len(order))
    vertices = xyz[order]
    tets = new[tets]
    tris = new[top_tris]
    p = vertices[tris]
    cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (
        p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    tris[cross < 0] = tris[cross < 0][:, [0, 2, 1]]
    from tactile_deploy.pad.meshing import signed_volumes

    vol = signed_volumes(vertices, tets)
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    w = new[wall]
    if geometry.shape == "disc":  # wall nodes exactly on the cylinder
        r = np.hypot(vertices[w, 0], vertices[w, 1])
        vertices[w, :2] *= (geometry.radius_mm / r)[:, None]
    else:  # and on the box's planes
        for axis, half in ((0, 0.5 * geometry.width_mm), (1, 0.5 * geometry.length_mm)):
            on = np.abs(np.abs(vertices[w, axis]) - half) < 1e-6 * half
            vertices[w[on], axis] = np.sign(vertices[w[on], axis]) * half
    g = geometry.model_copy(update={"name": f"{geometry.name}_truth"})
    return TruthMesh(geometry=g, vertices=vertices, tets=tets.astype(np.int32),
                     plane_triangles=tris.astype(np.int32), n_sensing=len(top),
                     bottom_nodes=np.sort(new[bottom]), wall_nodes=np.sort(new[wall]))
