"""Planning on rigs nobody tuned for: on a UR3e (random world 3) the default viewing
distances are out of reach; hand-eye plans closer, inside the soft limits, and
robot-kinematics scales its distances the same way. A target out of reach is refused
before any motion, by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from rigctl.config import parse_rig
from rigctl.errors import SolveError
from rigctl.mocks.random_world import random_world
from rigctl.mocks.world import World, WorldFile
from rigctl.procedures import get_procedure
from rigctl.procedures.robot_kinematics import RobotKinematicsParams, _scaled_to_reach
from rigctl.runner import check_plan
from tests.mockproc import rig_without_devices


def rig_for(world_data: dict):
    world = World(WorldFile.model_validate(world_data))
    rig = rig_without_devices(Path("world.yaml"), Path("/nonexistent"), "records", world)
    return parse_rig(yaml.safe_dump(rig))


def test_a_small_arm_is_planned_closer():
    data = random_world(3)
    assert data["arm"]["model"] == "ur3e"
    config = rig_for(data)
    proc = get_procedure("hand-eye")
    steps = proc.plan(proc.params_model(poses=4), config)
    assert len([s for s in steps if type(s).__name__ == "CaptureStep"]) == 4
    assert not check_plan(config, steps, proc.devices)
    notes = " ".join(s.text for s in steps if type(s).__name__ == "Note")
    assert "views: planned at 0.36 m instead of 0.45 m (4 of 4 views with the whole board" \
        in notes
    params, base, notes = _scaled_to_reach(config, RobotKinematicsParams())
    assert len(base) == 1 and params.sweep_distance_m < 0.7 and params.view_distance_m < 0.45
    assert "no straight view" in notes[0]


def test_target_out_of_reach_is_refused_before_motion():
    data = random_world(3)
    data["target"]["xyz_mm"] = [-3000.0, 0.0, 0.0]
    config = rig_for(data)
    proc = get_procedure("hand-eye")
    with pytest.raises(SolveError, match=r"only 0 of 4 views of the target are reachable at "
                                         r"0\.23-0\.65 m"):
        proc.plan(proc.params_model(poses=4), config)
    with pytest.raises(SolveError, match=r"no reachable view of the target from 0\.70 m"):
        _scaled_to_reach(config, RobotKinematicsParams())


@pytest.mark.heavy
@pytest.mark.timeout(600)  # a hang guard: ~70 s idle, past 120 s under the load check
def test_a_board_at_the_edge_of_the_reach_gets_a_leaning_sweep_base():
    """Random world 9078 (a UR3e, its board near the edge of the reach): no straight
    view is reachable at any distance tried, so the sweeps start from a view leaning
    toward the arm, instead of the run being refused; a board beyond the reach is still
    refused, by name."""
    data = random_world(9078)
    assert data["arm"]["model"] == "ur3e"
    config = rig_for(data)
    params, base, notes = _scaled_to_reach(config, RobotKinematicsParams())
    assert len(base) == 1 and params.sweep_distance_m < 0.5
    assert any("leaning 15 deg toward the arm" in n for n in notes)
    proc = get_procedure("robot-kinematics")  # the whole plan holds, inside the limits
    steps = proc.plan(proc.params_model(), config)
    assert not check_plan(config, steps, proc.devices)
    assert len([s for s in steps if type(s).__name__ == "CaptureStep"]) > 40
    data["target"]["xyz_mm"] = [-1500.0, 0.0, 0.0]
    with pytest.raises(SolveError, match="straight or leaning up to 45 deg toward the arm"):
        _scaled_to_reach(rig_for(data), RobotKinematicsParams())


def test_a_long_lens_close_up_gets_sweep_bases_that_show_the_whole_board():
    """Random world 13003 (a UR3e; f 1600 px on a 1280 x 720 image, the camera turned
    92 deg on the flange): the sweeps are reachable only at 0.35 m, where the board fits
    the image only with its longer side along the image's. The bases were planned without
    the intrinsics and spun freely: none showed the whole board, no joint could be swept,
    and planning crashed (an IndexError on no sweeps). Now every base shows the board and
    every joint is swept."""
    data = random_world(13003)
    assert data["arm"]["model"] == "ur3e"
    notes = _plan_sweeping_every_joint(data)
    assert any("sweeps at 0.35 m" in n for n in notes)


def _plan_sweeping_every_joint(data: dict, **params) -> list[str]:
    """robot-kinematics planned on world ``data`` with its true intrinsics: the plan is
    inside the limits and sweeps all six joints (24 sweep captures or more); its notes."""
    config = rig_for(data)
    given = {k: data["camera"][k] for k in ("fx", "fy", "cx", "cy")}
    proc = get_procedure("robot-kinematics")
    steps = proc.plan(proc.params_model(intrinsics=given, **params), config)
    assert not check_plan(config, steps, proc.devices)
    notes = [s.text for s in steps if type(s).__name__ == "Note"]
    swept = [n for n in notes if n.startswith("joint ") and ("sweep +" in n or "sweep -" in n)]
    assert len(swept) == 6, notes
    captures = [s for s in steps if type(s).__name__ == "CaptureStep"]
    assert len([c for c in captures if c.extra.get("kind") == "sweep"]) >= 24
    return notes


def test_a_long_lens_on_a_large_board_gets_its_sweeps_farther_than_asked():
    """Random world 21016 (a UR10e, f 1372 px, a 7 x 7 board of large squares): from no
    reachable base at the asked 0.70 m or nearer does the camera see the whole board, and
    the plan was refused before motion although the arm reaches farther views. Now the
    sweeps start farther (0.80 m), the views scale with them, and every joint is swept."""
    data = random_world(21016)
    assert data["arm"]["model"] == "ur10e"
    notes = _plan_sweeping_every_joint(data, use_controller_model=False)
    assert any("from no reachable base as near as asked: sweeps at 0.80 m and views at "
               "0.52 m" in n for n in notes), notes
    cam = data["camera"]
    # a target beyond every distance tried is still refused, naming them
    data["target"]["xyz_mm"] = [-3000.0, 0.0, 0.0]
    with pytest.raises(SolveError, match=r"or farther \(up to 1\.05 m\).*fits from"):
        _scaled_to_reach(rig_for(data), RobotKinematicsParams(), None,
                         np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]],
                                   [0, 0, 1.0]]))


def test_held_out_views_show_the_whole_board():
    """Random world 61004 (a UR10e whose sweeps are planned farther than asked): the
    held-out views were planned at the scaled view distance without checking that the
    board fits, and all six cut it (no held-out error was reported). Now every held-out
    view shows every corner of the board in the true world, inside the image."""
    data = random_world(61004)
    world = World(WorldFile.model_validate(data))
    config = rig_for(data)
    given = {k: data["camera"][k] for k in ("fx", "fy", "cx", "cy")}
    proc = get_procedure("robot-kinematics")
    steps = proc.plan(proc.params_model(intrinsics=given), config)
    assert not check_plan(config, steps, proc.devices)
    held, q = [], None
    for step in steps:
        if type(step).__name__ == "MoveArmJoints":
            q = step.q
        if type(step).__name__ == "CaptureStep" and step.extra.get("kind") == "heldout":
            held.append(world.target_corner_pixels(world.T_base_cam(q, (0.0, 0.0, 0.0))))
    assert len(held) == RobotKinematicsParams().heldout_poses
    w, h = data["camera"]["width"], data["camera"]["height"]
    for px in held:
        assert np.all((px > 0) & (px < [w - 1, h - 1])), px


def test_views_of_small_markers_are_planned_near_enough_to_decode_them():
    """Random world 99403 (a UR3e holding a ChArUco board of 6.31 mm 6x6 markers, the
    head beside the arm, f 1440 px): at validate-arm's 0.5 m a marker's cell spans
    2.3 px, and no view of the run decoded the board. Every planned view now brings it
    near enough for about 3.5 px per cell (each view's distance is drawn within 10 % of
    the planned one), and the plan says why it came nearer."""
    from rigctl.procedures.planning import (
        MIN_MARKER_CELL_PX,
        marker_cell_px,
        nominal_cam_target,
        planning_arm,
    )

    data = random_world(99403, target="charuco", mount="fixed")
    config = rig_for(data)
    cam = data["camera"]
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
    assert marker_cell_px(config, K, 0.5) == pytest.approx(2.27, abs=0.01)
    proc = get_procedure("validate-arm")
    params = proc.params_model(intrinsics={k: cam[k] for k in ("fx", "fy", "cx", "cy")})
    steps = proc.plan(params, config)
    assert not check_plan(config, steps, proc.devices)
    notes = " ".join(s.text for s in steps if type(s).__name__ == "Note")
    assert "markers span 2.3 px per cell at 0.50 m, too few to decode: planned from 0.32 m" \
        in notes
    model = planning_arm(config).model
    moves = [s for s in steps if type(s).__name__ == "MoveArmJoints" and s.label != "arm home"]
    assert len(moves) == params.poses
    cells = [marker_cell_px(config, K, nominal_cam_target(config, model, s.q)[2, 3])
             for s in moves]
    assert min(cells) > 0.85 * MIN_MARKER_CELL_PX, cells
    assert np.median(cells) > 0.95 * MIN_MARKER_CELL_PX, cells
