"""The service's decisions and bookkeeping without hardware: drift comparison, automatic
and operator decisions (accept, reject, 404, 409), who aborted or asked for a run that
never started, schedule parsing."""

from __future__ import annotations

import math
import os
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient

from rigctl import drift
from rigctl.config import DriftThresholds, parse_duration, parse_rig
from rigctl.errors import ConfigError
from rigctl.locks import rig_lock
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory, utcnow
from rigctl.service import RigService, create_app
from tests.waiting import wait_until

CAMERA = {"fx": 900.0, "fy": 902.0, "cx": 640.0, "cy": 360.0}


def _T(mm=(0.0, 0.0, 0.0), deg_about_z=0.0):
    c, s = math.cos(math.radians(deg_about_z)), math.sin(math.radians(deg_about_z))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = np.array(mm) / 1000
    return T.tolist()


def test_drift_compare_measures_each_calibration_against_its_limits():
    limits = DriftThresholds(focal_pct=0.5, principal_point_px=3.0, hand_eye_mm=1.0,
                             hand_eye_deg=0.2, link_mm=0.5, link_deg=0.05)
    same = drift.compare("active-camera", CAMERA, CAMERA, limits)
    assert same == ([], {"focal_pct": 0.0, "principal_point_px": 0.0})
    moved = {**CAMERA, "fy": 902.0 * 1.004, "cy": 364.0}
    breaches, metrics = drift.compare("active-camera", moved, CAMERA, limits)
    assert metrics["focal_pct"] == pytest.approx(0.4) and metrics["principal_point_px"] == 4.0
    assert breaches == ["principal point moved 4.00 px (limit 3.0 px)"]
    breaches, metrics = drift.compare("hand-eye", {"T_flange_cam": _T((0.6, 0.8, 0), 0.3)},
                                      {"T_flange_cam": _T()}, limits)
    assert metrics["hand_eye_mm"] == pytest.approx(1.0) and metrics["hand_eye_deg"] == \
        pytest.approx(0.3)
    assert breaches == ["hand-eye turned 0.300 deg (limit 0.2 deg)"]  # 1.0 mm is at the limit
    link = {"d": 0.1, "a": -0.4, "theta_offset": 0.0, "alpha": 0.0, "beta": 0.0}
    old = {"T_flange_cam": _T(), "links": [link] * 6}
    new = {"T_flange_cam": _T(), "links": [link] * 5 + [{**link, "a": -0.4008,
                                                           "beta": math.radians(0.01)}]}
    breaches, metrics = drift.compare("robot-kinematics", new, old, limits)
    assert metrics["link_mm"] == pytest.approx(0.8) and metrics["link_deg"] == \
        pytest.approx(0.01)
    assert breaches == ["link 6 a changed 0.800 mm (limit 0.5 mm)"]


def test_durations_and_schedules_are_read_or_refused_at_load():
    assert [parse_duration(t) for t in ("45s", "30m", "1h", "2h30m", "1h5s")] == \
        [45, 1800, 3600, 9000, 3605]
    for bad in ("", "5", "1x", "m5", "0s", "1h-"):
        with pytest.raises(ValueError, match="cannot read duration"):
            parse_duration(bad)
    ok = "service: {schedules: [{procedure: head-sweep, cron: '0 3 * * 1-5', max_delay: 2h}]}\n"
    assert parse_rig(ok).service.schedules[0].cron == "0 3 * * 1-5"
    for text, where in (
            ("[{procedure: head-sweep, cron: '61 * * * *'}]", "service.schedules.0.cron"),
            ("[{procedure: head-sweep, interval_s: 60, max_delay: soon}]",
             "service.schedules.0.max_delay"),
            ("[{procedure: head-sweep, interval_s: 60, cron: '* * * * *'}]",
             "exactly one of cron or interval_s")):
        with pytest.raises(ConfigError, match=where.replace(".", r"\.")):
            parse_rig(f"service: {{schedules: {text}}}\n", name="rig.yaml")


