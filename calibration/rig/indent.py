"""The indentation rig: a G-code stage pressing an indenter into the gel, a force gauge under it.

A press at sensor-frame contact ``(x_mm, y_mm, depth_mm)`` (tip ``depth_mm`` below the gel
surface at (x, y), whose sensor-frame height is ``surface_z_mm``, 0 for a flat pad):

1. every waypoint is checked against the stage soft limits, and the depth against the gel
   pad's thickness (:data:`PAD_THICKNESS_MM`), before anything moves;
2. Z up to ``travel_height_mm`` (sensor z), XY travel above the contact (G0), gauge tare
   (``tare_before_press``), G0 down to ``approach_clearance_mm`` above the surface;
3. G1 down in equal steps of at most ``approach_step_mm``, waiting for each (M400) and reading
   the force after each;
4. if a force exceeds ``force_limit_n`` the press **stops there, backs off to travel height and
   returns a record flagged** ``force_limited=True`` (it does not raise: a press sequence goes on
   with the next contact). The stage never goes deeper than the step at which the limit was
   exceeded, so the overshoot is at most one step: pick ``approach_step_mm`` so that one step of
   indentation adds little force;
5. at full depth: dwell ``dwell_s``, average ``force_samples`` readings, read the stage position
   back (M114), call ``on_pressed(record)`` with the indenter still held, then retract.

If anything fails during a press (timeout, stage error, an exception in ``on_pressed``, Ctrl-C)
the rig tries to retract to travel height before the exception propagates.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable, Iterable, NamedTuple, Sequence

from pydantic import BaseModel, ConfigDict, Field

from tactile_deploy.calibration.rig.base import RigDevice
from tactile_deploy.calibration.rig.config import RigConfig
from tactile_deploy.calibration.rig.factory import make_gauge, make_stage
from tactile_deploy.calibration.rig.stage import StagePosition
from tactile_deploy.pad.geometry import PadGeometry

logger = logging.getLogger(__name__)

#: Gel pad thickness, mm (the family's pad): a press must stay shallower, or the tip reaches the
#: backplate.
PAD_THICKNESS_MM = PadGeometry().thickness_mm

Vec3 = tuple[float, float, float]


class Contact(NamedTuple):
    """A commanded contact, sensor frame: tip at (x_mm, y_mm), ``depth_mm`` below the surface."""

    x_mm: float
    y_mm: float
    depth_mm: float


class RigReading(NamedTuple):
    """One reading of the whole rig."""

    stage_mm: StagePosition
    """Stage position (M114), stage frame, mm."""
    force_n: float
    """Tared force, N (compression positive)."""


class PressRecord(BaseModel):
    """What happened at one commanded contact."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    x_mm: float = Field(description="Commanded contact x, sensor frame, mm.")
    y_mm: float = Field(description="Commanded contact y, sensor frame, mm.")
    depth_mm: float = Field(description="Commanded depth below the gel surface, mm.")
    surface_z_mm: float = Field(description="Sensor-frame z of the gel surface at (x, y), mm.")
    stage_target_mm: Vec3 = Field(description="Commanded stage (X, Y, Z) at full depth, mm.")
    stage_readback_mm: Vec3 = Field(
        description="Stage (X, Y, Z) read back (M114) at the deepest point reached, mm."
    )
    tip_readback_mm: Vec3 = Field(
        description="Tip position from the read-back, sensor frame (x, y, z), mm."
    )
    reached_depth_mm: float = Field(
        description="Commanded depth of the deepest step taken, mm (< depth_mm if limited)."
    )
    force_n: float = Field(description="Force at the deepest point reached, N.")
    max_force_n: float = Field(description="Largest force read during the press, N.")
    force_limited: bool = Field(description="True if the press stopped at force_limit_n.")
    timestamp_s: float = Field(description="UNIX time of the force reading, s.")


def _approach_levels(top_z_mm: float, bottom_z_mm: float, step_mm: float) -> list[float]:
    """Sensor-frame z of each step from ``top_z_mm`` (excluded) down to ``bottom_z_mm``."""
    span = top_z_mm - bottom_z_mm
    n = max(1, math.ceil(span / step_mm - 1e-9))
    return [top_z_mm - span * k / n for k in range(1, n + 1)]


