"""Start a stand-in as its own process, read its JSON ready line, stop it by PID."""

from __future__ import annotations

from rigctl.childproc import ROOT, ChildProcess
from rigctl.mocks.jsonlines import ask_once

__all__ = ["ROOT", "MockProcess", "control"]


class MockProcess(ChildProcess):
    """A stand-in under test: stderr captured for the failure message."""

    def __init__(self, args: list[str], ready_timeout: float = 15.0) -> None:
        super().__init__(args, ready_timeout, capture_stderr=True)


def control(path: str, request: dict, timeout: float = 5.0) -> dict:
    """One request on a stand-in's control socket (``rigctl.mocks.jsonlines``)."""
    return ask_once(path, request, timeout)
