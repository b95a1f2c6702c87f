"""The controller's own model in the robot solves (simulated board views; no stand-ins):
the joint refinement starts from it among the other starts and names the start that won,
and hand-eye and robot-kinematics record the robot's kinematics hash whenever the
controller reported one, also with use_controller_model=false (the drift check's "robot
recalibrated or replaced" compares it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import yaml

from rigctl.calib import handeye, robot
from rigctl.calib.extrinsic import estimate_pose
from rigctl.calib.robot_pipeline import (
    BoardView,
    joint_refinement,
    joint_refinement_from,
    solve_robot,
)
from rigctl.geometry.kinematics import KinematicModel
from rigctl.mocks.world import WORLDS
from rigctl.procedures import get_procedure, hand_eye, robot_kinematics
from rigctl.procedures.base import SolveContext
from tests.test_planning_controller import rig_for
from tests.test_robot_math import DIST, OBJ, K, T_cam_target, board_views, ur_truth, view

HASH = "calib_1234567890"


def factory_of(world, seed=5) -> KinematicModel:
    """A controller's factory model: the truth's plain-DH part, a little off (no beta)."""
    rng = np.random.default_rng(seed)
    t = world.arm_true
    return KinematicModel(t.d + rng.normal(0, 2e-4, 6), t.a + rng.normal(0, 2e-4, 6),
                          t.alpha + rng.normal(0, 2e-4, 6),
                          theta_offset=t.theta_offset + rng.normal(0, 2e-4, 6))


def kinematics_dict(model: KinematicModel) -> dict:
    return {"theta": model.theta_offset.tolist(), "a": model.a.tolist(),
            "d": model.d.tolist(), "alpha": model.alpha.tolist(), "hash": HASH}


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
    assert sol.refinement_start == robot.first_of_least(starts)
    assert sol.ref.rms == starts[sol.refinement_start] < 0.3
    assert sol.heldout["factory"] is not None and sol.moved_from_controller is not None
    without = solve_robot(views, nominal, OBJ, K, np.asarray(DIST), None,
                          refine_camera=False)
    assert "controller" not in without.refinement_starts_rms_px
    assert without.refinement_start in without.refinement_starts_rms_px


def test_starts_ending_in_one_minimum_are_equals_and_the_first_of_them_wins():
    """Random world 99400's four starts ended within 1e-14 of each other; the least
    alone chose among them by rounding, and re-solves reported different (equivalent)
    D-H tables. Within a millionth they are equals; beyond, the least wins."""
    ends = {"link-by-link": 0.07707070845088546, "nominal": 0.07707070845088562,
            "axis-based": 0.0770707084508862, "controller": 0.07707070845087961}
    assert robot.first_of_least(ends) == "link-by-link"
    assert robot.first_of_least({**ends, "link-by-link": 0.0771}) == "nominal"
    assert robot.first_of_least({"a": 1.0 + 2e-6, "b": 1.0}) == "b"
    assert robot.first_of_least({"a": 1.0 + 5e-7, "b": 1.0}) == "a"


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
    # the three starts end in one minimum (to rounding): the first of equals wins
    assert max(rms.values()) < min(rms.values()) * (1 + 1e-9)
    assert won == "first"


@dataclass
class FakeRun:
    """What the solves read of a run directory here: its versions.json."""

    versions_json: dict | None
    path: Path = field(default_factory=lambda: Path("/nonexistent"))

    def versions(self):
        return self.versions_json


def observations(views) -> list[dict]:
    return [{"label": v.label, "kind": v.kind, "index": k, "joint": v.joint, "found": True,
             "q": v.q, "corners": v.corners, "C": v.C} for k, v in enumerate(views)]


def versions_with(kinematics: dict | None, hash_only: str | None = None) -> dict:
    return {"devices": {"arm": {"controller": "5.11.1.108318",
                                "kinematics_hash": kinematics["hash"] if kinematics
                                else hash_only,
                                "controller_kinematics": kinematics}}}


INTR = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
        "cy": float(K[1, 2]), "distortion": list(DIST), "source": "parameter"}


@pytest.fixture
def config(tmp_path):
    return rig_for(tmp_path, yaml.safe_load((WORLDS / "default.yaml").read_text()))


@pytest.mark.parametrize("use", [True, False])
def test_hand_eye_records_the_robot_hash_either_way(simulated, config, monkeypatch, use):
    _, world, views = simulated
    monkeypatch.setattr(hand_eye, "board_observations",
                        lambda ctx, intr: observations(views[:10]))
    proc = get_procedure("hand-eye")
    ctx = SolveContext(FakeRun(versions_with(kinematics_dict(factory_of(world)))), config,
                       proc.params_model(use_controller_model=use), {"intrinsics": INTR})
    result = proc.solve(ctx)
    assert result["robot_hash"] == HASH
    assert result["arm_model_used"] == ("controller" if use else "nominal")


def test_a_hash_without_a_table_is_recorded(simulated, config, monkeypatch):
    """A controller that reported its hash but no table (as versions.json has it)."""
    _, _, views = simulated
    monkeypatch.setattr(hand_eye, "board_observations",
                        lambda ctx, intr: observations(views[:10]))
    proc = get_procedure("hand-eye")
    ctx = SolveContext(FakeRun(versions_with(None, hash_only=HASH)), config,
                       proc.params_model(), {"intrinsics": INTR})
    result = proc.solve(ctx)
    assert result["robot_hash"] == HASH and result["arm_model_used"] == "nominal"
    ctx = SolveContext(FakeRun(None), config, proc.params_model(), {"intrinsics": INTR})
    assert proc.solve(ctx)["robot_hash"] is None


@pytest.mark.parametrize("use", [True, False])
def test_robot_kinematics_records_the_hash_and_the_winning_start(simulated, config,
                                                                 monkeypatch, use):
    """The hash whatever use_controller_model says; the controller's model a start (and
    the factory baseline) only when used; the summary names the start that won and the
    result says which model the views were planned with."""
    _, world, views = simulated
    monkeypatch.setattr(robot_kinematics, "board_observations",
                        lambda ctx, intr: observations(views))
    proc = get_procedure("robot-kinematics")
    planned = {"source": "controller", "robot_hash": HASH, "note": "planned with it",
               "controller_version": "5.11.1.108318", "controller_kinematics": None}
    ctx = SolveContext(FakeRun(versions_with(kinematics_dict(factory_of(world)))), config,
                       proc.params_model(use_controller_model=use, refine_camera=False),
                       {"intrinsics": INTR, "arm_model": planned})
    result = proc.solve(ctx)
    summary = result["summary"]
    assert result["robot_hash"] == HASH
    assert result["planned_with"] == {"source": "controller", "robot_hash": HASH,
                                      "note": "planned with it"}
    starts = summary["refinement_starts_rms_px"]
    assert summary["refinement_start"] == robot.first_of_least(starts)
    assert ("controller" in starts) == use
    assert (result["factory"] is not None) == use
    assert (summary["heldout_mm_factory"] is not None) == use
