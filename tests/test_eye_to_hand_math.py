"""The eye-to-hand math without stand-ins: a fixed camera watching a board on the flange,
synthetic poses with noise, truth known (``handeye.eye_to_hand``, ``robot.refine`` with
``Measurements.fixed``)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.calib import handeye, robot
from rigctl.calib.board import board_points
from rigctl.geometry.camera import camera_matrix
from rigctl.geometry.kinematics import nominal_ur
from rigctl.geometry.transforms import inv_T, look_at, make_T, rotvec_to_R

pytestmark = pytest.mark.timeout(120)

K = camera_matrix(900.0, 905.0, 640.0, 360.0)
OBJ = board_points(6, 8, 0.025)
T_BASE_CAM = look_at(np.array([-1.1, 0.35, 0.65]), np.array([-0.45, 0.0, 0.3]),
                     np.array([0.0, 0.0, -1.0]))
T_FLANGE_TARGET = make_T(rotvec_to_R([np.pi, 0.02, -0.03]), [-0.09, 0.07, 0.03])


def _views(model, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Joint configurations near a pose that shows the board to the camera, each kept
    when every corner projects in front of the camera inside a 1280x720 image."""
    q0 = model.ik(T_BASE_CAM @ make_T(t=[-0.09, -0.06, 0.5]) @ inv_T(T_FLANGE_TARGET),
                  np.radians([0, -100, -100, -70, 90, 0]))
    out = []
    while len(out) < n:
        q = q0 + rng.normal(0, [0.15, 0.12, 0.12, 0.3, 0.3, 0.6])
        px = _pixels(model, q)
        if px is not None and np.all((px > 20) & (px < [1260, 700])):
            out.append(q)
    return out


def _pixels(model, q):
    T = inv_T(T_BASE_CAM) @ model.fk(q) @ T_FLANGE_TARGET
    cam = (T[:3, :3] @ OBJ.T).T + T[:3, 3]
    if np.any(cam[:, 2] < 0.1):
        return None
    px = (K @ cam.T).T
    return px[:, :2] / px[:, 2:]


def test_eye_to_hand_closed_form_and_refinement_find_the_truth():
    model = nominal_ur("ur5e")
    rng = np.random.default_rng(3)
    qs = _views(model, 14, rng)
    from rigctl.calib.extrinsic import estimate_pose

    corners = [_pixels(model, q) + rng.normal(0, 0.3, (len(OBJ), 2)) for q in qs]
    C = [estimate_pose(OBJ, c, K, np.zeros(5)).T_cam_target for c in corners]
    F = [model.fk(q) for q in qs]
    closed, refined = handeye.eye_to_hand(F, C, corners, OBJ, K, np.zeros(5))
    rot, mm = handeye.transform_error(refined.X, T_BASE_CAM)
    assert rot < 0.05 and mm < 1.0
    rot, mm = handeye.transform_error(refined.W, T_FLANGE_TARGET)
    assert rot < 0.1 and mm < 1.0
    for X in closed.values():  # every closed form lands near the truth as well
        rot, mm = handeye.transform_error(X, T_BASE_CAM)
        assert rot < 1.0 and mm < 15.0
    assert refined.rms < 0.6


def test_fixed_camera_refinement_recovers_link_errors():
    nominal = nominal_ur("ur5e")
    truth = nominal.copy()
    truth.a[1] += 0.0012
    truth.alpha[3] += np.radians(0.08)
    truth.theta_offset[2] += np.radians(0.1)
    rng = np.random.default_rng(5)
    qs = _views(truth, 40, rng)
    corners = [_pixels(truth, q) + rng.normal(0, 0.2, (len(OBJ), 2)) for q in qs]
    meas = robot.Measurements(qs, corners=corners, obj=OBJ, K=K, dist=np.zeros(5), fixed=True)
    ref = robot.refine(nominal, T_BASE_CAM @ make_T(t=[0.003, 0, 0]), T_FLANGE_TARGET, meas)
    assert ref.rms < 0.3
    pos, _ = robot.pose_deviations(ref.model, ref.X, ref.W, qs,
                                   [robot.target_cam(truth, T_BASE_CAM, T_FLANGE_TARGET, q,
                                                     True) for q in qs], fixed=True)
    before, _ = robot.pose_deviations(nominal, T_BASE_CAM, T_FLANGE_TARGET, qs,
                                      [robot.target_cam(truth, T_BASE_CAM, T_FLANGE_TARGET,
                                                        q, True) for q in qs], fixed=True)
    after_mm, before_mm = (1000 * np.sqrt(np.mean(e ** 2)) for e in (pos, before))
    print(f"fixed camera: {before_mm:.3f} mm before, {after_mm:.3f} mm after")
    assert after_mm < 0.3 and after_mm < before_mm / 4
    names = dict(zip(ref.names, ref.values, strict=True))
    sig = dict(zip(ref.names, ref.sigma, strict=True))
    z = (names["link3.theta_offset"] - truth.theta_offset[2]) / sig["link3.theta_offset"]
    assert abs(z) < 4
