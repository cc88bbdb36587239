"""The mesh model contract (docs/onnx_contract.md), checked when a model is loaded.

Input ``depth`` (N, 1, 128, 128) float32 mm on the model grid; outputs ``vertices`` (N, n, 3)
float32 mm (sensor frame, the pad asset's vertex order), ``displacement`` (N, n, 3) mm and
``ood_score`` (N,). Metadata, written at export (:func:`mesh_model_metadata`) and checked at load
(:func:`check_model_contract`): the format and its version, the units, the frame, the input's
documentation, the pad, its mesh hash (equal to the pad mesh's content hash) and the node count.
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

#: The mesh model format this version writes and reads (metadata ``format``).
MESH_MODEL_FORMAT = "tactile-deploy.predictor/1"
#: The length unit of every input and output (metadata ``units``).
UNITS = "mm"
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


#: Metadata entries whose value must be exactly this version's (checked at load).
FIXED_ENTRIES = {"format": MESH_MODEL_FORMAT, "units": UNITS, "frame": FRAME,
                 "input.depth": DEPTH_DOC}


def mesh_model_metadata(pad: str, mesh_hash: str, n_nodes: int,
                        ood_threshold_mm: float | None = None,
                        sensor_family: str = SENSOR_FAMILY) -> dict[str, str]:
    """The contract entries of a mesh model's metadata (docs/onnx_contract.md)."""
    meta = {
        "format": MESH_MODEL_FORMAT,
        "sensor_family": sensor_family,
        "pad": pad,
        "mesh_hash": mesh_hash,
        "n_nodes": str(int(n_nodes)),
        "units": UNITS,
        "frame": FRAME,
        "input.depth": DEPTH_DOC,
        "output.vertices": f"vertices [N, {n_nodes}, 3] float32, mm, deformed positions = rest + "
                           "displacement",
        "output.displacement": f"displacement [N, {n_nodes}, 3] float32, mm, from the rest pad mesh",
        "output.ood_score": "ood_score [N] float32, mm: RMS error of the depth map's "
                            "reconstruction from the image VAE latent",
    }
    if ood_threshold_mm is not None:
        meta["ood_threshold"] = repr(float(ood_threshold_mm))
    return meta


def check_model_contract(model_path, expected_mesh_hash: str | None, n_nodes: int | None = None,
                         what: str = "model", session=None) -> dict:
    """Check names, shapes and metadata (format, units, frame, mesh hash, node count) of an ONNX
    mesh model; returns its metadata.

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
    for key, value in FIXED_ENTRIES.items():
        if meta.get(key) != value:
            raise ModelContractError(
                f"{where}: metadata {key!r} must be {value!r} (what this version of "
                f"tactile-deploy reads), the model has {meta.get(key)!r}; export the model again "
                "with this version (python -m tactile_deploy.training export)")
    if n_nodes is not None and meta.get("n_nodes") != str(n_nodes):
        raise ModelContractError(f"{where}: metadata 'n_nodes' must be '{n_nodes}' (the pad's "
                                 f"node count), the model has {meta.get('n_nodes')!r}")
    if expected_mesh_hash is not None and meta[META_MESH_HASH] != expected_mesh_hash:
        raise ModelContractError(
            f"{where}: its mesh hash {meta[META_MESH_HASH][:16]}... differs from the sensor "
            f"family's pad mesh {expected_mesh_hash[:16]}...; this model was trained for another "
            "mesh - use the model of this family, or a plugin made for that mesh")
    return meta
