"""A second Python process for a solve's independent refinements, and its plots.

A refinement spends its time in many numpy operations on arrays of 10,000 to 100,000
rows; two of them in threads of one process hold the interpreter in turn, so on two cores
they took as long side by side as one after the other (the demo's active-camera run: the
coarse refinements of three starts, 2.29 s serial, 2.24 s in two threads). In a second
process they overlap for real (1.30 s).

``SolveProcess`` starts ``python -m rigctl.calib.solve_process`` and hands it jobs: a
function of ``JOBS`` and its arguments, pickled over the child's stdin, the outcome
pickled back over its stdout. The child computes with one thread (``RIGCTL_SOLVE_THREADS``
and BLAS), so a job's numbers are those of the same call in the parent, bit for bit (the
solve's threads never change a number, ``calib.threads``). The child imports numpy and
scipy as it starts (about 0.4 s); a run starts it while the rig moves. ``rigctl solve``
starts it as the command begins, with ``plots``: the child then imports matplotlib too,
on the second core while the parent imports its own modules and loads the images, and
draws the plots after the result (``calib.active_plots``). A re-solve without one
(``rigctl bench solve``, the service) starts it as its rolls' tiers begin
(``active_pipeline._Helper``), and draws the plots itself.

The child only ever speeds a solve up: a job whose process has ended, or that failed
there other than with a ``SolveError``, is computed again in the parent (``run``). The
child ends when its stdin closes (``close``, or the parent gone however it went); it
ignores Ctrl-C, which the parent handles. ``close`` stops it by PID.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future
from queue import Queue
from typing import Any

from rigctl.calib.threads import THREADS_VARIABLE, solve_threads
from rigctl.childproc import ROOT
from rigctl.errors import RigError, SolveError

log = logging.getLogger(__name__)

# the functions a job may name: module, then name (nothing else is called)
JOBS = {("rigctl.calib.active_refine", "timed_refine"),
        ("rigctl.calib.active_plots", "draw_active_plots")}
# a child started with ``plots`` imports, before its first job, the plots' module and
# matplotlib's (``active_plots.import_plot_modules``)
PLOTS_VARIABLE = "RIGCTL_SOLVE_PROCESS_PLOTS"
HEADER = struct.Struct(">Q")  # each frame: its length, then a pickle
STOP_WAIT_S = 10.0  # after stdin closes: how long the child may finish its job


def _write_frame(stream, obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(HEADER.pack(len(data)))
    stream.write(data)
    stream.flush()


def _read_frame(stream) -> Any:
    """The next frame's object; EOFError when the stream ends (between or inside frames)."""
    head = stream.read(HEADER.size)
    if len(head) < HEADER.size:
        raise EOFError("the stream ended")
    (size,) = HEADER.unpack(head)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the stream ended inside a frame")
    return pickle.loads(data)


