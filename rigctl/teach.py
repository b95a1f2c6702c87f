"""The teach step: captures at poses the operator chooses by moving the arm by hand.

A procedure run with ``teach`` (``hand-eye``, ``robot-kinematics``) plans one
``TeachStep`` instead of its moves. The runner (``teach_step``) puts the arm in free
drive (ur_rtde's teach mode), then waits for the operator's presses: ``capture`` records
a capture exactly as a planned one (image, head angles, the joints read from the arm),
``done`` ends the step (once ``min_poses`` are taken). Free drive is left on every end
of the step: done, the last pose, an abort, a fault.

Presses come from the console or the API (``POST /runs/{id}/teach``) or from the
terminal of ``rigctl run`` (``read_terminal``: Enter = capture, ``done`` = finish), all
through the process's ``DESK``.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, ClassVar

from rigctl.errors import AbortedError, ConfigError
from rigctl.procedures.base import CaptureStep

log = logging.getLogger("rigctl.teach")

ACTIONS = ("capture", "done")
POLL_S = 0.1  # how often the step looks at the abort flag and the arm's safety
PRESS_TIMEOUT_S = 60.0  # how long a press waits for the step to take it


@dataclass(frozen=True)
class TeachStep:
    """Free drive: the operator takes up to ``max_poses`` captures (at least
    ``min_poses``), each a capture of kind ``kind`` labelled "taught N"."""

    kind: str = "view"
    min_poses: int = 3
    max_poses: int = 100
    links: bool = False  # the set must determine the arm's link parameters too
    label: str = "teach"
    device: ClassVar[str | None] = "arm"

    def describe(self) -> str:
        return (f"teach: free drive, capture at the operator's poses "
                f"({self.min_poses}-{self.max_poses})")


@dataclass
class Press:
    """One press of capture or done, answered by the step (``result`` or ``error``)."""

    action: str
    answered: threading.Event = field(default_factory=threading.Event)
    result: dict[str, Any] = field(default_factory=dict)
    error: str | None = None

    def answer(self, error: str | None = None, **result: Any) -> None:
        self.error, self.result = error, result
        self.answered.set()


@dataclass
class Session:
    """A teach step under way: its presses in order and the captures taken."""

    run_id: str
    step: TeachStep
    presses: deque = field(default_factory=deque)
    captures: int = 0
    cond: threading.Condition = field(default_factory=threading.Condition)

    def next(self, timeout: float) -> Press | None:
        with self.cond:
            if not self.presses:
                self.cond.wait(timeout)
            return self.presses.popleft() if self.presses else None

    def view(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "captures": self.captures,
                "min_poses": self.step.min_poses, "max_poses": self.step.max_poses}


class TeachDesk:
    """The teach steps under way in this process, by run id, and the presses for them."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sessions: dict[str, Session] = {}

    def open(self, run_id: str, step: TeachStep) -> Session:
        with self._lock:
            session = self._sessions[run_id] = Session(run_id, step)
        return session

    def close(self, run_id: str, why: str) -> None:
        """End a session: presses still waiting are answered with ``why``."""
        with self._lock:
            session = self._sessions.pop(run_id, None)
        if session is None:
            return
        with session.cond:
            pending, session.presses = list(session.presses), deque()
        for press in pending:
            press.answer(why)

    def active(self, run_id: str | None = None) -> dict[str, Any] | None:
        """The session of ``run_id`` (any, when None) as a dict, or None."""
        with self._lock:
            sessions = [s for s in self._sessions.values() if run_id in (None, s.run_id)]
        return sessions[0].view() if sessions else None

    def press(self, run_id: str | None, action: str,
              timeout: float = PRESS_TIMEOUT_S) -> dict[str, Any]:
        """Press ``action`` for the teach step of ``run_id`` (the only one, when None) and
        wait for the step's answer. ``ConfigError`` for an unknown action, no teach step
        under way, a refused press or no answer within ``timeout``."""
        if action not in ACTIONS:
            raise ConfigError(f"teach: unknown action {action!r}; one of {', '.join(ACTIONS)}")
        with self._lock:
            sessions = [s for s in self._sessions.values() if run_id in (None, s.run_id)]
        if not sessions:
            raise ConfigError(f"teach: {'run ' + run_id if run_id else 'no run'} is not "
                              "waiting for the operator's poses (no teach step under way)")
        session, press = sessions[0], Press(action)
        with session.cond:
            session.presses.append(press)
            session.cond.notify_all()
        if not press.answered.wait(timeout):
            raise ConfigError(f"teach: the run did not take the {action} within {timeout:g} s")
        if press.error:
            raise ConfigError(f"teach: {press.error}")
        return press.result


DESK = TeachDesk()


