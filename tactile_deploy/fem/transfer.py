"""Carry a truth-mesh solution onto another mesh of the same pad (the frozen output mesh).

Both meshes are in the sensor frame (mm) and cover the same pad. A point is located in the
truth mesh's *rest* configuration and the truth field is interpolated there with the linear
shape functions of the tet that holds it, so the interpolated displacement is exactly the
finite-element field of the truth solution. A point a rounding error outside every tet (a rim
node of a disc whose truth outline is a polygon) takes the nearest tet's extrapolation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tactile_deploy.fem.elasticity import shape_gradients


def locate_in_tets(points: np.ndarray, vertices: np.ndarray, tets: np.ndarray, k: int = 24):
    """Tet index (q,) and barycentric coordinates (q, 4) of ``points`` (q, 3) in a tet mesh.

    Candidates are the ``k`` tets with the nearest centroids, widened to ``4 k`` for points
    none of them holds; the best candidate (largest smallest coordinate) is taken.
    """
    points = np.asarray(points, float)
    grads, _ = shape_gradients(vertices, tets)
    p0 = vertices[tets[:, 0]]
    centroids = vertices[tets].mean(axis=1)
    tree = cKDTree(centroids)

    def candidates(pts, kk):
        kk = min(kk, len(tets))
        _, cand = tree.query(pts, k=kk)
        cand = cand.reshape(len(pts), kk)
        rel = pts[:, None, :] - p0[cand]  # (q, k, 3)
        lam = np.einsum("qkaj,qkj->qka", grads[cand], rel)
        lam[:, :, 0] += 1.0
        worst = lam.min(axis=2)
        best = np.argmax(worst, axis=1)
        rows = np.arange(len(pts))
        return cand[rows, best], lam[rows, best], worst[rows, best]

    which, bary, worst = candidates(points, k)
    outside = worst < -1e-9
    if np.any(outside):
        w2, b2, m2 = candidates(points[outside], 4 * k)
        better = m2 > worst[outside]
        idx = np.flatnonzero(outside)[better]
        which[idx], bary[idx] = w2[better], b2[better]
    return which, bary


class Transfer:
    """Interpolation of truth-mesh nodal fields at fixed points (rest configuration)."""

    def __init__(self, truth_vertices: np.ndarray, truth_tets: np.ndarray, points: np.ndarray):
        self.which, self.bary = locate_in_tets(points, truth_vertices, np.asarray(truth_tets))
        self.nodes = np.asarray(truth_tets)[self.which]  # (q, 4)

    def __call__(self, field: np.ndarray) -> np.ndarray:
        """Nodal field (n_truth, ...) -> values at the points (q, ...)."""
        f = np.asarray(field)
        return np.einsum("qa,qa...->q...", self.bary, f[self.nodes])
