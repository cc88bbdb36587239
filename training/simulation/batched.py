"""Batched contact simulation in torch (CPU or CUDA): the CPU simulator's results, many at once.

Data flow of :meth:`BatchedContactSimulator.solve` for B contacts::

    indenter index + pose (B,)  --(envelope grids, bilinear, float64)-->  delta (B, n_plane) mm
        --(exact contact on the surface compliance C, batched active sets)-->  forces (B, k, b) N
        --(one GEMM with the Green's functions G)-->  displacements (B, n, 3) mm
        --(batched rasteriser, tactile_deploy.training.simulation.depth_torch)-->  depth (B, 128, 128) mm

Every step solves the same equations as :class:`tactile_deploy.fem.simulator.ContactSimulator`
(``method="surface"``), which stays the reference: same intrusion, same candidate nodes, the same
primal-dual active-set iteration started from the same active set (so the same active sets and
forces up to solver round-off), the same penetration check, the same Green's functions and the
same depth rasterisation rules. Only torch and numpy are needed (+ scipy for the assembly).

Operators at E = 1 MPa (forces scale with ``E_mpa``, displacements do not):

* ``C`` (k b, k b) mm/N: compliance of the contact dofs (b = 1: z; b = 3: x, y, z per node,
  node-major), ``C = E_c' K_q^-1 E_c``;
* ``G`` (k b, n, 3) mm/N: displacement of every node per unit contact force.

:func:`compute_operators_torch` builds both on the device from the numpy-assembled stiffness by a
dense Cholesky factorisation of the reduced stiffness (16,140 dofs for the shipped pad: 2.1 GB in
float64); they can also be taken from the CPU simulator's operator cache.

Contact (per sample; notation of :mod:`tactile_deploy.fem.contact`): candidates are the nodes
with ``delta > -max(delta)``; the active set starts at ``delta > 0``; each step solves
``C_AA f_A = -delta_A e_z`` on the active nodes A, then ``A <- {fn - c gap > 0}`` over the
candidates (``c = 1 / diag C``) until A repeats. All samples iterate together: each step gathers
``C_AA`` per sample (padded to the largest active set of a group of samples of similar size, the
padding rows replaced by identity rows), factors them with one batched Cholesky and updates the
gaps of all nodes with one GEMM against C; samples leave the batch as they settle. The systems
are as large as the active sets (~20 nodes on average, a few hundred for a coin), not the
candidate sets, so there is no fixed candidate budget to overflow; ``max_active_nodes`` only caps
the memory of one factorisation. When the converged forces still push a non-candidate node
through the indenter, that node joins the candidates and the sample is solved again, as on the
CPU. In float32, samples that fail are first solved again in float64 on the device.
Samples whose active set is larger than ``max_active_nodes``, whose active set cycles
(it comes back after 2 to 17 steps: the deterministic iteration would never settle), that do not
settle in ``max_iter`` steps or whose factorisation fails are solved by the CPU code path on the
host (which, like ``ContactSimulator``, falls back to Lawson-Hanson for frictionless contact and
gives up for sticking contact: such samples are flagged, not solved) and counted (``stats``).

Units: mm, N, MPa; sensor frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tactile_deploy.fem.constraints import SENSOR_SUPPORTS, Supports, build_dof_map
from tactile_deploy.fem.material import Material
from tactile_deploy.pad.mesh import PadMesh
from tactile_deploy.training.simulation.active_sets import (
    BLOCK_ELEMENTS,
    PENETRATION_RTOL,
    ContactStats,
    size_bucket,
)

# Active sets remembered per sample to detect a cycling active-set iteration.
_CYCLE_HISTORY = 16
# Pose columns.
POSE_COLUMNS = ("x_mm", "y_mm", "theta_deg", "depth_mm")


# ----------------------------------------------------------------------------------- operators
def contact_columns(mesh: PadMesh, block: int, supports: Supports = SENSOR_SUPPORTS):
    """Columns of the reduced coordinates q acted on by contact, (n_plane, b) int64, and the dof
    map. b = 1: the z column of every sensing node; b = 3: its x, y and z columns."""
    dofs = build_dof_map(mesh, supports)
    nodes = mesh.sensing_nodes
    z = dofs.z_col[nodes]
    if np.any(z < 0):
        raise ValueError("every sensing node needs a free z direction")
    if block == 1:
        return z[:, None], dofs
    if block != 3:
        raise ValueError(f"block must be 1 (frictionless) or 3 (stick), got {block}")
    xy = dofs.xy_cols[nodes]
    if np.any(xy < 0):
        raise ValueError("sticking contact needs free x and y at every sensing node")
    return np.concatenate([xy, z[:, None]], axis=1), dofs


def compute_operators_torch(
    mesh: PadMesh,
    nu: float,
    block: int,
    *,
    supports: Supports = SENSOR_SUPPORTS,
    formulation: str = "nodal_pressure",
    device="cpu",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Surface compliance and Green's functions at E = 1 MPa by a dense Cholesky on ``device``.

    The stiffness is assembled with numpy (:func:`assemble_stiffness_numpy`), reduced to the free
    coordinates (``K_q = T' K T``), copied densely to the device and factored in float64.

    Returns ``C`` (k b, k b) float64 mm/N and ``G`` (k b, n, 3) float64 mm/N, on ``device``
    (k = n_plane sensing nodes, b = ``block``). Memory: ``2 n_q^2`` float64 on the device
    (4.2 GB for the shipped pad).
    """
    from tactile_deploy.fem.elasticity import assemble_stiffness_numpy

    cols, dofs = contact_columns(mesh, block, supports)
    K = assemble_stiffness_numpy(mesh.vertices, mesh.tets, 1.0, nu, formulation=formulation)
    T = dofs.T
    Kq = (T.T @ K @ T).tocoo()
    n_q = Kq.shape[0]
    device = torch.device(device)
    A = torch.zeros((n_q, n_q), dtype=torch.float64, device=device)
    rows = torch.as_tensor(Kq.row, dtype=torch.int64, device=device)
    cc = torch.as_tensor(Kq.col, dtype=torch.int64, device=device)
    A.index_put_((rows, cc), torch.as_tensor(Kq.data, dtype=torch.float64, device=device),
                 accumulate=True)
    L = torch.linalg.cholesky(A)
    del A
    flat = torch.as_tensor(cols.ravel(), dtype=torch.int64, device=device)
    rhs = torch.zeros((n_q, len(flat)), dtype=torch.float64, device=device)
    rhs[flat, torch.arange(len(flat), device=device)] = 1.0
    X = torch.cholesky_solve(rhs, L)  # (n_q, k b) = K_q^-1 E_c
    del L, rhs
    C = X[flat]
    C = 0.5 * (C + C.T)
    Tc = T.tocoo()
    U = torch.zeros((T.shape[0], len(flat)), dtype=torch.float64, device=device)
    U.index_add_(0, torch.as_tensor(Tc.row, dtype=torch.int64, device=device),
                 X[torch.as_tensor(Tc.col, dtype=torch.int64, device=device)]
                 * torch.as_tensor(Tc.data, dtype=torch.float64, device=device)[:, None])
    G = U.T.reshape(len(flat), mesh.n_nodes, 3).contiguous()
    return C, G


