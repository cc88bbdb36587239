"""The free parameters of an optics model: names such as ``lights.*.azimuth_deg`` resolved to
paths into the model, their values as one vector, and their bounds."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from tactile_deploy.optics.model import Light, OpticsModel, Vignetting


class OpticsFitError(ValueError):
    """Fit data or parameter names are not usable (the message says which and why)."""

_VECTOR_FIELDS = {"colour_grey": 3, "specular_grey": 3, "position_mm": 3}

_BOUNDS = {
    "azimuth_deg": (-math.inf, math.inf), "elevation_deg": (1.0, 89.0),
    "colour_grey": (0.0, 2000.0), "specular_grey": (0.0, 2000.0), "shininess": (1.0, 500.0),
    "falloff_per_mm": (0.0, 2.0), "position_mm": (-100.0, 100.0), "ambient_grey": (0.0, 255.0),
    "k2": (-1.0, 1.0), "k4": (-1.0, 1.0), "exposure_gain": (0.01, 10.0),
}

def _listify(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

def _model_doc(model: OpticsModel) -> dict:
    return {
        "lights": [_listify(lt.model_dump()) for lt in model.lights],
        "ambient_grey": list(model.ambient_grey),
        "vignetting": model.vignetting.model_dump(),
        "exposure_gain": model.exposure_gain,
    }

def parameter_paths(model: OpticsModel, names: Sequence[str]) -> list[tuple]:
    """Expand parameter names into scalar paths.

    Names: ``ambient_grey``, ``exposure_gain``, ``vignetting.k2``, ``vignetting.k4``,
    ``lights.<i>.<field>`` or ``lights.*.<field>`` with field one of azimuth_deg, elevation_deg,
    colour_grey, specular_grey, shininess, falloff_per_mm, position_mm (vectors expand to their
    components). Returns paths such as ``("lights", 0, "colour_grey", 2)``.
    """
    doc = _model_doc(model)
    out: list[tuple] = []
    for name in names:
        parts = name.split(".")
        if parts[0] == "lights" and len(parts) == 3:
            idx = range(len(model.lights)) if parts[1] == "*" else [int(parts[1])]
            for i in idx:
                if not 0 <= i < len(model.lights) or parts[2] not in doc["lights"][i]:
                    raise OpticsFitError(f"unknown optics parameter {name!r}")
                n = _VECTOR_FIELDS.get(parts[2], 0)
                out += [("lights", i, parts[2], c) for c in range(n)] if n else [
                    ("lights", i, parts[2])]
        elif name == "ambient_grey":
            out += [("ambient_grey", c) for c in range(3)]
        elif name in ("vignetting.k2", "vignetting.k4"):
            out.append(("vignetting", parts[1]))
        elif name == "exposure_gain":
            out.append(("exposure_gain",))
        else:
            raise OpticsFitError(
                f"unknown optics parameter {name!r}; use ambient_grey, exposure_gain, "
                "vignetting.k2, vignetting.k4 or lights.<i|*>.<field>")
    return out

def _get(doc, path):
    node = doc
    for key in path:
        node = node[key]
    return float(node)

def _set(doc, path, value):
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = float(value)

def parameter_vector(model: OpticsModel, paths: Sequence[tuple]) -> np.ndarray:
    """Current values of ``paths`` (see :func:`parameter_paths`), (p,) float64."""
    doc = _model_doc(model)
    return np.array([_get(doc, p) for p in paths])

def with_parameters(model: OpticsModel, paths: Sequence[tuple], values, validate: bool = False
                    ) -> OpticsModel:
    """A copy of ``model`` with ``paths`` set to ``values`` (validated when ``validate``)."""
    doc = _model_doc(model)
    for p, v in zip(paths, values):
        _set(doc, p, v)
    if validate:
        full = model.model_dump()
        full.update(lights=doc["lights"], ambient_grey=doc["ambient_grey"],
                    vignetting=doc["vignetting"], exposure_gain=doc["exposure_gain"])
        full["camera"] = model.camera  # already validated
        return OpticsModel.model_validate(full)
    tup = {k: tuple(v) if isinstance(v, list) else v for k, v in doc.items()}
    lights = tuple(Light.model_construct(**{k: tuple(v) if isinstance(v, list) else v
                                            for k, v in ld.items()}) for ld in doc["lights"])
    return model.model_copy(update={
        "lights": lights, "ambient_grey": tup["ambient_grey"],
        "vignetting": Vignetting.model_construct(**doc["vignetting"]),
        "exposure_gain": doc["exposure_gain"]})

def parameter_bounds(paths: Sequence[tuple]) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = [], []
    for p in paths:
        key = p[2] if p[0] == "lights" else (p[1] if p[0] == "vignetting" else p[0])
        b = _BOUNDS[key]
        if key == "position_mm" and p[3] == 2:
            b = (-100.0, -0.1)  # point lights stay below the sensing surface
        lo.append(b[0])
        hi.append(b[1])
    return np.array(lo), np.array(hi)

def normalise_model(model: OpticsModel) -> OpticsModel:
    """Azimuths wrapped into [0, 360) degrees (the fit leaves them unbounded); validated."""
    lights = tuple(lt.model_copy(update={"azimuth_deg": float(lt.azimuth_deg % 360.0)})
                   for lt in model.lights)
    doc = model.model_dump()
    doc["lights"] = [lt.model_dump() for lt in lights]
    doc["camera"] = model.camera
    return OpticsModel.model_validate(doc)
