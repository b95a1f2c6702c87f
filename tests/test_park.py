"""Park policies with the real drivers against the stand-ins: what each device does when
it is closed (after a run, an abort or a fault)."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from rigctl.config import load_rig
from rigctl.drivers.dynamixel import DynamixelHead
from rigctl.drivers.ur import URArm
from rigctl.mocks.sim import STAND_IN_TIMING
from rigctl.records import RunDirectory
from rigctl.runner import Runner
from tests.mockproc import ROOT, control
from tests.test_dynamixel import bus, head_config  # noqa: F401 (the bus fixture)
from tests.test_ur import HOME, arm_config, arm_proc  # noqa: F401 (the arm fixture)
from tests.waiting import wait_until

pytestmark = pytest.mark.integration

PULSES_PER_DEG = 4096 / 360


@pytest.mark.parametrize(("policy", "parks_home", "torque"), [
    ("hold", False, 1), ("home", True, 1), ("torque_off", False, 0),
    ("home_then_torque_off", True, 0)])
def test_head_park_policy_on_close(bus, policy, parks_home, torque):  # noqa: F811
    head = DynamixelHead(head_config(bus.ready["link"], park=f"{{policy: {policy}}}"))
    head.open()
    head.move_to(math.radians(10), math.radians(-5), 0.0).wait(15)
    head.close()
    servos = {s["id"]: s for s in control(bus.ready["control"], {"cmd": "dump"})["servos"]}
    pan, tilt = servos[1], servos[2]
    expected_pan = 2048 if parks_home else 2048 + round(10 * PULSES_PER_DEG)
    expected_tilt = 2048 if parks_home else 2048 - round(5 * PULSES_PER_DEG)
    assert abs(pan["present_position"] - expected_pan) <= 2, policy
    assert abs(tilt["present_position"] - expected_tilt) <= 2, policy
    assert pan["torque_enable"] == tilt["torque_enable"] == torque, policy


def test_arm_parks_home_on_close_and_holds_after_a_protective_stop(arm_proc):  # noqa: F811
    host = arm_proc.ready["host"]
    arm = URArm(arm_config(host, park="{policy: home}"))
    arm.open()
    arm.move_joint(5, math.radians(20)).wait(15)
    arm.close()  # park: home
    q = control(arm_proc.ready["control"], {"cmd": "dump"})["q"]
    assert np.allclose(q, HOME, atol=1e-3)
    # after a protective stop nothing moves, whatever the park policy says
    arm = URArm(arm_config(host, park="{policy: home}"))
    arm.open()
    arm.move_joint(5, math.radians(20)).wait(15)
    control(arm_proc.ready["control"], {"cmd": "protective_stop"})
    wait_until(lambda: arm.receive.isProtectiveStopped(), what="the protective stop")
    try:
        arm.close()
    except Exception as exc:  # refusing to move is the point; say why
        assert "protective stop" in str(exc)
    q = control(arm_proc.ready["control"], {"cmd": "dump"})["q"]
    assert q[5] == pytest.approx(HOME[5] + math.radians(20), abs=1e-3)


def test_rigctl_arm_unlock_clears_a_protective_stop(arm_proc, tmp_path):  # noqa: F811
    rig = tmp_path / "rig.yaml"
    rig.write_text(f"name: ur-rig\ndevices:\n  arm: {{host: {arm_proc.ready['host']}}}\n")
    control(arm_proc.ready["control"], {"cmd": "protective_stop"})
    assert control(arm_proc.ready["control"], {"cmd": "dump"})["safety_mode"] == 3
    done = subprocess.run([sys.executable, "-m", "rigctl.cli", "arm", "unlock", "--rig",
                           str(rig)], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "protective stop unlocked (Safetystatus: NORMAL)" in done.stderr
    assert control(arm_proc.ready["control"], {"cmd": "dump"})["safety_mode"] == 1


def _arm_rig(tmp_path, host) -> Path:
    """A rig with the arm alone, slow (a 40 degree move takes about 3 s) and parking
    home, its home where the stand-in starts (``HOME``)."""
    rig = tmp_path / "rig.yaml"
    home = [round(math.degrees(v), 6) for v in HOME]
    rig.write_text(f"name: ur-rig\nrecords: {{directory: {tmp_path / 'records'}}}\n"
                   f"devices:\n  arm: {{host: {host}, speed_cap_dps: 15, accel_cap_dps2: 60,"
                   f" stream_timeout_s: 5, home_deg: {home}, park: {{policy: home}}}}\n")
    return rig


def _sweep_in_thread(runner: Runner) -> tuple[threading.Thread, dict]:
    """arm-sweep of joint 6 to -40 then +40 degrees, in a thread; ``out`` gets the
    outcome ("o") or what the run raised ("error")."""
    out: dict = {}

    def run():
        try:
            out["o"] = runner.run("arm-sweep", {"joints": [6], "offsets_deg": [-40, 40],
                                                "settle_s": 0.0})
        except BaseException as exc:  # shown by the test, not lost in the thread
            out["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, out


def _outcome(thread: threading.Thread, out: dict):
    thread.join(timeout=120)
    assert not thread.is_alive(), "the run did not end within 120 s of the stop"
    assert "error" not in out, f"the run raised {out.get('error')!r}"
    return out["o"]


def _held_mid_move(proc) -> dict:
    """Wait until the move the stand-in was told to hold (``freeze`` armed before the run)
    stands held half-way: still under way, however late the test looks. Returns the
    stand-in's state then."""
    return wait_until(lambda: (d := control(proc.ready["control"], {"cmd": "dump"}))
                      ["frozen"] and d, timeout=60, what="joint 6 held half-way")


