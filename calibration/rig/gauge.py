"""A force gauge that answers an ASCII request with one line (e.g. ``?`` -> ``12.34 N``).

Protocol (host side): input is discarded, ``request`` + newline is sent, and reply lines are
read until one matches ``reply_regex`` in full. Its ``value`` group (or first group) times
``newtons_per_unit`` times ``force_sign`` is the raw force in N; :meth:`ForceGauge.read_n`
subtracts the tare offset, so compression reads positive and zero means "as at the last tare".

Faults:

* a line that does not match is garbled: it is logged and the request is sent again at once;
  more than ``max_unexpected_lines`` of them in one reading raise
  :class:`~tactile_deploy.calibration.rig.errors.GaugeError`;
* no matching line within ``timeout_s``: the request is sent again, up to ``retries`` times,
  then :class:`~tactile_deploy.calibration.rig.errors.RigTimeoutError` names the port and the request;
* after a reading that needed a repeat because of a timeout, the link is drained for
  ``timeout_s`` so a late reply cannot be taken for a later reading.
"""

from __future__ import annotations

import logging
import re
import time
from typing import Any, Callable

from tactile_deploy.calibration.rig.base import LineChannel, RigDevice
from tactile_deploy.calibration.rig.config import GaugeConfig
from tactile_deploy.calibration.rig.errors import GaugeError, RigTimeoutError

logger = logging.getLogger(__name__)


class ForceGauge(RigDevice):
    """A request/reply force gauge on one serial port. ``read()`` is :meth:`read_n`."""

    def __init__(self, config: GaugeConfig, *, opener: Callable[[str, int], Any] | None = None):
        self.config = config
        self._pattern = re.compile(config.reply_regex)
        self._channel = LineChannel(
            config.port, config.baudrate, config.newline, device="force gauge", opener=opener
        )
        #: Raw force subtracted from every reading, N (set by :meth:`tare`).
        self.tare_offset_n = 0.0

    @property
    def port(self) -> str:
        return self.config.port

    @property
    def is_connected(self) -> bool:
        return self._channel.is_open

    def connect(self) -> None:
        """Open the port and take one reading to check that the gauge answers."""
        if self.is_connected:
            return
        self._channel.open()
        try:
            self.read_raw_n()
        except BaseException:
            self._channel.close()
            raise

    def disconnect(self) -> None:
        self._channel.close()

    def read(self) -> float:
        """One tared reading, N (compression positive)."""
        return self.read_n()

    def tare(self) -> float:
        """Average ``tare_samples`` raw readings, store them as the zero offset, return it (N).

        Call it with nothing touching the gel.
        """
        samples = [self.read_raw_n() for _ in range(self.config.tare_samples)]
        self.tare_offset_n = sum(samples) / len(samples)
        return self.tare_offset_n

    def read_n(self, samples: int = 1) -> float:
        """Mean of ``samples`` tared readings, N (compression positive)."""
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        total = sum(self.read_raw_n() for _ in range(samples))
        return total / samples - self.tare_offset_n

    def _parse(self, line: str) -> float | None:
        match = self._pattern.fullmatch(line)
        if match is None:
            return None
        text = match.groupdict().get("value") or match.group(1)
        try:
            value = float(text)
        except (TypeError, ValueError):
            return None
        return self.config.force_sign * value * self.config.newtons_per_unit

    def read_raw_n(self) -> float:
        """One reading without the tare offset, N (compression positive)."""
        cfg = self.config
        attempts = cfg.retries + 1
        unexpected = 0
        timeouts = 0
        repeated = False
        while True:
            for stale in self._channel.discard_input():
                logger.debug("gauge %s: dropped stale line %r", self.port, stale)
            self._channel.write_line(cfg.request)
            reply = self._channel.read_line(time.monotonic() + cfg.timeout_s)
            if reply is None:
                timeouts += 1
                logger.warning(
                    "gauge %s: no reply to %r within %g s (attempt %d of %d)",
                    self.port, cfg.request, cfg.timeout_s, timeouts, attempts,
                )
                if timeouts >= attempts:
                    raise RigTimeoutError(
                        f"force gauge on '{self.port}' did not answer {cfg.request!r} within "
                        f"{cfg.timeout_s:g} s, {attempts} attempt(s). Check that the gauge is on, "
                        f"connected to '{self.port}' and in request/reply (not streaming) mode, "
                        f"the baud rate ({cfg.baudrate} bit/s) and the request string."
                    )
                repeated = True
                continue
            value = self._parse(reply)
            if value is not None:
                if repeated:
                    for late in self._channel.drain(cfg.timeout_s):
                        logger.info("gauge %s: dropped late reply %r", self.port, late)
                return value
            unexpected += 1
            logger.warning(
                "gauge %s: reply %r does not match reply_regex %r", self.port, reply,
                cfg.reply_regex,
            )
            if unexpected > cfg.max_unexpected_lines:
                raise GaugeError(
                    f"force gauge on '{self.port}' sent {unexpected} replies to {cfg.request!r} "
                    f"that do not match reply_regex {cfg.reply_regex!r} (last: {reply!r}). Check "
                    f"the baud rate ({cfg.baudrate} bit/s), the gauge's output units and format, "
                    "and the reply_regex in the gauge config."
                )
