"""The UR stand-in's clock while its loop idles (``Controller.wake``, ``at_rest``).

With nobody connected and nothing moving, the controller loop sleeps instead of stepping
500 times a second; whatever comes from outside (a connection, a control request, a
delayed program start) first brings the clock up to date in whole ticks. Pure logic of
the stand-in's own controller, in process: no sockets, no loop thread.
"""

from __future__ import annotations

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
