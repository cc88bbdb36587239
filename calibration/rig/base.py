"""Common base of the rig devices and the line-oriented serial link they share.

Every device (:class:`~tactile_deploy.calibration.rig.stage.GCodeStage`,
:class:`~tactile_deploy.calibration.rig.gauge.ForceGauge`, :class:`~tactile_deploy.calibration.rig.indent.IndentationRig`)
has ``connect()`` / ``read()`` / ``disconnect()`` and can be used with ``with``.

:class:`LineChannel` opens a port with ``serial.serial_for_url``, so a config may name a device
(``/dev/ttyUSB0``, ``COM3``), a pseudo-terminal, or a pyserial URL (``socket://host:port``,
``loop://``). Replies are split into lines on ``\\n`` and ``\\r`` (so ``\\n``, ``\\r\\n`` and
``\\r`` terminators all work); empty lines are dropped.
"""

from __future__ import annotations

import abc
import logging
import time
from typing import Any, Callable

from tactile_deploy.calibration.rig.errors import RigConnectionError

logger = logging.getLogger(__name__)

#: Longest reply line kept; a longer run of bytes without a terminator is returned as one line.
MAX_LINE_BYTES = 4096

#: How long one blocking read waits before the deadline is checked again, s.
POLL_S = 0.01


def _default_opener(port: str, baudrate: int) -> Any:
    import serial  # imported here: configs and docs must not need pyserial

    return serial.serial_for_url(port, baudrate=baudrate, timeout=POLL_S, write_timeout=5.0)


class LineChannel:
    """A serial port read and written one text line at a time.

    ``opener(port, baudrate)`` returns an open pyserial-like object (``read``, ``write``,
    ``flush``, ``in_waiting``, ``reset_input_buffer``, ``close``) whose read timeout is short
    (:data:`POLL_S`); the default uses ``serial.serial_for_url``.
    """

    def __init__(
        self,
        port: str,
        baudrate: int,
        newline: str,
        *,
        device: str,
        opener: Callable[[str, int], Any] | None = None,
    ):
        self.port = port
        self.baudrate = baudrate
        self.newline = newline
        self.device = device
        self._opener = opener or _default_opener
        self._serial: Any = None
        self._buffer = bytearray()

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        if self._serial is not None:
            return
        try:
            self._serial = self._opener(self.port, self.baudrate)
        except Exception as exc:  # pyserial raises SerialException (an OSError) or ValueError
            raise RigConnectionError(
                f"could not open the {self.device} port '{self.port}' at {self.baudrate} bit/s: "
                f"{exc}. Check the cable and power, the port name (list ports with "
                "`python -m serial.tools.list_ports`) and that no other program holds the port."
            ) from exc
        self._buffer.clear()

    def close(self) -> None:
        if self._serial is None:
            return
        try:
            self._serial.close()
        finally:
            self._serial = None
            self._buffer.clear()

    def _require_open(self):
        if self._serial is None:
            raise RigConnectionError(
                f"the {self.device} on '{self.port}' is not connected: call connect() or use it "
                "in a `with` block"
            )
        return self._serial

    def _lost(self, exc: Exception) -> RigConnectionError:
        return RigConnectionError(
            f"lost the link to the {self.device} on '{self.port}': {exc}. Check that the device "
            "is still powered and plugged in, then disconnect and connect again."
        )

    def write_line(self, text: str) -> None:
        """Send ``text`` followed by the configured newline (ASCII)."""
        ser = self._require_open()
        try:
            ser.write((text + self.newline).encode("ascii"))
            ser.flush()
        except OSError as exc:  # serial.SerialException and its timeout are OSErrors
            raise self._lost(exc) from exc

    def discard_input(self) -> list[str]:
        """Drop everything received but not yet read; return the complete lines dropped."""
        ser = self._require_open()
        try:
            waiting = ser.in_waiting
            if waiting:
                self._buffer.extend(ser.read(waiting))
            ser.reset_input_buffer()
        except OSError as exc:
            raise self._lost(exc) from exc
        dropped = self._pop_lines()
        self._buffer.clear()
        return dropped

    def _pop_lines(self) -> list[str]:
        lines = []
        while True:
            line = self._pop_line()
            if line is None:
                return lines
            lines.append(line)

    def _pop_line(self) -> str | None:
        """Next complete non-empty line from the buffer, or None."""
        while True:
            cut = -1
            for i, byte in enumerate(self._buffer):
                if byte in (10, 13):  # \n, \r
                    cut = i
                    break
            if cut < 0:
                if len(self._buffer) >= MAX_LINE_BYTES:
                    raw = bytes(self._buffer[:MAX_LINE_BYTES])
                    del self._buffer[:MAX_LINE_BYTES]
                    return raw.decode("ascii", errors="replace")
                return None
            raw = bytes(self._buffer[:cut])
            del self._buffer[: cut + 1]
            if raw.strip():
                return raw.decode("ascii", errors="replace").strip()

    def read_line(self, deadline: float) -> str | None:
        """Next non-empty line (stripped), or None if none is complete by ``deadline``.

        ``deadline`` is a ``time.monotonic()`` value. Bytes that are not ASCII decode to
        U+FFFD, so garbled lines stay visible as such.
        """
        ser = self._require_open()
        while True:
            line = self._pop_line()
            if line is not None:
                return line
            if time.monotonic() >= deadline:
                return None
            try:
                chunk = ser.read(max(1, ser.in_waiting))
            except OSError as exc:
                raise self._lost(exc) from exc
            if chunk:
                self._buffer.extend(chunk)

    def drain(self, window_s: float) -> list[str]:
        """Read and drop lines for ``window_s`` seconds (late replies after a retry)."""
        deadline = time.monotonic() + window_s
        dropped = []
        while True:
            line = self.read_line(deadline)
            if line is None:
                return dropped
            dropped.append(line)


class RigDevice(abc.ABC):
    """Base of every rig device: ``connect`` / ``read`` / ``disconnect``, usable with ``with``."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool:
        """True between ``connect()`` and ``disconnect()``."""

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the port(s) and check that the device answers."""

    @abc.abstractmethod
    def read(self) -> Any:
        """One reading of the device's main quantity (see the subclass)."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Close the port(s). Safe to call twice."""

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc_info) -> None:
        self.disconnect()
