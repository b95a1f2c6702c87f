"""Run records: one directory per run, plus an SQL index (SQLite by default).

Layout of a run directory::

    <records>/<run_id>/
        rig.yaml           copy of the rig file as used, its service token redacted
        params.json        procedure, parameters, operator, and where the rig file was
                           (its relative paths resolve against that folder on a re-solve)
        versions.json      software and device versions (``describe()`` of each device),
                           for failed and aborted runs too; rigctl's exact version, its
                           commit and whether its tree was dirty (``software_provenance``)
        run.log            the log
        captures/NNN.png   images, written the moment they are taken
        captures/NNN.json  sidecar: head angles, joint angles, timestamps, camera settings
        result.json        the solve, once there is one
        plots/*.png

The index row is written when the run starts (status ``running``) and updated when it
ends, so a crash never loses a run: a ``running`` row whose process is gone is shown
as ``interrupted``.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import os
import re
import secrets
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
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

if TYPE_CHECKING:
    from rigctl.config import RigConfig

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

def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def new_run_id(procedure: str) -> str:
    stamp = utcnow().strftime("%Y%m%dT%H%M%S")
    return f"{stamp}-{procedure}-{secrets.token_hex(3)}"


def run_row(config: RigConfig, run_id: str, procedure: str, status: str, operator: str,
            run_dir: str = "", **values: Any) -> dict[str, Any]:
    """The index row of a run of ``config``'s rig started now by this process on this
    host; ``values`` adds or overrides columns (``reason``, ``ended_at``, ...)."""
    return {"run_id": run_id, "procedure": procedure, "status": status, "reason": None,
            "started_at": utcnow(), "operator": operator, "rig_name": config.name,
            "config_hash": config.config_hash(), "run_dir": run_dir,
            "host": socket.gethostname(), "pid": os.getpid(), **values}


def to_jsonable(value: Any) -> Any:
    """Turn numpy values and tuples into plain JSON types."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        raise RigError(f"refusing to record a non-finite number ({value})")
    if isinstance(value, Path):
        return str(value)
    return value


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (temp file + rename) so a crash never leaves half a file."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(data), indent=2, sort_keys=False) + "\n")
    os.replace(tmp, path)


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


