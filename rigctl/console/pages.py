"""The operator console: server-rendered pages (Jinja2) over the service's own state, with
a little plain JavaScript for the live parts (the event stream) and the actions (the
JSON API, with the bearer token the page keeps in the browser session). Every asset is
served from the package: lab networks are often offline.

When reads need the token (``service.public_read`` off), a page asked for without it
answers 401 with a sign-in form (``login_routes``): the token, given once, buys a session
cookie (HttpOnly, SameSite=Strict) holding a keyed hash of it, never the token. Figures
need the ``plots`` extra; without it they answer 404 saying so."""

from __future__ import annotations

import datetime as dt
import math
import threading
import urllib.parse
from pathlib import Path
from typing import Any

import cv2
from fastapi import APIRouter, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates
from pydantic import ValidationError

from rigctl import __version__, drift, procedures, teach
from rigctl.console import compare, rigview, views
from rigctl.console.forms import form_fields
from rigctl.console.history import series
from rigctl.console.live import LiveReadings
from rigctl.errors import RigError
from rigctl.extras import missing_extra
from rigctl.records import RunDirectory

HERE = Path(__file__).parent
NAME = r"^[a-z][a-z0-9-]{0,63}$"
# a filter left at "any" arrives as an empty string (the form sends every field)
FILTER = r"^([a-z][a-z0-9-]{0,63})?$"
RUN_ID = PathParam(min_length=1, max_length=128)
STATUSES = ("running", "paused", "succeeded", "failed", "aborted", "interrupted",
            "skipped")
PLOT_NAME = r"^[A-Za-z0-9_.-]{1,100}\.png$"
THUMB_WIDTH = 320
MAX_LOGIN_BODY = 4096  # bytes of the sign-in form


class LoginRequiredError(Exception):
    """A console page asked for without the token while reads need it: answered 401
    with the sign-in form (``mount_static`` registers the handler)."""

    def __init__(self, path: str) -> None:
        super().__init__(path)
        self.path = path


def plots_module():
    """``rigctl.console.plots`` (matplotlib); a 404 naming the ``plots`` extra when it is
    not installed."""
    try:
        from rigctl.console import plots
    except ModuleNotFoundError as exc:
        missing = missing_extra(exc)
        if missing is None:
            raise
        raise HTTPException(404, f"figures: {missing}") from None
    return plots


