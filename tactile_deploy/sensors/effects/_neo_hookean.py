"""Neo-Hookean internal forces of the pad mesh (large deformation), numpy and warp kernels.

Energy (total Lagrangian, linear tets, reference configuration = the rest mesh, mm, MPa)::

    E(u) = sum_t V_t mu/2 (J_t^(-2/3) tr(F_t' F_t) - 3)  +  sum_n kappa/2 (v_n(u) - V_n)^2 / V_n

    F_t = I + sum_a u_a (x) g_a     (g_a: shape-function gradients of tet t, 1/mm)
    v_n(u) = sum_(t ∋ n) V_t J_t / 4,   V_n = v_n(0)   (deformed and rest nodal volumes, mm^3)

The first term is the isochoric neo-Hookean energy of each tet; the second penalises the change of
the volume of each node's patch (compressible, bulk modulus kappa = lambda + 2 mu / 3). Its
Hessian at u = 0 is exactly the locking-free ``nodal_pressure`` stiffness of
:func:`tactile_deploy.fem.elasticity.assemble_stiffness_numpy` (``K_dev + kappa D' diag(1/V) D``),
so ``f_int(u) - K u`` contains only the large-deformation terms, of second order in the strains.

Internal force on node a of tet t (N)::

    f_a = V_t [ mu J^(-2/3) (F - tr(F'F)/3 F^-T) + p_t J F^-T ] g_a,
    p_t = mean over the tet's nodes of kappa (v_n - V_n) / V_n

:func:`internal_forces_numpy` is the vectorised reference; :func:`internal_forces_warp` runs the
same equations as two warp kernels (per tet: F, J and the deviatoric forces, atomically summed
into the nodes, and the deformed nodal volumes; then the volumetric forces), on the CPU.
"""

from __future__ import annotations

import numpy as np

from tactile_deploy.fem.elasticity import lame_parameters, shape_gradients


class NeoHookeanPad:
    """Mesh data for the neo-Hookean forces of ``vertices`` (n, 3) mm and ``tets`` (m, 4).

    E_mpa, nu: Young's modulus (MPa) and Poisson's ratio.
    """

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, E_mpa: float, nu: float):
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.tets = np.ascontiguousarray(tets, np.int64)
        self.grads, self.volumes = shape_gradients(self.vertices, self.tets)
        lam, mu = lame_parameters(E_mpa, nu)
        self.mu = mu
        self.kappa = lam + 2.0 * mu / 3.0
        n = len(self.vertices)
        self.nodal_volumes = np.bincount(self.tets.ravel(), np.repeat(self.volumes / 4.0, 4),
                                         minlength=n)
        self._warp = None

    @property
    def n_nodes(self) -> int:
        return len(self.vertices)

    # ------------------------------------------------------------------------- numpy
    def deformation(self, u: np.ndarray) -> np.ndarray:
        """Deformation gradients F (m, 3, 3) for nodal displacements u (n, 3) mm."""
        return np.eye(3) + np.einsum("mai,maj->mij", u[self.tets], self.grads)

    def energy(self, u: np.ndarray) -> float:
        """Stored energy E(u), N mm (= mJ)."""
        F = self.deformation(np.asarray(u, np.float64))
        J = np.linalg.det(F)
        i1 = np.einsum("mij,mij->m", F, F)
        w_dev = 0.5 * self.mu * (J ** (-2.0 / 3.0) * i1 - 3.0)
        v = np.bincount(self.tets.ravel(), np.repeat(self.volumes * J / 4.0, 4),
                        minlength=self.n_nodes)
        V = self.nodal_volumes
        return float(self.volumes @ w_dev + 0.5 * self.kappa * np.sum((v - V) ** 2 / V))

    def internal_forces_numpy(self, u: np.ndarray) -> np.ndarray:
        """dE/du: internal nodal forces (n, 3) N for displacements u (n, 3) mm (vectorised)."""
        u = np.asarray(u, np.float64)
        F = self.deformation(u)
        J = np.linalg.det(F)
        Finv_t = np.transpose(np.linalg.inv(F), (0, 2, 1))
        i1 = np.einsum("mij,mij->m", F, F)
        jm23 = J ** (-2.0 / 3.0)
        P = self.mu * jm23[:, None, None] * (F - (i1 / 3.0)[:, None, None] * Finv_t)
        v = np.bincount(self.tets.ravel(), np.repeat(self.volumes * J / 4.0, 4),
                        minlength=self.n_nodes)
        p_node = self.kappa * (v - self.nodal_volumes) / self.nodal_volumes
        p_tet = p_node[self.tets].mean(axis=1)
        P = P + (p_tet * J)[:, None, None] * Finv_t
        fe = self.volumes[:, None, None] * np.einsum("mij,maj->mai", P, self.grads)
        out = np.zeros((self.n_nodes, 3))
        for c in range(3):
            out[:, c] = np.bincount(self.tets.ravel(), fe[:, :, c].ravel(), minlength=self.n_nodes)
        return out

    # -------------------------------------------------------------------------- warp
    def internal_forces_warp(self, u: np.ndarray) -> np.ndarray:
        """Same as :meth:`internal_forces_numpy`, computed by warp kernels on the CPU."""
        if self._warp is None:
            self._warp = _WarpForces(self)
        return self._warp(np.asarray(u, np.float64))

    def internal_forces(self, u: np.ndarray, backend: str = "auto") -> np.ndarray:
        """Internal forces (n, 3) N; backend "numpy", "warp" or "auto" (warp when installed)."""
        if backend == "numpy":
            return self.internal_forces_numpy(u)
        if backend == "warp":
            return self.internal_forces_warp(u)
        if backend != "auto":
            raise ValueError(f"backend must be 'auto', 'numpy' or 'warp', got {backend!r}")
        try:
            return self.internal_forces_warp(u)
        except ImportError:
            return self.internal_forces_numpy(u)


