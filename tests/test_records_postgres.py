"""The run index on PostgreSQL: a real server (pgserver's embedded PostgreSQL, reached over
a Unix socket only), shared by two rigs, through SQLAlchemy and psycopg."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest

from rigctl.config import load_rig
from rigctl.errors import ConfigError
from rigctl.records import RecordIndex, RunDirectory
from rigctl.runner import solve_recorded
from tests.mockproc import ROOT
from tests.test_runner import SMALL, make_runner

pgserver = pytest.importorskip("pgserver", reason="the postgres test needs pgserver (dev extra)")


@pytest.fixture
def postgres_url():
    data = Path(tempfile.mkdtemp(prefix="rigctl-pg-"))  # short: Unix socket paths are limited
    server = pgserver.get_server(data, cleanup_mode="stop")
    pid = int((data / "postmaster.pid").read_text().split()[0])
    try:
        listen = (data / "postmaster.pid").read_text().splitlines()[5]
        assert listen.strip() == "", f"postgres listens on {listen!r}; expected the socket only"
        yield server.get_uri().replace("postgresql://", "postgresql+psycopg://", 1)
    finally:
        server.cleanup()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            os.kill(pid, signal.SIGKILL)
        shutil.rmtree(data, ignore_errors=True)


def rig(tmp_path: Path, name: str, url: str):
    path = tmp_path / f"{name}.yaml"
    path.write_text(textwrap.dedent(f"""\
        name: {name}
        records: {{directory: records-{name}, database_url: "{url}"}}
        devices:
          head:
            port: /dev/null
            limits: {{pan: [-30, 30], tilt: [-20, 20], roll: [-180, 180]}}
            park: {{policy: home, angles_deg: [0, 0, 0]}}
            move_timeout_s: 5
        """))
    return load_rig(path)


@pytest.mark.timeout(120)
def test_two_rigs_share_one_postgres_index(tmp_path, postgres_url):
    rig_a, rig_b = rig(tmp_path, "rig-a", postgres_url), rig(tmp_path, "rig-b", postgres_url)
    first_a = make_runner(rig_a)[0].run("head-sweep", SMALL)
    first_b = make_runner(rig_b)[0].run("head-sweep", SMALL)
    second_a = make_runner(rig_a)[0].run("head-sweep", SMALL)
    assert {o.status for o in (first_a, first_b, second_a)} == {"succeeded"}

    index = RecordIndex(postgres_url)  # a fresh engine: what a second host would see
    assert {r["run_id"] for r in index.list()} == {first_a.run_id, first_b.run_id,
                                                    second_a.run_id}
    assert [r["run_id"] for r in index.list(rig_name="rig-a")] == [second_a.run_id,
                                                                   first_a.run_id]
    assert index.latest("head-sweep", rig_name="rig-b")["run_id"] == first_b.run_id
    # a decision on one rig's newest run moves "latest" back, for that rig only
    index.update(second_a.run_id, decision="rejected")
    assert index.latest("head-sweep", rig_name="rig-a")["run_id"] == first_a.run_id
    index.update(first_a.run_id, decision="accepted")
    assert index.latest("head-sweep", rig_name="rig-a")["decision"] == "accepted"
    assert index.latest("head-sweep", rig_name="rig-b")["run_id"] == first_b.run_id
    row = index.get(first_b.run_id)
    assert row["result_summary"]["poses"] == 4 and row["rig_name"] == "rig-b"
    # offline re-solve against the shared index keeps the first result
    again = solve_recorded(first_b.run_dir, index)
    assert again == first_b.result
    assert (RunDirectory(first_b.run_dir).path / "result.1.json").exists()
    # what each rig's service shows: its own runs, history and latest, never the other's
    from fastapi.testclient import TestClient

    from rigctl.service import RigService, create_app

    for config, own, other in ((rig_a, {first_a.run_id, second_a.run_id}, first_b.run_id),
                               (rig_b, {first_b.run_id}, first_a.run_id)):
        with TestClient(create_app(RigService(config))) as api:
            assert {r["run_id"] for r in api.get("/runs").json()} == own
            assert api.get(f"/runs/{other}").status_code == 404
            assert api.get("/rig").json()["last_readings"].get("run_id") in own | {None}
    # and the CLI's list
    listed = subprocess.run([sys.executable, "-m", "rigctl.cli", "runs", "list", "--rig",
                             str(tmp_path / "rig-b.yaml"), "--json"], capture_output=True,
                            text=True, timeout=60, cwd=ROOT)
    assert {r["run_id"] for r in json.loads(listed.stdout)} == {first_b.run_id}


def test_unreachable_postgres_names_the_key_and_url(tmp_path):
    url = f"postgresql+psycopg://postgres:@/postgres?host={tmp_path}/nothing-here"
    with pytest.raises(ConfigError) as info:
        RecordIndex(url)
    assert "records.database_url" in str(info.value) and "nothing-here" in str(info.value)
