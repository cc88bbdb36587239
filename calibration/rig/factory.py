"""Build rig devices from their configs; drivers are registered by name in plain dicts.

A config's ``kind`` picks the driver (``StageConfig.kind="gcode"``, ``GaugeConfig.kind="ascii"``).
To add one, put its class in :data:`STAGE_DRIVERS` or :data:`GAUGE_DRIVERS`.
"""

from __future__ import annotations

from typing import Any, Callable

from tactile_deploy.calibration.rig.config import GaugeConfig, StageConfig
from tactile_deploy.calibration.rig.errors import RigConfigError
from tactile_deploy.calibration.rig.gauge import ForceGauge
from tactile_deploy.calibration.rig.stage import GCodeStage

#: Stage driver classes by ``StageConfig.kind``.
STAGE_DRIVERS: dict[str, type[GCodeStage]] = {"gcode": GCodeStage}

#: Force gauge driver classes by ``GaugeConfig.kind``.
GAUGE_DRIVERS: dict[str, type[ForceGauge]] = {"ascii": ForceGauge}


def _lookup(drivers: dict[str, type], kind: str, what: str) -> type:
    try:
        return drivers[kind]
    except KeyError:
        known = ", ".join(sorted(drivers))
        raise RigConfigError(
            f"unknown {what} kind {kind!r}; known kinds: {known}. Fix '{what}.kind' in the rig "
            "config."
        ) from None


def make_stage(config: StageConfig, *, opener: Callable[[str, int], Any] | None = None):
    """The stage driver named by ``config.kind``, not yet connected."""
    return _lookup(STAGE_DRIVERS, config.kind, "stage")(config, opener=opener)


def make_gauge(config: GaugeConfig, *, opener: Callable[[str, int], Any] | None = None):
    """The force gauge driver named by ``config.kind``, not yet connected."""
    return _lookup(GAUGE_DRIVERS, config.kind, "gauge")(config, opener=opener)
