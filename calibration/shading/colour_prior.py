"""Smooth prior of the shading table: depth gradient as a polynomial in binned colour and position.

The binned table (:func:`.fit.fit_table`) has one entry per colour bin and position node. Where
the slopes are steep, the training colours are spread thin over the three-dimensional colour
space: on the virtual GelSlim (24 presses, 32 bins per channel) a contact-edge pixel's bin holds
0-3 samples, and those come from presses 6-10 mm away, where the LEDs (point lights beside the
gel) light the same slope in another colour. A table that falls back to the bin's mean over the
whole image then returns the slope of another place. This prior is a fallback that knows the
place: one polynomial of the colour (cubic in the three binned channel differences, plus an
indicator per saturated channel) whose coefficients are quadratic in image position, fitted by
ridge-regularised least squares to all training samples; the table blends it with the samples
of each (node, bin) entry (see :func:`.fit.fit_table`).

Colour coordinates are bin indices (``(bins + 1) ** 3`` flat, R-major, the last bin of each channel
for saturated values) mapped to ``[-1, 1]`` per channel; a saturated channel's coordinate is 0
and its indicator 1. Positions are image columns and rows (px) mapped to ``[-1, 1]``. Targets
and predictions are gradients of depth along image columns and rows (mm per mm).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations_with_replacement

import numpy as np


def _colour_monomials(x: np.ndarray, degree: int) -> list[np.ndarray]:
    """1 and every monomial of the columns of ``x`` (N, 3) up to ``degree``."""
    out = [np.ones(len(x))]
    for d in range(1, degree + 1):
        for comb in combinations_with_replacement(range(x.shape[1]), d):
            out.append(np.prod(x[:, list(comb)], axis=1))
    return out


def _position_terms(cols, rows, shape: tuple[int, int], degree: int) -> np.ndarray:
    """(N, 1 | 3 | 6) position basis: 1, u, v (degree >= 1), u^2, uv, v^2 (degree 2)."""
    h, w = shape
    u = np.asarray(cols, np.float64) / max(w - 1, 1) * 2.0 - 1.0
    v = np.asarray(rows, np.float64) / max(h - 1, 1) * 2.0 - 1.0
    terms = [np.ones_like(u)]
    if degree >= 1:
        terms += [u, v]
    if degree >= 2:
        terms += [u * u, u * v, v * v]
    return np.stack(terms, 1)


@dataclass(frozen=True)
class ColourPolynomial:
    """Gradient (2,) = polynomial(colour bin) with coefficients polynomial in image position.

    shape : (H, W) image size, px. bins : colour bins per channel (the saturated bin is
    ``bins``). coef : (n_colour_terms * n_position_terms, 2).
    """

    shape: tuple[int, int]
    bins: int
    colour_degree: int
    position_degree: int
    coef: np.ndarray

    @staticmethod
    def colour_terms(bin_coords, bins: int, colour_degree: int) -> np.ndarray:
        """(N, n_colour_terms) colour basis of bin coordinates (N, 3) int."""
        q = np.asarray(bin_coords)
        sat = q == bins
        x = np.where(sat, 0.0, (q + 0.5) / (bins / 2.0) - 1.0)
        return np.stack(_colour_monomials(x, colour_degree)
                        + [sat[:, k].astype(np.float64) for k in range(3)], 1)

    @classmethod
    def design(cls, bin_coords, cols, rows, shape, bins: int, colour_degree: int,
               position_degree: int) -> np.ndarray:
        """Design matrix (N, F) of bin coordinates (N, 3) int at pixels (cols, rows) (N,)."""
        colour = cls.colour_terms(bin_coords, bins, colour_degree)
        pos = _position_terms(cols, rows, shape, position_degree)
        return (colour[:, :, None] * pos[:, None, :]).reshape(len(colour), -1)

    @classmethod
    def fit(cls, keys, targets, cols, rows, shape: tuple[int, int], bins: int,
            weights=None, colour_degree: int = 3, position_degree: int = 2,
            ridge: float = 1e-3) -> ColourPolynomial:
        """Weighted least squares on samples: flat bin indices ``keys`` (S,), gradient
        ``targets`` (S, 2), pixel positions (S,); ``ridge`` x (total weight) on the diagonal."""
        nb = bins + 1
        q = np.stack(np.unravel_index(np.asarray(keys), (nb, nb, nb)), -1)
        w = np.ones(len(q)) if weights is None else np.asarray(weights, np.float64)
        a = cls.design(q, cols, rows, shape, bins, colour_degree, position_degree)
        aw = a * w[:, None]
        normal = a.T @ aw + ridge * float(w.sum()) * np.eye(a.shape[1])
        coef = np.linalg.solve(normal, aw.T @ np.asarray(targets, np.float64))
        return cls(tuple(shape), bins, colour_degree, position_degree, coef)

    def predict(self, keys, cols, rows) -> np.ndarray:
        """Gradients (N, 2) of flat bin indices (N,) at pixels (cols, rows) (N,)."""
        nb = self.bins + 1
        q = np.stack(np.unravel_index(np.asarray(keys), (nb, nb, nb)), -1)
        a = self.design(q, cols, rows, self.shape, self.bins, self.colour_degree,
                        self.position_degree)
        return a @ self.coef

    def at_nodes(self, keys, node_cols, node_rows) -> np.ndarray:
        """(n_nodes, len(keys), 2): the prediction for every bin in ``keys`` at every node
        (node positions in px, any shape, flattened)."""
        nb = self.bins + 1
        q = np.stack(np.unravel_index(np.asarray(keys), (nb, nb, nb)), -1)
        colour = self.colour_terms(q, self.bins, self.colour_degree)        # (K, C)
        pos = _position_terms(np.ravel(node_cols), np.ravel(node_rows), self.shape,
                              self.position_degree)                          # (nodes, P)
        coef = self.coef.reshape(colour.shape[1], pos.shape[1], 2)
        per_node = np.einsum("clk,nl->nck", coef, pos)                        # (nodes, C, 2)
        return np.einsum("sc,nck->nsk", colour, per_node)
