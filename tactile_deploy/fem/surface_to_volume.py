"""Physics without learning: from a depth map to the whole pad mesh and its contact forces.

Treat the depth map as the vertical displacement of every sensing node (``u_z = -depth`` at
the node's rest position; the surface free to slide sideways, as under frictionless contact) and
solve the linear FEM for the rest of the pad. With the surface compliance ``C`` (z forces -> z
displacements of the sensing nodes) and the responses ``G`` of every node to those forces, both
precomputed by :class:`~tactile_deploy.fem.simulator.ContactSimulator`:

    forces  f = C^-1 u_z                (N at E = 1 MPa; the inverse-FEM force estimate)
    volume  u = G' f = (G' C^-1) u_z     (mm)

``H = G' C^-1`` is one dense linear operator (n*3 x n_plane), applied to a depth map in a
fraction of a millisecond. It is the baseline of the learned predictor: it is exact when the
depth map is exact and the contact frictionless, and it degrades with depth-map noise (C^-1
amplifies it) and where the real contact sticks.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from tactile_deploy.fem.simulator import ContactSimulator


def sample_depth_at(depth_mm: np.ndarray, xy_mm: np.ndarray, half_extent_mm: float = 17.5) -> np.ndarray:
    """Bilinear sample of a depth image (row 0 = largest y) at sensor points (k, 2) mm -> (k,) mm."""
    from scipy.ndimage import map_coordinates

    h, w = depth_mm.shape
    pitch_x = 2.0 * half_extent_mm / w
    pitch_y = 2.0 * half_extent_mm / h
    col = (xy_mm[:, 0] + half_extent_mm) / pitch_x - 0.5
    row = (half_extent_mm - xy_mm[:, 1]) / pitch_y - 0.5
    return map_coordinates(np.asarray(depth_mm, np.float64), [row, col], order=1, mode="nearest")


class SurfaceToVolume:
    """Linear map from the sensing surface's vertical displacement to the whole pad (frictionless).

    Parameters
    ----------
    simulator : a frictionless ContactSimulator over all sensing nodes (its operators are reused).
    """

    def __init__(self, simulator: ContactSimulator):
        if simulator.block != 1 or len(simulator.contact_nodes) != simulator.mesh.n_plane:
            raise ValueError("SurfaceToVolume needs a frictionless simulator over all sensing nodes")
        self.simulator = simulator
        self.mesh = simulator.mesh
        C = simulator.compliance
        G = np.asarray(simulator.greens, dtype=np.float64).reshape(len(C), -1)  # (n_plane, n*3)
        self._stiffness = linalg.inv(C)  # surface stiffness at E = 1, N/mm
        self._stiffness = 0.5 * (self._stiffness + self._stiffness.T)
        self.H = (self._stiffness @ G).T.astype(np.float32)  # (n*3, n_plane)

    @property
    def E_mpa(self) -> float:
        return self.simulator.material.E_mpa

    def sensing_uz_from_depth(self, depth_mm: np.ndarray, half_extent_mm: float = 17.5) -> np.ndarray:
        """u_z (n_plane,) mm of the sensing nodes read from a depth image."""
        xy = self.mesh.vertices[self.mesh.sensing_nodes, :2]
        return -sample_depth_at(depth_mm, xy, half_extent_mm)

    def displacements(self, uz_mm: np.ndarray) -> np.ndarray:
        """Displacements (n, 3) mm of every node for sensing-node u_z (n_plane,) mm; batches (B, n_plane) too."""
        uz = np.asarray(uz_mm, dtype=np.float32)
        out = uz @ self.H.T
        return out.reshape(*uz.shape[:-1], self.mesh.n_nodes, 3)

    def forces_n(self, uz_mm: np.ndarray) -> np.ndarray:
        """Force (n_plane,) N of the indenter on each sensing node, + = pushing the gel in."""
        return -self.E_mpa * (self._stiffness @ np.asarray(uz_mm, dtype=np.float64))

    def vertices_from_depth(
        self, depth_mm: np.ndarray, half_extent_mm: float = 17.5, iterations: int = 3
    ) -> np.ndarray:
        """Deformed vertices (n, 3) mm of the pad for a depth image (128, 128) mm.

        The image shows the surface where it has moved to: each node's depth is read at its
        rest position first, then (``iterations`` - 1 times) at its predicted deformed position.
        """
        xy0 = self.mesh.vertices[self.mesh.sensing_nodes, :2]
        xy = xy0
        for _ in range(max(1, iterations)):
            u = self.displacements(-sample_depth_at(depth_mm, xy, half_extent_mm))
            xy = xy0 + u[: self.mesh.n_plane, :2]
        return self.mesh.vertices + u
