"""Random plausible worlds (``rigctl sim world --random SEED``): every draw is a valid
world file within the ranges the generator promises, the same seed gives the same rig,
and the CLI writes a file the simulator loads."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np

from rigctl.mocks.random_world import REACH_M, random_world
from rigctl.mocks.world import World, WorldFile, load_world

SEEDS = range(60)


def test_draws_stay_within_the_promised_ranges():
    models = set()
    for seed in SEEDS:
        data = random_world(seed)
        world = World(WorldFile.model_validate(data))
        cam = data["camera"]
        assert 600 <= cam["fx"] <= 1600
        assert abs(cam["fy"] / cam["fx"] - 1) <= 0.02 + 1e-9
        assert abs(cam["cx"] - (cam["width"] - 1) / 2) <= 30 + 1e-9
        assert abs(cam["cy"] - (cam["height"] - 1) / 2) <= 30 + 1e-9
        k1, k2, p1, p2, k3 = cam["distortion"]
        assert k3 != 0 and abs(p1) < 0.005 and abs(p2) < 0.005
        # the radial map is monotonic out past the image corner: no fold-over
        r = np.linspace(0, 1.15 * math.hypot(cam["width"] / 2, cam["height"] / 2) / cam["fx"],
                        100)
        assert np.all(1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4 + 7 * k3 * r ** 6 > 0)
        assert np.hypot(*data["head"]["roll_axis_tilt_deg"]) <= 0.5 + 1e-9
        assert np.linalg.norm(data["head"]["camera_offset_mm"]) <= 3.0 + 1e-9
        model = data["arm"]["model"]
        models.add(model)
        # the board's centre lies within the arm's comfortable reach, in front of it
        T = world.T_base_target
        half = np.array([data["target"]["cols"], data["target"]["rows"], 0]) * \
            data["target"]["square_mm"] / 2000
        centre = T[:3, :3] @ half + T[:3, 3]
        assert 0.4 * REACH_M[model] < np.hypot(*centre[:2]) < 0.8 * REACH_M[model]
        assert centre[0] < 0
        # the board faces up, tilted at most 15 degrees
        assert math.degrees(math.acos(-T[2, 2])) <= 15 + 1e-6
        # hand-eye: a few degrees of tilt, any yaw
        assert np.hypot(*data["hand_eye"]["rpy_deg"][:2]) <= 4 + 1e-9
    assert models == {"ur3e", "ur5e", "ur10e"}


def test_the_same_seed_draws_the_same_rig():
    assert random_world(7) == random_world(7)
    assert random_world(7) != random_world(8)


def test_cli_writes_a_world_the_simulator_loads(tmp_path):
    out = tmp_path / "world.yaml"
    proc = subprocess.run([sys.executable, "-m", "rigctl.cli", "sim", "world", "--random", "11",
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    world = load_world(out)
    assert world.spec.model_dump() == WorldFile.model_validate(random_world(11)).model_dump()
