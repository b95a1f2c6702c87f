"""Run the simulated rig (`rigctl sim up`) as a child process for the demo and benches."""

from __future__ import annotations

import tempfile
from pathlib import Path

from rigctl.bench.common import StandIn


class SimulatedRig:
    """Context manager: starts `sim up` on a world, yields the rig file path; stops it."""

    def __init__(self, world: str | Path, host: str = "127.0.0.1", records: str | Path = "",
                 port: int = 18080) -> None:
        self.world, self.host, self.port = Path(world).resolve(), host, port
        self.records = str(Path(records).resolve()) if records else ""
        self.tmp = tempfile.TemporaryDirectory(prefix="rigctl-simrig-")
        self.rig_path = Path(self.tmp.name) / "sim-rig.yaml"
        self.proc: StandIn | None = None

    def __enter__(self) -> Path:
        args = ["-m", "rigctl.cli", "sim", "up", "--world", str(self.world), "--rig-out",
                str(self.rig_path), "--host", self.host, "--camera-port", str(self.port)]
        if self.records:
            args += ["--records", self.records]
        self.proc = StandIn(args, timeout=60)
        self.ready = self.proc.ready
        return self.rig_path

    def __exit__(self, *exc) -> None:
        if self.proc is not None:
            self.proc.stop()
        self.tmp.cleanup()
