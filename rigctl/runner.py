"""Runs a procedure: lock, limits, progress, interruption, cleanup, recording.

Only the runner touches devices. A run:

1. validates the parameters and builds the plan (no device touched);
2. checks every move of the plan against the rig file's soft limits;
3. takes the rig lock ("busy, held by run X (pid N)" otherwise);
4. creates the run directory and its index row (status ``running``);
5. executes the steps, writing each capture the moment it is taken;
6. solves, and records ``succeeded`` with the result.

Ctrl-C, an abort request, SIGTERM, a device fault or a safety stop stop every
device the run touched, park them per policy, and record the run as
``aborted`` or ``failed`` with the reason; the captures stay on disk, and
``versions.json`` records the devices (their bus transaction counts) as for any run.
"""

from __future__ import annotations

import getpass
import logging
import os
import platform
import signal
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from rigctl import procedures, suspenders, teach
from rigctl import resume as resuming
from rigctl.calib.blas_threads import one_blas_thread
from rigctl.calib.solve_process import start_if_useful
from rigctl.config import RigConfig, parse_rig
from rigctl.drivers.camera import changed_share, mean_change
from rigctl.errors import AbortedError, ConfigError, DeviceError, RigError, SafetyError
from rigctl.extras import missing_extra
from rigctl.locks import rig_lock
from rigctl.plan_check import (  # noqa: F401 (the runner's public names)
    PlanCheck,
    check_plan,
    linear_path_q,
    prepare_run,
    refuse_violations,
)
from rigctl.procedures.base import (
    CaptureStep,
    MoveArmJoint,
    MoveArmJoints,
    MoveArmLinear,
    MoveHead,
    Note,
    Procedure,
    Settle,
    SolveContext,
    Step,
)
from rigctl.records import (
    RunDirectory,
    new_run_id,
    run_row,
    software_provenance,
    summarize,
    utcnow,
    write_json,
)
from rigctl.redaction import RedactingFormatter, redact_rig_text, scrub
from rigctl.rig import Rig
from rigctl.runner_resume import ResumeMixin

if TYPE_CHECKING:
    from rigctl.record_index import RecordIndex

log = logging.getLogger("rigctl.run")
# how long a capture keeps waiting for a fresh view when a frame after a motion shows
# the previous capture's view (``Runner._fresh_frame``)
STALE_RETRY_S = 3.0
# A frame after a motion is the previous capture's view only when both its mean change
# is under ``still_threshold`` and under this share of its 8 x 8 cells changed by more
# than 8 grey levels (``changed_share``). The mean alone took the demo's SHIFT capture
# (the arm 10 mm sideways: 0.88 grey levels, 3.6 % of cells) for stale and retried it
# for 3 s in every active-camera run.
STALE_CHANGED_SHARE = 0.005

EventSink = Callable[[dict[str, Any]], None]


@dataclass
class RunOutcome:
    run_id: str
    status: str
    reason: str | None
    run_dir: str
    result: dict[str, Any] | None
    timings_s: dict[str, float] = field(default_factory=dict)
    # aborted by the operator (abort(), SIGTERM, Ctrl-C), not by a device or a check
    operator_stop: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "status": self.status, "reason": self.reason,
                "run_dir": self.run_dir, "result": self.result, "timings_s": self.timings_s,
                "operator_stop": self.operator_stop}


def _write_versions(run: RunDirectory, devices: dict, hidden: list[str]) -> None:
    """``versions.json``: the software's versions and each device's ``describe()``
    (model, firmware, settings, bus transaction counts), with the ``hidden`` secrets
    redacted. A device that cannot describe itself is recorded with its error; a write
    that fails is logged: neither may end a run or hide its real outcome."""
    described = {}
    for kind, device in devices.items():
        try:
            described[kind] = device.describe()
        except Exception as exc:
            described[kind] = {"error": f"describe() failed: {type(exc).__name__}: {exc}"}
            log.error("%s: describe() failed: %s", kind, exc)
    try:
        write_json(run.path / "versions.json",
                   scrub({"software": _versions(), "devices": described}, hidden))
    except OSError as exc:
        log.error("cannot write versions.json: %s", exc)


