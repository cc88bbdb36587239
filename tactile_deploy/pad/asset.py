"""Frozen, versioned pad meshes shipped with the package.

A frozen pad is ``assets/pads/<name>_v<version>.npz`` (vertices, tets, plane triangles) plus a
JSON card (:class:`PadCard`) with the generating geometry, quality figures and the content hash.
Loading checks the hash, so a modified asset is refused rather than silently used.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import ConfigDict, Field

from tactile_deploy.atomic import write_json, write_npz
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.pad.family import FAMILIES, PadFamily
from tactile_deploy.pad.geometry import GELSLIM_PAD, PadGeometry
from tactile_deploy.pad.mesh import PadMesh, build_pad_mesh, content_hash
from tactile_deploy.pad.quality import quality_report
from tactile_deploy.shipped import asset_dir

ASSET_DIR = asset_dir("pads")

#: Pads we ship: name -> (version, geometry), one per pad family (tactile_deploy.pad.family).
SHIPPED_PADS: dict[str, tuple[int, PadGeometry]] = {"gelslim": (1, GELSLIM_PAD)}
SHIPPED_PADS.update({name: (1, fam.geometry()) for name, fam in FAMILIES.items()
                     if name != "gelslim"})


class PadCard(StrictModel):
    """Description of a frozen pad mesh (the JSON beside its .npz)."""

    model_config = ConfigDict(frozen=False)  # built field by field when a pad is frozen

    format_version: int = Field(1, description="Version of this card's format.")
    name: str = Field(description="Pad name, e.g. 'gelslim'.")
    version: int = Field(ge=1, description="Version of this pad's mesh; bump on any change.")
    geometry: PadGeometry = Field(description="Geometry the mesh was generated from.")
    n_nodes: int = Field(gt=0, description="Number of vertices.")
    n_tets: int = Field(gt=0, description="Number of tetrahedra.")
    n_sensing_nodes: int = Field(gt=0, description="Nodes on the sensing surface.")
    content_hash: str = Field(description="sha256 of vertices (nm, int64) and tets (int32).")
    min_dihedral_deg: float = Field(description="Smallest dihedral angle of any tet, degrees.")
    max_dihedral_deg: float = Field(description="Largest dihedral angle of any tet, degrees.")
    worst_aspect_ratio: float = Field(description="Largest circumradius / (3 inradius).")
    family: PadFamily | None = Field(None, description="The pad family the geometry was made "
                                     "from: outline, supports, sensing area, depth grid, and the "
                                     "sources and assumptions of every number.")
    sensing_spacing_mm: float | None = Field(None, description="Largest node spacing on the "
                                             "sensing area, mm (measured on the mesh).")


def asset_paths(name: str, version: int, directory: Path | None = None) -> tuple[Path, Path]:
    directory = ASSET_DIR if directory is None else directory
    stem = f"{name}_v{version}"
    return directory / f"{stem}.npz", directory / f"{stem}.json"


def freeze_pad(mesh: PadMesh, name: str, version: int, directory: Path | None = None,
               family: PadFamily | None = None) -> PadCard:
    """Write ``mesh`` as a frozen asset (atomic) and return its card (with ``family``, the
    sources and assumptions it was made from, when given)."""
    q = quality_report(mesh.vertices, mesh.tets)
    if not q.ok:
        raise ValueError(f"refusing to freeze pad '{name}': {q}")
    card = PadCard(
        name=name,
        version=version,
        geometry=mesh.geometry,
        n_nodes=mesh.n_nodes,
        n_tets=len(mesh.tets),
        n_sensing_nodes=mesh.n_plane,
        content_hash=mesh.content_hash,
        min_dihedral_deg=round(q.min_dihedral_deg, 3),
        max_dihedral_deg=round(q.max_dihedral_deg, 3),
        worst_aspect_ratio=round(q.worst_aspect_ratio, 4),
        family=family,
        sensing_spacing_mm=(None if family is None else
                            round(sensing_spacing_mm(mesh, family), 4)),
    )
    npz, js = asset_paths(name, version, directory)
    write_npz(npz, vertices=mesh.vertices, tets=mesh.tets, plane_triangles=mesh.plane_triangles)
    write_json(js, card.model_dump(mode="json"))
    return card


_LOADED: dict[tuple[str, int], PadMesh] = {}


def load_pad(name: str = "gelslim", version: int | None = None) -> PadMesh:
    """Load a shipped, frozen pad mesh and verify its content hash."""
    if name not in SHIPPED_PADS:
        raise KeyError(f"unknown pad '{name}'; shipped pads: {', '.join(sorted(SHIPPED_PADS))}")
    version = SHIPPED_PADS[name][0] if version is None else version
    key = (name, version)
    if key in _LOADED:
        return _LOADED[key]
    npz_path, json_path = asset_paths(name, version)
    if not npz_path.exists() or not json_path.exists():
        raise FileNotFoundError(
            f"pad asset {npz_path.name} / {json_path.name} missing from {ASSET_DIR}; "
            "reinstall tactile-deploy or run `tactile-deploy pad freeze`"
        )
    card = PadCard.model_validate(json.loads(json_path.read_text()))
    with np.load(npz_path) as data:
        vertices, tets, tris = data["vertices"], data["tets"], data["plane_triangles"]
    actual = content_hash(vertices, tets)
    if actual != card.content_hash:
        raise ValueError(
            f"{npz_path}: content hash {actual[:16]}... does not match its card "
            f"{json_path.name} ({card.content_hash[:16]}...); the asset was modified"
        )
    mesh = PadMesh(geometry=card.geometry, vertices=vertices, tets=tets, plane_triangles=tris)
    _LOADED[key] = mesh
    return mesh


def load_pad_card(name: str = "gelslim", version: int | None = None) -> PadCard:
    if name not in SHIPPED_PADS:
        raise KeyError(f"unknown pad '{name}'; shipped pads: {', '.join(sorted(SHIPPED_PADS))}")
    version = SHIPPED_PADS[name][0] if version is None else version
    return PadCard.model_validate(json.loads(asset_paths(name, version)[1].read_text()))


def regenerate_shipped(name: str) -> PadMesh:
    """Rebuild a shipped pad from its geometry (to compare with the frozen asset)."""
    return build_pad_mesh(SHIPPED_PADS[name][1])


def sensing_spacing_mm(mesh: PadMesh, family: PadFamily) -> float:
    """Longest edge (mm) of the sensing-surface triangles whose centroid lies in the family's
    sensing area: the spacing the depth map is sampled at there."""
    a = family.sensing_area
    p = mesh.vertices[mesh.plane_triangles][..., :2]
    c = p.mean(axis=1)
    inside = ((c[:, 0] >= a.x_min_mm) & (c[:, 0] <= a.x_max_mm)
              & (c[:, 1] >= a.y_min_mm) & (c[:, 1] <= a.y_max_mm))
    e = np.linalg.norm(p[:, [1, 2, 0]] - p, axis=2)[inside]
    # the longest edge of a right triangle of a grid is its diagonal: report the grid spacing
    # (the longer leg) for boxes, the longest edge for discs
    if family.outline == "rectangle":
        return float(np.sort(e, axis=1)[:, 1].max())
    return float(e.max())


def freeze_family(name: str, directory: Path | None = None) -> PadCard:
    """Mesh the shipped family ``name`` and freeze it (``python -m tactile_deploy.pad.asset NAME``)."""
    version, geometry = SHIPPED_PADS[name]
    return freeze_pad(build_pad_mesh(geometry), name, version, directory, FAMILIES[name])


if __name__ == "__main__":  # python -m tactile_deploy.pad.asset gelsight_mini digit
    import sys

    for pad_name in sys.argv[1:]:
        card = freeze_family(pad_name)
        print(f"froze {pad_name} v{card.version}: {card.n_nodes} nodes, {card.n_tets} tets, "
              f"sensing spacing {card.sensing_spacing_mm} mm, hash {card.content_hash[:16]}")
