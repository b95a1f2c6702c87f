"""The robot-kinematics plan with the head beside the arm: training views from head
stations when the intrinsics came with the head's geometry, each capture naming its
station and the head turned to it first; the sweeps and held-out views at home; the
head still, and saying why, without a geometry, with ``head_stations`` off, or where
the head's soft limits leave no station."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.calib.head_model import HeadGeometry
from rigctl.config import parse_rig
from rigctl.procedures.base import CaptureStep, MoveHead, Note
from rigctl.procedures.planning_e2h import NO_HEAD_GEOMETRY_NOTE, head_stations
from rigctl.procedures.robot_e2h import plan_eye_to_hand
from rigctl.procedures.robot_kinematics import RobotKinematicsParams

pytestmark = pytest.mark.timeout(300)

RIG = """\
name: t
devices:
  head:
    port: /dev/null
    mount: fixed
    fixed_pose: {{xyz_mm: [-1093.8, 222.0, 581.0], rpy_deg: [-112, 0, -104.32]}}
    limits: {{pan: {pan}, tilt: [-45, 45]}}
  arm: {{host: 127.0.0.1, model: ur5e}}
  camera: {{device: 0, width: 1280, height: 720}}
target: {{mount: flange, rows: 6, cols: 8, square_mm: 25,
         pose: {{xyz_mm: [0, 0, 30], rpy_deg: [180, 0, 0]}}}}
"""
INTRINSICS = {"fx": 900.0, "fy": 905.0, "cx": 652.3, "cy": 371.8,
              "distortion": [-0.08, 0.05, 0.0, 0.0, 0.0]}
GEOMETRY = HeadGeometry(mount_rotvec=np.radians([0.02, -0.02, 0.01]),
                        roll_tilts=np.radians([0.3, 0.0]),
                        rotation_covariance=np.diag(np.radians([0.04] * 5) ** 2))


def _plan(pan_limits=(-90, 90), geometry=True, **params):
    config = parse_rig(RIG.format(pan=list(pan_limits)))
    intrinsics = INTRINSICS | ({"head_geometry": GEOMETRY.as_dict()} if geometry else {})
    p = RobotKinematicsParams(intrinsics=intrinsics, use_controller_model=False,
                              sweep_steps=2, random_poses=12, heldout_poses=3, **params)
    return config, plan_eye_to_hand(p, config)


def _captures_by_head(steps) -> list[tuple[tuple, dict]]:
    """Each capture with the head angles (deg) it was taken at."""
    head, out = None, []
    for step in steps:
        if isinstance(step, MoveHead):
            head = tuple(round(math.degrees(a), 6) for a in (step.pan, step.tilt, step.roll))
        elif isinstance(step, CaptureStep):
            out.append((head, step.extra))
    return out


def test_training_views_come_from_head_stations_and_the_rest_from_home():
    config, steps = _plan()
    stations = [tuple(round(math.degrees(a), 6) for a in s)
                for s in head_stations(config, np.array([[900.0, 0, 652.3], [0, 905.0, 371.8],
                                                         [0, 0, 1]]))]
    # half the field of view, at most 25 deg pan and 20 deg tilt
    assert stations == [(0, 0, 0), (25, 0, 0), (-25, 0, 0), (0, 20, 0), (0, -20, 0)]
    taken = _captures_by_head(steps)
    used = set()
    for head, extra in taken:
        assert head == stations[extra.get("station", 0)], (head, extra)
        if extra["kind"] != "train":
            assert extra.get("station", 0) == 0 and head == (0, 0, 0), extra
        used.add(extra.get("station", 0))
    assert len(used) >= 3, used  # home and at least two stations away
    assert sum(extra["kind"] == "train" for _, extra in taken) == 12
    last_head = [s for s in steps if isinstance(s, MoveHead)][-1]
    assert (last_head.pan, last_head.tilt, last_head.roll) == (0.0, 0.0, 0.0)
    assert any(isinstance(s, Note) and "head stations" in s.text for s in steps)


def test_the_head_stays_home_without_its_geometry_or_when_told():
    for kwargs, why in (({"geometry": False}, NO_HEAD_GEOMETRY_NOTE),
                        ({"head_stations": False}, "head_stations is off")):
        _, steps = _plan(**kwargs)
        heads = {(s.pan, s.tilt, s.roll) for s in steps if isinstance(s, MoveHead)}
        assert heads == {(0.0, 0.0, 0.0)}, (kwargs, heads)
        assert all(extra.get("station", 0) == 0 for _, extra in _captures_by_head(steps))
        assert any(isinstance(s, Note) and why in s.text for s in steps), kwargs


def test_stations_beyond_the_heads_soft_limits_are_not_planned():
    _, steps = _plan(pan_limits=(-10, 10))
    heads = {tuple(round(math.degrees(a), 6) for a in (s.pan, s.tilt, s.roll))
             for s in steps if isinstance(s, MoveHead)}
    # the 25 deg pans are beyond the limits; the tilts remain
    assert all(pan == 0 for pan, _, _ in heads), heads
    assert heads & {(0, 20, 0), (0, -20, 0)}, heads
