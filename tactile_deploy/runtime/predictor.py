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

Sessions come from :func:`tactile_deploy.onnx_runtime.session.make_session` and every model is
checked against the contract (:func:`tactile_deploy.onnx_runtime.contract.check_model_contract`)
when it is loaded.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from tactile_deploy.onnx_runtime.contract import (
    GRID,
    INPUT_NAME,
    META_OOD_THRESHOLD,
    OUTPUT_DISPLACEMENT,
    OUTPUT_OOD,
    OUTPUT_VERTICES,
    check_model_contract,
)
from tactile_deploy.onnx_runtime.errors import ModelContractError
from tactile_deploy.onnx_runtime.session import make_session
from tactile_deploy.pad.topology import MeshTopology
from tactile_deploy.runtime.pipeline import (
    FrameError,
    ImagingPipeline,
    Laps,
    frame_to_mesh,
)
from tactile_deploy.runtime.plugins import SensorPlugin

log = logging.getLogger(__name__)

__all__ = ["MeshPrediction", "MeshPredictor", "MeshTopology", "ModelContractError"]


# ------------------------------------------------------------------------------------ results
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
    threads : onnxruntime intra-op threads. providers : see :func:`tactile_deploy.onnx_runtime.session.choose_providers`.
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
