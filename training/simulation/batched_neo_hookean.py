"""Large-deformation (neo-Hookean) frictionless contact for batches of contacts, in torch.

The batched twin of :func:`tactile_deploy.sensors.effects.hyperelastic.solve_neo_hookean` (the
reference, numpy/scipy): the same fixed point on the nominal pad mesh, for B contacts at once on
the CPU or a GPU. Data flow of :meth:`BatchedNeoHookean.solve_intrusion`::

    delta (B, n_plane) mm --(linear contact: BatchedContactSimulator)--> u0 (B, n, 3) mm
      repeat until every sample's update is below ``tol_mm`` (Anderson-accelerated, per sample):
        f_int(u)     neo-Hookean internal forces (B, n, 3) N at E = 1     (:class:`TorchNeoHookean`)
        u_b = T s (q - K_q^-1 T' f_int(u)),  q = T' u                       (one GEMM with K_q^-1)
        forces = exact frictionless contact on C for intrusions delta + u_b,z   (BatchedContact)
        u <- u_b + G forces
      --(batched rasteriser)--> depth (B, 128, 128) mm

i.e. ``K u_(k+1) = f_contact - s r(u_k)`` with ``r(u) = f_int(u) - K u`` the large-deformation
terms (``K_q^-1 K_q = I`` turns ``-K_q^-1 s r`` into the expression above). Every sample keeps its
own Anderson history (depth ``anderson``, mixing 0.5; a sample whose iterations break down --
an element inverts, a non-finite update -- restarts from the linear solution with mixing 0.2, as
the reference does) and leaves the batch when it has converged. Samples that break down twice, or
do not converge in ``max_iterations``, are flagged unsolved (``solved`` False, NaN results).

What is and is not the reference's: the fixed point (the solution) is the same; the path differs
only in the Anderson least-squares step (normal equations regularised at 1e-12 of their trace
here; truncated at rcond 1e-14 there), so two solves agree to the convergence tolerance, and to
round-off when both are run to a tolerance near it (``tests/test_batched_neo_hookean.py``).

Operators at E = 1 MPa: ``C``, ``G`` of the linear :class:`BatchedContactSimulator` and the dense
inverse of the reduced stiffness ``K_q^-1`` (``n_q^2`` float64: 2.1 GB for the shipped pad, on the
device; the memory per sample is reported by :meth:`BatchedNeoHookean.bytes_per_sample`).

Units: mm, N, MPa; sensor frame. Residual of the model (as the reference's): the contact is
linearised (gap along z at the nodes' rest positions, frictionless forces along z) on the nominal
~1 mm tet mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tactile_deploy.fem.constraints import build_dof_map
from tactile_deploy.fem.elasticity import assemble_stiffness_numpy
from tactile_deploy.fem.hyperelastic import COLLAPSE_BARRIER_J, NeoHookeanGel

#: Convergence tolerance (largest nodal change of one fixed-point map, mm): the reference's.
TOLERANCE_MM = 1e-6
#: Most fixed-point maps per sample before it is flagged unsolved: the reference's.
MAX_ITERATIONS = 200
#: Anderson mixing of the first attempt and of the restart after a breakdown: the reference's.
MIXING = (0.5, 0.2)


class TorchNeoHookean:
    """Internal forces of :class:`~tactile_deploy.fem.hyperelastic.NeoHookeanGel` (deviatoric
    energy per tet, volumetric energy on the nodal patches, the collapse barrier per tet) for
    batches of displacements.

    ``forces(u)``: u (B, n, 3) mm -> (forces (B, n, 3) N at the gel's E, ok (B,) bool: no tet
    inverted and every force finite). Samples that are not ok carry meaningless forces."""

    def __init__(self, gel: NeoHookeanGel, device="cpu", dtype=torch.float64):
        if gel.deviatoric != "element":
            raise ValueError("the batched neo-Hookean forces integrate the deviatoric energy per tet "
                             f"(deviatoric='element'), got {gel.deviatoric!r}")
        self.device, self.dtype = torch.device(device), dtype
        self.n_nodes = gel.n_nodes
        self.tets = torch.as_tensor(gel.tets, device=self.device)
        self.tets_flat = self.tets.reshape(-1)
        self.grads = torch.as_tensor(gel.grads, dtype=dtype, device=self.device)        # (m, 4, 3)
        self.volumes = torch.as_tensor(gel.volumes, dtype=dtype, device=self.device)    # (m,)
        self.nodal_volumes = torch.as_tensor(gel.nodal_volumes, dtype=dtype, device=self.device)
        self.mu, self.kappa = float(gel.mu), float(gel.kappa)

    def forces(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B = u.shape[0]
        F = torch.einsum("bmai,maj->bmij", u[:, self.tets], self.grads)
        F = F + torch.eye(3, dtype=self.dtype, device=self.device)
        cof = _cofactors(F)
        J = (F * cof)[..., 0, :].sum(dim=-1)                                          # (B, m)
        ok = torch.all(J > 0, dim=1)
        # inverted samples are flagged, and their tets evaluated at F = I so nothing overflows
        eye = torch.eye(3, dtype=self.dtype, device=self.device)
        Fs = torch.where(ok[:, None, None, None], F, eye)
        Js = torch.where(ok[:, None], J, 1.0)
        H = torch.where(ok[:, None, None, None], cof, eye) / Js[..., None, None]      # F^-T = cof(F) / J
        Jn = torch.zeros((B, self.n_nodes), dtype=self.dtype, device=self.device)
        Jn.index_add_(1, self.tets_flat, (self.volumes * Js / 4.0).repeat_interleave(4, dim=1))
        Jn = Jn / self.nodal_volumes
        i1 = (Fs * Fs).sum(dim=(-2, -1))
        P = self.mu * Js.pow(-2.0 / 3.0)[..., None, None] * (Fs - (i1 / 3.0)[..., None, None] * H)
        pbar = (self.kappa * (Jn - 1.0))[:, self.tets].mean(dim=2)                       # (B, m)
        # the collapse barrier's pressure, tets below COLLAPSE_BARRIER_J (0 above it)
        sj = torch.clamp(Js / COLLAPSE_BARRIER_J, max=1.0)
        pbar = pbar + self.kappa * COLLAPSE_BARRIER_J * (2.0 - sj - 1.0 / sj)
        P = P + (pbar * Js)[..., None, None] * H
        # f_ai = V sum_j P_ij g_aj
        fe = self.volumes[None, :, None, None] * torch.einsum("bmij,maj->bmai", P, self.grads)
        out = torch.zeros((B, self.n_nodes, 3), dtype=self.dtype, device=self.device)
        out.index_add_(1, self.tets_flat, fe.reshape(B, -1, 3))
        ok = ok & torch.isfinite(out).reshape(B, -1).all(dim=1)
        return out, ok


def _cofactors(F: torch.Tensor) -> torch.Tensor:
    """Cofactor matrices of 3 x 3 matrices F (..., 3, 3): ``cof(F) = det(F) F^-T``, element-wise
    (batched LU routines for millions of 3 x 3 matrices are far slower on a GPU)."""
    a, b, c = F[..., 0, 0], F[..., 0, 1], F[..., 0, 2]
    d, e, f = F[..., 1, 0], F[..., 1, 1], F[..., 1, 2]
    g, h, i = F[..., 2, 0], F[..., 2, 1], F[..., 2, 2]
    return torch.stack([e * i - f * h, f * g - d * i, d * h - e * g,
                        c * h - b * i, a * i - c * g, b * g - a * h,
                        b * f - c * e, c * d - a * f, a * e - b * d], dim=-1).reshape(F.shape)


@dataclass
class NeoHookeanStats:
    """Per batch: fixed-point maps of the slowest sample, samples restarted with the smaller
    mixing, samples left unsolved, and the mean maps per solved sample (the linear start's
    statistics are in the result's ``stats["linear_start"]``)."""

    iterations: int
    restarted: int
    unsolved: int
    mean_iterations: float


class BatchedNeoHookean:
    """Frictionless neo-Hookean contact of a :class:`BatchedContactSimulator`'s pad, batched.

    Parameters
    ----------
    linear : a frictionless ``BatchedContactSimulator`` in float64 with the ``nodal_pressure``
        formulation (the small-strain limit of the neo-Hookean gel); its operators, contact solver
        and camera are reused.
    strength : scale of the large-deformation terms (1: neo-Hookean; 0: the linear model).
    tol_mm, max_iterations, anderson : convergence tolerance (largest nodal change, mm), the most
        fixed-point maps per sample, the Anderson history.
    """

    def __init__(self, linear, strength: float = 1.0, *, tol_mm: float = TOLERANCE_MM,
                 max_iterations: int = MAX_ITERATIONS, anderson: int = 10):
        if linear.material.friction != "frictionless" or linear.block != 1:
            raise ValueError("the batched neo-Hookean solve is frictionless: give a frictionless "
                             f"BatchedContactSimulator, got friction={linear.material.friction!r}")
        if linear.formulation != "nodal_pressure":
            raise ValueError("the neo-Hookean gel's small-strain limit is the 'nodal_pressure' "
                             f"formulation, got {linear.formulation!r}")
        if linear.dtype != torch.float64:
            raise ValueError("the fixed point needs float64 (its tolerance is 1e-6 mm of ~1 mm): "
                             f"build the BatchedContactSimulator with dtype=torch.float64, got {linear.dtype}")
        if not (strength >= 0.0 and np.isfinite(strength)):
            raise ValueError(f"strength must be a number >= 0, got {strength}")
        self.linear, self.strength = linear, float(strength)
        self.tol_mm, self.max_iterations, self.anderson = float(tol_mm), int(max_iterations), int(anderson)
        mesh, dev = linear.mesh, linear.device
        self.mesh, self.device = mesh, dev
        gel = NeoHookeanGel(mesh.vertices, mesh.tets, 1.0, linear.material.nu)
        self.gel = TorchNeoHookean(gel, dev)
        dofs = build_dof_map(mesh, linear.supports)
        Tc = dofs.T.tocoo()
        idx = torch.as_tensor(np.vstack([Tc.row, Tc.col]), dtype=torch.int64, device=dev)
        vals = torch.as_tensor(Tc.data, dtype=torch.float64, device=dev)
        self.T = torch.sparse_coo_tensor(idx, vals, dofs.T.shape, check_invariants=True).coalesce()  # (3n, n_q)
        self.Tt = torch.sparse_coo_tensor(idx.flip(0), vals, dofs.T.shape[::-1], check_invariants=True).coalesce()
        K = assemble_stiffness_numpy(mesh.vertices, mesh.tets, 1.0, linear.material.nu, "nodal_pressure")
        Kq = (dofs.T.T @ K @ dofs.T).tocoo()
        n_q = Kq.shape[0]
        A = torch.zeros((n_q, n_q), dtype=torch.float64, device=dev)
        A.index_put_((torch.as_tensor(Kq.row, device=dev), torch.as_tensor(Kq.col, device=dev)),
                     torch.as_tensor(Kq.data, dtype=torch.float64, device=dev), accumulate=True)
        L = torch.linalg.cholesky(A)
        del A
        self.Kinv = torch.cholesky_inverse(L)                                           # (n_q, n_q)
        del L
        self.n_q = n_q
        self.sensing = torch.arange(mesh.n_plane, device=dev)

    # ------------------------------------------------------------------------------------------
    def bytes_per_sample(self) -> int:
        """An estimate of the device memory of one sample in the iterations (float64): its
        displacement, Anderson history (two ``anderson + 1`` deep stacks of 3n), the neo-Hookean
        forces' per-tet temporaries (about 8 (m, 3, 3) tensors), and its contact forces (17.5 MB
        on the shipped pad; ``bench/bench_sim_neo_hookean.py`` measured a 21.9 MB peak)."""
        n3, m = 3 * self.mesh.n_nodes, len(self.mesh.tets)
        return 8 * (n3 * (4 + 2 * (self.anderson + 1)) + 8 * 9 * m + 2 * self.mesh.n_plane)

    def _map(self, u: torch.Tensor, d: torch.Tensor, active: torch.Tensor | None = None):
        """One fixed-point map for samples u (b, n, 3), intrusions d (b, n_plane) ->
        (new u, contact forces (b, n_plane, 1) at E = 1, ok (b,) bool, active sets (b, n_plane)).
        ``active``: the contact's active sets to start from (the previous map's)."""
        b = u.shape[0]
        f_int, ok = self.gel.forces(u)
        q = torch.sparse.mm(self.Tt, u.reshape(b, -1).T)                                # (n_q, b)
        fq = torch.sparse.mm(self.Tt, f_int.reshape(b, -1).T)
        ub_q = self.strength * (q - self.Kinv @ fq)
        ub = torch.sparse.mm(self.T, ub_q).T.reshape(b, -1, 3)                          # (b, n, 3)
        d_eff = d + ub[:, : self.mesh.n_plane, 2]
        forces, active, cstats = self.linear.contact.solve(d_eff, active)
        if cstats.unsolved:
            bad = torch.zeros(b, dtype=torch.bool, device=self.device)
            bad[cstats.unsolved] = True
            ok = ok & ~bad
            forces = torch.where(bad[:, None, None], 0.0, forces)
        g = ub + self.linear.displacements_from_forces(forces)
        ok = ok & torch.isfinite(g).reshape(b, -1).all(dim=1)
        return g, forces, ok, active

    def solve_intrusion(self, delta: torch.Tensor, render: bool = True):
        """Neo-Hookean contacts for intrusions ``delta`` (B, n_plane) mm at the sensing nodes
        (-inf where the indenter does not cover a node). Returns
        (:class:`~tactile_deploy.training.simulation.batched.BatchedContactResult`,
        :class:`NeoHookeanStats`); unsolved samples are NaN with ``solved`` False."""
        from tactile_deploy.training.simulation.batched import BatchedContactResult

        lin = self.linear
        delta = torch.as_tensor(delta, dtype=torch.float64, device=self.device)
        first = lin.solve_intrusion(delta, render=False)
        B, n_plane = delta.shape
        u0 = torch.nan_to_num(first.displacements_mm, nan=0.0)
        u_out = torch.full_like(u0, torch.nan)
        f_out = torch.zeros((B, n_plane, 1), dtype=torch.float64, device=self.device)
        done = torch.zeros(B, dtype=torch.bool, device=self.device)
        iterations = torch.zeros(B, dtype=torch.int64)
        restarted = 0
        pending = torch.nonzero(first.solved).flatten()
        for attempt, beta in enumerate(MIXING):
            if len(pending) == 0:
                break
            failed = self._iterate(pending, u0, delta, beta, u_out, f_out, done, iterations)
            if attempt == 0:
                restarted = len(failed)
            pending = failed
        solved = done
        u = torch.where(solved[:, None, None], u_out, torch.nan)
        f3 = torch.zeros((B, n_plane, 3), dtype=torch.float64, device=self.device)
        f3[:, :, 2] = f_out[:, :, 0] * lin.material.E_mpa
        f3 = torch.where(solved[:, None, None], f3, torch.nan)
        fn = -f3[:, :, 2]
        depth = None
        if render:
            depth = lin.camera.render_displacements(torch.nan_to_num(u[:, :n_plane], nan=0.0))
            depth = torch.where(solved[:, None, None], depth, torch.nan)
        its = iterations[solved.cpu()]
        stats = NeoHookeanStats(iterations=int(iterations.max()) if B else 0, restarted=restarted,
                                unsolved=int((~solved).sum()),
                                mean_iterations=float(its.float().mean()) if len(its) else 0.0)
        result = BatchedContactResult(
            intrusion_mm=delta, displacements_mm=u, contact_forces_n=f3, contact_mask=fn > 0,
            force_n=fn.sum(dim=1), depth_mm=depth, solved=solved,
            stats={"neo_hookean": stats.__dict__, "linear_start": first.stats})
        return result, stats

    def _iterate(self, samples, u0, delta, beta, u_out, f_out, done, iterations) -> torch.Tensor:
        """Anderson-accelerated fixed point for ``samples`` (indices into the batch), started
        from ``u0``; converged samples are written to ``u_out``, ``f_out``, ``done``. Returns the
        samples that broke down or did not converge."""
        dev = self.device
        active = samples.clone()
        u = u0[active].clone()
        d = delta[active]
        hist_x: list[torch.Tensor] = []   # each (b, N): rows follow ``active``
        hist_f: list[torch.Tensor] = []
        failed = []
        sets = None   # each sample's last contact active set: the next contact solve starts there
        for it in range(1, self.max_iterations + 1):
            if len(active) == 0:
                break
            b = len(active)
            g, forces, ok, sets = self._map(u, d, sets)
            f = (g - u).reshape(b, -1)
            change = f.abs().amax(dim=1)
            ok = ok & torch.isfinite(change)
            conv = ok & (change < self.tol_mm)
            if bool(conv.any()):
                idx = active[conv]
                u_out[idx] = g[conv]
                f_out[idx] = forces[conv]
                done[idx] = True
                iterations[idx.cpu()] = it
            if bool((~ok).any()):
                failed.append(active[~ok])
            keep = ok & ~conv
            if not bool(keep.all()):
                active, u, d, f, sets = active[keep], u[keep], d[keep], f[keep], sets[keep]
                hist_x = [h[keep] for h in hist_x]
                hist_f = [h[keep] for h in hist_f]
                if len(active) == 0:
                    break
            b = len(active)
            hist_x = (hist_x + [u.reshape(b, -1)])[-(self.anderson + 1):]
            hist_f = (hist_f + [f])[-(self.anderson + 1):]
            if len(hist_x) > 1 and self.anderson > 0:
                X = torch.stack(hist_x, dim=2)                                         # (b, N, h)
                Fh = torch.stack(hist_f, dim=2)
                dX, dF = X.diff(dim=2), Fh.diff(dim=2)                                 # (b, N, h-1)
                A = dF.transpose(1, 2) @ dF                                           # (b, h-1, h-1)
                rhs = dF.transpose(1, 2) @ f[:, :, None]
                eye = torch.eye(A.shape[1], dtype=A.dtype, device=dev)
                reg = 1e-12 * torch.diagonal(A, dim1=1, dim2=2).sum(dim=1).clamp_min(1e-300)
                gamma = torch.linalg.solve(A + reg[:, None, None] * eye, rhs)          # (b, h-1, 1)
                u = (X[:, :, -1] + beta * f - ((dX + beta * dF) @ gamma)[:, :, 0]).reshape(b, -1, 3)
            else:
                u = u + beta * f.reshape(b, -1, 3)
        if len(active):
            failed.append(active)
        return torch.cat(failed) if failed else torch.zeros(0, dtype=torch.int64, device=dev)
