"""``onnxruntime`` sessions, built in one place.

Explicit providers checked against what is installed (CUDA when present, CPU otherwise, a
warning when CUDA was asked for or offered and dropped), one intra-op thread by default,
sequential execution, full graph optimisation.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

from tactile_deploy.onnx_runtime.errors import ModelContractError

CUDA = "CUDAExecutionProvider"
CPU = "CPUExecutionProvider"


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


