"""Runs that survive interruptions, on the simulated rig through the CLI and the real
clients (issue 42): a robot-kinematics run paused by a protective stop continues after
`rigctl arm unlock`; the same run killed with `kill -9` half-way is resumed with
`rigctl run --resume`; a rig file changed meanwhile refuses the resume (exit 2). Both
results are checked against the world's truth, within the model's own sigma.

One simulated rig serves the module (its runs take turns on the rig's lock)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rigctl.bench.truth import model_against_truth, position_z
from rigctl.config import load_rig
from rigctl.locks import rig_lock
from rigctl.mocks.world import load_world
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory
from tests.mockproc import ROOT, control, simulated_rig
from tests.waiting import wait_until

pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("resume-runs"),
              pytest.mark.heavy]

WORLD = ROOT / "rigctl/mocks/worlds/default.yaml"
# the smallest robot-kinematics plan that calibrates (as in test_console_browser), with
# the world's intrinsics given, so that no active-camera run is needed first
SMALL = {"sweep_steps": "3", "random_poses": "8", "heldout_poses": "2",
         "sweep_base_candidates": "4", "settle_s": "0.05"}


def _params() -> list[str]:
    truth = load_world(WORLD).truth()
    intr = {k: truth[k] for k in ("fx", "fy", "cx", "cy", "distortion")}
    intr["sigma"] = {"fx": 1.0, "fy": 1.0, "cx": 1.0, "cy": 1.0}
    out = [f"intrinsics={json.dumps(intr)}"] + [f"{k}={v}" for k, v in SMALL.items()]
    return [a for p in out for a in ("--param", p)]


def rigctl(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rigctl.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


def start_run(rig: Path, log: Path) -> subprocess.Popen:
    """`rigctl run robot-kinematics --json` in the background (stderr to ``log``)."""
    with open(log, "w") as err:
        return subprocess.Popen([sys.executable, "-m", "rigctl.cli", "run", "robot-kinematics",
                                 "--rig", str(rig), "--json", *_params()],
                                stdout=subprocess.PIPE, stderr=err, text=True, cwd=ROOT)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    with simulated_rig(tmp_path_factory.mktemp("resume-rig"), "default") as rig:
        yield rig


@pytest.fixture
def procs():
    """Processes a test starts, stopped by PID at its end."""
    started: list[subprocess.Popen] = []
    yield started
    for proc in started:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)


def only_new_row(rig: Path, seen: set[str]) -> dict | None:
    rows = [r for r in RecordIndex(load_rig(rig).database_url()).list(50)
            if r["run_id"] not in seen]
    return rows[0] if rows else None


def captures_of(row: dict | None) -> int:
    if row is None or not row["run_dir"]:
        return 0
    return len(RunDirectory(row["run_dir"]).captures())


def show(rig: Path, run_id: str) -> dict:
    done = rigctl("runs", "show", run_id, "--rig", str(rig), "--json", timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def check_against_truth(out: dict, rig: Path) -> tuple[float, float]:
    """The exported model's camera position against the truth: RMS (mm) and the RMS of
    the errors over the model's own predicted sigma."""
    world = load_world(WORLD)
    rms, _, count = model_against_truth(out, load_rig(rig), world)
    z = np.asarray(position_z(out, load_rig(rig), world))
    assert count > 60 and z.size > 60
    return rms, float(np.sqrt(np.mean(z ** 2)))


def plan_captures(run_dir: str) -> int:
    steps = json.loads(Path(run_dir, "plan.json").read_text())["steps"]
    return sum(s["kind"] == "CaptureStep" for s in steps)


def assert_complete(run_dir: str) -> None:
    """Every planned capture taken once, numbered without gaps or collisions, each
    with its step; the solve used them all (none lost)."""
    run = RunDirectory(run_dir)
    caps = run.captures()
    steps = [c.meta["step"] for c in caps]
    assert [c.index for c in caps] == list(range(len(caps)))
    assert len(set(steps)) == len(steps) == plan_captures(run_dir)


