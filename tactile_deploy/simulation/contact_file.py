"""The ``tactile-deploy simulate --out FILE.npz`` format: one simulated contact.

Arrays (sensor frame: origin at the centre of the sensing surface, z up out of the gel)::

    depth           (128, 128) float32  mm pushed in along -z (row 0 = largest y)
    depth_detail    (128, 128) float32  mm, depth with the indenter's fine features restored
    mask            (128, 128) bool     pixel inside the pad's outline
    vertices        (n, 3) float32      deformed pad mesh, mm
    rest_vertices   (n, 3) float32      rest pad mesh, mm
    force_n         () float32          total normal force, N
    contact_mask    (n_plane,) bool     sensing nodes in contact
    pressure_kpa    (n_plane,) float32  contact pressure, kPa
    stick_mask      (n_plane,) bool     sensing nodes in contact that stick (resolved contacts)
    frame           (H, W, 3) uint8     RGB camera frame (``--sensor NAME --rgb`` only)
    metadata        () str              JSON: :class:`ContactMetadata`

:class:`ContactMetadata` is what the writer (:meth:`ContactSample.npz_arrays
<tactile_deploy.simulation.contact.ContactSample.npz_arrays>`) checks before writing and what
:func:`load_contact` checks on reading: the indenter (a library name, or a mesh file's absolute
path and sha256), the pose, the material, the mesh, the solver and the meaning and units of every
array. Errors name the file, the field, what was expected and what was found.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from tactile_deploy.fem.material import Material
from tactile_deploy.fileformat import StrictModel, read_npz_arrays
from tactile_deploy.indenters import ContactPose
from tactile_deploy.jsonfile import validation_error_text

#: The arrays every contact file holds (``frame`` and ``stick_mask`` are optional).
REQUIRED_ARRAYS = ("depth", "depth_detail", "mask", "vertices", "rest_vertices", "force_n",
                   "contact_mask", "pressure_kpa", "metadata")
OPTIONAL_ARRAYS = ("frame", "stick_mask")


class ContactFileError(ValueError):
    """A contact file that cannot be read (the message names the file, field, expected, actual)."""


class TruthMeshRecord(StrictModel):
    """The resolved solver's mesh of one contact."""

    n_nodes: int = Field(gt=0, description="Nodes of the truth mesh.")
    n_tets: int = Field(gt=0, description="Tetrahedra of the truth mesh.")
    fine_spacing_mm: float = Field(gt=0, description="Node spacing where contact occurs, mm.")
    n_constraints: int = Field(ge=0, description="Contact constraints of the last solve.")


class ImageGeometry(StrictModel):
    """Where the depth maps' pixels are (sensor frame)."""

    shape_px: list[int] = Field(min_length=2, max_length=2, description="(rows, columns).")
    half_extent_mm: float = Field(gt=0, description="Half the side of the imaged square, mm.")
    pixel_pitch_mm: float = Field(gt=0, description="Pixel side, mm.")
    projection: str = Field(description="How the surface is projected onto the image.")
    pixel_centre: str = Field(description="Sensor-frame position of pixel (row i, column j).")


class EffectRecord(StrictModel):
    """A discrepancy effect of a virtual sensor (its JSON form)."""

    name: str = Field(description="Effect name (tactile_deploy.sensors.effects).")
    params: dict = Field(description="Its parameters (names carry units).")


