"""The UR stand-in's clock while its loop idles (``Controller.wake``, ``at_rest``).

With nobody connected and nothing moving, the controller loop sleeps instead of stepping
500 times a second; whatever comes from outside (a connection, a control request, a
delayed program start) first brings the clock up to date in whole ticks. Pure logic of
the stand-in's own controller, in process: no sockets, no loop thread.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from rigctl.mocks.ur_controller import PERIOD, RUNTIME_PLAYING, Controller
from rigctl.mocks.ur_motion import JointMove


def _controller() -> Controller:
    return Controller("ur5e", {}, "nominal")


def test_waking_an_idle_controller_catches_its_clock_up_in_whole_ticks():
    ctrl = _controller()
    ctrl._idle = True
    ctrl._next_t = time.perf_counter() - 0.1  # the loop slept through 0.1 s (50 ticks)
    ctrl.wake()
    assert ctrl.tick >= 50
    assert ctrl.t == ctrl.tick * PERIOD
    assert ctrl._woken.is_set()


def test_waking_a_running_controller_leaves_its_clock_to_the_loop():
    ctrl = _controller()
    ctrl._idle = False
    ctrl._next_t = time.perf_counter() - 1.0
    ctrl.wake()
    assert ctrl.tick == 0 and ctrl.t == 0.0
    assert ctrl._woken.is_set()


def test_a_move_or_a_running_program_keeps_the_loop_stepping():
    ctrl = _controller()
    assert ctrl.at_rest()
    ctrl.motion = JointMove(ctrl.q, ctrl.q + np.radians(5.0), 1.0, 1.0, ctrl.t)
    assert not ctrl.at_rest()
    ctrl.motion = None
    ctrl.runtime_state = RUNTIME_PLAYING
    assert not ctrl.at_rest()


class _CountingEvent(threading.Event):
    """An event that records whether each wait ended by being set (True) or timed out."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: list[bool] = []

    def wait(self, timeout=None) -> bool:
        woken = super().wait(timeout)
        self.waits.append(woken)
        return woken


def test_an_idle_loop_sleeps_until_something_wakes_it():
    # three rounds of the loop with nobody connected and nothing moving: every sleep
    # times out, none is cut short by the loop itself (it once woke itself and spun)
    ctrl = _controller()
    ctrl._woken = _CountingEvent()
    stop = threading.Event()
    rounds = []

    def watched() -> bool:
        rounds.append(1)
        if len(rounds) > 3:
            stop.set()
        return False

    ctrl.run_loop(stop, watched)
    assert len(ctrl._woken.waits) >= 3 and not any(ctrl._woken.waits)
