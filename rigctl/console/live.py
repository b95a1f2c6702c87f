"""The rig's state read now, for the console's rig page and ``GET /rig/live``.

While no run holds the rig, the devices are read without moving or writing anything:
the head through its bus (``DynamixelHead.connect``: ping and model check, then its
present angles and servo health, then the port closed; the bus lock keeps another
process's traffic apart) and the arm over RTDE's receive interface only (joints, TCP
pose, safety state; the control interface, which uploads a script, is never opened).
The rig lock is held for the read, so that no run starts on devices being read; a run
that asks meanwhile waits for it (``locks.RigLock.acquire``).

While a run holds the rig, the devices are its own: the newest capture's readings stand
in (the run reads them at every capture), marked as such.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

from rigctl.errors import BusyError, RigError
from rigctl.locks import BRIEF_HOLDER, rig_lock

LIVE_CACHE_S = 2.0  # a page refresh within this reuses the last reading
ARM_TIMEOUT_S = 5.0  # an RTDE receive interface that does not connect by then is reported


class LiveReadings:
    """Readings of ``service``'s rig: read now when the rig is free, else the newest
    capture's (``newest``: a callable giving ``rigview.newest_readings``'s dict).
    Each reading says its ``source``: ``read now`` or ``newest capture``; a device that
    could not be read is named under ``errors`` with the reason."""

    def __init__(self, service, newest) -> None:
        self.service = service
        self.newest = newest
        self._lock = threading.Lock()
        self._cached: tuple[float, dict[str, Any]] | None = None

    def read(self) -> dict[str, Any]:
        with self._lock:
            if self._cached and time.monotonic() - self._cached[0] < LIVE_CACHE_S:
                return self._cached[1]
            readings = self._read_devices()
            if readings is None:
                readings = {**self.newest(), "source": "newest capture"}
            self._cached = (time.monotonic(), readings)
            return readings

    def _read_devices(self) -> dict[str, Any] | None:
        """The devices read now, or None while a run holds the rig (or no device is
        configured to read)."""
        devices = self.service.config.devices
        if devices.head is None and devices.arm is None:
            return None
        lock = rig_lock(self.service.config)
        try:
            lock.acquire(BRIEF_HOLDER)
        except BusyError:
            return None
        try:
            out: dict[str, Any] = {"source": "read now", "time": time.time(), "errors": {}}
            if devices.head is not None:
                _read_head(devices.head, out)
            if devices.arm is not None:
                _read_arm(devices.arm, out)
            return out
        finally:
            lock.release()


def _read_head(cfg, out: dict[str, Any]) -> None:
    from rigctl.drivers.dynamixel import DynamixelHead

    head = DynamixelHead(cfg)
    try:
        head.connect()
        angles = head.read_angles()
        out["head"] = {"pan": angles.pan, "tilt": angles.tilt, "roll": angles.roll,
                       "timestamp": angles.timestamp}
        out["head_health"] = head.health()
    except (RigError, OSError) as exc:
        out["errors"]["head"] = f"{cfg.port}: {exc}"
    finally:
        with contextlib.suppress(OSError):  # a port that vanished: already named above
            head.disconnect()


def _read_arm(cfg, out: dict[str, Any]) -> None:
    import rtde_receive

    from rigctl.drivers.ur import bounded_call

    try:
        receive = bounded_call(
            lambda: rtde_receive.RTDEReceiveInterface(cfg.host, cfg.rtde_frequency_hz),
            ARM_TIMEOUT_S, "RTDE receive interface")
    except (RuntimeError, RigError) as exc:
        out["errors"]["arm"] = f"{cfg.host}: RTDE receive interface: {exc}"
        return
    try:
        safety = ("emergency_stop" if receive.isEmergencyStopped() else
                  "protective_stop" if receive.isProtectiveStopped() else "normal")
        out["arm"] = {"q": list(receive.getActualQ()),
                      "tcp_pose": list(receive.getActualTCPPose()),
                      "timestamp": time.time(), "safety": safety}
    except RuntimeError as exc:
        out["errors"]["arm"] = f"{cfg.host}: {exc}"
    finally:
        with contextlib.suppress(RuntimeError):  # a link already lost: named above
            receive.disconnect()
