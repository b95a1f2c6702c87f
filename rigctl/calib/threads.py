"""Independent pieces of a solve side by side, on this machine's cores.

OpenCV's filters and template matching, numpy's array arithmetic on large arrays and
scipy's k-d tree queries release the interpreter, so independent pieces of work (one
capture's edge map, one capture's tracking) overlap in threads. Results are collected in
the items' order, so a threaded stage gives the same result, bit for bit, as a serial one.
``RIGCTL_SOLVE_THREADS`` sets how many threads (1: serial).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import contextmanager
from typing import TypeVar

from rigctl.errors import ConfigError

T = TypeVar("T")
R = TypeVar("R")

# two is what a calibration rig's controller (and CI's machine) has to spare; more threads
# than cores only add switching
DEFAULT_THREADS = max(1, min(2, os.cpu_count() or 1))
THREADS_VARIABLE = "RIGCTL_SOLVE_THREADS"  # 1: every solve serial (a busy controller)
_local = threading.local()


def solve_threads() -> int:
    """The threads a solve may use: ``RIGCTL_SOLVE_THREADS`` when set (a positive
    integer), else ``DEFAULT_THREADS``."""
    value = os.environ.get(THREADS_VARIABLE, "").strip()
    if not value:
        return DEFAULT_THREADS
    try:
        threads = int(value)
    except ValueError:
        threads = 0
    if threads < 1:
        raise ConfigError(f"environment variable {THREADS_VARIABLE}={value!r}: a positive "
                          "integer, the threads a solve may use (1: serial)")
    return threads


def threads_here() -> int:
    """How many threads work started here may use: ``solve_threads()``, or one inside a
    thread of ``map_in_threads`` (its siblings already use the other cores)."""
    return getattr(_local, "threads", None) or solve_threads()


@contextmanager
def serial_here() -> Iterator[None]:
    """Inside it, work started in this thread is serial (``threads_here()`` is 1): the
    other cores are busy (e.g. a ``calib.solve_process`` computes beside it)."""
    before = getattr(_local, "threads", None)
    _local.threads = 1
    try:
        yield
    finally:
        _local.threads = before


def map_in_threads(fn: Callable[[T], R], items: Iterable[T],
                   threads: int | None = None) -> list[R]:
    """``[fn(item) for item in items]``, computed in up to ``threads`` threads (default
    and at most ``threads_here()``: one when called from such a thread); the first
    exception raised by ``fn`` (in the items' order) is raised again, once every item is
    done (none goes on behind the caller's back)."""
    items = list(items)
    limit = threads_here()
    threads = min(threads or limit, limit, len(items))
    if threads <= 1:
        return [fn(item) for item in items]

    def alone(item: T) -> R:
        _local.threads = 1
        return fn(item)

    futures = [_pool(threads).submit(alone, item) for item in items]
    wait(futures)
    return [future.result() for future in futures]


_pools: dict[int, ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()


def _pool(threads: int) -> ThreadPoolExecutor:
    """This process's pool of ``threads`` workers, made at its first use and kept: a pool
    made and shut down for every call cost 0.26 ms (two items) to 0.8 ms (31 items), and a
    solve makes hundreds of calls (each pass of the refinement's Jacobian is one)."""
    with _pools_lock:
        pool = _pools.get(threads)
        if pool is None:
            pool = _pools[threads] = ThreadPoolExecutor(max_workers=threads,
                                                        thread_name_prefix="rigctl-solve")
        return pool


def _forget_pools() -> None:
    """In a forked child: the parent's workers are not there; pools are made again."""
    global _pools_lock
    _pools.clear()
    _pools_lock = threading.Lock()


if hasattr(os, "register_at_fork"):  # POSIX
    os.register_at_fork(after_in_child=_forget_pools)


def row_chunks(counts: list[int], parts: int) -> list[tuple[int, int]]:
    """``counts`` (rows per block, e.g. per motion) cut into at most ``parts`` runs of
    whole blocks with about equal rows: ``(first, end)`` block indices of each run."""
    total = sum(counts)
    if parts <= 1 or len(counts) <= 1 or total == 0:
        return [(0, len(counts))]
    chunks, start, done = [], 0, 0
    for i, count in enumerate(counts):
        done += count
        if len(chunks) < parts - 1 and done >= total * (len(chunks) + 1) / parts \
                and i + 1 < len(counts):
            chunks.append((start, i + 1))
            start = i + 1
    chunks.append((start, len(counts)))
    return chunks
