"""The service's automatic decision on a calibration and an operator's accept or reject
made while the run is ending: the operator's lands between the run's record (succeeded)
and the service's drift check, deterministically (hooks, no sleeps), in process with the
worker thread, a stand-in runner and the FastAPI TestClient."""

from __future__ import annotations

import os
import threading

import pytest
from fastapi.testclient import TestClient

from rigctl.config import load_rig
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory, utcnow
from rigctl.runner import RunOutcome
from rigctl.service import Job, RigService, create_app
from tests.waiting import wait_until

CAMERA = {"fx": 900.0, "fy": 902.0, "cx": 640.0, "cy": 360.0}
EVENT_WAIT_S = 60  # a bound on waits for the other thread, never a measured time


def _service(tmp_path, auto_accept=False) -> RigService:
    rig = tmp_path / "rig.yaml"
    rig.write_text("name: decisions-rig\nrecords: {directory: records}\n"
                   f"service: {{auto_accept: {str(auto_accept).lower()}}}\n")
    return RigService(load_rig(rig))


def _record(service, run_id, result, decision=None):
    """A succeeded active-camera run, as the runner leaves it."""
    run = RunDirectory.create(service.config.records_dir(), run_id)
    run.write_result(result)
    service.index.insert({"run_id": run_id, "procedure": "active-camera",
                          "status": "succeeded", "reason": None, "started_at": utcnow(),
                          "ended_at": utcnow(), "operator": "test", "decision": decision,
                          "rig_name": service.config.name, "config_hash": "0" * 16,
                          "run_dir": str(run.path), "host": "test", "pid": os.getpid()})
    return run


def _stand_in_runner(service, result):
    class Runner:
        """Records the run as succeeded and returns, as the real one does at its end."""

        def __init__(self, config, **_kw):
            pass

        def abort(self, reason):
            pass

        def run(self, name, params, run_id):
            run = _record(service, run_id, result)
            return RunOutcome(run_id, "succeeded", None, str(run.path), result)

    return Runner


def _operator_between_end_and_decision(service, api, monkeypatch, action, body):
    """Hook the worker's call of ``decide`` (the run is recorded as succeeded by then):
    the operator's request is sent from another thread, and the service's decision goes
    on only once that request has been answered (code without ordering) or is waiting for
    the service's decision (code with it). Returns the operator's response."""
    landed, answer = threading.Event(), {}
    decide = service.decide
    wait = getattr(service, "_await_automatic_decision", None)

    def waiting(run_id, timeout):
        landed.set()  # the operator's request now waits for the service's decision
        return wait(run_id, timeout)

    def operator(run_id):
        try:
            answer["response"] = api.post(f"/calibrations/{run_id}/{action}", json=body)
        finally:
            landed.set()

    def hooked(run_id, procedure, result):
        thread = threading.Thread(target=operator, args=(run_id,))
        thread.start()
        answer["thread"] = thread  # started: the test may join it now
        assert landed.wait(EVENT_WAIT_S), "the operator's request never arrived"
        return decide(run_id, procedure, result)

    monkeypatch.setattr(service, "decide", hooked)
    monkeypatch.setattr(service, "_await_automatic_decision", waiting, raising=False)
    run_id = "20260101T000000-active-camera-race00"
    with service.cond:
        service.queue.append(Job(run_id, "active-camera", {}, operator="ada"))
        service.cond.notify_all()
    wait_until(lambda: "thread" in answer, timeout=EVENT_WAIT_S, what="the run's end")
    answer["thread"].join(EVENT_WAIT_S)
    assert not answer["thread"].is_alive()
    wait_until(lambda: service.current is None and not service.queue, timeout=EVENT_WAIT_S,
               what="the worker to finish the run")
    return run_id, answer["response"]


@pytest.mark.parametrize("action, decision", [("accept", "accepted"), ("reject", "rejected")])
def test_an_operator_decision_at_the_end_of_a_run_is_not_overwritten(
        tmp_path, monkeypatch, action, decision):
    service = _service(tmp_path)
    monkeypatch.setattr("rigctl.service.Runner", _stand_in_runner(service, CAMERA))
    service.start()
    try:
        with TestClient(create_app(service)) as api:
            run_id, response = _operator_between_end_and_decision(
                service, api, monkeypatch, action, {"comment": "looks right", "operator": "ada"})
            assert response.status_code == 200
            assert api.get(f"/runs/{run_id}").json()["decision"] == decision  # not pending
            assert response.json() == {"run_id": run_id, "decision": decision,
                                       "comment": "looks right", "supersedes": "pending"}
    finally:
        service.stop()
    assert RecordIndex(service.config.database_url()).get(run_id)["decision"] == decision
    trail = RunDirectory(tmp_path / "records" / run_id).decisions()
    assert [(d["decision"], d["by"], d.get("supersedes")) for d in trail] == [
        ("pending", "service", None), (decision, "ada", "pending")]


def test_an_operator_accept_supersedes_a_drift_verdict_and_says_so(tmp_path, monkeypatch):
    """Drift found by the service at the end of the run, the operator accepting at the same
    moment: the drift is recorded first, the accept after it, naming what it replaced."""
    service = _service(tmp_path)
    old = _record(service, "20250101T000000-active-camera-old000", CAMERA, "accepted")
    assert old.result() == CAMERA
    moved = {**CAMERA, "fx": 909.0}
    monkeypatch.setattr("rigctl.service.Runner", _stand_in_runner(service, moved))
    service.start()
    try:
        with TestClient(create_app(service)) as api:
            run_id, response = _operator_between_end_and_decision(
                service, api, monkeypatch, "accept", None)
    finally:
        service.stop()
    assert service.index.get(run_id)["decision"] == "accepted"
    assert response.json()["supersedes"] == "drift"
    trail = RunDirectory(tmp_path / "records" / run_id).decisions()
    assert [(d["decision"], d["by"]) for d in trail] == [("drift", "service"),
                                                         ("accepted", "operator")]
    assert "focal length changed 1.000 %" in trail[0]["comment"]


def test_the_automatic_decision_never_overwrites_one_already_made(tmp_path):
    """A decision already in the index (made elsewhere first) stays; the service's is not
    applied and not added to the trail, and decide says which decision is in force."""
    service = _service(tmp_path, auto_accept=True)
    run = _record(service, "20260101T000000-active-camera-made00", CAMERA, "rejected")
    assert service.decide(run.run_id, "active-camera", CAMERA) == "rejected"
    assert service.index.get(run.run_id)["decision"] == "rejected"
    assert run.decisions() == []


def test_an_operator_decision_the_service_keeps_waiting_is_refused_with_409(
        tmp_path, monkeypatch):
    """If the service's drift check on a finished run is still not recorded when the wait
    ends, the operator's accept is refused (409, try again), never recorded before it."""
    service = _service(tmp_path)
    run = _record(service, "20260101T000000-active-camera-slow00", CAMERA)
    service._deciding.add(run.run_id)  # as the worker does before the run
    monkeypatch.setattr("rigctl.service.DECISION_WAIT_S", 0)
    with TestClient(create_app(service)) as api:
        refused = api.post(f"/calibrations/{run.run_id}/accept")
        assert refused.status_code == 409 and "drift check" in refused.json()["detail"]
        assert service.index.get(run.run_id)["decision"] is None and run.decisions() == []
        assert service.decide(run.run_id, "active-camera", CAMERA) == "pending"
        assert api.post(f"/calibrations/{run.run_id}/accept").json()["supersedes"] == \
            "pending"