@dataclass
class Capture:
    """One recorded capture: its index, image path (if any) and sidecar metadata."""

    index: int
    image_path: Path | None
    meta: dict[str, Any]

    def load_image(self) -> np.ndarray:
        import cv2

        if self.image_path is None:
            raise RigError(f"capture {self.index:03d} has no image")
        image = cv2.imread(str(self.image_path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise RigError(f"{self.image_path}: cannot read image")
        return image

    @property
    def board_path(self) -> Path | None:
        return None if self.image_path is None else self.image_path.with_suffix(".board.json")

    def board_detection(self, target):
        """The target's corners in this capture (``rigctl.calib.board.Detection``: id
        order, NaN where not seen; None with a note when not found), from the
        ``NNN.board.json`` the runner wrote for the same target while the rig moved on,
        else detected now."""
        from rigctl.calib.board import Detection, detect_target, target_key

        path = self.board_path
        if path is not None and path.exists():
            saved = json.loads(path.read_text())
            # a run recorded before ChArUco boards: a checkerboard's rows and cols
            key = saved.get("target") or {"type": "checkerboard", "rows": saved.get("rows"),
                                          "cols": saved.get("cols")}
            if key == target_key(target):
                return _saved_detection(saved, target, Detection)
        return detect_target(self.load_image(), target)

    def board_corners(self, target) -> np.ndarray | None:
        """The target's corners in this capture (``board_detection``), None: not found."""
        return self.board_detection(target).corners

    def save_board_corners(self, target, image: np.ndarray | None = None) -> None:
        """Detect the target in this capture and write ``NNN.board.json`` (the corners
        seen with their ids, or the note saying why none are used)."""
        from rigctl.calib.board import detect_target, seen, target_key

        found = detect_target(self.load_image() if image is None else image, target)
        out: dict[str, Any] = {"target": target_key(target), "ids": None, "corners": None,
                               "note": found.note}
        if found.corners is not None:
            mask = seen(found.corners)
            out |= {"ids": np.flatnonzero(mask).tolist(), "corners": found.corners[mask]}
        write_json(self.board_path, out)


def _saved_detection(saved: dict, target, detection):
    """A ``Detection`` from a ``NNN.board.json``: ids and corners (a checkerboard's file
    from before ChArUco boards holds every corner, without ids)."""
    corners = saved.get("corners")
    if corners is None:
        return detection(None, saved.get("note"))
    corners = np.asarray(corners, float).reshape(-1, 2)
    ids = saved.get("ids")
    if ids is None:
        return detection(corners)
    out = np.full(((target.rows - 1) * (target.cols - 1), 2), np.nan)
    out[np.asarray(ids, int)] = corners
    return detection(out)


class RunDirectory:
    """Reads and writes one run directory."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.captures_dir = self.path / "captures"
        self.plots_dir = self.path / "plots"

    @classmethod
    def create(cls, root: Path, run_id: str) -> RunDirectory:
        run = cls(root / run_id)
        run.captures_dir.mkdir(parents=True, exist_ok=False)
        run.plots_dir.mkdir()
        return run

    @property
    def run_id(self) -> str:
        return self.path.name

    def write_capture(self, index: int, image: np.ndarray | None, meta: dict[str, Any]) -> Path:
        """Write ``NNN.png`` (if there is an image), then its ``NNN.json`` sidecar, now.
        Both appear whole (written aside, then renamed): a reader such as the service,
        serving captures during the run, never sees half a file, and a capture is
        complete once its sidecar exists."""
        import cv2

        stem = self.captures_dir / f"{index:03d}"
        tmp = stem.with_suffix(".png.tmp")
        try:
            if image is not None:
                ok, png = cv2.imencode(".png", image)
                if not ok:
                    raise RigError(f"{stem}.png: cannot encode image")
                tmp.write_bytes(png.tobytes())
                os.replace(tmp, stem.with_suffix(".png"))
                meta = {**meta, "image": f"{index:03d}.png"}
            write_json(stem.with_suffix(".json"), meta)
        except OSError as exc:  # a full disk: no half-written file is left as a capture
            for part in (tmp, stem.with_suffix(".json.tmp")):
                with contextlib.suppress(OSError):
                    part.unlink()
            raise RigError(f"{stem}: cannot write capture {index:03d}: "
                           f"{exc.strerror or exc}") from None
        return stem.with_suffix(".json")

    def capture(self, index: int) -> Capture:
        """One capture by index, as written by ``write_capture``."""
        sidecar = self.captures_dir / f"{index:03d}.json"
        meta = json.loads(sidecar.read_text())
        image = self.captures_dir / meta["image"] if meta.get("image") else None
        return Capture(index, image, meta)

    def captures(self) -> list[Capture]:
        out = []
        for sidecar in sorted(self.captures_dir.glob("[0-9][0-9][0-9].json")):
            try:
                meta = json.loads(sidecar.read_text())
            except json.JSONDecodeError as exc:
                raise RigError(f"{sidecar}: corrupt capture sidecar: {exc}") from None
            image = self.captures_dir / meta["image"] if meta.get("image") else None
            out.append(Capture(int(sidecar.stem), image, meta))
        return out

    def read_json(self, name: str) -> Any:
        path = self.path / name
        try:
            return json.loads(path.read_text())
        except FileNotFoundError:
            raise RigError(f"{path}: missing from the run directory") from None
        except json.JSONDecodeError as exc:
            raise RigError(f"{path}: corrupt JSON: {exc}") from None

    def write_result(self, result: dict[str, Any]) -> None:
        """Write ``result.json``; an earlier result is kept as ``result.<n>.json``."""
        target = self.path / "result.json"
        if target.exists():
            n = 1
            while (self.path / f"result.{n}.json").exists():
                n += 1
            os.replace(target, self.path / f"result.{n}.json")
        write_json(target, result)

    def result(self) -> dict[str, Any]:
        return self.read_json("result.json")

    def params(self) -> dict[str, Any]:
        return self.read_json("params.json")

    def append_decision(self, decision: str, by: str, comment: str = "",
                        **extra: Any) -> dict[str, Any]:
        """Append one decision on this calibration (accepted, rejected, drift, pending),
        who made it and why, to ``decisions.jsonl``: the index keeps only the latest
        decision, the run directory keeps them all."""
        entry = {"time": utcnow().isoformat(), "decision": decision, "by": by,
                 "comment": comment, **to_jsonable(extra)}
        with open(self.path / "decisions.jsonl", "a", encoding="utf-8") as f:
            f.write(json.dumps(entry) + "\n")
        return entry

    def decisions(self) -> list[dict[str, Any]]:
        """The decisions on this run, oldest first (empty if none was made); a torn last
        line (a crash while appending) is skipped."""
        path = self.path / "decisions.jsonl"
        if not path.exists():
            return []
        out = []
        for line in path.read_text(encoding="utf-8").splitlines():
            with contextlib.suppress(json.JSONDecodeError):
                out.append(json.loads(line))
        return out

    def versions(self) -> dict[str, Any] | None:
        """``versions.json`` (software and device versions), or None if not written."""
        if not (self.path / "versions.json").exists():
            return None
        return self.read_json("versions.json")


def summarize(result: dict[str, Any]) -> dict[str, Any]:
    """The small subset of a result kept in the index row."""
    summary = result.get("summary")
    if isinstance(summary, dict):
        return to_jsonable(summary)
    keys = ("fx", "fy", "cx", "cy", "rms_px")
    return {k: result[k] for k in keys if k in result}


# -- provenance ------------------------------------------------------------------------

def software_provenance() -> dict[str, Any]:
    """Which rigctl runs: its exact version, the commit it comes from and whether the
    tree had uncommitted changes (``dirty``; None when unknown). From a git checkout (a
    source tree on PYTHONPATH, an editable install) git is asked now; from a wheel,
    ``rigctl/_version.py``, which setuptools-scm wrote from git when the wheel was built."""
    import rigctl

    root = Path(rigctl.__file__).resolve().parent.parent
    return _checkout_provenance(root, rigctl.__version__) or \
        _built_provenance(rigctl.__version__, _built_commit())


def _git(root: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                              timeout=20, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip()


def _checkout_provenance(root: Path, version: str) -> dict[str, Any] | None:
    """None unless ``root`` is rigctl's own git checkout."""
    if not ((root / ".git").exists() and (root / "pyproject.toml").is_file()):
        return None
    commit = _git(root, "rev-parse", "HEAD")
    if not commit:
        return None
    status = _git(root, "status", "--porcelain", "--untracked-files=no")
    try:  # the version a build of this tree would carry (setuptools-scm: the dev extra)
        from setuptools_scm import get_version

        version = get_version(root=str(root), fallback_version=version)
    except Exception:  # not installed, or git metadata it cannot read
        pass
    return {"version": version, "commit": commit,
            "dirty": None if status is None else bool(status), "from": "git checkout"}


def _built_commit() -> str | None:
    """The commit setuptools-scm wrote into ``rigctl/_version.py`` (newer releases)."""
    try:
        from rigctl import _version
    except ImportError:
        return None
    commit = getattr(_version, "commit_id", None)  # git's is written "g<hash>"
    return commit[1:] if commit and re.fullmatch(r"g[0-9a-f]{7,40}", commit) else commit


def _built_provenance(version: str, commit: str | None = None) -> dict[str, Any]:
    """From a build's version (setuptools-scm: a local part that names the commit,
    ``+g<commit>``, and marks a dirty tree with the date, ``.d<yyyymmdd>``) and the
    commit its version file holds, when it holds one."""
    local = version.partition("+")[2]
    parts = local.split(".") if local else []
    if not commit:
        commit = next((p[1:] for p in parts if re.fullmatch(r"g[0-9a-f]{7,40}", p)), None)
    if any(re.fullmatch(r"d\d{8}", p) for p in parts):
        dirty = True
    else:  # clean when the version says where it comes from: a commit, or a bare tag
        dirty = False if commit or not parts else None
    return {"version": version, "commit": commit, "dirty": dirty, "from": "build"}
