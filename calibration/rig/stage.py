"""A three-axis stage driven with G-code over a serial line (Marlin-style firmware).

Protocol (host side)
--------------------
One command line is sent at a time; the next is sent only after the previous one got its
terminal reply:

* ``ok`` (or ``ok ...``) ends a command successfully;
* a line starting with ``error`` / ``Error`` or ``!!`` ends it with a failure:
  :class:`~tactile_deploy.calibration.rig.errors.StageError` quoting the command and the reply;
* ``echo:Unknown command ...`` means the firmware lacks the command:
  :class:`~tactile_deploy.calibration.rig.errors.StageError`;
* ``busy: ...`` is a keep-alive: the firmware is still working, the timeout restarts;
* ``echo:``, ``//``, ``start`` and ``wait`` lines are information and are skipped;
* for ``M114`` the line ``X:1.00 Y:2.00 Z:3.00 E:0.00 Count ...`` carries the position;
* any other line is unexpected (garbled by noise, for instance): it is logged and skipped, and
  more than ``max_unexpected_lines`` of them for one command raise ``StageError``.

Every command used here is idempotent in absolute mode (``connect()`` sends ``G21`` and
``G90``), so on a timeout, or an ``M114`` reply without a readable position, the command is sent
again, up to ``retries`` times; then :class:`~tactile_deploy.calibration.rig.errors.RigTimeoutError` names the
port and the command. Input is discarded before each command, and after a command that needed
a retry the link is drained for ``timeout_s`` so that a late reply to the first attempt cannot be
taken for the reply to the next command.

Targets are checked against the soft limits before anything is sent
(:class:`~tactile_deploy.calibration.rig.errors.SoftLimitError`).

All coordinates here are **stage-frame** mm; see :mod:`tactile_deploy.calibration.rig.config` for the mapping
to the sensor frame.
"""

from __future__ import annotations

import logging
import re
import time
from typing import Any, Callable, NamedTuple

from tactile_deploy.calibration.rig.base import LineChannel, RigDevice
from tactile_deploy.calibration.rig.config import StageConfig
from tactile_deploy.calibration.rig.errors import RigTimeoutError, SoftLimitError, StageError

logger = logging.getLogger(__name__)

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_POSITION_RE = re.compile(
    rf"X:\s*(?P<x>{_NUMBER})\s+Y:\s*(?P<y>{_NUMBER})\s+Z:\s*(?P<z>{_NUMBER})"
)
_INFO_PREFIXES = ("echo:", "//", "start", "wait")
_SOFT_LIMIT_TOLERANCE_MM = 1e-9


class StagePosition(NamedTuple):
    """Stage position as reported by ``M114``, stage frame, mm."""

    x_mm: float
    y_mm: float
    z_mm: float


def parse_position(line: str) -> StagePosition | None:
    """Position in an ``M114`` reply line (``X:1.00 Y:2.00 Z:3.00 E:0.00 Count ...``), or None.

    The first ``X: Y: Z:`` triple is the position; the ``Count`` triple that follows is in
    steps and is ignored.
    """
    match = _POSITION_RE.search(line)
    if match is None:
        return None
    return StagePosition(float(match["x"]), float(match["y"]), float(match["z"]))


def _fmt(value: float) -> str:
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


