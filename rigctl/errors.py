"""The one error hierarchy of rigctl.

Every error carries a message an operator can act on: it names what failed and
where (file and key, device and servo, packet, run).
"""

from __future__ import annotations


class RigError(Exception):
    """Base of every error rigctl raises on purpose."""


class ConfigError(RigError):
    """A rig file, world file or parameter is invalid; the message names file and key."""


class DeviceError(RigError):
    """A device failed, vanished or refused a command; the message names the device."""


class ProtocolError(DeviceError):
    """A device answered with a malformed or unexpected packet."""


class SafetyError(RigError):
    """A soft limit, protective stop or emergency stop stopped (or would stop) motion."""


class SolveError(RigError):
    """A solver found its input degenerate; the message names the cause."""


class BusyError(RigError):
    """The rig is held by another run."""


class AbortedError(RigError):
    """A run was stopped by an operator (Ctrl-C or an abort request)."""
