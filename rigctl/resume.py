"""What a run needs to be resumed: its plan recorded as it started (``plan.json``), its
segments (``segments.json``: each stretch of execution with its start, end and reason),
where to continue, how to approach that step safely, and the checks that the rig is the
one the run started on.

A resumed run re-plans nothing: it executes the recorded plan from the first step
whose capture is missing (each capture records its ``step``), after a joint move
(``moveJ``, as the planners move between views) to the pose the plan had reached there.
"""

from __future__ import annotations

import dataclasses
import json
import os
import socket
from pathlib import Path
from typing import Any

from rigctl.errors import ConfigError
from rigctl.procedures.base import (
    CaptureStep,
    MoveArmJoint,
    MoveArmJoints,
    MoveArmLinear,
    MoveHead,
    Note,
    Settle,
    Step,
)
from rigctl.records import RunDirectory, utcnow, write_json

STEP_TYPES = {cls.__name__: cls for cls in (MoveHead, MoveArmJoints, MoveArmJoint,
                                              MoveArmLinear, Settle, CaptureStep, Note)}
# ends a resumable run may have: an operator or a protective stop (aborted), a device
# fault (failed with one of these errors), a process that died (interrupted)
RESUMABLE_ERRORS = ("DeviceError", "ProtocolError", "SafetyError")


def step_record(n: int, step: Step) -> dict[str, Any]:
    """One step of ``plan.json``: its index, type and fields."""
    fields = {f.name: getattr(step, f.name) for f in dataclasses.fields(step)}
    return {"n": n, "kind": type(step).__name__, **fields}


def write_plan(run: RunDirectory, steps: list[Step]) -> None:
    """``plan.json``: every step of the plan with its index, written when the run starts."""
    write_json(run.path / "plan.json", {"steps": [step_record(n, s)
                                                  for n, s in enumerate(steps)]})


def read_plan(run: RunDirectory) -> list[Step]:
    """The recorded plan; ``ConfigError`` for a run recorded without one."""
    path = run.path / "plan.json"
    if not path.exists():
        raise ConfigError(f"{path}: missing: the run was recorded before plans were kept, "
                          "so it cannot be resumed")
    steps = []
    for row in json.loads(path.read_text())["steps"]:
        row = dict(row)
        cls = STEP_TYPES[row.pop("kind")]
        row.pop("n")
        for key in ("q", "pose"):
            if key in row:
                row[key] = tuple(row[key])
        steps.append(cls(**row))
    return steps


# -- segments --------------------------------------------------------------------------

def read_segments(run: RunDirectory) -> list[dict[str, Any]]:
    """The run's segments, oldest first (empty for a run recorded before them)."""
    path = run.path / "segments.json"
    return json.loads(path.read_text()) if path.exists() else []


def start_segment(run: RunDirectory, reason: str, from_step: int) -> None:
    """Append a segment started now by this process; a previous segment left open (its
    process died) is closed as ``interrupted`` at the run log's last write."""
    segments = close_dangling(read_segments(run), run)
    segments.append({"n": len(segments) + 1, "started_at": utcnow().isoformat(),
                     "start_reason": reason, "from_step": from_step,
                     "pid": os.getpid(), "host": socket.gethostname(),
                     "ended_at": None, "end": None, "end_reason": None})
    write_json(run.path / "segments.json", segments)


def end_segment(run: RunDirectory, end: str, reason: str | None,
                error: str | None = None) -> None:
    """Close the open segment with ``end`` (paused, succeeded, aborted, failed), its
    reason and the error type that ended it."""
    segments = read_segments(run)
    if segments and segments[-1]["ended_at"] is None:
        segments[-1].update(ended_at=utcnow().isoformat(), end=end, end_reason=reason,
                            error=error)
        write_json(run.path / "segments.json", segments)


def close_dangling(segments: list[dict], run: RunDirectory) -> list[dict]:
    """Segments with an open last one (its process was killed) closed as interrupted."""
    if segments and segments[-1]["ended_at"] is None:
        import datetime as dt

        log_path = run.path / "run.log"
        when = (dt.datetime.fromtimestamp(log_path.stat().st_mtime, dt.UTC).isoformat()
                if log_path.exists() else None)
        segments[-1].update(ended_at=when, end="interrupted",
                            end_reason=f"process {segments[-1]['pid']} ended without "
                                       "closing the run")
    return segments


# -- resumable? ------------------------------------------------------------------------

def check_resumable(row: dict[str, Any], run: RunDirectory) -> None:
    """``ConfigError`` saying why the run of index ``row`` cannot be resumed: it is
    running, succeeded, or failed on something other than a device (a bug, a solve)."""
    status, run_id = row["status"], row["run_id"]
    if not row.get("run_dir"):
        raise ConfigError(f"run {run_id} is {status} and never started (no run directory): "
                          "submit it again")
    if status in ("running", "paused"):
        raise ConfigError(f"run {run_id} is {status} (pid {row['pid']}): nothing to resume")
    if status == "failed":
        last = (read_segments(run) or [{}])[-1]
        error = last.get("error") or (row["reason"] or "").partition(":")[0]
        if error not in RESUMABLE_ERRORS:
            raise ConfigError(f"run {run_id} failed on {error or 'an error'}, not a device "
                              f"fault: resuming would not help ({row['reason']})")
    elif status not in ("aborted", "interrupted"):
        raise ConfigError(f"run {run_id} is {status}: only an aborted, interrupted or "
                          "device-failed run can be resumed")
    if not run.path.is_dir():
        raise ConfigError(f"run {run_id}: its directory {run.path} is gone")


