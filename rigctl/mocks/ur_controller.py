"""A Universal Robots controller stand-in (CB3, e-Series, UR-Series) that the real
``ur_rtde`` client drives.

Serves RTDE (30004), the dashboard (29999), the script port (30003) and the primary and
secondary interfaces (30001/30002: version, then robot state with KINEMATICS_INFO at 10 Hz)
on one loopback address, and runs a 500 Hz controller loop. Each model (``--model``, as
ur_description spells it: ur3 ... ur30) is played from the stand-in's own table
(``rigctl.mocks.ur_models``): its DH, its joint position limits and speeds, and what its
controller reports (software version on RTDE, the primary interface and the dashboard;
``get robot model``; serial number). A CB3 reports 3.15: ur_rtde then streams at 125 Hz,
skips the serial-number query and strips the ``$5.x`` lines of its control script, and
the dashboard refuses what a CB3 does not have (``safetystatus``, ``is in remote
control``). It recognises the uploaded ``rtde_control`` script and emulates its register
handshake (see ``shared/reference/ur-controller-protocol.md``)::

    rigctl mock arm [--host 127.0.0.1] [--model ur5e] [--world FILE] [--control SOCKET]
                    [--tcp-model factory|nominal|true]

Prints one JSON ready line and runs until SIGTERM. Control socket (JSON lines):
``protective_stop``, ``emergency_stop``, ``release_estop``, ``drop_connections``,
``stall_stream`` (for ``seconds``, or until ``resume_stream`` when none is given: a
latched fault), ``resume_stream``, ``freedrive`` (the operator's hand: ``q_deg``, six
joint angles the arm is pushed to, answered once it is there; refused unless the control
script's ``teach_mode()`` is on, see ``ur_teach``), ``freeze`` (``at_fraction``: the
move under way or the next one holds once it has run that fraction of its time, latched
until ``thaw`` or until a new motion command ends it), ``thaw``, ``script_start_delay``
(``seconds`` from an uploaded script to its program running; the running program ends at
once, and a stop meanwhile cancels the start), ``dump``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import socket
import struct
import sys
import threading
import time
from enum import IntEnum
from pathlib import Path

import numpy as np
import yaml

from rigctl.mocks import ur_models as models
from rigctl.mocks.jsonlines import listen, serve_stream
from rigctl.mocks.ur_kinematics import ArmModel, matrix_to_pose, pose_to_matrix
from rigctl.mocks.ur_motion import JointMove, LinearMove, ServoMove, SpeedMove, StopMove
from rigctl.mocks.ur_primary import dh_table, robot_state, version_message
from rigctl.mocks.ur_teach import end_teach, freedrive, refuse_in_teach, start_teach

log = logging.getLogger("mock.ur")

PERIOD = 0.002
REST_TICKS = 5  # the loop's ticks per wake-up while the arm is at rest (``run_loop``)
STREAM_RESYNC_S = 0.05  # a stream this late drops the packages it missed
JOINT_ACCEL_MAX = 40.0  # rad/s^2
# RTDE outputs a CB3 (3.x) does not offer (RTDE guide: added with PolyScope 5.x)
E_SERIES_ONLY_OUTPUTS = frozenset({"ft_raw_wrench", "actual_current_as_torque"})
# dashboard commands a CB3 does not know (UR Client Library's command table: 5.x only)
E_SERIES_ONLY_DASHBOARD = frozenset({"safetystatus", "is in remote control",
                                     "get operational mode"})

# Runtime, robot and safety modes as the RTDE guide numbers them.
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4
ROBOT_POWER_OFF, ROBOT_IDLE, ROBOT_RUNNING = 3, 5, 7
SAFETY_NORMAL, SAFETY_PROTECTIVE, SAFETY_ROBOT_ESTOP = 1, 3, 7


class Cmd(IntEnum):
    """Control-script command numbers (ur_rtde's ``RobotCommand::Type``, as the 1.6.5
    control script numbers them) that the stand-in serves or tells apart."""

    NO_CMD = 0  # the client's "clear": the previous command is taken
    MOVEJ = 1
    MOVEJ_IK = 2
    MOVEL = 3
    MOVEL_FK = 4
    FORCE_MODE = 6
    SPEEDJ = 9
    SPEEDL = 10
    SERVOJ = 11
    SPEED_STOP = 15
    SERVO_STOP = 16
    SET_PAYLOAD = 17
    TEACH_MODE = 18  # teachMode(): the script calls teach_mode()
    END_TEACH_MODE = 19  # endTeachMode(): end_teach_mode()
    SERVOL = 24
    TOOL_CONTACT = 25
    GET_STEPTIME = 26
    GET_ACTUAL_JOINT_POSITIONS_HISTORY = 27
    SET_TCP = 29
    GET_INVERSE_KINEMATICS_ARGS = 30
    PROTECTIVE_STOP = 31
    STOPL = 33
    STOPJ = 34
    SET_WATCHDOG = 35
    IS_POSE_WITHIN_SAFETY_LIMITS = 36
    IS_JOINTS_WITHIN_SAFETY_LIMITS = 37
    GET_JOINT_TORQUES = 38
    POSE_TRANS = 39
    GET_TCP_OFFSET = 40
    GET_FORWARD_KINEMATICS_DEFAULT = 43
    GET_FORWARD_KINEMATICS_ARGS = 44
    GET_INVERSE_KINEMATICS_DEFAULT = 46
    IS_STEADY = 47
    GET_ACTUAL_TOOL_FLANGE_POSE = 58
    GET_INVERSE_KINEMATICS_HAS_SOLUTION_DEFAULT = 60
    GET_INVERSE_KINEMATICS_HAS_SOLUTION_ARGS = 61
    DIRECT_TORQUE = 66
    GET_MASS_MATRIX = 67
    GET_CORIOLIS_AND_CENTRIFUGAL_TORQUES = 68
    GET_TARGET_JOINT_ACCELERATIONS = 69
    GET_JACOBIAN = 70
    GET_JACOBIAN_TIME_DERIVATIVE = 71
    STOP_SCRIPT = 255


# output_int_register_0 of the handshake (ur_rtde's UR_CONTROLLER_RDY_FOR_CMD and
# UR_CONTROLLER_DONE_WITH_CMD)
CMD_READY, CMD_DONE = 1, 2

# The script's real-time commands: applied every cycle while the register holds them,
# then "ready", never "done" (the script's main loop lists these numbers)
REALTIME_CMDS = frozenset({
    Cmd.SERVOL, Cmd.SERVOJ, Cmd.SPEEDJ, Cmd.SPEEDL, Cmd.FORCE_MODE, Cmd.TOOL_CONTACT,
    Cmd.GET_STEPTIME, Cmd.GET_ACTUAL_JOINT_POSITIONS_HISTORY, Cmd.GET_JOINT_TORQUES,
    Cmd.GET_ACTUAL_TOOL_FLANGE_POSE, Cmd.DIRECT_TORQUE, Cmd.GET_MASS_MATRIX,
    Cmd.GET_CORIOLIS_AND_CENTRIFUGAL_TORQUES, Cmd.GET_TARGET_JOINT_ACCELERATIONS,
    Cmd.GET_JACOBIAN, Cmd.GET_JACOBIAN_TIME_DERIVATIVE})

FIELD_SIZES = {"DOUBLE": ">d", "VECTOR6D": ">6d", "VECTOR3D": ">3d", "INT32": ">i",
               "UINT32": ">I", "UINT64": ">Q", "VECTOR6INT32": ">6i", "UINT8": ">B",
               "BOOL": ">?", "VECTOR6UINT32": ">6I"}

OUTPUT_TYPES = {
    "timestamp": "DOUBLE", "actual_execution_time": "DOUBLE", "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE", "payload": "DOUBLE", "io_current": "DOUBLE",
    "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
    "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE",
    "robot_mode": "INT32", "safety_mode": "INT32", "safety_status": "INT32",
    "tool_output_voltage": "INT32",
    "runtime_state": "UINT32", "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32", "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
    "script_control_line": "UINT32", "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
    "joint_mode": "VECTOR6INT32",
    "actual_tool_accelerometer": "VECTOR3D", "payload_cog": "VECTOR3D",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
    **{name: "VECTOR6D" for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
        "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose",
        "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
        "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench", "payload_inertia",
        "actual_current_as_torque")},
    **{f"output_int_register_{i}": "INT32" for i in range(48)},
    **{f"output_double_register_{i}": "DOUBLE" for i in range(48)},
}
INPUT_TYPES = {
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
    "external_force_torque": "VECTOR6D", "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32", "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE", "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8", "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8", "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8", "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8", "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
}


def load_arm_section(path: str | None) -> dict:
    """``arm`` of a world file (``errors``, ``home_deg``), or a small YAML of ``errors``."""
    if not path:
        return {}
    data = yaml.safe_load(Path(path).read_text()) or {}
    return data.get("arm", data) or {}


_ZERO6 = np.zeros(6)
# RTDE output fields that the stand-in holds constant (read-only arrays: a snapshot is
# shared with the stream threads and never changed in place)
_CONSTANT_FIELDS = {
    "target_qdd": _ZERO6, "target_current": _ZERO6, "target_moment": _ZERO6,
    "actual_current": np.full(6, 0.3), "joint_control_output": _ZERO6,
    "actual_TCP_force": _ZERO6, "actual_digital_input_bits": 0,
    "joint_temperatures": np.full(6, 31.5), "actual_execution_time": 0.4,
    "joint_mode": [253] * 6, "actual_tool_accelerometer": [0.0, 0.0, 9.81],
    "speed_scaling": 1.0, "target_speed_fraction": 1.0, "actual_momentum": 0.0,
    "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0,
    "actual_robot_current": 0.8, "actual_joint_voltage": np.full(6, 47.9),
    "actual_digital_output_bits": 0,
    "standard_analog_input0": 0.0, "standard_analog_input1": 0.0,
    "standard_analog_output0": 0.0, "standard_analog_output1": 0.0,
    "ft_raw_wrench": _ZERO6, "payload_cog": [0.0, 0.0, 0.0], "payload_inertia": _ZERO6,
    "actual_current_as_torque": _ZERO6, "elbow_velocity": [0.0, 0.0, 0.0],
}
for _value in _CONSTANT_FIELDS.values():
    if isinstance(_value, np.ndarray):
        _value.flags.writeable = False
_OUT_INT_NAMES = [f"output_int_register_{i}" for i in range(48)]
_OUT_DOUBLE_NAMES = [f"output_double_register_{i}" for i in range(48)]


class Controller:
    """Robot state, the running control script, and the 500 Hz loop."""

    def __init__(self, model: str, errors: dict, tcp_model: str,
                 home_deg: list[float] | None = None, factory_errors: dict | None = None,
                 calibration_status: int = 0) -> None:
        self.nominal = ArmModel.nominal(model)
        self.version = models.version(model)
        self.cb3 = models.is_cb3(model)
        self.limits = np.array(models.joint_limits_rad(model))
        self.speed_max = np.array(models.joint_speed_max(model))
        self.seen = {"rtde_frequencies": [], "script_lines": [], "dashboard": []}
        self.true = self.nominal.with_errors(**errors)
        self.factory = None if factory_errors is None else \
            self.nominal.with_errors(**factory_errors)
        self.model_name = model
        # The controller's own kinematics (behind actual_TCP_pose, FK, IK and the primary
        # interface's KINEMATICS_INFO): its factory calibration when the world has one.
        self.ctrl_model = {"true": self.true, "nominal": self.nominal}.get(
            tcp_model, self.factory or self.nominal)
        self.dh = dh_table(self.ctrl_model)
        self.calibration_status = calibration_status
        self.lock = threading.RLock()
        self.tick_cond = threading.Condition(self.lock)
        self.tick = 0
        # each RTDE stream's ticks per package, by stream: a stream faster than
        # REST_TICKS ticks a package caps the ticks stepped at one wake-up (``run_loop``)
        self.stream_ticks: dict[int, int] = {}
        self.loop_fault: str | None = None  # the loop's next wake-up raises this (``fail_loop``)
        self.t = 0.0
        self.q = np.radians(home_deg or [0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
        self.qd = np.zeros(6)
        self.q_target = self.q.copy()
        self.tcp = np.eye(4)
        self.payload = 0.0
        self.motion = None
        self.motion_kind = None  # "sync" | "async" | "stop_async" | "rt"
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.reg_offset = 0
        self.runtime_state = RUNTIME_STOPPED
        self.robot_mode = ROBOT_RUNNING
        self.safety_mode = SAFETY_NORMAL
        self.executing = False
        self.pending_done = False
        self.async_op_id = 0
        self.async_wr_count = 0
        self.watchdog_hz = 0.0
        self.last_input = time.monotonic()
        self.stall_until = 0.0
        self.script_start_s = 0.0  # from an uploaded script to its program running
        self.uploads = 0  # scripts uploaded and programs stopped, counted together
        # a held move (a test's latched fault, ``freeze``): armed at a fraction of the
        # next (or current) move's time; ``held`` is the move standing still
        self.freeze_at: float | None = None
        self.held = None
        self.estop = False
        self.teach = False  # teach_mode() of the running script (free drive)
        self.messages: list[str] = []
        self._snapshot: dict = {}
        self._snapshot_tick = -1
        self.steady_since = 0.0

    # -- registers --------------------------------------------------------------

    def rint(self, i: int) -> int:
        return self.in_int[i + self.reg_offset]

    def rdouble(self, i: int) -> float:
        return self.in_double[i + self.reg_offset]

    def wint(self, i: int, v: int) -> None:
        self.out_int[i + self.reg_offset] = int(v)

    def wdouble(self, i: int, v: float) -> None:
        self.out_double[i + self.reg_offset] = float(v)

    def q_from(self, i: int) -> np.ndarray:
        return np.array([self.rdouble(i + k) for k in range(6)])

    def to_out(self, i: int, values) -> None:
        for k, v in enumerate(values):
            self.wdouble(i + k, v)

    def _async_progress(self, value: int) -> None:
        self.async_wr_count = (self.async_wr_count + 1) % 128
        if value == 0:
            self.async_op_id = (self.async_op_id + 1) % 128
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.wint(2, reg)

    # -- program life cycle ------------------------------------------------------

    def load_script(self, text: str) -> None:
        lines = text.splitlines()
        self.seen["script_lines"].append(len(lines))
        offset = 0
        for i, line in enumerate(lines):
            if "reg_offset_int" in line and "=" in line and i + 1 < len(lines):
                try:
                    offset = int(lines[i + 1].split()[0])
                except (ValueError, IndexError):
                    offset = 0
                break
        with self.lock:
            self.uploads += 1
            upload = self.uploads
            delayed = self.script_start_s > 0
            if delayed:  # a controller compiling the new program: the old one has ended
                self.runtime_state = RUNTIME_STOPPED
        if delayed:
            threading.Timer(self.script_start_s, self._start_program,
                            (offset, upload, True)).start()
        else:
            self._start_program(offset, upload)

    def _cancel_start(self) -> None:
        """A program still starting (``script_start_delay``) never runs. Under the lock."""
        self.uploads += 1

    def _start_program(self, offset: int, upload: int, delayed: bool = False) -> None:
        with self.lock:
            if upload != self.uploads:  # stopped, or another script came, meanwhile
                return
            if delayed and self.safety_mode != SAFETY_NORMAL:  # a stop meanwhile
                self.messages.append("program rtde_control not started: safety stop")
                return
            self.reg_offset = offset
            self.executing = False
            self.pending_done = False
            self.wint(0, 0)
            self._async_progress(-1)
            self.wint(0, CMD_READY)
            self.runtime_state = RUNTIME_PLAYING
            self.messages.append(f"program rtde_control started (register offset {offset})")

    def stop_program(self, reason: str) -> None:
        with self.lock:
            self._cancel_start()
            if self.runtime_state != RUNTIME_STOPPED:
                self.messages.append(f"program stopped: {reason}")
            self.runtime_state = RUNTIME_STOPPED
            self._stop_motion(4.0)
            end_teach(self, "the program stopped")

    def _stop_motion(self, decel: float) -> None:
        if self.motion is not None and np.any(np.abs(self.qd) > 1e-9):
            self.motion = StopMove(self.q, self.qd, decel, self.t)
            self.motion_kind = "halt"
        elif self.motion_kind != "halt":
            self.motion = None
            self.motion_kind = None

    def protective_stop(self, reason: str) -> None:
        with self.lock:
            self._cancel_start()
            self.safety_mode = SAFETY_PROTECTIVE
            self.messages.append(f"protective stop: {reason}")
            self._stop_motion(20.0)
            end_teach(self, "protective stop")
            if self.runtime_state == RUNTIME_PLAYING:
                self.runtime_state = RUNTIME_PAUSED

    def emergency_stop(self) -> None:
        with self.lock:
            self._cancel_start()
            self.estop = True
            self.safety_mode = SAFETY_ROBOT_ESTOP
            self.robot_mode = ROBOT_POWER_OFF
            self.motion, self.motion_kind, self.qd = None, None, np.zeros(6)
            self.runtime_state = RUNTIME_STOPPED
            self.messages.append("emergency stop")
            end_teach(self, "emergency stop")

    # -- commands ----------------------------------------------------------------

    def _check_joints(self, q) -> bool:
        return bool(np.all(np.abs(q) <= self.limits))

    def _caps(self, v: float, a: float, delta=None) -> tuple[float, float]:
        """moveJ's leading-joint speed and acceleration, capped so that no joint exceeds
        its own maximum speed (the joints move in step, each at |delta_i| / max|delta| of
        the leading joint's speed)."""
        v, a = max(v, 1e-6), min(max(a, 1e-6), JOINT_ACCEL_MAX)
        vmax = float(np.max(self.speed_max))
        if delta is not None and np.max(np.abs(delta)) > 0:
            share = np.abs(delta) / np.max(np.abs(delta))
            moving = share > 0
            vmax = float(np.min(self.speed_max[moving] / share[moving]))
        if v > vmax:
            self.messages.append(f"moveJ speed {v:.3f} rad/s capped at {vmax:.3f} rad/s "
                                 "(joint speed limits)")
        return min(v, vmax), a

    def _start_joint_move(self, q1, v, a, sync: bool) -> bool:
        if not self._check_joints(q1):
            self.messages.append("moveJ target outside the joint limits: program halted")
            self.stop_program("joint limit violation")
            return False
        v, a = self._caps(v, a, np.asarray(q1) - self.q)
        self.motion = JointMove(self.q, q1, v, a, self.t)
        self._begin(sync)
        return True

    def _begin(self, sync: bool) -> None:
        self.motion_kind = "sync" if sync else "async"
        if not sync:
            self._async_progress(0)

    def process(self, cmd: int) -> None:
        """One command of the control script (``SCRIPT_HANDLERS``); sets
        ``pending_done`` for blocking ones. Unknown commands are ignored, as the real
        script ignores commands it has no branch for."""
        handler = SCRIPT_HANDLERS.get(cmd)
        if handler is not None:
            handler(self, self.rint(1) == 1)

    # -- script commands (the register layout is ur_rtde's control script) -----------

    def _cmd_move(self, cmd: int, async_flag: bool) -> None:
        v, a = self.rdouble(6), self.rdouble(7)
        self._kill_async()
        if refuse_in_teach(self, Cmd(cmd).name):
            return
        if cmd == Cmd.MOVEJ:
            self._start_joint_move(self.q_from(0), v, a, not async_flag)
        elif cmd == Cmd.MOVEJ_IK:
            q = self.ctrl_model.ik(pose_to_matrix(self.q_from(0)), self.q, self.tcp)
            if q is None:
                self.stop_program("moveJ_IK: no inverse kinematics solution")
                return
            self._start_joint_move(q, v, a, not async_flag)
        else:  # MOVEL to a pose, MOVEL_FK to joints
            T1 = pose_to_matrix(self.q_from(0)) if cmd == Cmd.MOVEL else \
                self.ctrl_model.tool(self.q_from(0), self.tcp)
            self.motion = LinearMove(self.ctrl_model, self.tcp, self.q, T1,
                                     min(v, 3.0), min(a, 15.0), self.t)
            self._begin(not async_flag)
        self.pending_done = not async_flag

    def _cmd_stop_move(self, async_flag: bool) -> None:  # stopL, stopJ
        decel = max(self.rdouble(0), 0.1)
        self._kill_async()
        self.motion = StopMove(self.q, self.qd, decel, self.t)
        if async_flag:
            self.motion_kind = "stop_async"
            self._async_progress(0)
        else:
            self.motion_kind = "sync"
            self.pending_done = True

    def _cmd_stop_realtime(self, _async: bool) -> None:  # speedStop, servoStop
        self.motion = StopMove(self.q, self.qd, max(self.rdouble(0), 0.1), self.t)
        self.motion_kind = "sync"
        self.pending_done = True

    def _cmd_speedj(self, _async: bool) -> None:
        target, accel = self.q_from(0), max(self.rdouble(6), 1e-3)
        target = np.clip(target, -self.speed_max, self.speed_max)
        if isinstance(self.motion, SpeedMove):
            self.motion.update(target, accel)
        else:
            self.motion = SpeedMove(self.q, self.qd, target, accel, self.t)
        self.motion_kind = "rt"

    def _cmd_servoj(self, _async: bool) -> None:
        target = self.q_from(0)
        if not self._check_joints(target):
            self.protective_stop("servoJ target outside the joint limits")
            return
        if isinstance(self.motion, ServoMove):
            self.motion.update(target, self.rdouble(9))
        else:
            self.motion = ServoMove(self.q, target, self.rdouble(9), self.speed_max, self.t)
        self.motion_kind = "rt"

    def _cmd_inverse_kinematics(self, cmd: int) -> None:
        with_q_near = cmd in (Cmd.GET_INVERSE_KINEMATICS_ARGS,
                              Cmd.GET_INVERSE_KINEMATICS_HAS_SOLUTION_ARGS)
        q_near = self.q_from(6) if with_q_near else self.q
        q = self.ctrl_model.ik(pose_to_matrix(self.q_from(0)), q_near, self.tcp)
        if cmd in (Cmd.GET_INVERSE_KINEMATICS_HAS_SOLUTION_DEFAULT,
                   Cmd.GET_INVERSE_KINEMATICS_HAS_SOLUTION_ARGS):
            self.wint(1, 1 if q is not None else 0)
        elif q is not None:
            self.to_out(0, q)
        else:
            self.stop_program("get_inverse_kin: no solution")

    def _cmd_set_watchdog(self) -> None:
        self.watchdog_hz = self.rdouble(0)
        self.last_input = time.monotonic()

    def _cmd_pose_within_limits(self) -> None:
        q = self.ctrl_model.ik(pose_to_matrix(self.q_from(0)), self.q, self.tcp)
        self.wint(1, int(q is not None and self._check_joints(q)))

    def _cmd_stop_script(self) -> None:
        self.messages.append("received stop script")
        self.runtime_state = RUNTIME_STOPPED
        self._stop_motion(4.0)
        end_teach(self, "the program stopped")

    def _kill_async(self) -> None:
        if self.motion_kind in ("async", "stop_async") and self.motion is not None:
            self._async_progress(-1)
        self.motion_kind = None

    def is_steady(self) -> bool:
        return self.motion is None and self.t - self.steady_since > 0.02

    # -- loop --------------------------------------------------------------------

    def step(self) -> None:
        with self.lock:
            self.tick += 1
            self.t = self.tick * PERIOD
            self._advance_motion()
            self._run_program()
            if self.watchdog_hz > 0 and self.runtime_state == RUNTIME_PLAYING and \
                    time.monotonic() - self.last_input > 1.0 / self.watchdog_hz:
                self.watchdog_hz = 0.0
                self.stop_program("RTDE watchdog: input registers not updated in time")
            self.tick_cond.notify_all()

    def freeze(self, at_fraction: float) -> None:
        """Hold the move under way, or the next joint or linear move, once it has run
        ``at_fraction`` of its time: the arm stands still there, the move not done, until
        ``thaw`` or until a new motion command (a stop, another move) replaces it."""
        if not 0.0 <= at_fraction < 1.0:
            raise ValueError(f"freeze at_fraction {at_fraction} outside [0, 1)")
        with self.lock:
            self.freeze_at, self.held = at_fraction, None

    def thaw(self) -> None:
        """Let a held move go on from where it stands (and disarm a freeze not yet due)."""
        with self.lock:
            self.freeze_at, self.held = None, None

    def _holding(self) -> bool:
        """Whether the move stands still this tick (latching an armed freeze when its
        move has run far enough); a held move's clock stops with it."""
        m = self.motion
        if self.held is not None and self.held is not m:
            self.held = None  # a new motion command ended the held move
        if self.held is None and self.freeze_at is not None \
                and isinstance(m, (JointMove, LinearMove)) and m.total > 0 \
                and m.progress(self.t) >= self.freeze_at:
            self.held, self.freeze_at = m, None
            return False  # this tick's step lands where it holds
        if self.held is None:
            return False
        m.t0 += PERIOD
        return True

    def _advance_motion(self) -> None:
        if self.motion is None:
            self.qd = _ZERO6
            return
        if self._holding():
            self.qd = _ZERO6
            return
        q, qd, done = self.motion.step(self.t)
        if not self._check_joints(q):
            self.q, self.qd = self.q, np.zeros(6)
            self.motion = None
            self.protective_stop("joint position limit reached")
            return
        # a move that latched its hold this tick lands there and stands: no speed left
        # for a stop to decelerate from
        self.q, self.qd = q, (_ZERO6 if self.held is self.motion else qd)
        if isinstance(self.motion, LinearMove) and self.motion.failed:
            self.motion = None
            self.stop_program("moveL: path left the workspace")
            return
        if done:
            kind = self.motion_kind
            self.motion, self.motion_kind = None, None
            self.qd = _ZERO6
            self.steady_since = self.t
            if kind in ("async", "stop_async"):
                self._async_progress(-1)

    def _run_program(self) -> None:
        if self.runtime_state != RUNTIME_PLAYING:
            return
        if self.pending_done:
            if self.motion is None or self.motion_kind not in ("sync",):
                self.pending_done = False
                self.wint(0, CMD_DONE)
            return
        cmd = self.rint(0)
        if cmd in REALTIME_CMDS:
            self.process(cmd)
            self.wint(0, CMD_READY)
        elif cmd == Cmd.NO_CMD:
            self.executing = False
            self.wint(0, CMD_READY)
        elif not self.executing:
            self.executing = True
            self.process(cmd)
            if not self.pending_done and cmd != Cmd.STOP_SCRIPT:
                self.wint(0, CMD_DONE)

    @property
    def snapshot(self) -> dict:
        """The state the RTDE streams send for the newest tick (the caller holds
        ``lock``): made when first read after a tick, not at every tick, since the streams
        read at their own rate (125 Hz or less, 500 at most) and a moving arm's pose
        fields cost a forward kinematics and a Jacobian each."""
        if self._snapshot_tick != self.tick:
            self._update_snapshot()
            self._snapshot_tick = self.tick
        return self._snapshot

    def _update_snapshot(self) -> None:
        """The state the RTDE stream sends this tick. The pose-dependent fields are
        computed again only when the joints or the TCP changed (500 times a second at
        rest would cost a tenth of a core)."""
        key = (self.q.tobytes(), self.tcp.tobytes())
        if key != getattr(self, "_pose_key", None):
            self._pose_key = key
            flange = self.ctrl_model.flange(self.q)
            self._pose = matrix_to_pose(flange @ self.tcp)
            self._elbow = flange[:3, 3] * 0.5
        pose = self._pose
        J = self.ctrl_model.jacobian(self.q, self.tcp) if np.any(self.qd) else None
        tcp_speed = J @ self.qd if J is not None else _ZERO6
        safety_bits = {SAFETY_NORMAL: 0x01, SAFETY_PROTECTIVE: 0x04,
                       SAFETY_ROBOT_ESTOP: 0x40 | 0x80}.get(self.safety_mode, 0)
        running = self.runtime_state == RUNTIME_PLAYING
        robot_bits = (0x01 if self.robot_mode >= ROBOT_IDLE else 0) | (0x02 if running else 0)
        snap = dict(_CONSTANT_FIELDS)
        snap.update({
            "timestamp": self.t, "target_q": self.q, "target_qd": self.qd,
            "actual_q": self.q, "actual_qd": self.qd,
            "actual_TCP_pose": pose, "actual_TCP_speed": tcp_speed, "target_TCP_pose": pose,
            "target_TCP_speed": tcp_speed,
            "robot_mode": self.robot_mode,
            "safety_mode": self.safety_mode, "safety_status": self.safety_mode,
            "runtime_state": self.runtime_state,
            "robot_status_bits": robot_bits, "safety_status_bits": safety_bits,
            "payload": self.payload, "elbow_position": self._elbow,
        })
        snap.update(zip(_OUT_INT_NAMES, self.out_int, strict=True))
        snap.update(zip(_OUT_DOUBLE_NAMES, self.out_double, strict=True))
        self._snapshot = snap

    def at_rest(self) -> bool:
        """Whether the arm stands with no move under way, none about to report done,
        and no free drive: a tick then changes nothing but the clock."""
        return self.motion is None and not self.pending_done and not self.teach

    def run_loop(self, stop: threading.Event) -> None:
        next_t = time.perf_counter()
        while not stop.is_set():
            # At rest, up to REST_TICKS ticks are stepped at one wake-up (no more than
            # the fastest stream's ticks per package), then the loop sleeps their
            # periods: the wake-ups at rest, most of the stand-in's CPU, drop to one in
            # REST_TICKS. A tick that leaves the rest (a command began a move) ends the
            # burst, and the next ticks come one a period again. At rest the clock is
            # then up to burst - 1 periods ahead, and a command is taken up as late:
            # within one package of the fastest stream.
            with self.lock:
                if self.loop_fault is not None:  # injected (control socket ``fail_loop``)
                    raise RuntimeError(self.loop_fault)
                burst = min([REST_TICKS, *self.stream_ticks.values()])
            ticks = 0
            while True:
                self.step()
                ticks += 1
                if ticks >= burst or not self.at_rest():
                    break
            next_t += ticks * PERIOD
            remaining = next_t - time.perf_counter()
            if remaining > 0:
                time.sleep(remaining)  # never spin: spinning holds the GIL from the streams
            if time.perf_counter() - next_t > 0.05:  # fell far behind: resynchronise
                next_t = time.perf_counter()

    def dump(self) -> dict:
        with self.lock:
            return {"t": self.t, "q": self.q.tolist(), "qd": self.qd.tolist(),
                    "tcp_pose": matrix_to_pose(self.ctrl_model.tool(self.q, self.tcp)).tolist(),
                    "runtime_state": self.runtime_state, "robot_mode": self.robot_mode,
                    "safety_mode": self.safety_mode, "out_int": self.out_int[:4],
                    "messages": self.messages[-20:], "messages_total": len(self.messages),
                    "model": self.model_name,
                    "frozen": self.held is not None and self.held is self.motion,
                    "teach_mode": self.teach,
                    "version": list(self.version), "seen": self.seen,
                    "joint_speed_max": self.speed_max.tolist(),
                    "joint_limits": [None if math.isinf(v) else v for v in self.limits]}


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("peer closed")
        buf += chunk
    return buf


class RTDEConnection:
    """One RTDE client: handshake, input recipes, and a stream of output packages."""

    def __init__(self, ctrl: Controller, sock: socket.socket, server) -> None:
        self.ctrl, self.sock, self.server = ctrl, sock, server
        self.output_names: list[str] = []
        self.output_fmt = ""
        self.inputs: dict[int, list[tuple[str, str]]] = {}
        self.streaming = False
        self.frequency = 500.0
        self.send_lock = threading.Lock()

    def send(self, kind: str, payload: bytes) -> None:
        with self.send_lock:
            self.sock.sendall(struct.pack(">HB", len(payload) + 3, ord(kind)) + payload)

    def serve(self) -> None:
        try:
            while True:
                size, kind = struct.unpack(">HB", _recv_exact(self.sock, 3))
                self.handle(chr(kind), _recv_exact(self.sock, size - 3))
        except (ConnectionError, OSError):
            pass
        finally:
            self.streaming = False
            self.server.forget(self.sock)

    def handle(self, kind: str, payload: bytes) -> None:
        if kind == "V":
            self.send("V", b"\x01")
        elif kind == "v":
            self.send("v", struct.pack(">IIII", *self.ctrl.version))
        elif kind == "O":
            self.frequency = struct.unpack(">d", payload[:8])[0]
            names = [n for n in payload[8:].decode().split(",") if n]
            offered = {k: v for k, v in OUTPUT_TYPES.items()
                       if not (self.ctrl.cb3 and k in E_SERIES_ONLY_OUTPUTS)}
            types = [offered.get(n, "NOT_FOUND") for n in names]
            with self.ctrl.lock:
                self.ctrl.seen["rtde_frequencies"].append(self.frequency)
            self.output_names = names
            self.output_fmt = ">B" + "".join(FIELD_SIZES[t][1:] for t in types
                                             if t != "NOT_FOUND")
            self.send("O", b"\x01" + ",".join(types).encode())
        elif kind == "I":
            names = [n for n in payload.decode().split(",") if n]
            types = [INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            recipe = len(self.inputs) + 1
            self.inputs[recipe] = list(zip(names, types, strict=True))
            self.send("I", bytes([recipe]) + ",".join(types).encode())
        elif kind == "S":
            self.send("S", b"\x01")
            if not self.streaming:
                self.streaming = True
                threading.Thread(target=self.stream, daemon=True).start()
        elif kind == "P":
            self.streaming = False
            self.send("P", b"\x01")
        elif kind == "U":
            self.on_input(payload)

    def on_input(self, payload: bytes) -> None:
        recipe = self.inputs.get(payload[0])
        if recipe is None:
            return
        offset = 1
        ctrl = self.ctrl
        with ctrl.lock:
            for name, kind in recipe:
                fmt = FIELD_SIZES.get(kind)
                if fmt is None:
                    return
                size = struct.calcsize(fmt)
                value = struct.unpack(fmt, payload[offset:offset + size])
                offset += size
                if name.startswith("input_int_register_"):
                    ctrl.in_int[int(name.rsplit("_", 1)[1])] = value[0]
                elif name.startswith("input_double_register_"):
                    ctrl.in_double[int(name.rsplit("_", 1)[1])] = value[0]
            ctrl.last_input = time.monotonic()

    def stream(self) -> None:
        ctrl = self.ctrl
        # one package of the newest tick's state per period of the asked rate (whole
        # ticks, never faster); the thread sleeps between packages instead of waking on
        # every 2 ms tick
        every = max(1, math.ceil(500.0 / max(self.frequency, 1.0) - 1e-9))
        period = every * PERIOD
        last_tick = -every
        next_t = time.monotonic()
        # each field's flattened value, kept while the snapshot holds the same value (at
        # rest most fields do): 500 packings a second cost a tenth of a core otherwise
        flat: dict[str, tuple] = {}
        with ctrl.lock:
            ctrl.stream_ticks[id(self)] = every
        try:
            while self.streaming:
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -STREAM_RESYNC_S:  # fell far behind: resynchronise
                    next_t = time.monotonic()
                with ctrl.tick_cond:  # a whole period of controller time after the last
                    ctrl.tick_cond.wait_for(lambda t=last_tick: ctrl.tick >= t + every,
                                            timeout=0.1)
                    tick, snap = ctrl.tick, ctrl.snapshot
                if tick < last_tick + every:
                    continue
                last_tick = tick
                if time.monotonic() < ctrl.stall_until:
                    continue
                values: list = []
                for name in self.output_names:
                    value = snap.get(name)
                    if value is None:
                        continue
                    # an array by its bytes (a move may update one in place), else
                    # by identity
                    token = value.tobytes() if isinstance(value, np.ndarray) else value
                    known = flat.get(name)
                    if known is None or (known[0] != token if isinstance(token, bytes)
                                         else known[0] is not token):
                        known = (token, _flatten(value))
                        flat[name] = known
                    values.extend(known[1])
                self.send("U", struct.pack(self.output_fmt, 1, *values))
        except OSError as exc:  # the client went away
            log.debug("stream ended: %s", exc)
            self.streaming = False
        except Exception as exc:  # a fault of this stand-in: never silent
            # a stream that stops with the socket open reads, to ur_rtde, as silence until
            # its own read deadline (2.5 s) drops the link; closing it says so at once
            log.warning("RTDE stream ended by a fault: %r; closing the connection", exc)
            self.streaming = False
            try:
                self.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        finally:
            with ctrl.lock:
                ctrl.stream_ticks.pop(id(self), None)


def _flatten(value) -> tuple:
    """An RTDE field's value as the flat tuple of numbers the packet carries."""
    if isinstance(value, np.ndarray):
        return tuple(value.tolist())
    if isinstance(value, (list, tuple)):
        return tuple(float(v) if isinstance(v, float | np.floating) else v for v in value)
    return (value,)


DASHBOARD_ANSWERS = {
    "is in remote control": "true",
    "close popup": "closing popup",
    "close safety popup": "closing safety popup",
}


class Server:
    """All listening sockets of one stand-in, on one loopback address."""

    def __init__(self, ctrl: Controller, host: str, control_path: Path | None,
                 on_fault=None) -> None:
        """``on_fault``: called when the controller loop ends by an error (``fault``
        then names it); the stand-in is then no controller, and should end."""
        self.ctrl, self.host, self.control_path = ctrl, host, control_path
        self.on_fault = on_fault
        self.fault: str | None = None
        self.stop_event = threading.Event()
        self.clients: set[socket.socket] = set()
        self.clients_lock = threading.Lock()
        self.listeners = {}
        for port, handler in ((30004, self.on_rtde), (29999, self.on_dashboard),
                              (30003, self.on_script), (30001, self.on_primary),
                              (30002, self.on_primary)):
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(8)
            self.listeners[port] = (sock, handler)
        self.control_sock = None
        if control_path is not None:
            self.control_sock = listen(control_path)

    def forget(self, sock: socket.socket) -> None:
        with self.clients_lock:
            self.clients.discard(sock)
        try:
            sock.close()
        except OSError:
            pass

    def start(self) -> None:
        threading.Thread(target=self._run_controller, daemon=True, name="controller").start()
        for port, (sock, handler) in self.listeners.items():
            threading.Thread(target=self._accept, args=(sock, handler), daemon=True,
                             name=f"accept-{port}").start()
        if self.control_sock is not None:
            threading.Thread(target=self._accept, args=(self.control_sock, self.on_control),
                             daemon=True, name="control").start()

    def _run_controller(self) -> None:
        """The controller loop; should it end by an error, the error is logged and
        ``on_fault`` called: a stand-in whose clock stopped would otherwise go on
        answering, its RTDE streams silent, the dashboard as if nothing happened."""
        try:
            self.ctrl.run_loop(self.stop_event)
        except Exception as exc:
            log.exception("controller loop failed")
            self.fault = f"controller loop failed: {exc!r}"
            if self.on_fault is not None:
                self.on_fault()

    def _accept(self, listener: socket.socket, handler) -> None:
        while not self.stop_event.is_set():
            try:
                sock, _ = listener.accept()
            except OSError:
                return
            if listener is not self.control_sock:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with self.clients_lock:
                    self.clients.add(sock)
            threading.Thread(target=handler, args=(sock,), daemon=True).start()

    def on_rtde(self, sock: socket.socket) -> None:
        RTDEConnection(self.ctrl, sock, self).serve()

    def on_primary(self, sock: socket.socket) -> None:
        """Primary/secondary interface: the version message once, then robot state at
        10 Hz (joint data, cartesian info, KINEMATICS_INFO). Scripts sent here are read
        and ignored."""
        ctrl = self.ctrl
        threading.Thread(target=self._drain, args=(sock,), daemon=True).start()
        try:
            sock.sendall(version_message(int(ctrl.t * 1e6), ctrl.version))
            while not self.stop_event.is_set():
                with ctrl.lock:
                    package = robot_state(ctrl.q, ctrl.qd, ctrl.snapshot["actual_TCP_pose"],
                                          matrix_to_pose(ctrl.tcp), ctrl.dh,
                                          ctrl.calibration_status)
                sock.sendall(package)
                if self.stop_event.wait(0.1):
                    break
        except OSError:
            pass
        self.forget(sock)

    def _drain(self, sock: socket.socket) -> None:
        try:
            while sock.recv(65536):
                pass
        except OSError:
            pass

    def on_script(self, sock: socket.socket) -> None:
        data = b""
        try:
            while True:
                chunk = sock.recv(65536)
                if not chunk:
                    break
                data += chunk
                text = data.decode(errors="replace")
                if text.lstrip().startswith("def rtde_control():") and \
                        text.rstrip().splitlines()[-1].strip() == "end":
                    self.ctrl.load_script(text)
                    data = b""
        except OSError:
            pass
        self.forget(sock)

    def on_dashboard(self, sock: socket.socket) -> None:
        try:
            sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
            buf = b""
            while True:
                chunk = sock.recv(4096)
                if not chunk:
                    break
                buf += chunk
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    answer = self.dashboard(line.decode(errors="replace").strip())
                    sock.sendall((answer + "\n").encode())
                    if answer == "Disconnected":
                        raise ConnectionError
        except (OSError, ConnectionError):
            pass
        self.forget(sock)

    def dashboard(self, command: str) -> str:
        """One dashboard-server command (port 29999): a fixed answer, or a handler of
        ``DASHBOARD_HANDLERS`` that may change the controller's state."""
        ctrl = self.ctrl
        with ctrl.lock:
            ctrl.seen["dashboard"] = [*ctrl.seen["dashboard"][-99:], command]
            if ctrl.cb3 and command in E_SERIES_ONLY_DASHBOARD:
                return f"could not understand: '{command}'"
            model = ctrl.model_name
            if command in ("PolyscopeVersion", "polyscopeVersion"):
                return models.polyscope_line(model)
            if command == "get robot model":
                return models.dashboard_model(model)
            if command == "get serial number":
                return models.serial_number(model)
            if command in DASHBOARD_ANSWERS:
                return DASHBOARD_ANSWERS[command]
            handler = DASHBOARD_HANDLERS.get(command)
            if handler is not None:
                return handler(self.ctrl)
        return f"could not understand: '{command}'"

    def on_control(self, sock: socket.socket) -> None:
        serve_stream(sock, self.control)

    def control(self, request: dict) -> dict:
        if request.get("cmd") == "freedrive":  # the operator's hand (``ur_teach``)
            return freedrive(self.ctrl, request.get("q_deg"), request.get("speed_dps", 30.0))
        return self._control(request)

    def _control(self, request: dict) -> dict:
        cmd = request.get("cmd")
        ctrl = self.ctrl
        if cmd == "protective_stop":
            ctrl.protective_stop("injected")
        elif cmd == "emergency_stop":
            ctrl.emergency_stop()
        elif cmd == "release_estop":
            with ctrl.lock:
                ctrl.estop = False
                ctrl.safety_mode = SAFETY_NORMAL
        elif cmd == "drop_connections":
            with self.clients_lock:
                clients = list(self.clients)
            for sock in clients:
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        elif cmd in ("stall_stream", "resume_stream", "script_start_delay"):
            self._timing(cmd, request.get("seconds"))
        elif cmd == "fail_loop":  # the stand-in's own fault: its loop ends, then it
            ctrl.loop_fault = str(request.get("message", "injected loop fault"))
        elif cmd == "freeze":
            ctrl.freeze(float(request.get("at_fraction", 0.5)))
        elif cmd == "thaw":
            ctrl.thaw()
        elif cmd == "dump":
            return {"ok": True, **ctrl.dump()}
        else:
            return {"ok": False, "error": f"unknown cmd {cmd!r}"}
        return {"ok": True}

    def _timing(self, cmd: str, seconds) -> None:
        """Injected delays: the RTDE stream stalled (``seconds``, None: until resumed) or
        resumed, and a program started ``seconds`` after its script arrives."""
        ctrl = self.ctrl
        if cmd == "stall_stream":
            ctrl.stall_until = math.inf if seconds is None else time.monotonic() + float(seconds)
        elif cmd == "resume_stream":
            ctrl.stall_until = 0.0
        else:
            ctrl.script_start_s = float(seconds or 0.0)

    def close(self) -> None:
        self.stop_event.set()
        for sock, _ in self.listeners.values():
            sock.close()
        with self.clients_lock:
            for sock in list(self.clients):
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                    sock.close()
                except OSError:
                    pass
        if self.control_sock is not None:
            self.control_sock.close()
            if self.control_path and self.control_path.exists():
                self.control_path.unlink()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rigctl mock arm",
                                     description="UR controller stand-in (RTDE, dashboard, "
                                                 "primary interface), any model.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--model", default="ur5e", choices=list(models.MODEL_NAMES),
                        help="the arm, as ur_description spells it (a world file's "
                             "arm.model wins)")
    parser.add_argument("--world", default=None, help="world file (arm.errors) or errors YAML")
    parser.add_argument("--control", type=Path, default=None, help="JSON-lines control socket")
    parser.add_argument("--tcp-model", choices=("factory", "nominal", "true"),
                        default="factory",
                        help="model behind actual_TCP_pose, FK, IK and KINEMATICS_INFO: the "
                             "world's arm.factory_errors (nominal when it has none), nominal, "
                             "or the truth")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not args.host.startswith("127.") and args.host not in ("localhost", "::1"):
        print(json.dumps({"error": f"--host {args.host}: the stand-in binds loopback only"}))
        return 2
    arm = load_arm_section(args.world)
    model = arm.get("model", args.model) if args.world else args.model
    ctrl = Controller(model, arm.get("errors") or {}, args.tcp_model, arm.get("home_deg"),
                      arm.get("factory_errors"))
    done = threading.Event()
    server = Server(ctrl, args.host, args.control, on_fault=done.set)
    server.start()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    print(json.dumps({"host": args.host, "rtde_port": 30004, "dashboard_port": 29999,
                      "script_port": 30003, "primary_port": 30001, "pid": os.getpid(),
                      "control": str(args.control) if args.control else None}), flush=True)
    done.wait()
    server.close()
    if server.fault is not None:
        print(json.dumps({"error": server.fault}), file=sys.stderr, flush=True)
        return 1
    return 0


def _set_payload(c, _a):
    c.payload = c.rdouble(0)


def _set_tcp(c, _a):
    c.tcp = pose_to_matrix(c.q_from(0))


def _pose_trans(c, _a):
    c.to_out(0, matrix_to_pose(pose_to_matrix(c.q_from(0)) @ pose_to_matrix(c.q_from(6))))


def _forward_kinematics_args(c, _a):
    c.to_out(0, matrix_to_pose(c.ctrl_model.tool(c.q_from(0), pose_to_matrix(c.q_from(6)))))


# command -> handler(controller, async_flag)
SCRIPT_HANDLERS = {
    **{cmd: (lambda c, a, cmd=cmd: c._cmd_move(cmd, a))
       for cmd in (Cmd.MOVEJ, Cmd.MOVEJ_IK, Cmd.MOVEL, Cmd.MOVEL_FK)},
    Cmd.STOPL: lambda c, a: c._cmd_stop_move(a),
    Cmd.STOPJ: lambda c, a: c._cmd_stop_move(a),
    Cmd.SPEED_STOP: lambda c, a: c._cmd_stop_realtime(a),
    Cmd.SERVO_STOP: lambda c, a: c._cmd_stop_realtime(a),
    Cmd.SPEEDJ: lambda c, a: c._cmd_speedj(a),
    Cmd.SERVOJ: lambda c, a: c._cmd_servoj(a),
    Cmd.SET_PAYLOAD: _set_payload,
    Cmd.TEACH_MODE: lambda c, a: start_teach(c),
    Cmd.END_TEACH_MODE: lambda c, a: end_teach(c, "end_teach_mode()"),
    Cmd.SET_TCP: _set_tcp,
    **{cmd: (lambda c, a, cmd=cmd: c._cmd_inverse_kinematics(cmd))
       for cmd in (Cmd.GET_INVERSE_KINEMATICS_ARGS, Cmd.GET_INVERSE_KINEMATICS_DEFAULT,
                   Cmd.GET_INVERSE_KINEMATICS_HAS_SOLUTION_DEFAULT,
                   Cmd.GET_INVERSE_KINEMATICS_HAS_SOLUTION_ARGS)},
    Cmd.PROTECTIVE_STOP: lambda c, a: c.protective_stop("triggerProtectiveStop"),
    Cmd.SET_WATCHDOG: lambda c, a: c._cmd_set_watchdog(),
    Cmd.IS_POSE_WITHIN_SAFETY_LIMITS: lambda c, a: c._cmd_pose_within_limits(),
    Cmd.IS_JOINTS_WITHIN_SAFETY_LIMITS:
        lambda c, a: c.wint(1, int(c._check_joints(c.q_from(0)))),
    Cmd.POSE_TRANS: _pose_trans,
    Cmd.GET_TCP_OFFSET: lambda c, a: c.to_out(0, matrix_to_pose(c.tcp)),
    Cmd.GET_FORWARD_KINEMATICS_DEFAULT:
        lambda c, a: c.to_out(0, matrix_to_pose(c.ctrl_model.tool(c.q, c.tcp))),
    Cmd.GET_FORWARD_KINEMATICS_ARGS: _forward_kinematics_args,
    Cmd.IS_STEADY: lambda c, a: c.wint(1, int(c.is_steady())),
    Cmd.GET_ACTUAL_TOOL_FLANGE_POSE:
        lambda c, a: c.to_out(0, matrix_to_pose(c.ctrl_model.flange(c.q))),
    Cmd.STOP_SCRIPT: lambda c, a: c._cmd_stop_script(),
}


def _dash_stop(ctrl) -> str:
    ctrl.stop_program("dashboard stop")
    return "Stopped"


def _dash_play(ctrl) -> str:
    if ctrl.runtime_state == RUNTIME_PAUSED and ctrl.safety_mode == SAFETY_NORMAL:
        ctrl.runtime_state = RUNTIME_PLAYING
        return "Starting program"
    return "Failed to execute: play"


def _dash_pause(ctrl) -> str:
    if ctrl.runtime_state == RUNTIME_PLAYING:
        ctrl.runtime_state = RUNTIME_PAUSED
    return "Pausing program"


def _dash_program_state(ctrl) -> str:
    state = {RUNTIME_PLAYING: "PLAYING", RUNTIME_PAUSED: "PAUSED"}.get(ctrl.runtime_state,
                                                                     "STOPPED")
    return f"{state} rtde_control"


def _dash_robot_mode(ctrl) -> str:
    names = {ROBOT_POWER_OFF: "POWER_OFF", ROBOT_IDLE: "IDLE", ROBOT_RUNNING: "RUNNING"}
    return f"Robotmode: {names.get(ctrl.robot_mode, 'RUNNING')}"


def _dash_safety(ctrl) -> str:
    names = {SAFETY_NORMAL: "NORMAL", SAFETY_PROTECTIVE: "PROTECTIVE_STOP",
             SAFETY_ROBOT_ESTOP: "ROBOT_EMERGENCY_STOP"}
    return f"Safetystatus: {names[ctrl.safety_mode]}"


def _dash_power_on(ctrl) -> str:
    if ctrl.estop:
        return "Failed to power on: emergency stop pressed"
    ctrl.robot_mode = ROBOT_IDLE
    return "Powering on"


def _dash_power_off(ctrl) -> str:
    ctrl.robot_mode = ROBOT_POWER_OFF
    ctrl.stop_program("power off")
    return "Powering off"


def _dash_brake_release(ctrl) -> str:
    if ctrl.robot_mode >= ROBOT_IDLE:
        ctrl.robot_mode = ROBOT_RUNNING
    return "Brake releasing"


def _dash_unlock(ctrl) -> str:
    if ctrl.safety_mode == SAFETY_PROTECTIVE:
        ctrl.safety_mode = SAFETY_NORMAL
        return "Protective stop releasing"
    return "Cannot unlock protective stop until 5s after occurrence. " \
           "Always inspect cause of protective stop before unlocking"


DASHBOARD_HANDLERS = {
    "stop": _dash_stop, "play": _dash_play, "pause": _dash_pause,
    "running": lambda c: f"Program running: {str(c.runtime_state == RUNTIME_PLAYING).lower()}",
    "programState": _dash_program_state, "robotmode": _dash_robot_mode,
    "safetystatus": _dash_safety,
    "safetymode": lambda c: _dash_safety(c).replace("Safetystatus", "Safetymode"),
    "power on": _dash_power_on, "power off": _dash_power_off,
    "brake release": _dash_brake_release, "unlock protective stop": _dash_unlock,
    "quit": lambda c: "Disconnected",
}


if __name__ == "__main__":
    sys.exit(main())

