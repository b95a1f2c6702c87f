"""A serial bus's lock, held across threads and processes.

A paused ``rigctl run`` polls its servos while an operator runs ``rigctl head reboot``
on the same bus (the pause's advice); two processes writing to one serial port read
each other's replies (a reboot once read "overheating, motor encoder, electrical shock,
overload" from a reply meant for the run). Every transaction therefore takes this lock:
a re-entrant thread lock, and for its outermost holder an advisory ``flock`` on the
port's open file, which every process that opens the same device shares (the same
inode), so their transactions take turns. A process that dies releases its flock.
"""

from __future__ import annotations

import fcntl
import threading
from collections.abc import Callable


class BusLock:
    """``with lock:`` around each bus transaction. ``fileno``: the open port's file
    descriptor, or None while it is closed (then only the thread lock is taken)."""

    def __init__(self, fileno: Callable[[], int | None]) -> None:
        self._fileno = fileno
        self._rlock = threading.RLock()
        self._depth = 0
        self._locked_fd: int | None = None

    def __enter__(self) -> BusLock:
        self._rlock.acquire()
        self._depth += 1
        if self._depth == 1:
            self._locked_fd = self._take()
        return self

    def __exit__(self, *exc) -> None:
        try:
            if self._depth == 1:
                self._release()
        finally:
            self._depth -= 1
            self._rlock.release()

    def port_opened(self) -> None:
        """The port was (re)opened: inside a held lock, take the flock on the new file
        (a closed port's flock went with its old file); outside one, nothing."""
        if self._depth:
            self._release()
            self._locked_fd = self._take()

    def _take(self) -> int | None:
        fd = self._fileno()
        if fd is None:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:  # not lockable (a closed or odd file): the thread lock still holds
            return None
        return fd

    def _release(self) -> None:
        if self._locked_fd is not None:
            try:
                fcntl.flock(self._locked_fd, fcntl.LOCK_UN)
            except OSError:  # closed with the port: the lock went with it
                pass
            self._locked_fd = None