def teach_plan(params, config, kind: str, min_poses: int, max_poses: int) -> list:
    """A taught run's plan: the head home (when the rig has one), the teach step, and
    no arm move (the arm stays where the operator leaves it; ``park`` applies at the
    end). ``ValueError`` when ``poses_file`` is given as well."""
    from rigctl.procedures.base import MoveHead, Note

    if getattr(params, "poses_file", None):
        raise ValueError("teach and poses_file exclude each other: the poses are either "
                         "taught by hand or read from the file")
    steps: list = [MoveHead(0.0, 0.0, 0.0, "head home")] if config.devices.head else []
    steps.append(Note(f"taught poses: up to {max_poses} captures of kind {kind!r}, at "
                      f"least {min_poses}; the pose set's identifiability is reported "
                      "with the result"))
    steps.append(TeachStep(kind, min_poses, max(min_poses, max_poses),
                           links=kind == "train"))
    return steps


def taught_set_report(config, step: TeachStep, run, session: Session) -> dict | None:
    """The identifiability of the poses taught so far (``planning.pose_set_report``:
    condition number and predicted camera-position 1-sigma against the D-optimal plan of
    as many views, and the warning when the set cannot determine the model), logged
    and written to the run directory (``teach.json``) before the solve. The nominal arm
    and the run's intrinsics; None (logged) when it cannot be computed."""
    from rigctl.geometry.kinematics import nominal_ur
    from rigctl.procedures.intrinsics import camera_model
    from rigctl.procedures.planning import pose_set_note, pose_set_report
    from rigctl.records import write_json

    qs = [c.meta["arm"]["q"] for c in run.captures()
          if (c.meta.get("extra") or {}).get("taught") and (c.meta.get("arm") or {}).get("q")]
    try:
        K = camera_model(run.read_json("inputs.json")["intrinsics"])[0]
        report = pose_set_report(config, qs, K, nominal_ur(config.devices.arm.model),
                                 step.links, 0.45, 30.0, 10)
    except Exception as exc:  # a report must never end the run
        log.warning("teach: no identifiability report for the taught set: %s", exc)
        return None
    note = pose_set_note(report)
    (log.warning if report["warning"] else log.info)("teach: taught set: %s", note)
    write_json(run.path / "teach.json", {"poses": len(qs), "pose_set": report,
                                         "note": note})
    return {**report, "note": note}


def teach_step(runner, rig, step: TeachStep, run, state: dict) -> None:
    """The runner's handler of ``TeachStep``: free drive on, one capture per press of
    capture (joints read from the arm), until done or ``max_poses``; free drive off on
    every way out. An abort ends it (``AbortedError``); so does a stop or a lost link
    (the arm's ``check_safety`` and ``read_state`` raise)."""
    arm = rig.open("arm")
    session = DESK.open(run.run_id, step)
    why = "the teach step ended"
    try:
        arm.teach_mode()
        log.info("teach: free drive on; move the arm, then press capture (console, API, or "
                 "Enter in the terminal of `rigctl run`); done when finished (%d-%d poses)",
                 step.min_poses, step.max_poses)
        while session.captures < step.max_poses:
            if runner.abort_event.is_set():
                why = f"the run was aborted: {runner._abort_reason}"
                raise AbortedError(runner._abort_reason)
            press = session.next(POLL_S)
            arm.check_safety()
            if press is None:
                arm.read_state()  # a lost link raises here, not at the next press
                continue
            if press.action == "done":
                if session.captures < step.min_poses:
                    press.answer(f"{session.captures} poses taken; at least "
                                 f"{step.min_poses} are needed before done")
                    continue
                press.answer(captures=session.captures, done=True,
                             pose_set=taught_set_report(runner.config, step, run, session))
                break
            press.answer(**_capture(runner, rig, step, run, state, session))
    except BaseException as exc:
        why = f"the teach step failed: {exc}"
        raise
    finally:
        DESK.close(run.run_id, why)
        arm.end_teach_mode()
    log.info("teach: %d poses taken; free drive off", session.captures)


def _capture(runner, rig, step: TeachStep, run, state: dict, session: Session
             ) -> dict[str, Any]:
    """One capture where the operator holds the arm, recorded like a planned one."""
    q = list(rig.devices["arm"].read_state().q)
    n = session.captures + 1
    state["last_motion_end"] = time.time()  # the frame must be newer than the press
    state["arm_commanded"] = {"kind": "taught", "q": q}
    index = state["capture"]
    runner._capture(rig, CaptureStep(f"taught {n}", extra={"kind": step.kind, "pose": n,
                                                           "taught": True}), run, state)
    session.captures = n
    log.info("teach: capture %03d at [%s] deg", index,
             ", ".join(f"{v * 57.29577951308232:.2f}" for v in q))
    return {"index": index, "captures": n}


def read_terminal(stream=None) -> threading.Thread:
    """Presses from the terminal of ``rigctl run``: an empty line (Enter) is capture,
    ``done`` finishes; each answer is printed. Reads on a daemon thread until the
    stream ends."""
    stream = stream or sys.stdin

    def loop() -> None:
        for line in stream:
            word = line.strip().lower()
            action = "capture" if word in ("", "c", "capture") else word
            try:
                answer = DESK.press(None, action)
                print(f"teach: {action}: {answer}", file=sys.stderr, flush=True)
            except ConfigError as exc:
                print(str(exc), file=sys.stderr, flush=True)

    thread = threading.Thread(target=loop, daemon=True, name="teach-terminal")
    thread.start()
    return thread
