"""The runner: lock, limits, dry run, abort and cleanup, records, re-solve."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from rigctl.config import load_rig
from rigctl.errors import BusyError, ConfigError, SafetyError
from rigctl.locks import RigLock
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory, utcnow
from rigctl.runner import Runner, solve_recorded
from tests.doubles import DoubleCamera, DoubleHead
from tests.service_stack import LockHolder


def make_runner(config, head=None, **kw):
    built = {}

    def head_factory(cfg):
        built["head"] = head or DoubleHead(cfg)
        return built["head"]

    runner = Runner(config, factories={"head": head_factory, "camera": DoubleCamera},
                    show_progress=False, operator="tester", **kw)
    return runner, built


SMALL = {"pan_deg": [-10, 10], "tilt_deg": [0, 5], "settle_s": 0.0}


def test_run_records_captures_index_and_result(rig_config):
    runner, built = make_runner(rig_config)
    outcome = runner.run("head-sweep", SMALL)
    assert outcome.status == "succeeded", outcome.reason
    run = RunDirectory(outcome.run_dir)
    captures = run.captures()
    assert len(captures) == 4
    first = captures[0].meta
    assert first["head_commanded"]["pan"] == pytest.approx(math.radians(-10))
    assert first["head"]["pan"] == pytest.approx(math.radians(-10), abs=1e-9)
    assert (run.path / "rig.yaml").read_text() == rig_config.source_text
    assert json.loads((run.path / "params.json").read_text())["params"]["pan_deg"] == [-10, 10]
    versions = json.loads((run.path / "versions.json").read_text())
    assert versions["devices"]["head"]["model"] == "double"
    assert "step 5/13: settle" in (run.path / "run.log").read_text()
    assert outcome.result["poses"] == 4
    assert outcome.result["axes"]["pan"]["max_abs_deg"] < 1e-6
    # index row, read back through a fresh engine
    row = RecordIndex(rig_config.database_url()).get(outcome.run_id)
    assert row["status"] == "succeeded" and row["operator"] == "tester"
    assert row["rig_name"] == "test-rig" and row["config_hash"] == rig_config.config_hash()
    assert row["result_summary"]["poses"] == 4
    assert "close" in built["head"].calls


def test_deferred_plots_run_after_the_result_is_recorded_and_cannot_fail_it(rig_config,
                                                                            monkeypatch):
    from rigctl.procedures import head_sweep

    seen = {}
    solve = head_sweep.PROCEDURE.solve

    def solve_with_deferred_work(ctx):
        result = solve(ctx)

        def plot():
            seen["result_on_disk"] = (ctx.run.path / "result.json").exists()
            seen["indexed"] = RecordIndex(rig_config.database_url()).get(
                ctx.run.run_id)["status"]

        def broken_plot():
            raise ValueError("no such colormap")

        ctx.defer("plot", plot)
        ctx.defer("broken plot", broken_plot)
        return result

    monkeypatch.setattr(head_sweep.PROCEDURE, "solve", solve_with_deferred_work)
    runner, _ = make_runner(rig_config)
    outcome = runner.run("head-sweep", SMALL)
    assert outcome.status == "succeeded", outcome.reason
    assert seen == {"result_on_disk": True, "indexed": "succeeded"}
    assert "after_result_s" in outcome.timings_s
    log_text = (RunDirectory(outcome.run_dir).path / "run.log").read_text()
    assert "after the result was recorded: broken plot: ValueError: no such colormap" \
        in log_text
    row = RecordIndex(rig_config.database_url()).get(outcome.run_id)
    assert row["status"] == "succeeded" and row["result_summary"]["poses"] == 4


def test_resolve_offline_keeps_previous_result(rig_config):
    runner, _ = make_runner(rig_config)
    outcome = runner.run("head-sweep", SMALL)
    again = solve_recorded(outcome.run_dir, RecordIndex(rig_config.database_url()))
    assert again == outcome.result
    run_dir = RunDirectory(outcome.run_dir)
    assert (run_dir.path / "result.1.json").exists()
    assert json.loads((run_dir.path / "result.1.json").read_text()) == outcome.result


def test_resolve_reads_relative_paths_against_the_recorded_rig_file(rig_config, tmp_path,
                                                                    monkeypatch):
    """The rig file's relative records directory resolves as it did when the run was
    planned, whatever the current directory, for the run directory and a copy of it;
    a run recorded without its rig file's place resolves against its own directory."""
    from rigctl.procedures import head_sweep

    outcome = make_runner(rig_config)[0].run("head-sweep", SMALL)
    params = json.loads((RunDirectory(outcome.run_dir).path / "params.json").read_text())
    assert params["rig_file"] == str(rig_config.source_path)
    seen = []
    solve = head_sweep.PROCEDURE.solve

    def solve_noting_the_records(ctx):
        seen.append(ctx.config.records_dir())
        return solve(ctx)

    monkeypatch.setattr(head_sweep.PROCEDURE, "solve", solve_noting_the_records)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    copy = shutil.copytree(outcome.run_dir, tmp_path / "copies" / outcome.run_id)
    assert solve_recorded(outcome.run_dir) == solve_recorded(copy) == outcome.result
    assert seen == [tmp_path / "records"] * 2
    assert rig_config.records_dir() == tmp_path / "records"
    del params["rig_file"]
    (copy / "params.json").write_text(json.dumps(params))
    assert solve_recorded(copy) == outcome.result
    assert seen[-1] == copy / "records"