def test_cron_days_are_read_as_cron_reads_them():
    """APScheduler's own crontab reader fires '0 3 * * 1' on Tuesdays (it counts days
    from Monday); the schedules fire on the days cron would."""
    import datetime as dt

    from rigctl.schedules import cron_trigger, cron_weekdays

    sunday = dt.datetime(2026, 11, 22, 12, 0, tzinfo=dt.UTC)

    def fire_days(text, count=7):
        trigger, when, days = cron_trigger(text), sunday, []
        for _ in range(count):
            when = trigger.get_next_fire_time(None, when + dt.timedelta(seconds=1))
            days.append(when.strftime("%a"))
        return days

    assert fire_days("0 3 * * 1", 2) == ["Mon", "Mon"]
    assert fire_days("0 3 * * 1-5", 5) == ["Mon", "Tue", "Wed", "Thu", "Fri"]
    assert fire_days("0 3 * * 0", 1) == fire_days("0 3 * * 7", 1) == ["Sun"]
    assert cron_weekdays("5-7") == "sun,fri,sat" and cron_weekdays("*/2") == "sun,tue,thu,sat"
    for bad in ("0 3 1 * 1", "0 3 * *", "0 3 * * 8", "0 3 * * 5-2"):
        with pytest.raises(ValueError):
            cron_trigger(bad)


def _service(tmp_path, auto_accept=False, name="units-rig"):
    tmp_path.mkdir(parents=True, exist_ok=True)
    rig = tmp_path / f"{name}.yaml"
    rig.write_text(f"name: {name}\nrecords: {{directory: records}}\n"
                   f"service: {{auto_accept: {str(auto_accept).lower()}}}\n")
    from rigctl.config import load_rig

    return RigService(load_rig(rig))


def _record(service, run_id, procedure, result, status="succeeded"):
    run = RunDirectory.create(service.config.records_dir(), run_id)
    run.write_result(result)
    service.index.insert({"run_id": run_id, "procedure": procedure, "status": status,
                          "reason": None, "started_at": utcnow(), "ended_at": utcnow(),
                          "operator": "test", "rig_name": service.config.name,
                          "config_hash": "0" * 16, "run_dir": str(run.path), "host": "test",
                          "pid": os.getpid()})


def test_decisions_pending_then_drift_and_automatic_accept(tmp_path):
    service = _service(tmp_path / "manual")
    _record(service, "r1-active-camera", "active-camera", CAMERA)
    assert service.decide("r1-active-camera", "active-camera", CAMERA) == "pending"
    service.index.update("r1-active-camera", decision="accepted")
    moved = {**CAMERA, "fx": 900.0 * 1.01}
    _record(service, "r2-active-camera", "active-camera", moved)
    assert service.decide("r2-active-camera", "active-camera", moved) == "drift"
    within = {**CAMERA, "cx": 641.0}
    _record(service, "r3-active-camera", "active-camera", within)
    assert service.decide("r3-active-camera", "active-camera", within) == "pending"
    auto = _service(tmp_path / "auto", auto_accept=True)
    _record(auto, "a1-active-camera", "active-camera", CAMERA)
    assert auto.decide("a1-active-camera", "active-camera", CAMERA) == "accepted"
    assert RecordIndex(auto.config.database_url()).get("a1")["decision"] == "accepted"


def test_accept_reject_and_their_404_and_409(tmp_path):
    service = _service(tmp_path)
    _record(service, "c1-active-camera", "active-camera", CAMERA)
    _record(service, "c2-active-camera", "active-camera", CAMERA, status="failed")
    _record(service, "h1-head-sweep", "head-sweep", {"poses": 1})
    with TestClient(create_app(service)) as api:
        assert api.post("/calibrations/c1-active-camera/reject").json() == {
            "run_id": "c1-active-camera", "decision": "rejected", "comment": ""}
        assert service.index.get("c1")["decision"] == "rejected"
        assert api.get("/calibrations/latest?procedure=active-camera").status_code == 404
        assert api.post("/calibrations/c1/accept").json()["decision"] == "accepted"
        assert api.get("/calibrations/latest").json()["active-camera"]["run_id"] == \
            "c1-active-camera"
        assert api.post("/calibrations/nope/accept").status_code == 404
        assert api.post("/calibrations/nope/reject").status_code == 404
        assert api.post("/calibrations/h1-head-sweep/accept").status_code == 409
        assert api.post("/calibrations/c2-active-camera/reject").status_code == 409
        assert api.post("/runs/nope/abort").status_code == 404
        assert api.get("/runs/nope").status_code == 404
        history = api.get("/calibrations/history?procedure=active-camera").json()
        assert [h["run_id"] for h in history] == ["c1-active-camera"]  # succeeded only


