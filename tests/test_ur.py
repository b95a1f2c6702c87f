"""The real ur_rtde client against the UR controller stand-in (RTDE, dashboard, script)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.config import load_rig, parse_rig
from rigctl.drivers.ur import URArm
from rigctl.errors import DeviceError, SafetyError
from rigctl.loopback import free_host
from rigctl.records import RunDirectory
from rigctl.runner import Runner
from tests.mockproc import MockProcess, control
from tests.waiting import raises, wait_until

pytestmark = pytest.mark.integration

HOME = np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


def start_arm(tmp_path, host=None, extra=()):
    host = host or free_host()
    sock = tmp_path / f"ur-{host}.sock"
    return MockProcess(["-m", "rigctl.mocks.ur_controller", "--host", host, "--control", str(sock),
                        *extra])


@pytest.fixture
def arm_proc(tmp_path):
    proc = start_arm(tmp_path)
    yield proc
    proc.stop()


@pytest.fixture
def clients(arm_proc):
    import rtde_control
    import rtde_receive

    receive = rtde_receive.RTDEReceiveInterface(arm_proc.ready["host"])
    ctrl = rtde_control.RTDEControlInterface(arm_proc.ready["host"])
    yield ctrl, receive
    ctrl.stopScript()
    ctrl.disconnect()
    receive.disconnect()


PUBLISHED_DH = {  # Universal Robots' published D-H tables: d and a, metres
    "ur5e": ([0.1625, 0, 0, 0.1333, 0.0997, 0.0996], [0, -0.425, -0.3922, 0, 0, 0]),
    "ur10e": ([0.1807, 0, 0, 0.17415, 0.11985, 0.11655], [0, -0.6127, -0.57155, 0, 0, 0]),
}


def ur5e_fk(q, model="ur5e"):
    """UR forward kinematics from the published DH table, written out for this test."""
    d, a = PUBLISHED_DH[model]
    alpha = [math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0]
    T = np.eye(4)
    for i in range(6):
        ct, st, ca, sa = math.cos(q[i]), math.sin(q[i]), math.cos(alpha[i]), math.sin(alpha[i])
        T = T @ np.array([[ct, -st * ca, st * sa, a[i] * ct], [st, ct * ca, -ct * sa, a[i] * st],
                          [0, sa, ca, d[i]], [0, 0, 0, 1]])
    return T


def rotation(pose):
    import cv2

    return cv2.Rodrigues(np.asarray(pose[3:6], float))[0]


def test_streams_every_subscribed_variable_consistently(clients):
    _ctrl, receive = clients
    assert receive.isConnected()
    assert np.allclose(receive.getActualQ(), HOME)
    assert np.allclose(receive.getTargetQ(), HOME)
    assert receive.getRobotMode() == 7 and receive.getSafetyMode() == 1
    # the uploaded control script is playing; the receive interface (connected before the
    # control interface uploaded it) sees that in a later packet, late on a busy host
    wait_until(lambda: receive.getRuntimeState() == 2, what="runtime state 2 (playing)")
    assert receive.getSafetyStatusBits() == 1
    assert receive.getSpeedScaling() == 1.0
    assert receive.getActualMainVoltage() == 48.0
    assert list(receive.getJointTemperatures()) == [31.5] * 6
    assert list(receive.getActualToolAccelerometer()) == [0.0, 0.0, 9.81]
    T = ur5e_fk(HOME)
    pose = receive.getActualTCPPose()
    assert np.allclose(pose[:3], T[:3, 3], atol=1e-9)
    assert np.allclose(rotation(pose), T[:3, :3], atol=1e-9)
    # the controller clock advances. (How fast is not asserted: the client's cached
    # timestamp may be stale by however long its reader was descheduled, so controller
    # time can seem to outrun the wall clock between two reads; the load check caught
    # 0.104 s of controller time in 0.093 s.)
    t0 = receive.getTimestamp()
    wait_until(lambda: receive.getTimestamp() - t0 >= 0.1, what="0.1 s of controller time")


def test_movej_lands_within_1e4_rad(clients):
    ctrl, receive = clients
    target = HOME + np.radians([20, -10, 15, 5, -12, 30])
    assert ctrl.moveJ(list(target), 1.05, 1.4)
    # the receive interface is its own stream: on a busy host its last sample may still be
    # from before the move ended (seen in the load check), so wait for it, then compare
    wait_until(lambda: np.max(np.abs(np.array(receive.getActualQ()) - target)) < 1e-4,
               what="the received joints at the moveJ target")


def test_movel_lands_on_pose_and_tcp_agrees_with_fk(clients):
    ctrl, receive = clients
    start = receive.getActualTCPPose()
    goal = list(start)
    goal[0] += 0.05
    goal[2] -= 0.04
    assert ctrl.moveL(goal, 0.2, 1.0)
    # the received pose may lag the move's end on a busy host (0.2 mm in one load-check
    # run); it must reach the goal, and stay there
    wait_until(lambda: np.allclose(receive.getActualTCPPose()[:3], goal[:3], atol=1e-6),
               what="the received TCP pose at the moveL goal")
    pose = receive.getActualTCPPose()
    assert np.allclose(pose[:3], goal[:3], atol=1e-6)
    T = ur5e_fk(receive.getActualQ())
    assert np.allclose(pose[:3], T[:3, 3], atol=1e-9)
    assert np.allclose(ctrl.getForwardKinematics()[:3], pose[:3], atol=1e-9)


def test_async_move_progress_then_stopj(clients):
    ctrl, receive = clients
    target = list(HOME + np.radians([60, 0, 0, 0, 0, 0]))
    assert ctrl.moveJ(target, 0.5, 1.0, True)
    wait_until(lambda: receive.getActualQ()[0] > 0.05, what="the async move under way")
    assert ctrl.getAsyncOperationProgress() >= 0  # running
    assert receive.getActualQ()[0] < math.radians(60)
    ctrl.stopJ(2.0, False)  # returns None in ur_rtde 1.6.5
    wait_until(lambda: ctrl.getAsyncOperationProgress() < 0 and ctrl.isSteady(),
               what="stopJ to end the move")
    stopped = receive.getActualQ()[0]
    assert stopped < math.radians(60) - 0.05  # stopped well short of the target
    ts = receive.getTimestamp()
    wait_until(lambda: receive.getTimestamp() > ts + 0.05, what="later samples")
    assert receive.getActualQ()[0] == stopped  # and stays there


def test_ik_fk_round_trip(clients):
    ctrl, _ = clients
    q = list(HOME + np.radians([15, 10, -20, 10, 25, -40]))
    pose = ctrl.getForwardKinematics(q, [0, 0, 0, 0, 0, 0])
    q_back = ctrl.getInverseKinematics(pose, q, 1e-10, 1e-10)
    assert np.max(np.abs(np.array(q_back) - q)) < 1e-8
    assert ctrl.getInverseKinematicsHasSolution(pose)
    moved = ctrl.poseTrans(pose, [0, 0, 0.1, 0, 0, 0])
    T = ur5e_fk(q)
    assert np.allclose(moved[:3], T[:3, 3] + 0.1 * T[:3, 2], atol=1e-9)


def arm_config(host, **extra):
    text = f"devices:\n  arm:\n    host: {host}\n    speed_cap_dps: 90\n    accel_cap_dps2: 180\n"
    for key, value in extra.items():
        text += f"    {key}: {value}\n"
    return parse_rig(text).devices.arm


def test_driver_move_joint_and_soft_limits(arm_proc):
    arm = URArm(arm_config(arm_proc.ready["host"],
                           joint_limits_deg="[[-90, 90], [-180, 0], [-160, 160], "
                                            "[-270, 90], [-180, 180], [-270, 270]]"))
    with arm:
        arm.move_joint(5, math.radians(25)).wait(10)
        state = arm.read_state()
        assert abs(state.q[5] - math.radians(25)) < 1e-4
        with pytest.raises(SafetyError, match=r"arm.joint1: target 95.00 deg outside soft"):
            arm.move_joint(0, math.radians(95))
        assert abs(arm.read_state().q[0]) < 1e-9  # nothing was sent
    assert arm.teardown_s is not None  # measured (bounded by teardown_timeout_s)


@pytest.mark.parametrize("extra, asked", [({}, 125.0), ({"rtde_frequency_hz": 500}, 500.0)])
def test_the_driver_streams_at_the_configured_rate(arm_proc, extra, asked):
    """Both RTDE interfaces ask the rig file's rate (125 Hz unless set), and the stream
    never comes faster: the packages' controller timestamps, read on the client, are at
    least a period apart (a busy host only spaces them more). Nor slower: some two are
    one period apart, also at rest, where the stand-in steps several ticks at a wake-up
    (never more than a package's)."""
    with URArm(arm_config(arm_proc.ready["host"], **extra)) as arm:
        seen = control(arm_proc.ready["control"], {"cmd": "dump"})["seen"]["rtde_frequencies"]
        assert seen == [asked, asked]  # receive, then control
        stamps = {arm.receive.getTimestamp()}
        wait_until(lambda: stamps.add(arm.receive.getTimestamp()) or len(stamps) > 40,
                   timeout=30, what="40 RTDE packages", poll=0.0005)
        assert 0.999 / asked < min(np.diff(sorted(stamps))) < 1.001 / asked


def test_a_controller_loop_that_fails_ends_the_stand_in_saying_so(arm_proc):
    """A stand-in whose controller loop ended by an error is no controller (its clock
    stopped, its streams silent): it ends with exit status 1 and the error on stderr,
    where `sim up` and the tests report a crashed stand-in."""
    assert control(arm_proc.ready["control"], {"cmd": "fail_loop", "message": "tick 42"})["ok"]
    wait_until(lambda: arm_proc.proc.poll() is not None, timeout=30,
               what="the stand-in to end")
    assert arm_proc.proc.returncode == 1
    stderr = arm_proc.stderr_text()
    assert "controller loop failed" in stderr and "tick 42" in stderr


def test_a_restarted_control_script_is_waited_for_before_the_next_move(arm_proc):
    """``recover`` (after an unlock) uploads the control script again; a controller that
    takes 0.3 s to start it still gets the next move (ur_rtde's ``reuploadScript`` does
    not wait, and a move sent before the program runs is refused)."""
    with URArm(arm_config(arm_proc.ready["host"])) as arm:
        assert control(arm_proc.ready["control"],
                       {"cmd": "script_start_delay", "seconds": 0.3})["ok"]
        arm.recover()
        assert arm.control.isProgramRunning()
        arm.move_joint(5, math.radians(10)).wait(10)
        assert abs(arm.read_state().q[5] - math.radians(10)) < 1e-4
    messages = control(arm_proc.ready["control"], {"cmd": "dump"})["messages"]
    assert sum("program rtde_control started" in m for m in messages) == 2


def test_after_an_unlock_from_another_process_the_run_moves_again(arm_proc):
    """A paused run's driver (``recover``) after the operator's ``rigctl arm unlock`` (a
    driver that never opened the arm): the stop ended the program, the controller takes
    0.3 s to start the new one, and the next move is still accepted."""
    cfg = arm_config(arm_proc.ready["host"])
    sock = arm_proc.ready["control"]
    with URArm(cfg) as arm:
        assert control(sock, {"cmd": "script_start_delay", "seconds": 0.3})["ok"]
        control(sock, {"cmd": "protective_stop"})
        wait_until(arm.receive.isProtectiveStopped, timeout=30, what="the protective stop")
        assert "protective stop unlocked" in URArm(cfg).unlock_protective_stop()
        # as a paused run's suspender does: wait for the stop's end on the run's stream
        wait_until(lambda: not arm.receive.isProtectiveStopped(), timeout=30,
                   what="the stop's end")
        arm.recover()
        arm.move_joint(5, math.radians(-10)).wait(10)
        assert abs(arm.read_state().q[5] - math.radians(-10)) < 1e-4


def test_protective_stop_mid_move_aborts_recorded_run(arm_proc, tmp_path):
    """With pausing off (``max_pause_s: 0``) a protective stop aborts the run."""
    rig = tmp_path / "rig.yaml"
    rig.write_text(f"name: ur-rig\nmax_pause_s: 0\ndevices:\n  arm: {{host: "
                   f"{arm_proc.ready['host']}, speed_cap_dps: 10, accel_cap_dps2: 40, "
                   "stream_timeout_s: 5}\n")
    runner = Runner(load_rig(rig), show_progress=False)
    import threading

    def inject(event):  # once the 40 deg move at 10 deg/s is under way
        if event.get("type") == "step" and event.get("index") == 1:
            threading.Timer(0.5, control, (arm_proc.ready["control"],
                                           {"cmd": "protective_stop"})).start()

    runner.on_event = inject
    outcome = runner.run("arm-sweep", {"joints": [6], "offsets_deg": [-40, 40]})
    assert outcome.status == "aborted"
    assert "protective stop" in outcome.reason
    run = RunDirectory(outcome.run_dir)
    assert (run.path / "run.log").exists()
    dump = control(arm_proc.ready["control"], {"cmd": "dump"})
    assert dump["safety_mode"] == 3  # still stopped: never unlocked automatically


def test_stand_in_killed_mid_move_raises_device_error(tmp_path):
    proc = start_arm(tmp_path)
    arm = URArm(arm_config(proc.ready["host"], speed_cap_dps=10))
    try:
        arm.open()
        status = arm.move_joint(0, math.radians(30))
        wait_until(lambda: status.progress > 0, what="the move under way")
        proc.kill()
        # reported as a lost link (bounded by stream_timeout_s), never a hang
        with pytest.raises(DeviceError, match="connection lost"):
            status.wait(10)
    finally:
        arm.close()  # bounded by teardown_timeout_s on a dead link
        proc.stop()
    assert proc.proc.poll() is not None


@pytest.fixture
def arms(tmp_path):
    """Start stand-ins on demand; every one started is stopped by PID in teardown."""
    started = []

    def start(**kwargs):
        started.append(start_arm(tmp_path, **kwargs))
        return started[-1]

    yield start
    for proc in started:
        proc.stop()


def test_two_stand_ins_side_by_side(arms):
    import rtde_receive

    a, b = arms(), arms(extra=("--model", "ur10e"))
    ra = rtde_receive.RTDEReceiveInterface(a.ready["host"])
    rb = rtde_receive.RTDEReceiveInterface(b.ready["host"])
    try:
        # each answers with its own model's kinematics at the same home joints
        for receive, model in ((ra, "ur5e"), (rb, "ur10e")):
            q = receive.getActualQ()
            assert np.allclose(receive.getActualTCPPose()[:3], ur5e_fk(q, model)[:3, 3],
                               atol=1e-6), model
    finally:
        ra.disconnect()
        rb.disconnect()


def test_arm_sweep_procedure_runs_through_runner(arm_proc, tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text(f"name: ur-rig\ndevices:\n  arm: {{host: {arm_proc.ready['host']}, "
                   f"speed_cap_dps: 120, accel_cap_dps2: 400, stream_timeout_s: 5}}\n")
    outcome = Runner(load_rig(rig), show_progress=False).run(
        "arm-sweep", {"joints": [6, 5], "offsets_deg": [-5, 5], "settle_s": 0.0})
    assert outcome.status == "succeeded", outcome.reason
    assert outcome.result["poses"] == 4
    assert outcome.result["max_joint_error_deg"] < 1e-3
    captures = RunDirectory(outcome.run_dir).captures()
    assert len(captures) == 4 and len(captures[0].meta["arm"]["q"]) == 6


def test_speedj_servoj_and_their_stops(clients):
    ctrl, receive = clients
    ctrl.speedJ([0.2, 0, 0, 0, 0, 0], 2.0, 0.002)
    # ramped at 2 rad/s^2 to 0.2 rad/s, then held there
    wait_until(lambda: receive.getActualQd()[0] == pytest.approx(0.2, abs=1e-6),
               what="joint 1 at 0.2 rad/s")
    ctrl.speedStop(5.0)
    wait_until(lambda: receive.getActualQd()[0] == 0.0, what="speedStop")
    start = np.array(receive.getActualQ())
    target = start + np.radians([0, 0, 0, 0, 0, 5])
    for _ in range(150):  # 0.3 s of servoJ at 500 Hz, as a client streaming setpoints would
        t_start = ctrl.initPeriod()
        ctrl.servoJ(list(target), 0.5, 0.5, 0.002, 0.05, 300)
        ctrl.waitPeriod(t_start)
    ctrl.servoStop(5.0)
    wait_until(lambda: abs(receive.getActualQ()[5] - target[5]) < math.radians(0.5),
               what="servoJ to reach its setpoint")


def test_set_tcp_moves_the_reported_tool_point(clients):
    ctrl, receive = clients
    flange = np.array(receive.getActualTCPPose())
    assert ctrl.setTcp([0, 0, 0.1, 0, 0, 0])
    wait_until(lambda: not np.allclose(receive.getActualTCPPose(), flange),
               what="the new TCP in the stream")
    tool = np.array(receive.getActualTCPPose())
    T = ur5e_fk(receive.getActualQ())
    assert np.allclose(tool[:3], flange[:3] + 0.1 * T[:3, 2], atol=1e-9)
    assert ctrl.getTCPOffset() == pytest.approx([0, 0, 0.1, 0, 0, 0])


def test_watchdog_stops_program_when_client_goes_quiet(clients, arm_proc):
    ctrl, receive = clients
    # playing before the watchdog is set, so that no kick has to come in time
    wait_until(lambda: receive.getRuntimeState() == 2, what="the program to be playing")
    assert ctrl.setWatchdog(2.0)  # kicks at least every 0.5 s, or the program stops
    assert ctrl.kickWatchdog()
    # no more kicks: the stand-in must stop the program
    wait_until(lambda: receive.getRuntimeState() == 1, what="the watchdog to stop the program")
    dump = control(arm_proc.ready["control"], {"cmd": "dump"})
    assert any("watchdog" in m for m in dump["messages"])


def test_a_stalled_stream_is_a_lost_link_until_the_arm_is_reopened(arm_proc):
    """The stand-in's stream stalls until told to resume (a latched fault) and the driver
    latches the lost link: it is seen however late the test looks, and stays reported
    after the stream is back, until the arm is opened again."""
    sock = arm_proc.ready["control"]
    arm = URArm(arm_config(arm_proc.ready["host"]))
    with arm:
        control(sock, {"cmd": "stall_stream"})
        lost = wait_until(lambda: raises(arm.read_state, DeviceError), what="a lost stream")
        assert "connection lost (no new sample for" in str(lost)
        control(sock, {"cmd": "resume_stream"})
        stalled_at = arm.receive.getTimestamp()
        wait_until(lambda: arm.receive.getTimestamp() > stalled_at + 0.1,
                   what="the stream back")
        again = raises(arm.read_state, DeviceError)
        assert again is not None and "latched until the arm is opened again" in str(again)
        with pytest.raises(DeviceError, match="connection lost"):
            arm.move_joint(5, 0.1)
    with URArm(arm_config(arm_proc.ready["host"])) as reopened:
        assert reopened.read_state().safety == "normal"


def test_emergency_stop_reaches_the_driver(arm_proc):
    arm = URArm(arm_config(arm_proc.ready["host"]))
    with arm:
        assert arm.read_state().safety == "normal"
        control(arm_proc.ready["control"], {"cmd": "emergency_stop"})
        wait_until(lambda: arm.receive.isEmergencyStopped(), what="the e-stop in the stream")
        with pytest.raises(SafetyError, match="emergency stop"):
            arm.move_joint(5, 0.1)
        control(arm_proc.ready["control"], {"cmd": "release_estop"})


def test_a_move_refused_for_a_protective_stop_just_before_it_is_a_safety_error(arm_proc):
    """A protective stop that lands between two moves: the control script refuses the next
    move while the receive stream does not show the stop yet (here the stream is held for
    a second). The refusal is the ``SafetyError`` it is, so that a run pauses on it, not
    a failed run's ``DeviceError``. (On a host too slow to start the move within that
    second, the stream shows the stop first and the move is refused as a ``SafetyError``
    before it is sent: the test then passes without this path.)"""
    sock = arm_proc.ready["control"]
    with URArm(arm_config(arm_proc.ready["host"], stream_timeout_s=5)) as arm:
        control(sock, {"cmd": "stall_stream", "seconds": 1.0})
        control(sock, {"cmd": "protective_stop"})
        refused = raises(lambda: arm.move_joint(5, 0.1), Exception)
        assert isinstance(refused, SafetyError), refused
        assert "protective stop" in str(refused)