def test_limit_violation_refused_before_any_device_is_touched(rig_config):
    runner, built = make_runner(rig_config)
    with pytest.raises(SafetyError) as info:
        runner.run("head-sweep", {"pan_deg": [0, 45], "tilt_deg": [0]})
    assert "head.pan: target 45.00 deg outside soft limits [-30.0, 30.0] deg" in str(info.value)
    assert "step 4" in str(info.value)
    assert built == {}  # no driver was even built
    assert RecordIndex(rig_config.database_url()).list() == []


def test_dry_run_touches_no_device_and_reports_violations(rig_config):
    runner, built = make_runner(rig_config)
    plan = runner.dry_run("head-sweep", {"pan_deg": [0, 45], "tilt_deg": [-25, 0]})
    assert built == {}
    assert len(plan.steps) == 2 * 2 * 3 + 1
    assert len(plan.violations) == 3  # (0,-25) (45,-25) (45,0)
    assert plan.as_dict()["limits_ok"] is False


def test_bad_parameter_names_the_parameter(rig_config):
    runner, _ = make_runner(rig_config)
    with pytest.raises(ConfigError, match=r"head-sweep: param pan_dgr: unknown parameter"):
        runner.run("head-sweep", {"pan_dgr": [1]})
    with pytest.raises(ConfigError, match=r"unknown procedure 'nope'"):
        runner.run("nope", {})


def test_second_run_on_same_rig_is_refused_naming_the_holder(rig_config, tmp_path):
    # Hold the lock from another process, as a concurrent CLI run would, until released
    # (not for a number of seconds that a slow test could outlast).
    lock_dir = rig_config.records_dir() / "locks"
    with LockHolder(lock_dir, "test-rig", "run-X") as holder:
        runner, built = make_runner(rig_config)
        with pytest.raises(BusyError) as info:
            runner.run("head-sweep", SMALL)
        assert str(info.value) == \
            f"rig 'test-rig' busy, held by run run-X (pid {holder.proc.pid})"
        assert built == {}
    # released when the holder dies
    lock = RigLock(lock_dir, "test-rig")
    lock.acquire("after")
    lock.release()


def test_abort_mid_move_stops_closes_and_keeps_captures(rig_config):
    """The runner's part of an abort: stop, then close, every device it opened (what a
    real driver's close does, its park policy, is checked with the real head driver in
    tests/test_park.py)."""
    slow = {"pan_deg": [-20, 20], "tilt_deg": [0], "settle_s": 0.0}
    # the second move stands half-way (latched) until the runner stops the head
    built_head = DoubleHead(rig_config.devices.head, hold_on_move=2)
    runner, _built = make_runner(rig_config, head=built_head)
    result = {}
    thread = threading.Thread(target=lambda: result.update(o=runner.run("head-sweep", slow)))
    thread.start()
    try:  # first move done, capture taken, second move held under way
        assert built_head.held.wait(30), "the second move never got under way"
    finally:
        runner.abort("operator pressed abort")
        thread.join(timeout=30)
    outcome = result["o"]
    assert outcome.status == "aborted"
    assert outcome.reason == "operator pressed abort"
    calls = [c for c in built_head.calls if not c.startswith("park:")]  # the double's own
    assert calls == ["open", "move:-20.0,0.0", "move:20.0,0.0", "stop", "close"]
    assert len(RunDirectory(outcome.run_dir).captures()) == 1
    assert not (RunDirectory(outcome.run_dir).path / "result.json").exists()
    row = RecordIndex(rig_config.database_url()).get(outcome.run_id)
    assert row["status"] == "aborted" and row["reason"] == "operator pressed abort"
    # the lock is free again
    assert runner.run("head-sweep", SMALL).status == "succeeded"


