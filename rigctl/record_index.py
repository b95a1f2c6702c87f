"""The SQL index of runs (SQLAlchemy; SQLite by default, PostgreSQL by URL).

One row per run, written when the run starts (status ``running``) and updated when it
ends; a ``running`` row whose process is gone is shown as ``interrupted``. The run
directories themselves (``rigctl.records``) hold everything a solve reads: the index only
finds runs. It is a module of its own so that a command that never opens the index (a
re-solve of a copied run directory, ``rigctl sim``, the stand-ins) does not import
SQLAlchemy (about 0.3 s of a process's start on this project's 2-core machine).

``JournaledIndex`` keeps a run's writes when the database is away, in the run directory,
and replays them when it is back.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import socket
from pathlib import Path
from typing import Any

from sqlalchemy import (
    JSON,
    Column,
    DateTime,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    create_engine,
    select,
    update,
)

from rigctl.errors import ConfigError, RigError
from rigctl.records import to_jsonable

metadata = MetaData()

runs_table = Table(
    "runs",
    metadata,
    Column("run_id", String(64), primary_key=True),
    Column("procedure", String(64), nullable=False, index=True),
    Column("status", String(16), nullable=False, index=True),
    Column("reason", Text, nullable=True),
    Column("started_at", DateTime(timezone=True), nullable=False),
    Column("ended_at", DateTime(timezone=True), nullable=True),
    Column("operator", String(64), nullable=True),
    Column("rig_name", String(64), nullable=False, index=True),
    Column("config_hash", String(32), nullable=False),
    Column("result_summary", JSON, nullable=True),
    Column("run_dir", Text, nullable=False),
    Column("host", String(128), nullable=False),
    Column("pid", Integer, nullable=False),
    Column("decision", String(16), nullable=True),  # accepted | rejected | drift | pending
)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class RecordIndex:
    """The SQL index of runs (SQLAlchemy; SQLite by default, PostgreSQL by URL)."""

    def __init__(self, url: str) -> None:
        if url.startswith("sqlite:///"):
            Path(url[len("sqlite:///"):]).parent.mkdir(parents=True, exist_ok=True)
        try:
            self.engine = create_engine(url, future=True)
            metadata.create_all(self.engine)
        except Exception as exc:  # SQLAlchemy raises many driver-specific types
            raise ConfigError(f"records.database_url: cannot open {url!r}: {exc}") from None

    def insert(self, row: dict[str, Any]) -> None:
        with self.engine.begin() as conn:
            conn.execute(runs_table.insert().values(**row))

    def update(self, run_id: str, **values: Any) -> None:
        with self.engine.begin() as conn:
            conn.execute(update(runs_table).where(runs_table.c.run_id == run_id).values(**values))

    def _refresh_interrupted(self, rows: list[dict]) -> list[dict]:
        host = socket.gethostname()
        for row in rows:
            if row["status"] in ("running", "paused") and row["host"] == host \
                    and not _pid_alive(row["pid"]):
                reason = f"process {row['pid']} ended without closing the run"
                self.update(row["run_id"], status="interrupted", reason=reason)
                row["status"], row["reason"] = "interrupted", reason
        return rows

    def list(self, limit: int = 50, procedure: str | None = None,
             rig_name: str | None = None) -> list[dict[str, Any]]:
        query = select(runs_table).order_by(runs_table.c.started_at.desc()).limit(limit)
        if procedure:
            query = query.where(runs_table.c.procedure == procedure)
        if rig_name:
            query = query.where(runs_table.c.rig_name == rig_name)
        with self.engine.connect() as conn:
            rows = [dict(r._mapping) for r in conn.execute(query)]
        return self._refresh_interrupted(rows)

    def latest(self, procedure: str, rig_name: str | None = None) -> dict[str, Any] | None:
        """The latest accepted run of ``procedure``; failing that, the latest succeeded one
        not rejected."""
        query = select(runs_table).where(runs_table.c.procedure == procedure,
                                         runs_table.c.status == "succeeded")
        if rig_name:
            query = query.where(runs_table.c.rig_name == rig_name)
        query = query.order_by(runs_table.c.started_at.desc())
        with self.engine.connect() as conn:
            rows = [dict(r._mapping) for r in conn.execute(query)]
        accepted = [r for r in rows if r["decision"] == "accepted"]
        if accepted:
            return accepted[0]
        usable = [r for r in rows if r["decision"] not in ("rejected", "drift")]
        return usable[0] if usable else None

    def get(self, run_id: str, rig_name: str | None = None) -> dict[str, Any]:
        """The run with this id, or with this unique id prefix; with ``rig_name``, only
        that rig's runs are looked at (an index may be shared by several rigs)."""
        query = select(runs_table).where(runs_table.c.run_id.startswith(run_id,
                                                                        autoescape=True))
        if rig_name:
            query = query.where(runs_table.c.rig_name == rig_name)
        with self.engine.connect() as conn:
            rows = [dict(r._mapping) for r in conn.execute(query)]
        exact = [r for r in rows if r["run_id"] == run_id]
        rows = exact or rows  # a whole id wins over the longer ids it is a prefix of
        if not rows:
            of_rig = f" of rig {rig_name!r}" if rig_name else ""
            raise RigError(f"no run with id {run_id!r}{of_rig} in the index")
        if len(rows) > 1:
            raise RigError(f"run id prefix {run_id!r} is ambiguous ({len(rows)} runs)")
        return self._refresh_interrupted(rows)[0]


