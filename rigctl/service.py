"""``rigctl serve``: HTTP API, a FIFO run queue with the rig's one lock, scheduled
recalibration, drift checks and the operator console (FastAPI + uvicorn + APScheduler;
the console's pages are in ``rigctl.console``).

Runs execute in one worker thread through the same ``Runner`` as the CLI, under the same
per-rig ``flock``: a CLI run while the service holds the rig fails with "busy, held by
run X", and the other way round. Mutating endpoints need the bearer token when one is
set (rig file ``service.token`` or ``RIGCTL_TOKEN``); binding anything but loopback
requires one. Reads (runs, captures, the devices' configuration, the console, the event
stream) need it too unless ``service.public_read`` (default: on a loopback bind only);
the console asks for it once and keeps a session cookie (``Access``). The token is
compared in constant time and never written or answered. No endpoint runs code or reads
a path it was given: captures are addressed by run id and index.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import hashlib
import hmac
import json
import logging
import threading
import urllib.request
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field

from rigctl import __version__, drift, procedures, teach
from rigctl.config import RigConfig, is_loopback, parse_duration
from rigctl.console.pages import (
    LoginRequiredError,
    console_routes,
    console_templates,
    login_routes,
    mount_static,
)
from rigctl.errors import BusyError, ConfigError, RigError, SafetyError
from rigctl.locks import rig_lock
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory, new_run_id, run_row, to_jsonable, utcnow
from rigctl.resume import close_dangling, read_segments
from rigctl.runner import Runner, prepare_run, refuse_violations, solve_recorded
from rigctl.service_resume import report_lost_queue, resume_run, save_queue

log = logging.getLogger("rigctl.service")
DECISION_WAIT_S = 30.0  # how long an operator's decision waits for the service's drift check
SESSION_COOKIE = "rigctl_session"
UNAUTHORIZED = "missing or wrong bearer token"


def service_token(config: RigConfig) -> str | None:
    """The bearer token in force: ``service.token``, else ``RIGCTL_TOKEN``."""
    return config.service.bearer_token()


def check_bind(config: RigConfig, host: str) -> None:
    """Refuse a non-loopback bind without a token, and reads that need a token when
    there is none."""
    if not is_loopback(host) and not service_token(config):
        raise ConfigError(f"service.bind {host}: binding beyond loopback requires a bearer "
                          "token (service.token in the rig file, or RIGCTL_TOKEN)")
    if not config.service.reads_public(host) and not service_token(config):
        raise ConfigError("service.public_read: false needs a bearer token (service.token "
                          "in the rig file, or RIGCTL_TOKEN): without one nothing could read")


class Access:
    """Who may do what: the bearer token (``Authorization: Bearer ...``) or the console's
    session cookie, compared in constant time. The cookie holds a keyed hash of the
    token, never the token itself."""

    def __init__(self, token: str | None, public_read: bool) -> None:
        self.token = token
        self.public_read = public_read or not token
        self.session = (hmac.new(token.encode(), b"rigctl console session",
                                 hashlib.sha256).hexdigest() if token else "")

    def token_matches(self, given: str | None) -> bool:
        """Whether ``given`` is the token (constant time)."""
        return bool(self.token) and given is not None and \
            hmac.compare_digest(given.encode(), self.token.encode())

    def allows(self, request: Request, credentials: HTTPAuthorizationCredentials | None
               ) -> bool:
        """Whether the request carries the token or the console's session cookie (always,
        when no token is set)."""
        if not self.token:
            return True
        if credentials is not None and self.token_matches(credentials.credentials):
            return True
        cookie = request.cookies.get(SESSION_COOKIE)
        return cookie is not None and hmac.compare_digest(cookie.encode(),
                                                          self.session.encode())


class EventBus:
    """Fan-out of runner events (from the worker thread) to SSE subscribers (asyncio)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscribers: list[tuple[asyncio.AbstractEventLoop, asyncio.Queue]] = []
        self.recent: deque[dict] = deque(maxlen=200)
        self._seq = 0

    def publish(self, event: dict) -> None:
        with self._lock:
            self._seq += 1
            event = {"seq": self._seq, "time": utcnow().isoformat(), **event}
            self.recent.append(event)
            subscribers = list(self._subscribers)
        for loop, queue in subscribers:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(queue.put_nowait, event)

    def subscribe(self) -> asyncio.Queue:
        queue: asyncio.Queue = asyncio.Queue()
        with self._lock:
            self._subscribers.append((asyncio.get_running_loop(), queue))
        return queue

    def unsubscribe(self, queue: asyncio.Queue) -> None:
        with self._lock:
            self._subscribers = [(lp, q) for lp, q in self._subscribers if q is not queue]


