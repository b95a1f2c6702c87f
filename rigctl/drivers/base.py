"""Device interfaces: the only surface procedures and the runner see.

Like python-can's ``BusABC``, each interface is abstract and has one backend per
hardware family (``rigctl.drivers.dynamixel``, ``rigctl.drivers.ur``,
``rigctl.drivers.camera``). All angles are radians, lengths metres, times seconds
(``time.time()`` epoch).
"""

from __future__ import annotations

import abc
import math
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl.errors import (
    AbortedError,
    ConfigError,
    DeviceError,
    ProtocolError,
    RigError,
    SafetyError,
    SolveError,
)

__all__ = [
    "AbortedError",
    "Arm",
    "ArmState",
    "Camera",
    "ConfigError",
    "Device",
    "DeviceError",
    "Frame",
    "Head",
    "HeadAngles",
    "ProtocolError",
    "RigError",
    "SafetyError",
    "SolveError",
    "Status",
    "check_axis_limit",
    "load_note",
]


def load_note(knobs: str | None) -> str:
    """A clause for a timeout message: the host's load, and the rig-file keys that give
    the device more time (``knobs``; None: no key helps). A process descheduled on a
    busy host (a stand-in, or the client itself) misses a timeout set for hardware; the
    message should say so."""
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:
        return (f"if the host is busy, raise {knobs} in the rig file" if knobs else
                "the host may have been too busy to reply in time")
    busy = "busy" if load >= 0.8 * cores else "not busy"
    note = f"host load {load:.1f} on {cores} cores ({busy}); a loaded host delays replies"
    return f"{note}, raise {knobs} in the rig file if this recurs" if knobs else note


def check_axis_limit(name: str, value: float, lo: float, hi: float) -> None:
    """Raise ``SafetyError`` naming the axis if ``value`` (rad) lies outside [lo, hi]."""
    if not (math.isfinite(value) and lo - 1e-9 <= value <= hi + 1e-9):
        raise SafetyError(
            f"{name}: target {math.degrees(value):.2f} deg outside soft limits "
            f"[{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg"
        )


class Status:
    """Completion handle of a motion, in the spirit of ophyd's Status objects.

    The device completes it from its own thread (``set_progress``, ``set_finished``,
    ``set_exception``); callers ``wait`` on it with a timeout and may ``watch`` progress.
    """

    def __init__(self, description: str = "") -> None:
        self.description = description
        self._event = threading.Event()
        self._lock = threading.Lock()
        self._exception: BaseException | None = None
        self._progress = 0.0

    @classmethod
    def finished(cls, description: str = "") -> Status:
        """A status that is already complete (for no-op moves)."""
        status = cls(description)
        status.set_finished()
        return status

    @property
    def done(self) -> bool:
        return self._event.is_set()

    @property
    def progress(self) -> float:
        return self._progress

    @property
    def exception(self) -> BaseException | None:
        return self._exception

    def set_progress(self, fraction: float) -> None:
        self._progress = float(min(max(fraction, 0.0), 1.0))

    def set_finished(self) -> None:
        if not self._event.is_set():
            self.set_progress(1.0)
            self._event.set()

    def set_exception(self, exc: BaseException) -> None:
        if not self._event.is_set():
            self._exception = exc
            self._event.set()

    def wait(self, timeout: float, abort: threading.Event | None = None) -> None:
        """Block until done; raise the device's exception, ``DeviceError`` on timeout,
        or ``AbortedError`` as soon as ``abort`` is set."""
        deadline = time.monotonic() + timeout
        while not self._event.wait(0.02):
            if abort is not None and abort.is_set():
                raise AbortedError(f"{self.description or 'motion'}: aborted")
            if time.monotonic() > deadline:
                raise DeviceError(
                    f"{self.description or 'motion'}: not complete after {timeout:.1f} s"
                )
        if self._exception is not None:
            raise self._exception


@dataclass(frozen=True)
class HeadAngles:
    """Pan (about y), tilt (about x), roll (about z) in radians, read at ``timestamp``."""

    pan: float
    tilt: float
    roll: float
    timestamp: float


