"""Shipped virtual sensors, by name: ``tactile_deploy/assets/sensors/<name>.json``.

* ``gelslim1``: a GelSlim-class unit, 640 x 480 px at 30 fps, wide-angle lens (barrel
  distortion, slightly oblique view), three RGB LEDs at the rim (near point lights), the nominal
  mechanics (no effects).
* ``gelslim2``: a second unit of the same design, differing as two builds do: LEDs placed a few
  degrees and millimetres off with other brightnesses, another lens and camera placement, more
  noise, a 0.03 mm zero offset of the pressing axis, a 0.8 degree mounting tilt and LED drift.
* ``gelsight_fots``: a GelSight-class sensor of a different character, its optics fitted to real
  ball presses (``python -m tactile_deploy.calibration.optics_fit``): portrait 240 x 320 px at 19.58 px/mm,
  directional lights, a domed gel and over-exposure.

:func:`list_sensors` names them, :func:`sensor_config` reads one, :func:`load_sensor` builds a
:class:`~tactile_deploy.sensors.virtual.VirtualSensor` (also from a JSON path).
"""

from __future__ import annotations

from pathlib import Path

from tactile_deploy.sensors.config import (
    SENSOR_DIR,
    VirtualSensorConfig,
    load_sensor_config,
)
from tactile_deploy.sensors.virtual import VirtualSensor


class UnknownSensorError(KeyError):
    """A sensor name that is not shipped (the message lists the shipped ones)."""

    def __str__(self) -> str:
        return str(self.args[0])


def list_sensors() -> list[str]:
    """Names of the shipped virtual sensors."""
    return sorted(p.stem for p in SENSOR_DIR.glob("*.json") if not p.name.endswith(".schema.json"))


def sensor_config(name_or_path: str | Path) -> VirtualSensorConfig:
    """Config of a shipped sensor (by name) or of a JSON file (by path)."""
    p = Path(name_or_path)
    if p.suffix == ".json":
        return load_sensor_config(p)
    path = SENSOR_DIR / f"{name_or_path}.json"
    if not path.is_file():
        raise UnknownSensorError(f"unknown virtual sensor {str(name_or_path)!r}; shipped: "
                                 f"{', '.join(list_sensors())} (or give a .json path)")
    return load_sensor_config(path)


def load_sensor(name_or_path: str | Path, simulator=None):
    """A :class:`~tactile_deploy.sensors.virtual.VirtualSensor` by name or JSON path."""

    return VirtualSensor(sensor_config(name_or_path), simulator=simulator)