def _versions() -> dict[str, Any]:
    """rigctl's exact version, commit and dirty tree (``software_provenance``), Python's,
    the platform's and the main libraries'."""
    prov = software_provenance()
    out = {"rigctl": prov["version"], "rigctl_commit": prov["commit"],
           "rigctl_dirty": prov["dirty"], "rigctl_from": prov["from"],
           "python": platform.python_version(), "platform": platform.platform()}
    for dist in ("numpy", "scipy", "opencv-python-headless", "dynamixel-sdk", "ur-rtde"):
        try:
            out[dist] = importlib_metadata.version(dist)
        except importlib_metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


class Runner(ResumeMixin):
    """Executes procedures on one rig. Thread-safe ``abort()`` and ``request_continue()``
    (a paused run); one run at a time."""

    def __init__(self, config: RigConfig, *, factories: dict | None = None,
                 console: Console | None = None, show_progress: bool = True,
                 operator: str | None = None, on_event: EventSink | None = None) -> None:
        self.config = config
        self.factories = factories
        self.console = console or Console(stderr=True)
        self.show_progress = show_progress
        self.operator = operator or _whoami()
        self.on_event = on_event
        self._board: CaptureWorker | None = None
        self._prefetch: CaptureWorker | None = None
        self._after_last: Callable[[], Any] | None = None  # see _start_after_last_capture
        self.abort_event = threading.Event()
        self.continue_event = threading.Event()  # the operator's resume of a paused run
        self._abort_reason = "abort requested"
        from rigctl.record_index import RecordIndex  # SQLAlchemy: only where a run opens it

        self.index = RecordIndex(config.database_url())
        self.paused: str | None = None  # the reason, while paused

    # -- planning -------------------------------------------------------------

    def prepare(self, name: str, overrides: dict[str, Any]) -> tuple[Procedure, Any, PlanCheck]:
        return prepare_run(self.config, name, overrides)

    def dry_run(self, name: str, overrides: dict[str, Any]) -> PlanCheck:
        """The whole plan with limits checked; touches no device."""
        return self.prepare(name, overrides)[2]

    # -- control --------------------------------------------------------------

    def abort(self, reason: str = "abort requested") -> None:
        self._abort_reason = reason
        self.abort_event.set()
        self.continue_event.set()  # wakes a paused run, which then sees the abort

    def request_continue(self) -> None:
        """The operator's resume of a paused run: check its condition now and continue
        when it has cleared (``suspenders.wait_clear``)."""
        self.continue_event.set()

    def _emit(self, **event: Any) -> None:
        if self.on_event is not None:
            try:
                self.on_event(event)
            except Exception:  # a broken listener must never break a run
                log.exception("event listener failed")

    # -- execution ------------------------------------------------------------

    def run(self, name: str, overrides: dict[str, Any] | None = None,
            run_id: str | None = None) -> RunOutcome:
        """Run ``name`` with parameter ``overrides``; returns the recorded outcome.

        Raises before anything moves (``ConfigError``, ``SafetyError``, ``BusyError``);
        once the run is recorded, failures end up in the outcome, not as exceptions.
        """
        procedure, params, plan = self.prepare(name, overrides or {})
        refuse_violations(plan)
        inputs = procedure.resolve_inputs(params, self.config)
        run_id = run_id or new_run_id(name)
        self.abort_event.clear()
        self._abort_reason = "abort requested"
        # SIGTERM aborts from here on: a signal between the run's record and its first
        # step must still end in an "aborted" record, not kill the process (seen in CI)
        return self._locked(run_id, lambda: self._run_locked(procedure, params, plan, run_id,
                                                             inputs))

    def _locked(self, run_id: str, body: Callable[[], RunOutcome]) -> RunOutcome:
        """``body`` with SIGTERM aborting, SIGUSR1 continuing a pause, and the rig lock."""
        # SIGTERM aborts from here on: a signal between the run's record and its first
        # step must still end in an "aborted" record, not kill the process (seen in CI)
        restore = self._install_sigterm()
        lock = rig_lock(self.config)
        try:
            lock.acquire(run_id)
            try:
                return body()
            finally:
                lock.release()
        finally:
            restore()

    def _begin(self, procedure: Procedure, plan: PlanCheck, run_id: str,
               inputs: dict[str, Any], rig: Rig, resumed: RunDirectory | None
               ) -> tuple[RunDirectory, int, int]:
        """A new run's directory and index row (its plan in ``plan.json``), or a resumed
        run's devices opened and checked (nothing moved) and its row running again; the
        step to start at and the first capture's number."""
        if resumed is None:
            run = RunDirectory.create(self.config.records_dir(), run_id)
            hidden = self.config.service.secrets()
            (run.path / "rig.yaml").write_text(redact_rig_text(self.config.source_text,
                                                               hidden))
            source = self.config.source_path
            write_json(run.path / "params.json", {
                "procedure": procedure.name, "params": plan.params,
                "operator": self.operator,
                "rig_file": str(source.resolve()) if source is not None else None})
            write_json(run.path / "inputs.json", inputs)
            resuming.write_plan(run, plan.steps)
            self._index_insert(run, run_row(self.config, run_id, procedure.name, "running",
                                            self.operator, str(run.path.resolve())))
            resuming.start_segment(run, "started", 0)
            return run, 0, 0
        run = resumed
        self._open_devices(rig, procedure)
        self._check_same_rig(rig, run)
        start = resuming.next_step(run, plan.steps)
        first_capture = max((c.index for c in run.captures()), default=-1) + 1
        self._index_update(run, run_id, status="running", reason=None, ended_at=None,
                           pid=os.getpid(), host=socket.gethostname())
        resuming.start_segment(run, f"resumed by {self.operator}", start)
        return run, start, first_capture

    def _run_locked(self, procedure: Procedure, params: Any, plan: PlanCheck,
                    run_id: str, inputs: dict[str, Any],
                    resumed: RunDirectory | None = None) -> RunOutcome:
        hidden = self.config.service.secrets()  # the service token: never on disk
        rig = Rig(self.config, self.factories)
        run, start, first_capture = self._begin(procedure, plan, run_id, inputs, rig, resumed)
        handler = logging.FileHandler(run.path / "run.log")
        handler.setFormatter(RedactingFormatter("%(asctime)s %(levelname)s %(name)s: %(message)s",
                                                hidden))
        root = logging.getLogger()
        root.addHandler(handler)
        if root.level > logging.INFO or root.level == logging.NOTSET:
            root.setLevel(logging.INFO)
        self._board = self._prefetch = None
        if procedure.detects_board and self.config.target:
            target = self.config.target
            self._board = CaptureWorker(
                lambda index, image, meta: run.capture(index).save_board_corners(target,
                                                                                image),
                "board detection")
        work = procedure.capture_work(params)
        if work is not None:
            self._prefetch = CaptureWorker(lambda index, image, meta: work(image, meta),
                                           "work while moving")
        self._emit(type="started", run_id=run_id, procedure=procedure.name,
                   total=len(plan.steps))
        status, reason, result = "running", None, None
        error: str | None = None
        operator_stop = False
        timings: dict[str, float] = {}
        ctx = SolveContext(run, self.config, params, inputs)
        if procedure.uses_solve_process:  # its interpreter starts while the rig moves
            ctx.solve_process = start_if_useful()
        after_last = getattr(work, "after_last_capture", None)
        # once the last capture is in, the work after it goes on beside the last moves
        # (not in a resumed run: the worker saw only the captures since the resume)
        self._after_last = None if after_last is None or resumed is not None else \
            (lambda: after_last(ctx))
        started = time.monotonic()
        try:
            if resumed is not None:
                log.info("resuming run %s at step %d/%d, captures from %03d", run_id,
                         start + 1, len(plan.steps), first_capture)
            self._execute(rig, procedure, plan.steps, run, run_id, start, first_capture)
            timings["motion_s"] = time.monotonic() - started
            _write_versions(run, rig.devices, hidden)
            problems = rig.close_all()
            if problems:
                log.warning("after the run: %s", "; ".join(problems))
            # the solve's time counts from here: the work on the captures still going on
            # when the motion ended is part of it
            solve_started = time.monotonic()
            self._finish_capture_work(ctx)
            self._emit(type="step", run_id=run_id, step="solve", index=len(plan.steps),
                       total=len(plan.steps))
            with one_blas_thread():
                result = procedure.solve(ctx)
            ctx.prefetched = {}  # the solve is done with them (hundreds of MB of edge maps)
            timings["solve_s"] = time.monotonic() - solve_started
            _log_solve_stages(ctx.timings_s)
            run.write_result(result)
            status = "succeeded"
        except (AbortedError, KeyboardInterrupt) as exc:
            requested, ctrl_c = self.abort_event.is_set(), isinstance(exc, KeyboardInterrupt)
            status, operator_stop = "aborted", requested or ctrl_c
            reason = self._abort_reason if requested else (
                "interrupted by Ctrl-C" if ctrl_c else str(exc))
        except RigError as exc:
            status, reason, error = _failure(exc)
        except Exception as exc:  # a bug: still record it, and keep the captures
            missing = missing_extra(exc)  # a device's client library not installed
            status, reason = "failed", (str(missing) if missing else
                                        f"internal error: {type(exc).__name__}: {exc}")
            log.exception("internal error")
        finally:
            if status != "succeeded":
                self._stop_and_record(rig, run, reason)
            self._end_capture_work(ctx)
            resuming.end_segment(run, status, reason, error)
            self._index_update(run, run_id, status=status, reason=reason, ended_at=utcnow(),
                               result_summary=summarize(result) if result else None)
            self.catch_up_index()
            if status == "succeeded" and ctx.deferred:
                timings["after_result_s"] = _run_deferred(ctx)
            timings["run_s"] = time.monotonic() - started
            log.info("run %s %s%s (%s)", run_id, status, f": {reason}" if reason else "",
                     ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in timings.items()))
            root.removeHandler(handler)
            handler.close()
            self._emit(type="finished", run_id=run_id, status=status, reason=reason)
        return RunOutcome(run_id, status, reason, str(run.path), result, timings,
                          operator_stop)

    def _finish_capture_work(self, ctx: SolveContext) -> None:
        """After the motion: wait for the work on the captures done while the rig moved
        (board detection, the procedure's ``capture_work``) and hand it to the solve; the
        wait is the solve's first stage (``waiting for the work while moving``)."""
        started = time.monotonic()
        if self._board is not None:
            self._board.finish()
        if self._prefetch is not None:
            ctx.prefetched = self._prefetch.finish()
            ctx.after_captures = self._prefetch.after
            ctx.timings_s["waiting for the work while moving"] = time.monotonic() - started

    def _end_capture_work(self, ctx: SolveContext) -> None:
        """When the run ends, however: the board detections submitted are finished (their
        files are part of the record), the procedure's capture work is dropped and the
        solve's second process stopped (by PID)."""
        if self._board is not None:
            self._board.finish()
        if self._prefetch is not None:
            self._prefetch.cancel()
            self._prefetch = None
        if ctx.solve_process is not None:
            ctx.solve_process.close()
            ctx.solve_process = None

    def _safe_stop(self, rig: Rig, reason: str | None) -> None:
        """Stop every touched device, then close each (which applies its park policy)."""
        log.warning("stopping devices: %s", reason)
        for problem in rig.stop_all() + rig.close_all():
            log.error("cleanup: %s", problem)

    def _stop_and_record(self, rig: Rig, run: RunDirectory, reason: str | None) -> None:
        """A failed or aborted run: stop and close its devices (``_safe_stop``), then
        record what they were in ``versions.json`` (unless the motion got as far as
        writing it): a failed run's bus transactions and retries are its evidence."""
        opened = dict(rig.devices)  # closing forgets them; describe() needs no link
        self._safe_stop(rig, reason)
        if not (run.path / "versions.json").exists():
            _write_versions(run, opened, self.config.service.secrets())

    def _install_sigterm(self) -> Callable[[], None]:
        """SIGTERM aborts the run, SIGUSR1 continues it when paused (how ``rigctl run
        --resume`` and the service reach a paused run of another process)."""
        if threading.current_thread() is not threading.main_thread():
            return lambda: None
        previous = signal.getsignal(signal.SIGTERM)
        previous_usr1 = signal.getsignal(signal.SIGUSR1)
        signal.signal(signal.SIGTERM, lambda *_: self.abort("SIGTERM received"))
        signal.signal(signal.SIGUSR1, lambda *_: self.request_continue())

        def restore() -> None:
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGUSR1, previous_usr1)
        return restore

    def _open_devices(self, rig: Rig, procedure: Procedure) -> None:
        """Open every device the procedure uses (before the first step)."""
        for kind in procedure.devices:
            rig.open(kind)
        for kind in procedure.optional_devices:
            if kind in rig.configured():
                rig.open(kind)

    def _execute(self, rig: Rig, procedure: Procedure, steps: list[Step], run: RunDirectory,
                 run_id: str, start: int = 0, first_capture: int = 0) -> None:
        """The steps from ``start`` (a resumed run: after an approach, ``resume.approach``),
        captures numbered from ``first_capture``. A pausable condition (``SuspendError``)
        pauses the run; once it clears, the interrupted step is redone from the start of
        its stretch (the moves after the last capture), after an approach."""
        self._open_devices(rig, procedure)
        self._record_rig(rig, run)
        progress = Progress(TextColumn("[bold]{task.description:<40}"), BarColumn(),
                            MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
                            console=self.console, disable=not self.show_progress, transient=False)
        state = {"last_motion_end": time.time(), "capture": first_capture,
                 "head_commanded": None, "arm_commanded": None, "step": None}
        n, approach = start, start > 0
        last_capture = max((i for i, step in enumerate(steps)
                            if isinstance(step, CaptureStep)), default=-1)
        with progress:
            task = progress.add_task(procedure.name, total=len(steps), completed=start)
            while n < len(steps):
                if n > last_capture:
                    self._start_after_last_capture()
                if self.abort_event.is_set():
                    raise AbortedError(self._abort_reason)
                try:
                    if approach:
                        for step in resuming.approach(steps, n):
                            if step.device in rig.devices:
                                log.info("approach: %s", step.describe())
                                self._do_step(rig, step, run, state)
                        approach = False
                    step = steps[n]
                    text = step.label or step.describe()
                    progress.update(task, description=f"{procedure.name}: {text}"[:40])
                    self._emit(type="step", run_id=run_id, index=n, total=len(steps),
                               step=step.describe())
                    log.info("step %d/%d: %s", n + 1, len(steps), step.describe())
                    state["step"] = n
                    self._do_step(rig, step, run, state)
                except suspenders.SuspendError as exc:
                    self._pause(rig, run, run_id, exc)
                    n, approach = resuming.segment_start(steps, n + exc.done), True
                    progress.update(task, completed=n)
                    continue
                n += 1
                progress.advance(task)
        self._start_after_last_capture()

    def _start_after_last_capture(self) -> None:
        """Once, when every capture is in: the capture work's ``after_last_capture`` goes
        to its worker, after the captures' own work (``Procedure.capture_work``)."""
        if self._after_last is not None and self._prefetch is not None:
            self._prefetch.submit_after(self._after_last)
        self._after_last = None

    def _pause(self, rig: Rig, run: RunDirectory, run_id: str,
               exc: suspenders.SuspendError) -> None:
        """Hold a run on a pausable condition until it clears (``suspenders.wait_clear``);
        the devices stopped meanwhile, the index row ``paused`` with the reason. With
        ``max_pause_s`` 0 the condition ends the run as before."""
        max_pause = self.config.max_pause_s
        if max_pause <= 0:
            raise exc
        self.paused = exc.reason
        log.warning("paused: %s (at most %g s)", exc.reason, max_pause)
        suspenders.hold_safe(rig, exc.kind)
        resuming.end_segment(run, "paused", exc.reason, type(exc.cause).__name__)
        self._index_update(run, run_id, status="paused", reason=exc.reason)
        self._emit(type="paused", run_id=run_id, reason=exc.reason)
        self.continue_event.clear()
        try:
            why = suspenders.wait_clear(rig, exc.kind, max_pause, self.abort_event,
                                        self.continue_event, lambda: self._abort_reason)
        except RigError:
            self.paused = None
            resuming.start_segment(run, "paused run ended", -1)
            raise
        suspenders.recover(rig, exc.kind)
        self.paused = None
        log.warning("continuing: %s", why.why)
        resuming.start_segment(run, f"continued: {why.why}", -1)
        self._index_update(run, run_id, status="running", reason=None)
        self._emit(type="continued", run_id=run_id, reason=why.why)

    def _do_step(self, rig: Rig, step: Step, run: RunDirectory, state: dict) -> None:
        """Execute one step through the handler registered for its type (``STEP_HANDLERS``)."""
        handler = STEP_HANDLERS.get(type(step))
        if handler is None:  # pragma: no cover - a new step type without a handler
            raise ConfigError(f"runner cannot execute step {step!r}")
        handler(self, rig, step, run, state)

    def _move_head(self, rig: Rig, step: MoveHead, run: RunDirectory, state: dict) -> None:
        head = rig.open("head")
        try:
            head.move_to(step.pan, step.tilt, step.roll).wait(
                self.config.devices.head.move_timeout_s, self.abort_event)
        except DeviceError as exc:  # a servo in alert pauses the run
            raise suspenders.head_suspend(head, exc) from exc
        state["head_commanded"] = {"pan": step.pan, "tilt": step.tilt, "roll": step.roll}
        state["last_motion_end"] = time.time()

    def _move_arm(self, rig: Rig, step, run: RunDirectory, state: dict) -> None:
        arm = rig.open("arm")
        try:
            if isinstance(step, MoveArmJoints):
                status = arm.move_joints(step.q)
            elif isinstance(step, MoveArmJoint):
                status = arm.move_joint(step.index, step.angle)
            else:
                status = arm.move_linear(step.pose)
            status.wait(self.config.devices.arm.move_timeout_s, self.abort_event)
        except SafetyError as exc:  # a protective stop pauses the run; an e-stop ends it
            raise suspenders.arm_suspend(arm, exc) from exc
        state["arm_commanded"] = {"kind": type(step).__name__, **_step_fields(step)}
        state["last_motion_end"] = time.time()

    def _settle(self, rig: Rig, step: Settle, run: RunDirectory, state: dict) -> None:
        if self.abort_event.wait(step.seconds):
            raise AbortedError(self._abort_reason)

    def _note(self, rig: Rig, step: Note, run: RunDirectory, state: dict) -> None:
        log.warning("plan: %s", step.text)

    def _fresh_frame(self, camera, state: dict):
        """The camera's frame after the last motion. When the rig was commanded to another
        pose since the previous capture yet the frame is the previous capture's image
        (``_same_view``), it is a stale frame from
        a backlog the grabber drained late (seen at load 12 on 2 cores: the pose before
        the move, consistent over two frames); the capture is taken again, for up to
        ``STALE_RETRY_S``, and the frame is kept (with a warning) if the view truly did
        not change."""
        frame = camera.capture(not_before=state["last_motion_end"])
        threshold = self.config.devices.camera.still_threshold
        pose = (state["head_commanded"], state["arm_commanded"])
        previous = state.get("previous_capture")
        state["previous_capture"] = None
        if previous is None or previous[1] == pose or threshold <= 0:
            state["previous_capture"] = (frame.image, pose)
            return frame
        deadline = time.monotonic() + STALE_RETRY_S
        while _same_view(previous[0], frame.image, threshold):
            if time.monotonic() > deadline:
                log.warning("capture after a motion shows the previous capture's view "
                            "(mean change under %.2f grey levels for %.1f s); kept",
                            threshold, STALE_RETRY_S)
                break
            log.warning("stale frame: the previous capture's view after a motion; "
                        "capturing again")
            frame = camera.capture(not_before=time.time())
        state["previous_capture"] = (frame.image, pose)
        return frame

    def _capture(self, rig: Rig, step: CaptureStep, run: RunDirectory, state: dict) -> None:
        meta: dict[str, Any] = {"index": state["capture"], "step": state["step"],
                                "label": step.label, "time": time.time(),
                                "extra": dict(step.extra)}
        image, health = None, None
        if step.image and "camera" in rig.configured():
            try:
                frame = self._fresh_frame(rig.open("camera"), state)
            except DeviceError as exc:  # a stalled stream pauses the run
                raise suspenders.camera_suspend(exc) from exc
            image = frame.image
            meta["camera"] = {"timestamp": frame.timestamp, "sequence": frame.sequence,
                              "settings": frame.settings}
        if "head" in rig.devices:
            angles = rig.devices["head"].read_angles()
            meta["head"] = {"pan": angles.pan, "tilt": angles.tilt, "roll": angles.roll,
                            "timestamp": angles.timestamp}
            meta["head_commanded"] = state["head_commanded"]
            if hasattr(rig.devices["head"], "health"):  # each servo's temperature, V, load
                health = meta["head_health"] = rig.devices["head"].health()
        if "arm" in rig.devices:
            arm_state = rig.devices["arm"].read_state()
            meta["arm"] = {"q": list(arm_state.q), "tcp_pose": list(arm_state.tcp_pose),
                           "timestamp": arm_state.timestamp, "safety": arm_state.safety}
            meta["arm_commanded"] = state["arm_commanded"]
        run.write_capture(state["capture"], image, meta)
        if image is not None and self._board is not None:
            self._board.submit(state["capture"], image, meta)
        if image is not None and self._prefetch is not None:
            self._prefetch.submit(state["capture"], image, meta)
        state["capture"] += 1
        if health is not None:  # a servo at its temperature limit or in alert pauses
            try:
                rig.devices["head"].check_health(health)
            except DeviceError as exc:
                suspend = suspenders.head_suspend(rig.devices["head"], exc)
                suspend.done = 1  # this capture is kept: continue after it
                raise suspend from exc


