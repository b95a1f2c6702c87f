"""Taught runs on the simulated rig, end to end: `rigctl run hand-eye --param teach=true`
reads the operator's presses from its terminal (Enter = capture, `done`), the test plays
the operator's hand through the arm stand-in's control socket (``freedrive``), and the
result is judged against the world's truth. Teach mode is left on every end: done, an
abort (SIGTERM), a fault (the camera stalls during a capture).

The camera model is given as the world's truth (``--param intrinsics=``): the hand-eye
and the taught set are what is judged here, and an active-camera run would double the
module's CPU time on a 2-core host."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from rigctl.bench.truth import model_against_truth
from rigctl.config import load_rig
from rigctl.geometry.kinematics import nominal_ur
from rigctl.mocks.world import WORLDS, load_world
from rigctl.procedures.planning import informative_views, visible_views
from rigctl.procedures.robot_kinematics import RobotKinematicsParams
from tests.mockproc import ROOT, control, simulated_rig
from tests.waiting import wait_until

# one simulated rig for the module, not one per worker
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("teach-run")]

WORLD = "default"
RUN_TIMEOUT_S = 600  # a hang guard: the waits below are on observed states


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    base = tmp_path_factory.mktemp("teach-rig")
    with simulated_rig(base, WORLD) as rig:
        yield rig, base / "records"


@pytest.fixture(scope="module")
def truth():
    return load_world(WORLDS / f"{WORLD}.yaml").truth()


def _intrinsics(truth) -> str:
    return json.dumps({k: truth[k] for k in ("fx", "fy", "cx", "cy", "distortion")})


def _arm(sim, request: dict, timeout: float = 60) -> dict:
    return control(sim[0].ready["arm"]["control"], request, timeout)


def _captures(records) -> int:
    return len(list(records.glob("*/captures/[0-9][0-9][0-9].json")))


class Taught:
    """`rigctl run ... teach=true` with its terminal on a pipe; stopped by PID."""

    def __init__(self, sim, truth, *params: str, rig_path: Path | None = None,
                 procedure: str = "hand-eye") -> None:
        rig, self.records = sim
        self.sim = sim
        args = [sys.executable, "-m", "rigctl.cli", "run", procedure, "--rig",
                str(rig_path or rig.rig_path), "--json", "--param", "teach=true",
                "--param", f"intrinsics={_intrinsics(truth)}", "--param", "settle_s=0"]
        for p in params:
            args += ["--param", p]
        self.before = _captures(self.records)
        self.messages_before = _arm(sim, {"cmd": "dump"})["messages_total"]
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, cwd=ROOT)
        wait_until(lambda: self._alive() and _arm(sim, {"cmd": "dump"})["teach_mode"],
                   timeout=120, what="the run to put the arm in teach mode", poll=0.1)

    def _alive(self) -> bool:
        if self.proc.poll() is not None:
            raise AssertionError(f"rigctl run exited: {self.proc.stderr.read()[-3000:]}")
        return True

    def pose(self, q_deg) -> None:
        """The operator moves the arm to ``q_deg`` and presses Enter; waits for the
        capture's sidecar."""
        moved = _arm(self.sim, {"cmd": "freedrive", "q_deg": list(q_deg), "speed_dps": 120})
        assert moved["ok"], moved
        want = _captures(self.records) + 1
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        wait_until(lambda: self._alive() and _captures(self.records) >= want, timeout=120,
                   what=f"capture {want - self.before}", poll=0.05)

    def finish(self, line: str = "done\n") -> tuple[int, str, str]:
        out, err = self.proc.communicate(line, timeout=RUN_TIMEOUT_S)
        return self.proc.returncode, out, err

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


@pytest.fixture
def taught(sim, truth):
    started: list[Taught] = []

    def start(*params: str, rig_path: Path | None = None,
              procedure: str = "hand-eye") -> Taught:
        started.append(Taught(sim, truth, *params, rig_path=rig_path, procedure=procedure))
        return started[-1]

    yield start
    for run in started:
        run.stop()


def _views(sim, truth, n: int) -> list[np.ndarray]:
    config = load_rig(sim[0].rig_path)
    K = np.array([[truth["fx"], 0, truth["cx"]], [0, truth["fy"], truth["cy"]], [0, 0, 1]])
    poses, _ = visible_views(config, n, 0.45, 30.0, 21, "view", K,
                             nominal_ur(config.devices.arm.model))
    assert len(poses) == n
    return poses


def _teach_off_explicitly(sim, run: Taught) -> None:
    """Teach mode is off, and this run ended it (the rig is shared by the module's runs:
    only the controller's messages since ``run`` started count)."""
    dump = _arm(sim, {"cmd": "dump"})
    assert dump["teach_mode"] is False
    since = dump["messages_total"] - run.messages_before
    assert since > 0, dump["messages"]
    assert "teach mode off: end_teach_mode()" in dump["messages"][-since:], dump["messages"]


