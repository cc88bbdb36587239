"""Configuration of the indentation rig: a G-code stage and a force gauge on two serial lines.

This module imports no hardware library (no pyserial): a config can be written, validated and
shipped on a machine without the rig.

Frames
------
* **Sensor frame**: origin at the centre of the sensing (top) surface of the gel pad, z up and
  out of the gel, mm. Contacts are given in this frame: ``(x_mm, y_mm, depth_mm)``, the tip at
  sensor-frame height ``surface_z_mm - depth_mm``.
* **Stage frame**: the coordinates the stage firmware reports with ``M114`` and accepts in
  ``G0``/``G1``, mm. The stage axes are parallel to the sensor axes; each may point the same way
  (sign +1) or the opposite way (sign -1).

:class:`StageFrame` maps one to the other for the indenter *tip*::

    X_stage = sensor_origin_x_mm + axis_sign_x * x_sensor
    Y_stage = sensor_origin_y_mm + axis_sign_y * y_sensor
    Z_stage = z_touch_mm         + axis_sign_z * z_sensor

``z_touch_mm`` is the stage Z at which the tip touches the undeformed gel surface at the sensor
origin; it is a calibrated value.

Files are JSON, read with :func:`load_rig_config` and written atomically with
:func:`save_rig_config`. The JSON Schema lives next to this module
(``rig_config.schema.json``) and is regenerated with ``python -m tactile_deploy.calibration.formats``.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from tactile_deploy.calibration.rig.errors import RigConfigError
from tactile_deploy.fileformat import StrictModel

#: Version of the rig config file format written by :func:`save_rig_config`.
RIG_CONFIG_FORMAT_VERSION = 1

#: Path of the committed JSON Schema of :class:`RigConfig`.
RIG_CONFIG_SCHEMA_PATH = Path(__file__).with_name("rig_config.schema.json")

Newline = Literal["\n", "\r", "\r\n"]
AxisSign = Literal[1, -1]


def _check_range(name: str, limits: tuple[float, float]) -> None:
    if not limits[0] < limits[1]:
        raise ValueError(f"{name}={list(limits)} must be [min, max] with min < max")


class StageFrame(StrictModel):
    """Where the sensor sits on the stage: the stage coordinates of the sensor-frame origin."""

    sensor_origin_x_mm: float = Field(
        50.0, description="Stage X of the indenter tip above the sensor-frame origin, mm."
    )
    sensor_origin_y_mm: float = Field(
        50.0, description="Stage Y of the indenter tip above the sensor-frame origin, mm."
    )
    z_touch_mm: float = Field(
        20.0,
        description="Stage Z at which the tip touches the undeformed gel surface at the "
        "sensor-frame origin (sensor z = 0), mm. Calibrated.",
    )
    axis_sign_x: AxisSign = Field(1, description="+1 if stage +X is sensor +x, -1 if it is -x.")
    axis_sign_y: AxisSign = Field(1, description="+1 if stage +Y is sensor +y, -1 if it is -y.")
    axis_sign_z: AxisSign = Field(
        1, description="+1 if stage +Z moves the tip up (out of the gel), -1 if down."
    )

    def sensor_to_stage(self, x_mm: float, y_mm: float, z_mm: float) -> tuple[float, float, float]:
        """Stage (X, Y, Z), mm, that puts the tip at sensor-frame point (x, y, z), mm."""
        return (
            self.sensor_origin_x_mm + self.axis_sign_x * x_mm,
            self.sensor_origin_y_mm + self.axis_sign_y * y_mm,
            self.z_touch_mm + self.axis_sign_z * z_mm,
        )

    def stage_to_sensor(self, x_mm: float, y_mm: float, z_mm: float) -> tuple[float, float, float]:
        """Sensor-frame tip position (x, y, z), mm, for stage position (X, Y, Z), mm."""
        return (
            self.axis_sign_x * (x_mm - self.sensor_origin_x_mm),
            self.axis_sign_y * (y_mm - self.sensor_origin_y_mm),
            self.axis_sign_z * (z_mm - self.z_touch_mm),
        )

    def contact_to_stage(
        self, x_mm: float, y_mm: float, depth_mm: float, surface_z_mm: float = 0.0
    ) -> tuple[float, float, float]:
        """Stage target, mm, for a contact ``depth_mm`` below the gel surface at (x, y).

        ``surface_z_mm`` is the sensor-frame height of the undeformed surface under the contact
        (0 for a flat pad; ``PadGeometry.top_height_mm(x, y)`` for a domed one).
        """
        return self.sensor_to_stage(x_mm, y_mm, surface_z_mm - depth_mm)


class StageConfig(StrictModel):
    """A three-axis stage that speaks G-code over a serial line."""

    kind: str = Field("gcode", description="Stage driver name (see tactile_deploy.calibration.rig.factory).")
    port: str = Field(
        ...,
        min_length=1,
        description="Serial port or pyserial URL, e.g. /dev/ttyUSB0, COM3, socket://host:port.",
    )
    baudrate: int = Field(115200, gt=0, description="Serial baud rate, bit/s.")
    newline: Newline = Field("\n", description="Line terminator appended to every command.")
    timeout_s: float = Field(
        2.0, gt=0, description="Time allowed for the reply to one command, s."
    )
    motion_timeout_s: float = Field(
        60.0,
        gt=0,
        description="Time allowed for commands that wait for motion to end (G28, M400), s. "
        "Each 'busy:' keep-alive line from the firmware restarts it.",
    )
    retries: int = Field(
        2,
        ge=0,
        description="Re-sends after a timeout or incomplete reply (attempts = retries + 1).",
    )
    max_unexpected_lines: int = Field(
        20, ge=0, description="Unexpected or garbled lines skipped per command before giving up."
    )
    startup_wait_s: float = Field(
        0.0,
        ge=0,
        description="Wait after opening the port before the first command, s (boards that reset "
        "on connect need about 2 s).",
    )
    travel_feed_mm_min: float = Field(
        1200.0, gt=0, description="Feed rate of travel moves (G0), mm/min."
    )
    press_feed_mm_min: float = Field(
        60.0, gt=0, description="Feed rate of pressing moves (G1), mm/min."
    )
    x_limits_mm: tuple[float, float] = Field(
        (0.0, 100.0), description="Soft limits [min, max] of stage X, mm."
    )
    y_limits_mm: tuple[float, float] = Field(
        (0.0, 100.0), description="Soft limits [min, max] of stage Y, mm."
    )
    z_limits_mm: tuple[float, float] = Field(
        (0.0, 50.0), description="Soft limits [min, max] of stage Z, mm."
    )
    frame: StageFrame = Field(
        default_factory=StageFrame, description="Stage coordinates of the sensor frame."
    )

    @model_validator(mode="after")
    def _check(self) -> "StageConfig":
        _check_range("x_limits_mm", self.x_limits_mm)
        _check_range("y_limits_mm", self.y_limits_mm)
        _check_range("z_limits_mm", self.z_limits_mm)
        origin = self.frame.sensor_to_stage(0.0, 0.0, 0.0)
        for axis, value, limits in zip("XYZ", origin, self.limits_mm()):
            if not limits[0] <= value <= limits[1]:
                raise ValueError(
                    f"the sensor-frame origin is at stage {axis}={value} mm (frame), outside "
                    f"{axis.lower()}_limits_mm={list(limits)}: fix the frame or the limits"
                )
        return self

    def limits_mm(self) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        """Soft limits of (X, Y, Z), each [min, max], stage frame, mm."""
        return (self.x_limits_mm, self.y_limits_mm, self.z_limits_mm)


class GaugeConfig(StrictModel):
    """A force gauge answering an ASCII request with one line, e.g. ``?`` -> ``12.34 N``."""

    kind: str = Field("ascii", description="Gauge driver name (see tactile_deploy.calibration.rig.factory).")
    port: str = Field(..., min_length=1, description="Serial port or pyserial URL.")
    baudrate: int = Field(9600, gt=0, description="Serial baud rate, bit/s.")
    newline: Newline = Field("\n", description="Line terminator appended to the request.")
    timeout_s: float = Field(0.5, gt=0, description="Time allowed for one reply, s.")
    retries: int = Field(
        2, ge=0, description="Re-requests after a timeout (attempts = retries + 1)."
    )
    max_unexpected_lines: int = Field(
        10, ge=0, description="Unreadable reply lines tolerated per reading before giving up."
    )
    request: str = Field("?", min_length=1, description="Text sent to ask for one reading.")
    reply_regex: str = Field(
        r"^\s*([-+]?\d+(?:\.\d*)?)\s*N\s*$",
        description="Regular expression a reply line must match in full; its group 'value' (or "
        "its first group) is the number.",
    )
    newtons_per_unit: float = Field(
        1.0, gt=0, description="Newtons per reply unit (1 for N, 9.80665 for kgf, 4.44822 for lbf)."
    )
    force_sign: AxisSign = Field(
        1, description="+1 if the gauge reports compression as positive, -1 if negative."
    )
    tare_samples: int = Field(
        5, ge=1, description="Readings averaged by tare() to find the zero offset."
    )

    @field_validator("reply_regex")
    @classmethod
    def _check_regex(cls, value: str) -> str:
        try:
            pattern = re.compile(value)
        except re.error as exc:
            raise ValueError(
                f"reply_regex {value!r} is not a valid regular expression: {exc}"
            ) from None
        if pattern.groups < 1:
            raise ValueError(
                f"reply_regex {value!r} has no capture group: put the number in (...) or "
                "(?P<value>...)"
            )
        return value


class RigConfig(StrictModel):
    """The whole indentation rig: stage, gauge and the pressing procedure."""

    format_version: Literal[1] = Field(
        RIG_CONFIG_FORMAT_VERSION, description="Version of this file format."
    )
    stage: StageConfig
    gauge: GaugeConfig
    force_limit_n: float = Field(
        10.0,
        gt=0,
        description="Force above which a press stops and backs off, N. The overshoot is at most "
        "one approach step.",
    )
    approach_step_mm: float = Field(
        0.05, gt=0, description="Z step between force readings while pressing, mm."
    )
    approach_clearance_mm: float = Field(
        1.0,
        gt=0,
        description="Height above the gel surface where stepping starts, mm (sensor frame).",
    )
    travel_height_mm: float = Field(
        5.0,
        gt=0,
        description="Sensor-frame z of XY travel and retract moves, mm: the height above the "
        "highest point of the pad (z = 0).",
    )
    dwell_s: float = Field(
        0.0, ge=0, description="Wait at full depth before reading the force, s."
    )
    force_samples: int = Field(
        1, ge=1, description="Readings averaged at full depth."
    )
    tare_before_press: bool = Field(
        True, description="Tare the gauge at travel height before each press."
    )

    @model_validator(mode="after")
    def _check(self) -> "RigConfig":
        if self.approach_clearance_mm > self.travel_height_mm:
            raise ValueError(
                f"approach_clearance_mm={self.approach_clearance_mm} must not exceed "
                f"travel_height_mm={self.travel_height_mm}"
            )
        if self.approach_step_mm > self.approach_clearance_mm:
            raise ValueError(
                f"approach_step_mm={self.approach_step_mm} must not exceed "
                f"approach_clearance_mm={self.approach_clearance_mm}"
            )
        return self


def _format_loc(loc: tuple) -> str:
    return ".".join(str(part) for part in loc) or "(top level)"


def _validation_message(source: str, exc: ValidationError) -> str:
    lines = [f"{source}: invalid rig config ({exc.error_count()} error(s)); see docs/rig.md:"]
    for err in exc.errors():
        field = _format_loc(err["loc"])
        if err["type"] == "extra_forbidden":
            lines.append(f"  field '{field}': unknown field (got {err['input']!r}); remove it")
        elif err["type"] == "missing":
            lines.append(f"  field '{field}': required, got nothing")
        else:
            lines.append(f"  field '{field}': expected {err['msg']}, got {err['input']!r}")
    return "\n".join(lines)


def rig_config_from_dict(data: dict, source: str = "<dict>") -> RigConfig:
    """Validate a plain dict as a :class:`RigConfig`; errors name ``source`` and each field."""
    try:
        return RigConfig.model_validate(data)
    except ValidationError as exc:
        raise RigConfigError(_validation_message(source, exc)) from None


def load_rig_config(path: str | os.PathLike) -> RigConfig:
    """Read a rig config JSON file.

    Raises :class:`RigConfigError` naming the file and, for a bad value, the field, what was
    expected and what was found.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RigConfigError(
            f"{path}: no such rig config file; write one with save_rig_config() or copy the "
            "example in docs/rig.md"
        ) from None
    except OSError as exc:
        raise RigConfigError(f"{path}: cannot read the rig config: {exc}") from None
    except UnicodeDecodeError:
        raise RigConfigError(
            f"{path}: not a text file (expected a rig config JSON); give the rig config, see "
            "docs/rig.md"
        ) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RigConfigError(
            f"{path}: not valid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    if not isinstance(data, dict):
        raise RigConfigError(
            f"{path}: expected a JSON object at the top level, got {type(data).__name__}"
        )
    return rig_config_from_dict(data, source=str(path))


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def save_rig_config(config: RigConfig, path: str | os.PathLike) -> None:
    """Write ``config`` as JSON to ``path`` atomically (temporary file + rename)."""
    write_text_atomic(path, config.model_dump_json(indent=2) + "\n")
