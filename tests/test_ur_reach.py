"""The closed-form reach test of a UR arm (``rigctl.geometry.ur_reach``) against the
forward kinematics (every pose the arm takes is reachable) and the iterative inverse
kinematics (no pose it calls unreachable is reached from any seed)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.errors import SolveError
from rigctl.geometry.kinematics import nominal_ur, puma560_3link
from rigctl.geometry.transforms import rotvec_to_R
from rigctl.geometry.ur_reach import is_ur_like, slack_for, surely_unreachable
from rigctl.hardware.ur_models import MODELS


@pytest.mark.parametrize("model_name", sorted(MODELS))
def test_every_pose_the_arm_takes_is_reachable(model_name):
    model = nominal_ur(model_name)
    assert is_ur_like(model)
    rng = np.random.default_rng(7)
    for q in rng.uniform(-math.pi, math.pi, (60, 6)):
        assert not surely_unreachable(model, model.fk(q), slack_m=0.0), q.tolist()


def test_a_calibrated_arms_poses_stay_reachable_within_its_slack():
    model = nominal_ur("ur5e")
    model.alpha = model.alpha + np.array([0.002, 0.0, -0.001, 0.0015, 0.0, 0.0])
    model.beta = np.array([0.0, 0.001, -0.002, 0.0, 0.0, 0.0])
    model.d = model.d + 0.003
    model.a = model.a + np.array([0.001, -0.002, 0.002, 0.0, 0.0, 0.0])
    model.theta_offset = np.full(6, 0.01)
    model.T_flange_tool = np.eye(4)
    model.T_flange_tool[:3, 3] = [0.01, 0.0, 0.05]
    assert is_ur_like(model) and slack_for(model) > 0.005
    rng = np.random.default_rng(8)
    for q in rng.uniform(-math.pi, math.pi, (200, 6)):
        assert not surely_unreachable(model, model.fk(q)), q.tolist()


def test_poses_it_calls_unreachable_are_reached_from_no_seed():
    rng = np.random.default_rng(9)
    judged = 0
    for model_name in ("ur3e", "ur10", "ur20"):
        model = nominal_ur(model_name)
        reach = abs(model.a[1]) + abs(model.a[2]) + float(np.sum(np.abs(model.d[3:])))
        for _ in range(40):
            T = np.eye(4)
            T[:3, :3] = rotvec_to_R(rng.normal(size=3))
            T[:3, 3] = rng.uniform(-0.8, 0.8, 3) * reach + [0.0, 0.0, model.d[0]]
            if not surely_unreachable(model, T):
                continue
            judged += 1
            for seed in rng.uniform(-math.pi, math.pi, (6, 6)):
                with pytest.raises(SolveError):
                    model.ik(T, seed)
    assert judged >= 30  # about half of such random poses


def test_the_shoulder_cylinder_and_beyond_the_reach_are_unreachable():
    model = nominal_ur("ur10e")
    d4, d6 = model.d[3], model.d[5]
    reach = abs(model.a[1]) + abs(model.a[2]) + abs(d4) + abs(model.d[4]) + abs(d6)
    # the wrist (link 5's origin) on joint 1's axis: inside the shoulder offset's cylinder
    inside = np.eye(4)
    inside[:3, 3] = [0.0, 0.0, 0.5 + d6]  # flange z up: link 5's origin at (0, 0, 0.5)
    assert surely_unreachable(model, inside)
    far = np.eye(4)
    far[:3, 3] = [reach + 0.05, 0.0, model.d[0]]
    assert surely_unreachable(model, far)


def test_other_arms_are_never_judged():
    puma = puma560_3link()
    assert not is_ur_like(puma)
    far = np.eye(4)
    far[:3, 3] = [10.0, 0.0, 0.0]
    assert not surely_unreachable(puma, far)
    bent = nominal_ur("ur5")
    bent.alpha = bent.alpha + np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.0])  # beyond the pattern
    assert not is_ur_like(bent)
    assert not surely_unreachable(bent, far)
