"""Faults the stand-ins inject, through the real clients and drivers: a late reply, an
input voltage out of range, dropped RTDE connections; and what a run they end records."""

from __future__ import annotations

import json
import math
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rigctl.config import load_rig
from rigctl.drivers.dynamixel import DynamixelHead
from rigctl.errors import DeviceError
from rigctl.mocks.sim import STAND_IN_TIMING
from rigctl.records import RunDirectory
from rigctl.runner import Runner
from tests.mockproc import ROOT, control
from tests.test_dynamixel import bus, head_config  # noqa: F401 (the bus fixture)
from tests.test_ur import arm_proc  # noqa: F401 (the arm fixture)

pytestmark = pytest.mark.integration


def test_a_late_reply_is_retried_and_a_silent_bus_is_reported(bus):  # noqa: F811
    # a 34 ms timeout so that the 0.1 s late reply times a try out; backoff (50, 100, 200,
    # 400, 800 ms) leaves the retries seconds of slack on a busy host
    head = DynamixelHead(head_config(bus.ready["link"], packet_timeout_ms=34, retries=5,
                                     retry_backoff_s=0.05))
    with head:
        control(bus.ready["control"], {"cmd": "delay_next", "seconds": 0.1})
        angles = head.read_angles()  # the first try times out, a retry gets the answer
        assert abs(angles.pan) < math.radians(0.1) and head.retries_used >= 1
        control(bus.ready["control"], {"cmd": "drop_next", "count": 10})
        with pytest.raises(DeviceError) as failed:
            head.read_angles()
    message = str(failed.value)
    assert "failed after 6 tries" in message and "There is no status packet" in message
    assert "host load" in message and "devices.head.packet_timeout_ms" in message


def test_input_voltage_out_of_range_stops_the_move_and_names_the_servo(bus):  # noqa: F811
    head = DynamixelHead(head_config(bus.ready["link"]))
    with head:
        control(bus.ready["control"], {"cmd": "set", "id": 2, "voltage": 9.0})
        with pytest.raises(DeviceError, match=r"head servo 2 \(tilt\).*input voltage") as e:
            head.move_to(0.0, math.radians(10), 0.0).wait(15)
    # input voltage is not in the X-series' default Shutdown mask (52): torque stays on
    assert "torque stays on" in str(e.value)
    servos = {s["id"]: s for s in control(bus.ready["control"], {"cmd": "dump"})["servos"]}
    assert servos[2]["hardware_error_status"] & 0x01 and servos[2]["torque_enable"] == 1


DROP_SCRIPT = """
import faulthandler, json, sys, time
faulthandler.dump_traceback_later(float(sys.argv[4]), exit=True)  # a hang: where it stopped
from rigctl.drivers.ur import URArm
from rigctl.config import parse_rig
from rigctl.errors import DeviceError
from tests.mockproc import ROOT, control
host, sock, report, fault, stream_timeout = sys.argv[1:4] + sys.argv[5:7]
def say(**kw):  # into a file of its own: ur_rtde's threads print to stdout and stderr
    with open(report, "a") as f:
        f.write(json.dumps(kw) + "\\n")
arm = URArm(parse_rig(f"devices:\\n  arm: {{host: {host}, stream_timeout_s: {stream_timeout}}}"
                      "\\n").devices.arm)
arm.open()
say(step="opened")
control(sock, json.loads(fault))
say(step="dropped")
deadline = time.monotonic() + 20
while time.monotonic() < deadline:
    try:
        arm.read_state()
        time.sleep(0.02)
    except DeviceError as exc:
        say(error=str(exc))
        break
say(step="closing")
arm.close()
say(step="closed")
"""
DROP_DUMP_S = 75  # the child dumps its threads' stacks and exits if it runs this long
DROP_WAIT_S = 90  # under the test's hang guard, so that a hang shows where it stopped


def _stopped_in(stderr: str) -> str | None:
    """The source line the child's main thread stood on when faulthandler's timer dumped
    its stacks (the innermost frame of the thread whose outermost is the script), or None
    when it did not dump."""
    if "Timeout (" not in stderr:
        return None
    for block in re.split(r"(?:Current thread|Thread) 0x", stderr)[1:]:
        frames = re.findall(r'File "(.+?)", line (\d+) in', block)
        if frames and frames[-1][0] == "<string>":
            path, line = frames[0]
            source = Path(path).read_text().splitlines() if Path(path).is_file() else []
            return source[int(line) - 1].strip() if int(line) <= len(source) else path
    return None


# the stand-in's fault, the rig file's stream_timeout_s, and what the driver must report
LINK_FAULTS = {
    "dropped": ({"cmd": "drop_connections"}, 1.0,
                "RTDE connection lost (closed by the controller"),
    # a stream silent for 4 s, past ur_rtde's own read deadline (2.5 s), under a limit of
    # 30 s: ur_rtde drops the link itself, and the driver names that deadline
    "silent": ({"cmd": "stall_stream", "seconds": 4.0}, 30.0,
               "ur_rtde closes its link after 2.5 s without data"),
}


