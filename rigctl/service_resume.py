"""The service's side of resumable runs: ``POST /runs/{id}/resume`` (a paused run is
told to continue; a stopped one is queued to resume), and the queue kept on disk so
that runs queued when the service died are reported on its restart, never lost
silently (and never started unattended after a crash)."""

from __future__ import annotations

import json
import logging
import os
import signal
from pathlib import Path
from typing import Any

from fastapi import HTTPException

from rigctl import resume as resuming
from rigctl.errors import ConfigError
from rigctl.records import RunDirectory, write_json

log = logging.getLogger("rigctl.service")


def queue_path(service) -> Path:
    """``<records>/queue/<rig>.json``: the jobs queued, for a restart to report."""
    return service.config.records_dir() / "queue" / f"{service.config.name}.json"


def save_queue(service) -> None:
    """Write the queue as it stands (call with ``service.cond`` held)."""
    path = queue_path(service)
    path.parent.mkdir(parents=True, exist_ok=True)
    jobs = [{"run_id": j.run_id, "procedure": j.procedure, "params": j.params,
             "source": j.source, "operator": j.operator, "resume": j.resume}
            for j in service.queue]
    write_json(path, {"pid": os.getpid(), "jobs": jobs})


def report_lost_queue(service) -> list[dict[str, Any]]:
    """Runs a previous service left queued and never started: each recorded ``aborted``
    with the reason, logged, and returned (``GET /status``: ``lost_queue``)."""
    path = queue_path(service)
    if not path.exists():
        return []
    try:
        saved = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.error("%s: unreadable queue of the previous service: %s", path, exc)
        return []
    lost = [j for j in saved.get("jobs", []) if not j.get("resume")]
    for job in lost:
        reason = (f"queued in service pid {saved.get('pid')}, which ended before the run "
                  "started; submit it again")
        log.warning("run %s (%s): %s", job["run_id"], job["procedure"], reason)
        service.record_without_run(job["procedure"], "aborted", reason, job["params"],
                                   job["run_id"], job["operator"])
    path.unlink()
    return lost


def resume_run(service, row: dict[str, Any], operator: str) -> dict[str, Any]:
    """``POST /runs/{id}/resume`` for the run of index ``row``: a paused run (the
    service's own, or a CLI run on this host) is told to continue; an aborted,
    interrupted or device-failed one is queued to resume (its rig is checked again in
    the worker before anything moves); 409 otherwise."""
    run_id = row["run_id"]
    current, runner = service.current, service.runner
    if row["status"] == "paused":
        if current is not None and current.run_id == run_id and runner is not None:
            runner.request_continue()
        else:
            try:
                os.kill(row["pid"], signal.SIGUSR1)
            except OSError as exc:
                raise HTTPException(409, f"run {run_id} is paused in process {row['pid']}, "
                                         f"which cannot be told to continue: {exc}") from None
        return {"run_id": run_id, "status": "continuing"}
    if current is not None and current.run_id == run_id:
        raise HTTPException(409, f"run {run_id} is running")
    if any(j.run_id == run_id for j in list(service.queue)):
        raise HTTPException(409, f"run {run_id} is already queued")
    try:
        resuming.check_resumable(row, RunDirectory(row["run_dir"]))
        changes = resuming.rig_file_changes(service.config, RunDirectory(row["run_dir"]))
    except ConfigError as exc:
        raise HTTPException(409, str(exc)) from None
    if changes:
        raise HTTPException(409, f"run {run_id} not resumed, the rig changed: "
                                 + "; ".join(changes))
    job = service.enqueue_resume(row, operator)
    return {"run_id": job.run_id, "status": "queued", "position": len(service.queue)}
