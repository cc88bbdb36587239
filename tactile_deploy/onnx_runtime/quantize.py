"""int8 quantisation of an ONNX graph, in one place.

Static (:func:`quantize_int8`): QDQ format, unsigned 8-bit activations and signed 8-bit
per-channel weights, MinMax calibration on example inputs; onnxruntime fuses the QDQ pairs into
integer kernels. An activation outside the calibration maps' range saturates.
Dynamic (:func:`quantize_int8_dynamic`, MatMul with constant weights): signed 8-bit per-channel
weights, the activation's range measured on every call (nothing saturates), fp32 output.
Only the named nodes are quantised (everything else stays fp32), and the fp32 graph's metadata is
kept. Needs the ``onnx`` package (the ``train`` or ``adapt`` extra).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.onnx_runtime.metadata import require_onnx, set_metadata


def quantize_int8(fp32_path: str | os.PathLike, out_path: str | os.PathLike,
                  calibration: np.ndarray, nodes: Sequence[str], input_name: str = "depth",
                  keep_metadata: bool = True) -> Path:
    """Quantise ``nodes`` of the graph ``fp32_path`` and write it to ``out_path`` (atomic).

    calibration : (K, ...) float32 example inputs of ``input_name``, one per calibration run
        (for the mesh model: depth maps (K, 1, 128, 128) mm).
    keep_metadata : copy the fp32 graph's metadata entries onto the quantised one.
    """
    require_onnx()
    from onnxruntime.quantization import (  # onnxruntime's optional quantisation tools
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    nodes = list(nodes)
    if not nodes:
        raise ValueError(f"{fp32_path}: no node to quantise")
    cal = np.asarray(calibration, np.float32)
    if len(cal) == 0:
        raise ValueError("quantisation needs at least one calibration input")

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter([{input_name: cal[i:i + 1]} for i in range(len(cal))])

        def get_next(self):
            return next(self.it, None)

    return _write_quantised(
        fp32_path, out_path, keep_metadata,
        lambda tmp: quantize_static(str(fp32_path), str(tmp), Reader(), quant_format=QuantFormat.QDQ,
                                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                                    per_channel=True, nodes_to_quantize=nodes))


def _write_quantised(fp32_path, out_path, keep_metadata: bool, quantise) -> Path:
    """Run ``quantise(tmp_path)`` into a temporary file renamed to ``out_path`` at the end (the
    quantiser's per-node INFO logging silenced), with the fp32 graph's metadata if ``keep_metadata``."""
    onnx = require_onnx()
    out_path = Path(out_path)
    level = logging.getLogger().level
    logging.getLogger().setLevel(logging.ERROR)  # the quantiser logs every node at INFO
    try:
        with atomic_path(out_path) as tmp:
            quantise(tmp)
            if keep_metadata:
                src = onnx.load(str(fp32_path), load_external_data=False)
                q = onnx.load(str(tmp))
                set_metadata(q, {p.key: p.value for p in src.metadata_props}, replace=True)
                onnx.save(q, str(tmp))
    finally:
        logging.getLogger().setLevel(level)
    return out_path


def quantize_int8_dynamic(fp32_path: str | os.PathLike, out_path: str | os.PathLike, nodes: Sequence[str],
                          keep_metadata: bool = True) -> Path:
    """Quantise the MatMul ``nodes`` of the graph ``fp32_path`` (constant weights) dynamically and
    write it to ``out_path`` (atomic): int8 per-channel weights, each call's activation range."""
    onnx = require_onnx()
    from onnxruntime.quantization import QuantType, quantize_dynamic  # onnxruntime's optional quantisation tools

    nodes = list(nodes)
    graph = onnx.load(str(fp32_path), load_external_data=False)
    ops = {n.name: n.op_type for n in graph.graph.node}
    wrong = [f"{n} ({ops.get(n, 'absent')})" for n in nodes if ops.get(n) != "MatMul"]
    if not nodes or wrong:
        raise ValueError(f"{fp32_path}: dynamic quantisation takes MatMul nodes; got {', '.join(wrong) or 'none'}")
    return _write_quantised(
        fp32_path, out_path, keep_metadata,
        lambda tmp: quantize_dynamic(str(fp32_path), str(tmp), weight_type=QuantType.QInt8, per_channel=True,
                                     nodes_to_quantize=nodes, extra_options={"MatMulConstBOnly": True}))
