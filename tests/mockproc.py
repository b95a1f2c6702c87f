"""Start a stand-in as its own process, read its JSON ready line, stop it by PID."""

from __future__ import annotations

import contextlib
from pathlib import Path

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


@contextlib.contextmanager
def simulated_rig(base: Path, world: str):
    """`sim up` on ``world`` with its records, rig file and log under ``base``; on exit
    its stand-ins are stopped by PID, and none may have outlived it or crashed."""
    from rigctl.simrig import SimulatedRig

    rig = SimulatedRig(world, records=base / "records", rig_out=base / "sim-rig.yaml",
                       log=base / "sim-up.log")
    try:
        yield rig
    finally:
        orphans = rig.stop()
        assert not orphans, f"stand-ins {orphans} outlived `sim up`"
        assert not rig.crash, rig.crash
