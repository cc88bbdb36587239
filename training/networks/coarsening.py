"""Layer-aware coarsening of the layered tetrahedral pad mesh, for COMA-style mesh networks.

COMA (Ranjan et al. 2018) down-samples triangle surfaces by quadric edge collapse and up-samples
with barycentric weights in the coarse triangles. Quadrics are degenerate on our mesh (every layer
is a flat disc) and edge collapse on tets would mix the five node layers. The pad mesh is an
extrusion: every node layer carries the same in-plane points and triangles, and the tets split
the prisms between layers. So we coarsen the **shared in-plane topology** and keep the layers:

1. In-plane selection (nested): level ``l + 1`` keeps ``1 / factor`` of level ``l``'s in-plane
   points: rim points evenly by angle (rim spacing grows by ``sqrt(factor)``), then farthest-point
   sampling of the interior. Deterministic.
2. Coarse topology: 2-D Delaunay of the kept points, extruded into the same node layers with the
   pad mesher's own prism split (:func:`tactile_deploy.pad.meshing.extrude`), so every level is a
   conforming tet mesh with the pad's node numbering (``node = layer * m + k``) and tet graph.
3. Up-sampling ``U_l`` (level ``l + 1`` -> ``l``): a fine node takes the barycentric weights of its
   in-plane point in the coarse triangle holding it, from the coarse nodes of the **same layer**
   (= barycentric interpolation in the coarse prism's face; layers sit at the same depths on every
   level). Fine rim points outside the coarse polygon are projected onto the nearest boundary edge
   (linear along the chord). Kept points get weight exactly 1.
4. Down-sampling ``D_l``: ``"select"`` (COMA: a coarse node takes its own fine value) or
   ``"average"`` (full weighting: ``D = diag(1 / U^T 1) U^T``, an anti-aliasing filter).

Node counts of the shipped pad with the default factors (4, 4, 4, 4): 5,380 -> 1,345 -> 335 ->
85 -> 20 (in-plane 1,076 -> 269 -> 67 -> 17 -> 4, five layers each).

Every sparse operator is a :class:`Resampling`: padded tables ``index`` / ``weight`` (n_out, S),
``y[i] = sum_s weight[i, s] * x[index[i, s]]`` -- the Gather + small dense block form that
onnxruntime runs well; :meth:`Resampling.matrix` gives the scipy matrix for analysis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tactile_deploy.pad.mesh import PadMesh
from tactile_deploy.pad.meshing import extrude, plane_triangles

POOLING = ("select", "average")


@dataclass(frozen=True)
class Resampling:
    """A fixed sparse linear map as padded tables: ``y[i] = sum_s weight[i, s] x[index[i, s]]``.

    index : (n_out, S) int64 -- padding entries point at row 0 with weight 0
    weight : (n_out, S) float64
    n_in : int -- rows of the input
    """

    index: np.ndarray
    weight: np.ndarray
    n_in: int

    @property
    def n_out(self) -> int:
        return len(self.index)

    def matrix(self) -> sp.csr_matrix:
        """(n_out, n_in) scipy CSR matrix (padding dropped, duplicates summed)."""
        rows = np.repeat(np.arange(self.n_out), self.index.shape[1])
        m = sp.coo_matrix(
            (self.weight.ravel(), (rows, self.index.ravel())), shape=(self.n_out, self.n_in)
        ).tocsr()
        m.eliminate_zeros()
        return m

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Apply along axis 0: ``x`` (n_in, ...) -> (n_out, ...)."""
        x = np.asarray(x)
        if x.shape[0] != self.n_in:
            raise ValueError(f"x must have {self.n_in} rows, got shape {x.shape}")
        g = x[self.index]  # (n_out, S, ...)
        w = self.weight.reshape(self.weight.shape + (1,) * (x.ndim - 1))
        return (g * w).sum(axis=1)

    @staticmethod
    def from_matrix(m: sp.spmatrix) -> "Resampling":
        """Padded tables of a scipy sparse matrix (width = most non-zeros in a row)."""
        m = sp.csr_matrix(m)
        m.sort_indices()
        counts = np.diff(m.indptr)
        width = max(int(counts.max(initial=0)), 1)
        index = np.zeros((m.shape[0], width), np.int64)
        weight = np.zeros((m.shape[0], width), np.float64)
        for i in range(m.shape[0]):
            a, b = m.indptr[i], m.indptr[i + 1]
            index[i, : b - a] = m.indices[a:b]
            weight[i, : b - a] = m.data[a:b]
        return Resampling(index, weight, m.shape[1])


