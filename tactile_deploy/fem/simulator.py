"""Quasi-static contact of a rigid indenter with the pad: the simulator's top-level API.

Data flow of :meth:`ContactSimulator.solve`::

    indenter + pose --(intrusion at sensing nodes)--> delta (n_plane,) mm
        --(contact on the surface compliance, exact active set)--> nodal contact forces, N
        --(one sparse solve of the volume)--> displacements (n, 3) mm
        --> ContactResult (deformed vertices, contact mask, pressure kPa, total force N)

Two interchangeable methods compute the contact forces:

* ``"surface"`` (fast path): the compliance of the sensing surface, ``C = E_c' K_q^-1 E_c``,
  is computed once per mesh, Poisson ratio and supports (Green's functions, cached on disk),
  and contact is solved on the surface only;
* ``"full"`` (reference): the active-set iteration re-solves the whole sparse system with the
  contact nodes' displacements prescribed; reaction forces give the contact forces.

They agree to solver round-off (tested). Under displacement control the displacement field does
not depend on E: everything is computed at E = 1 MPa and forces are scaled by ``E_mpa``.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from tactile_deploy.atomic import atomic_path
from tactile_deploy.fem.constraints import (
    SENSOR_SUPPORTS,
    DofMap,
    Supports,
    build_dof_map,
)
from tactile_deploy.fem.contact import solve_contact
from tactile_deploy.fem.elasticity import assemble_stiffness
from tactile_deploy.fem.material import Material
from tactile_deploy.fem.sparse_solver import SparseCholesky
from tactile_deploy.pad.mesh import PadMesh

log = logging.getLogger(__name__)


def cache_dir() -> Path:
    """Folder for cached operators: ``$TACTILE_DEPLOY_CACHE_DIR`` or ``~/.cache/tactile-deploy``
    (created when possible; one that cannot be is still returned: nothing is found in it, and
    :func:`save_cached` warns instead of writing)."""
    root = os.environ.get("TACTILE_DEPLOY_CACHE_DIR")
    path = Path(root) if root else Path.home() / ".cache" / "tactile-deploy"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        pass
    return path


_cache_warned = False


def load_cached(path: Path, shape: tuple[int, ...], what: str) -> np.ndarray | None:
    """The cached array at ``path`` when it is there, has ``shape`` and is finite; else None
    (after a warning naming ``what`` when a file is there but wrong or unreadable): the caller
    computes it again."""
    if not path.is_file():
        return None
    try:
        arr = np.load(path)
    except (OSError, ValueError) as e:
        log.warning("cached %s %s is unreadable (%s); recomputing", what, path, e)
        return None
    if arr.shape == tuple(shape) and np.all(np.isfinite(arr)):
        return arr
    log.warning("cached %s %s has the wrong shape or non-finite values; recomputing", what, path)
    return None


def save_cached(path: Path, arr: np.ndarray) -> bool:
    """Write ``arr`` to the cache file ``path`` (.npy, atomic). When the cache cannot be
    written, warn once per process and return False: the caller keeps its result in memory."""
    global _cache_warned

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.save(f, arr)
        return True
    except OSError as e:
        if not _cache_warned:
            _cache_warned = True
            log.warning("cannot write the cache in %s: %s; set TACTILE_DEPLOY_CACHE_DIR to a "
                        "writable folder (this run goes on with the result in memory, the next "
                        "one computes it again)", path.parent, e.strerror or e)
        return False


@dataclass(frozen=True)
class ContactResult:
    """Outcome of one commanded contact.

    Attributes
    ----------
    rest_vertices_mm : (n, 3) float64, sensor frame
    displacements_mm : (n, 3) float64, sensor frame
    contact_mask : (n_plane,) bool — sensing nodes touching the indenter
    contact_forces_n : (n_plane, 3) float64 — force of the indenter on each sensing node, N
    pressure_kpa : (n_plane,) float64 — normal contact pressure (compression > 0), kPa
    force_n : float — total normal force pressing the pad (compression > 0), N
    intrusion_mm : (n_plane,) float64 — indenter intrusion at each sensing node (-inf = none)
    stick_mask : (n_plane,) bool — nodes in contact that stick (Coulomb friction,
        :class:`tactile_deploy.fem.coulomb.CoulombSimulator`), or None for the other laws
    """

    rest_vertices_mm: np.ndarray
    displacements_mm: np.ndarray
    contact_mask: np.ndarray
    contact_forces_n: np.ndarray
    pressure_kpa: np.ndarray
    force_n: float
    intrusion_mm: np.ndarray
    stick_mask: np.ndarray | None = None

    @property
    def vertices_mm(self) -> np.ndarray:
        """Deformed vertex positions, (n, 3) float64, mm, sensor frame."""
        return self.rest_vertices_mm + self.displacements_mm


def surface_contact_forces(C: np.ndarray, delta: np.ndarray, block: int) -> np.ndarray:
    """Exact contact on a surface compliance: forces (k, b) N at E = 1 for intrusions ``delta`` (k,) mm.

    Solves on the candidate nodes (intrusion above minus the largest intrusion: the surface
    cannot sink further than that), then checks every other node for penetration and repeats
    with the offenders added until none penetrates.
    """
    b = block
    forces = np.zeros((len(delta), b))
    if not np.any(delta > 0):
        return forces
    reach = float(np.max(delta))
    cand = np.flatnonzero(delta > -reach)
    for _ in range(20):
        dofs = (cand[:, None] * b + np.arange(b)).ravel()
        sol = solve_contact(C[np.ix_(dofs, dofs)], delta[cand], b)
        forces[:] = 0.0
        forces[cand] = sol.forces
        active = cand[sol.active]
        adofs = (active[:, None] * b + np.arange(b)).ravel()
        u_normal = C[b - 1 :: b][:, adofs] @ forces[active].ravel()
        penetrating = np.flatnonzero(-delta - u_normal < -1e-9 * reach)
        missing = np.setdiff1d(penetrating, cand)
        if len(missing) == 0:
            return forces
        cand = np.union1d(cand, missing)
    raise RuntimeError("contact candidate set did not settle")


class ContactSimulator:
    """Linear-elastic pad + rigid indenter, frictionless or sticking contact (Coulomb friction:
    :class:`tactile_deploy.fem.coulomb.CoulombSimulator`, a subclass).

    Parameters
    ----------
    mesh : PadMesh
    material : Material — E (MPa) scales forces only; nu sets the operators; friction the law.
    supports : Supports — how the pad is held (the sensor: bonded to the backplate).
    method : "surface" (fast, Green's functions) or "full" (sparse re-solve per active set).
    assembly : "auto" | "numpy" | "warp" — stiffness assembly backend.
    formulation : "nodal_pressure" (locking-free, default) or "standard" linear tets.
    contact_nodes : sensing-node indices that may touch the indenter (default: all of them).
        Validation models restrict it to the region a contact can reach to save time.
    use_cache : keep the surface operators in :func:`cache_dir` between runs.
    """

    def __init__(
        self,
        mesh: PadMesh,
        material: Material = Material(),
        supports: Supports = SENSOR_SUPPORTS,
        method: str = "surface",
        assembly: str = "auto",
        formulation: str = "nodal_pressure",
        contact_nodes: np.ndarray | None = None,
        use_cache: bool = True,
    ):
        if method not in ("surface", "full"):
            raise ValueError(f"method must be 'surface' or 'full', got {method!r}")
        if material.friction == "coulomb":
            raise ValueError(
                "friction='coulomb' is solved by tactile_deploy.fem.coulomb.CoulombSimulator; "
                "ContactSimulator takes 'frictionless' or 'stick'"
            )
        self.mesh = mesh
        self.material = material
        self.supports = supports
        self.method = method
        self.assembly = assembly
        self.formulation = formulation
        self.block = 1 if material.friction == "frictionless" else 3
        self.dofs: DofMap = build_dof_map(mesh, supports)
        sensing = mesh.sensing_nodes
        self.contact_nodes = sensing if contact_nodes is None else np.asarray(contact_nodes)
        z = self.dofs.z_col[self.contact_nodes]
        if np.any(z < 0):
            raise ValueError("every contact node needs a free z direction")
        if self.block == 1:
            self.contact_cols = z[:, None]
        else:
            xy = self.dofs.xy_cols[self.contact_nodes]
            if np.any(xy < 0):
                raise ValueError("sticking contact needs free x and y at every contact node")
            self.contact_cols = np.concatenate([xy, z[:, None]], axis=1)  # (k, 3): x, y, z
        self._areas = mesh.sensing_nodal_areas_mm2()
        self._use_cache = use_cache
        self._K_q: sp.csr_matrix | None = None
        self._factor: SparseCholesky | None = None
        self._C: np.ndarray | None = None
        self._G: np.ndarray | None = None

    # ----------------------------------------------------------------- operators
    @property
    def K_q(self) -> sp.csr_matrix:
        """Reduced stiffness at E = 1 MPa, (n_q, n_q) N/mm (assembled on first use)."""
        if self._K_q is None:
            K = assemble_stiffness(
                self.mesh.vertices,
                self.mesh.tets,
                1.0,
                self.material.nu,
                backend=self.assembly,
                formulation=self.formulation,
            )
            T = self.dofs.T
            self._K_q = sp.csr_matrix(T.T @ K @ T)
        return self._K_q

    @property
    def factor(self) -> SparseCholesky:
        if self._factor is None:
            self._factor = SparseCholesky(self.K_q)
        return self._factor

    @property
    def operator_key(self) -> str:
        """Identifies the surface operators: mesh, nu, supports, contact dofs, formulation."""
        nodes = hashlib.sha256(np.ascontiguousarray(self.contact_nodes, "<i8").tobytes()).hexdigest()
        text = (
            f"{self.mesh.content_hash}|nu={self.material.nu:.6f}|{self.supports.key}"
            f"|b{self.block}|{self.formulation}|{nodes}"
        )
        return hashlib.sha256(text.encode()).hexdigest()[:20]

    @property
    def compliance(self) -> np.ndarray:
        """Compliance of the contact dofs at E = 1 MPa, (k*b, k*b) float64, mm/N.

        Rows/columns node-major over ``contact_nodes`` with b = 1 (z) or 3 (x, y, z).
        """
        if self._C is None:
            self._load_or_compute_operators()
        return self._C

    @property
    def greens(self) -> np.ndarray:
        """Displacement of every node per unit contact force, (k*b, n, 3) float32, mm/N at E = 1."""
        if self._G is None:
            self._load_or_compute_operators()
        return self._G

    def prepare(self, progress=None) -> bool:
        """Load or compute the surface operators now; True when they had to be computed.

        ``progress(n_columns_done)`` is called while computing (``n_operator_columns`` in all).
        """
        if self._C is not None and self._G is not None:
            return False
        return self._load_or_compute_operators(progress)

    @property
    def n_operator_columns(self) -> int:
        return int(self.contact_cols.size)

    def _load_or_compute_operators(self, progress=None) -> bool:
        folder = cache_dir() / f"surface_{self.operator_key}"
        n_c = self.contact_cols.size
        if self._use_cache and (folder / "C.npy").exists() and (folder / "G.npy").exists():
            try:
                C = np.load(folder / "C.npy")
                G = np.load(folder / "G.npy", mmap_mode="r")
                if C.shape == (n_c, n_c) and G.shape == (n_c, self.mesh.n_nodes, 3):
                    self._C, self._G = C, np.asarray(G)
                    return False
            except (OSError, ValueError):
                pass
        self._C, self._G = self.compute_operators(progress=progress)
        if self._use_cache:
            for name, arr in (("G.npy", self._G), ("C.npy", self._C)):
                if not save_cached(folder / name, arr):
                    break
        return True

    def compute_operators(self, chunk: int = 256, progress=None) -> tuple[np.ndarray, np.ndarray]:
        """Green's functions of the contact dofs: one sparse solve per dof, in chunks.

        Returns ``(C (k*b, k*b) float64 mm/N, G (k*b, n, 3) float32 mm/N)`` at E = 1 MPa.
        """
        cols = self.contact_cols.ravel()
        n_q = self.K_q.shape[0]
        C = np.empty((len(cols), len(cols)))
        G = np.empty((len(cols), self.mesh.n_nodes, 3), dtype=np.float32)
        T = self.dofs.T
        for start in range(0, len(cols), chunk):
            sel = cols[start : start + chunk]
            rhs = np.zeros((n_q, len(sel)))
            rhs[sel, np.arange(len(sel))] = 1.0
            X = self.factor.solve(rhs)
            C[:, start : start + len(sel)] = X[cols]
            G[start : start + len(sel)] = (T @ X).T.reshape(len(sel), -1, 3)
            if progress is not None:
                progress(len(sel))
        return 0.5 * (C + C.T), G

    # ----------------------------------------------------------------- solving
    def intrusion(self, indenter, pose) -> np.ndarray:
        """Indenter intrusion at the sensing nodes, (n_plane,) mm (-inf where not covered)."""
        xy = self.mesh.vertices[self.mesh.sensing_nodes, :2]
        delta = np.asarray(indenter.intrusion_mm(xy, pose), dtype=np.float64)
        # A domed pad: the rest surface lies below z = 0, so the intrusion shrinks by its sag.
        return delta + self.mesh.vertices[self.mesh.sensing_nodes, 2]

    def solve(self, indenter, pose) -> ContactResult:
        """Contact of ``indenter`` at ``pose`` (see :class:`ContactPose`)."""
        return self.solve_intrusion(self.intrusion(indenter, pose))

    def solve_intrusion(self, delta: np.ndarray) -> ContactResult:
        """Contact for an intrusion field ``delta`` (n_plane,) mm at the sensing nodes."""
        delta = np.asarray(delta, dtype=np.float64)
        if delta.shape != (self.mesh.n_plane,):
            raise ValueError(f"delta must have shape ({self.mesh.n_plane},), got {delta.shape}")
        d = delta[self.contact_nodes]
        if self.method == "surface":
            forces = self.surface_forces(d)
            u = self.displacements_from_forces(forces)
        else:
            forces, u = self._full_solve(d)
        return self._result(delta, forces, u)

    def displacements_from_forces(self, forces_e1: np.ndarray) -> np.ndarray:
        """Nodal displacements (n, 3) mm from contact forces at E = 1, (k, b) N."""
        flat = forces_e1.ravel()
        nz = np.flatnonzero(flat)
        if len(nz) == 0:
            return np.zeros((self.mesh.n_nodes, 3))
        G = self.greens
        return np.tensordot(flat[nz], G[nz], axes=1).astype(np.float64)

    def surface_forces(self, delta: np.ndarray) -> np.ndarray:
        """Contact forces at E = 1, (k, b) N, for intrusions ``delta`` (k,) at ``contact_nodes``."""
        if not np.any(delta > 0):
            return np.zeros((len(delta), self.block))
        return surface_contact_forces(self.compliance, delta, self.block)

    def _full_solve(self, delta: np.ndarray):
        """Reference: active-set iteration on the full sparse system (refactor per step)."""
        b = self.block
        K = self.K_q
        zc = self.contact_cols[:, -1]
        c = K.diagonal()[zc]  # N/mm, scales gaps against forces
        active = delta > 0
        n_q = K.shape[0]
        for _ in range(100):
            presc_cols = self.contact_cols[active].ravel()
            presc_vals = np.zeros((int(active.sum()), b))
            presc_vals[:, -1] = -delta[active]
            presc_vals = presc_vals.ravel()
            free = np.setdiff1d(np.arange(n_q), presc_cols)
            uq = np.zeros(n_q)
            uq[presc_cols] = presc_vals
            if len(presc_cols):
                rhs = -(K[free][:, presc_cols] @ presc_vals)
                uq[free] = SparseCholesky(K[free][:, free]).solve(rhs)
            reaction = K @ uq  # forces needed at prescribed dofs (zero elsewhere)
            forces = np.zeros((len(delta), b))
            forces[active] = reaction[self.contact_cols[active]].reshape(-1, b)
            fn = -forces[:, -1]
            gap = np.where(active, 0.0, -delta - uq[zc])
            new_active = (fn - c * gap) > 0
            if np.array_equal(new_active, active):
                return forces, (self.dofs.T @ uq).reshape(-1, 3)
            active = new_active
        raise RuntimeError("full-solve active set did not settle in 100 steps")

    def _result(self, delta, forces_e1, u) -> ContactResult:
        n_plane = self.mesh.n_plane
        f3 = np.zeros((n_plane, 3))
        if self.block == 1:
            f3[self.contact_nodes, 2] = forces_e1[:, 0]
        else:
            f3[self.contact_nodes] = forces_e1
        f3 *= self.material.E_mpa
        fn = -f3[:, 2]
        return ContactResult(
            rest_vertices_mm=self.mesh.vertices,
            displacements_mm=u,
            contact_mask=fn > 0,
            contact_forces_n=f3,
            pressure_kpa=1e3 * fn / self._areas,
            force_n=float(fn.sum()),
            intrusion_mm=delta,
        )
