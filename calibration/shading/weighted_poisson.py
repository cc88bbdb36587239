"""Depth from gradients with a weight per pixel: weighted least-squares integration (sparse direct).

The runtime integrates with one weight per axis (:mod:`tactile_deploy.imaging.poisson`, sine
transforms). Where the reliability of the gradients varies from pixel to pixel (a colour that
determines the slope poorly), a weight per pixel and axis lets the integration lean on the
reliable ones:

    minimise  sum over column edges  wc_e (z[i, j+1] - z[i, j] - e_col)^2
            + sum over row edges     wr_e (z[i+1, j] - z[i, j] - e_row)^2

with the edge targets ``e`` the mean of the two adjacent pixels' derivatives (0 on the image
border) and the edge weights the harmonic mean of the two pixels' weights (one unreliable pixel
makes its edges unreliable). The border is the runtime's: depth 0 half a pixel outside the image,
and with equal weights the result is the runtime solver's (to rounding).

This module is an analysis tool of the calibration (:mod:`.virtual_check` measures with it what
per-pixel weights could gain at best); it solves one sparse system per call (about 20 ms for
64 x 90 pixels), too slow and too weight-specific for the runtime.

Units: derivatives in units of z per pixel along image columns and rows, as in
:mod:`tactile_deploy.imaging.poisson`; weights dimensionless, > 0; the result has the units of z.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.sparse
import scipy.sparse.linalg


@lru_cache(maxsize=8)
def _difference_operators(h: int, w: int):
    """Sparse (edges, pixels) forward differences along columns and rows, each edge row
    ``z[k] - z[k-1]``; the border edges hold ``2 z`` (the ghost pixel outside is ``-z``)."""
    def along(n: int):
        k = np.arange(1, n)
        rows = np.r_[0, k, k, n]
        cols = np.r_[0, k - 1, k, n - 1]
        vals = np.r_[2.0, -np.ones(n - 1), np.ones(n - 1), -2.0]
        return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(n + 1, n))

    d_col = scipy.sparse.kron(scipy.sparse.eye(h), along(w)).tocsr()   # (h (w+1), h w)
    d_row = scipy.sparse.kron(along(h), scipy.sparse.eye(w)).tocsr()   # ((h+1) w, h w)
    return d_col, d_row


def _edge_weights(weight: np.ndarray, axis: int) -> np.ndarray:
    """Per-edge weights along ``axis`` (1: columns, 0: rows) of per-pixel weights (H, W):
    harmonic mean inside, the border pixel's weight / 2 on the border edges (so that equal
    weights give the runtime solver's boundary condition)."""
    a = np.moveaxis(weight, axis, 0)
    inner = 2.0 * a[1:] * a[:-1] / (a[1:] + a[:-1])
    out = np.concatenate([0.5 * a[:1], inner, 0.5 * a[-1:]], 0)
    return np.moveaxis(out, 0, axis)


def integrate_weighted(d_col, d_row, weight_col=None, weight_row=None) -> np.ndarray:
    """Surface z (H, W) float64 whose derivatives best match ``d_col``, ``d_row`` (z per px,
    (H, W) each) in the least squares weighted per pixel by ``weight_col``, ``weight_row``
    ((H, W), > 0; None: 1); z = 0 half a pixel outside the image (module docstring)."""
    gc = np.asarray(d_col, np.float64)
    gr = np.asarray(d_row, np.float64)
    if gc.ndim != 2 or gc.shape != gr.shape or min(gc.shape) < 2:
        raise ValueError(f"d_col and d_row must be (H, W) arrays of one shape, H, W >= 2; got "
                         f"{gc.shape} and {gr.shape}")
    h, w = gc.shape
    weights = []
    for name, wt in (("weight_col", weight_col), ("weight_row", weight_row)):
        wt = np.ones((h, w)) if wt is None else np.asarray(wt, np.float64)
        if wt.shape != (h, w):
            raise ValueError(f"{name} has shape {wt.shape}, expected {(h, w)}")
        if not np.all(np.isfinite(wt)) or not np.all(wt > 0):
            raise ValueError(f"{name} must be finite and > 0 everywhere (smallest "
                             f"{float(np.nanmin(wt)):.3g}); give unreliable pixels a small "
                             "positive weight instead of 0")
        weights.append(wt)
    e_col = np.zeros((h, w + 1))
    e_col[:, 1:-1] = 0.5 * (gc[:, 1:] + gc[:, :-1])
    e_row = np.zeros((h + 1, w))
    e_row[1:-1] = 0.5 * (gr[1:] + gr[:-1])
    w_col = _edge_weights(weights[0], 1).ravel()
    w_row = _edge_weights(weights[1], 0).ravel()
    dc, dr = _difference_operators(h, w)
    a = (dc.T @ scipy.sparse.diags(w_col) @ dc + dr.T @ scipy.sparse.diags(w_row) @ dr)
    b = dc.T @ (w_col * e_col.ravel()) + dr.T @ (w_row * e_row.ravel())
    return scipy.sparse.linalg.spsolve(a.tocsc(), b).reshape(h, w)
