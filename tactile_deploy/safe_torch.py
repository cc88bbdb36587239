"""Loading torch files without running code carried in them.

``torch.load(..., weights_only=False)`` unpickles arbitrary objects: a crafted file runs any
code it carries. Every torch file of this project (training checkpoints, the ``model.pt``
bundle, the adaptation step ``step.pt2``) holds only tensors, dicts, lists, strings and numbers,
plus numpy scalars in metrics and histories, so all of them load through torch's restricted
unpickler (``weights_only=True``) with numpy's scalar and dtype reconstruction allowed (data,
never code). A file naming any other global is refused (``pickle.UnpicklingError``) and nothing
in it runs. torch is imported only when a function here is called.
"""

from __future__ import annotations

import contextlib
import os


def _numpy_safe_globals() -> list:
    import numpy as np

    return [np._core.multiarray.scalar, np.dtype, np.dtypes.Float64DType, np.dtypes.Float32DType,
            np.dtypes.Int64DType, np.dtypes.Int32DType, np.dtypes.BoolDType]


def load_torch_file(path: str | os.PathLike, map_location="cpu"):
    """``torch.load`` with ``weights_only=True`` and numpy scalars allowed (module docstring)."""
    import torch

    with torch.serialization.safe_globals(_numpy_safe_globals()):
        return torch.load(path, map_location=map_location, weights_only=True)


@contextlib.contextmanager
def weights_only_loads():
    """Within: every ``torch.load``, also those inside torch (``torch.export.load`` falls back
    to ``weights_only=False`` for pickled weights and constants), uses the restricted unpickler."""
    import torch

    real = torch.load

    def restricted(f, *args, **kwargs):
        kwargs["weights_only"] = True
        with torch.serialization.safe_globals(_numpy_safe_globals()):
            return real(f, *args, **kwargs)

    torch.load = restricted
    try:
        yield
    finally:
        torch.load = real