def test_decisions_keep_their_comments_and_the_console_shows_them(tmp_path):
    """Every decision (the service's drift check, the operator's accept or reject) goes to
    the run's decisions.jsonl with who and why; the index keeps the latest; the console's
    pages show them and refuse what they should."""
    service = _service(tmp_path)
    camera = {**CAMERA, "width": 1280, "height": 720}
    _record(service, "d1-active-camera", "active-camera", camera)
    _record(service, "d1-active-camera-2", "active-camera", {**camera, "fx": 909.0})
    with TestClient(create_app(service)) as api:
        assert service.decide("d1-active-camera", "active-camera", CAMERA) == "pending"
        r = api.post("/calibrations/d1-active-camera/accept",
                     json={"comment": "first one <b>bold</b>", "operator": "ada"})
        assert r.json()["decision"] == "accepted"  # the whole id, not a prefix: no 404
        assert service.decide("d1-active-camera-2", "active-camera",
                              {**CAMERA, "fx": 909.0}) == "drift"
        trail = RunDirectory(tmp_path / "records" / "d1-active-camera").decisions()
        assert [(d["decision"], d["by"], d["comment"]) for d in trail] == [
            ("pending", "service", ""), ("accepted", "ada", "first one <b>bold</b>")]
        drifted = RunDirectory(tmp_path / "records" / "d1-active-camera-2").decisions()
        assert drifted[-1]["decision"] == "drift" and "focal length changed 1.000 %" in \
            drifted[-1]["comment"] and drifted[-1]["compared_with"] == "d1-active-camera"
        run_page = api.get("/console/runs/d1-active-camera").text
        assert "first one &lt;b&gt;bold&lt;/b&gt;" in run_page  # escaped, not markup
        diff_page = api.get("/console/runs/d1-active-camera-2").text
        assert "focal length changed 1.000 %" in diff_page
        png = api.get("/console/runs/d1-active-camera-2/difference.png")
        assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
        history = api.get("/console/history?procedure=active-camera").text
        rows = {m[0]: m[1] for m in re.findall(
            r'href="/console/runs/([^"]+)">[^<]*</a></td><td>[^<]*</td>\s*<td><span '
            r'class="badge (\w+)"', history)}
        assert rows == {"d1-active-camera": "accepted", "d1-active-camera-2": "drift"}
        assert api.get("/console/history/active-camera.png").content[:4] == b"\x89PNG"
        runs = api.get("/console/runs?status=succeeded&procedure=active-camera").text
        assert runs.count('href="/console/runs/d1-active-camera') == 2
        assert api.get("/console/runs?status=bogus!").status_code == 422
        assert api.get("/console/runs/d1-active-camera/plots/..%2Frig.yaml").status_code \
            in (404, 422)
        assert api.get("/console/runs/nope").status_code == 404
        assert api.get("/console/history/head-sweep.png").status_code == 404
        assert api.get("/console/start?procedure=nope").status_code == 404
        assert api.post("/calibrations/d1-active-camera/accept",
                        json={"comment": "x" * 3000}).status_code == 422


def _head_service(tmp_path, token="units-token"):
    """A service on a rig with a head (never opened: the worker is not started unless a
    test starts it, and then the rig's lock is held)."""
    rig = tmp_path / "head-rig.yaml"
    rig.write_text("name: head-rig\nrecords: {directory: records}\n"
                   "devices:\n  head: {port: /dev/null/not-a-port}\n"
                   f"service: {{token: {token}}}\n")
    from rigctl.config import load_rig

    return RigService(load_rig(rig)), {"Authorization": f"Bearer {token}"}