class ContactMetadata(StrictModel):
    """``metadata`` of a ``tactile-deploy simulate --out FILE.npz`` file.

    Three writers fill it: the resolved solver (``tactile-deploy simulate``: ``solver``,
    ``model``, ``truth_mesh``, ``max_penetration_mm``, ``tangential_force_n``), the frozen-mesh
    linear solver (:func:`~tactile_deploy.simulation.contact.simulate_contact`:
    ``formulation``) and a virtual sensor (``--sensor NAME``: ``sensor``, ``pose_reached``,
    ``effects``, ``frame_shape``).
    """

    indenter: str = Field(description="Library or analytic indenter name, or the absolute path "
                          "of the mesh file it was read from.")
    indenter_kind: str = Field("", description="Kind of indenter (primitive, novel, file, ...).")
    indenter_name: str | None = Field(None, description="Mesh-file indenters: the name it got.")
    indenter_sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$",
                                        description="Mesh-file indenters: sha256 of the file.")
    pressing_face: Literal["top", "bottom"] | None = Field(
        None, description="Mesh-file indenters: which face of the file pressed the gel.")
    scale_to_mm: float | None = Field(None, gt=0, description="Mesh-file indenters: factor that "
                                      "turned the file's units into mm.")
    pose: ContactPose = Field(description="Commanded contact (sensor frame, mm and degrees).")
    material: Material = Field(description="Gel material (E in MPa).")
    mesh_hash: str = Field(description="Content hash of the pad mesh of ``vertices``.")
    n_nodes: int = Field(gt=0, description="Nodes of that mesh (rows of ``vertices``).")
    generator_version: str | None = Field(None, description="Version of the contact generator.")
    solver: Literal["resolved"] | None = Field(None, description="\"resolved\": the truth "
                                               "solver with contact-refined mesh.")
    model: Literal["neo-hookean", "linear"] | None = Field(
        None, description="Resolved contacts: constitutive model.")
    formulation: str | None = Field(None, description="Frozen-mesh linear contacts: the "
                                    "element formulation.")
    truth_mesh: TruthMeshRecord | None = Field(None, description="Resolved contacts: its mesh.")
    max_penetration_mm: float | None = Field(None, ge=0, description="Resolved contacts: "
                                             "deepest penetration of the indenter, mm.")
    tangential_force_n: list[float] | None = Field(
        None, min_length=2, max_length=2, description="Resolved contacts: (x, y) tangential "
        "force on the gel, N, sensor frame.")
    slide_mm: list[float] | None = Field(
        None, min_length=2, max_length=2, description="Resolved contacts: (x, y) slide of the "
        "indenter along the surface after it was pressed, mm, sensor frame (absent: none).")
    sensor: str | None = Field(None, description="Virtual sensor that rendered ``frame``.")
    pose_reached: ContactPose | None = Field(None, description="Virtual sensors: the pose after "
                                             "contact effects (sensor frame).")
    effects: list[EffectRecord] | None = Field(None, description="Virtual sensors: effects.")
    frame_shape: list[int] | None = Field(None, min_length=3, max_length=3,
                                          description="Virtual sensors: (H, W, 3) of ``frame``.")
    units: dict[str, str] = Field(description="Unit of each array and number, by name.")
    frame: str = Field(description="Coordinate frame of the positions.")
    depth: str | None = Field(None, description="What ``depth`` is.")
    depth_detail: str | None = Field(None, description="What ``depth_detail`` is.")
    mask: str | None = Field(None, description="What ``mask`` is.")
    vertices: str | None = Field(None, description="What ``vertices`` are.")
    contact_mask: str | None = Field(None, description="What ``contact_mask`` is.")
    stick_mask: str | None = Field(None, description="What ``stick_mask`` is.")
    image: ImageGeometry | None = Field(None, description="Pixel geometry of the depth maps.")

    @model_validator(mode="after")
    def _complete(self):
        file_fields = ("indenter_name", "indenter_sha256", "pressing_face", "scale_to_mm")
        given = [k for k in file_fields if getattr(self, k) is not None]
        if given and len(given) != len(file_fields):
            missing = [k for k in file_fields if getattr(self, k) is None]
            raise ValueError(f"a mesh-file indenter records {', '.join(file_fields)}; "
                             f"{', '.join(missing)} missing")
        if given and not os.path.isabs(self.indenter):
            raise ValueError(f"field 'indenter' of a mesh-file indenter: expected the absolute "
                             f"path of the file, got {self.indenter!r}")
        if self.solver == "resolved":
            missing = [k for k in ("model", "truth_mesh", "max_penetration_mm",
                                   "tangential_force_n") if getattr(self, k) is None]
            if missing:
                raise ValueError(f"a resolved contact records {', '.join(missing)}; missing")
        return self

    def json_text(self) -> str:
        """The JSON written into the file (fields that do not apply left out)."""
        return self.model_dump_json(exclude_none=True)


def contact_metadata(meta: dict, where: str = "contact metadata") -> ContactMetadata:
    """``meta`` checked as :class:`ContactMetadata` (:class:`ContactFileError` naming the field,
    expected and actual value)."""
    try:
        return ContactMetadata.model_validate(meta)
    except ValidationError as e:
        raise ContactFileError(_message(where, e)) from None


def _message(where: str, e: ValidationError) -> str:
    return validation_error_text(where, e, "contact metadata",
                                 "the format is contact_metadata.schema.json in "
                                 "tactile_deploy/simulation/")


@dataclass(frozen=True)
class ContactFile:
    """A contact file read back: its arrays (names as in the module docstring) and metadata."""

    arrays: dict[str, np.ndarray]
    metadata: ContactMetadata


def load_contact(path: str | os.PathLike) -> ContactFile:
    """Read and check a ``tactile-deploy simulate --out FILE.npz`` file."""
    path = Path(path)
    arrays = read_npz_arrays(path, ContactFileError)
    missing = [k for k in REQUIRED_ARRAYS if k not in arrays]
    if missing:
        raise ContactFileError(f"{path}: field {missing[0]!r} missing: expected the arrays "
                               f"{', '.join(REQUIRED_ARRAYS)}, got {', '.join(sorted(arrays))}")
    unknown = sorted(set(arrays) - set(REQUIRED_ARRAYS) - set(OPTIONAL_ARRAYS))
    if unknown:
        raise ContactFileError(f"{path}: field {unknown[0]!r} is not part of the format "
                               f"(expected {', '.join(REQUIRED_ARRAYS + OPTIONAL_ARRAYS)})")
    text = str(arrays.pop("metadata"))
    try:
        meta = ContactMetadata.model_validate_json(text)
    except ValidationError as e:
        raise ContactFileError(_message(f"{path}: metadata", e)) from None
    n = arrays["vertices"].shape[0]
    if arrays["vertices"].shape != (meta.n_nodes, 3) or arrays["rest_vertices"].shape != (n, 3):
        raise ContactFileError(f"{path}: field 'vertices': expected ({meta.n_nodes}, 3) (metadata "
                               f"n_nodes) like rest_vertices, got {arrays['vertices'].shape} and "
                               f"{arrays['rest_vertices'].shape}")
    for name in ("depth", "depth_detail", "mask"):
        if meta.image is not None and list(arrays[name].shape) != meta.image.shape_px:
            raise ContactFileError(f"{path}: field {name!r}: expected shape "
                                   f"{tuple(meta.image.shape_px)} (metadata image.shape_px), got "
                                   f"{arrays[name].shape}")
    if "frame" in arrays and meta.frame_shape is not None and (
            list(arrays["frame"].shape) != meta.frame_shape):
        raise ContactFileError(f"{path}: field 'frame': expected shape {tuple(meta.frame_shape)} "
                               f"(metadata frame_shape), got {arrays['frame'].shape}")
    return ContactFile(arrays, meta)