@dataclass
class Job:
    run_id: str
    procedure: str
    params: dict[str, Any]
    source: str = "api"
    operator: str = "service"
    progress: dict[str, Any] = field(default_factory=dict)
    resume: bool = False  # resume the recorded run ``run_id`` (POST /runs/{id}/resume)


class RigService:
    """The queue, the worker, the scheduler and the drift decisions of one rig."""

    def __init__(self, config: RigConfig, factories: dict | None = None) -> None:
        self.config = config
        self.factories = factories
        self.index = RecordIndex(config.database_url())
        self.events = EventBus()
        self.queue: deque[Job] = deque()
        self.cond = threading.Condition()
        self.current: Job | None = None
        self.runner: Runner | None = None
        self.stopping = False
        # decisions on calibrations, in order: the service's automatic one (drift check)
        # first, then the operators'; runs whose automatic decision is still to come
        self.decisions = threading.Condition()
        self._deciding: set[str] = set()
        self.worker = threading.Thread(target=self._work, daemon=True, name="rig-worker")
        self.lost_queue: list[dict] = []  # queued when a previous service died (start())
        self.scheduler = None

    # -- queue ---------------------------------------------------------------------

    def submit(self, procedure: str, params: dict[str, Any], source: str = "api",
               operator: str = "service") -> Job:
        """Validate, plan and limit-check a run, then queue it; the run id is assigned now.
        Raises ``ConfigError`` (procedure, parameters) or ``SafetyError`` (soft limits) with
        the CLI's exit-2 text, before anything is queued or recorded."""
        _, _, plan = prepare_run(self.config, procedure, params)
        refuse_violations(plan)
        job = Job(new_run_id(procedure), procedure, params, source, operator)
        with self.cond:
            self.queue.append(job)
            save_queue(self)
            self.cond.notify_all()
        self.events.publish({"type": "queued", "run_id": job.run_id, "procedure": procedure,
                             "source": source})
        return job

    def enqueue_resume(self, row: dict, operator: str) -> Job:
        """Queue the resume of the recorded run of ``row`` (checked resumable)."""
        job = Job(row["run_id"], row["procedure"], {}, "api", operator, resume=True)
        with self.cond:
            self.queue.append(job)
            save_queue(self)
            self.cond.notify_all()
        self.events.publish({"type": "queued", "run_id": job.run_id,
                             "procedure": job.procedure, "source": "resume"})
        return job

    def busy_reason(self) -> str | None:
        """Why a scheduled run cannot start now (None if the rig is free)."""
        with self.cond:
            if self.current is not None:
                return f"rig busy: run {self.current.run_id} is running"
            if self.queue:
                return f"rig busy: {len(self.queue)} run(s) queued"
        lock = rig_lock(self.config)
        try:
            lock.acquire("probe")
        except BusyError as exc:
            return str(exc)
        lock.release()
        return None

    def record_without_run(self, procedure: str, status: str, reason: str,
                           params: dict | None = None, run_id: str | None = None,
                           operator: str = "scheduler") -> str:
        """Index a run that never started (refused, skipped, aborted in the queue); a
        queued job keeps the id the API returned for it. ``operator``: who ended it (the
        scheduler, the operator who aborted it) or who asked for it (a refused run)."""
        run_id = run_id or new_run_id(procedure)
        self.index.insert(run_row(self.config, run_id, procedure, status, operator,
                                  reason=reason, ended_at=utcnow(),
                                  result_summary={"params": params or {}}))
        self.events.publish({"type": "finished", "run_id": run_id, "status": status,
                             "reason": reason})
        return run_id

    def abort(self, run_id: str, operator: str = "operator") -> str:
        """Abort the current run (its record keeps the operator who started it), or take
        a queued one off the queue and record it as aborted, with ``operator`` as its
        operator."""
        with self.cond:
            if self.current is not None and self.current.run_id == run_id:
                self.runner.abort("aborted via the API")
                return "aborting"
            for job in list(self.queue):
                if job.run_id == run_id:
                    self.queue.remove(job)
                    save_queue(self)
                    if job.resume:  # its record stays as it was
                        return "removed from the queue"
                    self.record_without_run(job.procedure, "aborted",
                                            "aborted via the API before it started",
                                            job.params, job.run_id, operator)
                    return "removed from the queue"
        raise HTTPException(404, f"run {run_id} is neither running nor queued")

    def _work(self) -> None:
        while True:
            with self.cond:
                while not self.queue and not self.stopping:
                    self.cond.wait(0.5)
                if self.stopping:
                    return
                # the job is the current one before it leaves the queue: the API, which
                # reads both without the lock, finds its id in one or the other, never
                # in neither (a 404 right after the 202 that gave the id)
                job = self.current = self.queue[0]
                self.queue.popleft()
                save_queue(self)
                self.runner = Runner(self.config, factories=self.factories,
                                     show_progress=False, operator=job.operator,
                                     on_event=lambda e, j=job: self._on_event(j, e))
            if job.procedure in drift.CALIBRATIONS:
                with self.decisions:  # before the run can be recorded as succeeded
                    self._deciding.add(job.run_id)
            try:
                if job.resume:
                    outcome = self.runner.resume(job.run_id)
                    if outcome is None:
                        continue
                else:
                    outcome = self.runner.run(job.procedure, job.params, run_id=job.run_id)
                if outcome.status == "succeeded" and job.procedure in drift.CALIBRATIONS:
                    self.decide(job.run_id, job.procedure, outcome.result)
            except RigError as exc:  # refused before anything moved (busy, limits, params)
                if job.resume:  # the run's record stays as it was
                    log.error("resume of run %s refused: %s", job.run_id, exc)
                    self.events.publish({"type": "resume_refused", "run_id": job.run_id,
                                         "reason": f"{type(exc).__name__}: {exc}"})
                    continue
                status = "skipped" if job.source == "schedule" else "failed"
                self.record_without_run(job.procedure, status, f"{type(exc).__name__}: {exc}",
                                        job.params, job.run_id, job.operator)
            except Exception:
                log.exception("worker: run %s crashed", job.run_id)
            finally:
                self._decided(job.run_id)
                with self.cond:
                    self.current = None
                    self.runner = None

    def _on_event(self, job: Job, event: dict) -> None:
        if event.get("type") == "step":
            job.progress = {"index": event.get("index"), "total": event.get("total"),
                            "step": event.get("step")}
        self.events.publish(event)

    # -- drift ---------------------------------------------------------------------

    def decide(self, run_id: str, procedure: str, result: dict[str, Any]) -> str:
        """Compare with the last accepted calibration; mark drift, accept or leave pending.
        Applied only if the run has no decision yet: an operator's is never overwritten
        (the operators' wait for this one, ``decide_as_operator``). Returns the decision
        in force."""
        previous = self._last_accepted(procedure, exclude=run_id)
        breaches, metrics = [], {}
        if previous is not None:
            old = RunDirectory(previous["run_dir"]).result()
            breaches, metrics = drift.compare(procedure, result, old, self.config.service.drift)
        if breaches:
            decision = "drift"
            self._webhook({"rig": self.config.name, "run_id": run_id, "procedure": procedure,
                           "drift": breaches, "metrics": metrics,
                           "compared_with": previous["run_id"]})
        elif self.config.service.auto_accept:
            decision = "accepted"
        else:
            decision = "pending"
        with self.decisions:
            try:
                row = self.index.get(run_id)
                if row["decision"] is not None:
                    log.warning("run %s: already %s; the service's %s is not applied",
                                run_id, row["decision"], decision)
                    return row["decision"]
                self.set_decision(row, decision, "service", "; ".join(breaches),
                                  drift=breaches, metrics=metrics,
                                  compared_with=previous["run_id"] if previous else None)
            finally:
                self._decided(run_id)
        return decision

    def _decided(self, run_id: str) -> None:
        """The service will make no automatic decision on ``run_id`` (made, or the run
        ended without one): the operators' decisions waiting for it go ahead."""
        with self.decisions:
            self._deciding.discard(run_id)
            self.decisions.notify_all()

    def _await_automatic_decision(self, run_id: str, timeout: float) -> bool:
        """Wait (holding ``self.decisions``) until the service has made its automatic
        decision on ``run_id``, if one is still to come; False on timeout."""
        return self.decisions.wait_for(lambda: run_id not in self._deciding, timeout)

    def decide_as_operator(self, row: dict, decision: str, by: str, comment: str = "",
                           timeout: float | None = None) -> dict[str, Any]:
        """An operator's accept or reject, recorded after the service's own decision on a
        just finished run (waiting for it), and superseding it: the trail in
        ``decisions.jsonl`` keeps both, in order, and this one names the decision it
        replaced (``supersedes``). 409 if the service's decision is still not made."""
        run_id = row["run_id"]
        with self.decisions:
            if not self._await_automatic_decision(
                    run_id, DECISION_WAIT_S if timeout is None else timeout):
                raise HTTPException(409, f"run {run_id}: the service's drift check is still "
                                         "being recorded; try again")
            previous = self.index.get(run_id)["decision"]
            extra = {"supersedes": previous} if previous else {}
            self.set_decision(row, decision, by, comment, **extra)
        return {"run_id": run_id, "decision": decision, "comment": comment, **extra}

    def status(self) -> dict[str, Any]:
        """The rig without moving anything: its devices from the rig file, the lock
        holder, the last recorded readings (the newest capture's sidecar)."""
        config = self.config
        lock = rig_lock(config)
        last = {}
        for row in self.runs(20):
            sidecars = sorted(Path(row["run_dir"], "captures").glob("[0-9][0-9][0-9].json")) \
                if row["run_dir"] else []
            if sidecars:  # the newest only: pages ask for this often
                with contextlib.suppress(OSError, json.JSONDecodeError):
                    meta = json.loads(sidecars[-1].read_text())
                    last = {"run_id": row["run_id"], "head": meta.get("head"),
                            "arm": meta.get("arm"), "time": meta.get("time")}
                break
        devices = {k: (getattr(config.devices, k).model_dump() if getattr(config.devices, k)
                       else None) for k in ("head", "arm", "camera")}
        return {"rig": config.name, "busy": self.busy_reason(), "lock": lock.holder(),
                "devices": devices, "last_readings": last,
                "lost_queue": self.lost_queue}

    def set_decision(self, row: dict, decision: str, by: str, comment: str = "",
                     **extra: Any) -> None:
        """Record a decision on a finished calibration: the index's ``decision``, and
        the whole trail (who, when, why) in the run's ``decisions.jsonl``."""
        self.index.update(row["run_id"], decision=decision)
        if row.get("run_dir") and Path(row["run_dir"]).is_dir():
            RunDirectory(row["run_dir"]).append_decision(decision, by, comment, **extra)
        self.events.publish({"type": "decision", "run_id": row["run_id"],
                             "decision": decision, "by": by, **extra})

    def runs(self, limit: int, procedure: str | None = None) -> list[dict]:
        """This rig's runs, newest first (an index may be shared by several rigs)."""
        return self.index.list(limit, procedure, rig_name=self.config.name)

    def _last_accepted(self, procedure: str, exclude: str | None = None) -> dict | None:
        rows = [r for r in self.runs(500, procedure)
                if r["decision"] == "accepted" and r["run_id"] != exclude]
        return rows[0] if rows else None

    def _webhook(self, payload: dict) -> None:
        url = self.config.service.webhook
        if not url:
            return
        request = urllib.request.Request(url, data=json.dumps(payload).encode(),
                                         headers={"Content-Type": "application/json"})
        try:
            urllib.request.urlopen(request, timeout=3).close()
        except OSError as exc:
            log.warning("drift webhook %s failed: %s", url, exc)

    # -- scheduler -----------------------------------------------------------------

    def start(self) -> None:
        self.lost_queue = report_lost_queue(self)
        self.worker.start()
        if self.config.service.schedules:
            from apscheduler.schedulers.background import BackgroundScheduler
            from apscheduler.triggers.interval import IntervalTrigger

            from rigctl.schedules import cron_trigger

            self.scheduler = BackgroundScheduler(timezone="UTC")
            for k, sched in enumerate(self.config.service.schedules):
                trigger = (cron_trigger(sched.cron) if sched.cron
                           else IntervalTrigger(seconds=sched.interval_s))
                self.scheduler.add_job(self._scheduled, trigger, args=[sched], id=f"s{k}",
                                       misfire_grace_time=parse_duration(sched.max_delay),
                                       coalesce=True, max_instances=1)
            self.scheduler.start()

    def _scheduled(self, sched) -> None:
        reason = self.busy_reason()
        if reason is not None:
            self.record_without_run(sched.procedure, "skipped", reason, sched.params)
            return
        try:
            self.submit(sched.procedure, sched.params, source="schedule", operator="scheduler")
        except RigError as exc:
            self.record_without_run(sched.procedure, "skipped", str(exc), sched.params)

    def stop(self) -> None:
        if self.scheduler is not None:
            self.scheduler.shutdown(wait=False)
        with self.cond:
            self.stopping = True
            if self.runner is not None:
                self.runner.abort("service shutting down")
            self.cond.notify_all()
        if self.worker.is_alive():
            self.worker.join(timeout=30)


