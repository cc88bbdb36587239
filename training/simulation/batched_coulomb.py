"""Coulomb friction for batches of contacts in torch: the CPU solver's Newton steps, many at once.

Solves, for B intrusion fields and B friction coefficients at once, the problem
:func:`tactile_deploy.fem.coulomb.coulomb_surface_forces` solves for one (notation and
conditions in :mod:`tactile_deploy.fem.coulomb`; one load step from rest, ``r = 0``):

* candidates ``delta > -max(delta)``; active set ``delta > 0``, every active node sticking, at
  the first step;
* each step: the semi-smooth Newton system of Alart and Curnier's equations on the active nodes
  (3 rows per node: the gap; zero slip for sticking nodes; the friction law linearised with the
  cone-projected tangential force of Hueber, Stadler and Wohlmuth for slipping ones), gathered
  per sample from ``C``, padded to the largest active set of a group of samples of similar size
  (identity rows), solved by one batched LU; the displacements of every contact dof by one GEMM
  against ``C``; the next free / stick / slip sets from the Alart-Curnier predictors;
* a sample stops when its natural residual is at most ``TOL`` of its largest normal force and
  its active set repeats, as on the CPU; then nodes outside the candidates that the forces push
  through the indenter join the candidates and the sample is solved again.

Float64 throughout (the residual tolerance, 1e-10 of the largest normal force, is below float32's
resolution). Samples that do not settle in ``max_iter`` steps, whose system is singular or
larger than ``max_active_nodes`` go to the CPU solver on the host (the same equations), and are
flagged unsolved where it raises too.

Units: mm, N at E = 1 MPa; sensor frame; C node-major (x, y, z per contact node).
"""

from __future__ import annotations

import numpy as np
import torch

from tactile_deploy.fem.coulomb import MAX_ITER, TOL, CoulombSolveError, coulomb_surface_forces
from tactile_deploy.training.simulation.active_sets import BLOCK_ELEMENTS, PENETRATION_RTOL, ContactStats, size_bucket

# Failure reasons of one sample's Newton iteration on the device.
_NOT_SETTLED, _TOO_LARGE, _SINGULAR = 0, 1, 2
_REASONS = {_NOT_SETTLED: "not_settled", _TOO_LARGE: "active_set_too_large", _SINGULAR: "singular_system"}


