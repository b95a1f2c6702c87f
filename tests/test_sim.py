"""The whole rig on stand-ins: real OpenCV, dynamixel-sdk and ur_rtde clients."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rigctl.calib.board import detect_board
from rigctl.config import load_rig
from rigctl.errors import DeviceError
from rigctl.mocks.world import load_world
from rigctl.procedures.planning import plan_target_views
from rigctl.records import RunDirectory
from rigctl.rig import Rig
from rigctl.runner import Runner
from rigctl.simrig import SimulatedRig
from tests.mockproc import ROOT, control
from tests.waiting import wait_until

# one simulated rig for the module, not one per worker
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("sim")]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sim")
    rig = SimulatedRig("ideal", records=tmp / "records", rig_out=tmp / "sim-rig.yaml",
                       log=tmp / "sim-up.log")
    yield rig
    assert not rig.stop(), "stand-ins outlived `sim up`"
    assert not rig.crash, rig.crash


def corner_rms(world, image, q, head) -> float:
    corners = detect_board(image, world.spec.target.rows, world.spec.target.cols)
    assert corners is not None, "board not detected"
    truth = world.target_corner_pixels(world.T_base_cam(np.asarray(q), head))
    return float(np.sqrt(np.mean(np.sum((corners - truth) ** 2, axis=1))))


def test_frames_after_arm_and_head_moves_show_the_new_pose(sim):
    """Board corners in a frame captured after each move match the projection of the
    truth at the encoder readings: within 1 px RMS (ideal world, no noise)."""
    config = load_rig(sim.rig_path)
    world = load_world(config.world)
    views, _ = plan_target_views(config, 2)
    rig = Rig(config)
    try:
        head, arm, camera = rig.open("head"), rig.open("arm"), rig.open("camera")
        for q in views:
            arm.move_joints(q).wait(30)
            for pan, tilt in ((0.0, 0.0), (3.0, -2.0)):
                head.move_to(math.radians(pan), math.radians(tilt), 0.0).wait(10)
                moved = time.time()
                frame = camera.capture(not_before=moved)
                assert frame.timestamp > moved
                angles = head.read_angles()
                state = arm.read_state()
                rms = corner_rms(world, frame.image, state.q,
                                 (angles.pan, angles.tilt, angles.roll))
                assert rms < 1.0, f"view {np.degrees(q).round(1)} head {pan},{tilt}: {rms}"
        # A frame from *before* the last move would be off by the 3 deg pan (~47 px).
        stale = corner_rms(world, frame.image, state.q, (0.0, 0.0, 0.0))
        assert stale > 20
    finally:
        rig.close_all()


def test_capture_survey_end_to_end(sim):
    config = load_rig(sim.rig_path)
    outcome = Runner(config, show_progress=False).run(
        "capture-survey", {"pan_deg": [-5, 5], "tilt_deg": [0], "views": 3, "settle_s": 0.1})
    assert outcome.status == "succeeded", outcome.reason
    assert outcome.result["captures"] == 5
    assert outcome.result["board_detected"] == 3
    run = RunDirectory(outcome.run_dir)
    captures = run.captures()
    assert all(c.image_path is not None and c.image_path.exists() for c in captures)
    meta = captures[-1].meta
    assert meta["camera"]["settings"]["width"] == 1280 and len(meta["arm"]["q"]) == 6
    assert meta["camera"]["settings"]["decoded_on_capture"] is True  # MJPEG kept as bytes
    assert meta["camera"]["timestamp"] > meta["time"] - 1.0
    world = load_world(config.world)
    for capture in captures[2:]:
        head = tuple(capture.meta["head"][k] for k in ("pan", "tilt", "roll"))
        assert corner_rms(world, capture.load_image(), capture.meta["arm"]["q"], head) < 1.0


def test_stalled_stream_raises_device_error(sim):
    config = load_rig(sim.rig_path)
    config.devices.camera.timeout_s = 1.0
    rig = Rig(config)
    try:
        camera = rig.open("camera")
        # a stall far past the timeout, ended by the test: the capture gives up
        control(sim.ready["camera"]["control"], {"cmd": "stall", "seconds": 120})
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match=r"within 1\.0 s"):
            camera.capture(not_before=time.time())
        assert time.monotonic() - t0 >= 1.0  # it waited its timeout, no less
    finally:
        control(sim.ready["camera"]["control"], {"cmd": "stall", "seconds": 0})
        rig.close_all()
    # the stream is back for the tests after this one
    config.devices.camera.timeout_s = 20.0
    rig = Rig(config)
    try:
        assert rig.open("camera").capture(not_before=time.time()).image is not None
    finally:
        rig.close_all()


ORPHANING_PARENT = """
import json, subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"],
                         start_new_session=True)
