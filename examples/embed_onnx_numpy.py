"""Use a tactile-deploy mesh model with nothing but onnxruntime and numpy.

This is what robot software in another language does (C++, Rust, C#: the same onnxruntime
calls, and an .npz reader such as cnpy for the topology file): the contract is in
docs/onnx_contract.md.

    python examples/embed_onnx_numpy.py                       # the shipped gelslim2 plugin
    python examples/embed_onnx_numpy.py --plugin plugins/gelslim1
    python examples/embed_onnx_numpy.py --model M.onnx --topology T.npz

Steps: read the plugin's manifest (plain JSON) for the model and topology paths, check the
model's mesh hash against the topology file, build a depth map of a 4 mm ball pressed 0.6 mm
into the pad (the model's input grid and units), run the model, and report the mesh.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort

ROOT = Path(__file__).resolve().parent.parent
GRID = 128                  # the model grid: 128 x 128 pixels over +-17.5 mm
HALF_EXTENT_MM = 17.5


def sphere_press_depth(x_mm: float, y_mm: float, radius_mm: float, depth_mm: float) -> np.ndarray:
    """(128, 128) float32 depth map, mm, positive into the gel, of a rigid ball pressed in.

    Pixel (row i, column j) is centred at x = -17.5 + (j + 0.5) p, y = 17.5 - (i + 0.5) p with
    p = 35 / 128 mm: row 0 is the largest y (the pad seen from outside the gel).
    """
    p = 2 * HALF_EXTENT_MM / GRID
    x = -HALF_EXTENT_MM + (np.arange(GRID) + 0.5) * p
    y = HALF_EXTENT_MM - (np.arange(GRID) + 0.5) * p
    r2 = (x[None, :] - x_mm) ** 2 + (y[:, None] - y_mm) ** 2
    cap = depth_mm - (radius_mm - np.sqrt(np.maximum(radius_mm ** 2 - r2, 0.0)))
    return np.where(r2 < radius_mm ** 2, np.maximum(cap, 0.0), 0.0).astype(np.float32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plugin", type=Path, default=ROOT / "plugins" / "gelslim2",
                    help="plugin folder whose plugin.json names the model and topology")
    ap.add_argument("--model", type=Path, help="ONNX model (overrides the plugin's)")
    ap.add_argument("--topology", type=Path, help="topology .npz (overrides the plugin's)")
    args = ap.parse_args(argv)

    model_path, topology_path = args.model, args.topology
    if model_path is None or topology_path is None:
        manifest = json.loads((args.plugin / "plugin.json").read_text())
        ref = manifest["adapted_model"] or manifest["model"]
        model_path = model_path or (args.plugin / ref["path"])
        topology_path = topology_path or (args.plugin / manifest["topology"]["path"])

    # 1. the session: one thread, CPU (add "CUDAExecutionProvider" first to use a GPU)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(model_path), options, providers=["CPUExecutionProvider"])

    # 2. the fixed topology, and the check that the model outputs this very mesh
    with np.load(topology_path) as t:
        rest = t["rest_vertices_mm"]            # (n, 3) float64, mm, sensor frame
        tets = t["tets"]                        # (m, 4) int32
        surface_faces = t["surface_faces"]      # (f, 3) int32, outward normals
        sensing_nodes = t["sensing_nodes"]      # (k,) int32, nodes of the sensing surface
        mesh_hash = str(t["mesh_hash"])
    meta = session.get_modelmeta().custom_metadata_map
    if meta.get("mesh_hash") != mesh_hash:
        print(f"model {model_path} outputs mesh {meta.get('mesh_hash', '?')[:16]}..., the "
              f"topology file describes {mesh_hash[:16]}...: they do not belong together",
              file=sys.stderr)
        return 1

    # 3. one depth map in, one mesh out (a batch is the same call with N > 1)
    depth = sphere_press_depth(2.0, 3.0, 4.0, 0.6)
    vertices, displacement, ood = session.run(
        ["vertices", "displacement", "ood_score"], {"depth": depth[None, None]})
    v = vertices[0]                             # (n, 3) float32, mm, sensor frame
    d = displacement[0]
    threshold = float(meta["ood_threshold"]) if "ood_threshold" in meta else None

    top = d[sensing_nodes]
    deepest = sensing_nodes[np.argmin(top[:, 2])]
    print(f"model {model_path.name}: {len(v)} vertices, {len(tets)} tets, "
          f"{len(surface_faces)} surface faces")
    print(f"input: ball r 4 mm pressed 0.6 mm at (2, 3) mm; max depth {depth.max():.3f} mm")
    print(f"deepest sensing node {int(deepest)} at ({rest[deepest, 0]:.2f}, {rest[deepest, 1]:.2f}) "
          f"mm moved {-d[deepest, 2]:.3f} mm into the gel")
    print(f"max displacement {np.linalg.norm(d, axis=1).max():.3f} mm; "
          f"vertices - rest = displacement to {np.abs(v - rest - d).max():.1e} mm")
    state = "n/a" if threshold is None else ("in range" if ood[0] <= threshold else "OUT OF RANGE")
    print(f"out-of-distribution score {float(ood[0]):.4g} (threshold {threshold}): {state}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
