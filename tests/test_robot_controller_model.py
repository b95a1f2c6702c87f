"""The controller's own model in the robot solves (simulated board views; no stand-ins):
the joint refinement starts from it among the other starts and names the start that won."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.calib import handeye, robot
from rigctl.calib.extrinsic import estimate_pose
from rigctl.calib.robot_pipeline import (
    BoardView,
    joint_refinement,
    joint_refinement_from,
    solve_robot,
)
from rigctl.geometry.kinematics import KinematicModel
from tests.test_robot_math import DIST, OBJ, K, T_cam_target, board_views, ur_truth, view


def factory_of(world, seed=5) -> KinematicModel:
    """A controller's factory model: the truth's plain-DH part, a little off (no beta)."""
    rng = np.random.default_rng(seed)
    t = world.arm_true
    return KinematicModel(t.d + rng.normal(0, 2e-4, 6), t.a + rng.normal(0, 2e-4, 6),
                          t.alpha + rng.normal(0, 2e-4, 6),
                          theta_offset=t.theta_offset + rng.normal(0, 2e-4, 6))


@pytest.fixture(scope="module")
def simulated():
    """Training and held-out board views of a UR5e with link errors (0.2 px noise)."""
    nominal, world, X, _, rng = ur_truth(21)
    views = []
    for kind, n in (("train", 14), ("heldout", 4)):
        for k, q in enumerate(board_views(world, X, n, rng, tilt_deg=40.0, spread=0.2)):
            corners = view(world, T_cam_target(world, q), noise=0.2, rng=rng)
            C = estimate_pose(OBJ, corners, K, np.asarray(DIST)).T_cam_target
            views.append(BoardView(f"{kind} {k + 1}", kind, None, q, corners, C))
    return nominal, world, views


def test_the_controllers_model_is_a_start_and_the_winner_is_named(simulated):
    """With the controller's model the refinement has one more start; the start named
    as the winner is the one that ended lowest, and the refinement is its result."""
    nominal, world, views = simulated
    factory = factory_of(world)
    sol = solve_robot(views, nominal, OBJ, K, np.asarray(DIST), None, refine_camera=False,
                      controller=factory)
    starts = sol.refinement_starts_rms_px
    assert list(starts) == ["nominal (W averaged)", "nominal", "controller"]
    assert sol.refinement_start == min(starts, key=starts.get)
    assert sol.ref.rms == starts[sol.refinement_start] < 0.3
    assert sol.heldout["factory"] is not None and sol.moved_from_controller is not None
    without = solve_robot(views, nominal, OBJ, K, np.asarray(DIST), None,
                          refine_camera=False)
    assert "controller" not in without.refinement_starts_rms_px
    assert without.refinement_start in without.refinement_starts_rms_px


def test_named_starts_refine_as_joint_refinement_does(simulated):
    """``joint_refinement_from`` (named starts) ends where ``joint_refinement`` (one
    call, the lowest cost of its starts) does, value for value."""
    nominal, world, views = simulated
    train = [v for v in views if v.kind == "train"]
    meas = robot.Measurements([v.q for v in train], C=[v.C for v in train],
                              corners=[v.corners for v in train], obj=OBJ, K=K,
                              dist=np.asarray(DIST))
    F = [nominal.fk(q) for q in meas.q]
    he = handeye.refine_pixels(F, meas.corners, OBJ, K, meas.dist,
                               handeye.best_closed_form(handeye.closed_form(F, meas.C)),
                               C=meas.C)
    factory = factory_of(world)
    W_f = handeye.average_W([factory.fk(q) for q in meas.q], meas.C, he.X)
    others = [(nominal, he.X, he.W), (factory, he.X, W_f)]
    old = joint_refinement(meas, nominal, he.X, others)
    W0 = handeye.average_W(F, meas.C, he.X)
    new, won, rms = joint_refinement_from(
        meas, {"first": (nominal, he.X, W0), "nominal": others[0], "controller": others[1]})
    assert np.array_equal(old.values, new.values) and old.rms == new.rms
    assert rms[won] == min(rms.values())