class ResultCache:
    """Results by path, re-read when the file changes (a re-solve rewrites it)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[float, dict]] = {}

    def get(self, run_dir: str) -> dict[str, Any] | None:
        path = Path(run_dir) / "result.json" if run_dir else None
        if path is None or not path.is_file():
            return None
        mtime = path.stat().st_mtime
        with self._lock:
            hit = self._cache.get(str(path))
        if hit and hit[0] == mtime:
            return hit[1]
        result = views.read_optional(RunDirectory(run_dir), "result.json")
        if result is not None:
            with self._lock:
                self._cache[str(path)] = (mtime, result)
        return result


def _when(value: Any) -> str:
    """A time in UTC. SQLite gives the index's times back without their zone; they were
    written in UTC, so a naive time is UTC (not the server's local time)."""
    if isinstance(value, str):  # decisions.jsonl's ISO times
        try:
            value = dt.datetime.fromisoformat(value)
        except ValueError:
            return value
    if isinstance(value, dt.datetime):
        if value.tzinfo is None:
            value = value.replace(tzinfo=dt.UTC)
        return value.astimezone(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return str(value or "")


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:  # e.g. a z-score where a result reports no sigma
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if math.isfinite(value) else str(value)
    return str(value)


def console_templates(service) -> Jinja2Templates:
    """The console's templates, with its filters and the rig's name and version."""
    templates = Jinja2Templates(directory=HERE / "templates")
    templates.env.filters["when"] = _when
    templates.env.filters["fmt"] = _fmt
    templates.env.filters["deg"] = lambda v: "n/a" if v is None else f"{v:.2f}"
    templates.env.filters["mm"] = lambda v: "n/a" if v is None else f"{v:.1f}"
    templates.env.filters["when_epoch"] = lambda v: _when(
        dt.datetime.fromtimestamp(v, dt.UTC) if isinstance(v, int | float) else v)
    templates.env.globals |= {"rig": service.config.name, "version": __version__}
    return templates


def console_routes(service, templates: Jinja2Templates) -> APIRouter:
    """The console's pages under ``/console`` (and ``/`` redirecting to it)."""
    results = ResultCache()

    def page(request: Request, name: str, **context: Any) -> HTMLResponse:
        return templates.TemplateResponse(request, name, context)

    live = LiveReadings(service, lambda: rigview.newest_readings(service))
    router = APIRouter()
    router.include_router(_html_routes(service, results, page, live))
    router.include_router(_image_routes(service, results))
    router.include_router(_preview_route(rigview.Preview(service)))
    router.include_router(_live_route(live))
    return router


def _live_route(live: LiveReadings) -> APIRouter:
    router = APIRouter()

    @router.get("/rig/live")
    def live_readings() -> dict:
        """The rig's state in degrees, mm, deg C and V: read now when no run holds the
        rig (nothing moves or is written), else the newest capture's readings;
        ``source`` says which, ``errors`` names a device that could not be read."""
        return rigview.live_state(live.read())

    return router


def _preview_route(preview: rigview.Preview) -> APIRouter:
    router = APIRouter()

    @router.get("/console/preview.jpg")
    def camera_preview() -> Response:
        """What the camera sees now (its stream), else the newest capture; JPEG."""
        found = preview.jpeg()
        if found is None:
            raise HTTPException(404, "no camera picture yet: no stream and no capture")
        return Response(found[0], media_type="image/jpeg",
                        headers={"Cache-Control": "no-store", "X-Preview-Source": found[1]})

    return router


def _rig_context(service, live: LiveReadings) -> dict[str, Any]:
    return {"calibrations": rigview.calibrations(service),
            "state": rigview.live_state(live.read()),
            "rig_yaml": rigview.rig_yaml(service.config),
            "stopped": rigview.stopped_runs(service)}


def _html_routes(service, results: ResultCache, page, live: LiveReadings) -> APIRouter:
    """The pages: rig, runs, run, history, start."""
    router = APIRouter()

    @router.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/console/")

    @router.get("/console/", response_class=HTMLResponse)
    def rig_page(request: Request) -> HTMLResponse:
        """The rig: its calibrations (age, decision, next scheduled run), its state in
        degrees, mm, deg C and V, the camera's preview, runs to resume, the current run
        and the queue, and the rig file (YAML, token redacted) folded away."""
        return page(request, "rig.html", status=service.status(), **_rig_context(service, live),
                    **_now(service))

    @router.get("/console/now", response_class=HTMLResponse)
    def now_fragment(request: Request) -> HTMLResponse:
        """The current run and the queue, as the rig page's live section."""
        return page(request, "now.html", **_now(service))

    @router.get("/console/state", response_class=HTMLResponse)
    def state_fragment(request: Request) -> HTMLResponse:
        """Busy or free and the lock holder, refreshed with the live section (a finished
        run must not leave the page saying the rig is busy)."""
        return page(request, "state.html", status=service.status())

    @router.get("/console/runs", response_class=HTMLResponse)
    def runs_page(request: Request, procedure: str | None = Query(None, pattern=FILTER),
                  status: str | None = Query(None, pattern=FILTER),
                  limit: int = Query(100, ge=1, le=1000)) -> HTMLResponse:
        """Runs of this rig, filtered by procedure and status, newest first."""
        procedure, status = procedure or None, status or None
        rows = [r for r in service.runs(1000 if status else limit, procedure)
                if status in (None, r["status"])][:limit]
        return page(request, "runs.html", rows=rows, procedure=procedure, status=status,
                    procedures=procedures.procedure_names(), statuses=STATUSES)

    @router.get("/console/runs/{run_id}", response_class=HTMLResponse)
    def run_page(request: Request, run_id: str = RUN_ID) -> HTMLResponse:
        """One run: parameters, inputs, result with sigma, plots, captures, log, and for
        a calibration its difference from the last accepted one and the decisions."""
        row = _waiting_row(service, run_id) or _find_run(service, run_id)
        return page(request, "run.html", **_run_context(service, results, row))

    @router.get("/console/history", response_class=HTMLResponse)
    def history_page(request: Request,
                     procedure: str | None = Query(None, pattern=FILTER)) -> HTMLResponse:
        """Per calibration: the history plot and a table of every run and decision."""
        procedure = procedure or None
        names = _calibrations(procedure)
        tables = {name: [_history_row(r, results) for r in _finished(service, name)]
                  for name in names}
        return page(request, "history.html", names=names, tables=tables,
                    limits=service.config.service.drift, procedure=procedure,
                    all_names=drift.CALIBRATIONS)

    @router.get("/console/start", response_class=HTMLResponse)
    def start_page(request: Request,
                   procedure: str | None = Query(None, pattern=FILTER)) -> HTMLResponse:
        """A form for each procedure, generated from its parameter schema."""
        procedure = procedure or None
        names = procedures.procedure_names()
        if procedure is not None and procedure not in names:
            raise HTTPException(404, f"no procedure {procedure!r}; one of {', '.join(names)}")
        chosen = procedure or names[0]
        proc = procedures.get_procedure(chosen)
        configured = {**proc.device_defaults(service.config),
                      **service.config.procedures.get(chosen, {})}
        return page(request, "start.html", names=names, chosen=chosen, summary=proc.summary,
                    fields=form_fields(proc.params_model.model_json_schema(), configured,
                                       _model_defaults(proc.params_model)))

    return router


def _image_routes(service, results: ResultCache) -> APIRouter:
    """A run's plots, capture thumbnails and difference figure; the history figures."""
    router = APIRouter()

    @router.get("/console/runs/{run_id}/plots/{name}")
    def run_plot(run_id: str = RUN_ID, name: str = PathParam(pattern=PLOT_NAME)) -> Response:
        run = views.run_directory(_find_run(service, run_id))
        path = run.plots_dir / name if run else None
        if path is None or not path.is_file():
            raise HTTPException(404, f"run {run_id} has no plot {name}")
        return Response(path.read_bytes(), media_type="image/png")

    @router.get("/console/runs/{run_id}/captures/{n}/thumb.jpg")
    def thumbnail(run_id: str = RUN_ID, n: int = PathParam(ge=0, le=99_999)) -> Response:
        """A capture scaled to ``THUMB_WIDTH`` px wide, JPEG."""
        run = views.run_directory(_find_run(service, run_id))
        path = run.captures_dir / f"{n:03d}.png" if run else None
        image = cv2.imread(str(path)) if path and path.with_suffix(".json").is_file() else None
        if image is None:
            raise HTTPException(404, f"run {run_id} has no capture {n}")
        scale = THUMB_WIDTH / image.shape[1]
        small = cv2.resize(image, (THUMB_WIDTH, max(1, round(image.shape[0] * scale))),
                           interpolation=cv2.INTER_AREA)
        return Response(cv2.imencode(".jpg", small)[1].tobytes(), media_type="image/jpeg")

    @router.get("/console/runs/{run_id}/difference.png")
    def difference_plot(run_id: str = RUN_ID) -> Response:
        """The difference from the last accepted calibration, against its uncertainty."""
        row = _find_run(service, run_id)
        diff = _difference(service, results, row)
        if diff is None or diff.get("png") is None:
            raise HTTPException(404, f"run {run_id} has no difference to show")
        return Response(diff["png"](), media_type="image/png")

    @router.get("/console/history/{procedure}.png")
    def history_plot(procedure: str = PathParam(pattern=NAME)) -> Response:
        name = _calibrations(procedure)[0]
        rows = _finished(service, name)
        found = {r["run_id"]: results.get(r["run_dir"]) for r in rows}
        data = series(name, rows, {k: v for k, v in found.items() if v},
                      service.config.service.drift)
        return Response(plots_module().history_png(name, data), media_type="image/png")

    return router


def _safe_next(value: str | None) -> str:
    """Where to go after signing in: a path of this service, never another site."""
    if not value or not value.startswith("/") or value.startswith("//") or "\\" in value:
        return "/console/"
    return value


def login_page(templates: Jinja2Templates, request: Request, next_path: str,
               error: str = "", status_code: int = 401) -> HTMLResponse:
    """The sign-in form, answering a page that needs the token."""
    return templates.TemplateResponse(request, "login.html",
                                      {"next": _safe_next(next_path), "error": error},
                                      status_code=status_code)


def login_routes(access, templates: Jinja2Templates, cookie: str) -> APIRouter:
    """``/console/login`` (the form; posting the token sets the session cookie) and
    ``/console/logout``; open to all, left out of the API's schema."""
    router = APIRouter()

    @router.get("/console/login", response_class=HTMLResponse, include_in_schema=False)
    def login_form(request: Request,
                   next_path: str = Query("/console/", alias="next", max_length=2000)
                   ) -> HTMLResponse:
        return login_page(templates, request, next_path, status_code=200)

    @router.post("/console/login", include_in_schema=False)
    async def login(request: Request) -> Response:
        body = await request.body()
        form = urllib.parse.parse_qs(body[:MAX_LOGIN_BODY].decode("utf-8", "replace"))
        target = _safe_next((form.get("next") or [""])[0])
        if not access.token_matches((form.get("token") or [""])[0]):
            return login_page(templates, request, target, "wrong token")
        response = RedirectResponse(target, status_code=303)
        response.set_cookie(cookie, access.session, httponly=True, samesite="strict",
                            path="/")
        return response

    @router.post("/console/logout", include_in_schema=False)
    def logout() -> Response:
        response = RedirectResponse("/console/login", status_code=303)
        response.delete_cookie(cookie, path="/")
        return response

    return router


def mount_static(app, templates: Jinja2Templates) -> None:
    """The console's static files, and its answer to a page that needs the token."""
    app.mount("/console/static", StaticFiles(directory=HERE / "static"), name="console-static")

    @app.exception_handler(LoginRequiredError)
    async def sign_in(request: Request, exc: LoginRequiredError) -> HTMLResponse:
        query = f"?{request.url.query}" if request.url.query else ""
        return login_page(templates, request, exc.path + query)


def _model_defaults(model) -> dict[str, Any]:
    """The parameters a procedure runs with when given none (empty if some are required)."""
    try:
        return model().model_dump(mode="json")
    except ValidationError:
        return {}


def _calibrations(procedure: str | None) -> list[str]:
    if procedure is None:
        return list(drift.CALIBRATIONS)
    if procedure not in drift.CALIBRATIONS:
        raise HTTPException(404, f"{procedure!r} is not a calibration; one of "
                                 f"{', '.join(drift.CALIBRATIONS)}")
    return [procedure]


def _finished(service, procedure: str) -> list[dict]:
    return [r for r in service.runs(200, procedure) if r["status"] == "succeeded"]


def _find_run(service, run_id: str) -> dict:
    try:
        row = service.index.get(run_id)
    except RigError:
        raise HTTPException(404, f"no run {run_id}") from None
    if row["rig_name"] != service.config.name:
        raise HTTPException(404, f"no run {run_id} on rig {service.config.name}")
    return row


def _waiting_row(service, run_id: str) -> dict | None:
    """A run the API has answered with an id but the runner has not recorded yet (queued,
    or just taken off the queue): the start form links to its page at once."""
    with service.cond:
        current = service.current
        jobs = [current, *service.queue]
    for job in jobs:
        if job is not None and job.run_id == run_id:
            try:
                return _find_run(service, run_id)
            except HTTPException:  # as the API answers it (``rigctl.service._run_view``)
                status = "starting" if job is current else "queued"
                return {"run_id": run_id, "procedure": job.procedure, "status": status,
                        "decision": None, "started_at": None, "ended_at": None,
                        "operator": job.operator, "reason": None, "run_dir": "",
                        "rig_name": service.config.name}
    return None


def _now(service) -> dict[str, Any]:
    current = service.current
    return {"current": None if current is None else
            {"run_id": current.run_id, "procedure": current.procedure,
             "progress": current.progress},
            "queue": [{"run_id": j.run_id, "procedure": j.procedure, "source": j.source}
                      for j in list(service.queue)]}


def _history_row(row: dict, results: ResultCache) -> dict:
    run = views.run_directory(row)
    decisions = run.decisions() if run else []
    last = decisions[-1] if decisions else {}
    return {**row, "comment": last.get("comment", ""), "by": last.get("by", "")}


def _run_context(service, results: ResultCache, row: dict) -> dict[str, Any]:
    run = views.run_directory(row)
    result = results.get(row["run_dir"]) if run else None
    current = service.current
    # progress while the index says running: the service keeps a finished run as its
    # current one a moment longer (lock release, decision), and a page loaded then must
    # not show a bar and an abort button that nothing will update
    progress = current.progress if current and current.run_id == row["run_id"] \
        and row["status"] == "running" else {} if row["status"] in ("queued", "starting") else None
    context = {"row": row, "progress": progress, "result": result,
               "is_calibration": row["procedure"] in drift.CALIBRATIONS,
               "params": views.read_optional(run, "params.json") if run else None,
               "inputs": views.read_optional(run, "inputs.json") if run else None,
               "plots": views.plots(run) if run else [],
               "captures": views.captures(run) if run else [],
               "log": views.log_tail(run) if run else "",
               "decisions": run.decisions() if run else [],
               "rows": views.result_rows(row["procedure"], result) if result else [],
               "use": views.capture_use(result) if result else None,
               "curation": [d for d in run.decisions() if d.get("decision") == "excluded"]
               if run else [],
               "teaching": teach.DESK.active(row["run_id"]),
               "resumable": row["status"] in rigview.STOPPED,
               "summary": views.summary_rows(result) if result else []}
    context["difference"] = _difference(service, results, row) if result else None
    return context


def _difference(service, results: ResultCache, row: dict) -> dict[str, Any] | None:
    """The comparison with the last accepted calibration of the same procedure (not this
    run): drift's metrics and breaches, a summary, and a function drawing the figure."""
    procedure = row["procedure"]
    if procedure not in drift.CALIBRATIONS or row["status"] != "succeeded":
        return None
    new = results.get(row["run_dir"])
    previous = service._last_accepted(procedure, exclude=row["run_id"])
    old = results.get(previous["run_dir"]) if previous else None
    if new is None or old is None:
        return None
    breaches, metrics = drift.compare(procedure, new, old, service.config.service.drift)
    out: dict[str, Any] = {"against": previous["run_id"], "breaches": breaches,
                           "metrics": metrics, "png": None, "summary": {}}
    if procedure == "active-camera":
        w, h = int(new.get("width") or 0), int(new.get("height") or 0)
        if w > 0 and h > 0:
            pd = compare.projection_difference(new, old, w, h)
            fitted = compare.projection_difference(new, old, w, h, fit_rotation=True)
            out["summary"] = {k: v for k, v in pd.summary().items()
                              if k != "fitted_rotation_deg"}  # 0: nothing fitted there
            out["summary"] |= {"max_px_after_best_rotation": fitted.summary()["max_px"],
                               "best_rotation_deg": fitted.fitted_rotation_deg}
            out["png"] = lambda: plots_module().projection_difference_png(pd, w, h)
    elif procedure == "robot-kinematics":
        run = views.run_directory(row)
        q = [c.meta["arm"]["q"] for c in run.captures() if (c.meta.get("arm") or {}).get("q")]
        if q and "links" in old:
            ad = compare.arm_difference(new, old, q)
            out["summary"] = ad.summary()
            out["png"] = lambda: plots_module().arm_difference_png(ad)
    if "T_flange_cam" in new and "T_flange_cam" in old:
        out["summary"] |= {f"hand_eye_{k}": v
                           for k, v in compare.hand_eye_difference(new, old).items()}
    return out