def cached_cpu_operators(mesh: PadMesh, material: Material, supports: Supports = SENSOR_SUPPORTS,
                         formulation: str = "nodal_pressure"):
    """The CPU simulator's cached ``(C float64, G float32)`` numpy arrays, or None if not cached."""
    from tactile_deploy.fem.simulator import ContactSimulator, cache_dir

    sim = ContactSimulator(mesh, material, supports, formulation=formulation)
    folder = cache_dir() / f"surface_{sim.operator_key}"
    if not ((folder / "C.npy").exists() and (folder / "G.npy").exists()):
        return None
    sim.prepare()
    return sim.compliance, sim.greens


# ----------------------------------------------------------------------------------- intrusion
_KIND_GRID, _KIND_SPHERE, _KIND_PARABOLOID = 0, 1, 2
# Pixel positions closer than this to a pixel line are snapped onto it (as EnvelopeGrid.sample_mm).
_SNAP_PIXELS = 1e-6


class EnvelopeBank:
    """Pressing surfaces of several indenters on one device, for batched intrusion.

    Mesh indenters are sampled from their :class:`~tactile_deploy.indenters.EnvelopeGrid`
    exactly as ``EnvelopeGrid.sample_mm`` does (bilinear between pixel centres, +inf outside or
    above ``max_relief_mm``, positions within 1e-6 pixel of a pixel line snapped onto it), in
    float64 by gathers from one flat table of all grids; analytic spheres and paraboloids use
    their closed forms, as ``AnalyticIndenter.envelope_mm`` does. (Why not
    ``torch.nn.functional.grid_sample``: it re-derives pixel positions from normalised
    coordinates, so a point snapped onto a pixel line can get a ~1e-13 weight on an outside
    pixel, 1e30 mm high, and read as outside where the CPU path reads the footprint edge.)
    """

    def __init__(self, names, kinds, params, heights, offsets, device="cpu"):
        self.names = list(names)
        self.device = torch.device(device)
        self.kind = torch.as_tensor(np.asarray(kinds), dtype=torch.int64, device=self.device)
        # params columns: x0, y0, pitch, nx, ny, max_relief, radius (float64)
        self.params = torch.as_tensor(np.asarray(params, dtype=np.float64), device=self.device)
        self.offset = torch.as_tensor(np.asarray(offsets), dtype=torch.int64, device=self.device)
        self.heights = torch.as_tensor(np.asarray(heights, dtype=np.float32), device=self.device)

    def __len__(self) -> int:
        return len(self.names)

    @classmethod
    def from_indenters(cls, indenters, device="cpu") -> "EnvelopeBank":
        from tactile_deploy.indenters.base import AnalyticParaboloid, AnalyticSphere

        names, kinds, params, heights, offsets = [], [], [], [], []
        total = 0
        for ind in indenters:
            names.append(ind.name)
            relief = ind.max_relief_mm
            if isinstance(ind, (AnalyticSphere, AnalyticParaboloid)):
                kinds.append(_KIND_SPHERE if isinstance(ind, AnalyticSphere) else _KIND_PARABOLOID)
                params.append([0.0, 0.0, 1.0, 0.0, 0.0, relief, ind.radius_mm])
                offsets.append(0)
                continue
            g = ind.envelope_grid()
            kinds.append(_KIND_GRID)
            params.append([g.x0_mm, g.y0_mm, g.pitch_mm, g.nx, g.ny, g.max_relief_mm, 0.0])
            offsets.append(total)
            h = g.finite_heights_mm().ravel()
            heights.append(h)
            total += h.size
        flat = np.concatenate(heights) if heights else np.zeros(1, np.float32)
        return cls(names, kinds, params, flat, offsets, device)

    def save_npz(self, path) -> None:
        """Write the bank (names, grids, parameters) to a .npz file."""
        from tactile_deploy.atomic import write_npz

        write_npz(path, names=np.array(self.names), kinds=self.kind.cpu().numpy(),
                  params=self.params.cpu().numpy(), offsets=self.offset.cpu().numpy(),
                  heights=self.heights.cpu().numpy())

    @classmethod
    def load_npz(cls, path, device="cpu") -> "EnvelopeBank":
        with np.load(path) as f:
            return cls([str(n) for n in f["names"]], f["kinds"], f["params"], f["heights"],
                       f["offsets"], device)

    @classmethod
    def concat(cls, banks) -> "EnvelopeBank":
        """One bank holding ``banks``' indenters in order (on the first bank's device)."""
        names, kinds, params, heights, offsets = [], [], [], [], []
        total = 0
        for b in banks:
            names += b.names
            kinds.append(b.kind.cpu().numpy())
            params.append(b.params.cpu().numpy())
            offsets.append(b.offset.cpu().numpy() + total)
            h = b.heights.cpu().numpy()
            heights.append(h)
            total += h.size
        return cls(names, np.concatenate(kinds), np.concatenate(params), np.concatenate(heights),
                   np.concatenate(offsets), banks[0].device)

    def to(self, device) -> "EnvelopeBank":
        return EnvelopeBank(self.names, self.kind.cpu().numpy(), self.params.cpu().numpy(),
                            self.heights.cpu().numpy(), self.offset.cpu().numpy(), device)

    def envelope_mm(self, index: torch.Tensor, q_xy_mm: torch.Tensor) -> torch.Tensor:
        """Envelope heights (B, m) float64 mm (+inf outside) of indenters ``index`` (B,) at
        indenter-frame points ``q_xy_mm`` (B, m, 2) mm."""
        idx = index.to(self.device, torch.int64)
        q = q_xy_mm.to(self.device, torch.float64)
        prm = self.params[idx]  # (B, 7)
        x0, y0, pitch, nx, ny, relief, radius = (prm[:, i : i + 1] for i in range(7))
        kind = self.kind[idx][:, None]
        # Mesh indenters: bilinear in the grid (EnvelopeGrid.sample_mm, operation for operation).
        u = (q[..., 0] - x0) / pitch
        v = (q[..., 1] - y0) / pitch
        ru, rv = torch.round(u), torch.round(v)
        u = torch.where((u - ru).abs() < _SNAP_PIXELS, ru, u)
        v = torch.where((v - rv).abs() < _SNAP_PIXELS, rv, v)
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1) & (kind == _KIND_GRID)
        u = torch.where(inside, u, 0.0)
        v = torch.where(inside, v, 0.0)
        i = torch.minimum(torch.floor(u), nx - 2).clamp(min=0)
        j = torch.minimum(torch.floor(v), ny - 2).clamp(min=0)
        fx, fy = u - i, v - j
        nxi = nx.to(torch.int64)
        k = self.offset[idx][:, None] + j.to(torch.int64) * nxi + i.to(torch.int64)
        h = self.heights
        last = h.numel() - 1
        h00 = h[k.clamp(max=last)].double()
        h01 = h[(k + 1).clamp(max=last)].double()
        h10 = h[(k + nxi).clamp(max=last)].double()
        h11 = h[(k + nxi + 1).clamp(max=last)].double()
        top = h00 * (1.0 - fx) + h01 * fx
        bottom = h10 * (1.0 - fx) + h11 * fx
        e_grid = top * (1.0 - fy) + bottom * fy
        e_grid = torch.where(inside & (e_grid <= relief), e_grid, torch.inf)
        # Analytic indenters (AnalyticSphere / AnalyticParaboloid.height_of_radius_mm).
        r = torch.hypot(q[..., 0], q[..., 1])
        sphere = torch.where(r < radius,
                             radius - torch.sqrt(torch.clamp(radius * radius - r * r, min=0.0)),
                             torch.inf)
        parab = r * r / (2.0 * radius)
        e_an = torch.where(kind == _KIND_SPHERE, sphere, parab)
        e_an = torch.where(e_an <= relief, e_an, torch.inf)
        return torch.where(kind == _KIND_GRID, e_grid, e_an)

    def intrusion_mm(self, index: torch.Tensor, poses: torch.Tensor,
                     points_xy_mm: torch.Tensor) -> torch.Tensor:
        """Intrusion ``depth - envelope(R(-theta)(p - (x, y)))`` (B, m) float64 mm, -inf where
        not covered, of indenters ``index`` (B,) at ``poses`` (B, 4) = (x_mm, y_mm, theta_deg,
        depth_mm) at sensor-frame points ``points_xy_mm`` (m, 2)."""
        poses = poses.to(self.device, torch.float64)
        if poses.ndim != 2 or poses.shape[1] != 4:
            raise ValueError(f"poses must have shape (B, 4) = {POSE_COLUMNS}, got {tuple(poses.shape)}")
        idx = index.to(self.device, torch.int64)
        if idx.shape != poses.shape[:1]:
            raise ValueError(f"index must have shape ({poses.shape[0]},), got {tuple(idx.shape)}")
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= len(self)):
            raise ValueError(f"index must lie in 0..{len(self) - 1} (indenters of the bank)")
        relief = self.params[idx, 5]
        too_deep = poses[:, 3] > relief
        if bool(too_deep.any()):
            b = int(torch.nonzero(too_deep)[0])
            raise ValueError(
                f"pose {b}: depth_mm={float(poses[b, 3])} exceeds max_relief_mm="
                f"{float(relief[b])} of indenter {self.names[int(idx[b])]!r}"
            )
        p = points_xy_mm.to(self.device, torch.float64)
        theta = torch.deg2rad(poses[:, 2:3])
        c, s = torch.cos(theta), torch.sin(theta)
        dx = p[None, :, 0] - poses[:, 0:1]
        dy = p[None, :, 1] - poses[:, 1:2]
        q = torch.stack([c * dx + s * dy, c * dy - s * dx], dim=-1)
        return poses[:, 3:4] - self.envelope_mm(idx, q)


