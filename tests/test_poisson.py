"""Poisson integration (tactile_deploy.imaging.poisson) against independent references:
explicit sparse operators, a sparse least-squares solve, and analytic surfaces."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tactile_deploy.imaging.poisson import (
    PoissonSolver,
    edge_divergence,
    integrate_gradients,
    poisson_solver,
)


def _lap1d(n: int, boundary: str) -> sp.csr_matrix:
    """Second-difference matrix; Dirichlet at half a pixel outside (ghost = -value) or Neumann."""
    main = -2.0 * np.ones(n)
    if boundary == "dirichlet":
        main[[0, -1]] = -3.0
    else:
        main[[0, -1]] = -1.0
    return sp.diags([np.ones(n - 1), main, np.ones(n - 1)], [-1, 0, 1], format="csr")


def _laplacian(shape, boundary, weights):
    h, w = shape
    # row-major flattening: index = row * w + col
    lc = sp.kron(sp.identity(h), _lap1d(w, boundary))
    lr = sp.kron(_lap1d(h, boundary), sp.identity(w))
    return (weights[0] * lc + weights[1] * lr).tocsr()


@pytest.mark.parametrize("boundary", ["dirichlet", "neumann"])
@pytest.mark.parametrize("shape,weights", [((13, 17), (1.0, 1.0)), ((20, 9), (0.1, 1.0)),
                                           ((8, 8), (2.5, 0.7))])
def test_solve_divergence_inverts_explicit_laplacian(boundary, shape, weights):
    rng = np.random.default_rng(1)
    z = rng.standard_normal(shape)
    if boundary == "neumann":
        ring = np.zeros(shape, bool)
        ring[[0, -1], :] = ring[:, [0, -1]] = True
        z -= z[ring].mean()
    div = (_laplacian(shape, boundary, weights) @ z.ravel()).reshape(shape)
    got = PoissonSolver(shape, boundary, weights).solve_divergence(div)
    assert np.abs(got - z).max() < 1e-4 * np.abs(z).max()


def test_neumann_is_the_least_squares_surface():
    """Against scipy's sparse least squares on the edge-difference system of random gradients."""
    h, w = 11, 14
    rng = np.random.default_rng(2)
    gc = rng.standard_normal((h, w))
    gr = rng.standard_normal((h, w))
    wc, wr = 0.3, 1.0
    rows = []
    rhs = []
    idx = np.arange(h * w).reshape(h, w)
    for i in range(h):
        for j in range(w - 1):
            rows.append((np.sqrt(wc), idx[i, j + 1], idx[i, j]))
            rhs.append(np.sqrt(wc) * 0.5 * (gc[i, j] + gc[i, j + 1]))
    for i in range(h - 1):
        for j in range(w):
            rows.append((np.sqrt(wr), idx[i + 1, j], idx[i, j]))
            rhs.append(np.sqrt(wr) * 0.5 * (gr[i, j] + gr[i + 1, j]))
    data, ri, ci = [], [], []
    for k, (s, a, b) in enumerate(rows):
        data += [s, -s]
        ri += [k, k]
        ci += [a, b]
    a_mat = sp.csr_matrix((data, (ri, ci)), shape=(len(rows), h * w))
    ref = spla.lsqr(a_mat, np.array(rhs), atol=1e-14, btol=1e-14, iter_lim=20000)[0]
    ref = ref.reshape(h, w)
    got = PoissonSolver((h, w), "neumann", (wc, wr)).integrate(gc, gr)
    ring = np.zeros((h, w), bool)
    ring[[0, -1], :] = ring[:, [0, -1]] = True
    ref -= ref[ring].mean()
    assert np.abs(got - ref).max() < 1e-4


def _bump(n_rows, n_cols, sigma_frac=0.12):
    """Gaussian bump (negligible at the border) and its analytic derivatives per pixel."""
    r = np.arange(n_rows)[:, None] - (n_rows - 1) * 0.45
    c = np.arange(n_cols)[None, :] - (n_cols - 1) * 0.55
    s = sigma_frac * min(n_rows, n_cols)
    z = np.exp(-(r ** 2 + c ** 2) / (2 * s ** 2))
    return z, -c / s ** 2 * z, -r / s ** 2 * z


def test_dirichlet_recovers_analytic_surface_with_second_order_accuracy():
    errs = []
    for scale in (1, 2):
        z, dc, dr = _bump(40 * scale, 56 * scale)
        got = integrate_gradients(dc, dr, "dirichlet")
        errs.append(np.abs(got - z).max())
    assert errs[0] < 0.01          # 1 % of the bump height on a 40 x 56 grid
    assert errs[0] / errs[1] > 3.0  # halving the pixel size divides the error by ~4


