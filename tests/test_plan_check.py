"""The plan check covers straight-line arm moves (``MoveArmLinear``): every point of the
line must be reachable by the nominal model and inside the soft limits. Pure planning:
no devices."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from rigctl.config import parse_rig
from rigctl.mocks.ur_kinematics import ArmModel, matrix_to_pose
from rigctl.mocks.world import load_world
from rigctl.procedures.base import MoveArmJoints, MoveArmLinear
from rigctl.runner import check_plan
from tests.mockproc import rig_without_devices

ROOT = Path(__file__).resolve().parents[1]


def config_with(joint_limits_deg=None):
    world = load_world(ROOT / "rigctl/mocks/worlds/default.yaml")
    rig = rig_without_devices(Path("world.yaml"), Path("/nonexistent"), "records", world)
    if joint_limits_deg is not None:
        rig["devices"]["arm"]["joint_limits_deg"] = joint_limits_deg
    return parse_rig(yaml.safe_dump(rig)), world


def home_pose(world, dz: float = 0.0, dx: float = 0.0) -> tuple[float, ...]:
    """The flange's pose at home moved by dx, dz metres (the simulator's own FK)."""
    T = ArmModel.nominal(world.spec.arm.model).flange(world.home_q)
    T[0, 3] += dx
    T[2, 3] += dz
    return tuple(matrix_to_pose(T))


def test_a_short_straight_line_passes():
    config, world = config_with()
    assert check_plan(config, [MoveArmLinear(home_pose(world, dz=0.05))], ("arm",)) == []


def test_a_line_out_of_reach_is_named():
    config, world = config_with()
    problems = check_plan(config, [MoveArmLinear(home_pose(world, dx=-3.0))], ("arm",))
    assert len(problems) == 1 and "step 1 (arm linear" in problems[0]
    assert "leaves the arm's reach" in problems[0]


def test_a_line_that_turns_a_joint_past_its_soft_limit_is_named():
    # joint 1 may only turn +-5 deg: a line 20 cm sideways from home swings it further
    limits = [[-5.0, 5.0]] + [[-360.0, 360.0]] * 5
    config, world = config_with(limits)
    T = ArmModel.nominal(world.spec.arm.model).flange(world.home_q)
    pose = tuple(matrix_to_pose(T) + np.r_[0.0, 0.2, 0.0, 0.0, 0.0, 0.0])
    steps = [MoveArmJoints(tuple(world.home_q)), MoveArmLinear(pose)]
    problems = check_plan(config, steps, ("arm",))
    assert len(problems) == 1 and problems[0].startswith("step 2 (arm linear")
    assert "arm.joint1 would reach" in problems[0] and "soft limits [-5.0, 5.0]" in problems[0]