SWEEP = {"procedure": "head-sweep", "params": {"pan_deg": [0], "tilt_deg": [0]}}


def test_a_run_aborted_in_the_queue_is_recorded_as_aborted_by_its_caller(tmp_path):
    """The operator who aborts a queued run through the API is its record's operator (as
    for accept and reject: the body's ``operator``, "operator" without one), not the
    scheduler."""
    service, auth = _head_service(tmp_path)
    with TestClient(create_app(service)) as api:
        ids = [api.post("/runs", json={**SWEEP, "operator": "bob"}, headers=auth).json()
               ["run_id"] for _ in range(3)]
        assert api.post(f"/runs/{ids[0]}/abort", json={"operator": "ada"}).status_code == 401
        r = api.post(f"/runs/{ids[0]}/abort", json={"operator": "ada"}, headers=auth)
        assert r.json() == {"run_id": ids[0], "status": "removed from the queue"}
        assert api.post(f"/runs/{ids[1]}/abort", headers=auth).status_code == 200
        assert api.post(f"/runs/{ids[2]}/abort", json={}, headers=auth).status_code == 200
        assert api.post(f"/runs/{ids[0]}/abort", headers=auth).status_code == 404  # gone
        rows = [api.get(f"/runs/{run_id}").json() for run_id in ids]
        assert [(r["status"], r["operator"]) for r in rows] == [
            ("aborted", "ada"), ("aborted", "operator"), ("aborted", "operator")]
        assert rows[0]["reason"] == "aborted via the API before it started"
        assert not service.queue
        assert api.post(f"/runs/{ids[0]}/abort", json={"operator": "x" * 101},
                        headers=auth).status_code == 422


def test_a_run_taken_off_the_queue_answers_starting_not_404(tmp_path, monkeypatch):
    """The worker saves the queue after taking a job off it, before the runner records the
    run: a client polling the id its 202 gave gets "starting" meanwhile, never a 404
    (seen as a failed suite run: the job was in neither the queue nor ``current``)."""
    import threading

    from rigctl import service as service_module

    service, auth = _head_service(tmp_path)
    lock = rig_lock(service.config)
    lock.acquire("held-by-test")
    saving, release = threading.Event(), threading.Event()
    real_save = service_module.save_queue

    def held_save(svc):
        if not svc.queue and not saving.is_set():  # the worker, the job just taken
            saving.set()
            release.wait(30)
        real_save(svc)

    monkeypatch.setattr(service_module, "save_queue", held_save)
    try:
        service.start()
        with TestClient(create_app(service)) as api:
            run_id = api.post("/runs", json=SWEEP, headers=auth).json()["run_id"]
            assert saving.wait(30), "the worker never took the job"
            r = api.get(f"/runs/{run_id}")
            listed = {row["run_id"]: row["status"] for row in api.get("/runs").json()}
            release.set()
            assert r.status_code == 200 and r.json()["status"] == "starting", r.text
            assert listed[run_id] == "starting"
            wait_until(lambda: api.get(f"/runs/{run_id}").json().get("status") == "failed",
                       what="the refused run's record")
    finally:
        release.set()
        service.stop()
        lock.release()


def test_a_queued_run_refused_when_it_starts_keeps_the_operator_who_asked(tmp_path):
    """A run the worker cannot start (the rig held elsewhere) is recorded as failed with
    the operator who queued it, not the scheduler's name."""
    service, auth = _head_service(tmp_path)
    lock = rig_lock(service.config)
    lock.acquire("held-by-test")
    try:
        service.start()
        with TestClient(create_app(service)) as api:
            run_id = api.post("/runs", json={**SWEEP, "operator": "bob"},
                              headers=auth).json()["run_id"]
            # "starting" while the worker holds the job before it is recorded
            row = wait_until(lambda: (r := api.get(f"/runs/{run_id}").json()).get("status")
                             not in ("queued", "starting", "running") and r,
                             what="the refused run")
    finally:
        service.stop()
        lock.release()
    assert row["status"] == "failed" and "busy, held by run held-by-test" in row["reason"]
    assert row["operator"] == "bob"