NAME = r"^[a-z][a-z0-9-]{0,63}$"
RUN_ID = PathParam(min_length=1, max_length=128)
MAX_LIMIT = 1000


class RunRequest(BaseModel):
    procedure: str = Field(pattern=NAME, description="see GET /procedures")
    params: dict[str, Any] = Field(default_factory=dict, max_length=64)
    operator: str | None = Field(None, max_length=100)


class AbortRequest(BaseModel):
    operator: str | None = Field(None, max_length=100, description="who aborts; recorded")


class SolveRequest(BaseModel):
    exclude: list[int] = Field(default_factory=list, max_length=10_000,
                               description="capture indices to leave out (captures/NNN)")
    reason: str = Field("", max_length=2000, description="why; kept in decisions.jsonl")
    operator: str | None = Field(None, max_length=100, description="who; recorded")


def _row(row: dict) -> dict:
    return {k: (v.isoformat() if isinstance(v, dt.datetime) else v) for k, v in row.items()
            if k not in ("pid", "host")}


def create_app(service: RigService, stop_service_on_shutdown: bool = False,
               host: str | None = None) -> FastAPI:
    """The HTTP API of ``service``, listening on ``host`` (default: ``service.bind``;
    it decides whether reads are public when ``service.public_read`` is unset). With
    ``stop_service_on_shutdown``, the server's graceful shutdown (SIGTERM, SIGINT)
    aborts the current run and waits for it to be recorded: uvicorn re-raises the signal
    once it has shut down, so code after ``uvicorn.run`` never runs."""
    config = service.config
    host = host or config.service.bind
    check_bind(config, host)
    access = Access(service_token(config), config.service.reads_public(host))

    @contextlib.asynccontextmanager
    async def lifespan(_app):
        yield
        if stop_service_on_shutdown:
            await asyncio.to_thread(service.stop)

    app = FastAPI(title="rigctl", version=__version__, lifespan=lifespan,
                  description=f"Rig controller service for rig {config.name!r}")

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
        """422 naming each bad value's place and reason; the value itself is left out (a
        NaN or Infinity in the body is not JSON, and echoing it made the answer a 500)."""
        errors = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")),
                   "type": str(e.get("type", ""))} for e in exc.errors()]
        return JSONResponse(status_code=422, content={"detail": errors})

    bearer = HTTPBearer(auto_error=False, description="service.token (or RIGCTL_TOKEN)")

    def require_token(request: Request,
                      credentials: HTTPAuthorizationCredentials | None = Depends(bearer)
                      ) -> None:
        """Changes need the token (or the console's session)."""
        if not access.allows(request, credentials):
            raise HTTPException(401, UNAUTHORIZED, headers={"WWW-Authenticate": "Bearer"})

    def require_read(request: Request,
                     credentials: HTTPAuthorizationCredentials | None = Depends(bearer)
                     ) -> None:
        """Reads need the token too unless they are public (``service.public_read``); a
        console page answers with its sign-in form."""
        if access.public_read or access.allows(request, credentials):
            return
        path = request.url.path
        if request.method == "GET" and (path == "/" or path.startswith("/console")):
            raise LoginRequiredError(path)
        raise HTTPException(401, UNAUTHORIZED, headers={"WWW-Authenticate": "Bearer"})

    templates = console_templates(service)
    guarded, readers = [Depends(require_token)], [Depends(require_read)]
    app.include_router(_health_routes(service))
    app.include_router(login_routes(access, templates, SESSION_COOKIE))
    app.include_router(_rig_routes(service), dependencies=readers)
    app.include_router(_run_routes(service, guarded), dependencies=readers)
    app.include_router(_resume_routes(service, guarded), dependencies=readers)
    app.include_router(_calibration_routes(service, guarded), dependencies=readers)
    app.include_router(_page_routes(service, templates), dependencies=readers)
    app.include_router(_teach_routes(service, guarded), dependencies=readers)
    mount_static(app, templates)
    return app