# what the runner does for each step type (procedures only describe steps)
STEP_HANDLERS: dict[type, Callable[..., None]] = {
    MoveHead: Runner._move_head, MoveArmJoints: Runner._move_arm,
    MoveArmJoint: Runner._move_arm, MoveArmLinear: Runner._move_arm,
    Settle: Runner._settle, CaptureStep: Runner._capture, Note: Runner._note,
}
STEP_HANDLERS[teach.TeachStep] = teach.teach_step  # free drive (rigctl.teach)


class CaptureWorker:
    """Work on each capture's image (``work(index, image, meta)``, its metadata as
    recorded) on one worker thread, in the captures' order, while
    the rig moves on (OpenCV and numpy release the GIL). A failure there is logged (under
    ``what``) and that capture has no outcome: the solve then does the work itself.
    Used for the board's detection (whose outcome is its ``NNN.board.json``, part of the
    record) and for a procedure's ``capture_work`` (whose outcomes the solve takes)."""

    def __init__(self, work: Callable[[int, Any, dict], Any], what: str) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.work, self.what = work, what
        self.outcomes: dict[int, Any] = {}
        self.after: Any = None  # the outcome of ``submit_after``'s work
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=what.split()[0])

    def submit(self, index: int, image, meta: dict) -> None:
        self.pool.submit(self._do, index, image, meta)

    def submit_after(self, work: Callable[[], Any]) -> None:
        """``work()`` after the captures submitted so far; its outcome is ``after`` (a
        failure is logged, and ``after`` stays None)."""
        self.pool.submit(self._do_after, work)

    def _do_after(self, work: Callable[[], Any]) -> None:
        try:
            self.after = work()
        except Exception as exc:
            log.warning("%s after the last capture: %s", self.what, exc)

    def _do(self, index: int, image, meta: dict) -> None:
        try:
            self.outcomes[index] = self.work(index, image, meta)
        except Exception as exc:
            log.warning("%s in capture %03d: %s", self.what, index, exc)

    def finish(self) -> dict[int, Any]:
        """Wait for the captures already submitted; their outcomes, by capture index."""
        self.pool.shutdown(wait=True)
        return dict(self.outcomes)

    def cancel(self) -> None:
        """Drop what has not started (the run ended without a solve); wait for the one
        running, so that nothing of the run goes on after it."""
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.outcomes.clear()
        self.after = None


