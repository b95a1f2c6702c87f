"""What a test needs from the machine: in CI (``CI=true``) a missing dev dependency or
browser fails the run; elsewhere the test skips with a reason saying what to install."""

from __future__ import annotations

import importlib
import os
from types import ModuleType

import pytest

INSTALL_DEV = "pip install -e '.[dev]'"


def in_ci() -> bool:
    """True when the environment says this is CI (``CI=true``, as CI services set it)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def missing(what: str, install: str) -> None:
    """Fail (in CI) or skip (elsewhere) the calling test or module: ``what`` is missing."""
    message = f"{what} is missing; install it with: {install}"
    if in_ci():
        pytest.fail(f"CI=true: {message}", pytrace=False)
    pytest.skip(message, allow_module_level=True)


def dev_dependency(name: str, install: str = INSTALL_DEV) -> ModuleType:
    """Import the dev dependency ``name`` (the dev extra of pyproject.toml): in CI a
    missing one fails the run instead of skipping its tests."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        missing(f"the dev dependency {name!r} ({exc})", install)
        raise  # not reached: missing() fails or skips
