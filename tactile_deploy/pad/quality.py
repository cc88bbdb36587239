"""Tetrahedron quality measures.

* dihedral angles: the six angles between face pairs of each tet, degrees; a regular tet has
  70.53 deg everywhere, a sliver has angles near 0 and 180 deg;
* aspect ratio: circumradius / (3 x inradius), 1 for a regular tet, growing without bound for
  degenerate ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tactile_deploy.pad.meshing import signed_volumes

_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # face i is opposite vertex i
_EDGE_FACES = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


def dihedral_angles_deg(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Interior dihedral angles, (m, 6) float64, degrees."""
    p = vertices[tets]
    normals = []
    for face in _FACES:
        a, b, c = p[:, face[0]], p[:, face[1]], p[:, face[2]]
        n = np.cross(b - a, c - a)
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
    angles = []
    for i, j in _EDGE_FACES:
        cos = -np.einsum("ij,ij->i", normals[i], normals[j])
        angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.stack(angles, axis=1)


def aspect_ratios(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Circumradius / (3 inradius) per tet, (m,) float64; 1 for a regular tetrahedron."""
    p = vertices[tets]
    a = p[:, 1] - p[:, 0]
    b = p[:, 2] - p[:, 0]
    c = p[:, 3] - p[:, 0]
    six_vol = np.abs(np.einsum("ij,ij->i", np.cross(a, b), c))
    area = 0.0
    for face in _FACES:
        u = p[:, face[1]] - p[:, face[0]]
        w = p[:, face[2]] - p[:, face[0]]
        area = area + 0.5 * np.linalg.norm(np.cross(u, w), axis=1)
    inradius = 0.5 * six_vol / area  # 3 V / A
    # Circumradius: |a|^2 (b x c) + |b|^2 (c x a) + |c|^2 (a x b) over 2 * 6V.
    num = (
        np.sum(a * a, 1)[:, None] * np.cross(b, c)
        + np.sum(b * b, 1)[:, None] * np.cross(c, a)
        + np.sum(c * c, 1)[:, None] * np.cross(a, b)
    )
    circumradius = np.linalg.norm(num, axis=1) / (2.0 * six_vol)
    return circumradius / (3.0 * inradius)


@dataclass(frozen=True)
class QualityReport:
    """Summary of a tet mesh's quality."""

    n_tets: int
    n_inverted: int
    min_volume_mm3: float
    min_dihedral_deg: float
    max_dihedral_deg: float
    worst_aspect_ratio: float
    n_slivers: int  # tets with a dihedral angle under ``sliver_deg`` or over 180 - sliver_deg
    sliver_deg: float

    @property
    def ok(self) -> bool:
        return self.n_inverted == 0 and self.n_slivers == 0

    def __str__(self) -> str:
        return (
            f"{self.n_tets} tets, {self.n_inverted} inverted, {self.n_slivers} slivers "
            f"(dihedral < {self.sliver_deg:g} deg or > {180 - self.sliver_deg:g} deg); "
            f"dihedral {self.min_dihedral_deg:.1f}..{self.max_dihedral_deg:.1f} deg; "
            f"worst aspect ratio {self.worst_aspect_ratio:.2f}; "
            f"min volume {self.min_volume_mm3:.3g} mm^3"
        )


def quality_report(vertices: np.ndarray, tets: np.ndarray, sliver_deg: float = 10.0) -> QualityReport:
    """Check a tet mesh: inverted elements, slivers, dihedral extremes, worst aspect ratio."""

    vol = signed_volumes(vertices, tets)
    dih = dihedral_angles_deg(vertices, tets)
    slivers = np.any((dih < sliver_deg) | (dih > 180.0 - sliver_deg), axis=1)
    return QualityReport(
        n_tets=len(tets),
        n_inverted=int(np.sum(vol <= 0)),
        min_volume_mm3=float(vol.min()),
        min_dihedral_deg=float(dih.min()),
        max_dihedral_deg=float(dih.max()),
        worst_aspect_ratio=float(aspect_ratios(vertices, tets).max()),
        n_slivers=int(np.sum(slivers)),
        sliver_deg=sliver_deg,
    )
