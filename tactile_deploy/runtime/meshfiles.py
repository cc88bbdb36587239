"""Read the mesh files of ``tactile-deploy run`` back, in the pad mesh's vertex order.

Vertex i of every file is vertex i of the pad mesh (``topology.npz``, the model's output order).
The surface files (PLY, OBJ, GLB) hold all vertices, also the interior ones their faces do not
use, so that the order holds: readers that drop unused vertices or merge close ones (trimesh's
default ``process=True``, many mesh tools) renumber the mesh. :func:`read_mesh` keeps it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class MeshFile:
    """A mesh file's content in the sensor frame, mm.

    vertices_mm : (n, 3) float64, vertex i = pad mesh vertex i.
    faces : (f, 3) int64 outer surface triangles (PLY, OBJ, GLB), or None.
    tets : (m, 4) int64 tetrahedra (VTU), or None.
    depth_mm : (128, 128) float32 (NPZ), or None.
    """

    vertices_mm: np.ndarray
    faces: np.ndarray | None = None
    tets: np.ndarray | None = None
    depth_mm: np.ndarray | None = None


def read_mesh(path: str | os.PathLike) -> MeshFile:
    """A ``mesh_<frame>.<ply|obj|glb|vtu|npz>`` file of a run, in the sensor frame, mm, with
    the pad mesh's vertex order (GLB: converted back from metres and glTF's y-up axes)."""
    from tactile_deploy.pad.export import SENSOR_TO_GLTF

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            return MeshFile(z["vertices"].astype(np.float64),
                            depth_mm=z["depth"] if "depth" in z.files else None)
    if suffix == ".vtu":
        import meshio

        m = meshio.read(path)
        return MeshFile(np.asarray(m.points, np.float64),
                        tets=np.asarray(m.cells_dict["tetra"], np.int64))
    if suffix in (".ply", ".obj", ".glb"):
        import trimesh

        mesh = trimesh.load(path, force="mesh", process=False, maintain_order=True)
        v = np.asarray(mesh.vertices, np.float64)
        if suffix == ".glb":
            v = 1e3 * v @ SENSOR_TO_GLTF          # inverse rotation (orthogonal): row @ R
        return MeshFile(v, faces=np.asarray(mesh.faces, np.int64))
    raise ValueError(f"{path}: not a mesh file of a run (.ply, .obj, .glb, .vtu or .npz)")
