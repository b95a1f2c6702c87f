"""One lock per rig, shared by the CLI and the service (``flock`` on a file)."""

from __future__ import annotations

import fcntl
import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from rigctl.errors import BusyError

if TYPE_CHECKING:
    from rigctl.config import RigConfig

# the console reading the devices holds the rig for a moment (``console.live``); a run
# that asks meanwhile waits this long for it
BRIEF_HOLDER = "console-live-readings"
BRIEF_HOLD_WAIT_S = 10.0


class RigLock:
    """Exclusive, non-blocking lock on ``<records>/locks/<rig>.lock``.

    The lock dies with its process, so a crashed run never leaves the rig held.
    The file holds the holder's run id and pid, for the "busy" message.
    """

    def __init__(self, directory: Path, rig_name: str) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.path = directory / f"{rig_name}.lock"
        self.rig_name = rig_name
        self._fd: int | None = None

    def holder(self) -> dict:
        try:
            return json.loads(self.path.read_text() or "{}")
        except (OSError, json.JSONDecodeError):
            return {}

    def acquire(self, run_id: str) -> None:
        """Take the lock, or raise ``BusyError`` naming its holder. A brief holder (the
        console reading the devices, ``BRIEF_HOLDER``, or a holder still writing its
        name) is waited for, up to ``BRIEF_HOLD_WAIT_S``."""
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + BRIEF_HOLD_WAIT_S
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                held = self.holder()
                if held.get("run_id", BRIEF_HOLDER) == BRIEF_HOLDER and \
                        time.monotonic() < deadline:
                    time.sleep(0.05)
                    continue
                os.close(fd)
                raise BusyError(
                    f"rig {self.rig_name!r} busy, held by run {held.get('run_id', '?')} "
                    f"(pid {held.get('pid', '?')})"
                ) from None
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps({"run_id": run_id, "pid": os.getpid()}).encode())
        os.fsync(fd)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.ftruncate(self._fd, 0)
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def rig_lock(config: RigConfig) -> RigLock:
    """The lock of ``config``'s rig (``<records>/locks/<rig>.lock``): the one the CLI's
    runs and the service both take."""
    return RigLock(config.records_dir() / "locks", config.name)
