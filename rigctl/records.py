"""Run records: one directory per run (the SQL index of runs: ``rigctl.record_index``).

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

The index (``rigctl.record_index``) gets a run's row when the run starts (status
``running``) and updates it when the run ends, so a crash never loses a run: a
``running`` row whose process is gone is shown as ``interrupted``.
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

from rigctl.errors import RigError

if TYPE_CHECKING:
    from rigctl.config import RigConfig


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