def _same_view(before, after, threshold: float) -> bool:
    """Whether ``after`` shows the view of ``before``: a mean change under ``threshold``
    (``devices.camera.still_threshold``) and under ``STALE_CHANGED_SHARE`` of the cells
    clearly changed."""
    return mean_change(before, after) < threshold and \
        changed_share(before, after) < STALE_CHANGED_SHARE


def _failure(exc: RigError) -> tuple[str, str, str]:
    """Status, reason and error type (as a run's segment records it: any device fault
    as ``DeviceError``, resumable) of a run ended by ``exc``. A protective or emergency
    stop aborts the run; a pausable condition with pausing off ends it as its cause."""
    if isinstance(exc, suspenders.SuspendError):
        exc = exc.cause
    name = type(exc).__name__
    if isinstance(exc, SafetyError):
        return "aborted", f"{name}: {exc}", name
    return "failed", f"{name}: {exc}", "DeviceError" if isinstance(exc, DeviceError) else name


def _step_fields(step) -> dict[str, Any]:
    return {k: getattr(step, k) for k in ("q", "index", "angle", "pose") if hasattr(step, k)}


def _whoami() -> str:
    try:
        return getpass.getuser()
    except Exception:
        return "unknown"


def _log_solve_stages(stages: dict[str, float]) -> None:
    """The solve's stages and their seconds, in run.log (as ``rigctl bench solve`` times
    them offline): where a slow solve spent its time on the rig itself."""
    if stages:
        log.info("solve stages: %s", "; ".join(f"{name} {sec:.2f} s"
                                              for name, sec in stages.items()))


