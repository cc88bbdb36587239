"""Exceptions of the indentation rig.

Every message names the port (or file), what was sent or read, and what to check next.
"""

from __future__ import annotations


class RigError(RuntimeError):
    """Base class of every rig failure (stage, gauge, link)."""


class RigConnectionError(RigError):
    """A serial port could not be opened, or a device was used before ``connect()``."""


class StageError(RigError):
    """The stage answered a command with an error, or with too many unexpected lines."""


class GaugeError(RigError):
    """The force gauge answered with too many unreadable lines."""


class RigTimeoutError(RigError, TimeoutError):
    """A device did not answer within its timeout, retries included."""


class SoftLimitError(RigError, ValueError):
    """A stage target lies outside the configured soft limits; nothing was sent."""


class RigConfigError(ValueError):
    """A rig config file is missing, is not JSON, or has a bad field."""
