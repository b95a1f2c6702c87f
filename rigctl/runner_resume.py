"""The runner's resume of a recorded run (``rigctl run --resume``, ``POST
/runs/{id}/resume``), its record of the rig it ran on, and its index writes that
survive the database being away (``record_index.JournaledIndex``)."""

from __future__ import annotations

import logging
import os
import signal
from typing import Any

from rigctl import procedures
from rigctl import resume as resuming
from rigctl.errors import ConfigError, RigError
from rigctl.plan_check import PlanCheck, check_plan, refuse_violations
from rigctl.records import RunDirectory, write_json

log = logging.getLogger("rigctl.run")


class ResumeMixin:
    """Resume for ``rigctl.runner.Runner``."""

    def resume(self, run_id: str):
        """Continue the recorded run ``run_id`` (an id or unique prefix of this rig's
        index) where it stopped: its recorded plan from the first step whose capture is
        missing, in its own directory, captures numbered on. Refused (``ConfigError``,
        nothing moved) for a run that is running, succeeded or failed on other than a
        device, or when the rig differs from the one it ran on. A paused run of another
        process on this host is told to continue instead (SIGUSR1); returns None then."""
        try:
            row = self.index.get(run_id, rig_name=self.config.name)
        except RigError as exc:
            raise ConfigError(str(exc)) from None
        if row["status"] == "paused":
            os.kill(row["pid"], signal.SIGUSR1)
            log.info("run %s is paused in process %d: asked it to continue",
                     row["run_id"], row["pid"])
            return None
        run = RunDirectory(row["run_dir"])
        resuming.check_resumable(row, run)
        changes = resuming.rig_file_changes(self.config, run)
        if changes:
            raise ConfigError(f"run {row['run_id']} not resumed, the rig changed: "
                              + "; ".join(changes))
        params_doc = run.params()
        procedure = procedures.get_procedure(params_doc["procedure"])
        params = procedure.params_model.model_validate(params_doc["params"])
        steps = resuming.read_plan(run)
        plan = PlanCheck(procedure.name, params_doc["params"], steps,
                         check_plan(self.config, steps, procedure.devices))
        refuse_violations(plan)
        inputs = run.read_json("inputs.json") if (run.path / "inputs.json").exists() else {}
        self.abort_event.clear()
        self._abort_reason = "abort requested"
        return self._locked(row["run_id"], lambda: self._run_locked(
            procedure, params, plan, row["run_id"], inputs, resumed=run))

    def _record_rig(self, rig, run: RunDirectory) -> None:
        """``rig-check.json``: what the opened devices say they are (``describe()``),
        written when the run first opens them: what a resume compares the rig with.
        A resumed run keeps the first."""
        path = run.path / "rig-check.json"
        if path.exists():
            return
        described = {}
        for kind, device in rig.devices.items():
            try:
                described[kind] = {k: device.describe().get(k)
                                   for k in resuming.DEVICE_KEYS.get(kind, ())}
            except Exception as exc:  # recorded, compared as such
                described[kind] = {"error": f"{type(exc).__name__}: {exc}"}
        write_json(path, {"devices": described})

    def _check_same_rig(self, rig, run: RunDirectory) -> None:
        """``ConfigError`` naming each change of the opened devices since the run
        started (``resume.device_changes``); the devices are then closed without parking:
        nothing moves."""
        path = run.path / "rig-check.json"
        recorded = run.read_json("rig-check.json") if path.exists() else \
            resuming.run_versions(run)
        now = {kind: device.describe() for kind, device in rig.devices.items()}
        changes = resuming.device_changes(recorded, now)
        if changes:
            close_without_park(rig)
            raise ConfigError(f"run {run.run_id} not resumed, the rig changed: "
                              + "; ".join(changes))

    def _index_update(self, run: RunDirectory, run_id: str, **values: Any) -> None:
        """Update the run's index row; kept in the run directory while the database is
        away, and replayed when it returns."""
        self._journal(run).write("update", run_id, values)

    def _index_insert(self, run: RunDirectory, row: dict[str, Any]) -> None:
        """Insert the run's index row (journaled like ``_index_update``)."""
        self._journal(run).write("insert", row["run_id"], row)

    def _journal(self, run: RunDirectory):
        """The run's ``record_index.JournaledIndex`` over this runner's index (imported
        here: the runner's modules import without SQLAlchemy)."""
        from rigctl.record_index import JournaledIndex

        return JournaledIndex(self.index, run.path)

    def catch_up_index(self) -> int:
        """Replay the pending index writes of every run of this rig's records."""
        try:
            from rigctl.record_index import replay_pending

            return replay_pending(self.index, self.config.records_dir())
        except Exception as exc:  # never in a run's way
            log.warning("index catch-up: %s", exc)
            return 0


def close_without_park(rig) -> None:
    """Close every open device without its park policy (a refused resume moves
    nothing)."""
    for kind in reversed(list(rig.devices)):
        device = rig.devices[kind]
        cfg = getattr(device, "cfg", None)
        park = getattr(cfg, "park", None)
        if park is not None:
            device.cfg = cfg.model_copy(update={"park": park.model_copy(
                update={"policy": "hold"})})
        try:
            device.close()
        except Exception as exc:
            log.error("%s: close: %s", kind, exc)
    rig.devices.clear()