class BatchedCoulomb:
    """Coulomb contact on the surface compliance ``C`` (3k, 3k) mm/N at E = 1, float64, for
    batches of intrusions (B, k) mm and friction coefficients (B,).

    max_active_nodes : samples with more nodes in contact are solved on the host.
    max_iter, tol : Newton steps per round and the residual tolerance, as the CPU solver's.
    """

    def __init__(self, C: torch.Tensor, max_active_nodes: int = 768, max_iter: int = MAX_ITER,
                 tol: float = TOL, max_rounds: int = 20, block_elements: int = BLOCK_ELEMENTS):
        if C.dtype != torch.float64:
            raise ValueError(f"Coulomb contact is solved in float64, got C of dtype {C.dtype}")
        if C.ndim != 2 or C.shape[0] != C.shape[1] or C.shape[0] % 3:
            raise ValueError(f"C must be square with 3 rows per contact node, got {tuple(C.shape)}")
        self.C = C
        self.k = C.shape[0] // 3
        d = C.diagonal().reshape(self.k, 3)
        self.c_n = 1.0 / d[:, 2]  # (k,) N/mm
        self.c_t = 2.0 / (d[:, 0] + d[:, 1])
        self.max_active_nodes = int(max_active_nodes)
        self.max_iter = int(max_iter)
        self.tol = float(tol)
        self.max_rounds = int(max_rounds)
        self.block_elements = int(block_elements)
        self._C_host: np.ndarray | None = None

    # ----------------------------------------------------------------------------------------
    def solve(self, delta: torch.Tensor, mu) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, ContactStats]:
        """Forces (B, k, 3) N at E = 1 (indenter on gel, NaN for ``stats.unsolved``), active
        (B, k) and stick (B, k) bool, and :class:`ContactStats`, for intrusions ``delta``
        (B, k) mm (-inf: not covered) and friction coefficients ``mu`` (B,) or a scalar, >= 0."""
        k, dev = self.k, self.C.device
        delta = torch.as_tensor(delta, dtype=torch.float64, device=dev)
        if delta.ndim != 2 or delta.shape[1] != k:
            raise ValueError(f"delta must have shape (B, {k}), got {tuple(delta.shape)}")
        B = delta.shape[0]
        mu = torch.as_tensor(mu, dtype=torch.float64, device=dev).expand(B).contiguous()
        if bool((mu < 0).any()) or not bool(torch.isfinite(mu).all()):
            raise ValueError(f"friction coefficients must be finite and >= 0, got min {float(mu.min()):g}")
        stats = ContactStats(n_samples=B)
        forces = torch.zeros((B, k, 3), dtype=torch.float64, device=dev)
        active_out = torch.zeros((B, k), dtype=torch.bool, device=dev)
        stick_out = torch.zeros((B, k), dtype=torch.bool, device=dev)
        dmax = delta.amax(dim=1)
        work = torch.nonzero(dmax > 0).flatten()
        stats.samples_in_contact = int(work.numel())
        reach = dmax.clamp(min=0.0)
        cand = (delta > -reach[:, None]) & (dmax > 0)[:, None]
        failures: list[tuple[int, int]] = []
        for rnd in range(1, self.max_rounds + 1):
            if work.numel() == 0:
                break
            stats.rounds = rnd
            f, act, st, un, ok, it, reasons = self._newton(delta[work], cand[work], mu[work])
            stats.iterations = max(stats.iterations, it)
            bad = torch.nonzero(~ok).flatten()
            failures += [(i, r) for i, r in zip(work[bad].tolist(), reasons[bad].tolist())]
            good = torch.nonzero(ok).flatten()
            wg = work[good]
            forces[wg], active_out[wg], stick_out[wg] = f[good], act[good], st[good]
            pen = (-delta[wg] - un[good] < -PENETRATION_RTOL * reach[wg, None]) & ~cand[wg]
            missing = pen.any(dim=1)
            cand[wg] |= pen
            work = wg[missing]
        failures += [(i, _NOT_SETTLED) for i in work.tolist()]  # candidates did not settle
        for i, reason in failures:
            name = _REASONS[reason]
            stats.host_fallback[name] = stats.host_fallback.get(name, 0) + 1
            try:
                fh, sh, _ = coulomb_surface_forces(self.C_host, delta[i].cpu().numpy(), float(mu[i]))
            except CoulombSolveError:
                stats.unsolved.append(i)
                forces[i] = torch.nan
                active_out[i] = stick_out[i] = False
                continue
            forces[i] = torch.as_tensor(fh, device=dev)
            active_out[i] = torch.as_tensor(-fh[:, 2] > 0, device=dev)
            stick_out[i] = torch.as_tensor(sh, device=dev)
        return forces, active_out, stick_out & active_out, stats

    @property
    def C_host(self) -> np.ndarray:
        """The operator on the host (copied on first use), for the host fallback."""
        if self._C_host is None:
            self._C_host = self.C.detach().to("cpu").numpy()
        return self._C_host

    # ----------------------------------------------------------------------------------------
    def _newton(self, delta, cand, mu):
        """Semi-smooth Newton for samples (S, k) on fixed candidates: forces (S, k, 3), active,
        stick (S, k), normal displacements (S, k) mm at the solution, ok (S,), steps taken,
        failure reason (S,)."""
        C, k = self.C, self.k
        dev = C.device
        S = delta.shape[0]
        f_out = torch.zeros((S, k, 3), dtype=torch.float64, device=dev)
        act_out = torch.zeros((S, k), dtype=torch.bool, device=dev)
        st_out = torch.zeros((S, k), dtype=torch.bool, device=dev)
        un_out = torch.zeros((S, k), dtype=torch.float64, device=dev)
        ok = torch.zeros(S, dtype=torch.bool, device=dev)
        reason = torch.full((S,), _NOT_SETTLED, dtype=torch.int64, device=dev)
        rows = torch.arange(S, device=dev)
        active = (delta > 0) & cand
        stick = active.clone()
        f = torch.zeros((S, k, 3), dtype=torch.float64, device=dev)
        u = torch.zeros((S, k, 3), dtype=torch.float64, device=dev)
        steps = 0
        for it in range(1, self.max_iter + 1):
            steps = it
            counts = active.sum(dim=1)
            keep = counts <= self.max_active_nodes
            reason[rows[~keep]] = _TOO_LARGE
            f_new, singular = self._step(delta[rows], mu[rows], active, stick, f, u, counts)
            reason[rows[singular & keep]] = _SINGULAR
            keep &= ~singular
            u_new = (f_new.reshape(-1, 3 * k) @ C).reshape(-1, k, 3)
            res, new_active, new_stick = self._predictors(delta[rows], cand[rows], mu[rows], f_new, u_new)
            done = keep & (res <= self.tol) & (new_active == active).all(dim=1)
            d = rows[done]
            f_out[d], act_out[d], st_out[d] = f_new[done], active[done], stick[done] & active[done]
            un_out[d] = u_new[done][..., 2]
            ok[d] = True
            go = keep & ~done
            rows, active, stick = rows[go], new_active[go], new_stick[go]
            f, u = f_new[go], u_new[go]
            if rows.numel() == 0:
                break
        return f_out, act_out, st_out, un_out, ok, steps, reason

    def _predictors(self, delta, cand, mu, f, u):
        """Natural residual relative to the largest normal force (s,), and the next active and
        stick sets (s, k) over the candidates."""
        p, t = -f[..., 2], f[..., :2]
        g = -delta - u[..., 2]
        s = u[..., :2]
        c_n, c_t = self.c_n, self.c_t[:, None]
        pt = p - c_n * g
        rn = p - pt.clamp(min=0.0)
        eta = mu[:, None] * pt.clamp(min=0.0)
        z = t - c_t * s
        nz = torch.linalg.vector_norm(z, dim=-1)
        proj = z * torch.clamp(eta / nz.clamp(min=1e-300), max=1.0)[..., None]
        rt = torch.linalg.vector_norm(t - proj, dim=-1)
        r = torch.where(cand, torch.maximum(rn.abs(), rt), 0.0).amax(dim=1)
        scale = torch.where(cand, p, 0.0).amax(dim=1).clamp(min=1e-300)
        new_active = (pt > 0) & cand
        new_stick = new_active & (nz < eta)
        return r / scale, new_active, new_stick

    def _step(self, delta, mu, active, stick, f, u, counts):
        """One Newton step for every sample: forces (s, k, 3) and singular (s,) flags."""
        s, k = active.shape
        dev = self.C.device
        f_new = torch.zeros((s, k, 3), dtype=torch.float64, device=dev)
        singular = torch.zeros(s, dtype=torch.bool, device=dev)
        size = torch.where((counts == 0) | (counts > self.max_active_nodes), 0, size_bucket(counts))
        for n in torch.unique(size).tolist():
            if n == 0:
                continue  # nothing in contact (zero forces) or too large (solved on the host)
            members = torch.nonzero(size == n).flatten()
            per = max(1, self.block_elements // (9 * n * n))
            for start in range(0, members.numel(), per):
                sel = members[start : start + per]
                f_new[sel], singular[sel] = self._solve_group(delta[sel], mu[sel], active[sel], stick[sel],
                                                              f[sel], u[sel], counts[sel], n)
        return f_new, singular

    def _solve_group(self, delta, mu, active, stick, f, u, counts, n):
        """The Newton system of g samples padded to n nodes (3n rows), solved by batched LU."""
        C = self.C
        dev = C.device
        g, k = active.shape
        m = 3 * n
        order = torch.argsort((~active).to(torch.int8), dim=1, stable=True)[:, :n]
        valid = torch.arange(n, device=dev)[None, :] < counts[:, None]  # (g, n)
        nodes = torch.where(valid, order, 0)
        dofs = (nodes[:, :, None] * 3 + torch.arange(3, device=dev)).reshape(g, m)
        vd = valid[:, :, None].expand(g, n, 3).reshape(g, m)
        CA = C[dofs[:, :, None], dofs[:, None, :]] * (vd[:, :, None] & vd[:, None, :])  # (g, m, m)
        CA5 = CA.reshape(g, n, 3, m)
        # Last iterate at the active nodes.
        fk, uk = f.gather(1, nodes[..., None].expand(g, n, 3)), u.gather(1, nodes[..., None].expand(g, n, 3))
        dk = delta.gather(1, nodes)
        c_n, c_t = self.c_n[nodes], self.c_t[nodes]
        p_k = -fk[..., 2]
        g_k = -dk - uk[..., 2]
        eta = mu[:, None] * (p_k - c_n * g_k).clamp(min=0.0)  # (g, n)
        t_k = fk[..., :2]
        z_k = t_k - c_t[..., None] * uk[..., :2]
        nz = torch.linalg.vector_norm(z_k, dim=-1).clamp(min=1e-300)
        dirn = z_k / nz[..., None]
        nt = torch.linalg.vector_norm(t_k, dim=-1).clamp(min=1e-300)
        t_hat = t_k * torch.clamp(eta / nt, max=1.0)[..., None]
        eye2 = torch.eye(2, dtype=torch.float64, device=dev)
        Bm = t_hat[..., :, None] * dirn[..., None, :] - eta[..., None, None] * eye2  # (g, n, 2, 2)
        # Slip rows: B (E_t - c_t C_t.) f + |z| t - mu z_k (-f_z) terms, as tactile_deploy.fem.coulomb._slip_rows.
        slip = -c_t[..., None, None] * (Bm @ CA5[:, :, :2, :])  # (g, n, 2, m)
        local = torch.cat([Bm + nz[..., None, None] * eye2, mu[:, None, None, None] * z_k[..., :, None]], dim=-1)
        slip5 = slip.reshape(g, n, 2, n, 3)
        idx = torch.arange(n, device=dev)
        slip5[:, idx, :, idx, :] += local.permute(1, 0, 2, 3)
        slip_rhs = nz[..., None] * t_hat - eta[..., None] * z_k  # (g, n, 2)
        if bool((mu == 0).any()):  # frictionless samples: t = 0 in place of the friction law
            free_t = torch.zeros((g, n, 2, n, 3), dtype=torch.float64, device=dev)
            free_t[:, idx, :, idx, :2] = eye2
            frictionless = (mu == 0)[:, None, None, None]
            slip = torch.where(frictionless, free_t.reshape(g, n, 2, m), slip)
            slip_rhs = torch.where(frictionless[..., 0], 0.0, slip_rhs)
        # Tangential rows: zero slip (stick) or the friction law (slip); normal rows: zero gap.
        sticking = stick.gather(1, nodes)[..., None, None]
        tang = torch.where(sticking, CA5[:, :, :2, :], slip)
        tang_rhs = torch.where(sticking[..., 0], 0.0, slip_rhs)
        M = torch.cat([tang, CA5[:, :, 2:, :]], dim=2).reshape(g, m, m)
        rhs = torch.cat([tang_rhs, -dk[..., None]], dim=-1).reshape(g, m)
        # Padding: identity rows and zero right-hand sides (their columns are already zero).
        M = torch.where(vd[:, :, None], M, 0.0)
        M.diagonal(dim1=1, dim2=2).add_((~vd).to(torch.float64))
        rhs = torch.where(vd, rhs, 0.0)
        x, info = torch.linalg.solve_ex(M, rhs)
        bad = (info != 0) | ~torch.isfinite(x).all(dim=1)
        x = torch.where(vd & ~bad[:, None], x, 0.0)
        out = torch.zeros((g, k * 3), dtype=torch.float64, device=dev)
        out.scatter_add_(1, dofs, x)
        return out.reshape(g, k, 3), bad


__all__ = ["BatchedCoulomb"]
