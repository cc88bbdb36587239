"""A plugin of the real GelSight-class sensor of the FOTS ball presses (``../shared/data/real``).

    python -m tactile_deploy.calibration.shading.real_gelsight --out out/adapt/domains/fots-gelsight

Crop camera mapping (19.58 px/mm), shading model fitted on the 42 presses themselves, their
background as the reference frame and its depth as the noise reference (kept: it is part of the
sensor's signal), the shipped GelSlim family model; the presses are its demo clip. The
adaptation tables (``tactile-deploy bench adapt-tables``) read the real presses through it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from tactile_deploy.calibration.shading.fit import fit_shading
from tactile_deploy.calibration.shading.presses import PressSet, load_presses
from tactile_deploy.imaging.camera_mapping import crop_camera_mapping
from tactile_deploy.imaging.shading import save_shading
from tactile_deploy.pad.topology import MeshTopology
from tactile_deploy.runtime.pipeline import ImagingPipeline
from tactile_deploy.runtime.plugins import SensorPlugin, write_plugin
from tactile_deploy.runtime.sources.npz import save_clip
from tactile_deploy.shipped import model_path

#: The real ball presses beside the checkout.
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
#: Ball radius (mm) and scale (mm per px) of the presses.
REAL_BALL_RADIUS_MM = 2.35
REAL_MM_PER_PX = 1 / 19.58
#: Name of the plugin.
REAL_PLUGIN_NAME = "fots-gelsight"


def real_gelsight_plugin(folder: Path, shared_data: Path = SHARED_DATA) -> tuple[SensorPlugin, PressSet]:
    """A plugin of the real GelSight of the ball presses in ``folder`` (module docstring):
    ``(the plugin, the presses)``."""
    d = Path(shared_data) / "real" / "fots_gelsight_ballpress"
    if not (d / "annotate.csv").is_file():
        raise FileNotFoundError(f"real ball presses not found in {d}")
    presses = load_presses(d / "background.png", d, d / "annotate.csv")
    model = fit_shading(presses, REAL_BALL_RADIUS_MM, REAL_MM_PER_PX).model
    folder = Path(folder).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    h, w = presses.shape
    camera = crop_camera_mapping(w, h, REAL_MM_PER_PX)
    save_shading(model, folder / "shading.npz")
    cv2.imwrite(str(folder / "reference.png"), cv2.cvtColor(presses.reference, cv2.COLOR_RGB2BGR))
    pipe = ImagingPipeline(camera, model, presses.reference, None, "keep")
    np.save(folder / "noise_reference.npy", pipe.frame_to_depth(presses.reference))
    save_clip(folder / "demo.npz", presses.frames, np.arange(len(presses.frames)) * 50_000_000)
    topo = MeshTopology.from_pad()
    topo.save(folder / "topology.npz")
    write_plugin(folder, {
        "name": REAL_PLUGIN_NAME, "description": "real GelSight-class sensor of the FOTS ball presses",
        "family": {"name": "gelslim", "mesh_hash": topo.mesh_hash},
        "camera": json.loads(camera.model_dump_json()),
        "material": {"E_mpa": 0.3, "nu": 0.48}, "default_source": {"kind": "demo"},
        "noise_handling": "keep"},
        {"model": model_path("gelslim_mesh.onnx"), "shading": folder / "shading.npz",
         "reference_frame": folder / "reference.png", "noise_reference": folder / "noise_reference.npy",
         "demo_clip": folder / "demo.npz", "topology": folder / "topology.npz"}, overwrite=True)
    return SensorPlugin.load(folder), presses


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="plugin folder to write")
    ap.add_argument("--shared-data", type=Path, default=SHARED_DATA,
                    help="the shared data folder (default: %(default)s)")
    args = ap.parse_args(argv)
    plugin, presses = real_gelsight_plugin(args.out, args.shared_data)
    print(f"wrote plugin {plugin.name!r} in {plugin.folder} ({len(presses)} presses)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