def _starting(job: Job) -> dict:
    """The job the worker has taken but the runner has not recorded yet (it checks the
    rig and opens the run directory first): answered as "starting", so that the id the
    API returned for it never answers 404 on its way from the queue to the records."""
    return {"run_id": job.run_id, "procedure": job.procedure, "status": "starting",
            "progress": job.progress}


def _run_listing(service: RigService, limit: int, procedure: str | None) -> list[dict]:
    """The queued runs, the one starting (taken off the queue, not recorded yet), then
    the recorded ones, newest first."""
    queued = [{"run_id": j.run_id, "procedure": j.procedure, "status": "queued"}
              for j in list(service.queue) if procedure in (None, j.procedure)]
    current = service.current
    rows = [_row(r) for r in service.runs(limit, procedure)]
    if current is not None and procedure in (None, current.procedure) and \
            current.run_id not in {r["run_id"] for r in rows + queued}:
        queued.append(_starting(current))
    return queued + rows


def _run_view(service: RigService, run_id: str) -> dict:
    """One run: queued, starting, or its record with its progress and result."""
    for job in list(service.queue):
        if job.run_id == run_id:
            return {"run_id": run_id, "procedure": job.procedure, "status": "queued"}
    current = service.current
    try:
        row = _row(_own_run(service, run_id))
    except HTTPException:
        if current is None or current.run_id != run_id:
            raise
        return _starting(current)
    if current is not None and current.run_id == row["run_id"]:
        row["progress"] = current.progress
    if row["run_dir"] and Path(row["run_dir"], "result.json").exists():
        row["result"] = RunDirectory(row["run_dir"]).result()
    if row["run_dir"] and Path(row["run_dir"]).is_dir():
        segments = read_segments(RunDirectory(row["run_dir"]))
        row["segments"] = segments if row["status"] in ("running", "paused") else \
            close_dangling(segments, RunDirectory(row["run_dir"]))
    return row