class SolveProcess:
    """The child process and a thread that feeds it one job at a time (module
    docstring). ``submit`` returns a ``Future``; ``run`` waits for it, and computes the
    job here when the child cannot."""

    def __init__(self, plots: bool = False) -> None:
        # ``plots``: the child imports the plots' modules too, to draw a re-solve's plots
        self.plots = plots
        env = {**os.environ, THREADS_VARIABLE: "1", PLOTS_VARIABLE: "1" if plots else "",
               "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        self.proc = subprocess.Popen([sys.executable, "-m", "rigctl.calib.solve_process"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        self.pid = self.proc.pid
        self._jobs: Queue = Queue()
        self._gone: str | None = None  # why the child can take no more jobs
        self._feeder = threading.Thread(target=self._feed, name=f"solve process {self.pid}",
                                        daemon=True)
        self._feeder.start()

    def submit(self, fn: Callable, *args: Any, **kwargs: Any) -> Future:
        """``fn(*args, **kwargs)`` in the child, after the jobs before it. The future's
        exception is a ``SolveError`` raised there, or ``ChildGoneError``."""
        key = (fn.__module__, fn.__name__)
        if key not in JOBS:
            raise ValueError(f"solve process: {key[0]}.{key[1]} is not a job it takes")
        future: Future = Future()
        if self._gone is not None:
            future.set_exception(ChildGoneError(self._gone))
        else:
            self._jobs.put((future, key, args, kwargs))
        return future

    def run(self, future: Future, fn: Callable, *args: Any, **kwargs: Any) -> Any:
        """The outcome of ``future`` (``submit(fn, *args, **kwargs)``); computed here,
        with a warning in the log, when the child could not."""
        try:
            return future.result()
        except ChildGoneError as exc:
            log.warning("solve process %d: %s; computing its job here", self.pid, exc)
            return fn(*args, **kwargs)

    def take_back(self, future: Future, fn: Callable, *args: Any, **kwargs: Any) -> Any:
        """The outcome of ``future`` (``submit(fn, *args, **kwargs)``), computed here at
        once when the child has not taken it yet (it never will), else ``run``'s: for a
        parent with nothing else to do while the child still has jobs queued."""
        if future.cancel():
            return fn(*args, **kwargs)
        return self.run(future, fn, *args, **kwargs)

    def _feed(self) -> None:
        while True:
            item = self._jobs.get()
            if item is None:
                break
            future, key, args, kwargs = item
            if not future.set_running_or_notify_cancel():  # taken back (``take_back``)
                continue
            if self._gone is None:
                try:
                    _write_frame(self.proc.stdin, (key, args, kwargs))
                    kind, value = _read_frame(self.proc.stdout)
                except Exception as exc:  # pipe, pickle or import: it is gone
                    self._gone = f"ended ({type(exc).__name__}: {exc})"
            if self._gone is not None:
                future.set_exception(ChildGoneError(self._gone))
            elif kind == "ok":
                future.set_result(value)
            elif kind == "solve_error":
                future.set_exception(SolveError(value))
            else:  # a bug there: the parent computes it again and meets it itself
                future.set_exception(ChildGoneError(f"its job failed: {value}"))

    def close(self) -> None:
        """Stop the child: its stdin closed (it finishes the job in hand), then, after
        ``STOP_WAIT_S``, killed; waited for by PID. Jobs not yet fed to it fail with
        ``ChildGoneError``."""
        self._gone = self._gone or "closed"
        self._jobs.put(None)
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._feeder.join(STOP_WAIT_S)
        self.proc.stdout.close()
        while not self._jobs.empty():
            item = self._jobs.get()
            if item is not None and item[0].set_running_or_notify_cancel():
                item[0].set_exception(ChildGoneError("closed"))

    def __enter__(self) -> SolveProcess:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


class ChildGoneError(RigError):
    """The solve process could not do a job (it ended, or the job failed there); the
    parent computes it itself (``SolveProcess.run``). Never leaves this module's users."""


def start_if_useful(plots: bool = False) -> SolveProcess | None:
    """A ``SolveProcess`` when the solve may use more than one thread
    (``calib.threads.solve_threads``), else None (a busy controller: every solve
    serial, in one process), or when it cannot be started (logged: the solve then runs
    in this process alone, to the same result)."""
    if solve_threads() <= 1:
        return None
    try:
        return SolveProcess(plots)
    except OSError as exc:
        log.warning("solve process: not started (%s); solving in one process", exc)
        return None


def _serve() -> None:
    """The child: jobs from stdin until it closes, each outcome to the real stdout
    (anything printed goes to stderr)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    inp = sys.stdin.buffer
    import importlib

    while True:
        try:
            key, args, kwargs = _read_frame(inp)
        except EOFError:
            return
        try:
            if tuple(key) not in JOBS:
                raise ValueError(f"{key} is not a job this process takes")
            fn = getattr(importlib.import_module(key[0]), key[1])
            reply = ("ok", fn(*args, **kwargs))
        except SolveError as exc:
            reply = ("solve_error", str(exc))
        except Exception as exc:  # reported to the parent, which recomputes
            reply = ("failed", f"{type(exc).__name__}: {exc}")
        try:
            _write_frame(out, reply)
        except (pickle.PickleError, TypeError, AttributeError) as exc:
            _write_frame(out, ("failed", f"its outcome does not pickle: {exc}"))


if __name__ == "__main__":
    # the refinement's modules before the first job: the child starts while the parent
    # still tracks, and is ready when the refinements begin
    import rigctl.calib.active_refine  # noqa: F401

    if os.environ.get(PLOTS_VARIABLE):
        from rigctl.calib.active_plots import import_plot_modules

        import_plot_modules()
    _serve()
    # stdin closed: every outcome was flushed as it was written, so the interpreter's
    # teardown (0.2 s with matplotlib's modules, which the parent's ``close`` waits
    # for) is skipped
    sys.stderr.flush()
    os._exit(0)
