"""The service token never leaves the service: `rigctl serve` on loopback with a token and
``public_read: false`` runs a real capture-survey on the simulated rig (head, camera and
arm through their real clients); then the whole run directory, the index and every answer
of the API and the console are searched for the token. Reads without the token get 401
there (loopback bind, reads not public); with it, or with the console's session cookie,
200."""

from __future__ import annotations

import json
import math
import secrets
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import yaml

from rigctl.config import load_rig
from rigctl.loopback import free_port
from rigctl.records import RunDirectory
from rigctl.redaction import REDACTED
from rigctl.runner import recorded_config, solve_recorded
from tests.mockproc import ROOT
from tests.service_stack import HTTP, REQUEST_TIMEOUT_S, start_sim
from tests.waiting import wait_until

# one worker runs the module, so its service and run are made once
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("token-leak"),
              pytest.mark.heavy]

# long and random: it cannot turn up anywhere by chance
TOKEN = "tok-" + secrets.token_urlsafe(24)
PARAMS = {"pan_deg": [-5.0, 5.0], "tilt_deg": [0.0], "views": 2, "settle_s": 0.05}


class Service:
    """The simulated rig and `rigctl serve` on it, with ``TOKEN`` and reads not public;
    both stopped by PID."""

    def __init__(self, tmp: Path) -> None:
        self.sim = self.server = None
        try:
            self.sim = start_sim(tmp, "ideal")
            rig = yaml.safe_load((tmp / "sim-rig.yaml").read_text())
            self.port = free_port()
            rig["service"] = {"bind": "127.0.0.1", "port": self.port, "token": TOKEN,
                              "public_read": False}
            self.rig = tmp / "service-rig.yaml"
            # the token once more, in a comment: the copy must not carry it either
            self.rig.write_text(f"# service token for this rig: {TOKEN}\n"
                                + yaml.safe_dump(rig))
            self.stderr = open(tmp / "serve.log", "w+")  # noqa: SIM115 - closed in stop()
            self.server = subprocess.Popen(
                [sys.executable, "-m", "rigctl.cli", "serve", "--rig", str(self.rig)],
                cwd=ROOT, stdout=self.stderr, stderr=self.stderr)
            self.base = f"http://127.0.0.1:{self.port}"
            wait_until(self._healthy, timeout=90, what="the service to answer /health")
        except BaseException:
            self.stop()
            raise

    def _healthy(self) -> bool:
        if self.server.poll() is not None:
            raise RuntimeError(f"service exited: {Path(self.stderr.name).read_text()[-2000:]}")
        try:
            return HTTP.get(self.base + "/health", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    def stop(self) -> None:
        if self.server is not None and self.server.poll() is None:
            self.server.terminate()
            try:
                self.server.wait(20)
            except subprocess.TimeoutExpired:
                self.server.kill()
                self.server.wait(5)
        if self.sim is not None:
            self.sim.stop(timeout=20)
        if self.server is not None:
            self.stderr.close()


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    s = Service(tmp_path_factory.mktemp("token"))
    yield s
    s.stop()


def _get(service, path, **kwargs):
    return HTTP.get(service.base + path, timeout=REQUEST_TIMEOUT_S, **kwargs)


AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def finished_run(service):
    """A capture-survey queued with the token, followed to its end."""
    r = HTTP.post(service.base + "/runs", json={"procedure": "capture-survey",
                                                 "params": PARAMS},
                   headers=AUTH, timeout=REQUEST_TIMEOUT_S)
    assert r.status_code == 202, r.text
    run_id = r.json()["run_id"]

    def ended():
        got = _get(service, f"/runs/{run_id}", headers=AUTH)
        return got.json() if got.json()["status"] in ("succeeded", "failed", "aborted") \
            else None

    run = wait_until(ended, timeout=400, poll=0.3, what=f"run {run_id} to end")
    assert run["status"] == "succeeded", run.get("reason")
    return run


READS = ("/runs", "/rig", "/procedures", "/calibrations/latest", "/calibrations/history",
         "/console/", "/console/runs", "/console/history", "/console/start")


def _run_reads(run_id: str) -> tuple[str, ...]:
    return (f"/runs/{run_id}", f"/runs/{run_id}/captures/0", f"/console/runs/{run_id}",
            f"/console/runs/{run_id}/captures/0/thumb.jpg")


@pytest.mark.timeout(900)
def test_reads_need_the_token_on_loopback(service, finished_run):
    run_id = finished_run["run_id"]
    for path in READS + _run_reads(run_id) + ("/events", "/"):
        r = _get(service, path, follow_redirects=False)
        assert r.status_code == 401, (path, r.status_code)
        if path.startswith("/console") or path == "/":
            assert "Token needed" in r.text and 'name="token"' in r.text, path
    for path in READS + _run_reads(run_id):
        assert _get(service, path, headers=AUTH).status_code == 200, path
    last = "y" if TOKEN.endswith("x") else "x"
    wrong = {"Authorization": "Bearer " + TOKEN[:-1] + last}
    assert _get(service, "/runs", headers=wrong).status_code == 401
    assert _get(service, "/health").status_code == 200  # liveness stays open
    # the console asks once: a wrong token is refused, the right one buys a cookie
    with httpx.Client(base_url=service.base, timeout=REQUEST_TIMEOUT_S) as browser:
        refused = browser.post("/console/login", data={"token": "nope", "next": "/console/"})
        assert refused.status_code == 401 and "wrong token" in refused.text
        signed = browser.post("/console/login", follow_redirects=False,
                              data={"token": TOKEN, "next": f"/console/runs/{run_id}"})
        assert signed.status_code == 303
        assert signed.headers["location"] == f"/console/runs/{run_id}"
        cookie = signed.headers["set-cookie"]
        assert TOKEN not in cookie and "httponly" in cookie.lower()
        assert "samesite=strict" in cookie.lower()
        for path in READS + _run_reads(run_id):
            assert browser.get(path).status_code == 200, path
        # an abort with the cookie alone is let through (404: nothing to abort)
        assert browser.post(f"/runs/{run_id}/abort", json={}).status_code == 404


@pytest.mark.timeout(900)
def test_the_token_is_nowhere_in_records_or_answers(service, finished_run, tmp_path):
    run_id = finished_run["run_id"]
    config = load_rig(service.rig)
    # the run through the real clients: four captures, the head where it was sent, the
    # board in both arm views (the ideal world's target, planned to be in view)
    result = finished_run["result"]
    assert (result["captures"], result["target_views"], result["board_detected"]) == (4, 2, 2)
    run = RunDirectory(finished_run["run_dir"])
    heads = [c.meta["head"]["pan"] for c in run.captures() if c.meta["extra"]["kind"] == "head"]
    assert [math.degrees(p) for p in heads] == pytest.approx([-5.0, 5.0], abs=0.1)
    versions = json.loads((run.path / "versions.json").read_text())
    assert set(versions["devices"]) == {"head", "camera", "arm"}
    software = versions["software"]
    assert software["rigctl_from"] == "git checkout" and len(software["rigctl_commit"]) == 40
    assert isinstance(software["rigctl_dirty"], bool)

    # the copy of the rig file: loads, same rig, token redacted, comment kept
    copy = recorded_config(run)
    assert copy.service.token == REDACTED and copy.name == config.name
    assert copy.devices == config.devices
    assert "# service token for this rig: " in (run.path / "rig.yaml").read_text()
    solve_recorded(run.path)  # a re-solve reads the redacted copy
    assert run.result()["board_detected"] == 2

    # every file the service and the runs wrote, the index included
    records = config.records_dir()
    files = [p for p in records.rglob("*") if p.is_file()]
    assert any(p.name == "index.sqlite" for p in files)
    assert len([p for p in files if p.parent.name == "captures"]) >= 8
    leaks = [str(p) for p in files if TOKEN.encode() in p.read_bytes()]
    assert not leaks, f"the token is written in {leaks}"

    # every answer of the API and the console, with the token
    paths = [*READS, *_run_reads(run_id), "/openapi.json", "/health",
             "/console/history/active-camera.png"]
    for path in paths:
        r = _get(service, path, headers=AUTH)
        assert r.status_code in (200, 404), (path, r.status_code)
        assert TOKEN.encode() not in r.content, f"{path} answers the token"
        assert TOKEN.encode() not in json.dumps(dict(r.headers)).encode(), path
    # and what the service printed
    assert TOKEN not in Path(service.stderr.name).read_text()
