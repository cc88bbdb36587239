"""The pad's tetrahedral mesh: vertices, tets, node sets, surface faces and content hash.

The vertex order of a frozen pad mesh is the contract of every exported model: an ONNX graph
outputs vertices in exactly this order. :func:`content_hash` identifies it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from tactile_deploy.pad.geometry import PadGeometry
from tactile_deploy.pad.meshing import extrude, plane_points, plane_triangles

# Faces of a positively oriented tet (v0, v1, v2, v3), each wound so its normal points outward.
_TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def content_hash(vertices: np.ndarray, tets: np.ndarray) -> str:
    """sha256 (hex) of the vertex coordinates in whole nanometres (int64) and the tets (int32).

    Rounding to nanometres makes the hash independent of last-bit differences in floating
    point between platforms while any real change of the mesh changes it.
    """
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.rint(np.asarray(vertices) * 1e6), dtype="<i8").tobytes())
    h.update(np.ascontiguousarray(tets, dtype="<i4").tobytes())
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class PadMesh:
    """A layered tetrahedral pad mesh in the sensor frame.

    Attributes
    ----------
    geometry : PadGeometry
        The configuration it was built from.
    vertices : (n, 3) float64, mm, sensor frame
        Rest positions. Node ``layer * n_plane + i`` is in-plane point ``i`` on layer ``layer``;
        layer 0 is the sensing surface, the last layer lies on the backplate.
    tets : (m, 4) int32
        Positively oriented tetrahedra.
    plane_triangles : (t, 3) int32
        In-plane triangles of one layer (indices < n_plane), counter-clockwise seen from +z.
    """

    geometry: PadGeometry
    vertices: np.ndarray
    tets: np.ndarray
    plane_triangles: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_nodes(self) -> int:
        return len(self.vertices)

    @property
    def n_plane(self) -> int:
        """Nodes per layer (= number of sensing-surface nodes)."""
        return self.n_nodes // (self.geometry.n_layers + 1)

    @property
    def sensing_nodes(self) -> np.ndarray:
        """Indices of the sensing (top) surface nodes, (n_plane,) int64: 0 .. n_plane - 1."""
        return np.arange(self.n_plane)

    @property
    def backplate_nodes(self) -> np.ndarray:
        """Indices of the nodes bonded to the rigid backplate (bottom layer), (n_plane,) int64."""
        return np.arange(self.n_nodes - self.n_plane, self.n_nodes)

    @cached_property
    def side_nodes(self) -> np.ndarray:
        """Indices of the side-wall nodes (rim of every layer, top and bottom rims included)."""
        xy = self.vertices[: self.n_plane, :2]
        g = self.geometry
        if g.shape == "disc":
            rim = np.abs(np.hypot(xy[:, 0], xy[:, 1]) - g.radius_mm) < 1e-9 * g.radius_mm + 1e-12
        else:
            tol = 1e-9 * g.half_extent_mm
            rim = (np.abs(np.abs(xy[:, 0]) - 0.5 * g.width_mm) < tol) | (
                np.abs(np.abs(xy[:, 1]) - 0.5 * g.length_mm) < tol
            )
        plane_rim = np.flatnonzero(rim)
        layers = np.arange(g.n_layers + 1)[:, None] * self.n_plane
        return (layers + plane_rim[None, :]).ravel()

    @cached_property
    def symmetry_nodes(self) -> dict[str, np.ndarray]:
        """Nodes on the symmetry planes of a quarter model: ``{"x0": ..., "y0": ...}`` (empty for full pads)."""
        if self.geometry.sector_deg == 360.0:
            return {"x0": np.zeros(0, np.int64), "y0": np.zeros(0, np.int64)}
        tol = 1e-9 * self.geometry.half_extent_mm
        xy = self.vertices[:, :2]
        return {"x0": np.flatnonzero(np.abs(xy[:, 0]) < tol), "y0": np.flatnonzero(np.abs(xy[:, 1]) < tol)}

    @property
    def node_sets(self) -> dict[str, np.ndarray]:
        """Named node sets: ``backplate`` (fixed), ``sensing`` (top), ``side`` (wall)."""
        return {
            "backplate": self.backplate_nodes,
            "sensing": self.sensing_nodes,
            "side": self.side_nodes,
        }

    @property
    def sensing_faces(self) -> np.ndarray:
        """Triangles of the sensing surface, (t, 3) int32, normals pointing +z (out of the gel)."""
        return self.plane_triangles

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """All outer faces of the volume, (f, 3) int32, wound with outward normals."""
        faces = self.tets[:, _TET_FACES].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return faces[counts[inverse.ravel()] == 1].astype(np.int32)

    @cached_property
    def edges(self) -> np.ndarray:
        """Unique undirected edges of the tet mesh, (e, 2) int64 with i < j."""
        pairs = self.tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
        return np.unique(np.sort(pairs, axis=1), axis=0)

    @cached_property
    def content_hash(self) -> str:
        return content_hash(self.vertices, self.tets)

    def sensing_nodal_areas_mm2(self) -> np.ndarray:
        """Lumped area of each sensing node (one third of adjacent triangle areas), (n_plane,) mm^2."""
        p = self.vertices[self.plane_triangles]
        area = 0.5 * np.abs(
            (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
            - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
        )
        out = np.zeros(self.n_plane)
        np.add.at(out, self.plane_triangles.ravel(), np.repeat(area / 3.0, 3))
        return out


def build_pad_mesh(geometry: PadGeometry) -> PadMesh:
    """Generate the pad mesh of ``geometry`` (deterministic: same config, same mesh)."""
    points = plane_points(geometry)
    triangles = plane_triangles(points, geometry)
    vertices, tets = extrude(points, triangles, geometry)
    return PadMesh(
        geometry=geometry,
        vertices=vertices,
        tets=tets.astype(np.int32),
        plane_triangles=triangles.astype(np.int32),
    )
