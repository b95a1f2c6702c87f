"""``Arm`` on ``ur_rtde``: a Universal Robots arm (CB3, e-Series, UR-Series) over RTDE.

- Before anything else it asks the dashboard what the arm is (``get robot model``,
  ``get serial number``, ``PolyscopeVersion``) and refuses (``ConfigError``) a rig file
  whose ``devices.arm.model`` disagrees, naming both (``rigctl.hardware.ur_models``).

- Connects the receive and control interfaces with bounded retries (connections often
  fail right after a stop).
- Moves are started asynchronously (``moveJ``/``moveL`` with ``async=True``) and watched
  from a thread that reads the receive interface: a protective or emergency stop raises
  ``SafetyError``; a stream that stops advancing raises ``DeviceError`` within
  ``stream_timeout_s`` (rig file) (never hangs).
- Never unlocks a protective stop by itself: ``unlock_protective_stop()`` is an explicit
  operator action (``rigctl arm unlock``).
- Teardown: ``disconnect()`` of the control interface sleeps ~0.5 s in ur_rtde; the cost
  is measured and kept in ``describe()["teardown_s"]``. On a dead connection only
  ``disconnect()`` is called: ur_rtde's ``stopScript()`` would retry the link for a long
  time, and a thread abandoned inside the C++ library has crashed the process.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

from rigctl.drivers.base import Arm, ArmState, DeviceError, SafetyError, Status, load_note
from rigctl.drivers.ur_primary import PrimaryInfo, read_primary_info
from rigctl.hardware.ur_models import ControllerIdentity, check_model

log = logging.getLogger(__name__)

ARRIVAL_TOL_RAD = 1e-3
ARRIVAL_TOL_M = 1e-4  # a linear move's TCP
# After a move ends, how long newer samples are awaited for the arm to show it arrived.
# The end comes from the control interface's RTDE connection and the joints from the
# receive interface's, each read by its own thread; on a loaded host the receive
# stream's newest sample can predate the end by tenths of a second (load check, two busy
# cores: a sample taken "after" the end still 1.011 deg short, the move in fact done).
ARRIVAL_GRACE_S = 2.0
# ur_rtde's own deadline on each read of the RTDE stream: silent this long, its receive
# interface closes the socket and reports itself disconnected, with no reconnect
# (ur_rtde src/rtde.cpp, the default read deadline, 2.5 s; the same default is in the
# installed 1.6.5 library). A stream_timeout_s above it cannot be reached.
UR_RTDE_READ_DEADLINE_S = 2.5
# a link found closed after this much silence is put down to that deadline (the monitor
# polls every 20 ms, so a closure by the deadline is seen at about 2.5 s of silence)
DEADLINE_SILENCE_S = 0.8 * UR_RTDE_READ_DEADLINE_S


def bounded_call(fn, timeout: float, what: str):
    """Run ``fn`` in a daemon thread; give up (and say so) after ``timeout``."""
    box: dict[str, Any] = {}

    def target():
        try:
            box["value"] = fn()
        except Exception as exc:  # ur_rtde raises RuntimeError on a dead link
            box["error"] = exc

    thread = threading.Thread(target=target, daemon=True, name=what)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        raise DeviceError(f"arm: {what} did not return within {timeout:.1f} s")
    if "error" in box:
        raise box["error"]
    return box.get("value")


# ur_rtde waits as long for its first upload to run (``waitForProgramRunning``)
SCRIPT_START_TIMEOUT_S = 5.0


class URArm(Arm):
    teaching = False  # free drive on (``teach_mode``)

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self.control = None
        self.receive = None
        self.connect_s: dict[str, float] = {}
        self.teardown_s: float | None = None
        self._stop_event = threading.Event()
        self._watch_thread: threading.Thread | None = None
        self._last_ts = (0.0, time.monotonic())
        self._lost: str | None = None  # why the link was lost: latched until reopened
        self.serial = None
        self.polyscope = None
        self.primary: PrimaryInfo | None = None
        self.identity: ControllerIdentity | None = None
        self._monitor_stop = threading.Event()

    # -- connection -----------------------------------------------------------------

    def _with_retries(self, what: str, fn):
        last: Exception | None = None
        for attempt in range(self.cfg.connect_retries):
            try:
                t0 = time.perf_counter()
                value = fn()
                self.connect_s[what] = time.perf_counter() - t0
                return value
            except RuntimeError as exc:
                last = exc
                log.warning("arm: %s connect attempt %d/%d failed: %s", what, attempt + 1,
                            self.cfg.connect_retries, exc)
                time.sleep(0.2 * (attempt + 1))
        raise DeviceError(f"arm {self.cfg.host}: cannot connect {what} after "
                          f"{self.cfg.connect_retries} tries: {last}")

    def open(self) -> None:
        import rtde_control
        import rtde_receive

        self.identity = read_identity(self.cfg.host)
        if self.identity is not None:
            check_model(self.cfg.model, self.identity, self.cfg.host)
            self.serial, self.polyscope = self.identity.serial, self.identity.version
        hz = self.cfg.rtde_frequency_hz
        self.receive = self._with_retries(
            "receive", lambda: rtde_receive.RTDEReceiveInterface(self.cfg.host, hz))
        self.control = self._with_retries(
            "control", lambda: rtde_control.RTDEControlInterface(self.cfg.host, hz))
        self._last_ts = (self.receive.getTimestamp(), time.monotonic())
        self._lost = None
        self._monitor_stop = threading.Event()
        threading.Thread(target=self._monitor, daemon=True, name="arm-stream-monitor").start()
        try:
            self.primary = read_primary_info(self.cfg.host, timeout_s=self.cfg.primary_timeout_s)
        except DeviceError as exc:
            log.warning("arm: no controller version or kinematics from the primary "
                        "interface: %s", exc)
        self.check_safety()

    def close(self) -> None:
        if self.control is None and self.receive is None:
            return
        try:
            if self.cfg.park.policy == "home" and self._alive():
                self.move_joints(self.cfg.park_rad()).wait(self.cfg.move_timeout_s)
        finally:
            t0 = time.perf_counter()
            alive = self._alive()
            self._monitor_stop.set()
            control, receive = self.control, self.receive
            self.control = self.receive = None
            # On a dead link ur_rtde's stopScript() retries the connection for a long time
            # (and a thread abandoned inside it has crashed the process): only disconnect.
            if control is not None:
                try:
                    if alive:
                        bounded_call(control.stopScript, self.cfg.teardown_timeout_s,
                                 "control stopScript")
                    else:
                        self._let_reconnect_give_up(control)
                    control.disconnect()
                except Exception as exc:
                    log.warning("arm: control teardown: %s", exc)
            if receive is not None:
                try:
                    receive.disconnect()
                except Exception as exc:
                    log.warning("arm: receive teardown: %s", exc)
            self.teardown_s = time.perf_counter() - t0

    def _let_reconnect_give_up(self, control) -> None:
        """On a link the controller dropped, ur_rtde's control interface tries to reconnect
        and re-upload its script from its own thread; disconnecting during that attempt
        has crashed the process (SIGSEGV). Wait, bounded, until it reports itself
        disconnected."""
        deadline = time.monotonic() + self.cfg.teardown_timeout_s
        while time.monotonic() < deadline:
            try:
                if not control.isConnected():
                    return
            except Exception:
                return
            time.sleep(0.05)
        log.warning("arm: control interface still reconnecting after %.1f s; disconnecting",
                    self.cfg.teardown_timeout_s)

    def describe(self) -> dict[str, Any]:
        primary = self.primary.as_dict() if self.primary else {}
        kinematics = primary.get("kinematics")
        return {"controller": primary.get("controller_version"),
                "kinematics_hash": kinematics["hash"] if kinematics else None,
                "model": self.cfg.model, "host": self.cfg.host, "serial": self.serial,
                "controller_model": self.identity.robot_model if self.identity else None,
                "firmware": self.polyscope, "connect_s": self.connect_s,
                "teardown_s": self.teardown_s,
                "speed_cap_dps": self.cfg.speed_cap_dps, "accel_cap_dps2": self.cfg.accel_cap_dps2,
                "controller_kinematics": kinematics}

    def controller_kinematics(self):
        """The controller's own DH table (``KinematicsInfo``), or None if it sent none."""
        return self.primary.kinematics if self.primary else None

    # -- state ------------------------------------------------------------------------

    def _monitor(self) -> None:
        """Note when the controller timestamp last advanced (every 20 ms), and latch a lost
        link as soon as it is seen, whether or not anyone is reading the arm then."""
        receive = self.receive
        while not self._monitor_stop.is_set() and receive is not None:
            try:
                ts = receive.getTimestamp()
            except Exception:
                return
            if ts != self._last_ts[0]:
                self._last_ts = (ts, time.monotonic())
            if not self._alive():
                return  # latched: nothing more to watch
            self._monitor_stop.wait(0.02)

    def _link_problem(self) -> str | None:
        """Why the link is down now, or None while it is up."""
        silent = time.monotonic() - self._last_ts[1]
        if self.receive is None or not self.receive.isConnected():
            if silent < DEADLINE_SILENCE_S:
                return (f"arm {self.cfg.host}: RTDE connection lost (closed by the controller "
                        "or the network)")
            return (f"arm {self.cfg.host}: RTDE connection lost (no new sample for "
                    f"{silent:.1f} s: ur_rtde closes its link after "
                    f"{UR_RTDE_READ_DEADLINE_S:g} s without data, whatever "
                    f"devices.arm.stream_timeout_s says; {load_note(None)})")
        if silent < self.cfg.stream_timeout_s:
            return None
        return (f"arm {self.cfg.host}: RTDE connection lost (no new sample for {silent:.1f} s,"
                f" limit {self.cfg.stream_timeout_s:g} s; "
                f"{load_note('devices.arm.stream_timeout_s')})")

    def _alive(self) -> bool:
        """The stream is connected and its timestamp advanced within ``stream_timeout_s``.
        A lost link stays lost (latched) until the arm is opened again: samples missed in
        the gap cannot be trusted, and a link seen lost for a moment is a fault to report,
        not a window that a busy host may or may not let anyone see."""
        if self.receive is None:  # not open (or closed): nothing to latch
            return False
        if self._lost is None:
            self._lost = self._link_problem()
            if self._lost is not None:
                log.error("%s", self._lost)
        return self._lost is None

    def _require_alive(self) -> None:
        if not self._alive():
            lost = self._lost or self._link_problem()
            raise DeviceError(f"{lost} (latched until the arm is opened again)")

    def check_safety(self) -> None:
        if self.receive is None:
            raise DeviceError("arm: not connected")
        if self.receive.isEmergencyStopped():
            raise SafetyError(f"arm {self.cfg.host}: emergency stop")
        if self.receive.isProtectiveStopped():
            raise SafetyError(f"arm {self.cfg.host}: protective stop; inspect the cause, then "
                              "unlock explicitly with `rigctl arm unlock`")

    def read_state(self) -> ArmState:
        self._require_alive()
        r = self.receive
        safety = ("emergency_stop" if r.isEmergencyStopped() else
                  "protective_stop" if r.isProtectiveStopped() else "normal")
        return ArmState(tuple(r.getActualQ()), tuple(r.getActualTCPPose()), time.time(), safety)

    def joint_limits(self) -> list[tuple[float, float]]:
        return self.cfg.joint_limits_rad()

    # -- motion -----------------------------------------------------------------------

    def _caps(self) -> tuple[float, float]:
        return math.radians(self.cfg.speed_cap_dps), math.radians(self.cfg.accel_cap_dps2)

    def move_joints(self, q) -> Status:
        q = [float(v) for v in q]
        self.check_limits(q)
        self._require_alive()
        self.check_safety()
        v, a = self._caps()
        status = Status("arm moveJ to [" + ", ".join(f"{math.degrees(x):.1f}" for x in q) +
                        "] deg")
        if not self.control.moveJ(q, v, a, True):
            self._refused("moveJ")
        self._watch(status, target_q=q)
        return status

    def move_linear(self, pose) -> Status:
        pose = [float(v) for v in pose]
        self._require_alive()
        self.check_safety()
        if not self.control.isPoseWithinSafetyLimits(pose):
            raise SafetyError(f"arm: pose {pose} outside the controller's safety limits")
        status = Status("arm moveL")
        v, a = self.cfg.linear_speed_mm_s / 1000.0, self.cfg.linear_accel_mm_s2 / 1000.0
        if not self.control.moveL(pose, v, a, True):
            self._refused("moveL")
        self._watch(status, target_pose=pose)
        return status

    def _refused(self, command: str) -> None:
        """Raise for a ``command`` the controller refused. A protective or emergency stop
        that came just before it is the ``SafetyError`` it is (a run pauses on it): the
        receive stream shows the stop one sample later than the control script refuses,
        so the state is read from the second sample after the refusal. Anything else is
        a ``DeviceError``."""
        self._sample_after_now()
        self._sample_after_now()
        self.check_safety()
        raise DeviceError(f"arm {self.cfg.host}: {command} refused by the controller")

    def _watch(self, status: Status, target_q=None, target_pose=None) -> None:
        if self._watch_thread is not None and self._watch_thread.is_alive():
            self._stop_event.set()
            self._watch_thread.join(timeout=2)
        self._stop_event.clear()
        self._watch_thread = threading.Thread(
            target=self._watch_loop, args=(status, target_q, target_pose), daemon=True,
            name="arm-move")
        self._watch_thread.start()

    def _watch_loop(self, status: Status, target_q, target_pose) -> None:
        deadline = time.monotonic() + self.cfg.move_timeout_s
        start_q = list(self.receive.getActualQ())
        try:
            time.sleep(0.01)
            while True:
                if self._stop_event.is_set():
                    raise SafetyError("arm move stopped")
                self._require_alive()
                self.check_safety()
                q = self.receive.getActualQ()
                if target_q is not None:
                    span = max(max(abs(t - s) for t, s in zip(target_q, start_q, strict=True)),
                               1e-9)
                    left = max(abs(t - c) for t, c in zip(target_q, q, strict=True))
                    status.set_progress(1 - left / span)
                running = self.control.getAsyncOperationProgress() >= 0
                if not running:
                    # q above may predate the end of the move (a loaded host widens that
                    # gap): judge arrival on samples taken after the end
                    if target_q is not None:
                        left = self._settled_distance(
                            lambda: self._joints_from(target_q), ARRIVAL_TOL_RAD)
                        if left > ARRIVAL_TOL_RAD:
                            raise DeviceError(f"arm: move ended {math.degrees(left):.3f} deg "
                                              "short of its target")
                    if target_pose is not None:
                        err = self._settled_distance(
                            lambda: self._tcp_from(target_pose), ARRIVAL_TOL_M)
                        if err > ARRIVAL_TOL_M:
                            raise DeviceError(f"arm: moveL ended {err * 1000:.2f} mm short")
                    status.set_finished()
                    return
                if time.monotonic() > deadline:
                    raise DeviceError(f"arm: move not finished after {self.cfg.move_timeout_s} s")
                time.sleep(0.01)
        except Exception as exc:
            status.set_exception(exc)

    def _joints_from(self, target_q) -> float:
        """The largest joint's distance (rad) from ``target_q`` on a sample taken after
        the call."""
        q = self._sample_after_now()
        return max(abs(t - c) for t, c in zip(target_q, q, strict=True))

    def _tcp_from(self, target_pose) -> float:
        """The TCP's distance (m) from ``target_pose`` on a sample taken after the call."""
        self._sample_after_now()
        return math.dist(target_pose[:3], self.receive.getActualTCPPose()[:3])

    def _settled_distance(self, distance, tolerance: float) -> float:
        """``distance()`` (from the target, on a sample taken after the call) until it is
        within ``tolerance`` or ``ARRIVAL_GRACE_S`` have passed; the last value. A move
        that really stopped short (the arm in the operator's hands) is reported after the
        grace."""
        deadline = time.monotonic() + ARRIVAL_GRACE_S
        while True:
            value = distance()
            if value <= tolerance or time.monotonic() >= deadline:
                return value

    def _sample_after_now(self) -> list[float]:
        """Joint angles from an RTDE sample whose controller timestamp is newer than the one
        current at the call (so it was taken after whatever just happened)."""
        first = self.receive.getTimestamp()
        deadline = time.monotonic() + self.cfg.move_timeout_s
        while self.receive.getTimestamp() <= first and time.monotonic() < deadline:
            self._require_alive()
            time.sleep(0.002)
        return list(self.receive.getActualQ())

    def stop(self) -> None:
        """Decelerate now (stopJ); skipped when the link is already gone."""
        self._stop_event.set()
        if self.control is None or not self._alive():
            return
        try:
            bounded_call(lambda: self.control.stopJ(2.0, False), self.cfg.teardown_timeout_s,
                         "stopJ")
        except Exception as exc:
            log.error("arm: stopJ failed: %s", exc)

    def recover(self) -> None:
        """After a protective stop was unlocked (by the operator, ``rigctl arm unlock``):
        restart the control script, which the stop ended, so moves are accepted again."""
        self.check_safety()
        self._restart_script()
        self._stop_event.clear()

    def _restart_script(self) -> None:
        """Upload the control script again and wait until the controller runs it.
        ur_rtde's ``reuploadScript`` only sends it: a move sent before the controller
        reports the program running is refused ("RTDE control script is not running!"),
        and the next state package can be a whole stream period away."""
        if self.control is None:
            return
        if not self.control.reuploadScript():
            raise DeviceError(f"arm {self.cfg.host}: the control script could not be sent")
        deadline = time.monotonic() + SCRIPT_START_TIMEOUT_S
        while not self.control.isProgramRunning():
            self.check_safety()  # a stop meanwhile: the program will not start
            if time.monotonic() > deadline:
                raise DeviceError(f"arm {self.cfg.host}: the control script did not start "
                                  f"within {SCRIPT_START_TIMEOUT_S:g} s of its upload (an "
                                  "e-Series controller in Local mode ignores scripts; see the "
                                  "pendant)")
            time.sleep(0.01)

    # -- teach mode (free drive) -------------------------------------------------------

    def teach_mode(self) -> None:
        """Free drive: the operator moves the arm by hand (ur_rtde ``teachMode()``, the
        control script's ``teach_mode()``). Refused in a stop (``SafetyError``) or when the
        controller refuses it (``DeviceError``). End it with ``end_teach_mode()``."""
        self._require_alive()
        self.check_safety()
        if not bounded_call(self.control.teachMode, self.cfg.teardown_timeout_s, "teachMode"):
            raise DeviceError(f"arm {self.cfg.host}: teach mode refused by the controller")
        self.teaching = True
        log.info("arm: teach mode on (free drive)")

    def end_teach_mode(self) -> bool:
        """Leave free drive (``endTeachMode()``); True when the controller confirmed it.
        Never raises: it is called on every end of a taught run, a failed one included;
        on a dead link there is nothing to send, and the controller ends teach mode with
        the control script anyway."""
        self.teaching = False
        if self.control is None or not self._alive():
            log.warning("arm: teach mode not ended explicitly (no link); the controller "
                        "ends it with the control script")
            return False
        try:
            done = bool(bounded_call(self.control.endTeachMode, self.cfg.teardown_timeout_s,
                                 "endTeachMode"))
        except Exception as exc:
            log.error("arm: endTeachMode failed: %s", exc)
            return False
        log.info("arm: teach mode off")
        return done

    def unlock_protective_stop(self) -> str:
        """Operator action: unlock a protective stop, and restart the control script when
        this driver holds the arm. From another process (``rigctl arm unlock`` beside a
        paused run) the paused run restarts its own (``recover``)."""
        import dashboard_client

        dash = dashboard_client.DashboardClient(self.cfg.host)
        dash.connect()
        try:
            dash.unlockProtectiveStop()  # ur_rtde returns nothing; it raises when refused
            # a CB3 has no `safetystatus` (PolyScope 5.4+); its `safetymode` says the same
            cb3 = self.identity is not None and self.identity.major == 3
            status = dash.safetymode() if cb3 else dash.safetystatus()
        finally:
            dash.disconnect()
        if "PROTECTIVE_STOP" in status:
            raise SafetyError(f"arm {self.cfg.host}: still in a protective stop after the "
                              f"unlock ({status}); the controller allows it 5 s after the stop")
        self._restart_script()
        return f"protective stop unlocked ({status})"