def _own_run(service: RigService, run_id: str) -> dict:
    """The run with this id (or unique prefix) of this rig; 404 otherwise."""
    try:
        row = service.index.get(run_id)
    except RigError:
        raise HTTPException(404, f"no run {run_id}") from None
    if row["rig_name"] != service.config.name:
        raise HTTPException(404, f"no run {run_id} on rig {service.config.name} (it belongs "
                                 f"to rig {row['rig_name']})")
    return row


def _calibration_names(procedure: str | None) -> list[str]:
    if procedure is None:
        return list(drift.CALIBRATIONS)
    if procedure not in drift.CALIBRATIONS:
        raise HTTPException(422, f"procedure {procedure!r} is not a calibration; one of "
                                 f"{', '.join(drift.CALIBRATIONS)}")
    return [procedure]


def _calibration_rows(service: RigService, procedure: str | None,
                      limit: int = 200) -> list[dict]:
    rows = []
    for name in _calibration_names(procedure):
        rows += [r for r in service.runs(limit, name) if r["status"] == "succeeded"]
    return sorted(rows, key=lambda r: r["started_at"], reverse=True)


class DecisionRequest(BaseModel):
    comment: str = Field("", max_length=2000, description="why; kept in decisions.jsonl")
    operator: str | None = Field(None, max_length=100)


