"""Start a stand-in as its own process, read its JSON ready line, stop it by PID."""

from __future__ import annotations

import contextlib
from pathlib import Path

from rigctl.childproc import ROOT, ChildProcess
from rigctl.mocks.jsonlines import ask_once

__all__ = ["NO_CONTROLLER_HOST", "ROOT", "MockProcess", "control", "rig_without_devices"]

# The arm's address in a rig file whose tests plan without any controller: nothing listens
# there. Not 127.0.0.1, where `rigctl sim up` (its default host) or a URSim may run beside
# the suite (a UR5e there failed the planning tests of a ur3e rig: "the controller at
# 127.0.0.1 reports ... UR5"), and outside the 127.20-250.x.x range the suite's simulated
# controllers take (``rigctl.loopback.free_host``).
NO_CONTROLLER_HOST = "127.1.0.1"


def rig_without_devices(world_path, folder, records, world) -> dict:
    """The rig file ``rigctl sim up`` writes for ``world``, with nothing started: the arm
    at ``NO_CONTROLLER_HOST``, the camera at a port nothing serves."""
    from rigctl.mocks.sim import rig_text

    return rig_text(world_path, NO_CONTROLLER_HOST, folder, "http://127.0.0.1:9/stream",
                    records, world)


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
