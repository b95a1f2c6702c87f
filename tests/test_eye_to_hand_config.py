"""The head beside the arm in the rig and world files: the keys, the combinations refused
(naming the keys, exit 2), a board on the flange rendered where the arm holds it, and the
random worlds of each mounting."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

from rigctl.config import parse_rig
from rigctl.errors import ConfigError
from rigctl.mocks.random_world import random_world
from rigctl.mocks.world import World, WorldFile, load_world
from tests.mockproc import ROOT, rig_without_devices

pytestmark = pytest.mark.timeout(120)

FIXED_HEAD = """\
  head:
    port: /dev/null
    mount: fixed
    fixed_pose: {xyz_mm: [-1090, 220, 580], rpy_deg: [-112, 0, -104]}
  arm: {host: 127.0.0.1}
  camera: {device: 0, width: 1280, height: 720}
"""


def _rig(head: str = FIXED_HEAD, target: str = "target: {mount: flange}\n") -> str:
    return "name: t\ndevices:\n" + head + target


def test_fixed_head_needs_its_pose_and_only_it_takes_one():
    config = parse_rig(_rig())
    assert config.devices.head.fixed and config.target.mount == "flange"
    with pytest.raises(ConfigError, match=r"devices\.head: .*fixed_pose"):
        parse_rig(_rig(FIXED_HEAD.replace("    fixed_pose: {xyz_mm: [-1090, 220, 580], "
                                          "rpy_deg: [-112, 0, -104]}\n", "")))
    with pytest.raises(ConfigError, match="fixed_pose is a key of a head standing beside"):
        parse_rig(_rig(FIXED_HEAD.replace("mount: fixed", "mount: flange")))
    with pytest.raises(ConfigError, match=r"target\.mount"):
        parse_rig(_rig(target="target: {mount: table}\n"))


@pytest.mark.parametrize("head, target, keys", [
    (FIXED_HEAD, "", "devices.head.mount: fixed with target.mount: world"),
    (FIXED_HEAD.replace("mount: fixed", "mount: flange").replace(
        "    fixed_pose: {xyz_mm: [-1090, 220, 580], rpy_deg: [-112, 0, -104]}\n", ""),
     "target: {mount: flange}\n", "target.mount: flange with the camera on the flange")])
def test_hand_eye_refuses_a_rig_where_the_arm_moves_nothing(tmp_path, head, target, keys):
    rig = tmp_path / "rig.yaml"
    rig.write_text(_rig(head, target) + "records: {directory: records}\n")
    done = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "hand-eye", "--rig",
                           str(rig), "--dry-run"], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)
    assert done.returncode == 2, done.stderr[-2000:]
    assert keys in done.stderr


def test_world_refuses_camera_and_board_both_on_the_flange():
    data = random_world(300001)
    data["target"]["mount"] = "flange"
    with pytest.raises(ValueError, match=r"head\.mount: flange with target\.mount: flange"):
        WorldFile.model_validate(data)


def test_a_board_on_the_flange_moves_with_the_arm(tmp_path):
    from rigctl.calib.board import detect_target
    from rigctl.procedures.planning_e2h import board_views

    world = load_world("eye_to_hand")
    truth = world.truth()
    assert np.allclose(truth["T_base_cam"], world.T_base_cam(world.home_q, (0, 0, 0)))
    rig = parse_rig(yaml.safe_dump(rig_without_devices(tmp_path / "w.yaml", tmp_path,
                                                       "records", world)))
    (q0, q, *_), _ = board_views(rig, 4, 0.45, 30.0, 3, world.K)
    assert np.allclose(world.T_base_target_at(q),
                       world.arm_true.flange(q) @ np.array(truth["T_flange_target"]))
    cam = world.T_base_cam(q, (0, 0, 0))
    assert np.allclose(cam, truth["T_base_cam"])  # the camera does not move
    a, b = world.target_corner_pixels(cam, q0), world.target_corner_pixels(cam, q)
    assert np.max(np.abs(a - b)) > 20  # px: the board moved in the image
    # the rendered board is where its corners project
    found = detect_target(world.render(cam, noise=False, q=q), rig.target).corners
    assert found is not None
    d = np.linalg.norm(np.asarray(found)[:, None, :] - b[None], axis=2).min(axis=1)
    assert np.median(d) < 0.3  # px


@pytest.mark.parametrize("seed", [300002, 300003, 300006])
def test_random_worlds_draw_a_fixed_head_watching_the_flange(seed):
    data = random_world(seed, target="either", mount="fixed")
    world = World(WorldFile.model_validate(data))
    assert data["head"]["mount"] == "fixed" and data["target"]["mount"] == "flange"
    # the camera looks at the arm's front workspace: the flange at home is ahead of it
    cam = world.T_base_cam(world.home_q, (0, 0, 0))
    ahead = (np.linalg.inv(cam) @ np.r_[world.arm_true.flange(world.home_q)[:3, 3], 1])[2]
    assert ahead > 0.2
    same = random_world(seed)  # the rest of the world is the seed's own
    assert same["camera"] == data["camera"] and same["arm"] == data["arm"]


def test_procedures_planning_views_of_a_board_in_the_world_refuse_a_fixed_head(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text(_rig() + "records: {directory: records}\n")
    done = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "capture-survey",
                           "--rig", str(rig), "--dry-run"],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "with the head beside the arm" in done.stderr
