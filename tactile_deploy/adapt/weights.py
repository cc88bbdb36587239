"""Adapted ONNX model from the family's fp32 graph and the adapted step's weights.

The family's fp32 graph (``<model>_fp32.onnx``) is the same network as the step program's
encoder, projection and mesh decoder, exported with some constants folded in. Its initializers
that hold the encoder and the projection are replaced by the adapted tensors, as the step card's
``parameter_map`` says (``initializer = transform(parameter) x scale``); every other node,
initializer and the metadata stay, so the adapted model follows the same contract
(docs/onnx_contract.md). When the shipped family graph is int8, the adapted fp32 graph is
quantised the same way (:func:`tactile_deploy.onnx_runtime.quantize.quantize_int8`, same nodes,
calibrated on the adaptation's own depth maps).

Needs the ``onnx`` package (``pip install 'tactile-deploy[adapt]'``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tactile_deploy.adapt.card import AdaptationCard, CardError
from tactile_deploy.atomic import atomic_path
from tactile_deploy.onnx_runtime.metadata import set_metadata


class AdaptationUnavailable(RuntimeError):
    """A package the adaptation needs (torch, onnx) is not installed (the message says how)."""


INSTALL_HINT = ("install the adaptation extra: pip install 'tactile-deploy[adapt]' (on a CPU-only "
                "machine first: pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu)")


def require_onnx():
    try:
        import onnx
    except ImportError:
        raise AdaptationUnavailable(f"writing the adapted ONNX model needs the onnx package; {INSTALL_HINT}") from None
    return onnx


def write_adapted_onnx(card: AdaptationCard, fp32_path: str | Path, weights: dict[str, np.ndarray],
                       out_path: str | Path, metadata: dict[str, str] | None = None) -> Path:
    """Write the fp32 graph with the adapted ``weights`` (parameter name -> array) to ``out_path``
    (atomic); ``metadata`` entries are added to (or replace) the graph's metadata."""
    onnx = require_onnx()
    from onnx import numpy_helper

    model = onnx.load(str(fp32_path))
    inits = {init.name: init for init in model.graph.initializer}
    for m in card.parameter_map:
        if m.parameter not in weights:
            raise CardError(f"adapted weights lack parameter {m.parameter!r} named by the card's parameter_map")
        if m.initializer not in inits:
            raise CardError(f"{fp32_path}: no initializer {m.initializer!r} (card parameter_map for "
                            f"{m.parameter!r}); this graph is not the one the step was exported with")
        arr = np.asarray(weights[m.parameter], dtype=np.float32)
        if tuple(arr.shape) != tuple(m.shape):
            raise CardError(f"adapted parameter {m.parameter!r} has shape {arr.shape}, the card says {m.shape}")
        if m.transform == "transpose":
            arr = arr.T
        if m.scale != 1.0:
            arr = arr * np.float32(m.scale)
        old = inits[m.initializer]
        if tuple(old.dims) != arr.shape:
            raise CardError(f"{fp32_path}: initializer {m.initializer!r} has shape {tuple(old.dims)}, the "
                            f"adapted tensor {arr.shape}")
        old.CopyFrom(numpy_helper.from_array(np.ascontiguousarray(arr), m.initializer))
    if metadata:
        set_metadata(model, metadata)
    out_path = Path(out_path)
    with atomic_path(out_path) as tmp:
        onnx.save(model, str(tmp))
    return out_path


def adaptation_metadata(card: AdaptationCard, report: dict) -> dict[str, str]:
    """Metadata entries recording an adaptation in the adapted model."""
    return {"adapted": "true", "adaptation": json.dumps(report, sort_keys=True),
            "adaptation_step": card.name}


def read_adapted_weights(card: AdaptationCard, fp32_path: str | Path) -> dict[str, np.ndarray]:
    """The step's trainable tensors held by an (adapted) fp32 graph: the inverse of
    :func:`write_adapted_onnx` (parameter = transform^-1(initializer / scale))."""
    onnx = require_onnx()
    from onnx import numpy_helper

    model = onnx.load(str(fp32_path))
    inits = {i.name: i for i in model.graph.initializer}
    out = {}
    for m in card.parameter_map:
        if m.initializer not in inits:
            raise CardError(f"{fp32_path}: no initializer {m.initializer!r}; not a graph of this step")
        arr = numpy_helper.to_array(inits[m.initializer]).astype(np.float32)
        if m.scale != 1.0:
            arr = arr / np.float32(m.scale)
        if m.transform == "transpose":
            arr = arr.T
        out[m.parameter] = np.ascontiguousarray(arr)
    return out
