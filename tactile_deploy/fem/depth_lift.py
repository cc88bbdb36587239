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
is after the solve (a fixed point, found by relaxed iteration: :meth:`DepthLift.from_depth`). The
iteration needs only the sensing nodes' lateral motion, a linear map of their u_z: that map
(:meth:`DepthLift.lateral_operator`, 2 n_plane x n_driven, e.g. 51 MB for the GelSight Mini's
1,786 sensing nodes) is solved once per pad and material and cached on disk, so each iteration is
one dense product and the frame needs one sparse solve (the whole mesh at the converged read
positions) instead of one per iteration.

Frames: sensor frame, mm; depth positive into the gel (mm); forces N (+ = pressing the gel in).
Needs numpy and SciPy only (no torch, no warp).
"""

from __future__ import annotations

import hashlib

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import map_coordinates

from tactile_deploy.fem.constraints import SENSOR_SUPPORTS, Supports, build_dof_map
from tactile_deploy.fem.elasticity import assemble_stiffness_numpy
from tactile_deploy.fem.simulator import cache_dir, load_cached, save_cached
from tactile_deploy.fem.sparse_solver import SparseCholesky
from tactile_deploy.pad.mesh import PadMesh


#: Version of the cached lateral operator file; bump when its meaning changes.
LATERAL_CACHE_VERSION = 1
#: Right-hand sides per sparse solve while the lateral operator is built.
_OPERATOR_BLOCK = 256


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
        self._key = hashlib.sha256(
            f"v{LATERAL_CACHE_VERSION}|{mesh.content_hash}|{self.nu!r}|{supports.model_dump_json()}|"
            f"{formulation}".encode()).hexdigest()[:20]
        self._lateral: np.ndarray | None = None

    # ------------------------------------------------------------------ lateral operator
    @property
    def lateral_cache_path(self):
        """Where :meth:`lateral_operator` caches its matrix (the operator cache folder,
        ``$TACTILE_DEPLOY_CACHE_DIR`` or ``~/.cache/tactile-deploy``; keyed by mesh, nu, supports
        and formulation)."""
        return cache_dir() / f"depth_lift_lateral_{self._key}.npy"

    def lateral_operator(self, use_cache: bool = True) -> np.ndarray:
        """(2 n_plane, n_driven) float64: the sensing nodes' lateral displacements (mm; rows: x of
        every sensing node, then y) per mm of the driven sensing nodes' u_z. Built once (sparse
        solves of ``_OPERATOR_BLOCK`` right-hand sides at a time: ~20 s for the GelSight Mini's
        pad), then read from the cache."""
        if self._lateral is not None:
            return self._lateral
        n = self.mesh.n_plane
        shape = (2 * n, len(self._p))
        path = self.lateral_cache_path
        a = load_cached(path, shape, "lateral operator") if use_cache else None
        if a is not None:
            self._lateral = a
            return a
        rows = np.concatenate([3 * np.arange(n), 3 * np.arange(n) + 1])
        t_xy = self._T[rows]
        t_f = t_xy[:, self._f].tocsr()
        a = t_xy[:, self._p].toarray()
        for start in range(0, len(self._p), _OPERATOR_BLOCK):
            cols = slice(start, start + _OPERATOR_BLOCK)
            a[:, cols] -= t_f @ self._factor.solve(self._K_fp[:, cols].toarray())
        if use_cache:
            save_cached(path, a)
        self._lateral = a
        return a

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
                   tol_mm: float = 2e-3, relaxation: float = 0.7, lateral: str = "operator"
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Deformed vertices (n, 3) float64 mm and sensing-node forces (n_plane,) N for a depth
        map on ``grid``.

        The depth map shows the surface where it is now: a sensing node that moved sideways
        by ``u_xy`` must have ``u_z = -depth(x0 + u_xy)``. Solved by relaxed fixed-point
        iteration on the read positions (``x <- x + relaxation (x0 + u_xy(x) - x)``) until they
        move less than ``tol_mm``, at most ``iterations`` steps (deep presses of thick gels
        move the surface sideways by half a millimetre; 3-5 steps reach 2 um), then the whole
        mesh solved at the last read positions. ``lateral``: ``"operator"`` takes each step's
        u_xy from :meth:`lateral_operator` (one dense product), ``"solve"`` from a sparse solve
        of the whole mesh (the same numbers to round-off, one solve per step).
        """
        if lateral not in ("operator", "solve"):
            raise ValueError(f"lateral must be 'operator' or 'solve', got {lateral!r}")
        n = self.mesh.n_plane
        a = self.lateral_operator() if lateral == "operator" else None
        xy0 = self.mesh.vertices[self.mesh.sensing_nodes, :2]
        xy = xy0
        for _ in range(max(1, int(iterations))):
            read = xy
            uz = -sample_depth_grid(depth_mm, grid, read)
            if a is None:
                u, f = self.solve_uz(uz)
                u_xy = u[:n, :2]
            else:
                u_xy = (a @ uz[self.driven]).reshape(2, n).T
            step = xy0 + u_xy - read
            if np.abs(step).max() < tol_mm:
                break
            xy = read + relaxation * step
        if a is not None:
            u, f = self.solve_uz(uz)
        return self.mesh.vertices + u, f

    def forces_from_vertices(self, vertices_mm: np.ndarray) -> np.ndarray:
        """Sensing-node forces (n_plane,) N of a deformed mesh (n, 3) mm from its u_z alone."""
        v = np.asarray(vertices_mm, np.float64)
        return self.solve_uz(v[: self.mesh.n_plane, 2] - self.mesh.vertices[: self.mesh.n_plane, 2])[1]
