"""A run between the queue and the records: the worker has taken the job, the runner has
not recorded it yet (it checks the rig and opens the run directory first). The id the API
returned for it must answer "starting", never 404. Deterministic: the stand-in runner
holds the run at that point until the test has asked."""

from __future__ import annotations

import threading

from fastapi.testclient import TestClient

from rigctl.config import load_rig
from rigctl.runner import RunOutcome
from rigctl.service import Job, RigService, create_app
from tests.waiting import wait_until

EVENT_WAIT_S = 60  # a bound on waits for the worker thread, never a measured time


def test_a_run_taken_off_the_queue_but_not_yet_recorded_answers_starting(tmp_path,
                                                                        monkeypatch):
    rig = tmp_path / "rig.yaml"
    rig.write_text("name: starting-rig\nrecords: {directory: records}\n")
    service = RigService(load_rig(rig))
    entered, release = threading.Event(), threading.Event()

    class HeldRunner:
        """Stops where the real runner has not written the run's record yet."""

        def __init__(self, config, **_kw):
            pass

        def abort(self, reason):
            release.set()

        def run(self, name, params, run_id):
            entered.set()
            assert release.wait(EVENT_WAIT_S), "the test never released the run"
            return RunOutcome(run_id, "aborted", "test over", None, None)

    monkeypatch.setattr("rigctl.service.Runner", HeldRunner)
    service.start()
    try:
        with TestClient(create_app(service)) as api:
            run_id = "20260101T000000-head-sweep-start0"
            with service.cond:  # as ``submit`` queues it, after its plan check
                service.queue.append(Job(run_id, "head-sweep", {}, operator="ada"))
                service.cond.notify_all()
            assert entered.wait(EVENT_WAIT_S), "the worker never started the run"
            got = api.get(f"/runs/{run_id}")
            assert got.status_code == 200, got.text
            assert got.json()["status"] == "starting"
            assert got.json()["procedure"] == "head-sweep"
            listed = {r["run_id"]: r["status"] for r in api.get("/runs").json()}
            assert listed.get(run_id) == "starting"
            assert api.get("/runs/20260101T000000-head-sweep-nosuch").status_code == 404
            page = api.get(f"/console/runs/{run_id}")  # the console says the same
            assert page.status_code == 200
            assert 'id="run-status">starting<' in page.text
            release.set()
            wait_until(lambda: service.current is None, timeout=EVENT_WAIT_S,
                       what="the worker to finish the run")
    finally:
        release.set()
        service.stop()
