"""The library of candidate effects: what the workflow can name, and how each is fitted.

A candidate is a registered effect (:mod:`tactile_deploy.sensors.effects`) with the coordinates
the workflow fits (one or two), the parameter values its responses are tabulated at (three per
coordinate, spanning the effect's realistic range), the range a fit may reach, and how its
consequence on a depth map is simulated:

* ``"sensor"``: the sensor model with the effect added (or its parameter changed) reproduces the
  contact (FEM, effects stage by stage): mechanical and geometric effects;
* ``"view"``: an optics effect that changes the camera mapping: measured depth maps are made by
  an imaging pipeline calibrated on the nominal camera, so the map is seen through the changed
  view (:mod:`tactile_deploy.calibration.discrepancy.view_warp`); with measured frames the variant's own frame
  is imaged instead (:mod:`tactile_deploy.calibration.discrepancy.imaging`), exact.

Coordinates are the effect's parameters except for the tilt, fitted as its slope vector
``tan(angle) (cos azimuth, sin azimuth)`` (the residual is smooth in it, not in the azimuth).
Effects of the registry that are not candidates: ``compression_set`` (a dent at an unknown place:
four parameters; left out on purpose, the workflow reports it as unexplained), and the optics
effects that do not move features in a depth map made with the sensor's own reference frame
(``illumination_gradient``, ``saturation``, ``led_drift``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from tactile_deploy.sensors.effects import effect_class


@dataclass(frozen=True)
class Candidate:
    """One candidate effect.

    effect : registry name. coords : fitted coordinates. node_offsets : per coordinate the
    (lower, upper) offsets of the tabulated values from the current value (a lower node below the
    parameter's bound makes the nodes one-sided: current, +upper/2, +upper). fit_offsets : per
    coordinate the (lower, upper) range a fit may reach, from the current value. route : "sensor"
    or "view". needs_commanded : the effect moves the contact itself (not testable when contacts
    are estimated from the maps). needs_non_round : only indenters that are not bodies of
    revolution show it. signature : what it does to a depth map (for the report). nodes :
    tabulated values of a single coordinate (odd; more than 3 for responses that change shape
    quickly: interpolation then uses the 3 nearest). one_sided : the two tabulated values
    above the current one, as fractions of the upper offset, when the nodes are one-sided.
    """

    effect: str
    coords: tuple[str, ...]
    node_offsets: tuple[tuple[float, float], ...]
    fit_offsets: tuple[tuple[float, float], ...]
    route: Literal["sensor", "view"] = "sensor"
    needs_commanded: bool = False
    needs_non_round: bool = False
    signature: str = ""
    nodes: int = 3
    one_sided: tuple[float, float] = (0.5, 1.0)

    @property
    def name(self) -> str:
        return self.effect

    @property
    def fitted_params(self) -> tuple[str, ...]:
        """The effect parameters the fit sets (the rest keep their current values)."""
        return ("angle_deg", "azimuth_deg") if self.effect == "tilt" else self.coords

    @property
    def kind(self) -> str:
        return effect_class(self.effect).kind

    # ------------------------------------------------------------ coordinates <-> params
    def current(self, effects) -> dict[str, float]:
        """The effect's parameters in a sensor's effect list (null values when absent)."""
        cls = effect_class(self.effect)
        for e in effects:
            if e.name == self.effect:
                return cls.Params(**e.params).model_dump()
        return cls.Params().model_dump()

    def coords_of(self, params: dict[str, float]) -> np.ndarray:
        if self.effect == "tilt":
            t = math.tan(math.radians(params["angle_deg"]))
            a = math.radians(params["azimuth_deg"])
            return np.array([t * math.cos(a), t * math.sin(a)])
        return np.array([float(params[c]) for c in self.coords])

    def params_of(self, coords, current: dict[str, float]) -> dict[str, float]:
        """Effect parameters for fitted ``coords`` (other parameters kept from ``current``)."""
        c = np.asarray(coords, np.float64).ravel()
        out = dict(current)
        if self.effect == "tilt":
            out["angle_deg"] = math.degrees(math.atan(math.hypot(c[0], c[1])))
            out["azimuth_deg"] = math.degrees(math.atan2(c[1], c[0])) if c.any() else 0.0
            return out
        for name, v in zip(self.coords, c):
            out[name] = float(v)
        return out

    def _bounds(self, coord: str) -> tuple[float, float]:
        if self.effect == "tilt":
            return (-math.tan(math.radians(10.0)), math.tan(math.radians(10.0)))
        lo, hi = -math.inf, math.inf
        for m in effect_class(self.effect).Params.model_fields[coord].metadata:
            for attr in ("ge", "gt"):
                if hasattr(m, attr):
                    lo = getattr(m, attr)
            for attr in ("le", "lt"):
                if hasattr(m, attr):
                    hi = getattr(m, attr)
        return float(lo), float(hi)

    def axes(self, centre, limits: dict[str, tuple[float, float]] | None = None):
        """Per coordinate ``(nodes (3,), (fit_lo, fit_hi))``; ``limits`` narrows the bounds
        (e.g. the Poisson ratio's validated range)."""
        out = []
        for k, coord in enumerate(self.coords):
            c = float(centre[k])
            lo, hi = self._bounds(coord)
            if limits and coord in limits:
                lo, hi = max(lo, limits[coord][0]), min(hi, limits[coord][1])
            dn, up = self.node_offsets[k]
            if c + dn < lo - 1e-12:
                nodes = np.array([c, c + up * self.one_sided[0], c + up * self.one_sided[1]])
            elif self.nodes > 3 and len(self.coords) == 1:
                half = self.nodes // 2
                nodes = np.concatenate([c + dn * np.arange(half, 0, -1) / half, [c],
                                        c + up * np.arange(1, half + 1) / half])
            else:
                nodes = np.array([c + dn, c, c + up])
            nodes = np.clip(nodes, lo, hi)
            fl, fh = self.fit_offsets[k]
            out.append((nodes, (max(lo, c + fl), min(hi, c + fh))))
        return out


def lagrange_weights(nodes: np.ndarray, t) -> np.ndarray:
    """Quadratic Lagrange weights of 3 ``nodes`` at points ``t`` (m,) -> (m, 3)."""
    t = np.atleast_1d(np.asarray(t, np.float64))[:, None]
    x = np.asarray(nodes, np.float64)
    w = np.ones((t.shape[0], 3))
    for k in range(3):
        for j in range(3):
            if j != k:
                w[:, k] *= (t[:, 0] - x[j]) / (x[k] - x[j])
    return w


T2 = math.tan(math.radians(2.0))
T3 = math.tan(math.radians(3.0))

#: The candidate library (10 effects), in the order they are reported.
CANDIDATES: tuple[Candidate, ...] = (
    Candidate("zero_offset", ("offset_mm",), ((-0.05, 0.05),), ((-0.1, 0.1),),
              needs_commanded=True,
              signature="every contact deeper (or shallower) by the same amount"),
    Candidate("depth_scale", ("scale",), ((-0.05, 0.05),), ((-0.1, 0.1),), needs_commanded=True,
              signature="contacts deeper in proportion to the commanded depth"),
    Candidate("position_offset", ("dx_mm", "dy_mm"), ((-0.3, 0.3),) * 2, ((-0.5, 0.5),) * 2,
              needs_commanded=True,
              signature="a dipole across every contact, one direction for all"),
    Candidate("rotation_offset", ("dtheta_deg",), ((-6.0, 6.0),), ((-6.0, 6.0),),
              needs_commanded=True, needs_non_round=True, nodes=7,
              signature="edges and corners of non-round indenters turned by one angle"),
    Candidate("tilt", ("slope_x", "slope_y"), ((-T2, T2),) * 2, ((-T3, T3),) * 2,
              signature="a plane across each contact (one side deeper), slope the same for all"),
    Candidate("dome", ("height_mm",), ((-0.25, 0.5),), ((-0.5, 0.8),),
              signature="contacts shallower toward the rim, by the sag there"),
    # one-sided at 0.05 and 1: the small strength fixes the slope at the null value in a few
    # iterations, the large-deformation solve runs once at full strength per contact
    Candidate("hyperelastic", ("strength",), ((-0.5, 1.0),), ((-1.0, 1.5),),
              one_sided=(0.05, 1.0),
              signature="a gap growing about with the square of the depth (large-strain "
                        "stiffening)"),
    Candidate("poisson_drift", ("delta_nu",), ((-0.03, 0.01),), ((-0.045, 0.015),),
              signature="a ring outside each contact sinking more or less, growing with depth"),
    Candidate("lens_distortion", ("k1",), ((-0.15, 0.15),), ((-0.4, 0.2),), route="view",
              signature="features displaced radially from the image centre (cube of the radius)"),
    Candidate("pixel_scale", ("anisotropy",), ((-0.05, 0.05),), ((-0.08, 0.08),), route="view",
              signature="contacts squeezed along the image rows"),
)

for _c in CANDIDATES:
    if _c.effect == "tilt":
        continue
    _fields = effect_class(_c.effect).Params.model_fields
    if not set(_c.coords) <= set(_fields):
        raise RuntimeError(f"candidate {_c.effect}: coordinates {_c.coords} are not parameters")


def candidate_library(names=None) -> list[Candidate]:
    """The candidates (all, or those named), each a registered effect."""
    if names is None:
        return list(CANDIDATES)
    known = {c.name: c for c in CANDIDATES}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise KeyError(f"not candidates: {', '.join(unknown)}; the library has "
                       f"{', '.join(known)}")
    return [known[n] for n in names]
