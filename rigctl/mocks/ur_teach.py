"""Teach mode (free drive) of the UR controller stand-in.

ur_rtde's ``RTDEControlInterface.teachMode()`` and ``endTeachMode()`` send the control
script's commands 18 (``RobotCommand::Type::TEACH_MODE``) and 19 (``END_TEACH_MODE``)
through the register handshake (recipe 5 in ur_rtde 1.6's ``rtde_control_interface.cpp``);
its ``rtde_control.script`` answers them with ``teach_mode()`` and ``end_teach_mode()``
and reports "done". Teach mode lasts until ``end_teach_mode()`` or until the program
stops (a stopped program leaves free drive on a real controller too).

The operator's hand is the control socket's ``freedrive`` command: the joints are pushed
to ``q_deg`` at a hand's pace (``speed_dps``), refused while teach mode is off. While it
is on, the stand-in ignores the script's moveJ/moveL (a message says so): the arm is in
the operator's hands, and a runner that forgets to end teach mode sees its move fail.
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.mocks.ur_motion import JointMove

HAND_ACCEL = 2.0  # rad/s^2: a hand, not a motor
FREEDRIVE_TIMEOUT_S = 60.0


def start_teach(ctrl) -> None:
    """``teach_mode()``: free drive on (refused, with a message, in a stop)."""
    if ctrl.safety_mode != 1 or ctrl.estop:
        ctrl.messages.append("teach_mode(): refused, the arm is stopped")
        return
    ctrl.teach = True
    ctrl.messages.append("teach mode on")


def end_teach(ctrl, why: str) -> None:
    """``end_teach_mode()``, or the program's end: free drive off."""
    if ctrl.teach:
        ctrl.teach = False
        ctrl.messages.append(f"teach mode off: {why}")


def refuse_in_teach(ctrl, command: str) -> bool:
    """True (and a message) when a motion command arrives while teach mode is on."""
    if not ctrl.teach:
        return False
    ctrl.messages.append(f"{command} ignored: the arm is in teach mode (end_teach_mode first)")
    return True


def freedrive(ctrl, q_deg, speed_dps: float = 30.0) -> dict:
    """The operator pushes the arm to ``q_deg`` (degrees); answered once it is there, or
    refused (``ok`` false, ``error``) when teach mode is off or the target is bad."""
    try:
        q1 = np.radians(np.asarray(q_deg, float).reshape(6))
        speed = math.radians(float(speed_dps))
    except (TypeError, ValueError):
        return {"ok": False, "error": "freedrive needs q_deg: six joint angles in degrees"}
    if not np.all(np.isfinite(q1)) or not speed > 0:
        return {"ok": False, "error": "freedrive: q_deg and speed_dps must be finite"}
    with ctrl.lock:
        if not ctrl.teach:
            return {"ok": False, "error": "freedrive refused: teach mode is off (the arm "
                                          "holds its brakes and servo position)"}
        if not ctrl._check_joints(q1):
            return {"ok": False, "error": "freedrive: target outside the joint limits"}
        move = JointMove(ctrl.q, q1, speed, HAND_ACCEL, ctrl.t)
        ctrl.motion, ctrl.motion_kind = move, "hand"
        arrived = ctrl.tick_cond.wait_for(
            lambda: ctrl.motion is not move or not ctrl.teach, FREEDRIVE_TIMEOUT_S)
        if not arrived or not np.allclose(ctrl.q, q1, atol=1e-9):
            return {"ok": False, "error": "freedrive interrupted (teach mode ended or a "
                                          "stop)", "q": ctrl.q.tolist()}
        return {"ok": True, "q": ctrl.q.tolist()}
