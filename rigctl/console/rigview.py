"""What the console's rig page shows: each calibration with its age, decision and next
scheduled run; the rig's state in the units of the pendant and the servo tools (degrees,
millimetres, degrees Celsius, volts); the rig file as YAML with the service token
redacted; the runs waiting on a paused condition. Pure reads, no HTML."""

from __future__ import annotations

import datetime as dt
import math
import threading
import time
from typing import Any

import cv2

from rigctl import drift
from rigctl.redaction import redact_rig_text, redact_text

PREVIEW_WIDTH = 640
PREVIEW_CACHE_S = 1.0  # one grab serves every page asking within this time
STREAM_TIMEOUT_S = 3.0
STOPPED = ("aborted", "failed", "interrupted", "paused")  # what a resume can continue


def age(when: Any, now: dt.datetime | None = None) -> str:
    """How long ago ``when`` (a datetime, naive = UTC, or ISO text) was: "5 min", "3 h",
    "2 d"; "" when unknown."""
    if isinstance(when, str):
        try:
            when = dt.datetime.fromisoformat(when)
        except ValueError:
            return ""
    if not isinstance(when, dt.datetime):
        return ""
    if when.tzinfo is None:
        when = when.replace(tzinfo=dt.UTC)
    seconds = max(0.0, ((now or dt.datetime.now(dt.UTC)) - when).total_seconds())
    for unit, size in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            return f"{seconds / size:.0f} {unit}"
    return f"{seconds:.0f} s"


def next_runs(scheduler) -> dict[str, dt.datetime]:
    """The next time each procedure is scheduled (APScheduler jobs of the service)."""
    out: dict[str, dt.datetime] = {}
    if scheduler is None:
        return out
    for job in scheduler.get_jobs():
        when = getattr(job, "next_run_time", None)
        procedure = job.args[0].procedure if job.args else None
        if when is not None and procedure and (procedure not in out or when < out[procedure]):
            out[procedure] = when
    return out


def calibrations(service) -> list[dict[str, Any]]:
    """Per calibration (intrinsics, hand-eye, arm model): the newest finished run with its
    decision (accepted, pending, drift, rejected) and age, the accepted one in force and
    its age, and the next scheduled run."""
    names = {"active-camera": "intrinsics", "hand-eye": "hand-eye",
             "robot-kinematics": "arm model"}
    upcoming = next_runs(service.scheduler)
    rows = []
    for procedure in drift.CALIBRATIONS:
        done = [r for r in service.runs(200, procedure) if r["status"] == "succeeded"]
        newest = done[0] if done else None
        accepted = next((r for r in done if r["decision"] == "accepted"), None)
        rows.append({
            "name": names.get(procedure, procedure), "procedure": procedure,
            "newest": newest, "decision": (newest or {}).get("decision") or
            ("none" if newest is None else "pending"),
            "age": age(newest["ended_at"] or newest["started_at"]) if newest else "",
            "accepted": accepted,
            "accepted_age": age(accepted["ended_at"] or accepted["started_at"])
            if accepted else "",
            "next": upcoming.get(procedure)})
    return rows


def _deg(value: Any) -> float | None:
    return math.degrees(value) if isinstance(value, int | float) else None


def newest_readings(service) -> dict[str, Any]:
    """The newest capture's sidecar of the rig's recent runs (head, arm, servo health,
    time, run id); {} when there is none."""
    import json
    from pathlib import Path

    for row in service.runs(20):
        sidecars = sorted(Path(row["run_dir"], "captures").glob("[0-9][0-9][0-9].json")) \
            if row["run_dir"] else []
        if sidecars:
            try:
                meta = json.loads(sidecars[-1].read_text())
            except (OSError, ValueError):
                return {}
            return {"run_id": row["run_id"], **{k: meta.get(k) for k in
                                                ("head", "arm", "head_health", "time")}}
    return {}


