"""Side-by-side comparison of the shading model with the two reference methods on ball presses.

One run: grouped k-fold cross-validation over presses (every press held out once), the same
folds, circles and evaluation for all three methods (:mod:`.evaluate`). With ``workers > 1``
the methods run in separate processes (spawned, so torch is never forked).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from tactile_deploy.imaging.shading import DepthFromShading

from .baselines import fit_mlp, fit_rgb_table
from .evaluate import PressResult, Summary, cross_validate, summarise
from .fit import ShadingFitConfig, fit_shading
from .presses import PressSet

#: Row names of the comparison table.
METHOD_NAMES = {
    "lut": "position-dependent binned LUT (this package)",
    "rgb_table": "reference: 3-D RGB-difference table",
    "mlp": "reference: per-pixel MLP (RGB + position)",
}


@dataclass
class MethodComparison:
    """Per-method held-out results, summaries and wall time of the cross-validation, s."""

    results: dict[str, list[PressResult]]
    summaries: dict[str, Summary]
    seconds: dict[str, float]


def method_fitters(ball_radius_mm: float, mm_per_px: float,
                   config: ShadingFitConfig | None = None, mlp_steps: int = 800):
    """{key: fitter} for :func:`.evaluate.cross_validate` (keys of :data:`METHOD_NAMES`)."""

    def lut(train: PressSet):
        fit = fit_shading(train, ball_radius_mm, mm_per_px, config)
        return DepthFromShading(fit.model, train.reference)

    def rgb_table(train: PressSet):
        return fit_rgb_table(train, ball_radius_mm, mm_per_px)

    def mlp(train: PressSet):
        return fit_mlp(train, ball_radius_mm, mm_per_px, steps=mlp_steps)

    return {"lut": lut, "rgb_table": rgb_table, "mlp": mlp}


def _run_method(key, presses, ball_radius_mm, mm_per_px, folds, config, mlp_steps):
    t0 = time.perf_counter()
    fitter = method_fitters(ball_radius_mm, mm_per_px, config, mlp_steps)[key]
    res = cross_validate(presses, fitter, ball_radius_mm, mm_per_px, folds)
    return res, time.perf_counter() - t0


def compare_methods(presses: PressSet, ball_radius_mm: float, mm_per_px: float,
                    folds: int = 7, methods=("lut", "rgb_table", "mlp"),
                    config: ShadingFitConfig | None = None,
                    mlp_steps: int = 800, workers: int = 1) -> MethodComparison:
    """Cross-validate each method on the same folds; results keyed by method.

    workers : processes to run the methods in (1: all in this process).
    """
    unknown = [m for m in methods if m not in METHOD_NAMES]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; known: {sorted(METHOD_NAMES)}")
    args = (presses, ball_radius_mm, mm_per_px, folds, config, mlp_steps)
    if workers > 1 and len(methods) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(min(workers, len(methods)),
                                 mp_context=mp.get_context("spawn")) as pool:
            futures = {key: pool.submit(_run_method, key, *args) for key in methods}
            done = {key: f.result() for key, f in futures.items()}
    else:
        done = {key: _run_method(key, *args) for key in methods}
    results = {key: done[key][0] for key in methods}
    seconds = {key: done[key][1] for key in methods}
    summaries = {key: summarise(results[key]) for key in methods}
    return MethodComparison(results, summaries, seconds)
