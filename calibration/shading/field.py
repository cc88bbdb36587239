"""The whole field of view on ball presses: where each press lies, and its held-out figures under
several hold-out plans.

The shape error and fitted radius (:mod:`.evaluate`) of a press depend on where it lies: near the
image border the gel sunk around the ball reaches the border, and the illumination there differs
most from the middle (LEDs fade across the pad, channels clip earlier under a brighter
reference). A press counts as

* **corner**: its contact circle lies within ``CORNER_RADII`` contact radii of two image borders;
* **edge**: otherwise within ``EDGE_RADII`` contact radii of one border;
* **inside**: the rest.

Hold-out plans (every press judged by a model that never saw it; press numbers as in the file
names, 1-based):

* ``7-fold``: grouped 7-fold cross-validation, press i in fold i mod 7 (36 calibration presses per
  model, every press judged once);
* ``odd -> even`` / ``even -> odd``: calibrated on the odd- (even-) numbered presses, judged on
  the others (21 calibration presses: a stricter plan, as a user with fewer presses has).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .evaluate import MethodFitter, PressResult, cross_validate, press_result
from .presses import PressSet

#: Contact radii from two image borders within which a press counts as a corner press.
CORNER_RADII = 2.5
#: Contact radii from one image border within which a press counts as an edge press.
EDGE_RADII = 2.2


def press_places(circles, shape: tuple[int, int]) -> np.ndarray:
    """(N,) str: "corner", "edge" or "inside" for contact circles (N, 3) px in (H, W) images."""
    h, w = shape
    out = []
    for cx, cy, a in np.asarray(circles, np.float64):
        d = np.sort([cx / a, (w - 1 - cx) / a, cy / a, (h - 1 - cy) / a])
        out.append("corner" if d[1] < CORNER_RADII else "edge" if d[0] < EDGE_RADII else "inside")
    return np.array(out)


def press_numbers(presses: PressSet) -> np.ndarray:
    """(N,) int: the number in each press's file name (``0007.png`` -> 7), else its position + 1."""
    out = []
    for i, name in enumerate(presses.names):
        digits = "".join(ch for ch in name.rsplit(".", 1)[0] if ch.isdigit())
        out.append(int(digits) if digits else i + 1)
    return np.array(out)


@dataclass(frozen=True)
class PlanResult:
    """Held-out results of one plan: per judged press, in file order."""

    plan: str
    results: list[PressResult]
    calibration_presses: int


def held_out_plans(presses: PressSet, fitter: MethodFitter, ball_radius_mm: float,
                   mm_per_px: float, plans=("7-fold", "odd -> even", "even -> odd")
                   ) -> dict[str, PlanResult]:
    """Run the hold-out plans (module docstring) of one method; {plan: :class:`PlanResult`}."""
    numbers = press_numbers(presses)
    out = {}
    for plan in plans:
        if plan == "7-fold":
            res = cross_validate(presses, fitter, ball_radius_mm, mm_per_px, 7)
            out[plan] = PlanResult(plan, res, len(presses) - int(np.ceil(len(presses) / 7)))
            continue
        if plan not in ("odd -> even", "even -> odd"):
            raise ValueError(f"unknown plan {plan!r}")
        calib = numbers % 2 == (1 if plan.startswith("odd") else 0)
        predictor = fitter(presses.subset(calib))
        res = [press_result(presses.names[i], predictor.depth(presses.frames[i]),
                            presses.circles[i], presses.shape, mm_per_px, ball_radius_mm)
               for i in np.flatnonzero(~calib)]
        out[plan] = PlanResult(plan, res, int(calib.sum()))
    return out


def plan_summary(result: PlanResult, places: dict[str, str]) -> dict:
    """Mean / worst shape error (um), worst |fitted radius error| (fraction), the presses that
    miss the targets (shape > 40 um or radius off by more than 5 %), and per place the worst of
    each; ``places``: {press name: place}."""
    shape = np.array([r.shape_um for r in result.results])
    radius = np.array([r.radius_error for r in result.results])
    where = np.array([places[r.name] for r in result.results])
    by_place = {}
    for place in ("corner", "edge", "inside"):
        m = where == place
        if m.any():
            by_place[place] = {"n": int(m.sum()), "shape_mean_um": float(shape[m].mean()),
                               "shape_worst_um": float(shape[m].max()),
                               "radius_worst": float(np.abs(radius[m]).max())}
    misses = [r.name for r in result.results if r.shape_um > 40.0 or abs(r.radius_error) > 0.05]
    return {"n": len(shape), "shape_mean_um": float(shape.mean()),
            "shape_worst_um": float(shape.max()), "radius_worst": float(np.abs(radius).max()),
            "misses": misses, "by_place": by_place}
