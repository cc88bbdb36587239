"""Sparse symmetric positive definite solves: CHOLMOD through cholespy, SuperLU as fallback."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


class SparseCholesky:
    """Factor an SPD sparse matrix once, solve for one or many right-hand sides.

    ``solve(b)``: b (n,) or (n, k) float64 -> x of the same shape.
    """

    def __init__(self, A: sp.spmatrix):
        A = sp.csr_matrix(A)
        self.n = A.shape[0]
        try:
            from cholespy import CholeskySolverD, MatrixType
        except ImportError:  # pragma: no cover - cholespy is a hard dependency
            self._lu = sp.linalg.splu(A.tocsc())
            self._chol = None
        else:
            A.sort_indices()
            self._chol = CholeskySolverD(
                self.n,
                A.indptr.astype(np.int32),
                A.indices.astype(np.int32),
                A.data.astype(np.float64),
                MatrixType.CSR,
            )

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self._chol is None:
            return self._lu.solve(b)
        x = np.empty_like(b)
        self._chol.solve(b, x)
        return x
