"""Writing predicted meshes to files, on a background thread so the sensor loop never waits.

Formats (chosen per run): ``ply``, ``obj``, ``glb`` -- the outer surface through trimesh, vertex
colours by displacement magnitude on a fixed scale; ``vtu`` -- the tet volume through meshio with
point data ``displacement_mm`` (vector) and ``displacement_magnitude_mm``. PLY also carries the
displacement vector per vertex (``disp_x_mm``, ``disp_y_mm``, ``disp_z_mm``). Units mm, sensor
frame, except GLB: glTF's unit is the metre, so GLB positions are in metres and its per-vertex
displacement attributes are ``_disp_x_m``, ``_disp_y_m``, ``_disp_z_m`` (glTF names custom
attributes with a leading underscore). ``npz`` -- one NumPy archive per frame
(:func:`write_frame_npz`): ``vertices`` and ``rest_vertices`` (n, 3) float32 mm, ``depth``
(ny, nx) float32 mm on the plugin's depth grid, and the grid, units and frame. File names ``mesh_<frame index, 6 digits>.<ext>``; every
file is written atomically.

If writing fails (disk full, folder removed, permissions changed), the error is logged once,
further writes are skipped, and :attr:`MeshWriter.error` holds the message; the loop goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.runtime.preview import colourise

log = logging.getLogger(__name__)

SURFACE_FORMATS = ("ply", "obj", "glb")
VOLUME_FORMATS = ("vtu",)
ARRAY_FORMATS = ("npz",)
FORMATS = SURFACE_FORMATS + VOLUME_FORMATS + ARRAY_FORMATS


def parse_formats(text: str) -> tuple[str, ...]:
    """``"ply,vtu"`` -> ("ply", "vtu"); raises ValueError naming unknown formats."""
    fmts = tuple(dict.fromkeys(f.strip().lower().lstrip(".") for f in text.split(",") if f.strip()))
    bad = [f for f in fmts if f not in FORMATS]
    if bad or not fmts:
        raise ValueError(f"unknown mesh format(s) {bad or [text]}: choose from {', '.join(FORMATS)}")
    return fmts


def write_surface(path: Path, topology, vertices_mm: np.ndarray, max_mm: float = 1.0) -> None:
    import trimesh

    v = np.asarray(vertices_mm, np.float64)
    disp = v - topology.rest_vertices_mm
    mag = np.linalg.norm(disp, axis=1)
    glb = path.suffix == ".glb"
    scale, unit = (1e-3, "m") if glb else (1.0, "mm")
    mesh = trimesh.Trimesh(v * scale, topology.surface_faces, process=False)
    rgb = colourise(mag, max_mm)
    mesh.visual.vertex_colors = np.concatenate([rgb, np.full((len(v), 1), 255, np.uint8)], 1)
    if path.suffix in (".ply", ".glb"):
        for k, axis in enumerate("xyz"):
            mesh.vertex_attributes[f"disp_{axis}_{unit}"] = (disp[:, k] * scale).astype(np.float32)
    with atomic_path(path) as tmp:
        mesh.export(tmp)


def write_volume(path: Path, topology, vertices_mm: np.ndarray) -> None:
    import meshio

    v = np.asarray(vertices_mm, np.float64)
    disp = v - topology.rest_vertices_mm
    out = meshio.Mesh(v, [("tetra", topology.tets.astype(np.int64))],
                      point_data={"displacement_mm": disp,
                                  "displacement_magnitude_mm": np.linalg.norm(disp, axis=1)})
    with atomic_path(path) as tmp:
        meshio.write(tmp, out)


def write_frame_npz(path: Path, topology, vertices_mm: np.ndarray,
                    depth_mm: np.ndarray | None, depth_grid=None, index: int | None = None) -> None:
    """One frame as a NumPy archive (atomic): ``vertices``, ``rest_vertices`` (n, 3) float32 mm
    (sensor frame; the pad asset's vertex order), ``depth`` (ny, nx) float32 mm (positive into
    the gel; row 0 at the largest y) with ``depth_grid_mm`` = (x_min, x_max, y_min, y_max) and
    ``sensing_nodes`` (k,) int32, ``mesh_hash`` and ``units`` strings."""
    import json

    arrays = {
        "vertices": np.asarray(vertices_mm, np.float32),
        "rest_vertices": np.asarray(topology.rest_vertices_mm, np.float32),
        "sensing_nodes": np.asarray(topology.sensing_nodes, np.int32),
        "mesh_hash": np.array(topology.mesh_hash),
        "units": np.array(json.dumps({"vertices": "mm", "rest_vertices": "mm", "depth": "mm",
                                      "depth_grid_mm": "mm", "frame": "sensor frame: origin at "
                                      "the centre of the sensing surface, z out of the gel"})),
    }
    if depth_mm is not None:
        arrays["depth"] = np.asarray(depth_mm, np.float32)
    if depth_grid is not None:
        g = depth_grid
        arrays["depth_grid_mm"] = np.array([g.x_min_mm, g.x_max_mm, g.y_min_mm, g.y_max_mm])
    if index is not None:
        arrays["frame_index"] = np.array(int(index))
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


class MeshWriter:
    """Background writer of meshes into ``folder`` (module docstring).

    queue_size : meshes waiting at most; when the disk is slower than a live sensor, further
        meshes are skipped (counted in ``skipped``) instead of growing memory; a recording waits.
    """

    def __init__(self, folder: Path, topology, formats=("ply", "vtu"), max_mm: float = 1.0,
                 queue_size: int = 8, depth_grid=None):
        self.folder = Path(folder)
        self.topology = topology
        self.formats = tuple(formats)
        self.max_mm = float(max_mm)
        self.depth_grid = depth_grid
        self.written = 0
        self.skipped = 0
        self._count_lock = threading.Lock()  # skipped is counted by the loop and the writer
        self.error: str | None = None
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._thread = threading.Thread(target=self._work, name="mesh writer", daemon=True)
        self._thread.start()

    def submit(self, index: int, vertices_mm: np.ndarray, block: bool = False,
               depth_mm: np.ndarray | None = None) -> bool:
        """Queue a mesh; False when it was skipped (writing has failed, or the queue is full and
        ``block`` is False). Recordings block (every requested mesh is written); live sources
        do not (the sensor loop must not wait for the disk)."""
        if self.error is not None:
            self._skip()
            return False
        item = (int(index), np.array(vertices_mm, np.float32),
                None if depth_mm is None else np.array(depth_mm, np.float32))
        if block:
            while self._thread.is_alive() and self.error is None:
                try:
                    self._q.put(item, timeout=0.5)
                    return True
                except queue.Full:
                    continue
            self._skip()
            return False
        try:
            self._q.put_nowait(item)
            return True
        except queue.Full:
            self._skip()
            return False

    def _skip(self) -> None:
        with self._count_lock:
            self.skipped += 1

    def _work(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            index, v, depth = item
            if self.error is not None:      # queued before writing failed
                self._skip()
                continue
            try:
                for fmt in self.formats:
                    path = self.folder / f"mesh_{index:06d}.{fmt}"
                    if fmt in ARRAY_FORMATS:
                        write_frame_npz(path, self.topology, v, depth, self.depth_grid, index)
                    elif fmt in VOLUME_FORMATS:
                        write_volume(path, self.topology, v)
                    else:
                        write_surface(path, self.topology, v, self.max_mm)
                self.written += 1
            except Exception as e:  # noqa: BLE001 - any failure stops writing, the loop goes on
                self._skip()
                self.error = (f"writing meshes into {self.folder} failed at frame {index}: "
                              f"{type(e).__name__}: {e}; no further meshes are written")
                log.error(self.error)

    def close(self, timeout_s: float = 60.0) -> None:
        """Write what is queued, then stop the thread."""
        self._q.put(None)
        self._thread.join(timeout=timeout_s)
