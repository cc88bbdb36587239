"""Effects: named, parametrised departures of a virtual sensor from the nominal model.

An effect is one small module of this package: a subclass of :class:`Effect` with

* ``name`` (registry key), ``kind`` ("mechanical" or "optical") and ``stage`` (where it acts);
* ``Params``: a pydantic model of its parameters, units in the names, whose defaults are the
  **null values**: with them the effect does nothing and the sensor is exactly the nominal one;
* ``realistic_range``: the range of each parameter seen in real sensors (documentation, and the
  discrepancy workflow's priors);
* a docstring stating the physics, the residual it leaves (what it does not model) and the
  realistic range;
* one or more of the hooks below, each the identity by default.

Stages and hooks, in the order the virtual sensor applies them (:mod:`tactile_deploy.sensors.
virtual`)::

    geometry  rest_height_mm(xy)           rest shape of the sensing surface (sensor frame, mm)
    contact   contact_pose(pose)           the pose the indenter really reaches
              intrusion_mm(delta, xy, pose) the indenter's intrusion below z = 0 at points
    material  correct_contact(sim, delta, result)  the FEM solution (e.g. large-strain terms)
    optics    optics(model)                the optics model's parameters
              view_points(xy, camera)      (depth maps) the pad point a map made through a
                                           pipeline calibrated on ``camera`` shows at xy
    camera    frame_gain(renderer, rng)    per-frame multiplicative change of the radiance
    readout   readout_map(depth, xy)       the depth map a sensor's depth pipeline reports

Effects are registered by name (:mod:`tactile_deploy.sensors.effects`) and built from JSON as
``{"name": ..., "params": {...}}``.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

Stage = Literal["geometry", "contact", "material", "optics", "camera", "readout"]
Kind = Literal["mechanical", "optical"]


class EffectParams(BaseModel):
    """Base of every effect's parameters: strict, frozen, finite; defaults are the null values."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Effect:
    """Base class of an effect (see the module docstring)."""

    name: ClassVar[str] = ""
    kind: ClassVar[Kind] = "mechanical"
    stage: ClassVar[Stage] = "geometry"
    Params: ClassVar[type[EffectParams]] = EffectParams
    #: parameter name -> (low, high) seen in real sensors, in the parameter's unit
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {}

    def __init__(self, params: EffectParams | dict | None = None, **kwargs):
        if params is None:
            params = self.Params(**kwargs)
        elif isinstance(params, dict):
            params = self.Params(**params, **kwargs)
        elif kwargs:
            raise TypeError("give the parameters either as a Params object or as keywords")
        if not isinstance(params, self.Params):
            raise TypeError(f"effect {self.name!r} takes {self.Params.__name__}, got "
                            f"{type(params).__name__}")
        self.params = params

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r})"

    @property
    def is_null(self) -> bool:
        """True when every parameter has its null value (the effect does nothing)."""
        return self.params == self.Params()

    def spec(self) -> dict:
        """``{"name": ..., "params": {...}}``: the JSON form of this effect."""
        return {"name": self.name, "params": self.params.model_dump()}

    @classmethod
    def prepare(cls, simulator) -> None:
        """Build what this effect's solves need on ``simulator`` now (e.g. before forking
        worker processes that share it); nothing by default."""

    # ----------------------------------------------------------------- hooks (identity)
    def rest_height_mm(self, xy_mm: np.ndarray) -> np.ndarray:
        """Change of the rest height of the sensing surface at sensor points (k, 2) -> (k,) mm."""
        return np.zeros(len(xy_mm))

    def contact_pose(self, pose):
        """The pose the indenter actually reaches for a commanded ``pose``."""
        return pose

    def intrusion_mm(self, delta_mm: np.ndarray, xy_mm: np.ndarray, pose) -> np.ndarray:
        """The indenter's intrusion below z = 0 (k,) mm at sensor points (k, 2), for ``pose``."""
        return delta_mm

    def correct_contact(self, simulator, delta_mm: np.ndarray, result):
        """The contact solution after this effect (a ``ContactResult``)."""
        return result

    def optics(self, model):
        """The optics model after this effect."""
        return model

    def frame_gain(self, renderer, rng: np.random.Generator | None):
        """Per-frame multiplicative gain of the radiance: None (no change), a (3,) per-channel
        gain or an (H, W, 3) / (H, W, 1) map, dimensionless."""
        return None  # noqa: RET501 (the hook's documented "no change")

    # optics effects that move features: how a depth map made through a pipeline calibrated on
    # the nominal camera sees them (:mod:`tactile_deploy.sensors.depth_view`)
    #: True for optics effects that change where the camera sees the pad (they define
    #: :meth:`view_points`).
    moves_view: ClassVar[bool] = False

    def view_points(self, xy_mm: np.ndarray, camera) -> np.ndarray:
        """Sensor-plane points (k, 2) mm that a depth map made by a pipeline calibrated on the
        nominal ``camera`` (a ``CameraMapping``) shows at the plane points ``xy_mm`` (k, 2) when
        this effect is present; identity by default."""
        return np.asarray(xy_mm, np.float64)

    @property
    def depth_gain_exponent(self) -> float:
        """How a depth map's values follow the view's local stretch ``J = dq/dp``: they are
        multiplied by ``det(J) ** (-exponent / 2)`` (1: a pipeline that integrates measured
        slopes over the calibrated grid; 0: the map resampled, values unchanged)."""
        return float(getattr(self.params, "depth_gain_exponent", 0.0))

    def readout_map(self, depth_mm: np.ndarray, xy_mm: np.ndarray) -> np.ndarray:
        """The depth map (H, W) mm a sensor's depth pipeline reports for the surface's map
        ``depth_mm`` (H, W) mm, pixel centres ``xy_mm`` (H, W, 2) sensor frame; identity."""
        return depth_mm
