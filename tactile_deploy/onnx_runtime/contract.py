"""The mesh model contract (docs/onnx_contract.md), checked when a model is loaded.

Input ``depth`` (N, 1, 128, 128) float32 mm on the model grid; outputs ``vertices`` (N, n, 3)
float32 mm (sensor frame, the pad asset's vertex order), ``displacement`` (N, n, 3) mm and
``ood_score`` (N,); metadata ``mesh_hash`` equal to the pad mesh's content hash.
"""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.onnx_runtime.errors import ModelContractError
from tactile_deploy.onnx_runtime.session import make_session

INPUT_NAME = "depth"
OUTPUT_VERTICES = "vertices"
OUTPUT_DISPLACEMENT = "displacement"
OUTPUT_OOD = "ood_score"
META_MESH_HASH = "mesh_hash"
META_OOD_THRESHOLD = "ood_threshold"
GRID = 128

#: Sensor family, frame and input documentation written into the mesh model's metadata and card.
SENSOR_FAMILY = "gelslim"
FRAME = (
    "sensor frame: origin at the centre of the sensing surface, z up out of the gel, mm; "
    "vertex order of the frozen pad mesh (node = layer * 1076 + i, layer 0 = sensing surface)"
)
DEPTH_DOC = (
    "depth [N, 1, 128, 128] float32, mm the sensing surface is pushed in (>= 0); orthographic "
    "camera over +-17.5 mm, pixel (row i, col j) centred at x = -17.5 + (j + 0.5) 0.2734, "
    "y = 17.5 - (i + 0.5) 0.2734 mm (row 0 = largest y)"
)


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