@dataclass(frozen=True, eq=False)
class MeshLevel:
    """One level of the hierarchy: a layered tet mesh on a subset of the pad's in-plane points.

    plane_index : (m,) int64 -- indices of its in-plane points among the pad's (layer-0 node ids)
    plane_xy_mm : (m, 2) float64, mm, sensor frame
    plane_triangles : (t, 3) int64, counter-clockwise from +z
    vertices_mm : (n_layers * m, 3) float64, mm, sensor frame; node ``layer * m + k``
    tets : (q, 4) int64
    """

    plane_index: np.ndarray
    plane_xy_mm: np.ndarray
    plane_triangles: np.ndarray
    vertices_mm: np.ndarray
    tets: np.ndarray
    n_layers: int

    @property
    def n_plane(self) -> int:
        return len(self.plane_index)

    @property
    def n_nodes(self) -> int:
        return len(self.vertices_mm)

    @cached_property
    def edges(self) -> np.ndarray:
        """Unique undirected edges of the tet graph, (e, 2) int64, i < j."""
        pairs = self.tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
        return np.unique(np.sort(pairs, axis=1), axis=0)

    @cached_property
    def chebyshev_operator(self) -> Resampling:
        """The scaled normalised Laplacian ``2 L / lambda_max - I`` of the tet graph, as tables.

        ``L = I - D^-1/2 A D^-1/2`` (A: 0/1 adjacency). Its spectrum maps onto [-1, 1], where the
        Chebyshev polynomials of a ChebConv are bounded. The diagonal is the first column.
        """
        n = self.n_nodes
        e = self.edges
        a = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), (n, n))
        a = a.tocsr()
        dinv = 1.0 / np.sqrt(np.asarray(a.sum(axis=1)).ravel())
        lap = sp.identity(n) - sp.diags(dinv) @ a @ sp.diags(dinv)
        if n > 64:
            lmax = float(spla.eigsh(lap, k=1, which="LA", return_eigenvectors=False, tol=1e-8)[0])
        else:
            lmax = float(np.linalg.eigvalsh(lap.toarray()).max())
        scaled = (2.0 / lmax) * lap - sp.identity(n)
        # Diagonal first (self), then the neighbours in ascending order.
        scaled = sp.csr_matrix(scaled)
        diag = scaled.diagonal()
        off = scaled - sp.diags(diag)
        off.eliminate_zeros()
        tab = Resampling.from_matrix(off)
        index = np.concatenate([np.arange(n)[:, None], tab.index], axis=1)
        weight = np.concatenate([diag[:, None], tab.weight], axis=1)
        return Resampling(index, weight, n)


@dataclass(frozen=True, eq=False)
class Hierarchy:
    """Levels (0 = the pad mesh) and the resamplings between them.

    up[l] : level l + 1 -> level l (barycentric, same layer)
    down[l] : level l -> level l + 1 (``pooling``: "select" or "average")
    """

    levels: tuple[MeshLevel, ...]
    up: tuple[Resampling, ...]
    down: tuple[Resampling, ...]
    pooling: str
    mesh_hash: str

    @property
    def node_counts(self) -> tuple[int, ...]:
        return tuple(lv.n_nodes for lv in self.levels)

    def down_up(self, field: np.ndarray, level: int) -> np.ndarray:
        """Project ``field`` (n_0, ...) down to ``level`` and back up to level 0."""
        x = np.asarray(field, dtype=np.float64)
        for l in range(level):
            x = self.down[l].apply(x)
        for l in reversed(range(level)):
            x = self.up[l].apply(x)
        return x

    def least_squares_up(self, field: np.ndarray, level: int) -> np.ndarray:
        """Best level-0 field in the span of the up-sampling chain from ``level`` (L2 projection).

        The floor of any coarse representation interpolated with these weights.
        """
        u = sp.identity(self.levels[0].n_nodes, format="csr")
        for l in range(level):
            u = u @ self.up[l].matrix()
        x = np.asarray(field, dtype=np.float64).reshape(u.shape[0], -1)
        a = (u.T @ u).toarray()
        coef = np.linalg.solve(a + 1e-12 * np.trace(a) / len(a) * np.eye(len(a)), u.T @ x)
        return (u @ coef).reshape(np.shape(field))


def _rim_mask(xy: np.ndarray, mesh: PadMesh) -> np.ndarray:
    g = mesh.geometry
    if g.shape != "disc" or g.sector_deg != 360.0:
        raise ValueError(
            f"layer-aware coarsening supports full disc pads; pad '{g.name}' is shape={g.shape!r} "
            f"sector_deg={g.sector_deg}"
        )
    return np.abs(np.hypot(xy[:, 0], xy[:, 1]) - g.radius_mm) < 1e-9 * g.radius_mm + 1e-12


def select_plane_points(xy: np.ndarray, rim: np.ndarray, n_keep: int, n_rim: int) -> np.ndarray:
    """Indices (n_keep,) into ``xy`` (m, 2) mm: ``n_rim`` rim points evenly by angle, then FPS.

    Farthest-point sampling adds, one at a time, the point farthest from those already kept
    (ties: lowest index), which spreads the kept points evenly over the disc.
    """
    rim_idx = np.flatnonzero(rim)
    if n_rim > len(rim_idx) or n_keep > len(xy) or n_rim >= n_keep:
        raise ValueError(f"cannot keep {n_keep} points with {n_rim} on a rim of {len(rim_idx)}")
    ang = np.mod(np.arctan2(xy[rim_idx, 1], xy[rim_idx, 0]), 2.0 * math.pi)
    ordered = rim_idx[np.argsort(ang, kind="stable")]
    picks = np.floor(np.arange(n_rim) * len(ordered) / n_rim + 1e-9).astype(int)
    kept = list(ordered[picks])
    dist = np.min(np.linalg.norm(xy[:, None, :] - xy[kept][None, :, :], axis=2), axis=1)
    while len(kept) < n_keep:
        i = int(np.argmax(dist))
        kept.append(i)
        dist = np.minimum(dist, np.linalg.norm(xy - xy[i], axis=1))
    return np.asarray(kept, dtype=np.int64)


