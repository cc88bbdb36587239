"""Supports of the pad and the reduction of the FEM system to its free degrees of freedom.

Each node may be fixed (all three components zero) or carry rollers: zero displacement along
one or two unit normals, free along the others (skew normals allowed: a roller on a curved side
wall constrains the radial component). The free displacement of every node is written in a basis
of its free directions, so

    u = T q,       T : (3 n, n_q) sparse,  each column a unit vector of one node,

and the reduced stiffness is ``K_q = T' K T``. A node whose z direction is free keeps ``e_z`` as
one of its basis vectors (its *z column*), so contact on the sensing surface acts on single
columns of ``q``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from pydantic import BaseModel, ConfigDict, Field

from tactile_deploy.pad.mesh import PadMesh


class Supports(BaseModel):
    """How the pad is held.

    * ``backplate="fixed"``: the gel is bonded to the rigid backplate (the sensor);
      ``"rollers"``: the bottom may slide (u_z = 0 only), used by the patch tests; two pins
      (centre node in x and y, one rim node tangentially) then remove the rigid-body modes
      without restraining a uniform radial expansion.
    * ``side="free"`` (the sensor), ``"rollers"`` (zero normal displacement on the side wall,
      the confined-layer test) or ``"fixed"`` (side walls held by a rigid frame: every side node
      fixed).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    backplate: Literal["fixed", "rollers"] = Field("fixed", description="Bottom support.")
    side: Literal["free", "rollers", "fixed"] = Field("free", description="Side-wall support.")

    @property
    def key(self) -> str:
        return f"bp-{self.backplate}_side-{self.side}"


SENSOR_SUPPORTS = Supports()


def family_supports(family) -> Supports:
    """How a pad family (:class:`~tactile_deploy.pad.family.PadFamily`) holds its pad: a bonded
    backplate is fixed (a sliding one on rollers), fixed sides are fixed."""
    return Supports(backplate="fixed" if family.backplate == "bonded" else "rollers",
                    side="fixed" if family.sides == "fixed" else "free")


@dataclass(frozen=True)
class DofMap:
    """Map between full nodal displacements and free generalised coordinates ``q``.

    Attributes
    ----------
    T : (3 n, n_q) CSR
        ``u.ravel() = T @ q`` (node-major dofs).
    node_of_col : (n_q,) int64
        Node each column belongs to.
    direction_of_col : (n_q, 3) float64
        The column's unit direction (sensor frame).
    z_col : (n,) int64
        Column of ``e_z`` for each node, -1 where z is not a free direction.
    xy_cols : (n, 2) int64
        Columns of the node's horizontal free directions, -1 where absent.
    """

    T: sp.csr_matrix
    node_of_col: np.ndarray
    direction_of_col: np.ndarray
    z_col: np.ndarray
    xy_cols: np.ndarray

    @property
    def n_free(self) -> int:
        return self.T.shape[1]


def _node_normals(mesh: PadMesh, supports: Supports) -> dict[int, list[np.ndarray]]:
    normals: dict[int, list[np.ndarray]] = {}
    ez = np.array([0.0, 0.0, 1.0])
    v = mesh.vertices
    bottom = mesh.backplate_nodes
    if supports.backplate == "fixed":
        for i in bottom:
            normals[int(i)] = [np.eye(3)[0], np.eye(3)[1], ez]
    else:
        for i in bottom:
            normals.setdefault(int(i), []).append(ez)
    for plane, normal in (("x0", np.eye(3)[0]), ("y0", np.eye(3)[1])):
        for i in mesh.symmetry_nodes[plane]:  # symmetry planes of a quarter model
            normals.setdefault(int(i), []).append(normal)
    if supports.side == "fixed":
        for i in mesh.side_nodes:
            normals[int(i)] = [np.eye(3)[0], np.eye(3)[1], ez]
    if supports.side == "rollers":
        for i in mesh.side_nodes:
            for n in _side_normals(mesh, v[i]):
                normals.setdefault(int(i), []).append(n)
    if supports.backplate == "rollers":
        # Remove the rigid-body modes left by sliding supports with pins compatible with a
        # uniform expansion: the centre node in x and y (in-plane translation, unless side
        # rollers already hold it) and one rim node tangentially (rotation about z).
        xy = v[bottom, :2]
        radius = np.hypot(xy[:, 0], xy[:, 1])
        centre = int(bottom[np.argmin(radius)])
        if supports.side == "free" and mesh.geometry.sector_deg == 360.0:
            normals[centre] += [np.eye(3)[0], np.eye(3)[1]]
        if mesh.geometry.sector_deg == 360.0:
            rim = int(bottom[np.argmax(radius)])
            r = v[rim, :2] - v[centre, :2]
            tangent = np.array([-r[1], r[0], 0.0]) / np.hypot(r[0], r[1])
            normals[rim].append(tangent)
    return normals


