"""Sparse symmetric solves: CHOLMOD through cholespy (the linear pad models' positive definite
stiffness), MKL PARDISO or SuperLU (the resolved solver's tangents, :class:`SymmetricFactor`)."""

from __future__ import annotations

import functools
import os

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


def nested_dissection_order(adjacency: sp.spmatrix) -> np.ndarray | None:
    """A fill-reducing nested-dissection ordering (METIS, through pymetis) of the graph with
    this symmetric adjacency pattern (n, n); None where pymetis is not installed."""
    try:
        import pymetis
    except ImportError:
        return None
    A = sp.csr_matrix(adjacency, copy=True)
    A.setdiag(0)
    A.eliminate_zeros()
    A.sort_indices()
    try:
        graph = pymetis.CSRAdjacency(A.indptr, A.indices)
    except AttributeError:  # pymetis before 2025
        graph = None
    if graph is None:
        perm, _ = pymetis.nested_dissection(xadj=A.indptr, adjncy=A.indices)
    else:
        perm, _ = pymetis.nested_dissection(graph)
    return np.asarray(perm, dtype=np.int64)


@functools.lru_cache(maxsize=1)
def _pardiso_solver_class():
    """pypardiso's ``PyPardisoSolver`` (Intel MKL PARDISO) where the ``pardiso`` extra installed it
    and MKL loads on this machine; else None. The library found is named to pypardiso through its
    ``PYPARDISO_MKL_RT`` variable (unless set already): each new solver otherwise searches for it
    again (``ctypes.util.find_library``, half a second)."""
    try:
        from pypardiso import PyPardisoSolver

        probe = PyPardisoSolver(mtype=2)
    except (ImportError, OSError):
        return None
    os.environ.setdefault("PYPARDISO_MKL_RT", probe.libmkl._name)
    return PyPardisoSolver


def sparse_backend() -> str:
    """The direct solver :class:`SymmetricFactor` uses on this installation."""
    return "pardiso" if _pardiso_solver_class() is not None else "superlu"


class SymmetricFactor:
    """Direct factorisation of a sparse symmetric matrix A (n, n), positive definite as a rule.

    With the ``pardiso`` extra (pypardiso, x86-64): Intel MKL PARDISO's supernodal LDL' in its
    own nested-dissection (METIS) order; on the resolved solver's reduced neo-Hookean tangents
    (15,000 unknowns, 2.4 M non-zeros: the nodal-pressure stencil couples two rings of tets) it
    factorises about three times faster than SuperLU on one thread (docs/fem.md, Speed).
    Without it: SuperLU's supernodal LU in symmetric mode, no pivoting, in the order A is given
    in (``ordered=True``: already fill-reducing) or in minimum degree on A' + A (``ordered``
    False). A tangent that is not positive definite (where the gel is crushed, the geometric
    stiffness can make it indefinite) is factorised by PARDISO's LDL' all the same (its
    Bunch-Kaufman pivoting) if no pivot needs perturbing, else by SuperLU's LU with partial
    pivoting; the SuperLU path switches to that LU on a zero pivot.

    ``solve(b)``: b (n,) or (n, k) float64 -> x of the same shape.
    ``backend``: ``"pardiso"``, ``"pardiso-indefinite"``, ``"superlu"`` or ``"superlu-pivoting"``.
    """

    def __init__(self, A: sp.spmatrix, ordered: bool = True, backend: str | None = None):
        if backend not in (None, "pardiso", "superlu"):
            raise ValueError(f"backend must be 'pardiso', 'superlu' or None (PARDISO where "
                             f"installed, else SuperLU), got {backend!r}")
        self.n = A.shape[0]
        self._pardiso = None
        self.negative_eigenvalues = None  # A's inertia, where PARDISO factorised it
        pardiso = _pardiso_solver_class() if backend in (None, "pardiso") else None
        if backend == "pardiso" and pardiso is None:
            raise RuntimeError("backend 'pardiso' needs pypardiso and Intel MKL: "
                               "pip install 'tactile-deploy[pardiso]' (x86-64 only)")
        if pardiso is not None:
            from pypardiso.pardiso_wrapper import PyPardisoError

            upper = sp.triu(A, format="csr")
            upper.sort_indices()
            # Real symmetric indefinite (matrix type -2): LDL' with Bunch-Kaufman pivoting, as
            # fast as its Cholesky on these tangents and no second attempt where one is
            # indefinite; kept if no pivot had to be perturbed (iparm 14).
            solver = pardiso(mtype=-2)
            try:
                solver.factorize(upper)
            except PyPardisoError:  # a structurally or numerically singular matrix
                pass
            else:
                if solver.get_iparm(14) == 0:
                    self._pardiso, self._upper = solver, upper
                    self.negative_eigenvalues = int(solver.get_iparm(23))
                    self.backend = ("pardiso" if self.negative_eigenvalues == 0
                                    else "pardiso-indefinite")
                    return
            solver.free_memory(everything=True)
            self._factor_superlu(sp.csc_matrix(A), ordered, pivoting=True)
            return
        self._factor_superlu(sp.csc_matrix(A), ordered)

    def _factor_superlu(self, A: sp.csc_matrix, ordered: bool, pivoting: bool = False) -> None:
        import scipy.sparse.linalg as spla

        if not pivoting:
            try:
                self._lu = spla.splu(A, permc_spec="NATURAL" if ordered else "MMD_AT_PLUS_A",
                                     diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
                self.backend = "superlu"
                return
            except RuntimeError:  # a zero pivot (an indefinite tangent)
                pass
        self._lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A")  # LU with partial pivoting
        self.backend = "superlu-pivoting"

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self._pardiso is not None:
            return self._pardiso.solve(self._upper, b)
        return self._lu.solve(b)

    def __del__(self):
        # PARDISO keeps its factors in MKL's memory until told to release them.
        if getattr(self, "_pardiso", None) is not None:
            try:
                self._pardiso.free_memory(everything=True)
            except Exception:  # pragma: no cover - interpreter shutdown
                pass
            self._pardiso = None
