"""Process faults lose nothing (issue 42): the PostgreSQL index stopped mid-run (a real
server, pgserver's embedded PostgreSQL) and a full disk while a capture is written (a
real ENOSPC: the capture's temporary file is a link to /dev/full, which the kernel
answers "No space left on device"; no root, no test hook in rigctl)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import tempfile
from pathlib import Path

import pytest

from rigctl.config import load_rig
from rigctl.record_index import PENDING, RecordIndex, replay_pending
from rigctl.records import RunDirectory
from tests.needs import dev_dependency
from tests.test_runner import SMALL, make_runner
from tests.waiting import wait_until

pgserver = dev_dependency("pgserver")


def _postmaster(data: Path) -> int | None:
    try:
        return int((data / "postmaster.pid").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _alive(pid: int | None) -> bool:
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _stop(data: Path) -> None:
    """Stop the server of ``data`` (fast shutdown, by its PID) and wait until it is gone."""
    pid = _postmaster(data)
    if _alive(pid):
        os.kill(pid, signal.SIGINT)
        wait_until(lambda: not _alive(pid), timeout=30, what="postgres stopped")


@pytest.fixture
def postgres():
    """A PostgreSQL data directory with its server started; ``(data, url)``. Every server
    started on it is stopped by PID at the end."""
    data = Path(tempfile.mkdtemp(prefix="rigctl-pg-"))
    server = pgserver.get_server(data, cleanup_mode=None)
    try:
        yield data, server.get_uri().replace("postgresql://", "postgresql+psycopg://", 1)
    finally:
        try:
            _stop(data)
        finally:
            pid = _postmaster(data)
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
            shutil.rmtree(data, ignore_errors=True)


@pytest.mark.timeout(180)
def test_the_index_away_mid_run_catches_up_when_it_returns(rig_file, postgres):
    data, url = postgres
    path = rig_file()
    path.write_text(path.read_text().replace(
        "records:\n  directory: records\n",
        f'records:\n  directory: records\n  database_url: "{url}"\n'))
    config = load_rig(path)

    def on_event(event):
        if event.get("type") == "step" and event.get("index") == 3:
            _stop(data)  # the database goes away mid-run

    runner, _ = make_runner(config, on_event=on_event)
    outcome = runner.run("head-sweep", SMALL)
    assert outcome.status == "succeeded", outcome.reason  # the run went on
    run = RunDirectory(outcome.run_dir)
    assert len(run.captures()) == 4 and (run.path / "result.json").exists()
    pending = [json.loads(line) for line in (run.path / PENDING).read_text().splitlines()]
    assert pending[-1]["values"]["status"] == "succeeded"

    # the database returns (a new server on the same data: get_server() would hand back
    # its cached handle of the stopped one)
    pgserver.PostgresServer(data.resolve(), cleanup_mode=None)
    index = RecordIndex(url)
    assert index.get(outcome.run_id)["status"] == "running"  # as it last heard
    assert replay_pending(index, config.records_dir()) == 1
    row = RecordIndex(url).get(outcome.run_id)
    assert row["status"] == "succeeded" and row["ended_at"] is not None
    assert row["result_summary"] == json.loads(json.dumps(outcome.result.get("summary",
                                                                            row["result_summary"])))
    assert not (run.path / PENDING).exists()


@pytest.mark.timeout(60)
def test_a_full_disk_fails_the_run_and_leaves_no_half_capture(rig_config):
    full = Path("/dev/full")
    if not full.exists():
        pytest.skip("no /dev/full on this host")
    planted: list[Path] = []

    def on_event(event):
        if event.get("type") == "started":  # the third capture's sidecar goes to /dev/full
            link = rig_config.records_dir() / event["run_id"] / "captures" / "002.json.tmp"
            link.symlink_to(full)
            planted.append(link)

    runner, _ = make_runner(rig_config, on_event=on_event)
    outcome = runner.run("head-sweep", SMALL)
    assert planted
    assert outcome.status == "failed"
    assert "cannot write capture 002" in outcome.reason
    assert "No space left on device" in outcome.reason
    run = RunDirectory(outcome.run_dir)
    assert [c.index for c in run.captures()] == [0, 1]
    left = sorted(p.name for p in run.captures_dir.iterdir() if p.name.startswith("002"))
    assert left == []  # neither the image, nor its sidecar, nor the temporary file
    row = RecordIndex(rig_config.database_url()).get(outcome.run_id)
    assert row["status"] == "failed" and "No space left" in row["reason"]
