"""``plugin.json``: the strict manifest of a sensor plugin folder, and reading it.

A plugin folder holds ``plugin.json`` (:class:`PluginManifest`) and the files it names, each with
its sha256: the shading model (``.npz``), the no-contact reference frame (PNG, raw camera
pixels), the noise reference (``.npy`` depth map on the model's grid), the demo clip (``.npz`` or
a video) and, usually outside the folder, the ONNX model of the sensor family. Relative paths in
a manifest are relative to the plugin folder. The committed JSON Schema is
``tactile_deploy/runtime/manifest.schema.json`` (``python -m tactile_deploy.formats`` rewrites it).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Literal

from pydantic import (
    Field,
    ValidationError,
    model_validator,
)

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.imaging.camera_mapping import CameraMapping, OutputGrid
from tactile_deploy.jsonfile import read_json, validation_error_text
from tactile_deploy.runtime.drift import ReferenceRange
from tactile_deploy.runtime.sources.config import SourceConfig

#: Version of the manifest format this code reads and writes.
FORMAT_VERSION = 1
#: File name of the manifest inside a plugin folder.
MANIFEST_NAME = "plugin.json"
#: The depth grid every model of this project takes: +-17.5 mm, 128 x 128 (sensor frame).
MODEL_GRID = OutputGrid()

_SHA256 = r"^[0-9a-f]{64}$"
#: What a plugin name (and so a plugin folder's name) may be.
NAME_PATTERN = r"^[a-z0-9][a-z0-9_\-]*$"


class PluginError(ValueError):
    """A plugin is missing, invalid, or its files do not match it (the message says which file,
    which field, what was expected and found, and what to do)."""


# ------------------------------------------------------------------------------------ manifest
class FileRef(StrictModel):
    """A file of the plugin and its checksum."""

    path: str = Field(min_length=1, description="File path, relative to the plugin folder "
                      "(POSIX separators) or absolute.")
    sha256: str = Field(pattern=_SHA256, description="sha256 of the file's bytes, lower-case hex.")


class FamilySpec(StrictModel):
    """The sensor family: which pad mesh its model outputs."""

    name: str = Field(min_length=1, description="Family name, e.g. 'gelslim'.")
    pad: str = Field("gelslim", description="Shipped pad asset the model's vertices follow "
                     "(`tactile-deploy pad info --pad NAME`).")
    pad_version: int = Field(1, ge=1, description="Version of that pad asset.")
    mesh_hash: str = Field(pattern=_SHA256, description="Content hash of the pad mesh; the "
                           "model's metadata must carry the same hash.")


class MaterialSpec(StrictModel):
    """The calibrated gel material used for contact forces."""

    E_mpa: float = Field(gt=0, le=1e4, description="Young's modulus, MPa (scales forces).")
    nu: float = Field(ge=0.0, lt=0.5, description="Poisson's ratio (sets the stiffness shape).")
    source: str = Field("", description="Where the values come from (calibration run, paper).")


class NoiseReferenceSpec(FileRef):
    """Depth map of the sensor with nothing touching it: its fixed-pattern depth noise."""

    handling: Literal["subtract", "keep"] = Field(
        description="'subtract': removed from every depth map before the model (the model was "
        "trained on clean depth); 'keep': left in (the model was trained with this noise added "
        "to its inputs, as in the paper's augmentation).")


class PluginManifest(StrictModel):
    """``plugin.json``: everything the runtime needs to turn this sensor's frames into meshes."""

    format_version: Literal[1] = Field(FORMAT_VERSION, description="Version of this file format.")
    name: str = Field(pattern=NAME_PATTERN,
                      description="Plugin name (lower case, digits, '-' and '_').")
    description: str = Field("", description="One line about the sensor.")
    family: FamilySpec = Field(description="Sensor family and its pad mesh.")
    model: FileRef | None = Field(
        None, description="ONNX model of the family: depth (N, 1, 128, 128) mm -> vertices "
        "(N, n, 3) mm (docs/onnx_contract.md); null when the family has no learned model yet: "
        "meshes then come from the physics lift of the pad (`run --mesh physics`).")
    adapted_model: FileRef | None = Field(
        None, description="Optional model adapted to this very sensor; used instead of `model` "
        "unless the user asks for the family model.")
    camera: CameraMapping = Field(description="Camera mapping: lens, homography to the sensing "
                                  "plane, and the imaging grid the shading model works on.")
    depth_grid: OutputGrid = Field(default_factory=OutputGrid,
                                   description="Grid of the depth maps: the pad family's depth "
                                   "grid (the GelSlim model's: +-17.5 mm, 128 x 128), row 0 at "
                                   "the largest y.")
    view_edge_extension_mm: float = Field(
        0.0, ge=0.0, le=2.0, description="Depth-grid cells outside the camera's imaging grid and "
        "within this distance (mm) of its edge take the depth at the edge (a contact seen at the "
        "edge of the view goes on past it); farther out, depth 0 (the flat far field). 0 for "
        "plugins whose model was trained with depth 0 outside the view (GelSlim's); the "
        "calibration from recorded presses sets the strip between the view and the pad family's "
        "depth grid.")
    shading: FileRef = Field(description="Shading model (.npz with JSON header) fitted on frames "
                             "rectified onto the camera's imaging grid.")
    readout: FileRef | None = Field(
        None, description="Optional learned read-out of the sensor's design (.onnx: rectified "
        "frame features -> depth, tactile_deploy/imaging/learned_readout.py); when given, it "
        "turns frames into depth instead of the shading model and the integration.")
    readout_depth_gain: float = Field(
        1.0, gt=0, description="This unit's depth gain of the learned read-out (its depth is "
        "multiplied by it), calibrated from ball presses of known intrusion.")
    reference_frame: FileRef = Field(description="No-contact frame, raw camera pixels, RGB "
                                     "image file (PNG).")
    noise_reference: NoiseReferenceSpec = Field(description="No-contact depth map (.npy, "
                                                "float32 mm, depth grid) and how to use it.")
    material: MaterialSpec = Field(description="Calibrated E and nu of the gel.")
    default_source: SourceConfig = Field(description="Frame source used when none is given.")
    demo_clip: FileRef = Field(description="Short recording (.npz clip or video) that "
                               "`tactile-deploy run` plays without a sensor.")
    topology: FileRef = Field(description="Topology file of the model's mesh (.npz: rest "
                              "vertices, tets, surface faces, sensing nodes, mesh hash; "
                              "docs/onnx_contract.md), for programs that use the ONNX model "
                              "without tactile-deploy.")
    ood_threshold: float | None = Field(
        None, gt=0, description="Out-of-distribution score above which frames are flagged "
        "(None: the model's own threshold from its metadata).")
    provenance: dict[str, str] = Field(default_factory=dict,
                                       description="How the plugin was made (tool, date, inputs).")
    reference_range: ReferenceRange | None = Field(
        None, description="What the calibration saw of the no-contact image (illumination "
        "drift, noise): `tactile-deploy run` warns when frames drift beyond it.")

    @model_validator(mode="after")
    def _check(self) -> PluginManifest:
        if self.model is not None and self.depth_grid != MODEL_GRID:
            raise ValueError(f"depth_grid must be the model grid {MODEL_GRID.model_dump()} (the "
                             f"learned model's input), got {self.depth_grid.model_dump()}")
        return self

    def files(self) -> dict[str, FileRef]:
        """Every file reference of the manifest, by field name."""
        out = {"shading": self.shading,
               "reference_frame": self.reference_frame,
               "noise_reference": self.noise_reference, "demo_clip": self.demo_clip,
               "topology": self.topology}
        if self.model is not None:
            out["model"] = self.model
        if self.adapted_model is not None:
            out["adapted_model"] = self.adapted_model
        if self.readout is not None:
            out["readout"] = self.readout
        return out



def load_manifest(path: str | os.PathLike) -> PluginManifest:
    """Read and validate a ``plugin.json`` (the file, or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    if not path.is_file():
        raise PluginError(f"plugin manifest {path} not found; a plugin folder holds a "
                          f"{MANIFEST_NAME} (see `tactile-deploy plugins list`)")
    doc = read_json(path, PluginError, "a JSON plugin manifest")
    if not isinstance(doc, dict):
        raise PluginError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    if doc.get("format_version") != FORMAT_VERSION:
        raise PluginError(f"{path}: field 'format_version': this version of tactile-deploy reads "
                          f"version {FORMAT_VERSION}, the file has {doc.get('format_version')!r}")
    try:
        # strict JSON types: "0.3" is no number, "yes" no boolean, 1.0 no integer (an integer is
        # a number); JSON arrays fill the tuple fields
        return PluginManifest.model_validate_json(json.dumps(doc), strict=True)
    except ValidationError as e:
        raise PluginError(validation_error_text(
            path, e, "plugin manifest",
            "the format is described by tactile_deploy/runtime/manifest.schema.json")) from None
