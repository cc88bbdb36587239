"""``MeshPredictor``: depth map (or camera frame) -> volumetric pad mesh, through onnxruntime.

    from tactile_deploy.runtime import MeshPredictor

    predictor = MeshPredictor.from_plugin("gelslim2")
    topology = predictor.topology                 # fixed: rest vertices, tets, faces (once)
    pred = predictor.predict_frame(rgb)           # (480, 640, 3) uint8 RGB camera frame
    pred.vertices_mm                              # (5380, 3) float32, mm, sensor frame
    batch = predictor.predict_depth(depths)       # (N, 128, 128) float32 mm -> (N, 5380, 3)

The model contract (docs/onnx_contract.md): input ``depth`` (N, 1, 128, 128) float32 mm on the
model grid; outputs ``vertices`` (N, n, 3) float32 mm (sensor frame, the pad asset's vertex
order), ``displacement`` (N, n, 3) mm (vertices minus rest positions) and ``ood_score`` (N,)
(dimensionless; above the model's ``ood_threshold`` a frame is outside the training range). The
model's metadata carries ``mesh_hash``, which must equal the pad mesh's content hash.

One place builds the onnxruntime session (:func:`make_session`): explicit providers checked
against what is installed (CUDA when present, CPU otherwise, a warning when CUDA was asked for or
offered and dropped), one intra-op thread by default, sequential execution, full graph
optimisation.
"""

from __future__ import annotations

import logging
import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from tactile_deploy.runtime.pipeline import (
    FrameError,
    ImagingPipeline,
    Laps,
    frame_to_mesh,
)

log = logging.getLogger(__name__)

INPUT_NAME = "depth"
OUTPUT_VERTICES = "vertices"
OUTPUT_DISPLACEMENT = "displacement"
OUTPUT_OOD = "ood_score"
META_MESH_HASH = "mesh_hash"
META_OOD_THRESHOLD = "ood_threshold"
GRID = 128

CUDA = "CUDAExecutionProvider"
CPU = "CPUExecutionProvider"


class ModelContractError(ValueError):
    """An ONNX model does not follow the contract (names, shapes, metadata, mesh hash)."""


# ------------------------------------------------------------------------------------ session
def choose_providers(providers: str | list[str] = "auto") -> list[str]:
    """Execution providers to ask for: ``"auto"`` (CUDA when installed, then CPU), ``"cpu"``,
    ``"cuda"`` (CPU with a warning when CUDA is not installed), or an explicit list."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    if isinstance(providers, (list, tuple)):
        missing = [p for p in providers if p not in available]
        if missing:
            warnings.warn(f"onnxruntime providers {missing} are not installed (available: "
                          f"{available}); they are skipped", RuntimeWarning, stacklevel=3)
        chosen = [p for p in providers if p in available]
        return chosen or [CPU]
    mode = providers.lower()
    if mode == "cpu":
        return [CPU]
    if mode in ("auto", "cuda"):
        if CUDA in available:
            return [CUDA, CPU]
        if mode == "cuda":
            warnings.warn("CUDA was asked for but this onnxruntime has no CUDAExecutionProvider "
                          "(install onnxruntime-gpu with a matching CUDA); running on the CPU",
                          RuntimeWarning, stacklevel=3)
        return [CPU]
    raise ValueError(f"providers must be 'auto', 'cpu', 'cuda' or a list of provider names, "
                     f"got {providers!r}")


def make_session(model_path: str | os.PathLike, threads: int = 1,
                 providers: str | list[str] = "auto"):
    """An ``onnxruntime.InferenceSession`` with this project's defaults (module docstring)."""
    import onnxruntime as ort

    path = Path(model_path)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX model {path} not found")
    if int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    wanted = choose_providers(providers)
    try:
        session = ort.InferenceSession(str(path), so, providers=wanted)
    except Exception as e:  # onnxruntime raises its own exception types
        raise ModelContractError(f"{path}: onnxruntime cannot load it ({type(e).__name__}: "
                                 f"{e}); the file is damaged or not an ONNX model - restore it "
                                 "or export it again") from None
    used = session.get_providers()
    if CUDA in wanted and CUDA not in used:
        warnings.warn(f"onnxruntime could not start CUDA for {path.name} (missing CUDA/cuDNN "
                      "libraries?); running on the CPU", RuntimeWarning, stacklevel=2)
    return session


