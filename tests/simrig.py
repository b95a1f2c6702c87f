"""Start `rigctl sim up` as a process for a test, and stop it (and its children) by PID."""

from __future__ import annotations

from pathlib import Path

from tests.loopback import free_host
from tests.mockproc import ROOT, MockProcess


class SimRig:
    def __init__(self, tmp_path: Path, world: str = "ideal", host: str | None = None,
                 port: int = 0) -> None:
        host = host or free_host()
        self.host = host
        self.rig_path = tmp_path / "sim-rig.yaml"
        self.proc = MockProcess(["-m", "rigctl.cli", "sim", "up", "--world",
                                 str(ROOT / "mocks" / "worlds" / f"{world}.yaml"),
                                 "--rig-out", str(self.rig_path), "--host", host,
                                 "--records", str(tmp_path / "records"),
                                 "--camera-port", str(port)], ready_timeout=40)
        self.ready = self.proc.ready

    def stop(self) -> None:
        """Stop `sim up` by PID; stand-ins it left behind are killed, then reported."""
        self.proc.stop(timeout=20)
        assert not self.proc.orphans, f"stand-ins {self.proc.orphans} outlived `sim up`"