def _run_deferred(ctx: SolveContext) -> float:
    """The solve's deferred work (plots), after its result is recorded; a failure there,
    or a Ctrl-C, is logged and the result stands. Returns the seconds it took."""
    started = time.monotonic()
    try:
        problems = ctx.run_deferred()
    except KeyboardInterrupt:
        problems = ["interrupted by Ctrl-C (plots may be missing)"]
    for problem in problems:
        log.warning("after the result was recorded: %s", problem)
    return time.monotonic() - started


def recorded_config(run: RunDirectory) -> RigConfig:
    """The rig file a run used (its copy, ``rig.yaml``), with its relative paths resolved
    as they were when the run was planned: against the folder of the rig file that
    ``params.json`` records, else (runs recorded without it) against the run directory,
    never against the current directory."""
    copy = run.path / "rig.yaml"
    try:
        text = copy.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{copy}: missing from the run directory") from None
    params = run.params() if (run.path / "params.json").exists() else {}
    source = params.get("rig_file")
    return parse_rig(text, name=str(copy), path=Path(source) if source else copy)


class CuratedRun(RunDirectory):
    """A run directory whose captures leave out those the operator ``excluded`` (their
    indices, as in ``captures/NNN``): what a re-solve without them reads."""

    def __init__(self, path, excluded=()) -> None:
        super().__init__(path)
        self.excluded = sorted(set(excluded))

    def captures(self):
        return [c for c in super().captures() if c.index not in self.excluded]

    def check_excluded(self) -> None:
        """``ConfigError`` naming each excluded index that is not a capture of the run."""
        held = {c.index for c in super().captures()}
        unknown = [i for i in self.excluded if i not in held]
        if unknown:
            have = f"{min(held):03d}-{max(held):03d}" if held else "none"
            raise ConfigError(f"{self.captures_dir}: no capture {', '.join(map(str, unknown))} "
                              f"to exclude (this run's captures: {have})")


