"""SIGTERM mid-run: the CLI run and the service both stop the devices, record the run as
aborted and exit; the captures taken so far are kept."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import httpx
import pytest
import yaml

from rigctl.loopback import free_port
from rigctl.records import RecordIndex
from tests.mockproc import ROOT
from tests.waiting import wait_until

pytestmark = pytest.mark.integration

SLOW_SWEEP = ["--param", "pan_deg=[-40,-20,0,20,40]", "--param", "tilt_deg=[-20,0,20]",
              "--param", "settle_s=0.5"]


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
        lambda: _running(index), "the run to start", timeout=60)
    assert proc.returncode == 3, err[-2000:]
    assert json.loads(out)["status"] == "aborted"
    row = index.get(row["run_id"])
    assert row["status"] == "aborted" and row["reason"] == "SIGTERM received"


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
                return httpx.get(f"{url}/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(up, timeout=60, what="the service")
        params = {"pan_deg": [-40, -20, 0, 20, 40], "tilt_deg": [-20, 0, 20], "settle_s": 0.5}
        run_id = httpx.post(f"{url}/runs", json={"procedure": "head-sweep", "params": params},
                            timeout=30).json()["run_id"]
        wait_until(lambda: httpx.get(f"{url}/runs/{run_id}", timeout=30).json()["status"]
                   == "running", timeout=60, what="the run to start")
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=60)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=10)
    row = _index(rig_path).get(run_id)
    assert row["status"] == "aborted" and "service shutting down" in row["reason"]


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
