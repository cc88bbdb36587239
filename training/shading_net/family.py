"""A family of virtual units of one sensor design: the design's optics with each LED's place
and brightness, the specular lobes and the ambient light drawn within assembly tolerances, and
a frame-to-frame LED drift (the ``led_drift`` effect) of its own.

The camera is the design's: the read-out works on each unit's rectified imaging grid, so a
unit's own lens and mounting are taken out by its camera mapping before the network sees it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tolerances:
    """Half-widths of the uniform draws around the design (mm, relative factors)."""

    led_xy_mm: float = 1.5           # LED position in the sensor plane
    led_z_mm: float = 0.5            # LED height
    led_brightness: float = 0.15     # colour of each LED, x U(1 - b, 1 + b) per channel
    specular: float = 0.3            # specular lobe strength, x U(1 - s, 1 + s)
    ambient: float = 0.15            # ambient light, x U(1 - a, 1 + a) per channel
    led_drift: float = 0.03          # frame-to-frame LED drift (relative sigma) up to this


def family_configs(design: str, n_units: int, rng: np.random.Generator,
                   tolerances: Tolerances = Tolerances()) -> list:
    """``n_units`` :class:`~tactile_deploy.sensors.config.VirtualSensorConfig` of the design
    ``design`` (a virtual sensor name), each with its optics drawn within ``tolerances``."""
    from tactile_deploy.sensors.catalog import sensor_config
    from tactile_deploy.sensors.config import VirtualSensorConfig

    base = sensor_config(design)
    t = tolerances
    out = []
    for u in range(n_units):
        lights = []
        for lt in base.optics.lights:
            update = {"colour_grey": tuple(float(c * rng.uniform(1 - t.led_brightness, 1 + t.led_brightness))
                                           for c in lt.colour_grey),
                      "specular_grey": tuple(float(c * rng.uniform(1 - t.specular, 1 + t.specular))
                                             for c in lt.specular_grey)}
            if lt.kind == "point":
                p = np.asarray(lt.position_mm, float) + np.r_[rng.uniform(-t.led_xy_mm, t.led_xy_mm, 2),
                                                              rng.uniform(-t.led_z_mm, t.led_z_mm)]
                update["position_mm"] = tuple(float(v) for v in p)
            lights.append(lt.model_copy(update=update))
        ambient = tuple(float(a * rng.uniform(1 - t.ambient, 1 + t.ambient))
                        for a in base.optics.ambient_grey)
        doc = base.model_dump(mode="json")
        doc["name"] = f"{design}-family-{u}"
        doc["optics"]["lights"] = [lt.model_dump(mode="json") for lt in lights]
        doc["optics"]["ambient_grey"] = list(ambient)
        doc["effects"] = [e for e in doc["effects"] if e["name"] != "led_drift"] + [
            {"name": "led_drift", "params": {"sigma_rel": float(rng.uniform(0.0, t.led_drift))}}]
        out.append(VirtualSensorConfig.model_validate(doc))
    return out