def _set_decision(service: RigService, run_id: str, decision: str,
                  request: DecisionRequest | None) -> dict:
    row = _own_run(service, run_id)
    if row["procedure"] not in drift.CALIBRATIONS or row["status"] != "succeeded":
        raise HTTPException(409, f"run {run_id} is not a finished calibration")
    request = request or DecisionRequest()
    return service.decide_as_operator(row, decision, request.operator or "operator",
                                      request.comment)


def _health_routes(service: RigService) -> APIRouter:
    """Whether the service answers: open to all, whatever ``service.public_read``."""
    config, router = service.config, APIRouter()

    @router.get("/health")
    def health() -> dict:
        return {"status": "ok", "rig": config.name, "version": __version__}

    return router


def _rig_routes(service: RigService) -> APIRouter:
    """The rig's devices and readings, the procedures with their schemas."""
    router = APIRouter()

    @router.get("/rig")
    def rig_state() -> dict:
        """Device status read without moving anything: configuration, lock holder, the
        last recorded readings."""
        return service.status()

    @router.get("/procedures")
    def list_procedures() -> list[dict]:
        out = []
        for name in procedures.procedure_names():
            proc = procedures.get_procedure(name)
            out.append({"name": name, "summary": proc.summary, "devices": list(proc.devices),
                        "params_schema": proc.params_model.model_json_schema()})
        return out

    return router


