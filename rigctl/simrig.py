"""The one launcher of the simulated rig (`rigctl sim up` as a child process), for the
demo, the benchmarks and the tests.

Each rig gets its own loopback address (the UR protocols fix their ports) and an
ephemeral camera port unless told otherwise, so several can run on one host. ``stop``
ends `sim up` by PID and kills any stand-in that outlived it.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from rigctl.childproc import ChildProcess
from rigctl.loopback import free_host
from rigctl.mocks.world import world_file


class SimulatedRig:
    """`sim up` on ``world``; ``rig_path`` is the rig file it wrote, ``ready`` its ready
    line (host, pids of the stand-ins, camera port, workdir). Its stderr (and the
    stand-ins') goes to ``log`` when given, appended to and kept; else to a temporary
    file. After ``stop``, ``crash`` says whether `sim up` had ended on its own with an
    error (a stand-in crashed), with the end of that stderr."""

    def __init__(self, world: str | Path = "default", records: str | Path | None = None,
                 host: str | None = None, camera_port: int = 0,
                 workdir: str | Path | None = None, rig_out: str | Path | None = None,
                 ready_timeout: float = 60.0, log: str | Path | None = None) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="rigctl-simrig-")
        tmp = Path(self._tmp.name)
        self.host = host or free_host()
        self.world = str(world)
        self.log = Path(log) if log else None
        self.crash: str | None = None
        self.rig_path = Path(rig_out) if rig_out else tmp / "sim-rig.yaml"
        records = Path(records).resolve() if records else tmp / "records"
        args = ["-m", "rigctl.cli", "sim", "up", "--world", str(world_file(world)),
                "--rig-out", str(self.rig_path), "--host", self.host, "--records",
                str(records), "--camera-port", str(camera_port)]
        if workdir:
            args += ["--workdir", str(workdir)]
        try:
            self.proc = ChildProcess(args, ready_timeout, name=f"sim up ({world})",
                                     capture_stderr=True, stderr_log=self.log)
        except BaseException:
            self._tmp.cleanup()
            raise
        self.ready = self.proc.ready
        self.orphans: list[int] = []

    def stop(self, timeout: float = 20.0) -> list[int]:
        """Stop `sim up` by PID; returns the stand-ins that outlived it (killed now)."""
        self.proc.stop(timeout=timeout)
        status = self.proc.ended_before_stop
        if status not in (None, 0):
            where = f" (whole log: {self.log})" if self.log else ""
            self.crash = (f"`sim up` ({self.world}) ended on its own with status {status} "
                          f"before it was stopped{where}; its stderr ends:\n"
                          f"{self.proc.ended_stderr[-3000:]}")
        self.orphans = list(self.proc.orphans)
        self._tmp.cleanup()
        return self.orphans

    def __enter__(self) -> SimulatedRig:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