@dataclass(frozen=True)
class ArmState:
    """Joint angles (rad), TCP pose (x, y, z m; rotation vector rad) and safety state."""

    q: tuple[float, ...]
    tcp_pose: tuple[float, ...]
    timestamp: float
    safety: str = "normal"  # normal | protective_stop | emergency_stop | fault


@dataclass
class Frame:
    """One image with its arrival time, sequence number and the settings in force."""

    image: np.ndarray
    timestamp: float
    sequence: int
    settings: dict[str, Any] = field(default_factory=dict)


class Device(abc.ABC):
    """Common life cycle: open on ``__enter__``, close (with park policy) on ``__exit__``."""

    kind = "device"

    @abc.abstractmethod
    def open(self) -> None:
        """Connect and configure the device."""

    @abc.abstractmethod
    def close(self) -> None:
        """Apply the park policy and disconnect; never raises for an already-closed device."""

    @abc.abstractmethod
    def describe(self) -> dict[str, Any]:
        """Provenance: model, firmware, serial, settings in force."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion now. Safe to call at any time, from any thread."""

    def park(self) -> None:
        """Apply the configured park policy (default: stop)."""
        self.stop()

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


class Head(Device):
    """A pan/tilt/roll camera head."""

    kind = "head"

    @abc.abstractmethod
    def move_to(self, pan: float, tilt: float, roll: float) -> Status:
        """Start a move to the given angles (rad); soft limits are checked first."""

    @abc.abstractmethod
    def read_angles(self) -> HeadAngles:
        """Present angles with the time they were read."""

    @abc.abstractmethod
    def set_torque(self, enabled: bool) -> None:
        """Enable or disable holding torque on every axis."""

    @abc.abstractmethod
    def limits(self) -> dict[str, tuple[float, float]]:
        """Soft limits per axis in radians: ``{"pan": (lo, hi), ...}``."""

    def check_limits(self, pan: float, tilt: float, roll: float) -> None:
        """Raise ``SafetyError`` naming the axis if a target lies outside its soft limits."""
        limits = self.limits()
        for axis, value in (("pan", pan), ("tilt", tilt), ("roll", roll)):
            check_axis_limit(f"head.{axis}", value, *limits[axis])


class Arm(Device):
    """A six-joint arm."""

    kind = "arm"
    n_joints = 6

    @abc.abstractmethod
    def move_joints(self, q) -> Status:
        """Start a joint move to ``q`` (rad) within the speed and acceleration caps."""

    def move_joint(self, index: int, angle: float) -> Status:
        """Move one joint (0-based ``index``) to ``angle``, holding the others."""
        q = list(self.read_state().q)
        q[index] = float(angle)
        return self.move_joints(q)

    @abc.abstractmethod
    def move_linear(self, pose) -> Status:
        """Straight-line TCP move to ``pose`` (x, y, z m; rotation vector rad)."""

    @abc.abstractmethod
    def read_state(self) -> ArmState:
        """Joints, TCP pose and safety state with a timestamp."""

    @abc.abstractmethod
    def joint_limits(self) -> list[tuple[float, float]]:
        """Soft joint limits in radians."""

    def check_limits(self, q) -> None:
        """Raise ``SafetyError`` naming the joint if ``q`` lies outside the soft limits."""
        limits = self.joint_limits()
        if len(q) != len(limits):
            raise SafetyError(f"arm: expected {len(limits)} joint values, got {len(q)}")
        for i, (value, (lo, hi)) in enumerate(zip(q, limits, strict=True)):
            check_axis_limit(f"arm.joint{i + 1}", value, lo, hi)


class Camera(Device):
    """A camera that returns fresh frames."""

    kind = "camera"

    @abc.abstractmethod
    def capture(self, not_before: float | None = None) -> Frame:
        """A frame that arrived no earlier than ``not_before`` (epoch seconds)."""

    def stop(self) -> None:  # a camera has no motion to stop
        return None
