"""Load an indenter from a mesh file (STL, OBJ, PLY; units mm).

``pressing_face="top"``: the contact feature is the top (largest z) of the file, as for indenters
modelled standing on a mounting base (the shared FOTS set). The mesh is turned over by a
rotation of 180 degrees about the x axis, ``(x, y, z) -> (x, -y, -z)``, so that the feature
faces the gel. ``pressing_face="bottom"``: the feature already faces -z; the mesh is only moved.
Either way the result is then put in the indenter frame (x, y bounding-box centre at the origin,
lowest point at z = 0).
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np

from tactile_deploy.indenters.base import DEFAULT_MAX_RELIEF_MM, DEFAULT_PITCH_MM, Indenter

SUFFIXES = (".stl", ".obj", ".ply")
PRESSING_FACES = ("top", "bottom")
#: Plausible range (mm) of the largest bounding-box extent of an indenter.
EXTENT_RANGE_MM = (0.2, 300.0)


def load_indenter(
    path: str | Path,
    pressing_face: str = "top",
    name: str | None = None,
    scale_to_mm: float = 1.0,
    *,
    pitch_mm: float = DEFAULT_PITCH_MM,
    max_relief_mm: float = DEFAULT_MAX_RELIEF_MM,
) -> Indenter:
    """Read a triangle mesh and return it as an :class:`Indenter` of kind "file".

    path : mesh file (.stl, .obj, .ply) with coordinates in units that ``scale_to_mm`` turns
        into mm (1 for mm, 1000 for m, 25.4 for inches).
    pressing_face : "top" (feature at the file's largest z) or "bottom" (feature facing -z).
    name : defaults to the file stem.
    """
    path = Path(path)
    if pressing_face not in PRESSING_FACES:
        raise ValueError(f"{path}: pressing_face must be one of {PRESSING_FACES}, got {pressing_face!r}")
    if not (isinstance(scale_to_mm, (int, float)) and math.isfinite(scale_to_mm) and scale_to_mm > 0):
        raise ValueError(f"{path}: scale_to_mm must be a finite number > 0, got {scale_to_mm!r}")
    if not path.is_file():
        raise FileNotFoundError(f"indenter mesh {path} does not exist (or is not a file)")
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(
            f"{path}: expected a mesh file with suffix {', '.join(SUFFIXES)}, found {path.suffix!r}"
        )
    mesh = _read_mesh(path)
    if scale_to_mm != 1.0:
        mesh.apply_scale(scale_to_mm)
    extent = float(np.max(mesh.extents))
    lo, hi = EXTENT_RANGE_MM
    if not lo <= extent <= hi:
        raise ValueError(
            f"{path}: largest extent is {extent:.4g} mm after scale_to_mm={scale_to_mm:g}; an "
            f"indenter is expected between {lo:g} and {hi:g} mm. Pass scale_to_mm to convert "
            f"(1000 for a file in metres, 25.4 for inches)"
        )
    if pressing_face == "top":
        mesh.apply_transform(np.diag([1.0, -1.0, -1.0, 1.0]))
    indenter = Indenter(mesh, name or path.stem, "file", pitch_mm=pitch_mm,
                        max_relief_mm=max_relief_mm)
    # Where it came from, so that a contact can be simulated again from its record.
    indenter.source_path = str(path.resolve())
    indenter.source_sha256 = hashlib.sha256(path.read_bytes()).hexdigest()
    indenter.pressing_face = pressing_face
    indenter.scale_to_mm = float(scale_to_mm)
    return indenter


def _read_mesh(path: Path):
    """A ``trimesh.Trimesh`` with at least one face and finite vertices, or a clear error."""
    import trimesh

    if path.stat().st_size == 0:
        raise ValueError(f"{path}: file is empty; expected a triangle mesh")
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
    except Exception as err:  # every reader failure becomes one clear message
        raise ValueError(f"{path}: cannot be read as a triangle mesh ({type(err).__name__}: {err})") from err
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(f"{path}: expected a triangle mesh, found {type(loaded).__name__}")
    if len(loaded.faces) == 0:
        raise ValueError(
            f"{path}: expected a triangle mesh with faces, found {len(loaded.vertices)} vertices "
            f"and no faces"
        )
    if not np.all(np.isfinite(loaded.vertices)):
        raise ValueError(f"{path}: mesh has NaN or inf vertex coordinates")
    return loaded
