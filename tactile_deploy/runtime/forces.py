"""Contact forces from a predicted mesh: inverse FEM through the sensing surface's stiffness.

The pad is linear-elastic and the contact frictionless, so the normal forces ``f`` on the sensing
nodes and their normal displacements ``u`` are related by the surface compliance of the contact
simulator (:attr:`tactile_deploy.fem.simulator.ContactSimulator.compliance`, z dofs of every
sensing node, backplate bonded, computed at E = 1 MPa)::

    u = C f / E            =>            f = E K_s u,   K_s = C^-1   (k x k, N/mm at E = 1 MPa)

with ``u`` (mm) the z displacement of the k sensing nodes of the predicted mesh (deformed minus
rest z) and ``f`` (N) the z force on each node (negative: pushed into the gel). The normal
(compressive) force of node i is ``-f_i``; its pressure is ``-f_i / A_i`` with ``A_i`` the node's
lumped area (kPa after x 1e3). The total normal force is their sum. This is the paper's
inverse-FEM force estimate, restricted to normal forces: tangential (friction) forces are taken as
zero, and the lateral displacements of the predicted mesh are not used.

Exactness and noise: for a displacement field produced by the simulator the inverse returns its
contact forces to round-off (tested). For predicted meshes, errors in ``u`` are amplified at short
wavelengths (K_s is a stiffness), so the per-node pressure is noisier than the total force, which
is a smooth weighted sum of the displacements (weights ``K_s 1``). ``clip_tension=True`` sets
tensile (negative) pressures to zero, as a frictionless contact cannot pull.

Total force of a predicted mesh: a frictionless contact has traction only where the indenter
touches, but a predicted mesh carries small displacement errors over the whole surface, which the
stiffness turns into spurious nodal forces everywhere (and the total weights the bonded rim
heavily: a 1 um offset of the whole surface is about 0.5 N at E = 0.3 MPa). With
``contact_fraction`` (the runtime's :meth:`ForceEstimator.for_plugin` sets
:data:`CONTACT_FRACTION`) the total is the sum over the **contact patch**: the nodes whose
compressive force is at least that fraction of the largest one. On the simulator's own meshes this
changes the total by at most ~2 % (low-pressure nodes at the contact edge are left out); on
predicted meshes of virtual-sensor frames it removes the spurious part (docs/runtime.md gives
both figures). ``contact_fraction=None`` sums every node: the exact inverse of the FEM.

Cost: K_s is dense (1,076 x 1,076 for the GelSlim pad). It is computed on first use from the
sparse FEM stiffness (numpy assembly, sparse Cholesky; no warp; 15-30 s on two cores) and cached
in the operator cache folder (``$TACTILE_DEPLOY_CACHE_DIR`` or ``~/.cache/tactile-deploy``), or
taken from the contact simulator's cached operators when ``tactile-deploy simulate`` already
computed them for the same mesh and Poisson ratio; then a
frame costs one dot product for the total force and, when the per-node pressure is wanted, one
dense matrix-vector product (9 MB of float64: about 1-2 ms on one core, memory bound).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from tactile_deploy.fem.material import Material
from tactile_deploy.fem.simulator import ContactSimulator, cache_dir, load_cached, save_cached
from tactile_deploy.pad.asset import load_pad

#: Version of the cached stiffness file; bump when its meaning changes.
_CACHE_VERSION = 1
#: Contact patch of the runtime's total force: nodes with at least this fraction of the largest
#: nodal force. Chosen on 12 virtual-sensor presses (GelSlim 2, balls of 4 and 6 mm and a 3 mm
#: punch, seed 11) as the largest fraction that keeps the total of the FEM's own meshes within 1 %;
#: the benchmark measures it on other presses (seed 7).
CONTACT_FRACTION = 0.12


@dataclass(frozen=True)
class SurfaceStiffness:
    """Dense normal stiffness of the sensing surface at E = 1 MPa.

    nodes : (k,) int64, sensing-node indices (rows/columns in this order).
    matrix : (k, k) float64, N/mm: z forces from z displacements (frictionless, backplate fixed).
    key : identifies mesh, Poisson ratio and supports.
    """

    nodes: np.ndarray
    matrix: np.ndarray
    key: str

    @classmethod
    def from_compliance(cls, compliance: np.ndarray, nodes: np.ndarray,
                        key: str = "") -> SurfaceStiffness:
        """Invert a z-only surface compliance (k, k) mm/N at E = 1 (Cholesky)."""
        c = np.asarray(compliance, np.float64)
        if c.ndim != 2 or c.shape[0] != c.shape[1] or c.shape[0] != len(nodes):
            raise ValueError(f"compliance must be ({len(nodes)}, {len(nodes)}), got {c.shape}")
        factor = scipy.linalg.cho_factor(0.5 * (c + c.T))
        k = scipy.linalg.cho_solve(factor, np.eye(len(c)))
        return cls(np.asarray(nodes, np.int64), 0.5 * (k + k.T), key)

    @classmethod
    def from_simulator(cls, sim) -> SurfaceStiffness:
        """From a frictionless :class:`~tactile_deploy.fem.simulator.ContactSimulator`'s
        compliance (computes its Green's functions if they are not cached)."""
        if sim.block != 1:
            raise ValueError("the surface stiffness is defined for frictionless (z only) "
                             "contact; build the simulator with friction='frictionless'")
        return cls.from_compliance(sim.compliance, sim.contact_nodes, sim.operator_key)

    @staticmethod
    def _simulator(mesh, nu: float):
        return ContactSimulator(mesh, Material(nu=nu), assembly="numpy", use_cache=False)

    @classmethod
    def cache_path(cls, mesh, nu: float):
        """Where :meth:`for_pad` caches the stiffness of ``mesh`` at Poisson ratio ``nu``."""

        sim = cls._simulator(mesh, nu)
        key = hashlib.sha256(f"v{_CACHE_VERSION}|{sim.operator_key}".encode()).hexdigest()[:20]
        return cache_dir() / f"surface_stiffness_{key}.npy"

    @classmethod
    def for_pad(cls, mesh, nu: float, use_cache: bool = True, progress=None) -> SurfaceStiffness:
        """The stiffness of ``mesh`` for Poisson ratio ``nu`` (cached on disk after the first
        computation, which solves the sparse FEM system once per sensing node; ``progress(n)``
        is called as columns are done)."""

        sim = cls._simulator(mesh, nu)
        path = cls.cache_path(mesh, nu)
        key = path.stem.rsplit("_", 1)[1]
        k = len(sim.contact_nodes)
        m = load_cached(path, (k, k), "surface stiffness") if use_cache else None
        if m is not None:
            return cls(np.asarray(sim.contact_nodes, np.int64), m, key)
        if (cache_dir() / f"surface_{sim.operator_key}" / "C.npy").is_file():
            # the contact simulator already computed this compliance (same mesh, nu, supports)
            compliance = ContactSimulator(mesh, Material(nu=nu), assembly="numpy").compliance
        else:
            compliance = _z_compliance(sim, progress)
        stiff = cls.from_compliance(compliance, sim.contact_nodes, key)
        if use_cache:
            save_cached(path, stiff.matrix)     # an unwritable cache: a warning, no error
        return stiff


def _z_compliance(sim, progress=None, chunk: int = 256) -> np.ndarray:
    """The z-only compliance of the simulator's contact nodes (k, k) mm/N at E = 1, without its
    Green's functions of the whole volume (the same solves as ``sim.compliance``)."""
    cols = sim.contact_cols.ravel()
    n_q = sim.K_q.shape[0]
    out = np.empty((len(cols), len(cols)))
    for start in range(0, len(cols), chunk):
        sel = cols[start:start + chunk]
        rhs = np.zeros((n_q, len(sel)))
        rhs[sel, np.arange(len(sel))] = 1.0
        out[:, start:start + len(sel)] = sim.factor.solve(rhs)[cols]
        if progress is not None:
            progress(len(sel))
    return 0.5 * (out + out.T)


@dataclass(frozen=True)
class ContactForces:
    """Normal contact forces of one mesh (or a batch: a leading N axis on every array).

    total_normal_force_n : float, N, compression > 0 (over the contact patch when the estimator
        has a ``contact_fraction``, else over every sensing node).
    nodal_force_n : (k,) float32, normal force on each sensing node, N, compression > 0.
    pressure_kpa : (k,) float32, normal pressure on each sensing node, kPa, compression > 0.
    contact_mask : (k,) bool, the nodes the total sums (None: every node).
    """

    total_normal_force_n: float | np.ndarray
    nodal_force_n: np.ndarray
    pressure_kpa: np.ndarray
    contact_mask: np.ndarray | None = None


class ForceEstimator:
    """Normal contact forces from deformed pad meshes (module docstring).

    stiffness : :class:`SurfaceStiffness` of the pad at E = 1 MPa.
    E_mpa : calibrated Young's modulus, MPa. rest_vertices_mm : (n, 3) pad rest positions.
    areas_mm2 : (k,) lumped areas of the stiffness's nodes.
    contact_fraction : the total sums the nodes whose compressive force is at least this fraction
        of the largest (module docstring); None: every node (the exact inverse of the FEM).
    """

    def __init__(self, stiffness: SurfaceStiffness, E_mpa: float, rest_vertices_mm: np.ndarray,
                 areas_mm2: np.ndarray, contact_fraction: float | None = None):
        if not E_mpa > 0:
            raise ValueError(f"E_mpa must be > 0, got {E_mpa}")
        if contact_fraction is not None and not 0.0 <= contact_fraction < 1.0:
            raise ValueError(f"contact_fraction must be in [0, 1) or None, got {contact_fraction}")
        self.contact_fraction = contact_fraction
        self.stiffness = stiffness
        self.E_mpa = float(E_mpa)
        self.nodes = stiffness.nodes
        self._rest_z = np.asarray(rest_vertices_mm, np.float64)[self.nodes, 2]
        self._n_nodes = len(rest_vertices_mm)
        self._k_e = stiffness.matrix * self.E_mpa            # N/mm at this E
        self._row_sums = self._k_e.sum(axis=0)               # total force per unit u_z, N/mm
        self._inv_area_kpa = 1e3 / np.asarray(areas_mm2, np.float64)

    @classmethod
    def for_pad(cls, E_mpa: float, nu: float, pad: str = "gelslim", version: int | None = None,
                progress=None, contact_fraction: float | None = None) -> ForceEstimator:
        mesh = load_pad(pad, version)
        stiff = SurfaceStiffness.for_pad(mesh, nu, progress=progress)
        return cls(stiff, E_mpa, mesh.vertices, mesh.sensing_nodal_areas_mm2()[stiff.nodes],
                   contact_fraction=contact_fraction)

    @classmethod
    def for_plugin(cls, plugin, progress=None,
                   contact_fraction: float | None = CONTACT_FRACTION) -> ForceEstimator:
        """With the plugin's calibrated E and nu and its family's pad; the total over the contact
        patch of predicted meshes (``contact_fraction``, module docstring)."""
        m = plugin.manifest
        return cls.for_pad(m.material.E_mpa, m.material.nu, m.family.pad, m.family.pad_version,
                           progress, contact_fraction)

    def with_contact_fraction(self, contact_fraction: float | None) -> ForceEstimator:
        """The same estimator (stiffness, E, pad) with another ``contact_fraction``."""
        import copy

        if contact_fraction is not None and not 0.0 <= contact_fraction < 1.0:
            raise ValueError(f"contact_fraction must be in [0, 1) or None, got {contact_fraction}")
        other = copy.copy(self)
        other.contact_fraction = contact_fraction
        return other

    def estimate(self, vertices_mm: np.ndarray, clip_tension: bool = False,
                 pressure: bool = True) -> ContactForces:
        """Forces of a mesh (n, 3) or a batch (N, n, 3) of deformed vertices, mm, sensor frame.

        ``pressure=False`` computes only the total force (the per-node arrays are then empty):
        without ``contact_fraction`` a dot product with the precomputed row sums of the stiffness,
        ~1,000 x cheaper than the per-node forces; with it the per-node forces are needed for the
        contact patch. ``clip_tension`` needs the per-node forces (it implies ``pressure=True``).
        """
        v = np.asarray(vertices_mm)
        if v.shape[-2:] != (self._n_nodes, 3) or v.ndim not in (2, 3):
            raise ValueError(f"vertices_mm must be ({self._n_nodes}, 3) or (N, {self._n_nodes}, "
                             f"3), got {v.shape}")
        uz = v[..., self.nodes, 2].astype(np.float64) - self._rest_z     # (..., k) mm
        empty = np.zeros(uz.shape[:-1] + (0,), np.float32)
        if not (pressure or clip_tension) and self.contact_fraction is None:
            total = -(uz @ self._row_sums)
            return ContactForces(total if uz.ndim > 1 else float(total), empty, empty)
        fn = -(uz @ self._k_e)                                          # K symmetric; (..., k) N
        if clip_tension:
            fn = np.maximum(fn, 0.0)
        patch = None
        if self.contact_fraction is not None:  # the contact patch (module docstring)
            patch = (fn > 0) & (fn >= self.contact_fraction * fn.max(axis=-1, keepdims=True))
            total = np.where(patch, fn, 0.0).sum(axis=-1)
        else:
            total = fn.sum(axis=-1)
        total = total if fn.ndim > 1 else float(total)
        if not (pressure or clip_tension):
            return ContactForces(total, empty, empty, patch)
        return ContactForces(total, fn.astype(np.float32), (fn * self._inv_area_kpa).astype(np.float32), patch)