# ----------------------------------------------------------------------------------- contact
def _host_surface_forces(C: np.ndarray, delta: np.ndarray, block: int,
                         nnls_round: int | None = None) -> np.ndarray:
    """ContactSimulator.surface_forces for one sample (numpy, float64): the host fallback.

    ``nnls_round``: the candidate round in which the active-set iteration is known not to
    settle (found on the device); there ``solve_contact`` would end in its Lawson-Hanson
    fallback after ``max_iter`` steps, so that is called directly.
    """
    from tactile_deploy.fem.contact import solve_contact, solve_frictionless_nnls

    b = block
    forces = np.zeros((len(delta), b))
    if not np.any(delta > 0):
        return forces
    reach = max(float(np.max(delta, initial=0.0)), 0.0)
    cand = np.flatnonzero(delta > -reach)
    scale = max(float(delta.max()), 1e-12)
    for rnd in range(1, 21):
        dofs = (cand[:, None] * b + np.arange(b)).ravel()
        sub = C[np.ix_(dofs, dofs)]
        if rnd == nnls_round and b == 1:
            sol = solve_frictionless_nnls(sub, delta[cand])
        else:
            sol = solve_contact(sub, delta[cand], b)
        forces[:] = 0.0
        forces[cand] = sol.forces
        active = cand[sol.active]
        adofs = (active[:, None] * b + np.arange(b)).ravel()
        u_normal = C[b - 1 :: b][:, adofs] @ forces[active].ravel()
        penetrating = np.flatnonzero(-delta - u_normal < -PENETRATION_RTOL * scale)
        missing = np.setdiff1d(penetrating, cand)
        if len(missing) == 0:
            return forces
        cand = np.union1d(cand, missing)
    raise RuntimeError("contact candidate set did not settle")