def _dashboard_answer(dash, command: str, expect: str) -> str | None:
    """One dashboard command's answer when it starts with ``expect`` (a controller too
    old for the command answers "could not understand ..."), else None."""
    dash.send(command + "\n")
    answer = str(dash.receive()).strip()
    return answer if answer.startswith(expect) else None


def read_identity(host: str) -> ControllerIdentity | None:
    """What the controller at ``host`` says it is (dashboard ``get robot model``, ``get
    serial number``, ``PolyscopeVersion``; CB3 from 3.12, e-Series from 5.6), or None when
    the dashboard cannot be reached (then nothing can be checked; logged). The serial number
    is asked directly: ur_rtde's ``getSerialNumber`` refuses on a CB3, which has it."""
    try:
        import dashboard_client

        dash = dashboard_client.DashboardClient(host)
        dash.connect()
        try:
            version = dash.polyscopeVersion()
            model = _dashboard_answer(dash, "get robot model", "UR")
            serial = _dashboard_answer(dash, "get serial number", "20")
        finally:
            dash.disconnect()
    except Exception as exc:  # ur_rtde raises RuntimeError on a refused connection
        log.warning("arm %s: the dashboard did not say what the arm is: %s", host, exc)
        return None
    return ControllerIdentity(model, serial if serial and serial.isdigit() else None,
                              version or None)