def test_neumann_recovers_surface_up_to_the_border_level():
    """A tilted plane plus a bump: only the Neumann solve can hold a non-flat border."""
    h, w = 48, 64
    z, dc, dr = _bump(h, w)
    a, b = 0.02, -0.015
    rows, cols = np.mgrid[0:h, 0:w]
    z = z + a * cols + b * rows
    got = integrate_gradients(dc + a, dr + b, "neumann")
    ring = np.zeros((h, w), bool)
    ring[[0, -1], :] = ring[:, [0, -1]] = True
    assert np.abs(got - (z - z[ring].mean())).max() < 0.01
    flat = integrate_gradients(dc + a, dr + b, "dirichlet")
    assert np.abs(flat - z).max() > 0.1  # Dirichlet forces the tilted border to zero


def test_weights_favour_the_reliable_axis():
    """Column derivatives with a smooth error field: down-weighting them reduces the error."""
    h, w = 60, 60
    z, dc, dr = _bump(h, w)
    rows, cols = np.mgrid[0:h, 0:w]
    bad = dc + 0.01 * np.sin(2 * np.pi * rows / h) * np.sin(np.pi * cols / w)
    iso = np.abs(integrate_gradients(bad, dr, "dirichlet", (1.0, 1.0)) - z).max()
    aniso = np.abs(integrate_gradients(bad, dr, "dirichlet", (0.05, 1.0)) - z).max()
    assert aniso < 0.5 * iso


def test_edge_divergence_matches_hand_computation():
    gc = np.array([[1.0, 3.0, 5.0]], np.float32)
    gr = np.zeros_like(gc)
    # edges: [0, 2, 4, 0] -> div = [2, 2, -4]
    assert np.allclose(edge_divergence(gc, gr), [[2.0, 2.0, -4.0]])


def test_solver_cache_and_input_errors():
    assert poisson_solver((16, 16)) is poisson_solver((16, 16))
    assert poisson_solver((16, 16), "neumann") is not poisson_solver((16, 16))
    with pytest.raises(ValueError, match="shape"):
        PoissonSolver((1, 5))
    with pytest.raises(ValueError, match="boundary"):
        PoissonSolver((4, 4), "periodic")
    with pytest.raises(ValueError, match="weights"):
        PoissonSolver((4, 4), weights=(0.0, 1.0))
    with pytest.raises(ValueError, match=r"d_row has shape \(4, 5\), expected \(4, 4\)"):
        integrate_gradients(np.zeros((4, 4)), np.zeros((4, 5)))
    with pytest.raises(ValueError, match="2-D"):
        integrate_gradients(np.zeros(4), np.zeros(4))


def test_margin_is_the_least_squares_surface_on_the_padded_grid():
    """A margin of m pixels: the explicit Dirichlet system on the grid grown by m pixels on each
    side, with zero derivatives there, solved by scipy and cut back to the image."""
    h, w, m = 9, 12, 4
    rng = np.random.default_rng(5)
    gc = rng.standard_normal((h, w))
    gr = rng.standard_normal((h, w))
    weights = (0.2, 1.0)
    div = edge_divergence(np.pad(gc, m), np.pad(gr, m), weights).astype(np.float64)
    ref = spla.spsolve(_laplacian((h + 2 * m, w + 2 * m), "dirichlet", weights).tocsc(),
                       div.ravel()).reshape(h + 2 * m, w + 2 * m)[m:-m, m:-m]
    got = PoissonSolver((h, w), "dirichlet", weights, margin=m).integrate(gc, gr)
    assert got.shape == (h, w)
    assert np.abs(got - ref).max() < 1e-4 * np.abs(ref).max()
    assert poisson_solver((h, w), "dirichlet", weights, m) is poisson_solver((h, w), "dirichlet",
                                                                            weights, m)
    with pytest.raises(ValueError, match="margin must be a whole number"):
        PoissonSolver((h, w), margin=-1)


def test_margin_keeps_a_surface_that_is_still_deep_at_the_border():
    """An analytic bump centred 6 px inside the image's corner (a press near the corner whose
    surroundings are still sunk at the border): with the boundary half a pixel outside the image
    the bump is flattened towards the border; a margin draws the border towards zero instead of
    holding it there (the bump's continuation outside the image is unknown, so it softens the
    error rather than removing it: 0.117 -> 0.077 of the bump's height with 24 px, measured)."""
    h, w, s = 60, 48, 9.0
    rows, cols = np.mgrid[0:h, 0:w]
    r0, c0 = h - 7.0, 6.0
    z = np.exp(-((rows - r0) ** 2 + (cols - c0) ** 2) / (2 * s ** 2))
    dc, dr = -(cols - c0) / s ** 2 * z, -(rows - r0) / s ** 2 * z
    core = np.hypot(rows - r0, cols - c0) < s

    def shape_error(depth):     # RMS inside the bump's core after removing the mean offset
        e = (depth - z)[core]
        return np.sqrt(np.mean((e - e.mean()) ** 2))

    tight = shape_error(PoissonSolver((h, w), "dirichlet").integrate(dc, dr))
    wide = shape_error(PoissonSolver((h, w), "dirichlet", margin=24).integrate(dc, dr))
    assert tight > 0.1                  # 10 % of the bump's height lost to the zero border
    assert wide < 0.7 * tight