def test_an_operator_abort_stops_the_arm_mid_move_and_parks_it_home(arm_proc, tmp_path):  # noqa: F811
    """Through the runner and the real ur_rtde driver: abort while joint 6 turns (held
    half-way by the stand-in until something ends the move); the run is recorded aborted
    and the arm's park policy (home) brings it back."""
    runner = Runner(load_rig(_arm_rig(tmp_path, arm_proc.ready["host"])), show_progress=False)
    control(arm_proc.ready["control"], {"cmd": "freeze", "at_fraction": 0.5})
    thread, out = _sweep_in_thread(runner)
    dump = lambda: control(arm_proc.ready["control"], {"cmd": "dump"})  # noqa: E731
    held = _held_mid_move(arm_proc)
    assert held["q"][5] == pytest.approx(HOME[5] - math.radians(20), abs=math.radians(0.5))
    runner.abort("operator pressed abort")
    outcome = _outcome(thread, out)
    assert outcome.status == "aborted" and outcome.reason == "operator pressed abort"
    # stopped mid-move: the capture at -40 degrees, after the first move, never happened
    assert RunDirectory(outcome.run_dir).captures() == []
    assert np.allclose(dump()["q"], HOME, atol=1e-3)  # parked home on close


def test_a_protective_stop_mid_run_aborts_it_and_nothing_moves_after(arm_proc, tmp_path):  # noqa: F811
    """A fault (protective stop) while the runner moves the arm, with pausing off
    (``max_pause_s: 0``): the run is recorded aborted, naming it, and the park policy
    does not move a protective-stopped arm."""
    rig = _arm_rig(tmp_path, arm_proc.ready["host"])
    rig.write_text(rig.read_text() + "max_pause_s: 0\n")
    runner = Runner(load_rig(rig), show_progress=False)
    control(arm_proc.ready["control"], {"cmd": "freeze", "at_fraction": 0.5})
    thread, out = _sweep_in_thread(runner)
    dump = lambda: control(arm_proc.ready["control"], {"cmd": "dump"})  # noqa: E731
    held = _held_mid_move(arm_proc)
    control(arm_proc.ready["control"], {"cmd": "protective_stop"})
    outcome = _outcome(thread, out)
    assert outcome.status == "aborted" and "protective stop" in outcome.reason.lower()
    assert RunDirectory(outcome.run_dir).captures() == []
    # the run is over: every device it touched was stopped and closed (its park policy
    # applied or refused). Nothing is left to move the arm, and it stands where the
    # protective stop caught it, not parked home, no joint turning.
    after = dump()
    assert after["safety_mode"] == 3 and not after["frozen"]
    assert np.allclose(after["q"], held["q"], atol=1e-9)
    assert np.allclose(after["qd"], 0.0)


