"""The physics lift for any pad: a depth map of the sensing surface -> the whole deformed pad mesh.

The depth map gives the vertical displacement of every sensing node (``u_z = -depth`` read at
the node; the surface free to slide sideways, as under frictionless contact); the linear FEM of
the pad under its supports gives every other displacement and the reaction forces:

    K_ff u_f = -K_fp u_p           (u_p: the sensing nodes' u_z, prescribed; u_f: the rest)
    f_p      =  E (K_pf u_f + K_pp u_p)   (N: the force the indenter puts on each sensing node)

One sparse Cholesky factor of ``K_ff`` per pad (CHOLMOD, a few seconds for 10k nodes), then one
forward/back substitution per frame: no dense operator, so it scales to fine meshes (the dense
surface-to-volume operator of :mod:`tactile_deploy.fem.surface_to_volume` needs
``3 n x n_sensing`` floats). The two give the same displacements (tested).

The image shows the surface where it has moved to, so each node's depth is read where the node
is after the solve (a fixed point, found by relaxed iteration: :meth:`DepthLift.from_depth`).

Frames: sensor frame, mm; depth positive into the gel (mm); forces N (+ = pressing the gel in).
Needs numpy and SciPy only (no torch, no warp).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import map_coordinates

from tactile_deploy.fem.constraints import SENSOR_SUPPORTS, Supports, build_dof_map
from tactile_deploy.fem.elasticity import assemble_stiffness_numpy
from tactile_deploy.fem.sparse_solver import SparseCholesky
from tactile_deploy.pad.mesh import PadMesh


def sample_depth_grid(depth_mm: np.ndarray, grid, xy_mm: np.ndarray) -> np.ndarray:
    """Bilinear sample of a depth map on ``grid`` (an
    :class:`~tactile_deploy.imaging.camera_mapping.OutputGrid`; row 0 at the largest y) at
    sensor points (k, 2) mm -> (k,) mm. Points outside the grid read 0 (the flat far field: the
    depth maps of this project are 0 outside the sensing area), blending to it over the last
    half cell."""
    depth = np.asarray(depth_mm, np.float64)
    if depth.shape != (grid.ny, grid.nx):
        raise ValueError(f"depth map has shape {depth.shape}, its grid is {grid.ny} x {grid.nx}")
    col = (xy_mm[:, 0] - grid.x_min_mm) / grid.pitch_x_mm - 0.5
    row = (grid.y_max_mm - xy_mm[:, 1]) / grid.pitch_y_mm - 0.5
    padded = np.pad(depth, 1)  # a ring of zeros half a cell beyond the grid's edge
    return map_coordinates(padded, [row + 1, col + 1], order=1, mode="constant", cval=0.0)


class DepthLift:
    """Depth map -> deformed pad (module docstring).

    mesh : the pad mesh. nu : Poisson ratio. E_mpa : Young's modulus (MPa; forces only).
    supports : how the pad is held (default: bonded backplate, free sides).
    formulation : "nodal_pressure" (locking-free, as the simulator) or "standard".
    """

    def __init__(self, mesh: PadMesh, nu: float, E_mpa: float = 1.0,
                 supports: Supports = SENSOR_SUPPORTS, formulation: str = "nodal_pressure"):
        self.mesh = mesh
        self.nu = float(nu)
        self.E_mpa = float(E_mpa)
        dofs = build_dof_map(mesh, supports)
        K = assemble_stiffness_numpy(mesh.vertices, mesh.tets, 1.0, self.nu, formulation)
        Kq = sp.csr_matrix(dofs.T.T @ K @ dofs.T)
        sensing = mesh.sensing_nodes
        zc = dofs.z_col[sensing]
        #: sensing nodes whose z is free (a fixed side wall holds the rim's z at 0)
        self.driven = np.flatnonzero(zc >= 0)
        self._p = zc[self.driven]
        free = np.ones(Kq.shape[0], bool)
        free[self._p] = False
        self._f = np.flatnonzero(free)
        self._K_ff = Kq[self._f][:, self._f].tocsr()
        self._K_fp = Kq[self._f][:, self._p].tocsr()
        self._K_pf = Kq[self._p][:, self._f].tocsr()
        self._K_pp = Kq[self._p][:, self._p].tocsr()
        self._T = dofs.T.tocsr()
        self._factor = SparseCholesky(self._K_ff)
        self._n_q = Kq.shape[0]

    # ------------------------------------------------------------------ solving
    def solve_uz(self, uz_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Displacements (n, 3) mm and node forces (n_plane,) N for sensing-node u_z (n_plane,)
        mm (negative = pushed into the gel)."""
        uz = np.asarray(uz_mm, np.float64)
        if uz.shape != (self.mesh.n_plane,):
            raise ValueError(f"uz_mm must have shape ({self.mesh.n_plane},), got {uz.shape}")
        u_p = uz[self.driven]
        u_f = self._factor.solve(-(self._K_fp @ u_p))
        q = np.zeros(self._n_q)
        q[self._f] = u_f
        q[self._p] = u_p
        u = (self._T @ q).reshape(-1, 3)
        f = np.zeros(self.mesh.n_plane)
        f[self.driven] = -self.E_mpa * (self._K_pf @ u_f + self._K_pp @ u_p)
        return u, f

    def from_depth(self, depth_mm: np.ndarray, grid, iterations: int = 8,
                   tol_mm: float = 2e-3, relaxation: float = 0.7
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Deformed vertices (n, 3) float64 mm and sensing-node forces (n_plane,) N for a depth
        map on ``grid``.

        The depth map shows the surface where it is now: a sensing node that moved sideways
        by ``u_xy`` must have ``u_z = -depth(x0 + u_xy)``. Solved by relaxed fixed-point
        iteration on the read positions (``x <- x + relaxation (x0 + u_xy(x) - x)``) until they
        move less than ``tol_mm``, at most ``iterations`` solves (deep presses of thick gels
        move the surface sideways by half a millimetre; 3-5 solves reach 2 um).
        """
        xy0 = self.mesh.vertices[self.mesh.sensing_nodes, :2]
        xy = xy0
        for _ in range(max(1, int(iterations))):
            u, f = self.solve_uz(-sample_depth_grid(depth_mm, grid, xy))
            step = xy0 + u[: self.mesh.n_plane, :2] - xy
            if np.abs(step).max() < tol_mm:
                break
            xy = xy + relaxation * step
        return self.mesh.vertices + u, f

    def forces_from_vertices(self, vertices_mm: np.ndarray) -> np.ndarray:
        """Sensing-node forces (n_plane,) N of a deformed mesh (n, 3) mm from its u_z alone."""
        v = np.asarray(vertices_mm, np.float64)
        return self.solve_uz(v[: self.mesh.n_plane, 2] - self.mesh.vertices[: self.mesh.n_plane, 2])[1]
