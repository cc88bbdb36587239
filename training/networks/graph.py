"""Graph operators for the mesh networks: fixed sparse maps and Chebyshev convolutions (torch).

Node features are **node-major** ``(n, B, C)`` tensors (node, batch, channel): a sparse map then
acts on a contiguous ``(n, B * C)`` matrix without copies, and an exported Gather reads whole
rows. A fixed sparse map (up/down sampling, the scaled Laplacian) is used in two forms:

* eager training: torch sparse CSR products, forward ``A x`` and backward ``A^T g`` (both
  precomputed; several times faster than gathers and their scatter-add backward on CPU);
* export (``torch.export`` / ONNX) or ``use_tables``: padded tables ``index`` / ``weight``
  (n_out, S), ``y = sum_s w[:, s] x[index[:, s]]`` -- Gather and small dense products, standard
  operators only, no sparse tensors in the exported graph.

Both give the same numbers (tested).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from tactile_deploy.training.networks.coarsening import Resampling


def _exporting() -> bool:
    return bool(torch.compiler.is_exporting() or torch.jit.is_tracing() or torch.onnx.is_in_onnx_export())


def _csr(table: Resampling, transpose: bool) -> torch.Tensor:
    import warnings

    m = table.matrix()
    if transpose:
        m = m.T.tocsr()
    m.sort_indices()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(
            torch.as_tensor(m.indptr, dtype=torch.int64),
            torch.as_tensor(m.indices, dtype=torch.int64),
            torch.as_tensor(m.data, dtype=torch.float32),
            m.shape,
            check_invariants=True,
        )


class _SparseProduct(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, a_t, x):
        ctx.a_t = a_t
        return a @ x

    @staticmethod
    def backward(ctx, g):
        return None, None, ctx.a_t @ g.contiguous()


class SparseMap(nn.Module):
    """A fixed sparse linear map between node sets: ``(n_in, B, C) -> (n_out, B, C)``."""

    def __init__(self, table: Resampling):
        super().__init__()
        self.n_in = int(table.n_in)
        self.n_out = int(table.n_out)
        self.register_buffer("index", torch.as_tensor(table.index, dtype=torch.int64), persistent=False)
        self.register_buffer("weight", torch.as_tensor(table.weight, dtype=torch.float32), persistent=False)
        self._table = table
        self._sparse: dict = {}
        self.use_tables = False

    def _matrices(self, device: torch.device):
        key = str(device)
        if key not in self._sparse:
            self._sparse[key] = (_csr(self._table, False).to(device), _csr(self._table, True).to(device))
        return self._sparse[key]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.use_tables or _exporting():
            return self.tables(x)
        n, b, c = x.shape
        a, a_t = self._matrices(x.device)
        y = _SparseProduct.apply(a, a_t, x.reshape(n, b * c))
        return y.reshape(self.n_out, b, c)

    def tables(self, x: torch.Tensor) -> torch.Tensor:
        """Exported form: Gather rows (n_out, S, B, C), weight and sum over S."""
        g = x[self.index]
        return (g * self.weight[:, :, None, None]).sum(dim=1)


class ChebConv(nn.Module):
    """Chebyshev spectral graph convolution (Defferrard et al. 2016), as used by COMA.

    ``y = sum_{k<K} T_k(L~) x W_k + b`` with ``T_0 = I, T_1 = L~, T_k = 2 L~ T_{k-1} - T_{k-2}``
    and ``L~`` the scaled normalised Laplacian (spectrum in [-1, 1]).
    x : (n, B, C_in) -> (n, B, C_out)
    """

    def __init__(self, c_in: int, c_out: int, k: int, laplacian: SparseMap, bias: bool = True):
        super().__init__()
        if k < 1:
            raise ValueError(f"Chebyshev order k must be >= 1, got {k}")
        self.k = k
        self.laplacian = laplacian
        self.weight = nn.Parameter(torch.empty(k, c_in, c_out))
        self.bias = nn.Parameter(torch.zeros(c_out)) if bias else None
        bound = math.sqrt(6.0 / (c_in * k + c_out))
        nn.init.uniform_(self.weight, -bound, bound)

    def basis(self, x: torch.Tensor) -> list[torch.Tensor]:
        """``[T_0(L~) x, ..., T_{K-1}(L~) x]``."""
        out = [x]
        if self.k > 1:
            out.append(self.laplacian(x))
            for _ in range(2, self.k):
                out.append(2.0 * self.laplacian(out[-1]) - out[-2])
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, b, c_in = x.shape
        c_out = self.weight.shape[2]
        if c_out < c_in and self.k > 1:
            y = self.clenshaw(x)
            return y if self.bias is None else y + self.bias
        # One product of the stacked basis (n*B, K*C_in) with the stacked weights (K*C_in, C_out).
        t = torch.cat(self.basis(x), dim=-1).reshape(n * b, self.k * c_in)
        w = self.weight.reshape(self.k * c_in, c_out)
        y = torch.addmm(self.bias, t, w) if self.bias is not None else t @ w
        return y.reshape(n, b, c_out)

    def clenshaw(self, x: torch.Tensor) -> torch.Tensor:
        """The same sum (without bias) with the recursion on the C_out side (cheaper when C_out < C_in).

        ``z_k = x W_k``; ``b_k = z_k + 2 L~ b_{k+1} - b_{k+2}`` for k = K-1 .. 1 (b_K = b_{K+1} = 0);
        ``y = z_0 + L~ b_1 - b_2``.
        """
        n, b, c_in = x.shape
        k_, _, c_out = self.weight.shape
        w = self.weight.permute(1, 0, 2).reshape(c_in, k_ * c_out)
        z = (x.reshape(n * b, c_in) @ w).reshape(n, b, k_, c_out)
        b1 = z[:, :, k_ - 1]
        b2 = None
        for k in range(k_ - 2, 0, -1):
            nxt = z[:, :, k] + 2.0 * self.laplacian(b1)
            if b2 is not None:
                nxt = nxt - b2
            b2, b1 = b1, nxt
        y = z[:, :, 0] + self.laplacian(b1)
        return y if b2 is None else y - b2
