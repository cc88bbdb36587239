"""Export a (deformed) pad mesh to files FEM and graphics tools open.

* volume: VTU, VTK, MSH (gmsh 2.2), INP (Abaqus), MESH (Medit) through meshio (format from the
  suffix), with node-set and displacement point data; each is one self-contained file (XDMF is
  not offered: meshio writes it as two files and needs h5py);
* surface: STL, PLY, OBJ, GLB, ... through trimesh (the boundary triangles, outward normals),
  with per-vertex displacement magnitude as colour where the format keeps colours.

All files are written atomically. Sensor frame; units mm, except GLB: metres in glTF's axes (y up),
the same as the runtime's GLB meshes (tactile_deploy.runtime.writers).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.pad.mesh import PadMesh

#: Rotation from the sensor frame (z out of the gel) to glTF's axes (y up, right-handed):
#: a -90 degree turn about x, (x, y, z) -> (x, z, -y). GLB files (pad export and the runtime's
#: meshes) are written in these axes, in metres.
SENSOR_TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

VOLUME_SUFFIXES = (".vtu", ".vtk", ".msh", ".inp", ".mesh")
SURFACE_SUFFIXES = (".stl", ".ply", ".obj", ".glb", ".off")


def export_volume(
    mesh: PadMesh, path: str | os.PathLike, vertices_mm: np.ndarray | None = None
) -> Path:
    """Write the tet volume (deformed when ``vertices_mm`` (n, 3) is given) with meshio."""
    import meshio

    path = Path(path)
    if path.suffix.lower() not in VOLUME_SUFFIXES:
        raise ValueError(f"{path}: volume format must be one of {VOLUME_SUFFIXES}, got {path.suffix!r}")
    points = mesh.vertices if vertices_mm is None else np.asarray(vertices_mm, dtype=np.float64)
    if points.shape != mesh.vertices.shape:
        raise ValueError(f"vertices_mm must have shape {mesh.vertices.shape}, got {points.shape}")
    point_data = {"displacement_mm": points - mesh.vertices}
    for name, nodes in mesh.node_sets.items():
        flag = np.zeros(mesh.n_nodes, dtype=np.int32)
        flag[nodes] = 1
        point_data[f"set_{name}"] = flag
    out = meshio.Mesh(points, [("tetra", mesh.tets.astype(np.int64))], point_data=point_data)
    file_format = "gmsh22" if path.suffix.lower() == ".msh" else None
    with atomic_path(path) as tmp:
        meshio.write(tmp, out, file_format=file_format)
    return path


def export_surface(
    mesh: PadMesh, path: str | os.PathLike, vertices_mm: np.ndarray | None = None
) -> Path:
    """Write the boundary surface (deformed when ``vertices_mm`` is given) with trimesh: mm,
    sensor frame, except GLB: metres in glTF's axes, y up ((x, y, z) of the sensor frame ->
    (x, z, -y)), as the runtime writes its GLB meshes."""
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise ValueError(f"{path}: surface format must be one of {SURFACE_SUFFIXES}, got {path.suffix!r}")
    points = mesh.vertices if vertices_mm is None else np.asarray(vertices_mm, dtype=np.float64)
    if points.shape != mesh.vertices.shape:
        raise ValueError(f"vertices_mm must have shape {mesh.vertices.shape}, got {points.shape}")
    if path.suffix.lower() == ".glb":
        written = 1e-3 * points @ SENSOR_TO_GLTF.T
    else:
        written = points
    surface = trimesh.Trimesh(written, mesh.boundary_faces, process=False)
    magnitude = np.linalg.norm(points - mesh.vertices, axis=1)
    if magnitude.max() > 0:
        import matplotlib

        colours = matplotlib.colormaps["viridis"](magnitude / magnitude.max())
        surface.visual.vertex_colors = (255 * colours).astype(np.uint8)
    with atomic_path(path) as tmp:
        surface.export(tmp)
    return path
