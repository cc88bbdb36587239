"""The per-frame ``mesh_NNNNNN.npz`` of ``tactile-deploy run --format npz``: its metadata
(:class:`FrameMeshMetadata`) and its reader (:func:`load_frame_npz`).

Arrays (sensor frame: origin at the centre of the sensing surface, z up out of the gel)::

    vertices       (n, 3) float32  mm, deformed pad mesh (vertex i = pad mesh vertex i)
    rest_vertices  (n, 3) float32  mm, the undeformed pad mesh
    depth          (ny, nx) float32  mm pushed in along -z, model grid (row 0 = largest y);
                                   absent when the run made no depth map
    metadata       () str          JSON: :class:`FrameMeshMetadata`

The writer (:func:`tactile_deploy.runtime.writers.write_frame_npz`) builds the metadata through
the model; the reader checks it and the arrays against it. Errors name the file, the field, what
was expected and what was found.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError

from tactile_deploy.fileformat import StrictModel, read_npz_arrays
from tactile_deploy.jsonfile import validation_error_text

FRAME_FORMAT = "tactile-deploy.frame"
#: Version of the per-frame ``.npz`` layout.
FRAME_NPZ_VERSION = 1


class FrameFileError(ValueError):
    """A per-frame mesh file that cannot be read (the message names file, field, values)."""


class DepthGridRecord(StrictModel):
    """A pad family's own depth grid (docs/families.md), sensor frame, mm."""

    x_min: float = Field(description="Left edge of the grid, mm.")
    x_max: float = Field(description="Right edge of the grid, mm.")
    y_min: float = Field(description="Bottom edge of the grid, mm.")
    y_max: float = Field(description="Top edge of the grid (row 0), mm.")
    nx: int = Field(gt=0, description="Columns.")
    ny: int = Field(gt=0, description="Rows.")


class FrameMeshMetadata(StrictModel):
    """``metadata`` of a ``mesh_NNNNNN.npz`` written by ``tactile-deploy run``."""

    format: Literal["tactile-deploy.frame"] = Field(FRAME_FORMAT, description="Format name.")
    version: Literal[1] = Field(FRAME_NPZ_VERSION, description="Version of the layout.")
    units: dict[str, str] = Field(description="Unit of each array.")
    frame: str = Field(description="Coordinate frame of the positions.")
    mesh_hash: str = Field(description="Content hash of the pad mesh (rest_vertices, tets).")
    depth: str = Field(description="What ``depth`` is, and its grid.")
    depth_grid_mm: DepthGridRecord | None = Field(
        None, description="The family's own depth grid; None: 128 x 128 over +-17.5 mm.")
    sensor: str | None = Field(None, description="Plugin the frame was read with.")
    frame_index: int | None = Field(None, ge=0, description="Index of the frame in the run.")
    t_capture_ns: int | None = Field(None, description="Wall-clock time the frame was "
                                     "captured, ns since the epoch.")
    t_source_ns: int | None = Field(None, description="The source's own time stamp, ns.")
    source_label: str | None = Field(None, description="The source's name for the frame "
                                     "(file name of an image, ...).")
    ood_score: float | None = Field(None, description="Out-of-distribution score of the "
                                    "model (None: not computed).")
    total_normal_force_n: float | None = Field(None, description="Total normal force, N "
                                               "(None: forces not computed).")


def frame_metadata(meta: dict, where: str = "frame metadata") -> FrameMeshMetadata:
    """``meta`` checked as :class:`FrameMeshMetadata` (:class:`FrameFileError` naming each bad
    field and its value)."""
    try:
        return FrameMeshMetadata.model_validate(meta)
    except ValidationError as e:
        raise FrameFileError(validation_error_text(where, e, "frame metadata")) from None


@dataclass(frozen=True)
class FrameFile:
    """A per-frame mesh file read back: its arrays and its metadata."""

    arrays: dict[str, np.ndarray]
    metadata: FrameMeshMetadata


def load_frame_npz(path: str | os.PathLike) -> FrameFile:
    """Read and check a ``mesh_NNNNNN.npz`` of ``tactile-deploy run``."""
    path = Path(path)
    arrays = read_npz_arrays(path, FrameFileError)
    for name in ("vertices", "rest_vertices", "metadata"):
        if name not in arrays:
            raise FrameFileError(f"{path}: field {name!r} missing: expected vertices, "
                                 f"rest_vertices, metadata (and depth), got "
                                 f"{', '.join(sorted(arrays))}")
    unknown = sorted(set(arrays) - {"vertices", "rest_vertices", "depth", "metadata"})
    if unknown:
        raise FrameFileError(f"{path}: field {unknown[0]!r} is not part of the format "
                             "(expected vertices, rest_vertices, depth, metadata)")
    try:
        meta = FrameMeshMetadata.model_validate_json(str(arrays.pop("metadata")))
    except ValidationError as e:
        raise FrameFileError(validation_error_text(f"{path}: field 'metadata'", e,
                                                   "frame metadata")) from None
    v, rest = arrays["vertices"], arrays["rest_vertices"]
    if v.ndim != 2 or v.shape[1] != 3 or v.shape != rest.shape:
        raise FrameFileError(f"{path}: field 'vertices': expected (n, 3) like rest_vertices "
                             f"{rest.shape}, got {v.shape}")
    if "depth" in arrays:
        g = meta.depth_grid_mm
        expected = (128, 128) if g is None else (g.ny, g.nx)
        if arrays["depth"].shape != expected:
            raise FrameFileError(f"{path}: field 'depth': expected shape {expected} (metadata "
                                 f"depth_grid_mm), got {arrays['depth'].shape}")
    return FrameFile(arrays, meta)