def barycentric_weights(
    fine_xy: np.ndarray, coarse_xy: np.ndarray, triangles: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Interpolation of coarse in-plane values at fine points: ``(index (m, 3), weight (m, 3))``.

    A point inside a coarse triangle gets its barycentric coordinates; a point outside the coarse
    polygon (rim points between coarse rim points) is projected onto the nearest boundary edge.
    """
    p = coarse_xy[triangles]  # (t, 3, 2)
    v0, v1 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    d = fine_xy[:, None, :] - p[None, :, 0, :]  # (m, t, 2)
    b1 = (d[..., 0] * v1[:, 1] - d[..., 1] * v1[:, 0]) / det
    b2 = (v0[:, 0] * d[..., 1] - v0[:, 1] * d[..., 0]) / det
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=-1)  # (m, t, 3)
    score = bary.min(axis=-1)
    best = np.argmax(score, axis=1)
    inside = score[np.arange(len(fine_xy)), best] >= -1e-9
    index = triangles[best].astype(np.int64)
    weight = bary[np.arange(len(fine_xy)), best]
    # Outside: nearest boundary edge.
    e = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    for i in np.flatnonzero(~inside):
        a, b = coarse_xy[boundary[:, 0]], coarse_xy[boundary[:, 1]]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", fine_xy[i] - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
        dist = np.linalg.norm(a + t[:, None] * ab - fine_xy[i], axis=1)
        k = int(np.argmin(dist))
        index[i] = [boundary[k, 0], boundary[k, 1], boundary[k, 0]]
        weight[i] = [1.0 - t[k], t[k], 0.0]
    weight = np.where(np.abs(weight) < 1e-12, 0.0, weight)
    weight = np.clip(weight, 0.0, 1.0)
    weight /= weight.sum(axis=1, keepdims=True)
    return index, weight


def _layered(index: np.ndarray, weight: np.ndarray, m_out: int, m_in: int, n_layers: int) -> Resampling:
    """Repeat an in-plane table on every node layer (node = layer * m + k)."""
    idx = np.concatenate([index + layer * m_in for layer in range(n_layers)])
    w = np.concatenate([weight] * n_layers)
    return Resampling(idx, w, n_layers * m_in)


def build_hierarchy(
    mesh: PadMesh, factors: tuple[int, ...] = (4, 4, 4, 4), pooling: str = "select"
) -> Hierarchy:
    """Coarsen ``mesh`` level by level, each level ``factor`` times fewer nodes (see module doc)."""
    if pooling not in POOLING:
        raise ValueError(f"pooling must be one of {POOLING}, got {pooling!r}")
    g = mesh.geometry
    n_layers = g.n_layers + 1
    xy0 = mesh.vertices[: mesh.n_plane, :2]
    level0 = MeshLevel(
        plane_index=np.arange(mesh.n_plane),
        plane_xy_mm=xy0,
        plane_triangles=mesh.plane_triangles.astype(np.int64),
        vertices_mm=mesh.vertices,
        tets=mesh.tets.astype(np.int64),
        n_layers=n_layers,
    )
    levels = [level0]
    ups, downs = [], []
    n_rim = int(_rim_mask(xy0, mesh).sum())
    for factor in factors:
        prev = levels[-1]
        rim = _rim_mask(prev.plane_xy_mm, mesh)
        n_keep = max(4, int(round(prev.n_plane / factor)))
        n_rim = max(3, min(int(round(n_rim / math.sqrt(factor))), int(round(0.6 * n_keep))))
        local = select_plane_points(prev.plane_xy_mm, rim, n_keep, n_rim)
        xy = prev.plane_xy_mm[local]
        tris = plane_triangles(xy, g)
        vertices, tets = extrude(xy, tris, g)
        level = MeshLevel(
            plane_index=prev.plane_index[local],
            plane_xy_mm=xy,
            plane_triangles=tris,
            vertices_mm=vertices,
            tets=tets,
            n_layers=n_layers,
        )
        bi, bw = barycentric_weights(prev.plane_xy_mm, xy, tris)
        up = _layered(bi, bw, prev.n_plane, level.n_plane, n_layers)
        if pooling == "select":
            down = _layered(local[:, None], np.ones((len(local), 1)), level.n_plane, prev.n_plane, n_layers)
        else:
            ut = up.matrix().T.tocsr()
            down = Resampling.from_matrix(sp.diags(1.0 / np.asarray(ut.sum(axis=1)).ravel()) @ ut)
        levels.append(level)
        ups.append(up)
        downs.append(down)
    return Hierarchy(tuple(levels), tuple(ups), tuple(downs), pooling, mesh.content_hash)