def next_step(run: RunDirectory, steps: list[Step]) -> int:
    """Where a resumed run continues: after the last capture step taken before the first
    planned capture that is missing (so the moves leading to it are made again)."""
    taken = {c.meta.get("step") for c in run.captures()}
    first_missing = next((n for n, s in enumerate(steps)
                          if isinstance(s, CaptureStep) and n not in taken), None)
    if first_missing is None:  # every capture taken: finish the plan's last moves
        first_missing = max((n for n, s in enumerate(steps) if isinstance(s, CaptureStep)),
                            default=-1) + 1
    return segment_start(steps, first_missing)


def segment_start(steps: list[Step], n: int) -> int:
    """The first step after the last capture step before step ``n``: a step redone is
    redone with the moves and settle that lead to it."""
    while n > 0 and not isinstance(steps[n - 1], CaptureStep):
        n -= 1
    return n


def approach(steps: list[Step], n: int) -> list[Step]:
    """The moves that put the rig where the plan had it before step ``n``: the head's
    last commanded angles and the arm's joints (a joint move, as the planners move
    between views; never a straight line). Empty when the plan had moved nothing."""
    head: MoveHead | None = None
    arm_q: list[float] | None = None
    for step in steps[:n]:
        if isinstance(step, MoveHead):
            head = step
        elif isinstance(step, MoveArmJoints):
            arm_q = list(step.q)
        elif isinstance(step, MoveArmJoint) and arm_q is not None:
            arm_q[step.index] = step.angle
        elif isinstance(step, MoveArmLinear):
            arm_q = None  # a linear move's joints: approach from the next absolute move
    out: list[Step] = []
    if head is not None:
        out.append(MoveHead(head.pan, head.tilt, head.roll, "resume: head approach"))
    if arm_q is not None:
        out.append(MoveArmJoints(tuple(arm_q), "resume: arm approach"))
    return out


# -- the rig is the one the run started on ---------------------------------------------

def rig_file_changes(config, run: RunDirectory) -> list[str]:
    """How the given rig file differs from the run's recorded copy (by hash of the
    redacted text, as the index keeps it)."""
    from rigctl.redaction import redact_rig_text

    recorded = (run.path / "rig.yaml").read_text()
    given = redact_rig_text(config.source_text, config.service.secrets())
    if recorded == given:
        return []
    import hashlib

    def short(text: str) -> str:
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    return [f"rig file hash changed: {short(recorded)} -> {short(given)} (compare "
            f"{run.path / 'rig.yaml'} with {config.source_path})"]


# describe() keys compared per device: identity, kinematics, camera settings
DEVICE_KEYS = {"arm": ("model", "serial", "controller_model", "kinematics_hash"),
               "head": ("model", "servos"),
               "camera": ("serial", "settings")}
KEY_NAMES = {"kinematics_hash": "robot kinematics hash"}


def device_changes(recorded: dict[str, Any] | None, devices: dict[str, Any]) -> list[str]:
    """How the opened ``devices`` (their ``describe()``) differ from ``versions.json``
    as the run recorded it: the same devices, the robot's kinematics hash, the camera
    settings. A run killed before it wrote ``versions.json`` has nothing to compare."""
    if not recorded:
        return []
    then = recorded.get("devices", {})
    changes = []
    for kind in sorted(set(then) | set(devices)):
        if kind not in devices or kind not in then:
            changes.append(f"devices changed: {kind} "
                           f"{'added' if kind in devices else 'gone'}")
            continue
        now = devices[kind]
        for key in DEVICE_KEYS.get(kind, ()):
            before, after = then[kind].get(key), now.get(key)
            if key == "servos":  # ids and models, not the bus counters
                before, after = _servo_ids(before), _servo_ids(after)
            if before != after:
                changes.append(f"{kind} {KEY_NAMES.get(key, key)} changed: "
                               f"{_short(before)} -> {_short(after)}")
    return changes


def _servo_ids(servos) -> Any:
    if not isinstance(servos, dict):
        return servos
    return {k: (v or {}).get("model_name") for k, v in servos.items()}


def _short(value) -> str:
    text = json.dumps(value, sort_keys=True, default=str) if not isinstance(value, str) \
        else value
    return text if len(text) <= 120 else text[:117] + "..."


def run_versions(run: RunDirectory) -> dict[str, Any] | None:
    """``versions.json`` as the run left it, or None."""
    path: Path = run.path / "versions.json"
    return json.loads(path.read_text()) if path.exists() else None