PENDING = "index-pending.jsonl"  # index writes a run could not make (database away)


def _encode(values: dict[str, Any]) -> dict[str, Any]:
    return {k: {"datetime": v.isoformat()} if isinstance(v, dt.datetime) else to_jsonable(v)
            for k, v in values.items()}


def _decode(values: dict[str, Any]) -> dict[str, Any]:
    return {k: dt.datetime.fromisoformat(v["datetime"])
            if isinstance(v, dict) and set(v) == {"datetime"} else v
            for k, v in values.items()}


class JournaledIndex:
    """A run's writes to the index that outlive the database being away: a write that
    fails is appended to the run directory's ``index-pending.jsonl`` and the run goes
    on; the pending writes are replayed, in order, before the next write and whenever
    ``replay_pending`` is called (``rigctl runs list``, the service), so the index
    catches up when the database returns."""

    def __init__(self, index: RecordIndex, run_dir: Path) -> None:
        self.index, self.pending = index, Path(run_dir) / PENDING

    def write(self, op: str, run_id: str, values: dict[str, Any]) -> bool:
        """``op`` (insert: ``values`` is the row; update) now, after the pending ones;
        False (and journaled) when the database cannot be reached."""
        if self.replay() and self._apply(op, run_id, values):
            return True
        with open(self.pending, "a", encoding="utf-8") as f:
            f.write(json.dumps({"op": op, "run_id": run_id, "values": _encode(values)})
                    + "\n")
            f.flush()
            os.fsync(f.fileno())
        return False

    def _apply(self, op: str, run_id: str, values: dict[str, Any]) -> bool:
        try:
            if op == "insert":
                self.index.insert(values)
            else:
                self.index.update(run_id, **values)
        except Exception as exc:  # the driver's own errors: the database is away
            import logging

            logging.getLogger("rigctl.records").warning(
                "index unreachable, %s of run %s kept in %s: %s", op, run_id, self.pending,
                str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
            return False
        return True

    def replay(self) -> bool:
        """Apply the pending writes; True once none is left."""
        if not self.pending.exists():
            return True
        lines = [json.loads(line) for line in self.pending.read_text().splitlines()
                 if line.strip()]
        for k, entry in enumerate(lines):
            values = _decode(entry["values"])
            if entry["op"] == "insert" and self._exists(entry["run_id"]):
                continue  # an insert that reached the database before its answer was lost
            if not self._apply(entry["op"], entry["run_id"], values):
                rest = "".join(json.dumps(e) + "\n" for e in lines[k:])
                tmp = self.pending.with_suffix(".tmp")
                tmp.write_text(rest)
                os.replace(tmp, self.pending)
                return False
        self.pending.unlink()
        return True

    def _exists(self, run_id: str) -> bool:
        try:
            self.index.get(run_id)
        except Exception:  # not there, or the database away again
            return False
        return True


def replay_pending(index: RecordIndex, records_dir: Path) -> int:
    """Replay every run's pending index writes under ``records_dir``; how many runs
    caught up."""
    done = 0
    for pending in sorted(Path(records_dir).glob(f"*/{PENDING}")):
        done += JournaledIndex(index, pending.parent).replay()
    return done