def _resume_routes(service: RigService, guarded: list) -> APIRouter:
    """Resume a run (``rigctl.service_resume``)."""
    router = APIRouter()

    @router.post("/runs/{run_id}/resume", dependencies=guarded)
    def resume(run_id: str = RUN_ID, request: AbortRequest | None = None) -> dict:
        """Resume a run: a paused one continues (once its condition has cleared); an
        aborted, interrupted or device-failed one is queued to continue its recorded
        plan in its own directory. 404 unknown run, 409 not resumable (the detail says
        why: running, succeeded, failed on a bug or a solve, the rig file changed)."""
        operator = (request.operator if request else None) or "operator"
        return resume_run(service, _own_run(service, run_id), operator)

    return router


def _run_routes(service: RigService, guarded: list) -> APIRouter:
    """Queue, list, inspect and abort runs; a run's captures."""
    router = APIRouter()

    @router.post("/runs", status_code=202, dependencies=guarded)
    def queue_run(request: RunRequest) -> dict:
        try:
            job = service.submit(request.procedure, request.params,
                                 operator=request.operator or "api")
        except (ConfigError, SafetyError) as exc:  # the CLI's exit 2: nothing queued
            raise HTTPException(422, str(exc)) from None
        return {"run_id": job.run_id, "status": "queued", "position": len(service.queue)}

    @router.get("/runs")
    def list_runs(limit: int = Query(50, ge=1, le=MAX_LIMIT),
                  procedure: str | None = Query(None, pattern=NAME)) -> list[dict]:
        return _run_listing(service, limit, procedure)

    @router.get("/runs/{run_id}")
    def get_run(run_id: str = RUN_ID) -> dict:
        return _run_view(service, run_id)

    @router.post("/runs/{run_id}/abort", dependencies=guarded)
    def abort_run(run_id: str = RUN_ID, request: AbortRequest | None = None) -> dict:
        """Abort a run, running or queued; a queued one is recorded as aborted by the
        request's ``operator`` (default "operator", as for accept and reject)."""
        operator = (request.operator if request else None) or "operator"
        return {"run_id": run_id, "status": service.abort(run_id, operator)}

    solving = threading.Lock()  # one re-solve at a time: each renames result.json

    @router.post("/runs/{run_id}/solve", dependencies=guarded)
    def solve_run(run_id: str = RUN_ID, request: SolveRequest | None = None) -> dict:
        """Solve a finished run again from its records (``rigctl solve``), leaving out
        the ``exclude``d captures; who excluded which, and why, goes into its decisions,
        the previous result is kept, and the result names the captures used, excluded and
        rejected. 422 for a capture the run does not have or a solve that cannot run."""
        request = request or SolveRequest()
        row = _own_run(service, run_id)
        current = service.current
        if row["status"] == "running" or (current and current.run_id == row["run_id"]):
            raise HTTPException(409, f"run {row['run_id']} is still running")
        if not row["run_dir"] or not Path(row["run_dir"]).is_dir():
            raise HTTPException(409, f"run {row['run_id']} has no run directory to solve")
        with solving:
            try:
                result = solve_recorded(row["run_dir"], service.index, exclude=request.exclude,
                                        by=request.operator or "operator",
                                        reason=request.reason)
            except RigError as exc:  # an unknown capture, a solve with too few views
                raise HTTPException(422, f"{type(exc).__name__}: {exc}") from None
        service.events.publish({"type": "solved", "run_id": row["run_id"],
                                "excluded": request.exclude})
        return {"run_id": row["run_id"], "result": to_jsonable(result)}

    @router.get("/runs/{run_id}/captures/{n}")
    def capture_image(run_id: str = RUN_ID, n: int = PathParam(ge=0, le=99_999)
                      ) -> FileResponse:
        row = _own_run(service, run_id)
        path = Path(row["run_dir"]) / "captures" / f"{n:03d}.png" if row["run_dir"] else None
        # a capture is complete once its sidecar is written (RunDirectory.write_capture)
        if path is None or not path.is_file() or not path.with_suffix(".json").is_file():
            raise HTTPException(404, f"run {run_id} has no capture {n}")
        return FileResponse(path, media_type="image/png")

    return router


