"""Indentation rig: a G-code stage and a force gauge over pyserial, and a simulated rig.

Configs (:mod:`tactile_deploy.calibration.rig.config`) import no hardware library; the drivers
(:class:`GCodeStage`, :class:`ForceGauge`, :class:`IndentationRig`) share the
``connect`` / ``read`` / ``disconnect`` base and work as context managers. See docs/rig.md.
"""

from tactile_deploy.calibration.rig.config import (
    GaugeConfig,
    RigConfig,
    StageConfig,
    StageFrame,
    load_rig_config,
    rig_config_from_dict,
    save_rig_config,
)
from tactile_deploy.calibration.rig.errors import (
    GaugeError,
    RigConfigError,
    RigConnectionError,
    RigError,
    RigTimeoutError,
    SoftLimitError,
    StageError,
)
from tactile_deploy.calibration.rig.factory import GAUGE_DRIVERS, STAGE_DRIVERS, make_gauge, make_stage
from tactile_deploy.calibration.rig.gauge import ForceGauge
from tactile_deploy.calibration.rig.indent import Contact, IndentationRig, PressRecord, RigReading
from tactile_deploy.calibration.rig.stage import GCodeStage, StagePosition, parse_position

__all__ = [
    "GAUGE_DRIVERS",
    "STAGE_DRIVERS",
    "Contact",
    "ForceGauge",
    "GCodeStage",
    "GaugeConfig",
    "GaugeError",
    "IndentationRig",
    "PressRecord",
    "RigConfig",
    "RigConfigError",
    "RigConnectionError",
    "RigError",
    "RigReading",
    "RigTimeoutError",
    "SoftLimitError",
    "StageConfig",
    "StageError",
    "StageFrame",
    "StagePosition",
    "load_rig_config",
    "make_gauge",
    "make_stage",
    "parse_position",
    "rig_config_from_dict",
    "save_rig_config",
]
