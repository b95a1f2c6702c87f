"""Independent pieces of a solve side by side, on this machine's cores.

OpenCV's filters and template matching, numpy's array arithmetic on large arrays and
scipy's k-d tree queries release the interpreter, so independent pieces of work (one
capture's edge map, one capture's tracking) overlap in threads. Results are collected in
the items' order, so a threaded stage gives the same result, bit for bit, as a serial one.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

# two is what a calibration rig's controller (and CI's machine) has to spare; more threads
# than cores only add switching. ``RIGCTL_SOLVE_THREADS`` sets it (1: every solve serial,
# e.g. on a controller busy with other work).
SOLVE_THREADS = int(os.environ.get("RIGCTL_SOLVE_THREADS") or max(1, min(2, os.cpu_count() or 1)))
_local = threading.local()


def threads_here() -> int:
    """How many threads work started here may use: ``SOLVE_THREADS``, or one inside a
    thread of ``map_in_threads`` (its siblings already use the other cores)."""
    return getattr(_local, "threads", SOLVE_THREADS)


def map_in_threads(fn: Callable[[T], R], items: Iterable[T],
                   threads: int = SOLVE_THREADS) -> list[R]:
    """``[fn(item) for item in items]``, computed in up to ``threads`` threads (one when
    called from such a thread: ``threads_here``); the first exception raised by ``fn``
    (in the items' order) is raised again."""
    items = list(items)
    threads = min(threads, threads_here(), len(items))
    if threads <= 1:
        return [fn(item) for item in items]

    def alone(item: T) -> R:
        _local.threads = 1
        return fn(item)

    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(alone, items))


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