def _calibration_routes(service: RigService, guarded: list) -> APIRouter:
    """The accepted calibrations, their history, and the operator's decisions."""
    router = APIRouter()

    @router.get("/calibrations/latest")
    def latest_calibration(procedure: str | None = Query(None, pattern=NAME)) -> dict:
        out = {}
        for name in _calibration_names(procedure):
            row = service._last_accepted(name)
            if row is not None:
                out[name] = {**_row(row), "result": RunDirectory(row["run_dir"]).result()}
        if procedure and procedure not in out:
            raise HTTPException(404, f"no accepted {procedure} calibration")
        return out

    @router.get("/calibrations/history")
    def calibration_history(procedure: str | None = Query(None, pattern=NAME)) -> list[dict]:
        return [_row(r) for r in _calibration_rows(service, procedure)]

    @router.post("/calibrations/{run_id}/accept", dependencies=guarded)
    def accept(run_id: str = RUN_ID, request: DecisionRequest | None = None) -> dict:
        """Accept a finished calibration, with an optional comment that is recorded."""
        return _set_decision(service, run_id, "accepted", request)

    @router.post("/calibrations/{run_id}/reject", dependencies=guarded)
    def reject(run_id: str = RUN_ID, request: DecisionRequest | None = None) -> dict:
        """Reject a finished calibration, with an optional comment that is recorded."""
        return _set_decision(service, run_id, "rejected", request)

    return router


def _page_routes(service: RigService, templates) -> APIRouter:
    """The event stream and the operator console (``rigctl.console``)."""
    router = APIRouter()

    @router.get("/events")
    async def events(request: Request) -> StreamingResponse:
        queue = service.events.subscribe()

        async def stream():
            try:
                yield "retry: 2000\n\n"
                while True:
                    if await request.is_disconnected():
                        return
                    try:
                        event = await asyncio.wait_for(queue.get(), timeout=1.0)
                    except TimeoutError:
                        yield ": keep-alive\n\n"
                        continue
                    yield f"event: {event['type']}\ndata: {json.dumps(event, default=str)}\n\n"
            finally:
                service.events.unsubscribe(queue)

        return StreamingResponse(stream(), media_type="text/event-stream")

    router.include_router(console_routes(service, templates))
    return router


class TeachRequest(BaseModel):
    action: Literal["capture", "done"] = Field(
        "capture", description="capture: record one capture where the arm stands; done: "
                               "end the teach step")


def _teach_routes(service: RigService, guarded: list) -> APIRouter:
    """The teach step of a running taught run (``rigctl.teach``): its state, and the
    operator's presses of capture and done."""
    router = APIRouter()

    def _teaching(run_id: str) -> dict:
        found = teach.DESK.active(run_id)
        if found is None:
            raise HTTPException(409, f"run {run_id} is not waiting for the operator's poses "
                                     "(no teach step under way)")
        return found

    @router.get("/runs/{run_id}/teach")
    def teach_state(run_id: str = RUN_ID) -> dict:
        """The teach step under way: captures taken, the least and most it takes."""
        return _teaching(run_id)

    @router.post("/runs/{run_id}/teach", dependencies=guarded)
    def teach_press(run_id: str = RUN_ID, request: TeachRequest | None = None) -> dict:
        """Press capture (one capture where the operator holds the arm; answered once it
        is recorded, with its index) or done (ends the teach step: at least its minimum
        of poses taken, else 409 saying so)."""
        _teaching(run_id)
        action = (request or TeachRequest()).action
        try:
            answer = teach.DESK.press(run_id, action)
        except ConfigError as exc:
            raise HTTPException(409, str(exc)) from None
        service.events.publish({"type": "teach", "run_id": run_id, "action": action,
                                **answer})
        return {"run_id": run_id, "action": action, **answer}

    return router


def serve(config: RigConfig, host: str | None = None, port: int | None = None) -> None:
    """Run the service until SIGTERM/SIGINT (uvicorn handles the signals)."""
    import uvicorn

    host = host or config.service.bind
    port = port or config.service.port
    check_bind(config, host)
    service = RigService(config)
    service.start()
    app = create_app(service, stop_service_on_shutdown=True, host=host)
    try:
        uvicorn.run(app, host=host, port=port, log_level="warning")
    finally:
        service.stop()