def check_model_contract(model_path, expected_mesh_hash: str | None, n_nodes: int | None = None,
                         what: str = "model", session=None) -> dict:
    """Check names, shapes and the mesh hash of an ONNX model; returns its metadata.

    Raises :class:`ModelContractError` naming the model, what was expected and what was found.
    """
    path = Path(model_path)
    session = session or make_session(path, threads=1, providers="cpu")
    inputs = {i.name: i for i in session.get_inputs()}
    outputs = {o.name: o for o in session.get_outputs()}
    where = f"{what} {path}"
    if INPUT_NAME not in inputs:
        raise ModelContractError(f"{where}: expected an input named {INPUT_NAME!r}, the model "
                                 f"has {sorted(inputs)}")
    shape = inputs[INPUT_NAME].shape
    if len(shape) != 4 or list(shape[1:]) != [1, GRID, GRID]:
        raise ModelContractError(f"{where}: input {INPUT_NAME!r} must be [N, 1, {GRID}, {GRID}], "
                                 f"the model has {shape}")
    if inputs[INPUT_NAME].type != "tensor(float)":
        raise ModelContractError(f"{where}: input {INPUT_NAME!r} must be float32, the model has "
                                 f"{inputs[INPUT_NAME].type}")
    for name in (OUTPUT_VERTICES, OUTPUT_DISPLACEMENT, OUTPUT_OOD):
        if name not in outputs:
            raise ModelContractError(f"{where}: expected an output named {name!r}, the model has "
                                     f"{sorted(outputs)}")
    vshape = outputs[OUTPUT_VERTICES].shape
    if len(vshape) != 3 or vshape[2] != 3 or (n_nodes is not None and isinstance(vshape[1], int)
                                              and vshape[1] != n_nodes):
        raise ModelContractError(f"{where}: output {OUTPUT_VERTICES!r} must be [N, "
                                 f"{n_nodes or 'n'}, 3], the model has {vshape}")
    meta = dict(session.get_modelmeta().custom_metadata_map)
    if META_MESH_HASH not in meta:
        raise ModelContractError(f"{where}: metadata {META_MESH_HASH!r} is missing; export the "
                                 "model with the pad's content hash in its metadata")
    if expected_mesh_hash is not None and meta[META_MESH_HASH] != expected_mesh_hash:
        raise ModelContractError(
            f"{where}: its mesh hash {meta[META_MESH_HASH][:16]}... differs from the sensor "
            f"family's pad mesh {expected_mesh_hash[:16]}...; this model was trained for another "
            "mesh - use the model of this family, or a plugin made for that mesh")
    return meta


# ------------------------------------------------------------------------------------ results
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
        from tactile_deploy.pad.asset import load_pad

        mesh = load_pad(pad, version)
        return cls(mesh.vertices.astype(np.float64), mesh.tets.astype(np.int32),
                   mesh.boundary_faces.astype(np.int32), mesh.sensing_faces.astype(np.int32),
                   mesh.sensing_nodes.astype(np.int64), mesh.content_hash)

    def save(self, path: str | os.PathLike) -> None:
        """Write the topology file of the ONNX contract (.npz, atomic)."""
        from tactile_deploy.atomic import write_npz

        write_npz(path, rest_vertices_mm=self.rest_vertices_mm, tets=self.tets,
                  surface_faces=self.surface_faces, sensing_faces=self.sensing_faces,
                  sensing_nodes=self.sensing_nodes.astype(np.int32),
                  mesh_hash=np.array(self.mesh_hash))

    @classmethod
    def load(cls, path: str | os.PathLike) -> MeshTopology:
        with np.load(path, allow_pickle=False) as z:
            return cls(z["rest_vertices_mm"].astype(np.float64), z["tets"], z["surface_faces"], z["sensing_faces"],
                       z["sensing_nodes"].astype(np.int64), str(z["mesh_hash"]))


