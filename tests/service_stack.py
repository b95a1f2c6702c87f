"""The simulated rig with `rigctl serve` on it, for the tests of the service and of its
console: started on loopback, stopped by PID, also when starting fails half-way."""

from __future__ import annotations

import http.server
import json
import subprocess
import sys
import threading
import time

import httpx
import yaml

from rigctl.demo import QUICK_CAMERA
from rigctl.loopback import free_port
from rigctl.simrig import SimulatedRig
from tests.mockproc import ROOT
from tests.waiting import wait_until

TOKEN = "s3cret"
# The service's and the console's active-camera runs: pan and tilt 5 deg, then `rigctl demo
# --quick`'s plan (17 captures instead of the default 33). These tests check the service
# and its pages; the default plan's accuracy is tests/test_e2e_default_world.py's.
CAMERA_PARAMS = {"pan_deg": 5, "tilt_deg": 5, **QUICK_CAMERA}
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class Webhook:
    def __init__(self) -> None:
        self.received: list[dict] = []
        owner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                owner.received.append(json.loads(body))
                self.send_response(204)
                self.end_headers()

        self.server = http.server.HTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def start_sim(tmp, world, host=None, camera_port=0):
    """`sim up` on a fresh loopback address; a restart passes the old host and camera port
    so that the service's rig file still points at the stand-ins."""
    return SimulatedRig(world, records=tmp / "records", host=host, camera_port=camera_port,
                        workdir=tmp / "simwork", rig_out=tmp / "sim-rig.yaml",
                        log=tmp / "sim-up.log")


HELD_MOVE_TIMEOUT_S = 120.0


class Stack:
    """The simulated rig and `rigctl serve` on it; whatever was started is stopped by PID,
    also when the constructor fails half-way."""

    def __init__(self, tmp, schedules=()):
        self.tmp, self.sim, self.server = tmp, None, None
        self.crashes: list[str] = []  # simulated rigs that ended on their own
        self.hook = Webhook()
        try:
            self._start(tmp, list(schedules))
        except BaseException:
            self.stop()
            raise

    def _start(self, tmp, schedules):
        self.sim = start_sim(tmp, "ideal")
        rig = yaml.safe_load((tmp / "sim-rig.yaml").read_text())
        # a move the bus stand-in holds (a test's latched ``freeze``) waits for the test's
        # thaw or abort, however slow the host: at the default 15 s the held move of
        # test_abort_mid_run_and_cli_sees_the_rig_busy timed out (the run failed, not
        # aborted) while a CLI call started beside it, with two cores kept busy
        rig["devices"]["head"]["move_timeout_s"] = HELD_MOVE_TIMEOUT_S
        port = free_port()
        rig["service"] = {"bind": "127.0.0.1", "port": port, "token": TOKEN,
                          "webhook": self.hook.url, "auto_accept": False,
                          "schedules": schedules,
                          "drift": {"focal_pct": 0.5, "principal_point_px": 3.0}}
        self.rig_name = rig["name"]
        self.rig = tmp / "service-rig.yaml"
        self.rig.write_text(yaml.safe_dump(rig))
        self.server = subprocess.Popen([sys.executable, "-m", "rigctl.cli", "serve", "--rig",
                                        str(self.rig)], cwd=ROOT, stdout=subprocess.DEVNULL,
                                       stderr=subprocess.PIPE, text=True)
        self.base = f"http://127.0.0.1:{port}"

        def healthy():
            if self.server.poll() is not None:
                raise RuntimeError(f"service exited: {self.server.stderr.read()[-2000:]}")
            try:
                return get(self.base + "/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(healthy, timeout=90, what="the service to answer /health")

    def restart_sim(self, world):
        """The same devices (loopback host, camera port) on another world."""
        ready = self.sim.ready
        self._stop_sim()
        self.sim = start_sim(self.tmp, world, host=ready["host"],
                             camera_port=ready["camera"]["port"])

    def stop(self):
        if self.server is not None and self.server.poll() is None:
            self.server.terminate()
            try:
                self.server.wait(20)
            except subprocess.TimeoutExpired:
                self.server.kill()
                self.server.wait(5)
        self._stop_sim()
        self.hook.close()

    def assert_no_crash(self):
        """After ``stop``: no simulated rig of this stack ended on its own."""
        assert not self.crashes, "\n".join(self.crashes)

    def _stop_sim(self):
        if self.sim is not None:
            self.sim.stop(timeout=20)
            if self.sim.crash:
                self.crashes.append(self.sim.crash)
            self.sim = None


# One HTTP client per test process. httpx.get() and httpx.post() build a client, and
# with it an SSL context that loads the CA bundle, on every call: polling runs and
# /health spent 4 % of the suite's CPU there (py-spy over a whole suite run). No
# keep-alive: every request opens its own connection, as those calls did.
HTTP = httpx.Client(limits=httpx.Limits(max_keepalive_connections=0))

# A generous bound on every request: on a busy host the service can take seconds to
# answer (e.g. drawing /plots/history.png); the tests wait on conditions, not on speed.
REQUEST_TIMEOUT_S = 60


def get(url, **kwargs):
    return HTTP.get(url, timeout=kwargs.pop("timeout", REQUEST_TIMEOUT_S), **kwargs)


def post(stack, path, body=None, auth=True):
    return HTTP.post(stack.base + path, json=body, headers=AUTH if auth else {},
                     timeout=REQUEST_TIMEOUT_S)


def wait_for(stack, run_id, statuses=("succeeded", "failed", "aborted"), timeout=120):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        r = get(f"{stack.base}/runs/{run_id}")
        if r.status_code == 200 and r.json()["status"] in statuses:
            return r.json()
        time.sleep(0.3)
    raise AssertionError(f"run {run_id} did not reach {statuses}")


# The holder takes the lock as soon as the rig is free: a run already on it (a schedule
# that fired first, on a busy machine: load check, 1 run in 3) is waited for, as long as
# the rig stays busy, within this ceiling
HOLDER_WAIT_S = 120


class LockHolder:
    """Another process holding the rig's lock (as a CLI run on the rig would) until
    ``release``; stopped by PID, also from ``with``. It takes the lock once the rig is
    free (``HOLDER_WAIT_S``)."""

    def __init__(self, lock_dir, rig_name: str, run_id: str = "run-held") -> None:
        code = ("import sys, time; from pathlib import Path; from rigctl.locks import RigLock;"
                "from rigctl.errors import BusyError;"
                f"lock = RigLock(Path({str(lock_dir)!r}), {rig_name!r});"
                f"deadline = time.monotonic() + {HOLDER_WAIT_S};"
                "\nwhile True:"
                f"\n    try: lock.acquire({run_id!r}); break"
                "\n    except BusyError:"
                "\n        if time.monotonic() > deadline: raise"
                "\n        time.sleep(0.05)"
                "\nprint('held', flush=True); time.sleep(600)")
        self.proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT,
                                     stdout=subprocess.PIPE, text=True)
        try:
            assert self.proc.stdout.readline().strip() == "held", "the lock holder failed"
        except BaseException:
            self.release()
            raise

    def release(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
        self.proc.stdout.close()

    def __enter__(self) -> LockHolder:
        return self

    def __exit__(self, *exc) -> None:
        self.release()
