"""Pose files and the identifiability of the poses an operator chose (pure; no stand-ins):
the file is read and checked before anything moves, a run's poses round-trip through
``rigctl runs poses``' format, robot-kinematics plans every pose as a training view,
and a set that cannot determine the model is told apart from the planner's D-optimal
plan by its condition number, with the free directions that the geometry predicts."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from rigctl.config import load_rig
from rigctl.errors import ConfigError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.mocks.world import WORLDS, load_world
from rigctl.procedures.base import CaptureStep, MoveArmJoints, Note
from rigctl.procedures.planning import (
    MIN_CLEARANCE_M,
    UNDETERMINED_CONDITION,
    clearance_m,
    d_optimal_views,
    load_pose_file,
    pose_file_text,
    pose_set_report,
    visible_views,
)
from rigctl.records import RunDirectory
from rigctl.runner import prepare_run
from tests.mockproc import rig_without_devices

K = np.array([[900.0, 0, 652.3], [0, 905.0, 371.8], [0, 0, 1]])
NOMINAL_INTRINSICS = {"fx": 900.0, "fy": 905.0, "cx": 652.3, "cy": 371.8}


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    """The rig file ``rigctl sim up`` writes for the default world (nothing started)."""
    tmp_path = tmp_path_factory.mktemp("pose-file-rig")
    world_path = WORLDS / "default.yaml"
    rig = rig_without_devices(world_path, tmp_path, str(tmp_path / "records"),
                              load_world(world_path))
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    return load_rig(tmp_path / "rig.yaml")


@pytest.fixture(scope="module")
def views(config):
    """Twelve planned views of the board (nominal arm), the whole board in each."""
    poses, _ = visible_views(config, 12, 0.45, 30.0, 10, "view", K,
                             nominal_ur(config.devices.arm.model))
    assert len(poses) == 12
    return poses


def write_poses(path, poses) -> None:
    path.write_text("".join("- [" + ", ".join(f"{math.degrees(v):.6f}" for v in q) + "]\n"
                            for q in poses))


def test_a_runs_poses_round_trip_through_the_pose_file(config, views, tmp_path):
    run = RunDirectory.create(tmp_path, "run-a")
    for k, q in enumerate(views[:4]):
        run.write_capture(k, None, {"index": k, "label": f"view {k + 1}",
                                    "arm": {"q": list(q)}})
    run.write_capture(4, None, {"index": 4, "label": "head only"})  # no arm: left out
    text = pose_file_text(run, exclude={2})
    assert text.count("\n- [") == 3 and "# capture 003: view 4" in text
    path = tmp_path / "poses.yaml"
    path.write_text(text)
    back = load_pose_file(path, config)
    expected = [views[k] for k in (0, 1, 3)]
    # written to 1e-4 deg
    assert np.abs(np.degrees(np.array(back) - np.array(expected))).max() <= 5e-5 + 1e-12


@pytest.mark.parametrize("text, said", [
    ("", "expected a YAML list of poses"),
    ("- [0, -90, 90, -90, -90, 0]\n- [0, -90, 90, -90, x, 0]\n",
     ":2: pose 2: expected a list of 6 joint angles"),
    ("- [0, -90, 90, -90, -90, 0]\n-\n  - 0\n  - .nan\n  - 0\n  - 0\n  - 0\n  - 0\n",
     ":3: pose 2: joint angles must be finite"),  # the pose's list begins on line 3
    ("- [0, -90, 90, -90, -90, 0, 0]\n", ":1: pose 1: expected a list of 6"),
    ("- [0, -90, 90, -90, -90, true]\n", ":1: pose 1: expected a list of 6"),
    ("- [0, -90, 90, -90, -90, 0]\n- [-361, -90, 90, -90, -90, 0]\n",
     ":2: pose 2: joint 1 at -361.00 deg is outside the soft limits [-360.0, 360.0] deg"),
    ("- {a: 1}\n", ":1: pose 1: expected a list of 6"),
])
def test_a_bad_pose_file_names_its_line_and_pose(config, tmp_path, text, said):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as refused:
        load_pose_file(path, config)
    assert f"{path}{said}" in str(refused.value) if said.startswith(":") else \
        f"{path}: {said}" in str(refused.value)


def test_a_pose_into_the_target_plane_is_refused(config, tmp_path):
    """A configuration whose wrist or camera comes within MIN_CLEARANCE_M of the table
    the target lies on (found by a seeded search), refused with its clearance."""
    model = nominal_ur(config.devices.arm.model)
    rng = np.random.default_rng(4)
    low = next(q for q in (rng.uniform(-math.pi, math.pi, 6) for _ in range(5000))
               if clearance_m(config, model, q) < 0.0)
    path = tmp_path / "low.yaml"
    write_poses(path, [low])
    with pytest.raises(ConfigError, match=r":1: pose 1: the arm would come -?\d+\.\d cm from "
                                          "the target plane") as refused:
        load_pose_file(path, config)
    assert f"at least {100 * MIN_CLEARANCE_M:.0f} cm" in str(refused.value)


def test_robot_kinematics_plans_every_pose_as_a_training_view(config, views, tmp_path):
    path = tmp_path / "poses.yaml"
    write_poses(path, views)
    params = {"poses_file": str(path), "use_controller_model": False,
              "intrinsics": NOMINAL_INTRINSICS}
    _, _, plan = prepare_run(config, "robot-kinematics", params)
    assert not plan.violations
    captures = [s for s in plan.steps if isinstance(s, CaptureStep)]
    assert [c.label for c in captures] == [f"pose {k + 1}" for k in range(12)]
    assert {c.extra["kind"] for c in captures} == {"train"}
    moves = [s.q for s in plan.steps if isinstance(s, MoveArmJoints)]
    assert np.allclose(moves[:-1], views, atol=1e-8)  # the file's poses, then home
    notes = " ".join(s.text for s in plan.steps if isinstance(s, Note))
    assert "12 views, condition number" in notes and "D-optimal plan of 12 views" in notes
    assert plan.steps.index(next(s for s in plan.steps if isinstance(s, Note))) == 0
    # fewer poses than the solve needs: refused before anything moves
    write_poses(path, views[:7])
    with pytest.raises(ConfigError, match="7 poses; the procedure needs at least 8"):
        prepare_run(config, "robot-kinematics", params)


def test_an_informative_set_is_determined_and_the_d_optimal_plan_beats_it(config, views):
    model = nominal_ur(config.devices.arm.model)
    report = pose_set_report(config, views, K, model, True, 0.45, 30.0, 10)
    best = report["d_optimal"]
    assert report["determined"] and report["warning"] is None
    assert best["views"] == report["views"] == 12
    # link parameters, X and W: hundreds, as the planned runs report (Schroer's 100 is
    # for the link parameters alone); D-optimal views are better conditioned and predict
    # a smaller camera uncertainty over the same configurations
    assert best["condition_number"] < report["condition_number"] < UNDETERMINED_CONDITION
    ours, theirs = report["camera_position_sigma_mm"], best["camera_position_sigma_mm"]
    assert ours["configurations"] == theirs["configurations"] == 24
    assert 0 < theirs["median"] < ours["median"] < 5.0
    # the predicted sigma scales with the corner noise assumed
    double = pose_set_report(config, views, K, model, True, 0.45, 30.0, 10, sigma_px=0.6)
    assert double["camera_position_sigma_mm"]["median"] == pytest.approx(
        2 * ours["median"], rel=1e-6)


@pytest.mark.parametrize("joint", [1, 6])
def test_a_set_turned_about_one_joint_cannot_determine_the_model(config, views, joint):
    """Every pose one joint apart: the poses differ by rotations about one fixed axis,
    which leave the camera's offset along that axis free (Tsai and Lenz); with the link
    parameters as well, most of the arm is unseen. Both are flagged, the joint named."""
    model = nominal_ur(config.devices.arm.model)
    base = views[0]
    turns = np.radians(np.arange(-8, 9, 2) if joint == 1 else np.arange(-40, 41, 10))
    poses = [base + np.eye(6)[joint - 1] * t for t in turns]
    for links in (False, True):
        report = pose_set_report(config, poses, K, model, links, 0.45, 30.0, 10)
        assert not report["determined"], (joint, links)
        assert report["condition_number"] is None or \
            report["condition_number"] > 100 * UNDETERMINED_CONDITION
        assert report["camera_position_sigma_mm"] is None
        assert f"every pose differs from the others in joint {joint} only" in \
            report["warning"]
        assert report["d_optimal"]["determined"]
    if joint == 6:  # flange z is joint 6's axis: X's offset along it, and W's, are free
        hand_eye = pose_set_report(config, poses, K, model, False, 0.45, 30.0, 10)
        assert set(hand_eye["weakest_direction"]) >= {"X.z", "W.z"}


def test_d_optimal_views_are_chosen_for_the_model_asked(config):
    """Hand-eye (X and W only) and robot-kinematics (links too) choose differently."""
    model = nominal_ur(config.devices.arm.model)
    frames = d_optimal_views(config, K, 8, 0.45, 30.0, 3, model, False)
    links = d_optimal_views(config, K, 8, 0.45, 30.0, 3, model, True)
    assert len(frames) == len(links) == 8
    assert not all(any(np.allclose(a, b) for b in links) for a in frames)
