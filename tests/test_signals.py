"""SIGTERM mid-run: the CLI run and the service both stop the devices, park them, record
the run as aborted and exit; the captures taken so far are kept. The signal comes while
a move is known to be under way: the bus stand-in holds it half-way (latched)."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import httpx
import pytest
import yaml

from rigctl.loopback import free_port
from rigctl.record_index import RecordIndex
from tests.mockproc import ROOT, control
from tests.service_stack import HTTP
from tests.waiting import wait_until

pytestmark = pytest.mark.integration

SLOW_SWEEP = ["--param", "pan_deg=[-40,-20,0,20,40]", "--param", "tilt_deg=[-20,0,20]",
              "--param", "settle_s=0.5", "--param", "image=true"]


def _held_after_a_capture(sim, index) -> dict:
    """Once the running run has written its first capture, tell the bus stand-in to hold
    the pan servo's move under way (or its next) half-way, and wait until it stands
    there: the run is then mid-move, with its captures so far on disk, for as long as
    the test needs. Returns the running row and the captures on disk then."""
    row = wait_until(lambda: (r := _running(index)) and
                     (Path(r["run_dir"]) / "captures" / "000.json").exists() and r,
                     timeout=120, what="the run's first capture")
    sock = sim.ready["head"]["control"]
    control(sock, {"cmd": "freeze", "id": 1, "at_fraction": 0.5})
    wait_until(lambda: _servos(sock)[1]["frozen"], timeout=60, what="a pan move held")
    row["captures_then"] = sorted(p.name for p in (Path(row["run_dir"]) / "captures").iterdir())
    return row


def _servos(sock: str) -> dict[int, dict]:
    return {s["id"]: s for s in control(sock, {"cmd": "dump"})["servos"]}


def _assert_parked_home(sim) -> None:
    """Every servo's goal and present position at home (the centre), not moving."""
    for dxl_id, servo in _servos(sim.ready["head"]["control"]).items():
        assert abs(servo["actual_rad"]) < math.radians(0.1), (dxl_id, servo)
        assert abs(servo["goal_position"] - servo["present_position"]) <= 1, (dxl_id, servo)
        assert servo["moving"] == 0 and not servo["frozen"], (dxl_id, servo)


def _assert_captures_kept(rig_path, row) -> None:
    """The captures on disk when the signal came are all there, each image whole, and
    the record lists them (`rigctl runs show`)."""
    kept = sorted(p.name for p in (Path(row["run_dir"]) / "captures").iterdir())
    assert kept == row["captures_then"] and "000.png" in kept
    shown = subprocess.run([sys.executable, "-m", "rigctl.cli", "runs", "show", row["run_id"],
                            "--rig", str(rig_path), "--json"], capture_output=True, text=True,
                           timeout=60, cwd=ROOT)
    listed = json.loads(shown.stdout)
    assert listed["captures"] == len([n for n in kept if n.endswith(".json")]) >= 1
    assert listed["status"] == "aborted" and listed["run_dir"] == row["run_dir"]
    for name in kept:
        if name.endswith(".png"):
            assert cv2.imread(str(Path(row["run_dir"]) / "captures" / name)) is not None


def _index(rig_path):
    from rigctl.config import load_rig

    return RecordIndex(load_rig(rig_path).database_url())


def _running(index) -> dict | None:
    rows = [r for r in index.list(5) if r["status"] == "running"]
    return rows[0] if rows else None


def _sigterm_once(args: list[str], ready, what: str, timeout: float):
    """Start ``rigctl args``, send it SIGTERM once ``ready()`` holds, and wait for it to
    exit; killed (by PID) if it outlives the test. Returns the process, its (stdout,
    stderr) and what ``ready`` returned."""
    proc = subprocess.Popen([sys.executable, "-m", "rigctl.cli", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        state = wait_until(ready, timeout=timeout, what=what)
        proc.send_signal(signal.SIGTERM)
        return proc, proc.communicate(timeout=timeout), state
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


@pytest.mark.timeout(180)
def test_sigterm_on_a_cli_run_exits_3_and_records_it_aborted(start_sim):
    sim = start_sim()
    index = _index(sim.rig_path)
    proc, (out, err), row = _sigterm_once(
        ["run", "head-sweep", "--rig", str(sim.rig_path), "--json", *SLOW_SWEEP],
        lambda: _held_after_a_capture(sim, index), "a move held after a capture",
        timeout=120)
    assert proc.returncode == 3, err[-2000:]
    assert json.loads(out)["status"] == "aborted"
    recorded = index.get(row["run_id"])
    assert recorded["status"] == "aborted" and recorded["reason"] == "SIGTERM received"
    _assert_captures_kept(sim.rig_path, row)
    _assert_parked_home(sim)


@pytest.mark.timeout(180)
def test_sigterm_on_the_service_mid_run_aborts_the_run_and_exits(start_sim, tmp_path):
    sim = start_sim()
    rig = yaml.safe_load(sim.rig_path.read_text())
    port = free_port()
    rig["service"] = {"bind": "127.0.0.1", "port": port}
    rig_path = tmp_path / "service-rig.yaml"
    rig_path.write_text(yaml.safe_dump(rig))
    server = subprocess.Popen([sys.executable, "-m", "rigctl.cli", "serve", "--rig",
                               str(rig_path)], cwd=ROOT, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        def up():
            try:
                return HTTP.get(f"{url}/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(up, timeout=60, what="the service")
        params = {"pan_deg": [-40, -20, 0, 20, 40], "tilt_deg": [-20, 0, 20], "settle_s": 0.5,
                  "image": True}
        run_id = HTTP.post(f"{url}/runs", json={"procedure": "head-sweep", "params": params},
                            timeout=30).json()["run_id"]
        held = _held_after_a_capture(sim, _index(rig_path))
        assert held["run_id"] == run_id
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=60)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=10)
    row = _index(rig_path).get(run_id)
    assert row["status"] == "aborted" and "service shutting down" in row["reason"]
    _assert_captures_kept(rig_path, held)
    _assert_parked_home(sim)


def _processes_naming(text: str) -> list[int]:
    """PIDs whose command line names ``text`` (Linux /proc)."""
    from pathlib import Path

    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if text in (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode():
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


@pytest.mark.timeout(240)
def test_sigterm_stops_bench_worlds_not_just_one_world(tmp_path):
    """The runner turns SIGTERM into an aborted run; the benchmark must then stop (exit
    130, the unfinished world left out, its stand-ins stopped), not go on to the next."""
    import os

    keep = tmp_path / "kept"
    try:
        proc, (out, err), _ = _sigterm_once(
            ["bench", "worlds", "--n", "3", "--first-seed", "9100", "--keep", str(keep),
             "--plot", str(tmp_path / "plot.png"), "--json"],
            lambda: any((keep / "records-9100").glob("*-active-camera-*")),
            "the first world's first run", timeout=120)
    finally:
        left = _processes_naming(str(keep))
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 130, err[-2000:]
    report = json.loads(out)
    assert "SIGTERM received" in report["stopped"] and report["worlds"] == []
    assert not (keep / "world-9101.yaml").exists()  # the next world never started
    assert not left, f"stand-ins {left} outlived the benchmark"