class GCodeStage(RigDevice):
    """A G-code stage on one serial port. ``read()`` is :meth:`position`.

    ``opener(port, baudrate)`` may replace ``serial.serial_for_url`` (it must return an open
    pyserial-like object with a short read timeout).
    """

    def __init__(self, config: StageConfig, *, opener: Callable[[str, int], Any] | None = None):
        self.config = config
        self._channel = LineChannel(
            config.port, config.baudrate, config.newline, device="stage", opener=opener
        )

    # -- connection -------------------------------------------------------------------------

    @property
    def port(self) -> str:
        return self.config.port

    @property
    def is_connected(self) -> bool:
        return self._channel.is_open

    def connect(self) -> None:
        """Open the port, wait ``startup_wait_s``, select mm (G21) and absolute mode (G90)."""
        if self.is_connected:
            return
        self._channel.open()
        try:
            if self.config.startup_wait_s > 0:
                time.sleep(self.config.startup_wait_s)
            self.command("G21")
            self.command("G90")
        except BaseException:
            self._channel.close()
            raise

    def disconnect(self) -> None:
        self._channel.close()

    def read(self) -> StagePosition:
        """Current position (``M114``), stage frame, mm."""
        return self.position()

    # -- commands ---------------------------------------------------------------------------

    def home(self) -> StagePosition:
        """Home all axes (``G28``) and return the position read back, stage frame, mm."""
        self.command("G28", timeout_s=self.config.motion_timeout_s)
        return self.position()

    def check_limits(
        self, x_mm: float | None = None, y_mm: float | None = None, z_mm: float | None = None
    ) -> None:
        """Raise :class:`SoftLimitError` if a given stage coordinate is outside its soft limit."""
        for axis, value, limits in zip("XYZ", (x_mm, y_mm, z_mm), self.config.limits_mm()):
            if value is None:
                continue
            low, high = limits
            if not (low - _SOFT_LIMIT_TOLERANCE_MM <= value <= high + _SOFT_LIMIT_TOLERANCE_MM):
                raise SoftLimitError(
                    f"refusing to move the stage on '{self.port}' to {axis}={value:.4f} mm: "
                    f"outside the soft limit [{low}, {high}] mm ({axis.lower()}_limits_mm in the "
                    "stage config). Nothing was sent. Check the target and the sensor frame, or "
                    "widen the limit if the stage can really go there."
                )

    def move_to(
        self,
        x_mm: float | None = None,
        y_mm: float | None = None,
        z_mm: float | None = None,
        feed_mm_min: float | None = None,
        *,
        rapid: bool = False,
        wait: bool = True,
    ) -> None:
        """Move to an absolute stage-frame position, mm; axes left None do not move.

        ``rapid=True`` sends ``G0`` at ``travel_feed_mm_min``, otherwise ``G1`` at
        ``press_feed_mm_min``; ``feed_mm_min`` (mm/min) overrides either. With ``wait`` (the
        default) the call returns after ``M400``, i.e. when the motion has finished.
        """
        if x_mm is None and y_mm is None and z_mm is None:
            raise ValueError("move_to needs at least one of x_mm, y_mm, z_mm")
        self.check_limits(x_mm, y_mm, z_mm)
        if feed_mm_min is None:
            feed_mm_min = (
                self.config.travel_feed_mm_min if rapid else self.config.press_feed_mm_min
            )
        if not feed_mm_min > 0:
            raise ValueError(f"feed_mm_min must be > 0 mm/min, got {feed_mm_min}")
        words = ["G0" if rapid else "G1"]
        for axis, value in zip("XYZ", (x_mm, y_mm, z_mm)):
            if value is not None:
                words.append(f"{axis}{_fmt(float(value))}")
        words.append(f"F{_fmt(float(feed_mm_min))}")
        self.command(" ".join(words))
        if wait:
            self.wait_idle()

    def wait_idle(self) -> None:
        """Block until all queued motion has finished (``M400``)."""
        self.command("M400", timeout_s=self.config.motion_timeout_s)

    def position(self) -> StagePosition:
        """Current position from ``M114``, stage frame, mm."""
        return self.command("M114", parse=parse_position)

    # -- the link ---------------------------------------------------------------------------

    def command(
        self,
        line: str,
        *,
        timeout_s: float | None = None,
        parse: Callable[[str], Any] | None = None,
    ) -> Any:
        """Send one G-code line and wait for its terminal reply (see the module docstring).

        With ``parse``, the reply lines before ``ok`` (and the text after ``ok``) are passed to
        it; the first non-None result is returned, and a reply without one is retried. Without
        ``parse`` the return value is None.
        """
        cfg = self.config
        timeout_s = cfg.timeout_s if timeout_s is None else timeout_s
        attempts = cfg.retries + 1
        unexpected = 0
        failures: list[str] = []
        for attempt in range(1, attempts + 1):
            for stale in self._channel.discard_input():
                logger.debug("stage %s: dropped stale line %r before %r", self.port, stale, line)
            self._channel.write_line(line)
            deadline = time.monotonic() + timeout_s
            parsed = None
            while True:
                reply = self._channel.read_line(deadline)
                if reply is None:
                    failures.append(f"attempt {attempt}: no reply within {timeout_s:g} s")
                    logger.warning(
                        "stage %s: no reply to %r within %g s (attempt %d of %d)",
                        self.port, line, timeout_s, attempt, attempts,
                    )
                    break
                lowered = reply.lower()
                if lowered == "ok" or lowered.startswith("ok "):
                    if parse is not None and parsed is None:
                        parsed = parse(reply[3:])
                    if parse is not None and parsed is None:
                        failures.append(f"attempt {attempt}: 'ok' without a readable reply")
                        logger.warning(
                            "stage %s: reply to %r ended without a readable value "
                            "(attempt %d of %d)", self.port, line, attempt, attempts,
                        )
                        break
                    if attempt > 1:
                        for late in self._channel.drain(timeout_s):
                            logger.info("stage %s: dropped late reply %r", self.port, late)
                    return parsed
                if lowered.startswith("error") or reply.startswith("!!"):
                    self._channel.discard_input()
                    raise StageError(
                        f"stage on '{self.port}' rejected {line!r} with {reply!r}. Check the "
                        "command against the firmware, clear the fault (e.g. M999 or a power "
                        "cycle after a halt), re-home, then retry."
                    )
                if lowered.startswith("echo:unknown command"):
                    self._channel.discard_input()
                    raise StageError(
                        f"stage on '{self.port}' does not know {line!r} (reply {reply!r}): the "
                        "firmware must support G0/G1, G21, G28, G90, M114 and M400."
                    )
                if lowered.startswith("busy:"):
                    deadline = time.monotonic() + timeout_s
                    continue
                if lowered.startswith(_INFO_PREFIXES):
                    logger.debug("stage %s: %r", self.port, reply)
                    continue
                if parse is not None and parsed is None:
                    parsed = parse(reply)
                    if parsed is not None:
                        continue
                unexpected += 1
                logger.warning(
                    "stage %s: skipped unexpected line %r while waiting for the reply to %r",
                    self.port, reply, line,
                )
                if unexpected > cfg.max_unexpected_lines:
                    raise StageError(
                        f"stage on '{self.port}' sent {unexpected} unexpected lines while "
                        f"answering {line!r} (last: {reply!r}), more than max_unexpected_lines="
                        f"{cfg.max_unexpected_lines}. Check the baud rate ({cfg.baudrate} "
                        "bit/s), the cable and its grounding, and that the port is the stage."
                    )
        raise RigTimeoutError(
            f"stage on '{self.port}' gave no complete reply to {line!r} after {attempts} "
            f"attempt(s) ({'; '.join(failures)}). Check that the stage is powered and connected "
            f"to '{self.port}', the baud rate ({cfg.baudrate} bit/s), and that the firmware "
            "answers 'ok'; raise timeout_s or motion_timeout_s if moves are long."
        )
