"""Timing of named stages (solves report where their time goes; ``rigctl bench solve``)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator


def stage_timer(timings: dict[str, float]) -> Callable[[str], contextlib.AbstractContextManager]:
    """A context manager factory: ``with stage("name"):`` adds the block's seconds to
    ``timings["name"]``."""

    @contextlib.contextmanager
    def stage(name: str) -> Iterator[None]:
        started = time.perf_counter()
        try:
            yield
        finally:
            timings[name] = timings.get(name, 0.0) + time.perf_counter() - started

    return stage
