"""How well a shading method reconstructs depth: sphere fits on ball presses, grouped
cross-validation, and depth error against known depth maps.

Shape and scale of a reconstructed press (depth map in mm, positive into the gel):

* **shape error**: RMS residual (um) after fitting the sphere of the ball's known radius, with
  its centre (x, y) and vertical offset free, to the depth inside ``0.8 x`` the contact radius;
* **fitted radius**: the same fit with the radius free too, compared with the ball's radius.

Absolute depth cannot be judged on real presses (hand-labelled circles are good to 2-3 px and
1 px of contact radius moves the implied cap depth by ~0.1 mm); :func:`depth_errors` takes any
frames with known depth maps (virtual-sensor presses, synthetic renders).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.optimize import least_squares

from .presses import PressSet


class DepthPredictor(Protocol):
    def depth(self, frame) -> np.ndarray: ...


#: A method: fitted on presses (and their circles, px), returns a predictor for new frames.
MethodFitter = Callable[[PressSet], DepthPredictor]


@dataclass(frozen=True)
class SphereFit:
    """Sphere fitted to a depth map (sensor-plane lengths in mm, image-axis offsets).

    rms_um : RMS residual, um. radius_mm : sphere radius (fixed or fitted), mm.
    centre_px : (column, row) of the sphere's axis, px. apex_mm : depth at the centre, mm.
    n_pixels : pixels used.
    """

    rms_um: float
    radius_mm: float
    centre_px: tuple[float, float]
    apex_mm: float
    n_pixels: int


#: Fewest pixels inside the fit region for a sphere fit.
MIN_FIT_PIXELS = 10


def fit_region(shape, circle, region_fraction: float = 0.8):
    """(rows, cols, mask) of an image of ``shape`` (H, W): pixel indices (H, W) and the pixels
    within ``region_fraction`` of ``circle`` (column, row, contact radius; px), where
    :func:`fit_sphere` fits."""
    h, w = shape
    cx, cy, a = (float(v) for v in circle)
    rows, cols = np.mgrid[0:h, 0:w]
    return rows, cols, np.hypot(cols - cx, rows - cy) < region_fraction * a


def fit_sphere(depth_mm, circle, mm_per_px: float, radius_mm: float | None = None,
               region_fraction: float = 0.8) -> SphereFit:
    """Fit depth = apex - (R - sqrt(R^2 - rho^2)) inside ``region_fraction`` of ``circle``.

    depth_mm : (H, W) depth, mm. circle : (column, row, contact radius) px; its centre starts
    the fit and its radius sets the region. radius_mm : the known sphere radius (fixed), or
    None to fit it.
    """
    depth_mm = np.asarray(depth_mm, np.float64)
    cx, cy, a = (float(v) for v in circle)
    rows, cols, m = fit_region(depth_mm.shape, circle, region_fraction)
    if m.sum() < MIN_FIT_PIXELS:
        raise ValueError(f"circle {circle} leaves {int(m.sum())} pixels inside the image")
    x = (cols[m] - cx) * mm_per_px
    y = (rows[m] - cy) * mm_per_px
    z = depth_mm[m]
    free_r = radius_mm is None
    r0 = float(radius_mm) if radius_mm is not None else max(2.0 * a * mm_per_px, 1e-3)

    def unpack(p):
        return p[0], p[1], p[2], (p[3] if free_r else r0)

    def fun(p):
        x0, y0, apex, r = unpack(p)
        rho2 = (x - x0) ** 2 + (y - y0) ** 2
        q = np.sqrt(np.maximum(r * r - rho2, 1e-12))
        return apex - (r - q) - z

    def jac(p):
        x0, y0, _, r = unpack(p)
        rho2 = (x - x0) ** 2 + (y - y0) ** 2
        q = np.sqrt(np.maximum(r * r - rho2, 1e-12))
        cols_ = [(x - x0) / q, (y - y0) / q, np.ones_like(x)]
        if free_r:
            cols_.append(r / q - 1.0)
        return np.stack(cols_, 1)

    p0 = [0.0, 0.0, float(z.max())] + ([r0] if free_r else [])
    if free_r:
        rmax = np.sqrt(x ** 2 + y ** 2).max()
        lower = [-np.inf, -np.inf, -np.inf, 1.05 * rmax]
        p0[3] = max(p0[3], 1.2 * rmax)
        bounds = (lower, [np.inf] * 4)
    else:
        bounds = (-np.inf, np.inf)
    sol = least_squares(fun, p0, jac=jac, bounds=bounds, x_scale="jac")
    x0, y0, apex, r = unpack(sol.x)
    return SphereFit(float(np.sqrt(np.mean(sol.fun ** 2)) * 1e3), float(r),
                     (cx + x0 / mm_per_px, cy + y0 / mm_per_px), float(apex), int(m.sum()))


@dataclass(frozen=True)
class PressResult:
    """Held-out figures of one press: shape error (um), fitted radius (mm) and its relative
    error, distance of the circle centre from the image centre (px)."""

    name: str
    shape_um: float
    radius_mm: float
    radius_error: float
    centre_distance_px: float


def press_result(name, depth_mm, circle, shape, mm_per_px, ball_radius_mm) -> PressResult:
    """Shape error and fitted radius of one reconstructed press."""
    known = fit_sphere(depth_mm, circle, mm_per_px, ball_radius_mm)
    free = fit_sphere(depth_mm, circle, mm_per_px, None)
    h, w = shape
    dist = float(np.hypot(circle[0] - (w - 1) / 2.0, circle[1] - (h - 1) / 2.0))
    return PressResult(name, known.rms_um, free.radius_mm, free.radius_mm / ball_radius_mm - 1,
                       dist)


def cross_validate(presses: PressSet, fitter: MethodFitter, ball_radius_mm: float,
                   mm_per_px: float, folds: int = 7, eval_circles=None) -> list[PressResult]:
    """Grouped k-fold over presses: every press is held out once (press i in fold i mod k).

    fitter : trains on a :class:`PressSet` subset (with its circles) and returns a predictor.
    eval_circles : (N, 3) px circles whose radius sets the evaluation region (default: the
        presses' own circles).
    """
    if presses.circles is None and eval_circles is None:
        raise ValueError("cross-validation needs circles (labels) for the evaluation regions")
    circ = np.asarray(presses.circles if eval_circles is None else eval_circles, np.float64)
    n = len(presses)
    if not 2 <= folds <= n:
        raise ValueError(f"folds must lie in [2, {n}], got {folds}")
    fold = np.arange(n) % folds
    out: list[PressResult | None] = [None] * n
    for k in range(folds):
        predictor = fitter(presses.subset(fold != k))
        for i in np.flatnonzero(fold == k):
            depth = predictor.depth(presses.frames[i])
            out[i] = press_result(presses.names[i], depth, circ[i], presses.shape, mm_per_px,
                                  ball_radius_mm)
    return out  # type: ignore[return-value]


@dataclass(frozen=True)
class Summary:
    """Summary of held-out press results (um for shape; fractions for radius errors)."""

    shape_mean_um: float
    shape_worst_um: float
    radius_error_mean: float
    radius_error_worst: float          # largest |relative error|
    radius_error_centre: float         # mean over the half of presses nearest the image centre
    radius_error_edge: float           # mean over the half farthest from it
    radius_error_worst_edge: float     # largest |relative error| in the edge half
    n: int


def summarise(results: list[PressResult]) -> Summary:
    """Mean and worst figures, and the centre-vs-edge split (by circle distance, median)."""
    shape = np.array([r.shape_um for r in results])
    rerr = np.array([r.radius_error for r in results])
    dist = np.array([r.centre_distance_px for r in results])
    order = np.argsort(dist, kind="stable")
    half = len(results) // 2
    centre, edge = order[:half], order[half:]
    return Summary(float(shape.mean()), float(shape.max()), float(rerr.mean()),
                   float(np.abs(rerr).max()), float(rerr[centre].mean()),
                   float(rerr[edge].mean()), float(np.abs(rerr[edge]).max()), len(results))


def markdown_table(summaries: dict[str, Summary]) -> str:
    """The comparison table (one row per method) as GitHub markdown."""
    lines = [("| method | shape error mean (um) | shape error worst (um) | fitted radius error "
              "mean | worst abs | centre half mean | edge half mean | edge half worst abs |"),
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, s in summaries.items():
        lines.append(f"| {name} | {s.shape_mean_um:.1f} | {s.shape_worst_um:.1f} | "
                     f"{100 * s.radius_error_mean:+.1f} % | {100 * s.radius_error_worst:.1f} % | "
                     f"{100 * s.radius_error_centre:+.1f} % | {100 * s.radius_error_edge:+.1f} % | "
                     f"{100 * s.radius_error_worst_edge:.1f} % |")
    return "\n".join(lines)


def depth_errors(predictor: DepthPredictor, frames, depths_mm, mask=None) -> np.ndarray:
    """RMS depth error (um) of each frame against its known depth map (mm).

    frames : (N, H, W, 3) uint8 RGB. depths_mm : (N, H, W) true depth, mm. mask : optional
    (N, H, W) or (H, W) bool, pixels to score (default: all).
    """
    depths_mm = np.asarray(depths_mm, np.float64)
    if len(frames) != len(depths_mm):
        raise ValueError(f"{len(frames)} frames but {len(depths_mm)} depth maps")
    out = []
    for i, f in enumerate(frames):
        d = predictor.depth(f)
        if d.shape != depths_mm[i].shape:
            raise ValueError(f"frame {i}: depth map {d.shape} vs known depth {depths_mm[i].shape}")
        m = np.ones(d.shape, bool) if mask is None else np.asarray(mask, bool)
        if m.ndim == 3:
            m = m[i]
        out.append(np.sqrt(np.mean((d[m] - depths_mm[i][m]) ** 2)) * 1e3)
    return np.array(out)
