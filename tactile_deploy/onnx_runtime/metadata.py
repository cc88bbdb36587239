"""ONNX metadata entries: set at export (needs the ``onnx`` package, the ``train`` or ``adapt``
extra) and read at load (onnxruntime only). What the mesh model's entries must be is the
contract's (:mod:`tactile_deploy.onnx_runtime.contract`).
"""

from __future__ import annotations

import os
from pathlib import Path

from tactile_deploy.atomic import atomic_path
from tactile_deploy.onnx_runtime.session import make_session


def require_onnx():
    try:
        import onnx
    except ImportError:
        raise ImportError("writing ONNX metadata needs the onnx package: pip install "
                          "'tactile-deploy[train]' (or [adapt])") from None
    return onnx


def set_metadata(model, entries: dict[str, str], replace: bool = False) -> None:
    """Set ``entries`` in an in-memory ``onnx.ModelProto``: added to (or replacing) the model's
    entries, order kept and new ones last; ``replace``: the entries become the whole metadata."""
    props = {} if replace else {p.key: p.value for p in model.metadata_props}
    props.update({str(k): str(v) for k, v in entries.items()})
    del model.metadata_props[:]
    for key, value in props.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value


def write_metadata(path: str | os.PathLike, entries: dict[str, str], replace: bool = False,
                   producer: str | None = None) -> None:
    """Set ``entries`` in the metadata of the ONNX file ``path`` (atomic; see
    :func:`set_metadata`); ``producer`` sets the model's producer name."""
    onnx = require_onnx()
    path = Path(path)
    model = onnx.load(str(path))
    set_metadata(model, entries, replace)
    if producer is not None:
        model.producer_name = producer
    with atomic_path(path) as tmp:
        onnx.save(model, str(tmp))


def read_metadata(source) -> dict[str, str]:
    """The metadata of an ONNX file (path) or of an ``onnxruntime.InferenceSession``."""
    if isinstance(source, (str, os.PathLike)):
        source = make_session(source, threads=1, providers="cpu")
    return dict(source.get_modelmeta().custom_metadata_map)