@pytest.mark.timeout(900)
def test_a_taught_hand_eye_run_calibrates(sim, truth, taught):
    run = taught()
    for q in _views(sim, truth, 8):
        run.pose(np.degrees(q))
    code, out, err = run.finish()
    assert code == 0, err[-3000:]
    _teach_off_explicitly(sim, run)
    result = json.loads(out)
    assert result["summary"]["views"] == 8
    captures = sorted((p for p in sim[1].glob("*/captures/[0-9][0-9][0-9].json")),
                      key=lambda p: p.stat().st_mtime)[-8:]
    meta = [json.loads(p.read_text()) for p in captures]
    assert all(m["extra"]["taught"] and m["arm"]["q"] for m in meta)
    # the hand-eye against the world's truth, to the bounds a planned run of 8 views
    # reaches on this world (tests/test_e2e_default_world.py: 5 mm, 2 deg)
    X, X_true = np.array(result["T_flange_cam"]), np.array(truth["T_flange_cam"])
    assert 1000 * np.linalg.norm(X[:3, 3] - X_true[:3, 3]) < 5.0
    cos = (np.trace(X[:3, :3].T @ X_true[:3, :3]) - 1) / 2
    assert math.degrees(math.acos(np.clip(cos, -1, 1))) < 2.0
    # the taught set's identifiability, against the D-optimal plan of as many views
    report = result["pose_set"]
    assert report["determined"] and report["warning"] is None
    assert report["d_optimal"]["views"] == 8
    assert report["condition_number"] < 1e4
    assert 0 < report["camera_position_sigma_mm"]["median"] < 5.0
    teach_json = json.loads((captures[-1].parent.parent / "teach.json").read_text())
    assert teach_json["poses"] == 8 and teach_json["pose_set"]["determined"]


RK_VIEWS = 20


@pytest.mark.heavy
@pytest.mark.timeout(1200)
def test_taught_and_pose_file_robot_kinematics_runs_meet_the_truth(sim, truth, taught,
                                                                   tmp_path):
    """The same poses read from a file and taught by hand: both arm models within the
    random-world targets (median 0.12 mm, worst 0.25 mm RMS) against the world's truth,
    over configurations neither run saw."""
    rig, _ = sim
    config = load_rig(rig.rig_path)
    K = np.array([[truth["fx"], 0, truth["cx"]], [0, truth["fy"], truth["cy"]], [0, 0, 1]])
    # an informative set: the D-optimal views robot-kinematics itself would plan
    chosen, _ = informative_views(config, RobotKinematicsParams(), K, [], RK_VIEWS, 5)
    poses = [np.degrees(q) for q in chosen]
    assert len(poses) == RK_VIEWS
    pose_file = tmp_path / "poses.yaml"
    pose_file.write_text("".join("- [" + ", ".join(f"{v:.4f}" for v in q) + "]\n"
                                 for q in poses))
    filed = subprocess.run(
        [sys.executable, "-m", "rigctl.cli", "run", "robot-kinematics", "--rig",
         str(rig.rig_path), "--json", "--param", f"poses_file={pose_file}", "--param",
         f"intrinsics={_intrinsics(truth)}", "--param", "settle_s=0"],
        capture_output=True, text=True, timeout=RUN_TIMEOUT_S, cwd=ROOT)
    assert filed.returncode == 0, filed.stderr[-3000:]
    run = taught(procedure="robot-kinematics")
    for q in poses:
        run.pose(q)
    code, out, err = run.finish()
    assert code == 0, err[-3000:]
    _teach_off_explicitly(sim, run)
    world = load_world(WORLDS / f"{WORLD}.yaml")
    for how, result in (("pose file", json.loads(filed.stdout)), ("taught", json.loads(out))):
        assert result["summary"]["training_views"] >= RK_VIEWS - 1, how  # an outlier at most
        report = result["pose_set"]
        assert report["determined"] and report["warning"] is None, how
        rms, worst, count = model_against_truth(result, config, world)
        assert count > 60 and rms < 0.12 and worst < 0.25, (how, rms, worst)


@pytest.mark.timeout(600)
def test_a_degenerate_taught_set_gets_the_warning(sim, truth, taught):
    run = taught()
    base = np.degrees(_views(sim, truth, 8)[0])
    for k in range(4):  # every pose one joint (the last) apart from the others
        run.pose(base + np.array([0, 0, 0, 0, 0, 8.0 * k]))
    _code, _out, err = run.finish()
    _teach_off_explicitly(sim, run)
    newest = max(sim[1].glob("*/teach.json"), key=lambda p: p.stat().st_mtime)
    report = json.loads(newest.read_text())["pose_set"]
    assert not report["determined"]
    assert "every pose differs from the others in joint 6 only" in report["warning"]
    assert "cannot determine the model" in err  # said to the operator before the solve


@pytest.mark.timeout(600)
def test_teach_mode_ends_on_an_abort(sim, truth, taught):
    run = taught()
    run.pose(np.degrees(_views(sim, truth, 8)[0]))
    run.proc.send_signal(signal.SIGTERM)
    _code, out, err = run.finish("")
    assert json.loads(out)["status"] == "aborted", err[-2000:]
    _teach_off_explicitly(sim, run)


@pytest.mark.timeout(600)
def test_teach_mode_ends_on_a_fault(sim, truth, taught, tmp_path):
    # pausing off (``max_pause_s: 0``): the stalled stream ends the run instead of
    # pausing it (tests/test_resume_runs.py checks the pause)
    rig = tmp_path / "no-pause-rig.yaml"
    rig.write_text(sim[0].rig_path.read_text() + "max_pause_s: 0\n")
    run = taught(rig_path=rig)
    control(sim[0].ready["camera"]["control"], {"cmd": "stall", "seconds": 60})
    try:
        moved = _arm(sim, {"cmd": "freedrive", "q_deg": list(np.degrees(
            _views(sim, truth, 8)[0])), "speed_dps": 120})
        assert moved["ok"]
        _code, out, _err = run.finish("\n")  # capture, then the stream's fault ends the run
    finally:
        control(sim[0].ready["camera"]["control"], {"cmd": "stall", "seconds": 0})
    outcome = json.loads(out)
    assert outcome["status"] == "failed" and "camera" in outcome["reason"].lower(), outcome
    _teach_off_explicitly(sim, run)
    assert yaml.safe_dump(outcome)  # the outcome is plain data
