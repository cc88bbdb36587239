"""Adapted ONNX model from the family's fp32 graph and the adapted step's weights.

The family's fp32 graph (``<model>_fp32.onnx``) is the same network as the step program's
encoder, projection and mesh decoder, exported with some constants folded in. Its initializers
that hold the encoder and the projection are replaced by the adapted tensors, as the step card's
``parameter_map`` says (``initializer = transform(parameter) x scale``); every other node,
initializer and the metadata stay, so the adapted model follows the same contract
(docs/onnx_contract.md). When the shipped family graph is int8, the adapted fp32 graph is
quantised the same way (static QDQ, same nodes, calibrated on the adaptation's own depth maps).

Needs the ``onnx`` package (``pip install 'tactile-deploy[adapt]'``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tactile_deploy.adapt.card import AdaptationCard, CardError
from tactile_deploy.atomic import atomic_path


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
        _merge_metadata(model, metadata)
    out_path = Path(out_path)
    with atomic_path(out_path) as tmp:
        onnx.save(model, str(tmp))
    return out_path


def quantise_int8(fp32_path: str | Path, out_path: str | Path, calibration_mm: np.ndarray,
                  nodes: list[str]) -> Path:
    """Static int8 QDQ quantisation of ``nodes`` of ``fp32_path`` (u8 activations, s8 per-channel
    weights, MinMax calibration on depth maps (K, 1, 128, 128) mm), as the family model was;
    metadata copied. Written atomically to ``out_path``."""
    import logging

    onnx = require_onnx()
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    cal = np.asarray(calibration_mm, np.float32)

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter([{"depth": cal[i : i + 1]} for i in range(len(cal))])

        def get_next(self):
            return next(self.it, None)

    out_path = Path(out_path)
    level = logging.getLogger().level
    logging.getLogger().setLevel(logging.ERROR)
    try:
        with atomic_path(out_path) as tmp:
            quantize_static(str(fp32_path), str(tmp), Reader(), quant_format=QuantFormat.QDQ,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                            nodes_to_quantize=list(nodes))
            src = onnx.load(str(fp32_path))
            q = onnx.load(str(tmp))
            del q.metadata_props[:]
            for p in src.metadata_props:
                e = q.metadata_props.add()
                e.key, e.value = p.key, p.value
            onnx.save(q, str(tmp))
    finally:
        logging.getLogger().setLevel(level)
    return out_path


def _merge_metadata(model, entries: dict[str, str]) -> None:
    """Add or replace metadata entries of an in-memory ONNX model (order kept, new ones last)."""
    props = {p.key: p.value for p in model.metadata_props}
    props.update(entries)
    del model.metadata_props[:]
    for k, v in props.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v


def write_metadata_entries(path: str | Path, entries: dict[str, str]) -> None:
    """Add or replace metadata entries of an ONNX file (atomic)."""
    onnx = require_onnx()

    model = onnx.load(str(path))
    _merge_metadata(model, entries)
    with atomic_path(path) as tmp:
        onnx.save(model, str(tmp))


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