_KERNELS = None


def _kernels():
    """Compile (once per process; warp caches the binaries on disk) and return the kernels."""
    global _KERNELS
    if _KERNELS is not None:
        return _KERNELS
    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    wp.config.quiet = True

    @wp.kernel(enable_backward=False)
    def deviatoric_forces(u: wp.array(dtype=wp.vec3d), tets: wp.array(dtype=wp.vec4i),
                          grads: wp.array(dtype=wp.mat33d, ndim=2),
                          volumes: wp.array(dtype=wp.float64), mu: wp.float64,
                          forces: wp.array(dtype=wp.vec3d), jac: wp.array(dtype=wp.float64),
                          nodal_volume: wp.array(dtype=wp.float64)):
        # grads[t, 0] holds g_0..g_2 as rows, grads[t, 1][0] holds g_3 (row 0).
        t = wp.tid()
        idx = tets[t]
        g0 = grads[t, 0][0]
        g1 = grads[t, 0][1]
        g2 = grads[t, 0][2]
        g3 = grads[t, 1][0]
        F = wp.identity(3, dtype=wp.float64)
        F = F + wp.outer(u[idx[0]], g0) + wp.outer(u[idx[1]], g1)
        F = F + wp.outer(u[idx[2]], g2) + wp.outer(u[idx[3]], g3)
        J = wp.determinant(F)
        Fit = wp.transpose(wp.inverse(F))
        i1 = wp.ddot(F, F)
        third = wp.float64(1.0) / wp.float64(3.0)
        P = mu * wp.pow(J, wp.float64(-2.0) * third) * (F - i1 * third * Fit)
        V = volumes[t]
        wp.atomic_add(forces, idx[0], V * (P @ g0))
        wp.atomic_add(forces, idx[1], V * (P @ g1))
        wp.atomic_add(forces, idx[2], V * (P @ g2))
        wp.atomic_add(forces, idx[3], V * (P @ g3))
        jac[t] = J
        q = V * J * wp.float64(0.25)
        for k in range(4):
            wp.atomic_add(nodal_volume, idx[k], q)

    @wp.kernel(enable_backward=False)
    def volumetric_forces(u: wp.array(dtype=wp.vec3d), tets: wp.array(dtype=wp.vec4i),
                          grads: wp.array(dtype=wp.mat33d, ndim=2),
                          volumes: wp.array(dtype=wp.float64), kappa: wp.float64,
                          jac: wp.array(dtype=wp.float64),
                          nodal_volume: wp.array(dtype=wp.float64),
                          rest_nodal_volume: wp.array(dtype=wp.float64),
                          forces: wp.array(dtype=wp.vec3d)):
        t = wp.tid()
        idx = tets[t]
        g0 = grads[t, 0][0]
        g1 = grads[t, 0][1]
        g2 = grads[t, 0][2]
        g3 = grads[t, 1][0]
        F = wp.identity(3, dtype=wp.float64)
        F = F + wp.outer(u[idx[0]], g0) + wp.outer(u[idx[1]], g1)
        F = F + wp.outer(u[idx[2]], g2) + wp.outer(u[idx[3]], g3)
        Fit = wp.transpose(wp.inverse(F))
        p = wp.float64(0.0)
        for k in range(4):
            n = idx[k]
            p = p + kappa * (nodal_volume[n] - rest_nodal_volume[n]) / rest_nodal_volume[n]
        p = p * wp.float64(0.25)
        s = volumes[t] * p * jac[t]
        wp.atomic_add(forces, idx[0], s * (Fit @ g0))
        wp.atomic_add(forces, idx[1], s * (Fit @ g1))
        wp.atomic_add(forces, idx[2], s * (Fit @ g2))
        wp.atomic_add(forces, idx[3], s * (Fit @ g3))

    _KERNELS = (wp, deviatoric_forces, volumetric_forces)
    return _KERNELS


