"""Exact restructuring of the trained COMA decoder for onnxruntime (the "fused" export).

The decoder's graph operators are fixed and linear, so everything between two activations can
be regrouped without changing the function (up to float rounding, tested to 1e-5 mm):

* **Start folded.** FC(latent) -> up-sampling to level 3 -> Chebyshev conv at level 3 is one
  affine map of the 128-d latent: a single (128 x 85*16) matrix.
* **Coarse levels dense.** At level 2 the map ``x3 -> sum_k T_k(L2) U2 x3 W_k`` is computed as
  ``[T_0 U2 | ... | T_5 U2] (335 x 510)`` times the stacked ``x3 W_k``: one MatMul.
* **Fine levels layered.** Levels 1 and 0 hold 269 and 1,076 in-plane points on 5 node layers;
  a tet edge only joins nodes whose in-plane points are equal or neighbours, on equal or adjacent
  layers. So each sparse operator is applied to rows = in-plane points (all 5 layers, batch and
  channels in one row): one Gather of ~8 rows per point, then one (5 x 8*5) block per point
  (batched MatMul). That is 5-10x fewer gathered rows than node rows.
* **Narrow side.** The Chebyshev recursion runs on min(C_in, C_out) channels (Clenshaw for the
  last 16 -> 3 layer), and ``W_k`` is applied at level 1 before up-sampling (they commute).

Layout: in-plane-major ``(m, 5, N, C)`` at fine levels, node-major ``(n, N, C)`` at coarse ones.
Only MatMul, Gather, Reshape, Transpose, Add, Mul, Relu/Elu appear in the export.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn

from tactile_deploy.training.networks.coarsening import MeshLevel, Resampling
from tactile_deploy.training.networks.mesh_vae import MeshDecoder


def layered_blocks(level: MeshLevel, op: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Layered form of a square node operator of ``level`` (nodes ``layer * m + k``).

    Returns ``index (m, W)`` in-plane neighbours (incl. the point itself first; padding repeats it)
    and ``blocks (m, L, W * L)`` with ``blocks[i, l, s * L + l'] = op[(l, i), (l', index[i, s])]``.
    Raises if ``op`` couples points that are not in-plane neighbours.
    """
    m, n_layers = level.n_plane, level.n_layers
    coo = sp.coo_matrix(op)
    pi, li = coo.row % m, coo.row // m
    pj, lj = coo.col % m, coo.col // m
    neigh: list[list[int]] = [[i] for i in range(m)]
    for a, b in zip(pi, pj):
        if b not in neigh[a]:
            neigh[a].append(int(b))
    width = max(len(v) for v in neigh)
    index = np.array([v + [v[0]] * (width - len(v)) for v in neigh], dtype=np.int64)
    slot = {(i, j): s for i, v in enumerate(neigh) for s, j in enumerate(v)}
    blocks = np.zeros((m, n_layers, width * n_layers))
    for a, la, b, lb, val in zip(pi, li, pj, lj, coo.data):
        blocks[a, la, slot[(a, b)] * n_layers + lb] += val
    return index, blocks