@dataclass(frozen=True)
class MeshPrediction:
    """Model outputs for a batch (or, when ``batched`` is False, one input).

    vertices_mm : (N, n, 3) float32 (or (n, 3)), deformed vertices, mm, sensor frame.
    displacement_mm : same shape, vertices minus rest positions, mm.
    ood_score : (N,) float32 (or a float), out-of-distribution score, dimensionless.
    in_distribution : (N,) bool (or a bool), score at or below the threshold (True when the
        model has no threshold).
    depth_mm : (N, 128, 128) float32 (or (128, 128)) model input, when it came from frames.
    """

    vertices_mm: np.ndarray
    displacement_mm: np.ndarray
    ood_score: np.ndarray
    in_distribution: np.ndarray
    depth_mm: np.ndarray | None = None
    batched: bool = True

    def with_depth(self, depth: np.ndarray) -> MeshPrediction:
        return replace(self, depth_mm=depth)

    def single(self) -> MeshPrediction:
        """The first (only) item without the batch axis."""
        if not self.batched:
            return self
        return MeshPrediction(self.vertices_mm[0], self.displacement_mm[0],
                              float(self.ood_score[0]), bool(self.in_distribution[0]),
                              None if self.depth_mm is None else self.depth_mm[0], False)


# ------------------------------------------------------------------------------------ predictor
class MeshPredictor:
    """An ONNX mesh model with its topology, and optionally the imaging pipeline of a sensor.

    model_path : ONNX file following docs/onnx_contract.md.
    expected_mesh_hash : refuse a model whose metadata names another mesh (None: the pad's).
    pad, pad_version : the pad asset whose vertex order the model outputs.
    pipeline : :class:`ImagingPipeline` for :meth:`predict_frame` (None: depth input only).
    threads : onnxruntime intra-op threads. providers : see :func:`choose_providers`.
    warmup : number of warm-up runs at construction (first runs allocate and are slow).
    ood_threshold : override of the model's ``ood_threshold`` metadata.
    """

    def __init__(self, model_path, *, expected_mesh_hash: str | None = None,
                 pad: str = "gelslim", pad_version: int | None = None,
                 pipeline: ImagingPipeline | None = None, threads: int = 1,
                 providers: str | list[str] = "auto", warmup: int = 2,
                 ood_threshold: float | None = None, name: str | None = None):
        self.model_path = Path(model_path)
        self.name = name or self.model_path.stem
        self._topology = MeshTopology.from_pad(pad, pad_version)
        expected = expected_mesh_hash or self._topology.mesh_hash
        if expected != self._topology.mesh_hash:
            raise ModelContractError(
                f"expected mesh hash {expected[:16]}... is not the hash of pad {pad!r} "
                f"({self._topology.mesh_hash[:16]}...)")
        self.session = make_session(self.model_path, threads, providers)
        self.metadata = check_model_contract(self.model_path, expected,
                                             len(self._topology.rest_vertices_mm),
                                             what=self.name, session=self.session)
        if ood_threshold is None and META_OOD_THRESHOLD in self.metadata:
            try:
                ood_threshold = float(self.metadata[META_OOD_THRESHOLD])
            except ValueError:
                raise ModelContractError(
                    f"{self.model_path}: metadata {META_OOD_THRESHOLD!r} = "
                    f"{self.metadata[META_OOD_THRESHOLD]!r} is not a number") from None
        self.ood_threshold = ood_threshold
        self.pipeline = pipeline
        self.plugin = None
        self.providers = self.session.get_providers()
        self._outputs = [OUTPUT_VERTICES, OUTPUT_DISPLACEMENT, OUTPUT_OOD]
        for _ in range(int(warmup)):
            self.infer(np.zeros((1, 1, GRID, GRID), np.float32))

    @classmethod
    def from_plugin(cls, plugin="gelslim2", *, adapted: bool | None = None, threads: int = 1,
                    providers: str | list[str] = "auto", warmup: int = 2) -> MeshPredictor:
        """Predictor of a sensor plugin (by name, folder, or a loaded
        :class:`~tactile_deploy.runtime.plugins.SensorPlugin`), with its imaging pipeline.
        ``adapted``: use the plugin's adapted model (default: when it has one)."""
        from tactile_deploy.runtime.plugins import SensorPlugin

        plugin = SensorPlugin.load(plugin)
        m = plugin.manifest
        model_path = plugin.model_path(adapted)
        pipeline = ImagingPipeline.from_plugin(plugin)
        predictor = cls(model_path, expected_mesh_hash=m.family.mesh_hash, pad=m.family.pad,
                        pad_version=m.family.pad_version, pipeline=pipeline, threads=threads,
                        providers=providers, warmup=warmup, ood_threshold=m.ood_threshold,
                        name=f"{m.name} model")
        predictor.plugin = plugin
        return predictor

    @property
    def topology(self) -> MeshTopology:
        """The fixed topology (rest vertices, tets, faces): fetch it once, reuse it."""
        return self._topology

    @property
    def n_nodes(self) -> int:
        return len(self._topology.rest_vertices_mm)

    # -- calls
    def infer(self, depth: np.ndarray) -> MeshPrediction:
        """Run the model on a checked (N, 1, 128, 128) float32 C-contiguous batch, mm."""
        v, d, ood = self.session.run(self._outputs, {INPUT_NAME: depth})
        ood = np.asarray(ood, np.float32).reshape(-1)
        inside = (ood <= self.ood_threshold if self.ood_threshold is not None
                  else np.ones(ood.shape, bool))
        return MeshPrediction(v, d, ood, inside)

    def predict_depth(self, depth) -> MeshPrediction:
        """Depth (128, 128), (N, 128, 128) or (N, 1, 128, 128), mm, model grid -> mesh(es).

        A single map gives an unbatched :class:`MeshPrediction`. NaN or inf values are refused
        (:class:`FrameError`): fill them (e.g. with 0, the unloaded surface) first.
        """
        arr = np.asarray(depth)
        if arr.dtype.kind not in "fiu":
            raise FrameError(f"depth must be a numeric array in mm, got dtype {arr.dtype}")
        single = arr.ndim == 2
        if arr.ndim == 2:
            arr = arr[None, None]
        elif arr.ndim == 3:
            arr = arr[:, None]
        if arr.ndim != 4 or arr.shape[1:] != (1, GRID, GRID) or arr.shape[0] < 1:
            raise FrameError(f"depth must have shape ({GRID}, {GRID}), (N, {GRID}, {GRID}) or "
                             f"(N, 1, {GRID}, {GRID}) on the model grid, got {np.shape(depth)}")
        arr = np.ascontiguousarray(arr, dtype=np.float32)
        bad = ~np.isfinite(arr)
        if bad.any():
            raise FrameError(f"depth holds {int(bad.sum())} NaN/inf values (of {arr.size}); "
                             "replace them (e.g. np.nan_to_num(depth, nan=0.0)) before predicting")
        pred = self.infer(arr).with_depth(arr[:, 0])
        return pred.single() if single else pred

    def predict_frame(self, frame, laps: Laps | None = None) -> MeshPrediction:
        """Camera frame (H, W, 3) uint8 RGB -> mesh (unbatched), through the sensor's pipeline."""
        if self.pipeline is None:
            raise FrameError("this predictor has no imaging pipeline; build it with "
                             "MeshPredictor.from_plugin(NAME) or pass pipeline=")
        return frame_to_mesh(frame, self.pipeline, self, laps).single()

    def predict_frames(self, frames) -> MeshPrediction:
        """Several frames (N, H, W, 3) uint8 -> batched prediction (one model call)."""
        if self.pipeline is None:
            raise FrameError("this predictor has no imaging pipeline; build it with "
                             "MeshPredictor.from_plugin(NAME) or pass pipeline=")
        depths = np.stack([self.pipeline.frame_to_depth(f) for f in frames])
        return self.infer(depths[:, None]).with_depth(depths)