print(json.dumps({"pid": 0, "children": [child.pid]}), flush=True)
time.sleep(600)
"""


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_child_process_stop_stops_the_children_it_reported_in_other_sessions():
    """`sim up` starts its stand-ins in sessions of their own and lists them as
    `children`: when `sim up` itself has to be killed, ChildProcess.stop still stops them."""
    from rigctl.childproc import ChildProcess

    parent = ChildProcess(["-c", ORPHANING_PARENT], timeout=30)
    (child,) = parent.ready["children"]
    try:
        assert _alive(child) and os.getsid(child) != os.getsid(parent.pid)
        parent.kill()  # SIGKILL to the parent's group: the child is in another session
        assert _alive(child)
    finally:
        parent.stop(timeout=5)
    assert parent.orphans == [child]
    wait_until(lambda: not _alive(child), what="the orphan to die")


DEAF_TO_SIGTERM = """
import json, os, signal, time
signal.signal(signal.SIGTERM, lambda *_: None)
print(json.dumps({"pid": os.getpid()}), flush=True)
time.sleep(600)
"""

# ends on SIGTERM only once the other child has ended (its file written): it can end by
# itself only when the other was asked to stop before its own wait ran out
ENDS_AFTER_THE_OTHER = """
import json, os, signal, sys, time
from pathlib import Path
asked = []
signal.signal(signal.SIGTERM, lambda *_: asked.append(1))
print(json.dumps({"pid": os.getpid()}), flush=True)
while not (asked and Path(sys.argv[1]).exists()):
    time.sleep(0.01)
"""

ENDS_ON_SIGTERM = """
import json, os, signal, sys, time
from pathlib import Path
def end(*_):
    Path(sys.argv[1]).write_text("ended")
    sys.exit(0)
signal.signal(signal.SIGTERM, end)
print(json.dumps({"pid": os.getpid()}), flush=True)
time.sleep(600)
"""


def test_stop_all_asks_every_child_before_waiting_for_any(tmp_path):
    """`sim up` stops its stand-ins with stop_all: all are sent SIGTERM first, so a slow
    one does not hold back the others' shutdown (one after the other, three slow
    stand-ins outlasted the 20 s `SimulatedRig.stop` gives `sim up`)."""
    from rigctl.childproc import ChildProcess, stop_all

    marker = tmp_path / "second-ended"
    first = ChildProcess(["-c", ENDS_AFTER_THE_OTHER, str(marker)], timeout=30)
    second = ChildProcess(["-c", ENDS_ON_SIGTERM, str(marker)], timeout=30)
    try:
        stop_all([first, second], timeout=20.0)  # a hang guard: both end in milliseconds
    finally:
        first.kill()
        second.kill()
    assert marker.read_text() == "ended"
    assert (first.proc.returncode, second.proc.returncode) == (0, 0)  # neither was killed


def test_stop_all_kills_children_deaf_to_sigterm_and_names_them(capsys):
    from rigctl.childproc import ChildProcess, stop_all

    children = [ChildProcess(["-c", DEAF_TO_SIGTERM], timeout=30, name=f"deaf {i}")
                for i in range(2)]
    try:
        stop_all(children, timeout=1.0)
    finally:
        for child in children:
            child.kill()
    assert [c.proc.returncode for c in children] == [-signal.SIGKILL] * 2
    err = capsys.readouterr().err
    for child in children:
        assert not _alive(child.pid)
        assert f"{child.name} (pid {child.pid}, state S" in err
    assert err.count("did not end within") == 2


def test_sim_truth_json():
    result = subprocess.run([sys.executable, "-m", "rigctl.cli", "sim", "truth", "--world",
                             str(ROOT / "rigctl/mocks/worlds/default.yaml"), "--json"],
                            capture_output=True, text=True, timeout=60, cwd=ROOT)
    truth = json.loads(result.stdout)
    assert (truth["fx"], truth["cy"]) == (900.0, 371.8)
    assert truth["roll_axis_in_cam"][1] == pytest.approx(-math.sin(math.radians(0.3)))
    assert len(truth["arm"]["links"]) == 6
    assert truth["arm"]["links"][1]["a"] == pytest.approx(-0.425 + 0.0024)  # a_mm[1] = 2.4
    assert np.allclose(np.array(truth["T_flange_cam"])[:3, 3], [0, 0, 0.05])


def test_sim_up_then_down_leaves_nothing_running(start_sim):
    rig = start_sim()  # stopped by PID in teardown even if an assertion fails
    workdir = Path(rig.ready["workdir"])
    assert (workdir / "dxl").is_symlink()
    result = subprocess.run([sys.executable, "-m", "rigctl.cli", "sim", "down", "--host",
                             rig.host], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["stopped"] is True
    rig.proc.proc.wait(timeout=10)
    for pid in [rig.ready["pid"], *rig.ready["children"]]:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    assert not workdir.exists()


@pytest.mark.timeout(120)
def test_a_crashed_stand_in_ends_sim_up_with_an_error_and_its_log_is_kept(tmp_path):
    """A stand-in that dies (here SIGKILL to the head's bus) ends `sim up` with status 1
    and every other stand-in; the rig says so after stop, and its stderr outlives it in
    the log file, where a failing test's teardown can point."""
    log = tmp_path / "sim-up.log"
    rig = SimulatedRig("ideal", records=tmp_path / "records",
                       rig_out=tmp_path / "sim-rig.yaml", log=log)
    try:
        os.kill(rig.ready["head"]["pid"], signal.SIGKILL)
        wait_until(lambda: rig.proc.proc.poll() is not None, timeout=60, poll=0.1,
                   what="`sim up` to end after its head stand-in died")
    finally:
        orphans = rig.stop()
    assert rig.proc.proc.returncode == 1
    assert not orphans
    for pid in rig.ready["children"]:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    assert rig.crash and "status 1" in rig.crash and str(log) in rig.crash
    assert "sim head stand-in exited (-9)" in rig.crash
    assert "sim head stand-in exited (-9)" in log.read_text()
