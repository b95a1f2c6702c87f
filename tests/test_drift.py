"""drift.compare on plain data: every threshold, at, under and over its limit, with the
measured changes checked against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.config import DriftThresholds
from rigctl.drift import compare

LIMITS = DriftThresholds()  # focal 0.5 %, pp 3 px, link 0.5 mm / 0.05 deg, hand-eye 2 mm / 0.2 deg
CAMERA = {"fx": 900.0, "fy": 905.0, "cx": 652.3, "cy": 371.8}


def pose(x_mm=0.0, y_mm=0.0, z_mm=0.0, about_z_deg=0.0, about_x_deg=0.0) -> list:
    """A 4x4 written out by hand (Rz then Rx), not with the code under test."""
    cz, sz = math.cos(math.radians(about_z_deg)), math.sin(math.radians(about_z_deg))
    cx, sx = math.cos(math.radians(about_x_deg)), math.sin(math.radians(about_x_deg))
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Rx
    T[:3, 3] = np.array([0.10 + x_mm / 1000, -0.02 + y_mm / 1000, 0.05 + z_mm / 1000])
    return T.tolist()


BASE = np.array(pose(about_z_deg=30.0, about_x_deg=-10.0))


def moved(x_mm=0.0, y_mm=0.0, z_mm=0.0, about_z_deg=0.0) -> list:
    """BASE moved by a translation (mm, base frame) and turned about its own z axis."""
    c, s = math.cos(math.radians(about_z_deg)), math.sin(math.radians(about_z_deg))
    T = BASE.copy()
    T[:3, :3] = BASE[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    T[:3, 3] += np.array([x_mm, y_mm, z_mm]) / 1000
    return T.tolist()


def links(d_mm=0.0, alpha_deg=0.0, joint=2) -> list[dict]:
    out = [{"theta_offset": 0.0, "d": 0.1625, "a": 0.0, "alpha": math.pi / 2, "beta": 0.0},
           {"theta_offset": 0.0, "d": 0.0, "a": -0.425, "alpha": 0.0, "beta": 0.0},
           {"theta_offset": 0.0, "d": 0.0, "a": -0.3922, "alpha": 0.0, "beta": 0.0},
           {"theta_offset": 0.0, "d": 0.1333, "a": 0.0, "alpha": math.pi / 2, "beta": 0.0},
           {"theta_offset": 0.0, "d": 0.0997, "a": 0.0, "alpha": -math.pi / 2, "beta": 0.0},
           {"theta_offset": 0.0, "d": 0.0996, "a": 0.0, "alpha": 0.0, "beta": 0.0}]
    out[joint]["d"] += d_mm / 1000
    out[joint]["alpha"] += math.radians(alpha_deg)
    return out


def test_camera_unchanged_has_zero_metrics_and_no_breach():
    breaches, metrics = compare("active-camera", dict(CAMERA), dict(CAMERA), LIMITS)
    assert breaches == [] and metrics == {"focal_pct": 0.0, "principal_point_px": 0.0}


def test_principal_point_alone_breaches_on_the_worse_axis():
    new = {**CAMERA, "cx": CAMERA["cx"] - 1.0, "cy": CAMERA["cy"] + 3.5}
    breaches, metrics = compare("active-camera", new, CAMERA, LIMITS)
    assert metrics["focal_pct"] == 0.0
    assert metrics["principal_point_px"] == pytest.approx(3.5, abs=1e-9)
    assert breaches == ["principal point moved 3.50 px (limit 3.0 px)"]


def test_principal_point_under_the_limit_passes():
    new = {**CAMERA, "cx": CAMERA["cx"] + 2.9, "cy": CAMERA["cy"] - 2.9}
    breaches, metrics = compare("active-camera", new, CAMERA, LIMITS)
    assert breaches == [] and metrics["principal_point_px"] == pytest.approx(2.9, abs=1e-9)


def test_focal_takes_the_larger_of_fx_and_fy():
    new = {**CAMERA, "fx": 900.0 * 1.001, "fy": 905.0 * 0.994}  # 0.1 % and -0.6 %
    breaches, metrics = compare("active-camera", new, CAMERA, LIMITS)
    assert metrics["focal_pct"] == pytest.approx(0.6, abs=1e-9)
    assert breaches == ["focal length changed 0.600 % (limit 0.5 %)"]


def test_focal_and_principal_point_breach_together():
    new = {"fx": 918.0, "fy": 923.1, "cx": 657.3, "cy": 368.8}  # the drift world's lens
    breaches, metrics = compare("active-camera", new, CAMERA, LIMITS)
    assert metrics["focal_pct"] == pytest.approx(2.0, abs=1e-9)
    assert metrics["principal_point_px"] == pytest.approx(5.0, abs=1e-9)
    assert len(breaches) == 2


def test_thresholds_come_from_the_rig_file():
    new = {**CAMERA, "cx": CAMERA["cx"] + 3.5}
    wide = DriftThresholds(principal_point_px=4.0)
    assert compare("active-camera", new, CAMERA, wide)[0] == []


def test_hand_eye_translation_breach_only():
    new = {"T_flange_cam": moved(x_mm=1.8, y_mm=-2.4)}  # 3.0 mm
    breaches, metrics = compare("hand-eye", new, {"T_flange_cam": BASE.tolist()}, LIMITS)
    assert metrics["hand_eye_mm"] == pytest.approx(3.0, abs=1e-9)
    assert metrics["hand_eye_deg"] == pytest.approx(0.0, abs=1e-5)
    assert breaches == ["hand-eye moved 3.00 mm (limit 2.0 mm)"]


def test_hand_eye_rotation_breach_only():
    new = {"T_flange_cam": moved(z_mm=0.5, about_z_deg=0.3)}
    breaches, metrics = compare("hand-eye", new, {"T_flange_cam": BASE.tolist()}, LIMITS)
    assert metrics["hand_eye_mm"] == pytest.approx(0.5, abs=1e-9)
    assert metrics["hand_eye_deg"] == pytest.approx(0.3, abs=1e-4)
    assert breaches == ["hand-eye turned 0.300 deg (limit 0.2 deg)"]


def test_hand_eye_within_limits():
    new = {"T_flange_cam": moved(x_mm=1.0, about_z_deg=-0.15)}
    breaches, metrics = compare("hand-eye", new, {"T_flange_cam": BASE.tolist()}, LIMITS)
    assert breaches == [] and metrics["hand_eye_deg"] == pytest.approx(0.15, abs=1e-4)


def test_robot_kinematics_links_and_hand_eye():
    old = {"links": links(), "T_flange_cam": BASE.tolist()}
    new = {"links": links(d_mm=0.8, alpha_deg=-0.07), "T_flange_cam": moved(y_mm=2.5)}
    breaches, metrics = compare("robot-kinematics", new, old, LIMITS)
    assert metrics["link_mm"] == pytest.approx(0.8, abs=1e-9)
    assert metrics["link_deg"] == pytest.approx(0.07, abs=1e-9)
    assert metrics["hand_eye_mm"] == pytest.approx(2.5, abs=1e-9)
    assert breaches == ["hand-eye moved 2.50 mm (limit 2.0 mm)",
                        "link 3 d changed 0.800 mm (limit 0.5 mm)",
                        "link 3 alpha changed 0.0700 deg (limit 0.05 deg)"]


def test_robot_kinematics_small_link_changes_pass():
    old = {"links": links()}
    new = {"links": links(d_mm=-0.3, alpha_deg=0.03, joint=4)}
    breaches, metrics = compare("robot-kinematics", new, old, LIMITS)
    assert breaches == []
    assert metrics == pytest.approx({"link_mm": 0.3, "link_deg": 0.03}, abs=1e-9)


def test_robot_kinematics_with_a_different_arm_is_a_breach_not_a_crash():
    breaches, _ = compare("robot-kinematics", {"links": links()[:5]}, {"links": links()},
                          LIMITS)
    assert breaches == ["the arm model changed: 5 links, 6 before"]


def test_missing_pieces_and_other_procedures_compare_nothing():
    assert compare("robot-kinematics", {"links": links()}, {}, LIMITS) == ([], {})
    assert compare("hand-eye", {}, {"T_flange_cam": BASE.tolist()}, LIMITS) == ([], {})
    assert compare("head-sweep", {"fx": 1.0}, {"fx": 2.0}, LIMITS) == ([], {})


def test_a_change_within_the_uncertainty_of_the_difference_is_not_drift():
    """1.0 % focal change: drift when both runs are sure to 0.1 px, noise when each has
    a 6 px sigma (difference sigma 8.5 px, change 9 px: 1.06 sigma)."""
    new = {**CAMERA, "fx": CAMERA["fx"] * 1.01}
    sure = {k: 0.1 for k in CAMERA}
    breaches, metrics = compare("active-camera", {**new, "sigma": sure},
                                {**CAMERA, "sigma": sure}, LIMITS)
    assert len(breaches) == 1 and "focal length changed 1.000 %" in breaches[0]
    assert metrics["focal_z"] == pytest.approx(9.0 / math.hypot(0.1, 0.1))
    unsure = {k: 6.0 for k in CAMERA}
    breaches, metrics = compare("active-camera", {**new, "sigma": unsure},
                                {**CAMERA, "sigma": unsure}, LIMITS)
    assert breaches == [] and metrics["focal_z"] == pytest.approx(9.0 / math.hypot(6, 6))
    # without a sigma on one side, the threshold alone decides, as before
    breaches, _ = compare("active-camera", {**new, "sigma": unsure}, dict(CAMERA), LIMITS)
    assert len(breaches) == 1


def test_a_link_change_within_its_uncertainty_is_not_drift():
    """0.8 mm on link 3's d: drift when both models know it to 0.1 mm, noise when each
    has 0.5 mm (difference sigma 0.71 mm, 1.1 sigma)."""
    sure = {f"link{i + 1}.{k}": (1e-4 if k in ("d", "a") else 1e-5) for i in range(6)
            for k in ("d", "a", "theta_offset", "alpha", "beta")}
    unsure = {**sure, "link3.d": 5e-4}
    new = {"links": links(d_mm=0.8), "uncertainty": {"parameters": sure}}
    old = {"links": links(), "uncertainty": {"parameters": sure}}
    breaches, metrics = compare("robot-kinematics", new, old, LIMITS)
    assert breaches == ["link 3 d changed 0.800 mm (limit 0.5 mm, "
                        f"{0.8 / math.hypot(0.1, 0.1):.1f} sigma of the difference)"]
    assert metrics["link_mm"] == pytest.approx(0.8)
    new["uncertainty"]["parameters"] = old["uncertainty"]["parameters"] = unsure
    breaches, metrics = compare("robot-kinematics", new, old, LIMITS)
    assert breaches == [] and metrics["link_mm"] == pytest.approx(0.8)


def test_unchanged_links_with_and_without_sigma_compare_without_a_crash():
    """A real model: the fixed parameters (link1.d, ...) have no sigma, the identified
    ones do, and most are unchanged; equal changes with and without a z once made the
    comparison raise TypeError (seen on the console's first two robot calibrations)."""
    identified = {f"link{i + 1}.a": 1e-5 for i in range(6)}
    new = {"links": links(d_mm=0.8), "uncertainty": {"parameters": identified}}
    old = {"links": links(), "uncertainty": {"parameters": identified}}
    breaches, metrics = compare("robot-kinematics", new, old, LIMITS)
    assert breaches == ["link 3 d changed 0.800 mm (limit 0.5 mm)"]
    assert metrics["link_mm"] == pytest.approx(0.8) and metrics["link_deg"] == 0.0


@pytest.mark.parametrize("procedure", ["hand-eye", "robot-kinematics"])
def test_a_different_robot_hash_is_flagged_even_when_nothing_moved(procedure):
    same = {"T_flange_cam": BASE.tolist(), "links": links()}
    breaches, _ = compare(procedure, {**same, "robot_hash": "calib_2"},
                          {**same, "robot_hash": "calib_1"}, LIMITS)
    assert breaches == ["robot recalibrated or replaced: the controller's kinematics hash is "
                        "calib_2, the accepted calibration was made with calib_1"]
    # the same robot, or a calibration that recorded no hash: nothing to say
    assert compare(procedure, {**same, "robot_hash": "calib_1"},
                   {**same, "robot_hash": "calib_1"}, LIMITS)[0] == []
    assert compare(procedure, {**same, "robot_hash": "calib_2"}, same, LIMITS)[0] == []


def test_link_breaches_name_the_link_the_parameter_and_the_sigma_of_the_difference():
    """Each kind's message names the largest significant change's link (counted from 1)
    and parameter, with the difference's sigma when both models give one, and how many
    more of that kind are over the limit; a larger change within its noise is not the one
    named."""
    sigma = {f"link{i + 1}.{k}": (1e-4 if k in ("d", "a") else 1e-5) for i in range(6)
             for k in ("d", "a", "theta_offset", "alpha", "beta")}
    old, new = links(), links()
    new[3]["a"] += 1.094e-3             # link 4 a: 1.094 mm, 7.7 sigma
    new[0]["d"] += 0.7e-3               # link 1 d: 0.7 mm, over the limit too
    new[5]["d"] += 1.5e-3               # link 6 d: 1.5 mm but within its noise
    new[1]["beta"] += math.radians(0.08)  # link 2 beta: 0.08 deg, 79 sigma
    noisy = {**sigma, "link6.d": 1e-3}
    breaches, metrics = compare("robot-kinematics",
                                {"links": new, "uncertainty": {"parameters": noisy}},
                                {"links": old, "uncertainty": {"parameters": noisy}}, LIMITS)
    z_len = 1.094 / math.hypot(0.1, 0.1)
    z_ang = math.radians(0.08) / math.hypot(1e-5, 1e-5)
    assert breaches == [
        f"link 4 a changed 1.094 mm (limit 0.5 mm, {z_len:.1f} sigma of the difference; "
        "1 other link length over the limit too)",
        f"link 2 beta changed 0.0800 deg (limit 0.05 deg, {z_ang:.1f} sigma of the "
        "difference)"]
    assert metrics["link_mm"] == pytest.approx(1.5)  # the largest change, significant or not
    assert metrics["link_length_z"] == pytest.approx(z_len)
    # without sigma, the threshold alone decides and the message says no sigma
    breaches, _ = compare("robot-kinematics", {"links": new}, {"links": old}, LIMITS)
    assert breaches == ["link 6 d changed 1.500 mm (limit 0.5 mm; 2 other link lengths "
                        "over the limit too)",
                        "link 2 beta changed 0.0800 deg (limit 0.05 deg)"]
    new = links()
    new[4]["theta_offset"] += math.radians(0.06)
    breaches, _ = compare("robot-kinematics", {"links": new}, {"links": old}, LIMITS)
    assert breaches == ["link 5 theta_offset changed 0.0600 deg (limit 0.05 deg)"]