def live_state(last: dict[str, Any]) -> dict[str, Any]:
    """Readings (``console.live.LiveReadings``: read now, or the newest capture's) in the
    units of
    the pendant and the servo tools: head and joint angles in degrees, the TCP position
    in mm and its rotation vector in degrees, each servo's temperature (deg C) and input
    voltage (V), the arm's safety state."""
    if not last:
        return {}
    head, arm = last.get("head") or {}, last.get("arm") or {}
    out: dict[str, Any] = {"run_id": last.get("run_id"), "time": last.get("time"),
                           "source": last.get("source", "newest capture"),
                           "errors": last.get("errors") or {}}
    if head:
        out["head_deg"] = {k: _deg(head.get(k)) for k in ("pan", "tilt", "roll")}
    if arm.get("q"):
        out["joints_deg"] = [_deg(v) for v in arm["q"]]
    pose = arm.get("tcp_pose") or []
    if len(pose) == 6:
        out["tcp_mm"] = [1000.0 * v for v in pose[:3]]
        out["tcp_rotvec_deg"] = [math.degrees(v) for v in pose[3:]]
    if arm:
        out["safety"] = str(arm.get("safety") or "unknown").replace("_", " ")
    health = last.get("head_health") or {}
    out["servos"] = [{"axis": axis, "temperature_c": h.get("temperature_c"),
                      "voltage_v": h.get("voltage_v"),
                      "temperature_limit_c": h.get("temperature_limit_c")}
                     for axis, h in health.items() if isinstance(h, dict)]
    return out


def rig_yaml(config) -> str:
    """The rig file as written (comments kept), the service token redacted."""
    hidden = config.service.secrets()
    text = config.source_text or ""
    return redact_text(redact_rig_text(text, hidden), hidden)


def stopped_runs(service, limit: int = 50) -> list[dict[str, Any]]:
    """Recent runs a resume can continue, paused ones first (with their reason)."""
    rows = [r for r in service.runs(limit) if r["status"] in STOPPED]
    return sorted(rows, key=lambda r: r["status"] != "paused")


class Preview:
    """A JPEG of what the camera sees: a fresh frame from the camera's stream URL when it
    is one (grabbed on a worker, bounded), else the newest capture of the rig's runs;
    None when there is neither. Cached for ``PREVIEW_CACHE_S``."""

    def __init__(self, service) -> None:
        self.service = service
        self._lock = threading.Lock()
        self._cached: tuple[float, bytes, str] | None = None

    def jpeg(self) -> tuple[bytes, str] | None:
        with self._lock:
            if self._cached and time.monotonic() - self._cached[0] < PREVIEW_CACHE_S:
                return self._cached[1], self._cached[2]
            image, source = self._stream_frame(), "camera"
            if image is None:
                image, source = self._newest_capture(), "newest capture"
            if image is None:
                return None
            scale = PREVIEW_WIDTH / image.shape[1]
            small = cv2.resize(image, (PREVIEW_WIDTH, max(1, round(image.shape[0] * scale))),
                               interpolation=cv2.INTER_AREA)
            data = cv2.imencode(".jpg", small)[1].tobytes()
            self._cached = (time.monotonic(), data, source)
            return data, source

    def _stream_frame(self):
        camera = self.service.config.devices.camera
        url = str(getattr(camera, "device", "") or "") if camera else ""
        if "://" not in url:
            return None  # a V4L2 device belongs to the run holding it
        box: dict[str, Any] = {}

        def grab() -> None:
            cap = cv2.VideoCapture(url)
            try:
                ok, frame = cap.read()
                box["frame"] = frame if ok else None
            finally:
                cap.release()

        worker = threading.Thread(target=grab, daemon=True, name="console-preview")
        worker.start()
        worker.join(STREAM_TIMEOUT_S)
        return box.get("frame")

    def _newest_capture(self):
        from pathlib import Path

        for row in self.service.runs(20):
            pngs = sorted(Path(row["run_dir"], "captures").glob("[0-9][0-9][0-9].png")) \
                if row["run_dir"] else []
            for png in reversed(pngs):
                image = cv2.imread(str(png))
                if image is not None:
                    return image
        return None