def layered_resampling(table: Resampling, m_out: int, m_in: int, n_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """In-plane part of a per-layer resampling (same weights on every layer): index, weight (m_out, S)."""
    idx, w = table.index[:m_out], table.weight[:m_out]
    for layer in range(1, n_layers):
        if not (
            np.array_equal(table.index[layer * m_out : (layer + 1) * m_out], idx + layer * m_in)
            and np.allclose(table.weight[layer * m_out : (layer + 1) * m_out], w)
        ):
            raise ValueError("resampling is not the same on every layer")
    return idx, w


class LayeredOp(nn.Module):
    """Square operator on ``(m, L, N, C)``: Gather in-plane neighbours, one (L x W*L) block per point."""

    def __init__(self, index: np.ndarray, blocks: np.ndarray):
        super().__init__()
        self.register_buffer("index", torch.as_tensor(index))
        self.register_buffer("blocks", torch.as_tensor(blocks, dtype=torch.float32))
        self.m, self.layers = blocks.shape[0], blocks.shape[1]
        self.width = index.shape[1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, c = x.shape[2], x.shape[3]
        g = x[self.index].reshape(self.m, self.width * self.layers, n * c)
        return torch.matmul(self.blocks, g).reshape(self.m, self.layers, n, c)


class LayeredUp(nn.Module):
    """Up-sampling on ``(m_in, L, N, C) -> (m_out, L, N, C)`` with in-plane weights."""

    def __init__(self, index: np.ndarray, weight: np.ndarray):
        super().__init__()
        self.register_buffer("index", torch.as_tensor(index))
        self.register_buffer("weight", torch.as_tensor(weight[:, None, :], dtype=torch.float32))
        self.m, self.s = index.shape

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        l, n, c = x.shape[1], x.shape[2], x.shape[3]
        g = x[self.index].reshape(self.m, self.s, l * n * c)
        return torch.matmul(self.weight, g).reshape(self.m, l, n, c)


def _cheb_polys(op: sp.csr_matrix, k: int) -> list[sp.csr_matrix]:
    t = [sp.identity(op.shape[0], format="csr")]
    if k > 1:
        t.append(sp.csr_matrix(op))
        for _ in range(2, k):
            t.append(sp.csr_matrix(2.0 * op @ t[-1] - t[-2]))
    return t


class FusedComaDecoder(nn.Module):
    """Same function as a trained :class:`MeshDecoder` (4 levels), restructured for export.

    Input z (N, latent); output normalised displacement (N, n0, 3), node order of the pad.
    """

    def __init__(self, decoder: MeshDecoder):
        super().__init__()
        h = decoder.graphs.hierarchy
        if decoder.n_levels != 4:
            raise ValueError(f"the fused decoder is written for 4 coarsening levels, got {decoder.n_levels}")
        self.act = decoder.act
        lv = h.levels
        ups = [t.matrix() for t in h.up]
        laps = [lv_.chebyshev_operator.matrix() for lv_ in lv]
        convs = decoder.convs
        with torch.no_grad():
            # -- start: latent -> level 3 pre-activation, one affine map ------------------------
            fc_w = decoder.fc.weight.double().numpy()  # (n4*C4, latent)
            fc_b = decoder.fc.bias.double().numpy()
            n4, c4 = decoder.n_last, decoder.c_last
            c3 = convs[3].weight.shape[2]
            t3 = _cheb_polys(laps[3], convs[3].k)
            w3 = convs[3].weight.double().numpy()  # (K, C4, C3)
            a = np.zeros((lv[3].n_nodes * c3, fc_w.shape[1]))
            # pre3[n, c] = sum_k (T_k U3 X4)[n] W_k[:, c], X4 = reshape(fc_w z + fc_b, (n4, c4))
            x4_w = fc_w.reshape(n4, c4, -1)  # per latent dim
            x4_b = fc_b.reshape(n4, c4)
            pre_b = np.zeros((lv[3].n_nodes, c3))
            for k, tk in enumerate(t3):
                m = (tk @ ups[3]).toarray()  # (n3, n4)
                a += np.einsum("nj,jcz,cd->ndz", m, x4_w, w3[k]).reshape(-1, fc_w.shape[1])
                pre_b += m @ x4_b @ w3[k]
            if convs[3].bias is not None:
                pre_b += convs[3].bias.double().numpy()
            self.start = nn.Linear(fc_w.shape[1], lv[3].n_nodes * c3)
            self.start.weight.copy_(torch.as_tensor(a))
            self.start.bias.copy_(torch.as_tensor(pre_b.reshape(-1)))
            self.n3, self.c3 = lv[3].n_nodes, c3
            # -- level 2: dense [T_k U2] --------------------------------------------------------
            k2 = convs[2].k
            self.c2 = convs[2].weight.shape[2]
            self.k2 = k2
            mats = [(tk @ ups[2]).toarray() for tk in _cheb_polys(laps[2], k2)]
            self.register_buffer("cheb2", torch.as_tensor(np.concatenate(mats, axis=1), dtype=torch.float32))
            self.register_buffer("w2", convs[2].weight.detach().permute(1, 0, 2).reshape(self.c3, -1).clone())
            self.register_buffer("b2", convs[2].bias.detach().clone())
            self.n2 = lv[2].n_nodes
            # -- level 1: layered up-sampling and Laplacian -------------------------------------
            L = lv[0].n_layers
            self.layers = L
            self.p2, self.p1, self.p0 = lv[2].n_plane, lv[1].n_plane, lv[0].n_plane
            self.up1 = LayeredUp(*layered_resampling(h.up[1], lv[1].n_plane, lv[2].n_plane, L))
            self.lap1 = LayeredOp(*layered_blocks(lv[1], laps[1]))
            self.k1 = convs[1].k
            self.c1 = convs[1].weight.shape[2]
            self.register_buffer("w1", convs[1].weight.detach().reshape(-1, self.c1).clone())
            self.register_buffer("b1", convs[1].bias.detach().clone())
            # -- level 0: W_k at level 1, layered up-sampling, Clenshaw on 3 channels -----------
            self.up0 = LayeredUp(*layered_resampling(h.up[0], lv[0].n_plane, lv[1].n_plane, L))
            self.lap0 = LayeredOp(*layered_blocks(lv[0], laps[0]))
            self.k0 = convs[0].k
            self.register_buffer("w0", convs[0].weight.detach().permute(1, 0, 2).reshape(self.c1, -1).clone())
            self.b0 = None if convs[0].bias is None else nn.Parameter(convs[0].bias.detach().clone())

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        n = z.shape[0]
        # level 3 (node-major (n3, N, C3))
        x3 = self.act(self.start(z)).reshape(n, self.n3, self.c3)
        # level 2: y = [T_k U2] stack_k(x3 W_k)
        zk = torch.matmul(x3, self.w2).reshape(n, self.n3, self.k2, self.c2)
        zk = zk.transpose(1, 2).reshape(n, self.k2 * self.n3, self.c2)
        x2 = self.act(torch.matmul(self.cheb2, zk) + self.b2)  # (N, n2, C2)
        # to layered (m2, L, N, C2)
        x2 = x2.reshape(n, self.layers, self.p2, self.c2).permute(2, 1, 0, 3)
        # level 1: up, Chebyshev basis (C2 = C1 channels), one product with stacked weights
        u = self.up1(x2)
        basis = [u]
        if self.k1 > 1:
            basis.append(self.lap1(u))
            for _ in range(2, self.k1):
                basis.append(2.0 * self.lap1(basis[-1]) - basis[-2])
        x1 = self.act(torch.matmul(torch.cat(basis, dim=-1), self.w1) + self.b1)  # (m1, L, N, C1)
        # level 0: z_k = x1 W_k at level 1, up-sample, Clenshaw with L0 on 3 channels
        zk = self.up0(torch.matmul(x1, self.w0))  # (m0, L, N, K0 * 3)
        k0 = self.k0
        parts = [zk[..., 3 * k : 3 * k + 3] for k in range(k0)]
        if k0 == 1:
            y = parts[0]
        else:
            b1, b2 = parts[k0 - 1], None
            for k in range(k0 - 2, 0, -1):
                nxt = parts[k] + 2.0 * self.lap0(b1)
                if b2 is not None:
                    nxt = nxt - b2
                b2, b1 = b1, nxt
            y = parts[0] + self.lap0(b1)
            if b2 is not None:
                y = y - b2
        if self.b0 is not None:
            y = y + self.b0
        # (m0, L, N, 3) -> (N, L * m0, 3), node = layer * m0 + i
        return y.permute(2, 1, 0, 3).reshape(n, self.layers * self.p0, 3)
