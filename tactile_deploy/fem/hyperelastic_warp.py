"""Warp kernels of the neo-Hookean internal forces of :class:`tactile_deploy.fem.hyperelastic.NeoHookeanGel`.

The same equations as :meth:`NeoHookeanGel.forces <tactile_deploy.fem.hyperelastic.NeoHookeanGel.forces>`
(first Piola stress of the isochoric part per tet, the volumetric part on the nodal patch
volumes), as two kernels on the CPU: per tet F, J and the deviatoric forces, atomically summed
into the nodes, and the deformed nodal volumes; then the volumetric forces. Needs warp-lang (the
``sim`` extra); :class:`NeoHookeanForces` falls back to numpy without it. Units: mm, MPa, N.
"""

from __future__ import annotations

import numpy as np

from tactile_deploy.fem.hyperelastic import COLLAPSE_BARRIER_J, NeoHookeanGel


class NeoHookeanForces:
    """Internal forces of ``gel`` by numpy or the warp kernels (built on first use).

    ``forces(u, backend)``: (n, 3) N at displacements u (n, 3) mm; backend "numpy"
    (:meth:`NeoHookeanGel.forces`, which raises
    :class:`~tactile_deploy.fem.hyperelastic.InvertedElementError` on an inverted tet), "warp"
    (these kernels: an inverted tet gives non-finite forces) or "auto" (warp when installed).
    """

    def __init__(self, gel: NeoHookeanGel):
        self.gel = gel
        self._warp = None

    def __call__(self, u: np.ndarray, backend: str = "auto") -> np.ndarray:
        if backend not in ("auto", "numpy", "warp"):
            raise ValueError(f"backend must be 'auto', 'numpy' or 'warp', got {backend!r}")
        if backend == "numpy":
            return self.gel.forces(u)
        if self._warp is None:
            try:
                self._warp = WarpForces(self.gel)
            except ImportError:
                if backend == "warp":
                    raise
                return self.gel.forces(u)
        return self._warp(np.asarray(u, np.float64))


_KERNELS = None


def _kernels():
    """Compile (once per process; warp caches the binaries on disk) and return the kernels."""
    global _KERNELS
    if _KERNELS is not None:
        return _KERNELS
    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    wp.config.quiet = True

    @wp.func
    def deformation_gradient(u: wp.array(dtype=wp.vec3d), idx: wp.vec4i, g0: wp.vec3d,
                             g1: wp.vec3d, g2: wp.vec3d, g3: wp.vec3d):
        """F = I + sum_k u_k (x) g_k of one linear tet (g_k: shape-function gradients, 1/mm)."""
        F = wp.identity(3, dtype=wp.float64)
        F = F + wp.outer(u[idx[0]], g0) + wp.outer(u[idx[1]], g1)
        return F + wp.outer(u[idx[2]], g2) + wp.outer(u[idx[3]], g3)

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
        F = deformation_gradient(u, idx, g0, g1, g2, g3)
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
                          barrier_j: wp.float64,
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
        F = deformation_gradient(u, idx, g0, g1, g2, g3)
        Fit = wp.transpose(wp.inverse(F))
        p = wp.float64(0.0)
        for k in range(4):
            n = idx[k]
            p = p + kappa * (nodal_volume[n] - rest_nodal_volume[n]) / rest_nodal_volume[n]
        p = p * wp.float64(0.25)
        # the collapse barrier's pressure (0 while J >= barrier_j)
        sj = wp.min(jac[t] / barrier_j, wp.float64(1.0))
        p = p + kappa * barrier_j * (wp.float64(2.0) - sj - wp.float64(1.0) / sj)
        s = volumes[t] * p * jac[t]
        wp.atomic_add(forces, idx[0], s * (Fit @ g0))
        wp.atomic_add(forces, idx[1], s * (Fit @ g1))
        wp.atomic_add(forces, idx[2], s * (Fit @ g2))
        wp.atomic_add(forces, idx[3], s * (Fit @ g3))

    _KERNELS = (wp, deviatoric_forces, volumetric_forces)
    return _KERNELS


class WarpForces:
    """Device arrays of one :class:`NeoHookeanGel` and the two-kernel force evaluation:
    ``WarpForces(gel)(u)`` is ``gel.forces(u)`` (n, 3) N for displacements u (n, 3) mm, without
    the inverted-element check (an inverted tet gives non-finite forces)."""

    def __init__(self, pad: NeoHookeanGel):
        if pad.deviatoric != "element":
            raise ValueError("the warp kernels integrate the deviatoric energy per tet; got a gel "
                             f"with deviatoric={pad.deviatoric!r}")
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
                  inputs=[uw, self.tets, self.grads, self.volumes, wp.float64(pad.kappa),
                          wp.float64(COLLAPSE_BARRIER_J), self.jac,
                          self.nv, self.rest_nv], outputs=[self.forces])
        return self.forces.numpy().astype(np.float64).reshape(-1, 3)
