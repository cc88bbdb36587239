"""Per-pixel weighted depth integration (tactile_deploy.calibration.shading.weighted_poisson)."""

import numpy as np
import pytest

from tactile_deploy.calibration.shading.weighted_poisson import integrate_weighted
from tactile_deploy.imaging.poisson import poisson_solver


@pytest.mark.parametrize("weights", [(1.0, 1.0), (0.05, 1.0), (3.0, 0.5)])
def test_equal_weights_reproduce_the_runtime_solver(weights):
    rng = np.random.default_rng(3)
    gc, gr = rng.normal(size=(2, 40, 57))
    z_runtime = poisson_solver((40, 57), "dirichlet", weights).integrate(gc, gr)
    z = integrate_weighted(gc, gr, np.full((40, 57), weights[0]), np.full((40, 57), weights[1]))
    assert np.abs(z - z_runtime).max() <= 1e-5 * np.abs(z_runtime).max()


def _bump(h=48, w=64):
    """A dimple of known depth (px units) and its analytic pixel-centred derivatives."""
    r, c = np.mgrid[0:h, 0:w].astype(float)
    s2 = 2 * 6.0 ** 2
    z = 5.0 * np.exp(-((c - 30) ** 2 + (r - 22) ** 2) / s2)
    return z, -2 * (c - 30) / s2 * z, -2 * (r - 22) / s2 * z


def test_low_weight_on_corrupted_gradients_recovers_the_surface():
    z, gc, gr = _bump()
    bad = np.zeros(z.shape, bool)
    bad[18:26, 24:30] = True               # wrong slopes on the dimple's flank
    gc_bad = np.where(bad, gc + 0.4, gc)
    clean = np.abs(integrate_weighted(gc, gr) - z).max()
    plain = np.abs(integrate_weighted(gc_bad, gr) - z).max()
    w = np.where(bad, 1e-4, 1.0)
    weighted = np.abs(integrate_weighted(gc_bad, gr, w, w) - z).max()
    assert plain > 10 * clean               # the corruption matters unweighted ...
    assert weighted < 3 * clean             # ... and hardly at all when weighted down
    assert weighted < plain / 5


def test_bad_weights_are_named():
    _, gc, gr = _bump(8, 9)
    with pytest.raises(ValueError, match="weight_row must be finite and > 0"):
        integrate_weighted(gc, gr, None, np.zeros((8, 9)))
    with pytest.raises(ValueError, match=r"weight_col has shape \(8, 8\), expected \(8, 9\)"):
        integrate_weighted(gc, gr, np.ones((8, 8)))
