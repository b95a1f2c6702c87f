"""rigctl serve against a real uvicorn server on loopback, driving the simulated rig."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import httpx
import pytest

from tests.mockproc import ROOT, control
from tests.service_stack import (
    CAMERA_PARAMS,
    HTTP,
    REQUEST_TIMEOUT_S,
    LockHolder,
    Stack,
    get,
    post,
    wait_for,
)
from tests.waiting import wait_until

# one service stack and its accepted camera for the module, not one per worker
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("service")]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    s = Stack(tmp_path_factory.mktemp("service"))
    yield s
    s.stop()
    s.assert_no_crash()


@pytest.fixture(scope="module")
def accepted_camera(stack):
    """An accepted active-camera calibration on the ideal world (run here unless an earlier
    test already accepted one), so that drift has something to compare with."""
    latest = get(stack.base + "/calibrations/latest").json()
    if "active-camera" in latest:
        return latest["active-camera"]["run_id"]
    run_id = post(stack, "/runs", {"procedure": "active-camera",
                                   "params": CAMERA_PARAMS}).json()["run_id"]
    assert wait_for(stack, run_id, timeout=400)["status"] == "succeeded"
    wait_until(lambda: get(f"{stack.base}/runs/{run_id}").json()["decision"],
               what="the decision on the calibration")
    assert post(stack, f"/calibrations/{run_id}/accept").status_code == 200
    return run_id


def test_token_and_input_validation(stack):
    assert get(stack.base + "/health").json()["status"] == "ok"
    assert post(stack, "/runs", {"procedure": "head-sweep"}, auth=False).status_code == 401
    wrong = HTTP.post(stack.base + "/runs", json={"procedure": "head-sweep"},
                       timeout=REQUEST_TIMEOUT_S,
                       headers={"Authorization": "Bearer nope"})
    assert wrong.status_code == 401
    bad = post(stack, "/runs", {"procedure": "head-sweep", "params": {"pan_dgr": [1]}})
    assert bad.status_code == 422 and "pan_dgr: unknown parameter" in bad.text
    assert post(stack, "/runs", {"procedure": "rm -rf /"}).status_code == 422
    schema = get(stack.base + "/openapi.json").json()
    assert "/runs/{run_id}/abort" in schema["paths"]
    procs = {p["name"]: p for p in get(stack.base + "/procedures").json()}
    assert "pan_deg" in procs["active-camera"]["params_schema"]["properties"]
    console = get(stack.base + "/", follow_redirects=True)
    assert console.url.path == "/console/" and f"rigctl · {stack.rig_name}" in console.text
    assert get(stack.base + "/rig").json()["devices"]["head"] is not None


@pytest.mark.timeout(900)
def test_active_camera_with_progress_events_then_accept(stack):
    events, run_id = [], None
    with httpx.stream("GET", stack.base + "/events", timeout=180) as stream:
        r = post(stack, "/runs", {"procedure": "active-camera",
                                  "params": CAMERA_PARAMS})
        assert r.status_code == 202
        run_id = r.json()["run_id"]
        for line in stream.iter_lines():
            if line.startswith("data: "):
                event = json.loads(line[6:])
                if event.get("run_id") == run_id:
                    events.append(event)
                    if event["type"] == "decision":
                        break
    kinds = [e["type"] for e in events]
    assert kinds[0] == "queued" and "started" in kinds and "finished" in kinds
    steps = [e for e in events if e["type"] == "step"]
    assert len(steps) > 10 and steps[-1]["index"] >= steps[0]["index"]
    assert events[-1]["decision"] == "pending"  # the first calibration waits for an operator
    run = get(f"{stack.base}/runs/{run_id}").json()
    assert run["status"] == "succeeded"
    assert abs(run["result"]["fx"] / 900.0 - 1) < 0.005
    assert post(stack, f"/calibrations/{run_id}/accept", auth=False).status_code == 401
    accepted = post(stack, f"/calibrations/{run_id}/accept",
                    {"comment": "first intrinsics of this lens", "operator": "ada"})
    assert accepted.json()["decision"] == "accepted"
    page = get(f"{stack.base}/console/runs/{run_id}").text
    assert "first intrinsics of this lens" in page and "ada" in page
    latest = get(stack.base + "/calibrations/latest?procedure=active-camera").json()
    assert latest["active-camera"]["run_id"] == run_id
    image = get(f"{stack.base}/runs/{run_id}/captures/0")
    assert image.status_code == 200 and image.content[:4] == b"\x89PNG"
    assert get(f"{stack.base}/runs/{run_id}/captures/99").status_code == 404
    assert get(f"{stack.base}/console/history/active-camera.png").content[:4] == b"\x89PNG"


def test_two_requests_run_one_after_the_other(stack):
    params = {"pan_deg": [-5, 5], "tilt_deg": [0], "settle_s": 0.2}
    a = post(stack, "/runs", {"procedure": "head-sweep", "params": params}).json()["run_id"]
    b = post(stack, "/runs", {"procedure": "head-sweep", "params": params}).json()["run_id"]
    ra, rb = wait_for(stack, a), wait_for(stack, b)
    assert ra["status"] == rb["status"] == "succeeded"
    assert ra["ended_at"] <= rb["started_at"]  # FIFO, never together


def _head_control(stack) -> str:
    return stack.sim.ready["head"]["control"]


def _pan_held(stack) -> bool:
    servos = control(_head_control(stack), {"cmd": "dump"})["servos"]
    return next(s for s in servos if s["id"] == 1)["frozen"]


def test_abort_mid_run_and_cli_sees_the_rig_busy(stack):
    """Once the run's first capture is served, the bus stand-in holds the next pan move
    half-way (latched): the run is known to be under way while the CLI is refused and
    the abort comes, however slow the host."""
    params = {"pan_deg": [-20, 20, -20, 20, -20, 20], "tilt_deg": [0, 5], "settle_s": 0.5,
              "image": True}
    run_id = post(stack, "/runs", {"procedure": "head-sweep", "params": params}).json()["run_id"]
    try:
        wait_for(stack, run_id, statuses=("running",), timeout=60)
        # served while the run writes its next captures: each one whole (a half-written
        # PNG once broke this response mid-body on a busy host)
        capture = wait_until(lambda: (c := get(f"{stack.base}/runs/{run_id}/captures/0"))
                             .status_code == 200 and c, timeout=60, poll=0.2,
                             what="the first capture served")
        assert capture.content[:8] == b"\x89PNG\r\n\x1a\n"
        control(_head_control(stack), {"cmd": "freeze", "id": 1, "at_fraction": 0.5})
        wait_until(lambda: _pan_held(stack), timeout=60, what="a pan move held half-way")
        assert get(f"{stack.base}/runs/{run_id}").json()["status"] == "running"
        cli = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "head-sweep", "--rig",
                              str(stack.rig)], capture_output=True, text=True, timeout=120,
                             cwd=ROOT)
        assert cli.returncode == 2 and f"busy, held by run {run_id}" in cli.stderr
        assert post(stack, f"/runs/{run_id}/abort", auth=False).status_code == 401
        assert post(stack, f"/runs/{run_id}/abort").json()["status"] == "aborting"
        run = wait_for(stack, run_id)
        assert run["status"] == "aborted" and "aborted via the API" in run["reason"]
        assert get(f"{stack.base}/runs/{run_id}/captures/0").status_code == 200
    finally:  # a failure above must not leave the run holding the rig for the next test
        post(stack, f"/runs/{run_id}/abort")
        control(_head_control(stack), {"cmd": "thaw", "id": 1})
        wait_for(stack, run_id)


def _lock_holder(lock_dir) -> dict | None:
    files = list(lock_dir.glob("*.lock"))
    text = files[0].read_text() if files else ""
    return json.loads(text) if text else None


def test_service_run_while_cli_holds_the_rig_fails_busy(stack):
    """The CLI run's first move is held half-way by the bus stand-in (latched) until the
    service's run has been refused; then let go, the CLI run succeeds."""
    sock = _head_control(stack)
    control(sock, {"cmd": "freeze", "id": 1, "at_fraction": 0.5})
    cli = subprocess.Popen([sys.executable, "-m", "rigctl.cli", "run", "head-sweep", "--rig",
                            str(stack.rig), "--param", "pan_deg=[-20, 20, -20, 20]",
                            "--param", "settle_s=0.5"], cwd=ROOT, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    try:
        lock = stack.tmp / "records" / "locks"
        holder = wait_until(lambda: (h := _lock_holder(lock)) and h.get("pid") == cli.pid
                            and h, timeout=60, poll=0.1, what="the CLI run to take the rig")
        wait_until(lambda: _pan_held(stack), timeout=60, what="the CLI run's move held")
        body = {"procedure": "head-sweep", "params": {"pan_deg": [0], "tilt_deg": [0]}}
        run_id = post(stack, "/runs", body).json()["run_id"]
        run = wait_for(stack, run_id, timeout=60)  # the id the API returned stays valid
        assert run["status"] == "failed"
        assert f"busy, held by run {holder['run_id']} (pid {cli.pid})" in run["reason"]
        assert cli.poll() is None  # still held, still running
    finally:
        control(sock, {"cmd": "thaw", "id": 1})
        try:
            cli.wait(timeout=120)
        finally:
            if cli.poll() is None:
                cli.kill()
                cli.wait(timeout=10)
    assert cli.returncode == 0


@pytest.mark.timeout(300)
def test_schedule_fires_skips_while_the_rig_is_busy_and_records_its_runs(tmp_path):
    """A stack of its own (its schedule never holds the rig during the other tests): while
    another process holds the rig, an interval schedule's firing is recorded skipped,
    naming the holder; once it lets go, a scheduled run succeeds. Both are the
    scheduler's. The lock is held until the skip is seen: no timing decides the case."""
    schedule = {"procedure": "head-sweep", "interval_s": 3, "max_delay": "5s",
                "params": {"pan_deg": [0], "tilt_deg": [0], "settle_s": 0}}
    own = Stack(tmp_path, schedules=[schedule])

    def scheduled(status):
        runs = get(own.base + "/runs?limit=200&procedure=head-sweep").json()
        return [r for r in runs if r.get("operator") == "scheduler" and r["status"] == status]

    try:
        with LockHolder(tmp_path / "records" / "locks", own.rig_name, "run-held") as holder:
            skipped = wait_until(lambda: [r for r in scheduled("skipped")
                                          if "run-held" in (r["reason"] or "")],
                                 timeout=120, poll=0.5, what="a scheduled run skipped as busy")
            assert f"busy, held by run run-held (pid {holder.proc.pid})" in skipped[0]["reason"]
        before = {r["run_id"] for r in scheduled("succeeded")}
        wait_until(lambda: {r["run_id"] for r in scheduled("succeeded")} - before,
                   timeout=120, poll=0.5, what="a scheduled run after the rig is free")
        assert all("busy" in (r["reason"] or "") for r in scheduled("skipped"))
    finally:
        own.stop()
    own.assert_no_crash()


@pytest.mark.timeout(900)
def test_drifted_intrinsics_are_flagged_and_wait(stack, accepted_camera):
    stack.restart_sim("drift")  # same devices, refocused lens
    try:
        run_id = post(stack, "/runs", {"procedure": "active-camera",
                                       "params": CAMERA_PARAMS}).json()["run_id"]
        run = wait_for(stack, run_id, timeout=400)
    finally:
        stack.restart_sim("ideal")  # the next test finds the rig as it was
    assert run["status"] == "succeeded", run.get("reason")
    deadline = time.monotonic() + 10
    while get(f"{stack.base}/runs/{run_id}").json()["decision"] is None:
        assert time.monotonic() < deadline
        time.sleep(0.2)
    assert get(f"{stack.base}/runs/{run_id}").json()["decision"] == "drift"
    assert stack.hook.received and stack.hook.received[-1]["run_id"] == run_id
    assert any("focal length changed" in d for d in stack.hook.received[-1]["drift"])
    latest = get(stack.base + "/calibrations/latest?procedure=active-camera").json()
    assert latest["active-camera"]["run_id"] == accepted_camera  # still the accepted one
    history = get(stack.base + "/calibrations/history?procedure=active-camera").json()
    assert {h["decision"] for h in history} >= {"accepted", "drift"}


def test_non_loopback_bind_requires_a_token(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text("devices: {}\nservice: {bind: 0.0.0.0}\n")
    # a hang guard, not a time limit (as the other CLI calls': under the load check, two
    # busy cores beside five workers, this 2 s refusal outlived 30 s once)
    result = subprocess.run([sys.executable, "-m", "rigctl.cli", "serve", "--rig", str(rig)],
                            capture_output=True, text=True, timeout=120, cwd=ROOT,
                            env={"PATH": "/usr/bin:/bin"})
    assert result.returncode == 2 and "requires a bearer token" in result.stderr
