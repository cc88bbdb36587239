"""Writing predicted meshes to files, on a background thread so the sensor loop never waits.

Formats (chosen per run): ``ply``, ``obj``, ``glb`` -- the outer surface through trimesh, vertex
colours by displacement magnitude on a fixed scale; ``vtu`` -- the tet volume through meshio with
point data ``displacement_mm`` (vector) and ``displacement_magnitude_mm``; ``npz`` -- the frame's arrays
for programs (:func:`write_frame_npz`: ``vertices``, ``rest_vertices``, ``depth``). PLY also carries the
displacement vector per vertex (``disp_x_mm``, ``disp_y_mm``, ``disp_z_mm``). Units mm, sensor
frame, except GLB: glTF's unit is the metre and its up axis is y, so GLB positions are in metres
in glTF's axes (sensor (x, y, z) -> glTF (x, z, -y): the pad's surface faces +y) and its
per-vertex displacement attributes ``_disp_x_m``, ``_disp_y_m``, ``_disp_z_m`` are along glTF's
axes (glTF names custom attributes with a leading underscore).

Vertex order: vertex i of every file is vertex i of the pad mesh (the model's output order,
``topology.npz``). Surface files (PLY, OBJ, GLB) hold all vertices, the interior ones unused by
their faces: a reader that drops unused vertices or merges duplicates renumbers the mesh.
:func:`tactile_deploy.runtime.meshfiles.read_mesh` reads every format back in this order. File names ``mesh_<frame index, 6 digits>.<ext>``; every
file is written atomically.

If writing fails (disk full, folder removed, permissions changed), the error is logged once,
further writes are skipped, and :attr:`MeshWriter.error` holds the message; the loop goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import Counter, deque
from pathlib import Path

import numpy as np

from tactile_deploy.pad.export import SENSOR_TO_GLTF

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
    if glb:       # glTF: metres, y up: (x, y, z) of the sensor frame -> (x, z, -y)
        v, disp = v @ SENSOR_TO_GLTF.T, disp @ SENSOR_TO_GLTF.T
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


def write_frame_npz(path: Path, topology, vertices_mm: np.ndarray, depth_mm: np.ndarray | None,
                    metadata: dict | None = None, depth_grid=None) -> None:
    """One frame's arrays as ``.npz`` (compressed, atomic), the names of ``simulate --out``:

    vertices       (n, 3) float32  mm, sensor frame, deformed (vertex i = pad mesh vertex i)
    rest_vertices  (n, 3) float32  mm, sensor frame, the undeformed pad mesh
    depth          (128, 128) float32  mm pushed in along -z, model grid (row 0 = largest y)
    metadata       () str          JSON: :class:`~tactile_deploy.runtime.frame_file.FrameMeshMetadata`
                                   (format, version, units, frame, mesh_hash, and what the run
                                   adds: sensor, frame_index, t_capture_ns, ...), checked before
                                   writing; read back with
                                   :func:`~tactile_deploy.runtime.frame_file.load_frame_npz`
    """
    from tactile_deploy.atomic import write_npz
    from tactile_deploy.runtime.frame_file import FRAME_FORMAT, FRAME_NPZ_VERSION, frame_metadata
    from tactile_deploy.runtime.publish import SENSOR_FRAME

    meta = {"format": FRAME_FORMAT, "version": FRAME_NPZ_VERSION,
            "units": {"vertices": "mm", "rest_vertices": "mm", "depth": "mm"},
            "frame": SENSOR_FRAME, "mesh_hash": topology.mesh_hash,
            "depth": "mm the surface is pushed in along -z; 128 x 128 over +-17.5 mm, row 0 at the "
                     "largest y"}
    if depth_grid is not None:      # a pad family's own depth grid (docs/families.md)
        g = depth_grid
        meta["depth"] = (f"mm the surface is pushed in along -z; {g.ny} x {g.nx} cells of "
                         f"{g.pitch_x_mm:.4g} mm, row 0 at the largest y")
        meta["depth_grid_mm"] = {"x_min": g.x_min_mm, "x_max": g.x_max_mm, "y_min": g.y_min_mm,
                                 "y_max": g.y_max_mm, "nx": g.nx, "ny": g.ny}
    meta.update(metadata or {})
    arrays = {"vertices": np.asarray(vertices_mm, np.float32),
              "rest_vertices": np.asarray(topology.rest_vertices_mm, np.float32)}
    if depth_mm is not None:
        arrays["depth"] = np.asarray(depth_mm, np.float32)
    from tactile_deploy.atomic import finite_or_null

    # strict JSON: a score not computed (NaN, the physics lift has no OOD score) is null
    checked = frame_metadata(finite_or_null(meta), f"{path}: metadata to write")
    write_npz(path, **arrays, metadata=np.array(checked.model_dump_json()))


#: Why a requested mesh was not written.
REASON_QUEUE_FULL = "writer queue full (the disk is slower than the live sensor)"
REASON_FAILED = "writing failed (see the write error)"




class MeshWriter:
    """Background writer of meshes into ``folder`` (module docstring).

    queue_size : meshes waiting at most; when the disk is slower than a live sensor, further
        meshes are skipped (counted in ``skipped``) instead of growing memory; a recording waits.
    """

    def __init__(self, folder: Path, topology, formats=("ply", "vtu"), max_mm: float = 1.0,
                 queue_size: int = 8, depth_grid=None):
        self.folder = Path(folder)
        self.depth_grid = depth_grid
        self.topology = topology
        self.formats = tuple(formats)
        self.max_mm = float(max_mm)
        self.written = 0
        self.skipped = 0
        #: skipped meshes by reason
        self.skipped_reasons: Counter = Counter()
        #: ``(frame index, None or the reason it was not written)`` of each queued mesh, in
        #: order, appended by the writer thread (the run drains it for frames.csv)
        self.results: deque = deque()
        self._count_lock = threading.Lock()  # skipped is counted by the loop and the writer
        self.error: str | None = None
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._thread = threading.Thread(target=self._work, name="mesh writer", daemon=True)
        self._thread.start()

    def submit(self, index: int, vertices_mm: np.ndarray, block: bool = False,
               depth_mm: np.ndarray | None = None, metadata: dict | None = None) -> bool:
        """Queue a mesh; False when it was skipped (writing has failed, or the queue is full and
        ``block`` is False). Recordings block (every requested mesh is written); live sources
        do not (the sensor loop must not wait for the disk)."""
        if self.error is not None:
            self._skip(REASON_FAILED)
            return False
        item = (int(index), np.array(vertices_mm, np.float32),
                None if depth_mm is None else np.array(depth_mm, np.float32), metadata)
        if block:
            while self._thread.is_alive() and self.error is None:
                try:
                    self._q.put(item, timeout=0.5)
                    return True
                except queue.Full:
                    continue
            self._skip(REASON_FAILED)
            return False
        try:
            self._q.put_nowait(item)
            return True
        except queue.Full:
            self._skip(REASON_QUEUE_FULL)
            return False

    def files_for(self, index: int) -> list[str]:
        """Names of the files written for frame ``index``."""
        return [f"mesh_{int(index):06d}.{fmt}" for fmt in self.formats]

    def _skip(self, reason: str) -> None:
        with self._count_lock:
            self.skipped += 1
            self.skipped_reasons[reason] += 1

    def _work(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            index, v, depth, meta = item
            if self.error is not None:      # queued before writing failed
                self._skip(REASON_FAILED)
                self.results.append((index, REASON_FAILED))
                continue
            try:
                for fmt in self.formats:
                    path = self.folder / f"mesh_{index:06d}.{fmt}"
                    if fmt in VOLUME_FORMATS:
                        write_volume(path, self.topology, v)
                    elif fmt in ARRAY_FORMATS:
                        write_frame_npz(path, self.topology, v, depth, meta, self.depth_grid)
                    else:
                        write_surface(path, self.topology, v, self.max_mm)
                self.written += 1
                self.results.append((index, None))
            except Exception as e:  # noqa: BLE001 - any failure stops writing, the loop goes on
                self._skip(REASON_FAILED)
                self.results.append((index, REASON_FAILED))
                self.error = (f"writing meshes into {self.folder} failed at frame {index}: "
                              f"{type(e).__name__}: {e}; no further meshes are written")
                log.error(self.error)

    def close(self, timeout_s: float = 60.0) -> None:
        """Write what is queued, then stop the thread."""
        self._q.put(None)
        self._thread.join(timeout=timeout_s)
