"""Wait on a condition, never on the clock: a busy host only makes the wait longer."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def wait_until(condition: Callable[[], Any], timeout: float = 10.0, what: str = "condition",
               poll: float = 0.01) -> Any:
    """Poll ``condition`` until it returns something truthy (returned); fail after
    ``timeout`` seconds with ``what`` in the message."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(poll)


def raises(fn: Callable[[], Any], exc_type: type[BaseException]) -> BaseException | None:
    """The exception ``fn()`` raises if it is an ``exc_type`` (None when it returns)."""
    try:
        fn()
    except exc_type as exc:
        return exc
    return None