class _WarpForces:
    """Device arrays of one mesh and the two-kernel force evaluation."""

    def __init__(self, pad: NeoHookeanPad):
        wp, self._dev, self._vol = _kernels()
        self.wp = wp
        self.pad = pad
        m = len(pad.tets)
        g = np.zeros((m, 2, 3, 3))
        g[:, 0] = pad.grads[:, :3]
        g[:, 1, 0] = pad.grads[:, 3]
        dev = "cpu"
        self.tets = wp.array(pad.tets.astype(np.int32), dtype=wp.vec4i, device=dev)
        self.grads = wp.array(g, dtype=wp.mat33d, device=dev)
        self.volumes = wp.array(pad.volumes, dtype=wp.float64, device=dev)
        self.rest_nv = wp.array(pad.nodal_volumes, dtype=wp.float64, device=dev)
        self.jac = wp.zeros(m, dtype=wp.float64, device=dev)
        self.nv = wp.zeros(pad.n_nodes, dtype=wp.float64, device=dev)
        self.forces = wp.zeros(pad.n_nodes, dtype=wp.vec3d, device=dev)
        self.device = dev

    def __call__(self, u: np.ndarray) -> np.ndarray:
        wp = self.wp
        pad = self.pad
        uw = wp.array(u, dtype=wp.vec3d, device=self.device)
        self.forces.zero_()
        self.nv.zero_()
        m = len(pad.tets)
        wp.launch(self._dev, dim=m, device=self.device,
                  inputs=[uw, self.tets, self.grads, self.volumes, wp.float64(pad.mu)],
                  outputs=[self.forces, self.jac, self.nv])
        wp.launch(self._vol, dim=m, device=self.device,
                  inputs=[uw, self.tets, self.grads, self.volumes, wp.float64(pad.kappa), self.jac,
                          self.nv, self.rest_nv], outputs=[self.forces])
        return self.forces.numpy().astype(np.float64).reshape(-1, 3)
