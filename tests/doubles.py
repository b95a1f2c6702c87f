"""Small test doubles of the device interfaces, for runner tests only (issue 2).

Integration tests use the mock servers through the real client libraries instead.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np

from rigctl.drivers.base import Camera, DeviceError, Frame, Head, HeadAngles, Status


class DoubleHead(Head):
    """Moves at ``speed`` rad/s in a thread; records every call. Move number
    ``hold_on_move`` (1 = the first) stops half-way and stays under way until ``stop``
    (a latched fault: ``held`` is set once it stands there)."""

    def __init__(self, cfg, speed: float = 2.0, fail_on_move: int | None = None,
                 hold_on_move: int | None = None) -> None:
        self.cfg = cfg
        self.speed = speed
        self.fail_on_move = fail_on_move
        self.hold_on_move = hold_on_move
        self.held = threading.Event()
        self.calls: list[str] = []
        self.angles = np.zeros(3)
        self._stop = threading.Event()
        self.moves = 0
        self.is_open = False

    def open(self) -> None:
        self.calls.append("open")
        self.is_open = True

    def close(self) -> None:
        self.calls.append("close")
        if self.cfg.park.policy == "home" and self.is_open:
            self.angles = np.radians(self.cfg.park.angles_deg)
            self.calls.append("park:home")
        self.is_open = False

    def describe(self) -> dict:
        return {"model": "double", "firmware": 0}

    def limits(self):
        return self.cfg.limits_rad()

    def set_torque(self, enabled: bool) -> None:
        self.calls.append(f"torque:{enabled}")

    def stop(self) -> None:
        self.calls.append("stop")
        self._stop.set()

    def read_angles(self) -> HeadAngles:
        return HeadAngles(*self.angles, timestamp=time.time())

    def move_to(self, pan, tilt, roll) -> Status:
        self.check_limits(pan, tilt, roll)
        self.moves += 1
        self.calls.append(f"move:{math.degrees(pan):.1f},{math.degrees(tilt):.1f}")
        status = Status("double head move")
        if self.fail_on_move is not None and self.moves == self.fail_on_move:
            status.set_exception(DeviceError("head servo 2 (tilt): overload, torque off"))
            return status
        target = np.array([pan, tilt, roll])
        self._stop.clear()
        hold = self.moves == self.hold_on_move

        def motion():
            start = self.angles.copy()
            duration = max(np.max(np.abs(target - start)) / self.speed, 0.01)
            t0 = time.monotonic()
            while not self._stop.is_set():
                f = min((time.monotonic() - t0) / duration, 1.0)
                if hold and f >= 0.5:
                    f = 0.5
                    self.held.set()
                self.angles = start + f * (target - start)
                status.set_progress(f)
                if f >= 1.0:
                    status.set_finished()
                    return
                time.sleep(0.005)
            status.set_exception(DeviceError("stopped"))

        threading.Thread(target=motion, daemon=True).start()
        return status


class DoubleCamera(Camera):
    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self.sequence = 0

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def describe(self) -> dict:
        return {"model": "double camera"}

    def capture(self, not_before=None) -> Frame:
        self.sequence += 1
        image = np.full((self.cfg.height, self.cfg.width), self.sequence % 255, np.uint8)
        return Frame(image, time.time(), self.sequence, {"fourcc": self.cfg.fourcc})
