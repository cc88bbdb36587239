"""The runtime: sensor plugins, frame sources, the imaging pipeline, the ONNX mesh predictor,
contact forces, publishing, and the ``tactile-deploy run`` loop (docs/runtime.md).

Embedding in robot software::

    from tactile_deploy.runtime import MeshPredictor

    predictor = MeshPredictor.from_plugin("gelslim2")
    pred = predictor.predict_frame(rgb)     # (480, 640, 3) uint8 RGB -> pred.vertices_mm (5380, 3)

Imports nothing of torch or warp.
"""

from __future__ import annotations

__all__ = [
    "ForceEstimator",
    "ImagingPipeline",
    "MeshPrediction",
    "MeshPredictor",
    "MeshTopology",
    "SensorPlugin",
    "make_source",
    "parse_source",
]


def __getattr__(name: str):
    if name in ("MeshPredictor", "MeshPrediction", "MeshTopology"):
        from tactile_deploy.runtime import predictor

        return getattr(predictor, name)
    if name == "SensorPlugin":
        from tactile_deploy.runtime.plugins import SensorPlugin

        return SensorPlugin
    if name == "ImagingPipeline":
        from tactile_deploy.runtime.pipeline import ImagingPipeline

        return ImagingPipeline
    if name == "ForceEstimator":
        from tactile_deploy.runtime.forces import ForceEstimator

        return ForceEstimator
    if name == "make_source":
        from tactile_deploy.runtime.sources.factory import make_source

        return make_source
    if name == "parse_source":
        from tactile_deploy.runtime.sources.config import parse_source

        return parse_source
    raise AttributeError(f"module 'tactile_deploy.runtime' has no attribute {name!r}")
