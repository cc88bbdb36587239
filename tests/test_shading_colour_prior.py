"""The shading table's colour-polynomial fallback (calibration/shading/colour_prior.py).

Truth is planted: gradients made by a known polynomial of the colour bin whose coefficients vary
over the image, as point-like LEDs beside the gel make them vary.
"""

from __future__ import annotations

import numpy as np
import pytest

from tactile_deploy.calibration.shading.colour_prior import ColourPolynomial
from tactile_deploy.calibration.shading.fit import fit_table

BINS = 16
SHAPE = (60, 90)           # (H, W) px
NB = BINS + 1


def _keys(q):
    return np.ravel_multi_index(np.asarray(q).T, (NB, NB, NB))


def _planted(q, cols, rows):
    """A position-dependent colour-to-gradient relation (N, 2): the colour axes turn and scale
    across the image, as a light beside the gel lights the same slope differently."""
    x = (np.asarray(q, float) + 0.5) / (BINS / 2.0) - 1.0
    u = cols / (SHAPE[1] - 1) * 2.0 - 1.0
    v = rows / (SHAPE[0] - 1) * 2.0 - 1.0
    g_col = (0.4 + 0.2 * u) * x[:, 0] - 0.1 * x[:, 1] + 0.05 * u * v * x[:, 2] + 0.1 * x[:, 0] ** 3
    g_row = 0.3 * x[:, 1] * (1.0 - 0.3 * v) + 0.2 * x[:, 2] * u - 0.05 * x[:, 0] * x[:, 1]
    return np.stack([g_col, g_row], 1)


def test_polynomial_recovers_a_planted_relation():
    """Noise-free samples of a planted cubic-in-colour, quadratic-in-position relation: the fit
    reproduces it on new bins and places, and the per-node evaluation agrees with the direct one."""
    rng = np.random.default_rng(3)
    n = 4000
    q = rng.integers(0, BINS, (n, 3))
    cols, rows = rng.uniform(0, SHAPE[1] - 1, n), rng.uniform(0, SHAPE[0] - 1, n)
    poly = ColourPolynomial.fit(_keys(q), _planted(q, cols, rows), cols, rows, SHAPE, BINS,
                                ridge=1e-12)
    q_new = rng.integers(0, BINS, (500, 3))
    c_new, r_new = rng.uniform(0, SHAPE[1] - 1, 500), rng.uniform(0, SHAPE[0] - 1, 500)
    np.testing.assert_allclose(poly.predict(_keys(q_new), c_new, r_new),
                               _planted(q_new, c_new, r_new), atol=1e-6)
    node_c, node_r = np.meshgrid([0.0, 30.0, 89.0], [0.0, 59.0])
    at = poly.at_nodes(_keys(q_new[:20]), node_c, node_r)
    assert at.shape == (6, 20, 2)
    for k, (c, r) in enumerate(zip(node_c.ravel(), node_r.ravel())):
        np.testing.assert_allclose(at[k], poly.predict(_keys(q_new[:20]), np.full(20, c),
                                                       np.full(20, r)), atol=1e-9)


def test_saturated_channel_has_its_own_term():
    """A saturated channel (bin ``BINS``) is not read as the brightest unsaturated colour: its
    indicator carries its own gradient."""
    rng = np.random.default_rng(4)
    n = 3000
    q = rng.integers(0, BINS + 1, (n, 3))
    cols, rows = rng.uniform(0, SHAPE[1] - 1, n), rng.uniform(0, SHAPE[0] - 1, n)
    target = np.where((q[:, 0] == BINS)[:, None], [[0.7, -0.2]], [[0.0, 0.0]])
    poly = ColourPolynomial.fit(_keys(q), target, cols, rows, SHAPE, BINS, ridge=1e-12)
    probe = np.array([[BINS, 3, 5], [BINS - 1, 3, 5]])
    pred = poly.predict(_keys(probe), np.array([40.0, 40.0]), np.array([30.0, 30.0]))
    np.testing.assert_allclose(pred[0], [0.7, -0.2], atol=1e-6)
    np.testing.assert_allclose(pred[1], [0.0, 0.0], atol=1e-6)


@pytest.fixture(scope="module")
def sparse_bins():
    """Samples of the planted relation: bins 4-13 per channel everywhere, and one steep bin
    (channel 0 one step beyond) seen only on the left of the image, as a contact edge's colour
    is seen in few presses."""
    rng = np.random.default_rng(5)
    q = rng.integers(4, 14, (6000, 3))
    cols = rng.uniform(0, SHAPE[1] - 1, 6000)
    rows = rng.uniform(0, SHAPE[0] - 1, 6000)
    steep = np.array([[14, 8, 8]])
    q = np.concatenate([q, np.repeat(steep, 40, 0)])
    cols = np.concatenate([cols, rng.uniform(0, 15, 40)])
    rows = np.concatenate([rows, rng.uniform(0, SHAPE[0] - 1, 40)])
    return _keys(q), _planted(q, cols, rows), cols, rows, steep


def test_table_falls_back_to_the_place_not_the_image_mean(sparse_bins):
    """At a node on the right, where the steep bin was never seen, the image-mean fallback
    returns the left side's gradient; the colour-polynomial fallback returns the right side's."""
    keys, targets, cols, rows, steep = sparse_bins
    spacing = 15.0
    poly = ColourPolynomial.fit(keys, targets, cols, rows, SHAPE, BINS)
    node_col = 90.0                                        # the rightmost node column
    truth = _planted(steep, np.array([node_col]), np.array([30.0]))[0]
    left = _planted(steep, np.array([7.5]), np.array([30.0]))[0]
    assert np.abs(truth - left).max() > 0.1                # the place matters
    values = {}
    for name, prior in (("image-mean", None), ("colour-polynomial", poly)):
        slot_of_bin, table = fit_table(keys, targets, cols, rows, SHAPE, spacing, 5.0, BINS,
                                       1.0, None, prior)
        node = (2, int(node_col / spacing))                # row 30 px, column 90 px
        values[name] = table[node[0], node[1], slot_of_bin[_keys(steep)[0]]]
    np.testing.assert_allclose(values["colour-polynomial"], truth, atol=0.02)
    np.testing.assert_allclose(values["image-mean"], left, atol=0.1)
    assert np.abs(values["image-mean"] - truth).max() > 0.1


def test_unknown_fallback_is_refused():
    """A misspelt fallback names the setting and the accepted values."""
    from tactile_deploy.calibration.shading.fit import ShadingFitConfig, fit_shading
    from tactile_deploy.calibration.shading.presses import PressSet

    rng = np.random.default_rng(6)
    ref = rng.integers(90, 160, (40, 50, 3)).astype(np.uint8)
    frames = np.stack([ref, ref])
    presses = PressSet(ref, frames, ["a.png", "b.png"], np.array([[20, 20, 5.0], [30, 20, 5.0]]))
    with pytest.raises(ValueError, match="prior_model must be 'image-mean' or "
                                         "'colour-polynomial', got 'colour'"):
        fit_shading(presses, 1.0, 0.05, ShadingFitConfig(prior_model="colour"))