def test_an_emergency_stop_mid_run_ends_it_even_with_pausing_on(arm_proc, tmp_path):  # noqa: F811
    """Pausing on (the default ``max_pause_s``): a protective stop would pause the run,
    but an emergency stop always ends it, recorded aborted, naming it."""
    rig = _arm_rig(tmp_path, arm_proc.ready["host"])
    config = load_rig(rig)
    assert config.max_pause_s > 0
    runner = Runner(config, show_progress=False)
    control(arm_proc.ready["control"], {"cmd": "freeze", "at_fraction": 0.5})
    thread, out = _sweep_in_thread(runner)
    _held_mid_move(arm_proc)
    control(arm_proc.ready["control"], {"cmd": "emergency_stop"})
    outcome = _outcome(thread, out)
    assert outcome.status == "aborted" and "emergency stop" in outcome.reason.lower(), \
        outcome.reason
    assert runner.index.get(outcome.run_id)["status"] == "aborted"
    control(arm_proc.ready["control"], {"cmd": "release_estop"})


def _head_rig(tmp_path, link: str, policy: str = "home") -> Path:
    """A rig with the head alone on the stand-in's bus, at the timing `sim up` writes for
    stand-in processes, parking per ``policy``."""
    rig = tmp_path / "rig.yaml"
    head = {"port": link, "speed_cap_dps": 120, "accel_cap_dps2": 600,
            **STAND_IN_TIMING["head"], "park": {"policy": policy}}
    rig.write_text(yaml.safe_dump({"name": "dxl-rig", "records": {"directory": "records"},
                                   "devices": {"head": head}}))
    return rig


def servos(sock: str) -> dict[int, dict]:
    """Each servo's state, by ID, from the stand-in's control socket."""
    return {s["id"]: s for s in control(sock, {"cmd": "dump"})["servos"]}


@pytest.mark.timeout(120)
def test_an_abort_mid_move_parks_the_real_head_home_and_keeps_the_capture(bus, tmp_path):  # noqa: F811
    """The runner with the real Dynamixel driver: the second move of a sweep is held
    half-way by the stand-in (latched), the operator aborts; the run is recorded aborted
    with the first capture kept, and the park policy (home) leaves every servo's goal
    and present position at home, motion over, torque on."""
    sock = bus.ready["control"]
    heads = []

    def on_event(event):  # the second head move: hold it half-way, whenever it comes
        if event["type"] == "step" and event["step"].startswith("head"):
            heads.append(event["index"])
            if len(heads) == 2:
                control(sock, {"cmd": "freeze", "id": 1, "at_fraction": 0.5})

    runner = Runner(load_rig(_head_rig(tmp_path, bus.ready["link"])), show_progress=False,
                    on_event=on_event)
    out: dict = {}
    thread = threading.Thread(target=lambda: out.update(o=runner.run(
        "head-sweep", {"pan_deg": [-20, 10], "tilt_deg": [5], "settle_s": 0.0})), daemon=True)
    thread.start()
    try:
        held = wait_until(lambda: servos(sock)[1]["frozen"] and servos(sock), timeout=60,
                          what="the second move held half-way")
    finally:
        runner.abort("operator pressed abort")
        thread.join(timeout=60)
    assert not thread.is_alive()
    # held away from home: pan half-way from -20 to +10 degrees, tilt at +5
    assert held[1]["present_position"] == pytest.approx(2048 - 5 * PULSES_PER_DEG, abs=3)
    assert held[2]["present_position"] == pytest.approx(2048 + 5 * PULSES_PER_DEG, abs=3)
    outcome = out["o"]
    assert outcome.status == "aborted" and outcome.reason == "operator pressed abort"
    captures = RunDirectory(outcome.run_dir).captures()
    assert [c.index for c in captures] == [0]
    assert captures[0].meta["head"]["pan"] == pytest.approx(math.radians(-20), abs=1e-3)
    assert not (Path(outcome.run_dir) / "result.json").exists()
    parked = servos(sock)
    for dxl_id in (1, 2, 3):  # home is the centre, 2048, on these servos
        assert parked[dxl_id]["goal_position"] == 2048, parked[dxl_id]
        assert abs(parked[dxl_id]["present_position"] - 2048) <= 1, parked[dxl_id]
        assert parked[dxl_id]["moving"] == 0 and parked[dxl_id]["torque_enable"] == 1
        assert not parked[dxl_id]["frozen"]
