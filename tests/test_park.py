"""Park policies with the real drivers against the stand-ins: what each device does when
it is closed (after a run, an abort or a fault)."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rigctl.config import load_rig
from rigctl.drivers.dynamixel import DynamixelHead
from rigctl.drivers.ur import URArm
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


def test_an_operator_abort_stops_the_arm_mid_move_and_parks_it_home(arm_proc, tmp_path):  # noqa: F811
    """Through the runner and the real ur_rtde driver: abort while joint 6 turns; the run
    is recorded aborted and the arm's park policy (home) brings it back."""
    runner = Runner(load_rig(_arm_rig(tmp_path, arm_proc.ready["host"])), show_progress=False)
    thread, out = _sweep_in_thread(runner)
    dump = lambda: control(arm_proc.ready["control"], {"cmd": "dump"})  # noqa: E731
    wait_until(lambda: abs(dump()["q"][5] - HOME[5]) > math.radians(3), what="joint 6 moving")
    runner.abort("operator pressed abort")
    outcome = _outcome(thread, out)
    assert outcome.status == "aborted" and outcome.reason == "operator pressed abort"
    # stopped mid-move: the capture at -40 degrees, after the first move, never happened
    assert RunDirectory(outcome.run_dir).captures() == []
    assert np.allclose(dump()["q"], HOME, atol=1e-3)  # parked home on close


def test_a_protective_stop_mid_run_aborts_it_and_nothing_moves_after(arm_proc, tmp_path):  # noqa: F811
    """A fault (protective stop) while the runner moves the arm: the run is recorded
    aborted, naming it, and the park policy does not move a protective-stopped arm."""
    runner = Runner(load_rig(_arm_rig(tmp_path, arm_proc.ready["host"])), show_progress=False)
    thread, out = _sweep_in_thread(runner)
    dump = lambda: control(arm_proc.ready["control"], {"cmd": "dump"})  # noqa: E731
    wait_until(lambda: abs(dump()["q"][5] - HOME[5]) > math.radians(3), what="joint 6 moving")
    control(arm_proc.ready["control"], {"cmd": "protective_stop"})
    outcome = _outcome(thread, out)
    assert outcome.status == "aborted" and "protective stop" in outcome.reason.lower()
    assert RunDirectory(outcome.run_dir).captures() == []
    stopped_at = dump()["q"][5]
    assert abs(stopped_at - HOME[5]) > math.radians(3)  # not parked home
    time.sleep(1.0)  # an observation window, not a wait: nothing may move in it
    assert dump()["q"][5] == pytest.approx(stopped_at, abs=1e-6)  # still there a second on
