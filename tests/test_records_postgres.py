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
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory, run_row, utcnow
from rigctl.runner import solve_recorded
from tests.mockproc import ROOT
from tests.needs import dev_dependency
from tests.test_runner import SMALL, make_runner

pgserver = dev_dependency("pgserver")


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


def _rigctl(*args):
    return subprocess.run([sys.executable, "-m", "rigctl.cli", *args], capture_output=True,
                          text=True, timeout=60, cwd=ROOT)


def _record(config, run_id: str, procedure: str, result: dict, decision: str | None = None):
    """A finished calibration of ``config``'s rig in the shared index (its run directory
    with the result, its row, its decision), as a run would leave it."""
    run = RunDirectory.create(config.records_dir(), run_id)
    run.write_result(result)
    RecordIndex(config.database_url()).insert(run_row(
        config, run_id, procedure, "succeeded", "test", str(run.path.resolve()),
        ended_at=utcnow(), decision=decision))
    return run_id


def _hand_eye(x_mm: float) -> dict:
    T = [[1.0, 0, 0, x_mm / 1000], [0, 1.0, 0, 0], [0, 0, 1.0, 0.05], [0, 0, 0, 1.0]]
    return {"T_flange_cam": T, "T_base_target": T}


CAMERA = {"fy": 905.0, "cx": 640.0, "cy": 360.0, "width": 1280, "height": 720}


@pytest.mark.timeout(120)
def test_each_rig_sees_only_its_own_calibrations_in_a_shared_index(tmp_path, postgres_url):
    """Two rigs with accepted calibrations of their own, far apart, in one PostgreSQL
    index. The records are interleaved so that, for each rig, another rig's accepted
    calibration is the newest in the index: a check that read the index unscoped would
    compare with it (and call a new calibration drift), list it, or show it."""
    from fastapi.testclient import TestClient

    from rigctl.service import RigService, create_app

    rig_a, rig_b = rig(tmp_path, "rig-a", postgres_url), rig(tmp_path, "rig-b", postgres_url)
    own = {"rig-a": set(), "rig-b": set()}

    def record(config, run_id, procedure, result, decision=None):
        own[config.name].add(_record(config, run_id, procedure, result, decision))
        return run_id

    # active-camera: rig-b's accepted one is older than rig-a's; hand-eye: the reverse
    record(rig_b, "b-cam-1", "active-camera", {**CAMERA, "fx": 1200.0}, "accepted")
    record(rig_a, "a-cam-1", "active-camera", {**CAMERA, "fx": 900.0}, "accepted")
    record(rig_a, "a-he-1", "hand-eye", _hand_eye(0.0), "accepted")
    record(rig_b, "b-he-1", "hand-eye", _hand_eye(50.0), "accepted")
    service = {"rig-a": RigService(rig_a), "rig-b": RigService(rig_b)}
    # drift: each new calibration is compared with its own rig's accepted one
    b_new = record(rig_b, "b-cam-2", "active-camera", {**CAMERA, "fx": 1200.1})
    assert service["rig-b"].decide(b_new, "active-camera", {**CAMERA, "fx": 1200.1}) \
        == "pending"
    a_new = record(rig_a, "a-he-2", "hand-eye", _hand_eye(0.5))
    assert service["rig-a"].decide(a_new, "hand-eye", _hand_eye(0.5)) == "pending"
    for config, run_id, against in ((rig_b, b_new, "b-cam-1"), (rig_a, a_new, "a-he-1")):
        decision = RunDirectory(config.records_dir() / run_id).decisions()[-1]
        assert decision["compared_with"] == against and decision["drift"] == []
    # the API of each rig's service: latest, history, runs
    for name, other in (("rig-a", "rig-b"), ("rig-b", "rig-a")):
        with TestClient(create_app(service[name])) as api:
            latest = api.get("/calibrations/latest").json()
            assert {p: r["run_id"] for p, r in latest.items()} == {
                "active-camera": f"{name[-1]}-cam-1", "hand-eye": f"{name[-1]}-he-1"}
            history = api.get("/calibrations/history").json()
            assert {r["run_id"] for r in history} == own[name]
            assert {r["run_id"] for r in api.get("/runs").json()} == own[name]
            for run_id in own[other]:
                assert api.get(f"/runs/{run_id}").status_code == 404
                assert api.post(f"/calibrations/{run_id}/accept").status_code == 404
    # the CLI, given one rig's file: its list, show and export
    rig_file = str(tmp_path / "rig-a.yaml")
    listed = _rigctl("runs", "list", "--rig", rig_file, "--json")
    assert {r["run_id"] for r in json.loads(listed.stdout)} == own["rig-a"]
    shown = _rigctl("runs", "show", "a-cam-1", "--rig", rig_file, "--json")
    assert json.loads(shown.stdout)["result"]["fx"] == 900.0
    refused = _rigctl("runs", "show", "b-cam-1", "--rig", rig_file, "--json")
    assert refused.returncode == 2
    assert json.loads(refused.stdout)["error"] == \
        "no run with id 'b-cam-1' of rig 'rig-a' in the index"
    # a prefix both rigs' ids share is this rig's run alone
    out = tmp_path / "a-cam.json"
    exported = _rigctl("export", "a-cam", "--rig", rig_file, "--out", str(out))
    assert exported.returncode == 0, exported.stderr
    assert json.loads(out.read_text())["fx"] == 900.0
    other = _rigctl("export", "b-cam-1", "--rig", rig_file, "--out", str(tmp_path / "b.json"))
    assert other.returncode == 1 and "of rig 'rig-a'" in other.stderr
    assert not (tmp_path / "b.json").exists()


def test_unreachable_postgres_names_the_key_and_url(tmp_path):
    url = f"postgresql+psycopg://postgres:@/postgres?host={tmp_path}/nothing-here"
    with pytest.raises(ConfigError) as info:
        RecordIndex(url)
    assert "records.database_url" in str(info.value) and "nothing-here" in str(info.value)