def solve_recorded(run_path, index: RecordIndex | None = None,
                   timings_s: dict[str, float] | None = None, exclude=(),
                   by: str | None = None, reason: str = "",
                   solve_process: Any = None) -> dict[str, Any]:
    """Solve a recorded run again, offline, from its run directory alone.

    The previous ``result.json`` is kept as ``result.<n>.json``. ``timings_s``, when
    given, receives the time of each stage of the solve. ``exclude``: capture indices
    the solve leaves out (``CuratedRun``; ``ConfigError`` before solving for one the run
    does not have); who (``by``, the user by default) excluded which and why
    (``reason``) is appended to the run's decisions, and the result names them
    (``excluded``). ``solve_process``: a second process for the solve and its plots
    (``calib.solve_process``, started and closed by the caller), for a procedure that
    uses one.
    """
    run = CuratedRun(run_path, exclude)
    if not run.path.is_dir():
        raise ConfigError(f"{run.path}: not a run directory")
    run.check_excluded()
    params_doc = run.params()
    config = recorded_config(run)
    procedure = procedures.get_procedure(params_doc["procedure"])
    params = procedure.params_model.model_validate(params_doc["params"])
    inputs = run.read_json("inputs.json") if (run.path / "inputs.json").exists() else {}
    run.plots_dir.mkdir(exist_ok=True)  # a copy may have lost it: plots are drawn again
    ctx = SolveContext(run, config, params, inputs)
    if procedure.uses_solve_process:
        ctx.solve_process = solve_process
    with one_blas_thread():
        result = procedure.solve(ctx)
    if run.excluded:
        result = {**result, "excluded": run.excluded}
        result.setdefault("captures", {"used": [c.index for c in run.captures()],
                                       "excluded": run.excluded, "rejected": None})
    had_result = (run.path / "result.json").exists()
    run.write_result(result)
    if run.excluded:  # the previous result was kept as the highest-numbered result.N.json
        kept = max(run.path.glob("result.*.json"), default=None,
                   key=lambda p: int(p.stem[7:]) if p.stem[7:].isdigit() else -1)
        run.append_decision("excluded", by or _whoami(), reason, excluded=run.excluded,
                            previous_result=kept.name if kept and had_result else None)
    if index is not None:
        try:
            index.get(run.run_id)
            index.update(run.run_id, result_summary=summarize(result))
        except RigError:
            pass  # the run is not in this index (copied from another machine)
    _run_deferred(ctx)
    if timings_s is not None:
        timings_s.update(ctx.timings_s)
    return result

