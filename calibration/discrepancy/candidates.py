"""The library of candidate effects: what the workflow can name, and how each is fitted.

A candidate is a registered effect (:mod:`tactile_deploy.sensors.effects`) with the coordinates
the workflow fits, the values its responses are first tabulated at (around the sensor model's
current value, spanning the effect's realistic range), the range a fit may reach from there,
and what a change of it costs to simulate (``route``):

* ``"fem"``: the sensor model with the effect added (or its parameter changed) reproduces the
  contact with the linear FEM (tens of ms a contact): geometry, contact and material effects;
* ``"nonlinear"``: the same with a large-deformation or friction solve (seconds a contact);
* ``"view"``: an optics effect that moves where the camera sees the pad: depth maps made through
  the sensor's calibrated pipeline see the surface through the changed view
  (:mod:`tactile_deploy.sensors.depth_view`); measured frames are the variant's own frames
  through the pipeline (:mod:`tactile_deploy.calibration.discrepancy.imaging`). Both reuse the contact's FEM
  solution;
* ``"readout"``: a departure of the depth pipeline itself (a gain across the field, blur,
  saturated shading), applied to the map.

**Coordinates.** Most are effect parameters; three effects are fitted in coordinates in which
their maps change smoothly: the tilt as its slope vector ``tan(angle) (cos az, sin az)``; the
pixel scale as ``(scale, anisotropy cos 2(axis - 90), anisotropy sin 2(axis - 90))`` (an
anisotropy of either sign along any image direction; the chart takes anisotropy >= 0 and folds
the rest into the scale). Coordinates in ``refine_coords`` have no effect where the primary
ones are null (a distortion's centre, the depth-gain exponent of a view) or pin down the shape
only once the effect is found (a dome's apex): they join the fit when the candidate's table is
re-centred on a fit away from the null value (:mod:`tactile_deploy.calibration.discrepancy.tables`).
``fixed`` parameters are those the first tabulation uses instead of the effect's defaults
(the views' depth-gain exponent half-way between a resampled map and an integrating pipeline).

Effects of the registry that are not candidates: ``compression_set`` (a dent at an unknown place:
four parameters; left out on purpose, the workflow reports it as unexplained), and the optics
effects that do not move features in a depth map made with the sensor's own reference frame
(``illumination_gradient``, ``saturation``, ``led_drift``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from tactile_deploy.sensors.effects import effect_class

Route = Literal["fem", "nonlinear", "view", "readout"]


@dataclass(frozen=True)
class Candidate:
    """One candidate effect.

    effect : registry name. coords : coordinates of the first tabulation. node_offsets : per
    coordinate the (lower, upper) offsets of the tabulated values from the current value (a lower
    node below the coordinate's bound makes the nodes one-sided: current, +upper/2, +upper).
    fit_offsets : per coordinate the (lower, upper) range a fit may reach from the current value.
    route : see the module docstring. refine_coords : coordinates added when the table is
    re-centred, with their node offsets and fit half-ranges. frames_refine : whether they are
    fitted with measured frames too (False: the frames render the effect without them, or each
    of their values would cost seven imaged maps a contact per round: a dome's apex stays at
    the model's value with frames). fixed :
    parameter values of the first tabulation (instead of the defaults). needs_commanded : the
    effect moves the contact itself. needs_non_round : only indenters that are not bodies of
    revolution show it. signature : what it does to a depth map (for the report). nodes :
    tabulated values of a single coordinate (odd; more than 3 for responses that change shape
    quickly: interpolation then uses the 3 nearest). one_sided : the two tabulated values above
    the current one, as fractions of the upper offset, when the nodes are one-sided.
    """

    effect: str
    coords: tuple[str, ...]
    node_offsets: tuple[tuple[float, float], ...]
    fit_offsets: tuple[tuple[float, float], ...]
    route: Route = "fem"
    refine_coords: tuple[str, ...] = ()
    refine_offsets: tuple[float, ...] = ()
    refine_fit: tuple[float, ...] = ()
    frames_refine: bool = True
    fixed: dict = field(default_factory=dict)
    needs_commanded: bool = False
    needs_non_round: bool = False
    signature: str = ""
    nodes: int = 3
    one_sided: tuple[float, float] = (0.5, 1.0)

    @property
    def name(self) -> str:
        return self.effect

    @property
    def kind(self) -> str:
        return effect_class(self.effect).kind

    @property
    def cheap(self) -> bool:
        """Its maps reuse the contact's FEM solution (or a linear one): refinement is cheap."""
        return self.route in ("view", "readout")

    def all_coords(self, frames: bool = False) -> tuple[str, ...]:
        """Coordinates of a re-centred table."""
        if frames and not self.frames_refine:
            return self.coords
        return self.coords + self.refine_coords

    def fitted_params(self, names: tuple[str, ...]) -> tuple[str, ...]:
        """The effect parameters a fit of coordinates ``names`` sets."""
        out = []
        for n in names:
            out += list(_PARAMS_OF_COORD.get((self.effect, n), (n,)))
        return tuple(dict.fromkeys(out))

    # ------------------------------------------------------------ coordinates <-> params
    def current(self, effects) -> dict[str, float]:
        """The effect's parameters in a sensor's effect list (null values and this candidate's
        ``fixed`` values when absent)."""
        cls = effect_class(self.effect)
        for e in effects:
            if e.name == self.effect:
                return cls.Params(**e.params).model_dump()
        return cls.Params(**self.fixed).model_dump()

    def coords_of(self, params: dict[str, float], names: tuple[str, ...] | None = None
                  ) -> np.ndarray:
        """Coordinates ``names`` (default: the first tabulation's) of effect parameters."""
        names = names or self.coords
        if self.effect == "tilt":
            t = math.tan(math.radians(params["angle_deg"]))
            a = math.radians(params["azimuth_deg"])
            derived = {"slope_x": t * math.cos(a), "slope_y": t * math.sin(a)}
        elif self.effect == "pixel_scale":
            derived = _pixel_scale_coords(params)
        else:
            derived = {}
        return np.array([float(derived[n] if n in derived else params[n]) for n in names])

    def params_of(self, coords, current: dict[str, float],
                  names: tuple[str, ...] | None = None) -> dict[str, float]:
        """Effect parameters for fitted ``coords`` of ``names`` (other parameters kept from
        ``current``)."""
        names = names or self.coords
        c = dict(zip(names, np.asarray(coords, np.float64).ravel().tolist()))
        out = dict(current)
        if self.effect == "tilt":
            sx, sy = c.pop("slope_x"), c.pop("slope_y")
            out["angle_deg"] = math.degrees(math.atan(math.hypot(sx, sy)))
            out["azimuth_deg"] = math.degrees(math.atan2(sy, sx)) if (sx or sy) else 0.0
        elif self.effect == "pixel_scale":
            cur = _pixel_scale_coords(current)
            s = c.pop("scale", cur["scale"])
            a1, a2 = c.pop("aniso_c", cur["aniso_c"]), c.pop("aniso_s", cur["aniso_s"])
            out.update(_pixel_scale_params(s, a1, a2))
        for n, v in c.items():
            out[n] = float(v)
        return out

    def bounds(self, coord: str) -> tuple[float, float]:
        """The coordinate's hard bounds (the effect parameter's validated range)."""
        if self.effect == "tilt":
            return (-math.tan(math.radians(10.0)), math.tan(math.radians(10.0)))
        if self.effect == "pixel_scale" and coord in ("aniso_c", "aniso_s"):
            return (-0.25, 0.25)
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
        """Per first-tabulation coordinate ``(nodes, (fit_lo, fit_hi))``; ``limits`` narrows
        the bounds (e.g. the Poisson ratio's validated range)."""
        out = []
        for k, coord in enumerate(self.coords):
            c = float(centre[k])
            lo, hi = self.limited_bounds(coord, limits)
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

    def limited_bounds(self, coord: str, limits=None) -> tuple[float, float]:
        lo, hi = self.bounds(coord)
        if limits and coord in limits:
            lo, hi = max(lo, limits[coord][0]), min(hi, limits[coord][1])
        return lo, hi

    def step(self, coord: str) -> float:
        """Node offset of a coordinate in a re-centred table before any shrinking."""
        if coord in self.coords:
            dn, up = self.node_offsets[self.coords.index(coord)]
            return 0.5 * (abs(dn) + abs(up)) if dn < 0 else 0.5 * abs(up)
        return self.refine_offsets[self.refine_coords.index(coord)]

    def reach(self, coord: str) -> float:
        """How far a fit of a re-centred table may move in one round."""
        if coord in self.coords:
            fl, fh = self.fit_offsets[self.coords.index(coord)]
            return max(abs(fl), abs(fh))
        return self.refine_fit[self.refine_coords.index(coord)]


#: Effect parameters set by non-parameter coordinates.
_PARAMS_OF_COORD = {
    ("tilt", "slope_x"): ("angle_deg", "azimuth_deg"),
    ("tilt", "slope_y"): ("angle_deg", "azimuth_deg"),
    ("pixel_scale", "aniso_c"): ("anisotropy", "axis_deg"),
    ("pixel_scale", "aniso_s"): ("anisotropy", "axis_deg"),
}


def _pixel_scale_coords(params: dict) -> dict:
    """(scale, aniso_c, aniso_s) of pixel-scale parameters: ``(1 + scale)(I + a n n^T)``
    written with a >= 0 (a < 0 along n is a' = -a / (1 + a) along the perpendicular, the scale
    times 1 + a)."""
    s, a, axis = float(params["scale"]), float(params["anisotropy"]), float(params["axis_deg"])
    if a < 0:
        s, a, axis = (1.0 + s) * (1.0 + a) - 1.0, -a / (1.0 + a), axis + 90.0
    t = math.radians(2.0 * (axis - 90.0))
    return {"scale": s, "aniso_c": a * math.cos(t), "aniso_s": a * math.sin(t)}


def _pixel_scale_params(scale: float, a1: float, a2: float) -> dict:
    a = math.hypot(a1, a2)
    axis = 90.0 + 0.5 * math.degrees(math.atan2(a2, a1)) if a > 0 else 90.0
    return {"scale": float(scale), "anisotropy": float(a), "axis_deg": float(axis)}


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

#: The candidate library, in the order they are reported.
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
              refine_coords=("centre_x_mm", "centre_y_mm"), refine_offsets=(1.5, 1.5),
              refine_fit=(4.0, 4.0), frames_refine=False,
              signature="contacts shallower (domed gel) or deeper (dished) toward the rim, by "
                        "the sag there"),
    # one-sided at 0.05 and 1: the small strength fixes the slope at the null value in a few
    # iterations, the large-deformation solve runs once at full strength per contact
    Candidate("hyperelastic", ("strength",), ((-0.5, 1.0),), ((-1.0, 1.5),), route="nonlinear",
              one_sided=(0.05, 1.0),
              signature="a gap growing about with the square of the depth (large-strain "
                        "stiffening)"),
    Candidate("friction", ("mu",), ((-1.0, 1.0),), ((0.0, 3.0),), route="nonlinear",
              signature="the gel held back from spreading under the contact: contacts pushed "
                        "in more uniformly, sharper edges, more force"),
    Candidate("poisson_drift", ("delta_nu",), ((-0.03, 0.01),), ((-0.045, 0.015),),
              signature="a ring outside each contact sinking more or less, growing with depth"),
    Candidate("lens_distortion", ("k1",), ((-0.15, 0.15),), ((-0.4, 0.4),), route="view",
              refine_coords=("centre_dx_px", "centre_dy_px", "depth_gain_exponent"),
              refine_offsets=(15.0, 15.0, 0.5), refine_fit=(60.0, 60.0, 1.0),
              frames_refine=False, fixed={"depth_gain_exponent": 0.5},
              signature="features displaced radially from a centre (cube of the radius)"),
    Candidate("pixel_scale", ("scale", "aniso_c", "aniso_s"), ((-0.05, 0.05),) * 3,
              ((-0.1, 0.1),) * 3, route="view",
              refine_coords=("depth_gain_exponent",), refine_offsets=(0.5,), refine_fit=(1.0,),
              frames_refine=False, fixed={"depth_gain_exponent": 0.5},
              signature="contacts larger or smaller, squeezed along one image direction"),
    Candidate("gain_gradient", ("gain", "gain_per_mm_x", "gain_per_mm_y"),
              ((-0.1, 0.1), (-0.02, 0.02), (-0.02, 0.02)),
              ((-0.3, 0.3), (-0.05, 0.05), (-0.05, 0.05)), route="readout",
              signature="the map scaled by a gain that changes across the pad"),
    Candidate("blur", ("sigma_mm",), ((-0.3, 0.3),), ((0.0, 0.8),), route="readout",
              signature="contact edges and peaks smoothed (the map's Laplacian)"),
    Candidate("shading_saturation", ("inverse_max_slope",), ((-2.0, 2.0),), ((0.0, 6.0),),
              route="readout",
              signature="steep slopes read as a limit slope: sharp or deep contacts shallower"),
)

for _c in CANDIDATES:
    _fields = effect_class(_c.effect).Params.model_fields
    _names = [n for n in _c.coords + _c.refine_coords
              if (_c.effect, n) not in _PARAMS_OF_COORD and not (
                  _c.effect == "pixel_scale" and n == "scale")]
    if not set(_names) <= set(_fields) or not set(_c.fixed) <= set(_fields):
        raise RuntimeError(f"candidate {_c.effect}: coordinates {_c.coords + _c.refine_coords} "
                           "are not parameters")
    if not (len(_c.refine_coords) == len(_c.refine_offsets) == len(_c.refine_fit)):
        raise RuntimeError(f"candidate {_c.effect}: refine_coords, refine_offsets and "
                           "refine_fit differ in length")


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
