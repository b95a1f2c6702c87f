"""Suspenders: device conditions that pause a run instead of ending it (Bluesky's
suspenders). A protective stop, a servo alert or over-temperature, and a camera stall
pause the run; it continues by itself once the condition clears (polled with backoff,
each transition logged), or on the operator's request, and ends ``aborted`` after the
rig file's ``max_pause_s``. An emergency stop never pauses: it ends the run.

The runner raises ``SuspendError`` where it meets such a condition; ``wait_clear`` holds the
run while it lasts. Nothing here moves a device.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from rigctl.errors import AbortedError, DeviceError, RigError, SafetyError

log = logging.getLogger("rigctl.run")

# a servo over its temperature limit continues once this far below it (hysteresis)
TEMPERATURE_MARGIN_C = 5
POLL_FIRST_S, POLL_MAX_S, POLL_GROWTH = 0.2, 5.0, 1.5


class SuspendError(RigError):
    """A pausable condition met during a step: ``kind`` names the device (arm, camera,
    head), ``cause`` is the device's error (raised as is when pausing is off)."""

    def __init__(self, kind: str, reason: str, cause: RigError) -> None:
        super().__init__(reason)
        self.kind, self.reason, self.cause = kind, reason, cause
        self.done = 0  # 1 when the step itself completed (a capture kept)


@dataclass
class Continue:
    """Why a pause ended: the condition cleared, or the operator asked."""

    why: str


def arm_safety(arm) -> str:
    """The arm's safety state now: normal, protective_stop, emergency_stop; ``unknown``
    when the arm cannot be read."""
    try:
        return arm.read_state().safety
    except RigError:
        return "unknown"


def arm_suspend(arm, exc: RigError) -> SuspendError:
    """``SuspendError`` for a protective stop of ``arm``; ``exc`` itself (re-raised by the
    caller) for anything else, an emergency stop first of all."""
    if arm is not None and arm_safety(arm) == "protective_stop":
        return SuspendError("arm", f"arm: protective stop ({exc}); inspect the cause, then "
                       "`rigctl arm unlock`", exc)
    raise exc


def head_suspend(head, exc: RigError) -> SuspendError:
    """``SuspendError`` for a servo in alert or at its temperature limit; ``exc`` otherwise."""
    if isinstance(exc, DeviceError) and ("alert" in str(exc) or "temperature" in str(exc)):
        return SuspendError("head", f"head: {exc}; cool down, or `rigctl head reboot`", exc)
    read = getattr(head, "hardware_errors", None)
    try:
        alerts = read() if read is not None else {}
    except RigError:
        alerts = {}
    if alerts:
        return SuspendError("head", f"head: servo alert ({exc}); `rigctl head reboot`", exc)
    raise exc


def camera_suspend(exc: RigError) -> SuspendError:
    """``SuspendError`` for a camera that stopped delivering frames (a stall)."""
    if isinstance(exc, DeviceError):
        return SuspendError("camera", f"camera stall: {exc}", exc)
    raise exc


def _arm_clear(rig) -> str | None:
    arm = rig.devices.get("arm")
    state = arm_safety(arm) if arm is not None else "normal"
    if state == "emergency_stop":
        raise SafetyError("arm: emergency stop while the run was paused")
    return None if state == "normal" else f"arm safety {state}"


def _camera_clear(rig) -> str | None:
    camera = rig.devices.get("camera")
    if camera is None:
        return None
    try:
        camera.close()
        camera.open()
        camera.capture(not_before=time.time())
    except RigError as exc:
        return f"camera: {exc}"
    return None


def _head_clear(rig) -> str | None:
    """A servo alert cleared (``rigctl head reboot``) and every servo below its
    temperature limit by ``TEMPERATURE_MARGIN_C``. The port is held only for the check,
    so that the operator's bus tools can reach the servos in between."""
    head = rig.devices.get("head")
    if head is None:
        return None
    try:
        head.connect()
        try:
            health = head.health()
        finally:
            head.disconnect()
    except RigError as exc:
        return f"head: {exc}"
    for axis, h in health.items():
        if h["hardware_error"]:
            return f"head {axis}: hardware error {h['hardware_error']}"
        limit = h.get("temperature_limit_c")
        if limit is not None and h["temperature_c"] > limit - TEMPERATURE_MARGIN_C:
            return f"head {axis}: {h['temperature_c']} C (limit {limit} C)"
    return None


CHECKS: dict[str, Callable] = {"arm": _arm_clear, "camera": _camera_clear, "head": _head_clear}


def hold_safe(rig, kind: str) -> None:
    """Stop every device of a paused run; a head in alert lets go of its port (the
    operator's ``rigctl head reboot`` needs it). Never raises."""
    for problem in rig.stop_all():
        log.error("pause: %s", problem)
    head = rig.devices.get("head")
    if kind == "head" and head is not None and hasattr(head, "disconnect"):
        try:
            head.disconnect()
        except Exception as exc:  # a port already gone
            log.error("pause: head disconnect: %s", exc)


def recover(rig, kind: str) -> None:
    """Bring the device that paused the run back to work: the arm's control script
    restarted after an unlock (``URArm.recover``), the head opened again (a reboot
    turns torque off). The camera was reopened by its check."""
    if kind == "arm" and hasattr(rig.devices.get("arm"), "recover"):
        rig.devices["arm"].recover()
    elif kind == "head" and "head" in rig.devices:
        head = rig.devices["head"]
        head.disconnect()
        head.open()


def wait_clear(rig, kind: str, max_pause_s: float, abort: threading.Event,
               resume: threading.Event, abort_reason: Callable[[], str]) -> Continue:
    """Hold until the condition of ``kind`` clears (polled with backoff, from
    ``POLL_FIRST_S`` to ``POLL_MAX_S``) or the operator asks to continue (``resume``);
    ``AbortedError`` on ``abort`` or after ``max_pause_s``; ``SafetyError`` on an
    emergency stop meanwhile."""
    check = CHECKS[kind]
    deadline = time.monotonic() + max_pause_s
    delay, last = POLL_FIRST_S, None
    while True:
        if abort.is_set():
            raise AbortedError(abort_reason())
        asked = resume.is_set()
        resume.clear()
        state = check(rig)
        if state != last:
            log.info("paused (%s): %s", kind, state or "condition cleared")
            last = state
        if state is None:
            return Continue("operator resume" if asked else f"{kind} condition cleared")
        if asked:
            log.warning("resume requested, but the %s condition holds: %s", kind, state)
        if time.monotonic() > deadline:
            raise AbortedError(f"paused longer than max_pause_s ({max_pause_s:g} s): {state}")
        # the runner's abort() sets ``resume`` too, so either wakes this wait at once
        if not resume.wait(min(delay, max(0.0, deadline - time.monotonic()) + 0.01)):
            delay = min(delay * POLL_GROWTH, POLL_MAX_S)
