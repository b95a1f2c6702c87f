"""`kill -9` of `rigctl serve` mid-run, then a restart (issue 42): the run is
`interrupted` with its captures intact and the lock freed, the run queued behind it is
reported (recorded aborted with the reason, listed in GET /rig), and POST
/runs/{id}/resume completes the run in its own directory. Real processes throughout:
`rigctl serve` on the simulated rig."""

from __future__ import annotations

import subprocess
import sys

import httpx
import pytest

from rigctl.config import load_rig
from rigctl.locks import rig_lock
from rigctl.records import RunDirectory
from tests.mockproc import ROOT
from tests.service_stack import Stack, get, post, wait_for
from tests.waiting import wait_until

pytestmark = pytest.mark.integration

SWEEP = {"pan_deg": [-10, -5, 0, 5, 10], "tilt_deg": [0, 5, 10], "settle_s": 0.3}


@pytest.fixture
def stack(tmp_path):
    s = Stack(tmp_path)
    try:
        yield s
    finally:
        s.stop()
        s.assert_no_crash()


def _serve(stack) -> subprocess.Popen:
    """Start `rigctl serve` again on the stack's rig file (stopped by the stack, by PID)."""
    stack.server = subprocess.Popen([sys.executable, "-m", "rigctl.cli", "serve", "--rig",
                                     str(stack.rig)], cwd=ROOT, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, text=True)

    def healthy():
        assert stack.server.poll() is None, stack.server.stderr.read()[-2000:]
        try:
            return get(stack.base + "/health", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False
    wait_until(healthy, timeout=90, what="the service to answer /health")


def _captures(stack, run_id: str) -> int:
    r = get(f"{stack.base}/runs/{run_id}")
    if r.status_code != 200 or not r.json().get("run_dir"):
        return 0
    return len(RunDirectory(r.json()["run_dir"]).captures())


@pytest.mark.timeout(300)
def test_a_killed_service_leaves_its_run_resumable_and_reports_its_queue(stack):
    first = post(stack, "/runs", {"procedure": "head-sweep", "params": SWEEP}).json()
    queued = post(stack, "/runs", {"procedure": "head-sweep", "params": SWEEP}).json()
    wait_until(lambda: _captures(stack, first["run_id"]) >= 3, timeout=120,
               what="three captures")
    run_dir = get(f"{stack.base}/runs/{first['run_id']}").json()["run_dir"]
    stack.server.kill()  # SIGKILL: nothing is cleaned up
    stack.server.wait(30)
    kept = len(RunDirectory(run_dir).captures())
    assert 3 <= kept < 15

    _serve(stack)
    run = get(f"{stack.base}/runs/{first['run_id']}").json()
    assert run["status"] == "interrupted" and run["segments"][0]["end"] == "interrupted"
    assert len(RunDirectory(run["run_dir"]).captures()) == kept
    lock = rig_lock(load_rig(stack.rig))  # freed with the killed process
    lock.acquire("probe")
    lock.release()
    lost = get(f"{stack.base}/rig").json()["lost_queue"]
    assert [j["run_id"] for j in lost] == [queued["run_id"]]
    never = get(f"{stack.base}/runs/{queued['run_id']}").json()
    assert never["status"] == "aborted" and "ended before the run started" in never["reason"]

    assert post(stack, f"/runs/{first['run_id']}/resume", auth=False).status_code == 401
    assert post(stack, "/runs/no-such-run/resume").status_code == 404
    refused = post(stack, f"/runs/{queued['run_id']}/resume")
    assert refused.status_code == 409 and "never started" in refused.json()["detail"]
    resumed = post(stack, f"/runs/{first['run_id']}/resume")
    assert resumed.status_code == 200 and resumed.json()["status"] == "queued"
    done = wait_for(stack, first["run_id"], timeout=180)
    assert done["status"] == "succeeded", done["reason"]
    assert [s["end"] for s in done["segments"]] == ["interrupted", "succeeded"]
    caps = RunDirectory(done["run_dir"]).captures()
    assert [c.index for c in caps] == list(range(15))
    assert sorted(c.meta["step"] for c in caps) == sorted({c.meta["step"] for c in caps})
    again = post(stack, f"/runs/{first['run_id']}/resume")
    assert again.status_code == 409 and "succeeded" in again.json()["detail"]