def test_device_fault_fails_run_with_reason_and_captures_intact(rig_config):
    head = DoubleHead(rig_config.devices.head, fail_on_move=3)
    runner, _ = make_runner(rig_config, head=head)
    outcome = runner.run("head-sweep", SMALL)
    assert outcome.status == "failed"
    assert outcome.reason == "DeviceError: head servo 2 (tilt): overload, torque off"
    assert len(RunDirectory(outcome.run_dir).captures()) == 2
    # stopped, then closed (the real drivers' park on close: tests/test_park.py)
    calls = [c for c in head.calls if not c.startswith("park:")]
    assert calls[-2:] == ["stop", "close"]


def test_run_left_running_by_killed_process_shows_interrupted(rig_config):
    index = RecordIndex(rig_config.database_url())
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    import socket

    index.insert({"run_id": "dead-run", "procedure": "head-sweep", "status": "running",
                  "started_at": utcnow(), "rig_name": "test-rig", "config_hash": "x",
                  "run_dir": "/nowhere", "host": socket.gethostname(), "pid": proc.pid})
    index.insert({"run_id": "live-run", "procedure": "head-sweep", "status": "running",
                  "started_at": utcnow(), "rig_name": "test-rig", "config_hash": "x",
                  "run_dir": "/nowhere", "host": socket.gethostname(), "pid": os.getpid()})
    rows = {r["run_id"]: r for r in RecordIndex(rig_config.database_url()).list()}
    assert rows["dead-run"]["status"] == "interrupted"
    assert "ended without closing" in rows["dead-run"]["reason"]
    assert rows["live-run"]["status"] == "running"


def test_camera_capture_written_as_png_with_settings(rig_file):
    config = load_rig(rig_file(camera=True))
    runner, _ = make_runner(config)
    outcome = runner.run("head-sweep", {**SMALL, "image": True})
    captures = RunDirectory(outcome.run_dir).captures()
    image = captures[0].load_image()
    assert image.shape == (48, 64)
    assert captures[0].meta["camera"]["settings"] == {"fourcc": "MJPG"}


class ReplayCamera(DoubleCamera):
    """Delivers the given images in turn (a drained backlog replays old views)."""

    def __init__(self, cfg, images) -> None:
        super().__init__(cfg)
        self.images, self.calls = list(images), 0

    def capture(self, not_before=None):
        from rigctl.drivers.base import Frame

        self.calls += 1
        return Frame(self.images.pop(0), time.time(), self.calls, {})


def test_a_stale_view_after_a_motion_is_captured_again(rig_file, caplog):
    import numpy as np

    config = load_rig(rig_file(camera=True))
    runner, _ = make_runner(config)
    rng = np.random.default_rng(0)
    old, new = (rng.integers(0, 255, (48, 64), dtype=np.uint8) for _ in range(2))
    noisy_old = np.clip(old + rng.normal(0, 2, old.shape), 0, 255).astype(np.uint8)
    camera = ReplayCamera(config.devices.camera, [old, noisy_old, old, new, new])
    state = {"last_motion_end": time.time(), "head_commanded": {"pan": 0.0},
             "arm_commanded": None}
    assert runner._fresh_frame(camera, state).image is old
    state["head_commanded"] = {"pan": 0.1}  # moved: the old view twice is stale
    assert runner._fresh_frame(camera, state).image is new and camera.calls == 4
    assert "stale frame" in caplog.text
    camera.calls = 0  # not moved since: the same view is what it should be
    assert runner._fresh_frame(camera, state).image is new and camera.calls == 1


def test_a_small_move_of_a_sparse_view_is_not_taken_for_a_stale_frame(rig_file, caplog):
    """The arm's small SHIFT moves thin contours by a few pixels: a mean change under
    ``still_threshold`` but clear changes in some cells; captured once, no retry."""
    from tests.test_camera_still import sparse_scene

    config = load_rig(rig_file(camera=True))
    runner, _ = make_runner(config)
    rng = np.random.default_rng(1)
    before, shifted = sparse_scene(rng), sparse_scene(rng, shift=8)
    camera = ReplayCamera(config.devices.camera, [before, shifted])
    state = {"last_motion_end": time.time(), "head_commanded": {"pan": 0.0},
             "arm_commanded": None}
    assert runner._fresh_frame(camera, state).image is before
    state["arm_commanded"] = {"kind": "MoveArmLinear"}  # the SHIFT
    assert runner._fresh_frame(camera, state).image is shifted and camera.calls == 2
    assert "stale frame" not in caplog.text
