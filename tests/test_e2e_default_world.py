"""End to end on the simulated rig (default world: distortion, 0.5 px noise, 0.3 deg
roll-axis tilt, mm-level arm errors), through the CLI and the real clients: active-camera,
then hand-eye, robot-kinematics and validate-arm on the same rig; every result is checked
against the world's truth, which the solvers never see.

The rig and its active-camera run are shared by the module (``camera_run``): the run is
made the first time a test asks for it, so each test also runs alone (``-k``), and the
chain costs one active-camera run instead of two."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from rigctl.bench.truth import model_against_truth
from rigctl.calib import robot
from rigctl.config import load_rig
from rigctl.geometry.kinematics import nominal_ur
from rigctl.mocks.ur_primary import VERSION as UR_VERSION
from rigctl.mocks.world import load_world
from rigctl.simrig import SimulatedRig
from tests.mockproc import ROOT
from tests.resolve_check import assert_resolves_alone

# one worker runs the module, so its rig and active-camera run are made once
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("e2e-default-world"),
              pytest.mark.heavy]


def rigctl(*args, timeout=1200):  # a hang guard, not a timing claim
    return subprocess.run([sys.executable, "-m", "rigctl.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


@dataclass
class CameraRun:
    rig: SimulatedRig
    records: Path
    result: subprocess.CompletedProcess


@pytest.fixture(scope="module")
def camera_run(tmp_path_factory):
    """The default world's simulated rig with one active-camera run (its default plan) on
    it; stopped with its stand-ins, by PID, after the module's last test."""
    base = tmp_path_factory.mktemp("default-rig")
    rig = SimulatedRig("default", records=base / "records", rig_out=base / "sim-rig.yaml",
                       log=base / "sim-up.log")
    try:
        result = rigctl("run", "active-camera", "--rig", str(rig.rig_path), "--json")
        yield CameraRun(rig, base / "records", result)
    finally:
        orphans = rig.stop()
        assert not orphans, f"stand-ins {orphans} outlived `sim up`"
        assert not rig.crash, rig.crash


@pytest.mark.timeout(600)
def test_active_camera_on_default_world(camera_run):
    result = camera_run.result
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout)  # stdout is JSON and nothing else
    truth = load_world(ROOT / "rigctl/mocks/worlds/default.yaml").truth()
    assert abs(out["fx"] / truth["fx"] - 1) < 0.0005
    assert abs(out["fy"] / truth["fy"] - 1) < 0.0005
    assert abs(out["cx"] - truth["cx"]) < 1.2 and abs(out["cy"] - truth["cy"]) < 1.2
    assert set(out["strategies"]) >= {"A", "B", "C", "D", "refined"}
    assert "fx" in out["strategies"]["D"] and out["sigma"]["fx"] > 0
    # the 0.3 deg roll-axis tilt shows in the recovered roll axis (about -sin(0.3 deg) in y)
    assert out["roll_axis_in_cam"][1] == pytest.approx(truth["roll_axis_in_cam"][1], abs=2e-3)
    run_dirs = list((camera_run.records).glob("*active-camera*"))
    assert len(run_dirs) == 1
    for name in ("camera.opencv.yaml", "camera_info.yaml", "plots/contours.png",
                 "plots/residuals.png", "result.json"):
        assert (run_dirs[0] / name).exists(), name
    # the reference, pan/tilt +-3, +-8, +-12, +-16, +-20 and +-25 deg, seven rolls (every
    # 45 deg), and one capture after the arm moved the camera 10 mm sideways
    assert len(list(Path(run_dirs[0], "captures").glob("*.png"))) == 33
    # every capture's edge map was taken while the head moved on (the re-solve in
    # test_robot_kinematics_end_to_end takes them from the PNGs, to the same result)
    log_text = (run_dirs[0] / "run.log").read_text()
    assert "active-camera: 33 of 33 captures' edge maps taken while the rig moved" in \
        log_text
    # and the stages up to the rolls while the head rolled, which the solve used (the
    # re-solve takes them itself, to the same result)
    assert "the stages up to the rolls taken while the rig rolls" in log_text
    assert "are not used" not in log_text
    assert "while moving: tracking: wide" in log_text  # the solve's stages, in the log
    # each tier of rolls tracked as its captures came in, the last with the last capture
    assert "roll tiers tracked while the rig rolls: 4 of 4" in log_text
    assert "while moving: tracking: rolls_-180" in log_text
    # the wait for that work after the motion is the solve's time, and named in its stages
    assert "solve stages: waiting for the work while moving" in log_text
    # the whole solve went on from the last capture, while the head went home, and the
    # solve used it (the re-solve, from scratch, gives the same result)
    assert "solved from the last capture on, while the rig made its last moves" in log_text
    assert "after the last capture: strategies A-D" in log_text
    depths = out["tracking"]["scene_depth"]
    assert depths["contours_measured"] >= 6
    assert np.linalg.norm(depths["move_in_camera_mm"]) == pytest.approx(10.0, rel=0.01)
    # the scene (2-6 m in this world) at the depths the world placed it
    assert 1.5 < depths["depth_m"]["min"] < depths["depth_m"]["max"] < 8.0
    # this world's camera sits on the head's axes: the estimated offset says so
    parallax = out["parallax"]
    assert parallax["estimated"]
    for got, sigma in zip(parallax["centre_offset_mm"], parallax["sigma_mm"], strict=True):
        assert abs(got) < max(3 * sigma, 0.3)
    for key in ("fx", "fy", "cx", "cy"):
        assert abs(out[key] - truth[key]) < max(3 * out["sigma"][key], 0.2), key
    # the full covariance is kept, and the reported sigma is its diagonal
    cov = out["covariance"]
    matrix = np.array(cov["matrix"])
    assert matrix.shape == (len(cov["names"]),) * 2 and np.allclose(matrix, matrix.T)
    for key in ("fx", "fy", "cx", "cy"):
        i = cov["names"].index(key)
        assert math.sqrt(matrix[i, i]) == pytest.approx(out["sigma"][key], rel=1e-9)


