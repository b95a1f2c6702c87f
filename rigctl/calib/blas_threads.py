"""One BLAS thread for the solves.

The solves' matrices are small (a Jacobian of about 10,000 x 16, normal equations of
about 50 x 50). Multi-threaded OpenBLAS gains nothing on them, and on a busy host its
spinning worker threads compete with everything else: re-solving the demo's
active-camera run with two busy cores took 12.4 s with OpenBLAS's default threads and
6.3 s with one (``rigctl bench solve``). ``threadpoolctl`` sets the limit for the
duration of a solve and restores it after.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

from threadpoolctl import threadpool_limits

P = ParamSpec("P")
R = TypeVar("R")


def one_blas_thread() -> threadpool_limits:
    """A context manager that holds BLAS (OpenBLAS, MKL) to one thread inside it."""
    return threadpool_limits(limits=1, user_api="blas")


def with_one_blas_thread(func: Callable[P, R]) -> Callable[P, R]:
    """Decorator form of ``one_blas_thread`` for a solve's entry point."""
    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with one_blas_thread():
            return func(*args, **kwargs)
    return wrapper