def _side_normals(mesh: PadMesh, p: np.ndarray) -> list[np.ndarray]:
    """Outward normals of the side walls through point ``p`` (two at a box's vertical edge)."""
    g = mesh.geometry
    if g.shape == "disc":
        n = np.array([p[0], p[1], 0.0])
        return [n / np.linalg.norm(n)]
    tol = 1e-9 * g.half_extent_mm
    out = []
    if abs(abs(p[0]) - 0.5 * g.width_mm) < tol:
        out.append(np.array([np.sign(p[0]), 0.0, 0.0]))
    if abs(abs(p[1]) - 0.5 * g.length_mm) < tol:
        out.append(np.array([0.0, np.sign(p[1]), 0.0]))
    return out


def _free_basis(normals: list[np.ndarray]) -> np.ndarray:
    """Orthonormal basis (k, 3) of the directions orthogonal to ``normals``; e_z first if free."""
    N = np.array(normals)
    ez = np.array([0.0, 0.0, 1.0])
    _, s, vt = np.linalg.svd(N)
    rank = int(np.sum(s > 1e-9))
    null = vt[rank:]
    if len(null) == 0:
        return null
    if np.all(np.abs(N @ ez) < 1e-12):  # z free: keep e_z exactly, complete with horizontals
        horiz = null - np.outer(null @ ez, ez)
        keep = [ez]
        for h in horiz:
            for k in keep:
                h = h - (h @ k) * k
            if np.linalg.norm(h) > 1e-9:
                keep.append(h / np.linalg.norm(h))
        return np.array(keep[: len(null)])
    return null


def build_dof_map(mesh: PadMesh, supports: Supports) -> DofMap:
    """Free-coordinate basis of ``mesh`` under ``supports``."""
    n = mesh.n_nodes
    normals = _node_normals(mesh, supports)
    rows, cols, vals, node_of_col, dirs = [], [], [], [], []
    z_col = -np.ones(n, dtype=np.int64)
    xy_cols = -np.ones((n, 2), dtype=np.int64)
    col = 0
    eye = np.eye(3)
    for i in range(n):
        basis = _free_basis(normals[i]) if i in normals else eye[[2, 0, 1]]
        n_xy = 0
        for d in basis:
            nz = np.flatnonzero(np.abs(d) > 0)
            rows.extend(3 * i + nz)
            cols.extend([col] * len(nz))
            vals.extend(d[nz])
            node_of_col.append(i)
            dirs.append(d)
            if np.allclose(d, eye[2]):
                z_col[i] = col
            elif abs(d[2]) < 1e-12 and n_xy < 2:
                xy_cols[i, n_xy] = col
                n_xy += 1
            col += 1
    T = sp.csr_matrix((vals, (rows, cols)), shape=(3 * n, col))
    return DofMap(
        T=T,
        node_of_col=np.asarray(node_of_col, dtype=np.int64),
        direction_of_col=np.asarray(dirs, dtype=float).reshape(-1, 3),
        z_col=z_col,
        xy_cols=xy_cols,
    )
