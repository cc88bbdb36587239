"""Meshes without a learned model: the plugin's depth maps through the pad's physics lift.

``tactile-deploy run --mesh physics`` (and any plugin whose manifest has no ``model``) turns
each frame into a mesh with :class:`PhysicsPredictor`: the imaging pipeline's depth map on the
family's depth grid -> :class:`~tactile_deploy.fem.depth_lift.DepthLift` of the pad (linear FEM,
the depth as the sensing surface's vertical displacement, free to slide sideways) -> every
vertex, and the contact forces from the same solve. It works for any pad family without
training; it is slower than the learned model (one sparse solve per frame, tens of ms on
10k-node pads, after a start of 20-40 s that builds the pad's factor and, once per pad and
material, its lateral operator) and carries every error of the depth map into the mesh (no
prior of what contacts look like).

``PhysicsPredictor`` has the interface the run loop uses of
:class:`~tactile_deploy.runtime.predictor.MeshPredictor` (``infer``, ``predict_frame``,
``predict_depth``, ``topology``, ``pipeline``, ``plugin``); it has no out-of-distribution score
(``ood_score`` is NaN and every frame counts as in range). Its :attr:`forces` is a force
estimator with the interface of :class:`~tactile_deploy.runtime.forces.ForceEstimator`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from tactile_deploy.fem.constraints import family_supports
from tactile_deploy.fem.depth_lift import DepthLift
from tactile_deploy.pad.asset import load_pad
from tactile_deploy.pad.family import FAMILIES
from tactile_deploy.runtime.forces import ContactForces
from tactile_deploy.runtime.pipeline import FrameError, ImagingPipeline, frame_to_mesh
from tactile_deploy.runtime.plugins import PluginError
from tactile_deploy.runtime.predictor import MeshPrediction, MeshTopology

log = logging.getLogger(__name__)

#: What ``--mesh`` accepts.
MESH_MODES = ("learned", "physics")


class PhysicsForces:
    """Contact forces of meshes from the physics lift (interface of ``ForceEstimator``)."""

    def __init__(self, predictor: PhysicsPredictor):
        self.predictor = predictor
        areas = predictor.lift.mesh.sensing_nodal_areas_mm2()
        self._inv_area_kpa = 1e3 / areas
        self.nodes = predictor.lift.mesh.sensing_nodes

    def estimate(self, vertices_mm: np.ndarray, clip_tension: bool = False,
                 pressure: bool = True):
        fn = self.predictor.forces_of(vertices_mm)
        if clip_tension:
            fn = np.maximum(fn, 0.0)
        if not (pressure or clip_tension):
            empty = np.zeros(0, np.float32)
            return ContactForces(float(fn.sum()), empty, empty)
        return ContactForces(float(fn.sum()), fn.astype(np.float32),
                             (fn * self._inv_area_kpa).astype(np.float32))


class PhysicsPredictor:
    """Depth map -> pad mesh by the physics lift (module docstring).

    plugin : a :class:`~tactile_deploy.runtime.plugins.SensorPlugin` (its family's pad and
        supports, its calibrated E and nu, its imaging pipeline).
    iterations : most solves per frame (:meth:`~tactile_deploy.fem.depth_lift.DepthLift.from_depth`:
        the depth read where each node moved to, to 2 um).
    """

    def __init__(self, plugin, pipeline: ImagingPipeline | None = None, iterations: int = 8):
        m = plugin.manifest
        fam = m.family
        mesh = load_pad(fam.pad, fam.pad_version)
        family = FAMILIES.get(fam.pad)
        supports = family_supports(family) if family is not None else None
        kwargs = {} if supports is None else {"supports": supports}
        self.lift = DepthLift(mesh, m.material.nu, m.material.E_mpa, **kwargs)
        self.lift.lateral_operator()   # built (or read from the cache) now, not in the first frame
        self.plugin = plugin
        self.pipeline = pipeline if pipeline is not None else ImagingPipeline.from_plugin(plugin)
        self.depth_grid = m.depth_grid
        self.iterations = int(iterations)
        self._topology = MeshTopology.from_pad(fam.pad, fam.pad_version)
        self.name = f"{m.name} physics lift"
        self.model_path = Path(f"physics lift of pad {fam.pad} v{fam.pad_version}")
        self.metadata: dict[str, str] = {"mesh": "physics"}
        self.providers = ["FEM physics lift (CPU)"]
        self.ood_threshold = None
        self._last = None            # (sensing u_z, forces) of the last mesh
        self.forces = PhysicsForces(self)

    @property
    def topology(self) -> MeshTopology:
        return self._topology

    @property
    def n_nodes(self) -> int:
        return len(self._topology.rest_vertices_mm)

    def infer(self, depth: np.ndarray) -> MeshPrediction:
        """(N, 1, ny, nx) float32 depth maps (mm, the family's depth grid) -> meshes."""
        depth = np.asarray(depth)
        verts, forces = [], []
        for d in depth[:, 0]:
            v, f = self.lift.from_depth(d, self.depth_grid, self.iterations)
            verts.append(v)
            forces.append(f)
        v = np.asarray(verts, np.float32)
        n_plane = self.lift.mesh.n_plane
        self._last = (v[-1, :n_plane, 2].copy(), forces[-1])
        rest = self._topology.rest_vertices_mm.astype(np.float32)
        n = len(v)
        return MeshPrediction(v, v - rest, np.full(n, np.nan, np.float32), np.ones(n, bool))

    def forces_of(self, vertices_mm: np.ndarray) -> np.ndarray:
        """Sensing-node forces (n_plane,) N of a mesh this predictor made (or any mesh)."""
        v = np.asarray(vertices_mm)
        n_plane = self.lift.mesh.n_plane
        if self._last is not None and np.array_equal(v[:n_plane, 2], self._last[0]):
            return self._last[1]
        return self.lift.forces_from_vertices(v)

    def predict_depth(self, depth) -> MeshPrediction:
        """Depth (ny, nx) or (N, ny, nx) mm on the family's depth grid -> mesh(es)."""
        arr = np.asarray(depth, np.float32)
        g = self.depth_grid
        single = arr.ndim == 2
        if single:
            arr = arr[None]
        if arr.ndim != 3 or arr.shape[1:] != (g.ny, g.nx):
            raise FrameError(f"depth must have shape ({g.ny}, {g.nx}) or (N, {g.ny}, {g.nx}) on "
                             f"the depth grid of pad {self.plugin.manifest.family.pad}, got "
                             f"{np.shape(depth)}")
        if not np.all(np.isfinite(arr)):
            raise FrameError("depth holds NaN/inf values; replace them (e.g. with 0) first")
        pred = self.infer(arr[:, None]).with_depth(arr)
        return pred.single() if single else pred

    def predict_frame(self, frame, laps=None) -> MeshPrediction:
        """Camera frame (H, W, 3) uint8 RGB -> mesh (unbatched), through the plugin's pipeline."""
        return frame_to_mesh(frame, self.pipeline, self, laps).single()


def choose_mesh_mode(plugin, requested: str | None) -> tuple[str, str | None]:
    """``(mode, note)``: the mesh mode for ``plugin`` given ``--mesh`` (None: learned when the
    plugin has a learned model, else physics, with a note saying so)."""
    has_model = plugin.manifest.model is not None or plugin.adapted_model_path() is not None
    if requested is None:
        if has_model:
            return "learned", None
        return "physics", (f"plugin {plugin.name!r} has no learned model for pad "
                           f"{plugin.manifest.family.pad}: meshes come from the pad's physics "
                           "lift (the depth map through its FEM; --mesh physics)")
    if requested not in MESH_MODES:
        raise PluginError(f"--mesh must be one of {', '.join(MESH_MODES)}, got {requested!r}")
    if requested == "learned" and not has_model:
        raise PluginError(f"--mesh learned: plugin {plugin.name!r} has no learned model (field "
                          f"'model' is null; pad {plugin.manifest.family.pad}); use --mesh "
                          "physics, or leave --mesh out")
    return requested, None
