"""``rigctl.calib.threads``: independent pieces of a solve side by side, in order. Pure
Python, no mocks."""

from __future__ import annotations

import itertools
import threading

import pytest

from rigctl.calib.threads import map_in_threads, row_chunks, threads_here


@pytest.mark.parametrize(("counts", "parts", "expected"), [
    ([10, 10, 10, 10], 2, [(0, 2), (2, 4)]),
    ([100, 1, 1], 2, [(0, 1), (1, 3)]),
    ([1, 1, 100], 2, [(0, 3)]),  # no cut leaves the last block's run nearer half
    ([5], 2, [(0, 1)]),
    ([3, 3, 3], 3, [(0, 1), (1, 2), (2, 3)]),
    ([4, 4, 4], 1, [(0, 3)]),
    ([], 2, [(0, 0)]),
])
def test_row_chunks_are_whole_blocks_of_about_equal_rows(counts, parts, expected):
    chunks = row_chunks(counts, parts)
    assert chunks == expected
    # contiguous, covering every block once
    assert chunks[0][0] == 0 and chunks[-1][1] == len(counts)
    assert all(a[1] == b[0] for a, b in itertools.pairwise(chunks))


def test_map_in_threads_keeps_order_and_nests_serially():
    seen = []

    def inner(i: int) -> tuple[int, int, str]:
        seen.append(threading.current_thread().name)
        return i * i, threads_here(), threading.current_thread().name

    def outer(i: int):
        return map_in_threads(inner, [i, i + 1], threads=2)

    out = map_in_threads(outer, range(4), threads=2)
    assert [[v for v, _, _ in pair] for pair in out] == [[i * i, (i + 1) ** 2]
                                                         for i in range(4)]
    # inside a worker thread, work runs serially in that thread (no threads of threads)
    assert all(here == 1 for pair in out for _, here, _ in pair)
    assert all(pair[0][2] == pair[1][2] for pair in out)


def test_map_in_threads_raises_the_first_error_in_order():
    def fn(i: int) -> int:
        if i in (2, 3):
            raise ValueError(f"item {i}")
        return i

    with pytest.raises(ValueError, match="item 2"):
        map_in_threads(fn, range(5), threads=2)
    assert map_in_threads(fn, [0, 1], threads=1) == [0, 1]


@pytest.mark.parametrize("value", ["two", "0", "-1", "1.5"])
def test_a_bad_thread_count_is_refused_naming_the_variable(monkeypatch, value):
    from rigctl.calib.threads import solve_threads
    from rigctl.errors import ConfigError

    monkeypatch.setenv("RIGCTL_SOLVE_THREADS", value)
    with pytest.raises(ConfigError, match="RIGCTL_SOLVE_THREADS"):
        solve_threads()


def test_the_thread_count_comes_from_the_environment(monkeypatch):
    from rigctl.calib.threads import DEFAULT_THREADS, solve_threads

    monkeypatch.setenv("RIGCTL_SOLVE_THREADS", "1")
    assert solve_threads() == 1 and threads_here() == 1
    seen = map_in_threads(lambda _: threading.current_thread().name, range(4))
    assert set(seen) == {threading.current_thread().name}  # serial, in this thread
    monkeypatch.setenv("RIGCTL_SOLVE_THREADS", "3")
    assert solve_threads() == 3
    monkeypatch.delenv("RIGCTL_SOLVE_THREADS")
    assert solve_threads() == DEFAULT_THREADS >= 1


def test_every_item_is_done_before_the_first_error_is_raised():
    """The pool is the process's and outlives the call: an item still running after the
    error was raised would go on writing into the caller's arrays."""
    import time

    done = []

    def fn(i: int) -> int:
        if i == 0:
            raise ValueError("item 0")
        time.sleep(0.05)
        done.append(i)
        return i

    with pytest.raises(ValueError, match="item 0"):
        map_in_threads(fn, range(4), threads=2)
    assert sorted(done) == [1, 2, 3]


def _squares_in_threads(_) -> list[int]:
    return map_in_threads(lambda i: i * i, range(6), threads=2)


@pytest.mark.timeout(60)
def test_a_forked_child_makes_its_own_pool():
    """A child forked after the parent used its pool has none of the parent's workers: it
    makes its own instead of waiting on theirs forever."""
    import multiprocessing

    assert map_in_threads(lambda i: -i, range(4), threads=2) == [0, -1, -2, -3]
    with multiprocessing.get_context("fork").Pool(1) as pool:
        squares = pool.map_async(_squares_in_threads, [None]).get(timeout=30)
    assert squares == [[0, 1, 4, 9, 16, 25]]
