"""The optional parts of rigctl (pyproject's extras) and the one message for a missing one.

The core installs the head, the camera, the solvers, the records, the CLI and the
simulated rig; ``pip install 'rigctl[service,arm,plots,postgres]'`` adds the rest. A
command that reaches a module of a missing extra fails with ``MissingExtraError`` (a
``ConfigError``: exit 2 from the CLI) naming the extra to install.
"""

from __future__ import annotations

import importlib.util
import sys

from rigctl.errors import ConfigError

# what each extra brings, by the top-level module its code imports (pyproject.toml)
EXTRAS: dict[str, tuple[str, ...]] = {
    "service": ("fastapi", "starlette", "uvicorn", "apscheduler", "jinja2"),
    "arm": ("rtde_control", "rtde_receive", "rtde_io", "dashboard_client"),
    "plots": ("matplotlib",),
    "postgres": ("psycopg",),
}
WHAT = {"service": "the HTTP service and its console (rigctl serve)",
        "arm": "a Universal Robots arm (ur-rtde)",
        "plots": "figures (matplotlib)",
        "postgres": "a PostgreSQL index of runs (psycopg)"}


class MissingExtraError(ConfigError):
    """A command needs an extra that is not installed."""

    def __init__(self, extra: str, module: str) -> None:
        self.extra, self.module = extra, module
        super().__init__(f"this needs {WHAT[extra]}, which is not installed (no module "
                         f"{module!r}): pip install 'rigctl[{extra}]'")


def extra_of(module: str | None) -> str | None:
    """The extra that provides ``module`` (or its top-level package), or None."""
    top = (module or "").split(".")[0]
    return next((extra for extra, modules in EXTRAS.items() if top in modules), None)


def missing_extra(exc: BaseException) -> MissingExtraError | None:
    """For an import that failed because an extra is not installed, the error naming the
    extra to install; None for anything else (a bug stays a bug)."""
    if isinstance(exc, MissingExtraError):
        return exc
    if not isinstance(exc, ModuleNotFoundError):
        return None
    extra = extra_of(exc.name)
    return None if extra is None else MissingExtraError(extra, exc.name or "")


def importable(module: str) -> bool:
    """Whether ``module`` is installed (without importing it)."""
    if module in sys.modules:
        return sys.modules[module] is not None
    return importlib.util.find_spec(module) is not None


def require(extra: str) -> None:
    """Raise ``MissingExtraError`` unless every module of ``extra`` is installed."""
    for module in EXTRAS[extra]:
        if not importable(module):
            raise MissingExtraError(extra, module)