def check_press_depth(depth_mm: float) -> None:
    """Raise ValueError when ``depth_mm`` would reach through the gel pad to its backplate."""
    if not depth_mm < PAD_THICKNESS_MM:
        raise ValueError(
            f"depth {depth_mm:g} mm reaches through the {PAD_THICKNESS_MM:g} mm gel pad to its "
            f"backplate: command a depth below {PAD_THICKNESS_MM:g} mm"
        )


class IndentationRig(RigDevice):
    """Stage + force gauge. ``read()`` returns a :class:`RigReading`.

    ``stage`` and ``gauge`` default to the drivers named in ``config``; ``opener`` replaces
    ``serial.serial_for_url`` for both.
    """

    def __init__(
        self,
        config: RigConfig,
        *,
        stage: Any = None,
        gauge: Any = None,
        opener: Callable[[str, int], Any] | None = None,
    ):
        self.config = config
        self.stage = stage if stage is not None else make_stage(config.stage, opener=opener)
        self.gauge = gauge if gauge is not None else make_gauge(config.gauge, opener=opener)

    @property
    def frame(self):
        return self.config.stage.frame

    @property
    def is_connected(self) -> bool:
        return self.stage.is_connected and self.gauge.is_connected

    def connect(self) -> None:
        self.stage.connect()
        try:
            self.gauge.connect()
        except BaseException:
            self.stage.disconnect()
            raise

    def disconnect(self) -> None:
        try:
            self.gauge.disconnect()
        finally:
            self.stage.disconnect()

    def read(self) -> RigReading:
        return RigReading(self.stage.position(), self.gauge.read_n())

    def home(self) -> StagePosition:
        """Home the stage (G28); returns the stage position read back, mm."""
        return self.stage.home()

    def retract(self) -> None:
        """Move the tip straight up (Z only) to ``travel_height_mm``, sensor frame."""
        z_stage = self.frame.sensor_to_stage(0.0, 0.0, self.config.travel_height_mm)[2]
        self.stage.move_to(z_mm=z_stage, rapid=True)

    def _waypoints(self, x_mm: float, y_mm: float, depth_mm: float, surface_z_mm: float):
        if not depth_mm >= 0:
            raise ValueError(f"depth_mm must be >= 0 mm (into the gel), got {depth_mm}")
        cfg = self.config
        if surface_z_mm + cfg.approach_clearance_mm > cfg.travel_height_mm:
            raise ValueError(
                f"the approach starts at sensor z={surface_z_mm + cfg.approach_clearance_mm} mm "
                f"(surface_z_mm={surface_z_mm} + approach_clearance_mm="
                f"{cfg.approach_clearance_mm}), above travel_height_mm={cfg.travel_height_mm}: "
                "raise travel_height_mm"
            )
        travel = self.frame.sensor_to_stage(x_mm, y_mm, cfg.travel_height_mm)
        start = self.frame.sensor_to_stage(x_mm, y_mm, surface_z_mm + cfg.approach_clearance_mm)
        target = self.frame.contact_to_stage(x_mm, y_mm, depth_mm, surface_z_mm)
        for point in (travel, start, target):
            self.stage.check_limits(*point)
        check_press_depth(depth_mm)
        return travel, start, target

    def press(
        self,
        x_mm: float,
        y_mm: float,
        depth_mm: float,
        *,
        surface_z_mm: float = 0.0,
        on_pressed: Callable[[PressRecord], Any] | None = None,
        retract: bool = True,
    ) -> PressRecord:
        """Press at sensor-frame (x_mm, y_mm) to ``depth_mm`` below the surface (module doc).

        Returns the :class:`PressRecord`; ``force_limited=True`` when the force limit stopped
        it (the rig has then backed off to travel height whatever ``retract`` says).
        ``on_pressed(record)`` runs at full depth, only when the limit was not hit.
        """
        cfg = self.config
        travel, start, target = self._waypoints(x_mm, y_mm, depth_mm, surface_z_mm)
        try:
            self.stage.move_to(z_mm=travel[2], rapid=True)
            self.stage.move_to(x_mm=travel[0], y_mm=travel[1], rapid=True)
            if cfg.tare_before_press:
                self.gauge.tare()
            self.stage.move_to(z_mm=start[2], rapid=True)
            force = self.gauge.read_n()
            max_force = force
            top_z = surface_z_mm + cfg.approach_clearance_mm
            reached_z = top_z
            if force <= cfg.force_limit_n:
                for z_sensor in _approach_levels(top_z, surface_z_mm - depth_mm,
                                                 cfg.approach_step_mm):
                    self.stage.move_to(z_mm=self.frame.sensor_to_stage(x_mm, y_mm, z_sensor)[2])
                    reached_z = z_sensor
                    force = self.gauge.read_n()
                    max_force = max(max_force, force)
                    if force > cfg.force_limit_n:
                        break
            limited = max_force > cfg.force_limit_n
            if not limited:
                if cfg.dwell_s > 0:
                    time.sleep(cfg.dwell_s)
                force = self.gauge.read_n(cfg.force_samples)
                max_force = max(max_force, force)
                limited = force > cfg.force_limit_n
            timestamp_s = time.time()
            readback = self.stage.position()
            record = PressRecord(
                x_mm=x_mm,
                y_mm=y_mm,
                depth_mm=depth_mm,
                surface_z_mm=surface_z_mm,
                stage_target_mm=target,
                stage_readback_mm=tuple(readback),
                tip_readback_mm=self.frame.stage_to_sensor(*readback),
                reached_depth_mm=max(0.0, surface_z_mm - reached_z),
                force_n=force,
                max_force_n=max_force,
                force_limited=limited,
                timestamp_s=timestamp_s,
            )
            if limited:
                logger.warning(
                    "press at (%.3f, %.3f) mm stopped at depth %.3f of %.3f mm: %.3f N > "
                    "force_limit_n=%.3f N; backing off",
                    x_mm, y_mm, record.reached_depth_mm, depth_mm, max_force, cfg.force_limit_n,
                )
            elif on_pressed is not None:
                on_pressed(record)
        except BaseException:
            try:
                self.retract()
            except Exception as exc:  # keep the original error; say the indenter may be in
                logger.error("could not retract after a failed press (%s): the indenter may "
                             "still be in the gel; jog it up by hand", exc)
            raise
        if retract or limited:
            self.retract()
        return record

    def press_sequence(
        self,
        contacts: Iterable[Sequence[float]],
        on_pressed: Callable[[PressRecord], Any] | None = None,
        *,
        surface_z_fn: Callable[[float, float], float] | None = None,
        stop_on_limit: bool = False,
    ) -> list[PressRecord]:
        """Press at each contact ``(x_mm, y_mm, depth_mm)`` (sensor frame), one record each.

        ``surface_z_fn(x_mm, y_mm)`` gives the sensor-frame surface height (e.g.
        ``PadGeometry.top_height_mm``); default flat (0). All contacts are checked against the
        soft limits before the first move. ``on_pressed(record)`` runs at each contact that
        reached full depth, with the indenter held (grab a camera frame there). A force-limited
        contact is recorded with ``force_limited=True`` and the sequence goes on, unless
        ``stop_on_limit``.
        """
        plan = []
        for i, contact in enumerate(contacts):
            if len(contact) != 3:
                raise ValueError(
                    f"contact {i} is {contact!r}: expected (x_mm, y_mm, depth_mm), sensor frame"
                )
            c = Contact(*(float(v) for v in contact))
            surface = float(surface_z_fn(c.x_mm, c.y_mm)) if surface_z_fn is not None else 0.0
            self._waypoints(c.x_mm, c.y_mm, c.depth_mm, surface)
            plan.append((c, surface))
        records = []
        for c, surface in plan:
            record = self.press(
                c.x_mm, c.y_mm, c.depth_mm, surface_z_mm=surface, on_pressed=on_pressed
            )
            records.append(record)
            if record.force_limited and stop_on_limit:
                break
        return records
