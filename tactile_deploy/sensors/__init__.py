"""Virtual tactile sensors: pad + FEM + optics + effects + noise (see docs/optics.md and
docs/effects.md).

``load_sensor("gelslim1")`` builds a shipped sensor; :mod:`tactile_deploy.sensors.effects` holds
one module per effect. Importing this package is cheap (no FEM, no renderer until used).
"""

from tactile_deploy.sensors.catalog import list_sensors, load_sensor, sensor_config
from tactile_deploy.sensors.config import (
    EffectSpec,
    SensorConfigError,
    VirtualSensorConfig,
    load_sensor_config,
    save_sensor_config,
)

__all__ = [
    "EffectSpec",
    "SensorConfigError",
    "VirtualSensorConfig",
    "list_sensors",
    "load_sensor",
    "load_sensor_config",
    "save_sensor_config",
    "sensor_config",
]
