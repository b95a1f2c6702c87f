"""The command line, run as a real subprocess: --json output, errors, exit codes."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from rigctl import __version__
from rigctl.errors import RigError
from rigctl.exports import export_result
from rigctl.mocks.sim import STAND_IN_TIMING
from tests.conftest import ROOT
from tests.mockproc import MockProcess


def rigctl(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "rigctl.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


def test_version():
    """The version from git (setuptools-scm), one PEP 440 version."""
    result = rigctl("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"rigctl {__version__}"
    assert re.fullmatch(r"\d+(\.\d+)*(\.dev\d+)?(\+[a-z0-9.]+)?", __version__), __version__


def test_dry_run_json_is_only_json_and_touches_nothing(rig_file):
    path = rig_file()
    result = rigctl("run", "head-sweep", "--rig", str(path), "--dry-run", "--json",
                    "--param", "pan_deg=[0, 10]", "--param", "tilt_deg=[0]")
    assert result.returncode == 0, result.stderr
    plan = json.loads(result.stdout)
    assert plan["limits_ok"] is True and len(plan["steps"]) == 7
    assert plan["steps"][0]["description"] == "head -> pan +0.00, tilt +0.00, roll +0.00 deg"
    assert not (path.parent / "records" / "locks").exists()  # no run was started


def test_dry_run_reports_limit_violation_with_exit_2(rig_file):
    result = rigctl("run", "head-sweep", "--rig", str(rig_file()), "--dry-run",
                    "--param", "pan_deg=[40]")
    assert result.returncode == 2
    assert "head.pan: target 40.00 deg outside soft limits [-30.0, 30.0] deg" in result.stderr


def test_bad_rig_file_error_names_file_and_key(tmp_path):
    bad = tmp_path / "rig.yaml"
    bad.write_text("devices:\n  head:\n    port: /dev/x\n    limits: {pan: [-90, 200]}\n")
    result = rigctl("run", "head-sweep", "--rig", str(bad), "--json")
    assert result.returncode == 2
    assert json.loads(result.stdout) == {
        "error": "rig.yaml: devices.head.limits.pan: max 200 deg exceeds the servo range "
                 "of 180 deg", "type": "ConfigError"}


def test_bad_param_syntax(rig_file):
    result = rigctl("run", "head-sweep", "--rig", str(rig_file()), "--param", "pan_deg")
    assert result.returncode == 2 and "--param 'pan_deg': expected key=value" in result.stderr


@pytest.mark.timeout(300)  # a hang guard: eight CLI processes, two re-solves timed
def test_run_list_show_solve_export_against_stand_in(tmp_path):
    link = tmp_path / "dxl"
    proc = MockProcess(["-m", "rigctl.mocks.dynamixel_bus", "--link", str(link)])
    try:
        rig = tmp_path / "rig.yaml"
        # The stand-in's timing, as `sim up` writes it: the hardware default (34 ms a try)
        # is shorter than a descheduled stand-in process on a busy host.
        head = {"port": str(link), "speed_cap_dps": 180, "accel_cap_dps2": 1000,
                **STAND_IN_TIMING["head"]}
        rig.write_text(yaml.safe_dump({"name": "cli-rig", "devices": {"head": head}}))
        result = rigctl("run", "head-sweep", "--rig", str(rig), "--json",
                        "--param", "pan_deg=[-5, 5]", "--param", "tilt_deg=[0]")
        assert result.returncode == 0, result.stderr + result.stdout
        doc = json.loads(result.stdout)
        assert doc["poses"] == 2
        listed = json.loads(rigctl("runs", "list", "--rig", str(rig), "--json").stdout)
        assert [r["status"] for r in listed] == ["succeeded"]
        run_id = listed[0]["run_id"]
        shown = json.loads(rigctl("runs", "show", run_id[:20], "--rig", str(rig), "--json").stdout)
        assert shown["captures"] == 2 and shown["result"]["poses"] == 2
        resolved = rigctl("solve", shown["run_dir"], "--json")
        assert resolved.returncode == 0 and json.loads(resolved.stdout) == doc
        _time_resolve_reads_the_run_only(Path(shown["run_dir"]))
        exported = rigctl("export", run_id, "--rig", str(rig), "--format", "opencv")
        assert exported.returncode == 1
        assert "has no camera intrinsics to export" in exported.stderr
        doctor = rigctl("doctor", "--rig", str(rig), "--json")
        rows = {r["device"]: r for r in json.loads(doctor.stdout)}
        assert rows["head"]["state"] == "ok" and rows["arm"]["state"] == "missing"
        assert rows["head"]["describe"]["servos"]["2"]["model"] == 1020
        assert rows["head"]["latency_ms"] > 0  # measured; timing belongs to benchmarks
        # a pty has no USB-serial latency timer: nothing to set, and doctor says so
        assert rows["head"]["latency_timer_ms"] is None and rows["head"]["hint"] is None
        assert "no USB-serial latency timer" in rows["head"]["latency_timer_note"]
        # the bus record: every transaction counted, per servo and for the group reads
        stats = rows["head"]["describe"]["bus_stats"]
        assert stats["2"]["transactions"] >= 5 and stats["2"]["errors"] == 0
        assert stats["group"]["transactions"] >= 20
    finally:
        assert proc.stop() == 0


def time_resolve(*args, timeout=300):  # a hang guard, not a timing claim
    return subprocess.run([sys.executable, str(ROOT / "tools" / "time_resolve.py"), *args],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _time_resolve_reads_the_run_only(run_dir: Path) -> None:
    """tools/time_resolve.py re-solves a copy of ``run_dir`` as a whole `rigctl solve`
    process: its summary adds up, and the run directory is left as it was."""
    before = _digests(run_dir)
    timed = time_resolve(str(run_dir), "--runs", "2", "--json")
    assert timed.returncode == 0, timed.stderr[-2000:]
    summary = json.loads(timed.stdout)
    assert summary["run"] == str(run_dir) and len(summary["runs"]) == 2
    for one in summary["runs"]:
        assert one["whole_s"] > 0 and 0 <= one["solve_s"] < one["whole_s"]
        assert one["beyond_s"] == pytest.approx(one["whole_s"] - one["solve_s"])
    beyond = [one["beyond_s"] for one in summary["runs"]]
    assert summary["beyond_median_s"] == pytest.approx(sum(beyond) / 2)
    assert summary["met"] == (summary["beyond_median_s"] <= summary["target_beyond_s"])
    assert sum(line.startswith("run ") for line in timed.stderr.splitlines()) == 2
    assert _digests(run_dir) == before
    refused = time_resolve(str(run_dir.parent))
    assert refused.returncode == 2
    assert f"{run_dir.parent}: not a run directory (no params.json)" in refused.stderr


def test_doctor_says_clearly_what_is_missing(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text(f"devices:\n  head: {{port: {tmp_path / 'no-such-port'}}}\n")
    result = rigctl("doctor", "--rig", str(rig), "--json")
    assert result.returncode == 1
    head = json.loads(result.stdout)[0]
    assert head["state"] == "error" and "cannot open" in head["message"]


RESULT = {"fx": 900.5, "fy": 905.25, "cx": 652.0, "cy": 371.5, "width": 1280, "height": 720,
          "distortion": [-0.1, 0.02, 0.0, 0.0, 0.0]}


def test_opencv_export_reads_back(tmp_path):
    path = export_result(RESULT, "opencv", tmp_path / "cam.yaml", "run-1")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    assert K[0, 0] == 900.5 and K[1, 2] == 371.5
    assert fs.getNode("image_width").real() == 1280
    assert np.allclose(fs.getNode("distortion_coefficients").mat().ravel(), RESULT["distortion"])


def test_ros_camera_info_export(tmp_path):
    doc = yaml.safe_load(export_result(RESULT, "ros", tmp_path / "ci.yaml", "r").read_text())
    assert doc["camera_matrix"]["data"][:3] == [900.5, 0.0, 652.0]
    assert doc["projection_matrix"]["data"][5] == 905.25
    assert doc["distortion_model"] == "plumb_bob" and doc["image_height"] == 720


def test_export_without_intrinsics_is_a_clear_error(tmp_path):
    with pytest.raises(RigError, match="run r: result has no camera intrinsics"):
        export_result({"poses": 3}, "ros", tmp_path / "x.yaml", "r")
