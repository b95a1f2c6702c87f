"""The UR ROS 2 driver's kinematics YAML and the URDF, checked by a URDF library nobody
here wrote (yourdfpy): its forward kinematics must match the model's."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from rigctl.errors import RigError
from rigctl.exports import export_result
from rigctl.exports_ur import joint_origins, ur_kinematics
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from tests.needs import dev_dependency

yourdfpy = dev_dependency("yourdfpy")


def rz(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def urdf_origin(xyz, rpy):
    """URDF <origin>: translate, then rotate about fixed x, y, z (Rz Ry Rx)."""
    r, p, y = rpy
    cx, sx, cy, sy, cz, sz = (math.cos(r), math.sin(r), math.cos(p), math.sin(p),
                              math.cos(y), math.sin(y))
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = xyz
    return T


# ur_description's default_kinematics.yaml for the UR5e (values as published there)
UR5E_DEFAULT = {
    "shoulder": ([0, 0, 0.1625], [0, 0, 0]),
    "upper_arm": ([0, 0, 0], [1.570796327, 0, 0]),
    "forearm": ([-0.425, 0, 0], [0, 0, 0]),
    "wrist_1": ([-0.3922, 0, 0.1333], [0, 0, 0]),
    "wrist_2": ([0, -0.0997, -2.044881182297852e-11], [1.570796327, 0, 0]),
    "wrist_3": ([0, 0.0996, -2.042830148012698e-11], [1.570796326589793, 3.141592653589793,
                                                       3.141592653589793]),
}


def test_nominal_ur5e_matches_ur_description_defaults():
    doc = ur_kinematics(nominal_ur("ur5e"), "calib_1")["kinematics"]
    assert doc["hash"] == "calib_1"
    for name, (xyz, rpy) in UR5E_DEFAULT.items():
        e = doc[name]
        ours = urdf_origin([e["x"], e["y"], e["z"]], [e["roll"], e["pitch"], e["yaw"]])
        assert np.allclose(ours, urdf_origin(xyz, rpy), atol=1e-9), name


def random_model(rng, beta=True) -> tuple[KinematicModel, np.ndarray, np.ndarray]:
    m = nominal_ur(str(rng.choice(["ur3e", "ur5e", "ur10e"])))
    m.theta_offset = rng.normal(0, 0.002, 6)
    m.d = m.d + rng.normal(0, 0.002, 6)
    m.a = m.a + rng.normal(0, 0.002, 6)
    m.alpha = m.alpha + rng.normal(0, 0.002, 6)
    m.beta = rng.normal(0, 0.002, 6) if beta else np.zeros(6)
    T0 = np.eye(4)
    T0[:3, :3] = urdf_origin([0, 0, 0], rng.normal(0, 0.01, 3))[:3, :3]
    T0[:3, 3] = rng.normal(0, 0.003, 3)
    m.T_base_link0 = T0
    X = urdf_origin(rng.normal(0, 0.05, 3), rng.uniform(-math.pi, math.pi, 3))
    W = urdf_origin(rng.normal(0, 0.5, 3), rng.uniform(-math.pi, math.pi, 3))
    return m, X, W


def export_pair(tmp_path, model, X, W, robot_hash="calib_42"):
    result = {"links": model.links(), "T_base_link0": model.T_base_link0.tolist(),
              "T_flange_cam": X.tolist(), "T_base_target": W.tolist(), "arm_model": "ur5e"}
    versions = {"devices": {"arm": {"kinematics_hash": robot_hash}}}
    kin = export_result(result, "ur-kinematics", tmp_path / "k.yaml", "run1", versions)
    urdf = export_result(result, "urdf", tmp_path / "arm.urdf", "run1", versions)
    return yaml.safe_load(kin.read_text()), yourdfpy.URDF.load(
        str(urdf), load_meshes=False, build_collision_scene_graph=False,
        load_collision_meshes=False)


def test_urdf_forward_kinematics_match_the_model_over_1000_configurations(tmp_path):
    rng = np.random.default_rng(7)
    worst = 0.0
    for k in range(3):
        model, X, W = random_model(rng)
        (tmp_path / str(k)).mkdir()
        kin, robot = export_pair(tmp_path / str(k), model, X, W)
        assert kin["kinematics"]["hash"] == "calib_42"
        names = list(robot.actuated_joint_names)
        assert names == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                         "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
        flip = rz(math.pi)  # base_link is the controller's base turned half a turn
        assert np.allclose(robot.get_transform("target", "base_link"), flip @ W, atol=1e-12)
        n = 1000 if k == 0 else 100
        for q in rng.uniform(-math.pi, math.pi, (n, 6)):
            robot.update_cfg(dict(zip(names, q, strict=True)))
            theirs = robot.get_transform("camera_optical_frame", "base_link")
            ours = flip @ model.fk(q) @ X
            worst = max(worst, float(np.abs(theirs[:3, 3] - ours[:3, 3]).max()))
            assert np.allclose(theirs[:3, :3], ours[:3, :3], atol=1e-9)
    assert worst < 1e-9, worst


def test_beta_terms_survive_and_joint_frames_sit_on_the_links(tmp_path):
    rng = np.random.default_rng(11)
    model, X, W = random_model(rng)
    model.beta[1] = math.radians(0.1)
    model.d[1] = model.d[2] = 0.005
    flat = model.copy()
    flat.beta[:] = 0.0
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _, robot = export_pair(tmp_path / "a", model, X, W)
    _, robot_flat = export_pair(tmp_path / "b", flat, X, W)
    q = np.radians([10, -80, 70, -60, -90, 20])
    cfg = dict(zip(robot.actuated_joint_names, q, strict=True))
    robot.update_cfg(cfg)
    robot_flat.update_cfg(cfg)
    cam = robot.get_transform("camera_optical_frame", "base_link")
    cam_flat = robot_flat.get_transform("camera_optical_frame", "base_link")
    assert np.allclose(cam, rz(math.pi) @ model.fk(q) @ X, atol=1e-9)
    assert np.linalg.norm(cam[:3, 3] - cam_flat[:3, 3]) > 5e-4  # 0.1 deg over the forearm
    # ur_calibration's placement: joints 2 and 3 carry no d; the upper arm starts where
    # link 1's passive segment ends
    origins, _ = joint_origins(model)
    assert np.allclose(origins[1][:3, 3], [model.a[0], 0, 0], atol=1e-12)


def test_kinematics_file_needs_the_robots_own_hash(tmp_path):
    model, X, _W = random_model(np.random.default_rng(3))
    result = {"links": model.links(), "T_flange_cam": X.tolist()}
    with pytest.raises(RigError, match="kinematics_hash"):
        export_result(result, "ur-kinematics", tmp_path / "k.yaml", "run9", {"devices": {}})
    with pytest.raises(RigError, match="no arm kinematics"):
        export_result({"fx": 1.0}, "urdf", tmp_path / "a.urdf", "run9", None)


def test_urdf_and_static_transform_of_a_camera_beside_the_arm(tmp_path):
    """Eye-to-hand: the camera fixed to base_link at T_base_cam, the board on tool0 at
    T_flange_target, through the calibrated joints; the static transform YAML is the
    same T_base_cam from base_link."""
    rng = np.random.default_rng(11)
    model, X, W = random_model(rng)
    result = {"links": model.links(), "T_base_link0": model.T_base_link0.tolist(),
              "T_base_cam": W.tolist(), "T_flange_target": X.tolist(), "arm_model": "ur5e"}
    versions = {"devices": {"arm": {"kinematics_hash": "calib_42"}}}
    urdf = export_result(result, "urdf", tmp_path / "arm.urdf", "run1", versions)
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False,
                               build_collision_scene_graph=False, load_collision_meshes=False)
    flip = rz(math.pi)
    assert np.allclose(robot.get_transform("camera_optical_frame", "base_link"), flip @ W,
                       atol=1e-12)
    names = list(robot.actuated_joint_names)
    for q in rng.uniform(-math.pi, math.pi, (50, 6)):
        robot.update_cfg(dict(zip(names, q, strict=True)))
        assert np.allclose(robot.get_transform("target", "base_link"), flip @ model.fk(q) @ X,
                           atol=1e-9)
    static = yaml.safe_load(export_result(result, "ros-static", tmp_path / "cam.yaml", "run1",
                                          versions).read_text())
    assert (static["frame_id"], static["child_frame_id"]) == ("base_link",
                                                              "camera_optical_frame")
    t, r = static["translation"], static["rotation"]
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([r["x"], r["y"], r["z"], r["w"]]).as_matrix()
    T[:3, 3] = [t["x"], t["y"], t["z"]]
    assert np.allclose(T, flip @ W, atol=1e-12)
    with pytest.raises(RigError, match="no T_base_cam"):
        export_result({"T_flange_cam": X.tolist()}, "ros-static", tmp_path / "x.yaml", "run1")
