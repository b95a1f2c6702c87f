"""`rigctl export` run as a subprocess, for each format an operator loads elsewhere:
OpenCV FileStorage and ROS camera_info from a camera calibration, the UR ROS 2 driver's
kinematics YAML and a URDF from an arm calibration. Each file is read back (by OpenCV,
PyYAML and yourdfpy) and checked against the recorded result; the arm's forward
kinematics are written out here from the model's definition (rigctl.exports_ur)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from rigctl.config import load_rig
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory, run_row, utcnow
from tests.mockproc import ROOT
from tests.needs import dev_dependency

yourdfpy = dev_dependency("yourdfpy")

CAMERA = {"fx": 912.25, "fy": 908.5, "cx": 641.75, "cy": 362.125, "width": 1280,
          "height": 720, "distortion": [-0.11, 0.035, 0.0004, -0.0002, 0.001]}
KIN_HASH = "calib_7f3e"


def rigctl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rigctl.cli", *args], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)


def Rx(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def Ry(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def Rz(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def Tr(x=0.0, y=0.0, z=0.0):
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def model_fk(result: dict, q) -> np.ndarray:
    """The recorded model: T_base_link0 A_1 ... A_6 with
    A_i = Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)."""
    T = np.array(result["T_base_link0"])
    for qi, lk in zip(q, result["links"], strict=True):
        T = T @ Rz(qi + lk["theta_offset"]) @ Tr(z=lk["d"]) @ Tr(x=lk["a"]) \
            @ Rx(lk["alpha"]) @ Ry(lk["beta"])
    return T


def origin(xyz, rpy) -> np.ndarray:
    """A URDF <origin> / kinematics entry: translate, then fixed-axis roll, pitch, yaw."""
    return Tr(*xyz) @ Rz(rpy[2]) @ Ry(rpy[1]) @ Rx(rpy[0])


def arm_result() -> dict:
    """A robot-kinematics result: a UR5e a few millimetres and tenths of a degree off
    nominal, beta terms included, with its camera and target."""
    rng = np.random.default_rng(38)
    m = nominal_ur("ur5e")
    m.theta_offset = rng.normal(0, 0.002, 6)
    m.d, m.a = m.d + rng.normal(0, 0.002, 6), m.a + rng.normal(0, 0.002, 6)
    m.alpha, m.beta = m.alpha + rng.normal(0, 0.002, 6), rng.normal(0, 0.002, 6)
    T0 = Rz(0.004) @ Ry(-0.003) @ Tr(0.001, -0.002, 0.0015)
    X = Tr(0.012, -0.034, 0.051) @ Rz(0.3) @ Ry(-0.2) @ Rx(2.9)
    W = Tr(0.35, 0.1, 0.0) @ Rx(math.pi)
    return {"convention": "thesis", "units": "m, rad", "arm_model": "ur5e",
            "links": m.links(), "T_base_link0": T0.tolist(), "T_flange_cam": X.tolist(),
            "T_base_target": W.tolist()}


def recorded_run(tmp_path: Path, procedure: str, result: dict, versions: dict | None) -> tuple:
    """A run of ``procedure`` recorded as the runner records one (its directory with
    ``result.json`` and ``versions.json``, its index row), on a rig file of its own."""
    rig = tmp_path / "rig.yaml"
    rig.write_text("name: export-rig\nrecords: {directory: records}\ndevices: {}\n")
    config = load_rig(rig)
    run_id = f"20260101T000000-{procedure}-abc123"
    run = RunDirectory.create(config.records_dir(), run_id)
    run.write_result(result)
    if versions is not None:
        (run.path / "versions.json").write_text(json.dumps(versions))
    index = RecordIndex(config.database_url())
    index.insert(run_row(config, run_id, procedure, "succeeded", "tester", str(run.path)))
    index.update(run_id, ended_at=utcnow())
    return rig, run


@pytest.mark.timeout(240)
def test_opencv_and_ros_exports_from_a_camera_calibration(tmp_path):
    rig, run = recorded_run(tmp_path, "active-camera", CAMERA, None)
    K = np.array([[CAMERA["fx"], 0, CAMERA["cx"]], [0, CAMERA["fy"], CAMERA["cy"]], [0, 0, 1]])
    # by run directory, to the default file beside the result
    done = rigctl("export", str(run.path), "--format", "opencv")
    assert done.returncode == 0, done.stderr
    path = run.path / "export.opencv.yaml"
    assert f"wrote {path}" in done.stderr.replace("\n", "")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert np.array_equal(fs.getNode("camera_matrix").mat(), K)
    assert fs.getNode("distortion_coefficients").mat().ravel().tolist() == CAMERA["distortion"]
    assert (fs.getNode("image_width").real(), fs.getNode("image_height").real()) == (1280, 720)
    assert fs.getNode("run_id").string() == run.run_id
    fs.release()
    # by run id on the rig, to a file named with --out
    out = tmp_path / "camera_info.yaml"
    done = rigctl("export", run.run_id, "--rig", str(rig), "--format", "ros", "--out", str(out))
    assert done.returncode == 0, done.stderr
    doc = yaml.safe_load(out.read_text())
    assert (doc["image_width"], doc["image_height"]) == (1280, 720)
    assert doc["distortion_model"] == "plumb_bob"
    assert np.array_equal(np.reshape(doc["camera_matrix"]["data"], (3, 3)), K)
    assert doc["distortion_coefficients"]["data"] == CAMERA["distortion"]
    assert np.array_equal(np.reshape(doc["projection_matrix"]["data"], (3, 4)),
                          np.hstack([K, np.zeros((3, 1))]))
    assert np.array_equal(np.reshape(doc["rectification_matrix"]["data"], (3, 3)), np.eye(3))
    # a camera calibration has no arm to export: exit 1, saying so
    refused = rigctl("export", str(run.path), "--format", "urdf")
    assert refused.returncode == 1 and "no arm kinematics" in refused.stderr


QS = [np.zeros(6), np.radians([10, -80, 70, -60, -90, 20]),
      np.radians([-135, -30, 120, 45, 60, -170]), np.radians([170, -150, -40, 100, -120, 90])]


@pytest.mark.timeout(240)
def test_ur_kinematics_and_urdf_exports_from_an_arm_calibration(tmp_path):
    result = arm_result()
    versions = {"devices": {"arm": {"kinematics_hash": KIN_HASH}}}
    rig, run = recorded_run(tmp_path, "robot-kinematics", result, versions)
    for q in QS:  # the definition written out here is rigctl's
        assert np.allclose(model_fk(result, q), KinematicModel.from_export(result).fk(q),
                           atol=1e-12)
    done = rigctl("export", run.run_id, "--rig", str(rig), "--format", "ur-kinematics")
    assert done.returncode == 0, done.stderr
    doc = yaml.safe_load((run.path / "export.ur_kinematics.yaml").read_text())["kinematics"]
    assert doc["hash"] == KIN_HASH  # the robot's own: the driver checks it on connect
    names = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
    last = result["links"][5]
    passive_6 = Tr(x=last["a"]) @ Rx(last["alpha"]) @ Ry(last["beta"])
    for q in QS:  # the entries chained about each joint's z reach the flange of the model
        T = np.eye(4)
        for name, qi in zip(names, q, strict=True):
            e = doc[name]
            T = T @ origin([e["x"], e["y"], e["z"]], [e["roll"], e["pitch"], e["yaw"]]) @ Rz(qi)
        assert np.allclose(T @ passive_6, model_fk(result, q), atol=1e-9)
    out = tmp_path / "arm.urdf"
    done = rigctl("export", str(run.path), "--format", "urdf", "--out", str(out))
    assert done.returncode == 0, done.stderr
    robot = yourdfpy.URDF.load(str(out), load_meshes=False, build_collision_scene_graph=False,
                               load_collision_meshes=False)
    joints = list(robot.actuated_joint_names)
    assert joints == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                      "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
    flip = Rz(math.pi)  # ur_description's base_link is the controller's base turned
    X, W = np.array(result["T_flange_cam"]), np.array(result["T_base_target"])
    assert np.allclose(robot.get_transform("target", "base_link"), flip @ W, atol=1e-12)
    for q in QS:
        robot.update_cfg(dict(zip(joints, q, strict=True)))
        camera = robot.get_transform("camera_optical_frame", "base_link")
        assert np.allclose(camera, flip @ model_fk(result, q) @ X, atol=1e-9)
    # an arm calibration recorded without the robot's kinematics hash: refused, exit 1
    (run.path / "versions.json").write_text(json.dumps({"devices": {"arm": {}}}))
    refused = rigctl("export", str(run.path), "--format", "ur-kinematics")
    assert refused.returncode == 1 and "kinematics_hash" in refused.stderr