@pytest.mark.timeout(900)
def test_a_protective_stop_pauses_the_run_until_arm_unlock(sim, procs, tmp_path):
    rig, sock = sim.rig_path, sim.ready["arm"]["control"]
    seen = {r["run_id"] for r in RecordIndex(load_rig(rig).database_url()).list(50)}
    proc = start_run(rig, tmp_path / "run.log")
    procs.append(proc)
    wait_until(lambda: captures_of(only_new_row(rig, seen)) >= 8, timeout=600,
               what="eight captures")
    control(sock, {"cmd": "protective_stop"})
    row = wait_until(lambda: (r := only_new_row(rig, seen)) and r["status"] == "paused" and r,
                     timeout=120, what="the run paused")
    assert "protective stop" in row["reason"] and "rigctl arm unlock" in row["reason"]
    shown = show(rig, row["run_id"])
    assert shown["status"] == "paused" and shown["segments"][0]["end"] == "paused"
    assert proc.poll() is None  # a paused run keeps its process
    # nothing moves while paused: the arm held in its protective stop, at rest
    held = wait_until(lambda: (d := control(sock, {"cmd": "dump"}))
                      and not any(d["qd"]) and d, timeout=30, what="the arm at rest")
    assert held["safety_mode"] == 3
    unlocked = rigctl("arm", "unlock", "--rig", str(rig), timeout=120)
    assert unlocked.returncode == 0, unlocked.stderr
    out, _ = proc.communicate(timeout=900)
    assert proc.returncode == 0, (tmp_path / "run.log").read_text()[-3000:]
    result = json.loads(out)
    row = show(rig, row["run_id"])
    assert row["status"] == "succeeded"
    ends = [s["end"] for s in row["segments"]]
    assert ends == ["paused", "succeeded"], row["segments"]
    assert row["segments"][1]["start_reason"].startswith("continued")
    assert_complete(row["run_dir"])
    rms, z = check_against_truth(result, rig)
    print(f"protective stop: {rms:.3f} mm RMS against the truth, z RMS {z:.2f}")
    assert rms < 1.0 and z < 2.0


@pytest.mark.timeout(900)
def test_a_run_killed_half_way_is_resumed_to_the_same_accuracy(sim, procs, tmp_path):
    rig = sim.rig_path
    seen = {r["run_id"] for r in RecordIndex(load_rig(rig).database_url()).list(50)}
    proc = start_run(rig, tmp_path / "run.log")
    procs.append(proc)
    row = wait_until(lambda: only_new_row(rig, seen), timeout=120, what="the run recorded")
    half = math.ceil(plan_captures(row["run_dir"]) / 2)
    wait_until(lambda: captures_of(row) >= half, timeout=600, what="half the captures")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=60)
    kept = captures_of(row)
    assert kept >= half
    shown = show(rig, row["run_id"])
    assert shown["status"] == "interrupted" and shown["segments"][0]["end"] == "interrupted"
    lock = rig_lock(load_rig(rig))  # the lock died with the process
    lock.acquire("probe")
    lock.release()

    # a rig file changed meanwhile refuses the resume, and nothing moves
    text = rig.read_text()
    # the killed run's last move may still be running on the controller: wait for rest
    before = wait_until(lambda: (d := control(sim.ready["arm"]["control"], {"cmd": "dump"}))
                        and not any(d["qd"]) and d, timeout=60, what="the arm at rest")["q"]
    rig.write_text(text + "\n# changed\n")
    try:
        refused = rigctl("run", "--resume", row["run_id"], "--rig", str(rig), "--json")
    finally:
        rig.write_text(text)
    assert refused.returncode == 2, refused.stderr[-2000:]
    assert "rig file hash changed" in json.loads(refused.stdout)["error"]
    assert control(sim.ready["arm"]["control"], {"cmd": "dump"})["q"] == before
    assert show(rig, row["run_id"])["status"] == "interrupted"

    done = rigctl("run", "--resume", row["run_id"][:24], "--rig", str(rig), "--json")
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout)
    shown = show(rig, row["run_id"])
    assert shown["status"] == "succeeded"
    assert [s["end"] for s in shown["segments"]] == ["interrupted", "succeeded"]
    assert shown["segments"][1]["from_step"] > 0
    assert_complete(row["run_dir"])
    assert [c.index for c in RunDirectory(row["run_dir"]).captures()][:kept] == \
        list(range(kept))  # the captures kept are the ones taken before the kill
    rms, z = check_against_truth(result, rig)
    print(f"kill -9 and resume: {rms:.3f} mm RMS against the truth, z RMS {z:.2f}")
    assert rms < 1.0 and z < 2.0
    again = rigctl("run", "--resume", row["run_id"], "--rig", str(rig), "--json")
    assert again.returncode == 2 and "succeeded" in json.loads(again.stdout)["error"]
