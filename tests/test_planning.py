"""Sweep planning with the nominal model (pure; no stand-ins): offsets spread over the
range in which the board stays in view, and per-joint bases that widen that range."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from rigctl.config import load_rig
from rigctl.geometry.kinematics import nominal_ur
from rigctl.mocks.world import WORLDS, load_world
from rigctl.procedures.planning import (
    MIN_CLEARANCE_M,
    board_visible,
    clearance_m,
    plan_sweeps,
    plan_target_views,
    spread_offsets,
)
from tests.mockproc import rig_without_devices


@pytest.fixture
def config(tmp_path):
    """The rig file ``rigctl sim up`` writes for the default world (nothing started)."""
    world_path = WORLDS / "default.yaml"
    rig = rig_without_devices(world_path, tmp_path, str(tmp_path / "records"),
                              load_world(world_path))
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    return load_rig(tmp_path / "rig.yaml")


def test_spread_offsets_reach_both_ends_in_proportion():
    assert spread_offsets(-42, 19, 4) == [19, -14, -28, -42]
    assert spread_offsets(-7, 7, 4) == [3.5, 7, -3.5, -7]
    assert spread_offsets(-1, 30, 3) == [10, 20, 30]  # a side under 2 deg gets none
    assert spread_offsets(-60, 60, 6) == [20, 40, 60, -20, -40, -60]
    assert spread_offsets(-1.5, 1.5, 4) == []


def test_sweeps_from_the_widest_bases_stay_in_view_and_sweep_further(config):
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    model = nominal_ur(config.devices.arm.model)
    limits = config.devices.arm.joint_limits_rad()
    base, _ = plan_target_views(config, 1, 0.7, 0.0, 0)
    more, _ = plan_target_views(config, 16, 0.7, 45.0, 7)
    common, _ = plan_sweeps(config, base, K, 4)
    widest, notes = plan_sweeps(config, base + more, K, 4)
    assert sorted(widest) == list(range(6)) and len(notes) == 6
    for j, sweep in widest.items():
        lo, hi = sweep.visible
        assert lo <= min(sweep.offsets) and max(sweep.offsets) <= hi
        assert max(sweep.offsets) - min(sweep.offsets) >= 0.9 * (hi - lo)
        for off in sweep.offsets:  # every planned capture sees the whole board
            q = sweep.q_base + np.eye(6)[j] * math.radians(off)
            assert limits[j][0] <= q[j] <= limits[j][1]
            assert board_visible(config, model, q, K)
            assert clearance_m(config, model, q) >= MIN_CLEARANCE_M
        c_lo, c_hi = common[j].visible
        assert hi - lo >= c_hi - c_lo
    # joints 3 and 4 (parallel, close to the camera) lose the board within ~+-10 deg of
    # one straight-down view; from their best candidate views they sweep at least twice
    # as far
    for j in (2, 3):
        assert np.ptp(widest[j].offsets) >= 2 * np.ptp(common[j].offsets)


def test_clearance_guard_sees_an_arm_reaching_below_the_target_plane(config):
    model = nominal_ur(config.devices.arm.model)
    # the target lies on the table (z = 0): upper arm horizontal at shoulder height, then
    # the forearm hanging straight down 0.39 m: the wrists are 0.23 m below the table
    down = np.radians([0, 0, 90, 0, 0, 0])
    up = np.radians([0, -90, 0, -90, 0, 0])  # pointing straight up
    assert clearance_m(config, model, down) < -0.1
    assert clearance_m(config, model, up) > 0.1