class BatchedContact:
    """Exact contact on a surface compliance for batches of intrusion fields.

    C : (k b, k b) tensor, mm/N at E = 1 (node-major, normal dof last in each block), on the
        device and in the dtype to solve in.
    C64 : the same operator in float64 on the device (default: C when it is float64, else C
        converted). When C is float32, samples whose float32 iteration fails (cycles, does not
        settle, factorisation fails) are solved again in float64 on the device before anything
        goes to the host; the host fallback (the CPU code path, on ``C64`` copied to the host)
        then sees only what float64 cannot do on the device.
    max_iter : active-set steps per round, as ``solve_contact_pdas`` (100): a sample that does
        not settle in as many steps here does not settle on the CPU either.
    """

    def __init__(self, C: torch.Tensor, block: int, C64: torch.Tensor | None = None,
                 max_active_nodes: int = 768, max_iter: int = 100, max_rounds: int = 20,
                 block_elements: int = BLOCK_ELEMENTS):
        if block not in (1, 3):
            raise ValueError(f"block must be 1 or 3, got {block}")
        if C.ndim != 2 or C.shape[0] != C.shape[1] or C.shape[0] % block:
            raise ValueError(f"C must be square with a multiple of {block} rows, got {tuple(C.shape)}")
        self.C = C
        self.block = block
        self.k = C.shape[0] // block
        self.normal = torch.arange(self.k, device=C.device) * block + (block - 1)
        self.C_normal = C[:, self.normal].contiguous()  # (k b, k): gaps from forces, C symmetric
        self.c = 1.0 / C.diagonal()[self.normal]  # (k,) N/mm
        self.max_active_nodes = int(max_active_nodes)
        self.max_iter = int(max_iter)
        self.max_rounds = int(max_rounds)
        self.block_elements = int(block_elements)
        if C.dtype == torch.float64:
            self.C64 = C if C64 is None else C64
            self.exact = None
        else:
            self.C64 = (C if C64 is None else C64).to(torch.float64)
            self.exact = BatchedContact(self.C64, block, max_active_nodes=max_active_nodes,
                                        max_iter=max_iter, max_rounds=max_rounds,
                                        block_elements=block_elements)
        self._C_host: np.ndarray | None = None

    @property
    def C_host(self) -> np.ndarray:
        """The float64 operator on the host (copied on first use), for the host fallback."""
        if self._C_host is None:
            self._C_host = self.C64.detach().to("cpu").numpy()
        return self._C_host

    def solve(self, delta: torch.Tensor, initial_active: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, ContactStats]:
        """Contact forces at E = 1 for intrusions ``delta`` (B, k) mm (-inf: not covered).

        ``initial_active`` (B, k) bool: the active sets the iteration starts from (default
        ``delta > 0``), e.g. the previous solution's when ``delta`` changed a little; the
        solution does not depend on it (the problem's solution is unique), only the number of
        steps does.

        Returns ``forces`` (B, k, b) N in C's dtype (the force of the indenter on each node;
        normal component last; NaN for the samples listed in ``stats.unsolved``), ``active``
        (B, k) bool, and :class:`ContactStats`.
        """
        C, b, k = self.C, self.block, self.k
        dt, dev = C.dtype, C.device
        delta = delta.to(dev)
        if delta.ndim != 2 or delta.shape[1] != k:
            raise ValueError(f"delta must have shape (B, {k}), got {tuple(delta.shape)}")
        B = delta.shape[0]
        stats = ContactStats(n_samples=B)
        forces = torch.zeros((B, k * b), dtype=dt, device=dev)
        active_out = torch.zeros((B, k), dtype=torch.bool, device=dev)
        dmax = delta.amax(dim=1)
        touching = dmax > 0
        work = torch.nonzero(touching).flatten()
        stats.samples_in_contact = int(work.numel())
        if work.numel() == 0:
            return forces.reshape(B, k, b), active_out, stats
        reach = dmax.clamp(min=0.0)
        cand = (delta > -reach[:, None]) & touching[:, None]
        scale = dmax.clamp(min=1e-12)
        failures: list[tuple[int, int, int]] = []  # (sample, reason, round)
        for rnd in range(1, self.max_rounds + 1):
            stats.rounds = rnd
            f, act, un, ok, it, reasons = self._pdas(
                delta[work], cand[work], None if initial_active is None or rnd > 1 else initial_active[work])
            stats.iterations = max(stats.iterations, it)
            bad = torch.nonzero(~ok).flatten()
            if bad.numel():
                failures += [(i, r, rnd) for i, r in zip(work[bad].tolist(), reasons[bad].tolist())]
            good = torch.nonzero(ok).flatten()
            wg = work[good]
            forces[wg] = f[good]
            active_out[wg] = act[good]
            # Penetration check on the nodes that are not candidates (one GEMM, done in _pdas).
            dg = delta[wg].to(dt)
            pen = (-dg - un[good] < -PENETRATION_RTOL * scale[wg, None].to(dt)) & ~cand[wg]
            missing = pen.any(dim=1)
            if not bool(missing.any()):
                work = work[:0]
                break
            cand[wg] |= pen
            work = wg[missing]
        failures += [(i, _ROUNDS, self.max_rounds) for i in work.tolist()]
        if not failures:
            return forces.reshape(B, k, b), active_out, stats
        if self.exact is not None:
            # Solve the failed samples again in float64 on the device.
            idx = torch.tensor([i for i, _, _ in failures], dtype=torch.int64, device=dev)
            f64, a64, st64 = self.exact.solve(delta[idx])
            forces[idx] = f64.reshape(len(idx), k * b).to(dt)
            active_out[idx] = a64
            stats.escalated_to_float64 = len(failures)
            stats.host_fallback = dict(st64.host_fallback)
            stats.unsolved = [int(idx[j]) for j in st64.unsolved]
            return forces.reshape(B, k, b), active_out, stats
        for i, reason, rnd in failures:
            name = _REASONS[reason]
            stats.host_fallback[name] = stats.host_fallback.get(name, 0) + 1
            fh = self._host(delta[i], reason, rnd)
            if fh is None:
                stats.unsolved.append(i)
                forces[i] = torch.nan
                active_out[i] = False
                continue
            forces[i] = torch.as_tensor(fh.ravel(), dtype=dt, device=dev)
            active_out[i] = torch.as_tensor(-fh[:, -1] > 0, device=dev)
        return forces.reshape(B, k, b), active_out, stats

    def _host(self, delta: torch.Tensor, reason: int, rnd: int) -> np.ndarray | None:
        """Forces (k, b) of one failed float64 sample by the CPU code path, or None where the
        CPU path raises (ContactSimulator would raise for this contact)."""
        from tactile_deploy.fem.contact import ContactSolveError

        if reason == _ROUNDS:
            return None  # the CPU path raises "candidate set did not settle"
        nnls_round = None
        if reason in (_CYCLING, _NOT_SETTLED):
            # The iteration is the CPU's, step for step: it does not settle there either.
            if self.block == 3:
                return None  # solve_contact raises for sticking contact
            nnls_round = rnd  # frictionless: the CPU path ends in Lawson-Hanson
        d = delta.to("cpu", torch.float64).numpy()
        try:
            return _host_surface_forces(self.C_host, d, self.block, nnls_round)
        except (ContactSolveError, RuntimeError):
            return None

    def _pdas(self, delta, cand, initial=None):
        """Primal-dual active sets for samples (S, k), started from ``initial`` (S, k) bool or
        ``delta > 0``: forces (S, k b), active (S, k), normal displacement (S, k) at the
        solution, ok (S,), iterations, failure reason (S,)."""
        C, b = self.C, self.block
        dt, dev = C.dtype, C.device
        S, k = delta.shape
        d = delta.to(dt)
        f_out = torch.zeros((S, k * b), dtype=dt, device=dev)
        un_out = torch.zeros((S, k), dtype=dt, device=dev)
        act_out = torch.zeros((S, k), dtype=torch.bool, device=dev)
        ok = torch.zeros(S, dtype=torch.bool, device=dev)
        reason = torch.full((S,), _NOT_SETTLED, dtype=torch.int64, device=dev)
        rows = torch.arange(S, device=dev)  # rows of the samples still iterating
        active = ((delta > 0) if initial is None else initial.to(dev)) & cand
        # Active sets of the last _CYCLE_HISTORY steps before the current one (cycle test).
        history = torch.zeros((0, S, k), dtype=torch.bool, device=dev)
        iterations = 0
        for it in range(1, self.max_iter + 1):
            iterations = it
            counts = active.sum(dim=1)
            too_big = counts > self.max_active_nodes
            if bool(too_big.any()):
                reason[rows[too_big]] = _TOO_LARGE
                keep = ~too_big
                rows, active, history, counts = rows[keep], active[keep], history[:, keep], counts[keep]
            if rows.numel() == 0:
                break
            f, failed = self._solve_active(d[rows], active, counts)
            if bool(failed.any()):
                reason[rows[failed]] = _FACTOR_FAILED
                keep = ~failed
                rows, active, history, f = rows[keep], active[keep], history[:, keep], f[keep]
                if rows.numel() == 0:
                    break
            un = f @ self.C_normal  # (s, k)
            gap = -d[rows] - un
            fn = -f[:, b - 1 :: b]
            new = (fn - self.c * gap > 0) & cand[rows]
            same = (new == active).all(dim=1)
            if bool(same.any()):
                done = rows[same]
                f_out[done] = f[same]
                un_out[done] = un[same]
                act_out[done] = active[same]
                ok[done] = True
            # The iteration is a fixed map of the active set: a set that comes back after two or
            # more steps cycles for ever (the CPU path gives up after max_iter steps).
            cycling = (new[None] == history).all(dim=2).any(dim=0) & ~same
            if bool(cycling.any()):
                reason[rows[cycling]] = _CYCLING
            go = ~same & ~cycling
            history = torch.cat([history, active[None]])[-_CYCLE_HISTORY:]
            rows, history, active = rows[go], history[:, go], new[go]
            if rows.numel() == 0:
                break
        return f_out, act_out, un_out, ok, iterations, reason

    def _solve_active(self, d, active, counts):
        """Forces (s, k b) solving C_AA f_A = -d_A e_z per sample; failed (s,) factorisations."""
        C, b = self.C, self.block
        dt, dev = C.dtype, C.device
        s, k = active.shape
        f = torch.zeros((s, k * b), dtype=dt, device=dev)
        failed = torch.zeros(s, dtype=torch.bool, device=dev)
        size = size_bucket(counts)
        size = torch.where(counts == 0, 0, size)
        for n in torch.unique(size).tolist():
            if n == 0:
                continue  # no active node: zero forces
            members = torch.nonzero(size == n).flatten()
            m = n * b
            per = max(1, self.block_elements // (m * m))
            for start in range(0, members.numel(), per):
                sel = members[start : start + per]
                f[sel], failed[sel] = self._solve_group(d[sel], active[sel], counts[sel], n)
        return f, failed

    def _solve_group(self, d, active, counts, n):
        C, b = self.C, self.block
        dt, dev = C.dtype, C.device
        g, k = active.shape
        # Active nodes first, in increasing order (stable sort), then padding.
        order = torch.argsort((~active).to(torch.int8), dim=1, stable=True)[:, :n]
        valid = torch.arange(n, device=dev)[None, :] < counts[:, None]
        nodes = torch.where(valid, order, 0)
        dofs = (nodes[:, :, None] * b + torch.arange(b, device=dev)).reshape(g, n * b)
        vd = valid[:, :, None].expand(g, n, b).reshape(g, n * b)
        M = C[dofs[:, :, None], dofs[:, None, :]]
        M = M * (vd[:, :, None] & vd[:, None, :])
        M.diagonal(dim1=1, dim2=2).add_((~vd).to(dt))
        rhs = torch.zeros((g, n, b), dtype=dt, device=dev)
        rhs[:, :, b - 1] = torch.where(valid, -d.gather(1, nodes), 0.0)
        L, info = torch.linalg.cholesky_ex(M)
        x = torch.cholesky_solve(rhs.reshape(g, n * b, 1), L)[..., 0]
        x = torch.where(vd, x, 0.0)
        failed = (info != 0) | ~torch.isfinite(x).all(dim=1)
        out = torch.zeros((g, k * b), dtype=dt, device=dev)
        out.scatter_add_(1, dofs, torch.where(failed[:, None], 0.0, x))
        return out, failed


_NOT_SETTLED, _TOO_LARGE, _FACTOR_FAILED, _CYCLING, _ROUNDS = 0, 1, 2, 3, 4
_REASONS = {_NOT_SETTLED: "not_settled", _TOO_LARGE: "active_set_too_large",
            _FACTOR_FAILED: "factorisation_failed", _CYCLING: "active_set_cycles",
            _ROUNDS: "candidates_not_settled"}


# ----------------------------------------------------------------------------------- simulator
@dataclass(frozen=True)
class BatchedContactResult:
    """Outcome of B contacts (tensors on the simulator's device).

    intrusion_mm : (B, n_plane) float64, mm, -inf where the indenter does not cover a node
    displacements_mm : (B, n, 3) dtype, mm, sensor frame
    contact_forces_n : (B, n_plane, 3) dtype, N — force of the indenter on each sensing node
    contact_mask : (B, n_plane) bool — sensing nodes touching the indenter
    force_n : (B,) dtype, N — total normal force (compression > 0)
    depth_mm : (B, H, W) dtype, mm pushed in (image rows, row 0 = largest y) or None
    solved : (B,) bool — False for contacts the CPU path cannot solve either (all their fields
        are NaN; drop them, as the data generator drops poses it rejects)
    stats : dict — contact :class:`ContactStats` fields, padded pixel boxes of the render
    stick_mask : (B, n_plane) bool — Coulomb contact: nodes in contact that stick (None for the
        other laws)
    """

    intrusion_mm: torch.Tensor
    displacements_mm: torch.Tensor
    contact_forces_n: torch.Tensor
    contact_mask: torch.Tensor
    force_n: torch.Tensor
    depth_mm: torch.Tensor | None
    solved: torch.Tensor
    stats: dict
    stick_mask: torch.Tensor | None = None


class BatchedContactSimulator:
    """The surface method of :class:`ContactSimulator` for batches of contacts, in torch.

    Parameters
    ----------
    mesh : PadMesh
    material : Material — friction "frictionless" (b = 1), "stick" or "coulomb" (b = 3; Coulomb
        contact in float64 by :class:`~tactile_deploy.training.simulation.batched_coulomb.BatchedCoulomb`,
        one friction coefficient per sample given to :meth:`solve`, ``material.mu`` by default);
        nu sets the operators; E_mpa scales the forces.
    device, dtype : where and in which precision contact, displacements and depth are computed
        (intrusion is always float64).
    operators : "auto" (the CPU simulator's cache when present, else computed on the device),
        "torch" (:func:`compute_operators_torch`), "cache" (the CPU simulator's cache; computed
        on the CPU when absent), or a tuple ``(C, G)`` of arrays / tensors at E = 1.
    camera : DepthCamera or None — the depth camera to emulate (default 128 x 128).
    max_active_nodes : samples with more active nodes are solved on the host.
    """

    def __init__(
        self,
        mesh: PadMesh,
        material: Material = Material(),
        device="cpu",
        dtype: torch.dtype = torch.float32,
        *,
        supports: Supports = SENSOR_SUPPORTS,
        formulation: str = "nodal_pressure",
        operators="auto",
        camera=None,
        max_active_nodes: int = 768,
    ):
        if material.friction not in ("frictionless", "stick", "coulomb"):
            raise ValueError(
                f"friction={material.friction!r}: the batched simulator solves 'frictionless', "
                f"'stick' and 'coulomb' contact"
            )
        self.mesh = mesh
        self.material = material
        self.device = torch.device(device)
        self.dtype = dtype
        self.block = 1 if material.friction == "frictionless" else 3
        self.supports = supports
        self.formulation = formulation
        C, G, source = self._operators(operators)
        self.operator_source = source
        C64 = torch.as_tensor(C).to(self.device, torch.float64)
        self.C = C64.to(dtype)
        kb = self.C.shape[0]
        if kb != mesh.n_plane * self.block or tuple(G.shape) != (kb, mesh.n_nodes, 3):
            raise ValueError(
                f"operators have shapes C {tuple(C.shape)}, G {tuple(G.shape)}; expected "
                f"({kb}, {kb}) and ({kb}, {mesh.n_nodes}, 3) for this mesh and friction"
            )
        self.G = torch.as_tensor(G).to(self.device, dtype).reshape(kb, mesh.n_nodes * 3)
        if material.friction == "coulomb":
            from tactile_deploy.training.simulation.batched_coulomb import BatchedCoulomb

            self.contact = BatchedCoulomb(C64, max_active_nodes=max_active_nodes)
        else:
            self.contact = BatchedContact(self.C, self.block, C64, max_active_nodes=max_active_nodes)
        self.sensing_xy = torch.as_tensor(mesh.vertices[: mesh.n_plane, :2], dtype=torch.float64,
                                          device=self.device)
        self.sensing_z = torch.as_tensor(mesh.vertices[: mesh.n_plane, 2], dtype=torch.float64,
                                         device=self.device)
        self._camera_arg = camera
        self._torch_camera = None

    def _operators(self, operators):
        if isinstance(operators, tuple):
            C, G = operators
            return torch.as_tensor(C), torch.as_tensor(G), "given"
        if operators not in ("auto", "torch", "cache"):
            raise ValueError(f"operators must be 'auto', 'torch', 'cache' or (C, G), got {operators!r}")
        # Coulomb contact shares the operators of sticking contact (three dofs per node).
        material = self.material.model_copy(update={"friction": "stick"}) if self.block == 3 else self.material
        if operators in ("auto", "cache"):
            ops = cached_cpu_operators(self.mesh, material, self.supports, self.formulation)
            if ops is None and operators == "cache":
                from tactile_deploy.fem.simulator import ContactSimulator

                sim = ContactSimulator(self.mesh, material, self.supports,
                                       formulation=self.formulation)
                sim.prepare()
                ops = (sim.compliance, sim.greens)
            if ops is not None:
                C, G = (np.array(a) for a in ops)  # writable copies (the cache is memory-mapped)
                return torch.from_numpy(C), torch.from_numpy(G), "cpu_cache"
        C, G = compute_operators_torch(self.mesh, self.material.nu, self.block,
                                       supports=self.supports, formulation=self.formulation,
                                       device=self.device)
        return C, G, "torch"

    @property
    def camera(self):
        """The :class:`~tactile_deploy.training.simulation.depth_torch.TorchDepthCamera` (built on first use)."""
        if self._torch_camera is None:
            from tactile_deploy.training.simulation.depth_torch import TorchDepthCamera

            self._torch_camera = TorchDepthCamera(self.mesh, self._camera_arg, self.device,
                                                  self.dtype)
        return self._torch_camera

    # ------------------------------------------------------------------------------------------
    def intrusion(self, bank: EnvelopeBank, index, poses) -> torch.Tensor:
        """Intrusion at the sensing nodes (B, n_plane) float64 mm (-inf where not covered), as
        ``ContactSimulator.intrusion`` (the rest surface's sag included)."""
        index = torch.as_tensor(index, device=bank.device)
        poses = torch.as_tensor(poses, dtype=torch.float64, device=bank.device)
        delta = bank.intrusion_mm(index, poses, self.sensing_xy.to(bank.device))
        return delta.to(self.device) + self.sensing_z

    def solve(self, bank: EnvelopeBank, index, poses, render: bool = True, mu=None) -> BatchedContactResult:
        """Contacts of indenters ``index`` (B,) of ``bank`` at ``poses`` (B, 4) = (x_mm, y_mm,
        theta_deg, depth_mm) (see :class:`~tactile_deploy.indenters.ContactPose`); ``mu`` (B,)
        or a scalar: friction coefficients of Coulomb contact (default ``material.mu``)."""
        return self.solve_intrusion(self.intrusion(bank, index, poses), render=render, mu=mu)

    def solve_intrusion(self, delta: torch.Tensor, render: bool = True,
                        stage_seconds: dict | None = None, mu=None) -> BatchedContactResult:
        """Contacts for intrusion fields ``delta`` (B, n_plane) mm at the sensing nodes.

        ``stage_seconds``: when given, the device is synchronised after each stage and the
        seconds spent in "contact", "volume" and "depth" are added to it (profiling).
        ``mu``: Coulomb contact's friction coefficients, (B,) or a scalar (default
        ``material.mu``); not allowed for the other laws.
        """
        delta = torch.as_tensor(delta, dtype=torch.float64, device=self.device)
        if delta.ndim != 2 or delta.shape[1] != self.mesh.n_plane:
            raise ValueError(f"delta must have shape (B, {self.mesh.n_plane}), got {tuple(delta.shape)}")
        clock = _StageClock(self.device, stage_seconds)
        stick_mask = None
        if self.material.friction == "coulomb":
            forces, active, stick_mask, cstats = self.contact.solve(delta, self.material.mu if mu is None else mu)
        elif mu is not None:
            raise ValueError(f"mu is the friction coefficient of Coulomb contact; this simulator's friction "
                             f"is {self.material.friction!r}")
        else:
            forces, active, cstats = self.contact.solve(delta)
        clock("contact")
        B, n_plane = delta.shape
        solved = torch.ones(B, dtype=torch.bool, device=self.device)
        if cstats.unsolved:
            solved[cstats.unsolved] = False
            forces = torch.where(solved[:, None, None], forces, 0.0)
        u = self.displacements_from_forces(forces)
        clock("volume")
        f3 = torch.zeros((B, n_plane, 3), dtype=self.dtype, device=self.device)
        if self.block == 1:
            f3[:, :, 2] = forces[:, :, 0]
        else:
            f3[:] = forces.to(self.dtype)
        f3 = f3 * self.material.E_mpa
        fn = -f3[:, :, 2]
        stats = {
            "n_samples": cstats.n_samples,
            "samples_in_contact": cstats.samples_in_contact,
            "max_active_set_iterations": cstats.iterations,
            "max_candidate_rounds": cstats.rounds,
            "contact_host_fallback": dict(cstats.host_fallback),
            "n_contact_fallback": cstats.n_fallback,
            "n_escalated_to_float64": cstats.escalated_to_float64,
            "n_unsolved": len(cstats.unsolved),
        }
        depth = None
        if render:
            depth = self.camera.render_displacements(u[:, :n_plane])
            stats["render_pixels_per_triangle"] = self.camera.last_pixels_per_triangle
            clock("depth")
        if cstats.unsolved:
            nan = torch.tensor(torch.nan, dtype=self.dtype, device=self.device)
            u = torch.where(solved[:, None, None], u, nan)
            f3 = torch.where(solved[:, None, None], f3, nan)
            fn = torch.where(solved[:, None], fn, nan)
            if depth is not None:
                depth = torch.where(solved[:, None, None], depth, nan)
        return BatchedContactResult(
            intrusion_mm=delta,
            displacements_mm=u,
            contact_forces_n=f3,
            contact_mask=fn > 0,
            force_n=fn.sum(dim=1),
            depth_mm=depth,
            solved=solved,
            stats=stats,
            stick_mask=None if stick_mask is None else stick_mask & (fn > 0),
        )

    def displacements_from_forces(self, forces_e1: torch.Tensor) -> torch.Tensor:
        """Nodal displacements (B, n, 3) mm from contact forces at E = 1, (B, k, b) N (one GEMM)."""
        B = forces_e1.shape[0]
        return (forces_e1.reshape(B, -1).to(self.dtype) @ self.G).reshape(B, self.mesh.n_nodes, 3)


class _StageClock:
    """Adds the seconds since the previous call to ``seconds[name]`` (device synchronised)."""

    def __init__(self, device, seconds: dict | None):
        import time

        self.device, self.seconds, self.time = device, seconds, time.perf_counter
        self.last = self.time() if seconds is not None else 0.0

    def __call__(self, name: str) -> None:
        if self.seconds is None:
            return
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        now = self.time()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self.last
        self.last = now


def poses_tensor(poses, dtype=torch.float64) -> torch.Tensor:
    """(B, 4) tensor (x_mm, y_mm, theta_deg, depth_mm) from a list of ContactPose."""
    return torch.tensor([[p.x_mm, p.y_mm, p.theta_deg, p.depth_mm] for p in poses], dtype=dtype)


__all__ = [
    "POSE_COLUMNS",
    "BatchedContact",
    "BatchedContactResult",
    "BatchedContactSimulator",
    "ContactStats",
    "EnvelopeBank",
    "cached_cpu_operators",
    "compute_operators_torch",
    "contact_columns",
    "poses_tensor",
]