@pytest.mark.timeout(900)  # a hang guard: five runs on the simulated rig, ~2 min idle
def test_robot_kinematics_end_to_end(tmp_path, camera_run):
    rig, records = camera_run.rig, camera_run.records
    assert camera_run.result.returncode == 0, camera_run.result.stderr[-2000:]
    handeye = rigctl("run", "hand-eye", "--rig", str(rig.rig_path), "--json",
                     "--param", "poses=8")
    result = rigctl("run", "robot-kinematics", "--rig", str(rig.rig_path), "--json",
                    "--param", "random_poses=12", "--param", "heldout_poses=5",
                    "--param", "sweep_steps=3")
    validate = rigctl("run", "validate-arm", "--rig", str(rig.rig_path), "--json",
                      "--param", "poses=5")
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout)
    for key in ("convention", "units", "links", "T_base_link0", "T_flange_cam",
                "T_base_target", "uncertainty", "heldout"):
        assert key in out, key
    # the camera is free in the final bundle adjustment, the active-camera run its prior
    assert out["intrinsics_prior"]["source"].startswith("run ")
    assert out["intrinsics"]["source"].startswith("robot-kinematics joint refinement")
    summary = out["summary"]
    assert summary["heldout_mm_before"] > 1.5          # several mm before ...
    assert summary["heldout_mm_after"] <= 0.5          # ... at most 0.5 mm after
    # each joint swept from the view that keeps the board in sight longest: the single
    # methods alone beat the nominal model (with one common base they did not: 7-15 mm)
    assert summary["heldout_mm_axis_based"] < 0.5 * summary["heldout_mm_before"]
    assert summary["heldout_mm_link_by_link"] < summary["heldout_mm_before"]
    # the controller's factory model lies between nominal and the truth in this world
    # (rigctl/mocks/worlds/default.yaml): the calibration improves on it, not only on nominal
    assert summary["heldout_mm_after"] < summary["heldout_mm_factory"] \
        < summary["heldout_mm_before"]
    # ... and it was a start of the joint refinement; the summary names the one that won
    starts = summary["refinement_starts_rms_px"]
    assert "controller" in starts and summary["refinement_start"] == robot.first_of_least(starts)
    # D-optimal training views: Schroer's guideline (below 100) for the link parameters
    assert 1 < out["uncertainty"]["condition_number_kinematic"] < 100
    assert min(out["uncertainty"]["plain_dh_smallest_singular_values"]) < 1e-3

    # the independent intrinsics check (Zhang on the same board views) against the truth
    world = load_world(ROOT / "rigctl/mocks/worlds/default.yaml")
    truth = world.truth()
    check = out["intrinsics_check"]
    assert check["views"] >= 20 and abs(check["board"]["fx"] / truth["fx"] - 1) < 0.003
    for key in ("cx", "cy"):
        assert abs(check["board"][key] - truth[key]) < max(3 * check["sigma"][key], 1.0)

    # the camera model the arm model was fitted with, against the truth, within its sigma
    used = out["intrinsics"]
    assert abs(used["fx"] / truth["fx"] - 1) < 0.002
    for key in ("fx", "fy", "cx", "cy"):
        assert abs(used[key] - truth[key]) < max(3 * used["sigma"][key], 0.5), key

    # The exported model against the truth, over views the calibration never saw
    rms, _, count = model_against_truth(out, load_rig(rig.rig_path), world)
    assert count > 60 and rms < 0.5
    # validate-arm on new views, with the calibration just recorded
    assert validate.returncode == 0, validate.stderr[-3000:]
    check = json.loads(validate.stdout)
    before, after = check["before"], check["after"]
    assert check["views"] >= 4
    assert after["position_rms_mm"] < 0.5 * before["position_rms_mm"]
    assert after["target_in_camera_rms_mm"] < 0.5 < before["target_in_camera_rms_mm"]
    # the predicted board lands on the detected corners to their own noise (~0.2 px)
    assert after["reprojection_rms_px"] < 0.4 < 1.0 < before["reprojection_rms_px"]
    # hand-eye against the true T_flange_cam: it works on the nominal arm, whose link errors
    # (mm and tenths of a degree in this world) it absorbs, about 0.9 deg here; a frame
    # or convention slip would be tens of degrees or centimetres off
    assert handeye.returncode == 0, handeye.stderr[-3000:]
    X = np.array(json.loads(handeye.stdout)["T_flange_cam"])
    X_true = np.array(truth["T_flange_cam"])
    assert np.linalg.norm(X[:3, 3] - X_true[:3, 3]) < 0.005  # m
    cos = (np.trace(X[:3, :3].T @ X_true[:3, :3]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 2.0
    # each solve is a function of its run directory alone
    for procedure in ("active-camera", "hand-eye", "robot-kinematics", "validate-arm"):
        recorded = next(records.glob(f"*-{procedure}-*"))
        assert_resolves_alone(recorded, tmp_path / "elsewhere")
    # exports
    run_dir = next(records.glob("*robot-kinematics*"))
    # the controller's version and kinematics hash, in the run's versions.json and in
    # the results the drift check compares; the views were planned with its model
    arm = json.loads((run_dir / "versions.json").read_text())["devices"]["arm"]
    assert arm["controller"] == ".".join(str(v) for v in UR_VERSION)
    assert arm["kinematics_hash"].startswith("calib_")
    assert arm["controller_kinematics"]["hash"] == arm["kinematics_hash"]
    assert out["robot_hash"] == arm["kinematics_hash"]
    assert json.loads(handeye.stdout)["robot_hash"] == arm["kinematics_hash"]
    planned = json.loads((run_dir / "inputs.json").read_text())["arm_model"]
    assert planned["source"] == "controller" and planned["robot_hash"] == arm["kinematics_hash"]
    assert out["planned_with"]["source"] == "controller"
    assert check["calibration_run"] == run_dir.name
    assert rigctl("export", str(run_dir), "--format", "json").returncode == 0
    exported = json.loads((run_dir / "export.json").read_text())
    assert "summary" not in exported
    config = load_rig(rig.rig_path)
    rms, _, _ = model_against_truth(exported, config, world)  # the file, against the truth
    assert rms < 0.5
    assert rigctl("export", str(run_dir), "--format", "ur").returncode == 0
    ur = yaml.safe_load((run_dir / "export.ur_calibration.yaml").read_text())
    # nominal + the exported deltas is the calibrated arm: rebuilt, it meets the truth
    nominal = nominal_ur(ur["model"])
    links = [{"theta_offset": ur["delta_theta"][i], "d": nominal.d[i] + ur["delta_d"][i],
              "a": nominal.a[i] + ur["delta_a"][i],
              "alpha": nominal.alpha[i] + ur["delta_alpha"][i], "beta": ur["beta"][i]}
             for i in range(6)]
    rebuilt, _, _ = model_against_truth({**exported, "links": links}, config, world)
    assert rebuilt == pytest.approx(rms, abs=1e-6) and rebuilt < 0.5
