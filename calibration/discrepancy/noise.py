"""The pixel noise of measured depth maps, from the maps themselves.

White noise of standard deviation sigma gives the 5-point Laplacian ``4 r(i, j) - r(i +- 1, j) -
r(i, j +- 1)`` a standard deviation of ``sqrt(20) sigma``, while a residual that is smooth at the
pixel scale (every effect of the library away from contact edges) contributes almost nothing to
it. The median absolute Laplacian over the pad's interior pixels (those whose four neighbours are
on the pad) is robust to the few pixels where the residual bends sharply:
``sigma = 1.4826 median|L| / sqrt(20)``. Its standard error comes from a bootstrap over samples.

Assumption: the noise is white (independent from pixel to pixel). Depth maps integrated from
shading gradients have correlated noise: for measured frames the noise comes instead from
realisations of the model's own imaged maps (:func:`noise_from_realisations`), or give it
(``noise_mm`` in the measured data).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_erosion

MAD_TO_SIGMA = 1.4826
#: Smallest noise the statistics use, mm (float32 depth maps near 1 mm resolve ~1e-7 mm).
NOISE_FLOOR_MM = 1e-6


@dataclass(frozen=True)
class NoiseEstimate:
    """sigma_mm : pixel noise (one sigma), mm; se_mm : its standard error; source : how;
    energy_factor : variance of the residual's squared sum over its white-noise value
    ``2 sigma^4 pixels`` (1 for white noise; larger when neighbouring pixels' noise is
    correlated: fewer independent values)."""

    sigma_mm: float
    se_mm: float
    source: str
    energy_factor: float = 1.0


def estimate_noise(residual_mm: np.ndarray, pad_mask: np.ndarray, seed: int = 0,
                   bootstrap: int = 50) -> NoiseEstimate:
    """Noise of the maps from their residuals ``residual_mm`` (N, H, W) mm (measured minus
    simulated: the Laplacian of a smooth simulation adds nothing), on ``pad_mask`` (H, W)."""
    r = np.asarray(residual_mm, np.float64)
    interior = binary_erosion(pad_mask, iterations=1)
    lap = (4.0 * r[:, 1:-1, 1:-1] - r[:, :-2, 1:-1] - r[:, 2:, 1:-1] - r[:, 1:-1, :-2]
           - r[:, 1:-1, 2:])
    vals = np.abs(lap[:, interior[1:-1, 1:-1]])  # (N, k)

    def sigma(rows):
        return MAD_TO_SIGMA * float(np.median(vals[rows])) / np.sqrt(20.0)

    n = len(vals)
    s = sigma(np.arange(n))
    rng = np.random.default_rng(seed)
    boots = [sigma(rng.integers(n, size=n)) for _ in range(bootstrap if n > 1 else 0)]
    se = float(np.std(boots)) if boots else 0.0
    return NoiseEstimate(max(s, NOISE_FLOOR_MM), se, "median absolute Laplacian of the residual "
                         f"over {vals.size:,} pad pixels")


def known_noise(sigma_mm: float) -> NoiseEstimate:
    """A pixel noise given with the data."""
    return NoiseEstimate(max(float(sigma_mm), NOISE_FLOOR_MM), 0.0, "given with the data")


def noise_from_realisations(noise_energy: np.ndarray, dof: np.ndarray, seed: int = 0,
                            bootstrap: int = 50) -> NoiseEstimate:
    """The noise of imaged maps from realisations of it: ``noise_energy`` (N, J) squared sums
    (mm^2) of J noise realisations on each sample's ROI (its nuisance projected out), ``dof``
    (N,) their degrees of freedom. sigma^2 is the mean energy per degree of freedom; the
    energy factor compares the realisations' spread with white noise's."""
    e = np.asarray(noise_energy, np.float64)
    dof = np.asarray(dof, np.float64)
    n, j = e.shape

    def sigma2(rows):
        return float(e[rows].mean(axis=1).sum() / max(dof[rows].sum(), 1.0))

    s2 = sigma2(np.arange(n))
    rng = np.random.default_rng(seed)
    boots = [np.sqrt(sigma2(rng.integers(n, size=n))) for _ in range(bootstrap if n > 1 else 0)]
    se = float(np.std(boots)) if boots else 0.0
    var = float(e.var(axis=1, ddof=1).sum()) if j > 1 else 0.0
    factor = max(var / max(2.0 * s2**2 * dof.sum(), 1e-300), 1.0)
    return NoiseEstimate(max(math.sqrt(s2), NOISE_FLOOR_MM), se,
                         f"the model's imaged maps under {j} camera-noise draws per contact "
                         f"(correlated: {factor:.0f}x the white-noise variance of the squared "
                         "residual)", factor)