@pytest.mark.timeout(150)  # a hang guard, above DROP_WAIT_S
@pytest.mark.parametrize("fault", sorted(LINK_FAULTS))
def test_a_lost_rtde_link_is_reported_by_its_cause(arm_proc, tmp_path, fault):  # noqa: F811
    """In a child process: the stand-in drops its RTDE connections, or its stream falls
    silent past ur_rtde's read deadline (which then closes the sockets itself). After
    that, ur_rtde's control interface reconnects from its own thread, and that thread
    has crashed the process (SIGSEGV, or SIGABRT from the C library's "double free
    detected") in about half of the trials here, whatever the driver does meanwhile, and
    once under the load check hung it past 120 s (a known doubt, see the closing notes).
    The driver's own report, naming the cause, must come first; the child's steps tell
    where a hang stopped. Only a crash or a hang inside the arm's teardown, after the
    report, is put down to that doubt."""
    command, stream_timeout_s, expected = LINK_FAULTS[fault]
    report = tmp_path / "steps.jsonl"
    child = subprocess.Popen([sys.executable, "-c", DROP_SCRIPT, arm_proc.ready["host"],
                              arm_proc.ready["control"], str(report), str(DROP_DUMP_S),
                              json.dumps(command), str(stream_timeout_s)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        _, err = child.communicate(timeout=DROP_WAIT_S)
    except subprocess.TimeoutExpired:  # not even faulthandler's timer ended it
        child.kill()
        _, err = child.communicate(timeout=30)
    finally:
        if child.poll() is None:  # interrupted meanwhile: stopped by its PID all the same
            child.kill()
            child.wait(timeout=30)
    stopped_in = _stopped_in(err)
    hung = stopped_in is not None or child.returncode == -signal.SIGKILL
    lines = [json.loads(line) for line in report.read_text().splitlines()] \
        if report.exists() else []
    steps = [line.get("step", "error" if "error" in line else "?") for line in lines]
    where = (f"child's steps {steps}, stopped in {stopped_in!r}, exit {child.returncode}; "
             f"stderr: {err[-3000:]}")
    errors = [line["error"] for line in lines if "error" in line]
    assert steps[:3] == ["opened", "dropped", "error"], where
    assert expected in errors[0], where
    if child.returncode == 0:
        assert steps[-1] == "closed", where
        return
    # ur_rtde's own teardown, after the report: a crash, or a hang inside one of its calls
    # (the driver's own waits are bounded by teardown_timeout_s)
    assert steps[-1] == "closing", where
    if hung:
        assert stopped_in and re.search(r"\.(disconnect|isConnected|stopScript)\(", stopped_in), \
            where
        pytest.xfail(f"ur_rtde hung in the arm's teardown, at {stopped_in!r}")
    assert child.returncode in (-signal.SIGSEGV, -signal.SIGABRT), where


@pytest.mark.parametrize("end", ["failed", "aborted"])
def test_a_run_that_fails_or_is_aborted_still_records_its_devices(bus, tmp_path, end):  # noqa: F811
    """versions.json (each device's describe(): model, firmware, bus transaction counts)
    is written for a run that a device fault fails (servo 2's input voltage out of range
    when the second capture is taken) or that the operator aborts at the same point: its
    bus record is the evidence of what went wrong. The captures taken before the end
    stay on disk, listed by the record, and the head parks home (its default policy).
    Pausing is off (``max_pause_s: 0``): the servo alert ends the run."""
    rig = tmp_path / "rig.yaml"
    head = {"port": bus.ready["link"], "speed_cap_dps": 180, "accel_cap_dps2": 1000,
            **STAND_IN_TIMING["head"]}
    rig.write_text(yaml.safe_dump({"name": "dxl-rig", "records": {"directory": "rec"},
                                   "devices": {"head": head}, "max_pause_s": 0}))
    runner, captures = None, []

    def on_event(event):
        if event["type"] == "step" and event["step"].startswith("capture"):
            captures.append(event["index"])
            if len(captures) < 2:
                return
            if end == "failed":
                control(bus.ready["control"], {"cmd": "set", "id": 2, "voltage": 9.0})
            else:
                runner.abort("operator pressed abort")

    runner = Runner(load_rig(rig), show_progress=False, on_event=on_event)
    outcome = runner.run("head-sweep", {"pan_deg": [-6, 6], "tilt_deg": [0, 3],
                                        "settle_s": 0.0})
    assert outcome.status == end, outcome.reason
    if end == "failed":
        assert "servo 2" in outcome.reason and "input voltage" in outcome.reason
    else:
        assert outcome.reason == "operator pressed abort"
    versions = json.loads((Path(outcome.run_dir) / "versions.json").read_text())
    assert versions["software"]["rigctl"]
    described = versions["devices"]["head"]
    assert described["model"] == "xm430-w350" and described["eeprom_writes"] is not None
    stats = described["bus_stats"]
    assert all(stats[str(i)]["transactions"] > 0 for i in (1, 2, 3))
    assert stats["group"]["transactions"] > 0
    # the two captures taken (the second before its health check failed the run), on
    # disk and listed by the record; nothing after them
    kept = sorted(p.name for p in (Path(outcome.run_dir) / "captures").iterdir())
    assert kept == ["000.json", "001.json"]
    shown = subprocess.run([sys.executable, "-m", "rigctl.cli", "runs", "show",
                            outcome.run_id, "--rig", str(rig), "--json"], capture_output=True,
                           text=True, timeout=60, cwd=ROOT)
    assert json.loads(shown.stdout)["captures"] == 2 and json.loads(shown.stdout)["status"] \
        == end
    commanded = [RunDirectory(outcome.run_dir).capture(i).meta["head_commanded"]["pan"]
                 for i in (0, 1)]
    assert commanded == pytest.approx([math.radians(-6), math.radians(6)])
    # parked home: goal and present position at the centre on every servo
    servos = control(bus.ready["control"], {"cmd": "dump"})["servos"]
    for servo in servos:
        assert servo["goal_position"] == 2048 and abs(servo["present_position"] - 2048) <= 1, \
            servo

