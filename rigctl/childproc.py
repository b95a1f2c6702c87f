"""A child process that prints one JSON ready line, stopped by PID (stand-ins, sim up)."""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _die_with_parent() -> None:
    """In the child, before exec (Linux): SIGTERM when the parent dies, however it dies. A
    parent killed by SIGKILL or a crash in a C extension runs no ``finally``; without this,
    its stand-ins (in sessions of their own) would run on."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


class ChildProcess:
    """``python <args>`` in its own session; ``ready`` is its first stdout line (JSON)."""

    def __init__(self, args: list[str], timeout: float = 20.0, name: str = "",
                 capture_stderr: bool = False, stderr_log: str | Path | None = None) -> None:
        """``capture_stderr``: the child's stderr to a temporary file (``stderr_text``);
        ``stderr_log``: to that file instead, appended to and kept after ``stop``, so a
        crash's traceback outlives the process that captured it."""
        env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH",
                                                                                 "")}
        self.name = name or " ".join(args[:2])
        # stderr to a file, never an unread pipe (a full pipe would block the child)
        if stderr_log is not None:
            self._stderr = open(stderr_log, "a+")  # noqa: SIM115 - closed in stop()
        elif capture_stderr:
            self._stderr = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 - closed in stop()
        else:
            self._stderr = None
        self.ended_before_stop: int | None = None  # its exit status, if it ended on its own
        self.ended_stderr = ""  # and its stderr then
        self._stop_called = False
        self.proc = subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE,
                                     stderr=self._stderr, text=True, env=env, cwd=ROOT,
                                     start_new_session=True, preexec_fn=_die_with_parent)
        self.pid = self.proc.pid
        self.orphans: list[int] = []
        self.ready = self._read_ready(timeout)

    def _read_ready(self, timeout: float) -> dict:
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.proc.poll() is None:
            if sel.select(0.1):
                line = self.proc.stdout.readline()
                if line:
                    ready = json.loads(line)
                    if "error" not in ready:
                        return ready
                    break
        stderr = self.stderr_text()
        self.stop()
        raise RuntimeError(f"{self.name}: did not become ready {stderr[-2000:]}")

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL to the group after ``timeout``; then any process the ready
        line lists under ``children`` (stand-ins in sessions of their own) that outlived
        it is killed too and named in ``orphans``. A child that had already ended leaves
        its exit status in ``ended_before_stop`` and its stderr in ``ended_stderr``."""
        stop_all([self], timeout)
        return self.proc.returncode

    def terminate(self) -> None:
        """The first step of a stop: SIGTERM if it still runs, else its exit status kept
        as ``ended_before_stop`` (once: a later call does nothing)."""
        if self._stop_called:
            return
        self._stop_called = True
        self._terminated_at = time.monotonic()
        if self.proc.poll() is not None:
            self.ended_before_stop = self.proc.returncode
            self.ended_stderr = self.stderr_text()
            return
        try:
            os.kill(self.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass

    def _kill_group(self) -> None:
        """SIGKILL to its group, named on stderr with its state and how long it had had."""
        waited = time.monotonic() - self._terminated_at
        print(f"{self.name} (pid {self.pid}, state {_proc_state(self.pid)}) did not end "
              f"within {waited:.1f} s of SIGTERM; killing its group", file=sys.stderr,
              flush=True)
        try:
            os.killpg(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def _release(self) -> None:
        """After the stop: the listed children that outlived it killed (``orphans``), its
        pipes closed."""
        self.orphans = [pid for pid in getattr(self, "ready", {}).get("children", [])
                        if _kill_if_alive(pid)]
        if self.proc.stdout:
            self.proc.stdout.close()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def stderr_text(self) -> str:
        if self._stderr is None:
            return ""
        self._stderr.seek(0)
        return self._stderr.read()

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.pid, signal.SIGKILL)
            self.proc.wait(timeout=5)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def stop_all(children: list[ChildProcess], timeout: float = 8.0,
             reap_timeout: float = 5.0) -> None:
    """Stop several children within ``timeout`` in all: each is sent SIGTERM first, then
    waited for until the one deadline; those still running then are killed together
    (SIGKILL to each group, named on stderr) and reaped, each within ``reap_timeout``.
    Every child is released (``orphans`` killed, pipes closed) whatever happened to the
    others; one that cannot be reaped even after SIGKILL is named on stderr and left to
    init."""
    for child in children:
        child.terminate()
    deadline = time.monotonic() + timeout
    for child in children:
        try:
            child.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    late = [child for child in children if child.proc.poll() is None]
    for child in late:
        child._kill_group()
    for child in children:
        try:
            if child in late:
                child.proc.wait(timeout=reap_timeout)
        except subprocess.TimeoutExpired:
            print(f"{child.name} (pid {child.pid}, state {_proc_state(child.pid)}) did not "
                  f"end within {reap_timeout:.0f} s of SIGKILL", file=sys.stderr, flush=True)
        finally:
            child._release()


def _state_letter(pid: int) -> str | None:
    """The process's state letter from /proc (``Z``: a zombie), or None when it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return None


def _proc_state(pid: int) -> str:
    """The process's state letter and kernel wait channel, for a log line."""
    state = _state_letter(pid)
    try:
        wchan = Path(f"/proc/{pid}/wchan").read_text().strip() or "-"
    except OSError:
        wchan = "-"
    return "gone" if state is None else f"{state}, waiting in {wchan}"


def _kill_if_alive(pid: int) -> bool:
    """SIGKILL ``pid`` if it still runs (a zombie does not count); True if it did."""
    if _state_letter(pid) in (None, "Z"):
        return False
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        return False
    return True
