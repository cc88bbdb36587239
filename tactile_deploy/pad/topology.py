"""The topology file of the ONNX contract: the fixed mesh every prediction shares.

``MeshTopology.from_pad`` builds it from a shipped pad asset; :meth:`MeshTopology.save` writes the
``topology.npz`` that plugins carry for programs using the ONNX model without tactile-deploy
(docs/onnx_contract.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from tactile_deploy.atomic import write_npz
from tactile_deploy.pad.asset import load_pad


@dataclass(frozen=True)
class MeshTopology:
    """The fixed mesh every prediction shares (sensor frame, mm).

    rest_vertices_mm : (n, 3) float64 (exact: the mesh hash is computed from it). tets : (m, 4) int32, positively oriented.
    surface_faces : (f, 3) int32, all outer faces, outward normals.
    sensing_faces : (t, 3) int32, faces of the sensing (top) surface, normals +z.
    sensing_nodes : (k,) int64, nodes of the sensing surface. mesh_hash : content hash.
    """

    rest_vertices_mm: np.ndarray
    tets: np.ndarray
    surface_faces: np.ndarray
    sensing_faces: np.ndarray
    sensing_nodes: np.ndarray
    mesh_hash: str

    @classmethod
    def from_pad(cls, pad: str = "gelslim", version: int | None = None) -> MeshTopology:
        mesh = load_pad(pad, version)
        return cls(mesh.vertices.astype(np.float64), mesh.tets.astype(np.int32),
                   mesh.boundary_faces.astype(np.int32), mesh.sensing_faces.astype(np.int32),
                   mesh.sensing_nodes.astype(np.int64), mesh.content_hash)

    def save(self, path: str | os.PathLike) -> None:
        """Write the topology file of the ONNX contract (.npz, atomic)."""
        write_npz(path, rest_vertices_mm=self.rest_vertices_mm, tets=self.tets,
                  surface_faces=self.surface_faces, sensing_faces=self.sensing_faces,
                  sensing_nodes=self.sensing_nodes.astype(np.int32),
                  mesh_hash=np.array(self.mesh_hash))

    @classmethod
    def load(cls, path: str | os.PathLike) -> MeshTopology:
        with np.load(path, allow_pickle=False) as z:
            return cls(z["rest_vertices_mm"].astype(np.float64), z["tets"], z["surface_faces"], z["sensing_faces"],
                       z["sensing_nodes"].astype(np.int64), str(z["mesh_hash"]))
