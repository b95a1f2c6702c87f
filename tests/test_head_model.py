"""The head geometry's transforms (``rigctl.calib.head_model``) against the simulated
worlds' own head chain (``World.T_head_cam``, written independently), its aim, its
sigma and its record in a result."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.calib import head_model
from rigctl.calib.head_model import HeadGeometry
from rigctl.errors import SolveError
from rigctl.geometry.transforms import R_to_rotvec
from rigctl.mocks.random_world import random_world
from rigctl.mocks.world import World, WorldFile


def _truth(world: World) -> HeadGeometry:
    """The world's head as a geometry: no mounting rotation (the world has none), its
    roll axis's tilts and the camera's offset."""
    return HeadGeometry(mount_rotvec=np.zeros(3),
                        roll_tilts=np.radians(world.spec.head.roll_axis_tilt_deg),
                        offset_m=world.cam_offset, offset_estimated=True)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("seed", [3, 11015, 62019])
def test_home_to_camera_matches_the_worlds_head_chain(seed):
    world = World(WorldFile.model_validate(random_world(seed)))
    geometry = _truth(world)
    T0_inv = np.linalg.inv(world.T_head_cam(0.0, 0.0, 0.0))
    rng = np.random.default_rng(seed)
    for _ in range(20):
        angles = tuple(rng.uniform(-math.radians(60), math.radians(60), 3))
        expected = T0_inv @ world.T_head_cam(*angles)
        assert np.allclose(geometry.T_home_cam(angles), expected, atol=1e-12)
    assert np.allclose(geometry.roll_axis, world.roll_axis, atol=1e-12)


def _tilted() -> HeadGeometry:
    return HeadGeometry(mount_rotvec=np.radians([0.8, -1.1, 0.5]),
                        roll_tilts=np.radians([0.4, -0.3]),
                        offset_m=np.array([0.002, -0.003, 0.004]), offset_estimated=True)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("point", [(0.3, -0.2, 1.0), (-0.6, 0.4, 0.9), (0.0, 0.0, 0.5)])
def test_aim_puts_the_point_on_the_optical_axis(point):
    geometry = _tilted()
    pan, tilt = geometry.aim(np.array(point))
    T = geometry.T_home_cam((pan, tilt, 0.0))
    in_cam = T[:3, :3].T @ (np.array(point) - T[:3, 3])
    assert in_cam[2] > 0
    assert math.hypot(in_cam[0], in_cam[1]) / in_cam[2] < 1e-9
    # the closed form for N = I alone would miss by the mounting's degree or so
    plain = HeadGeometry(mount_rotvec=np.zeros(3), roll_tilts=np.zeros(2))
    if math.hypot(point[0], point[1]) > 0.1:
        assert abs(plain.aim(np.array(point))[0] - pan) > math.radians(0.05)


@pytest.mark.timeout(60)
def test_aim_refuses_a_point_behind_on_the_axis():
    with pytest.raises(SolveError, match="not in front"):
        _tilted().aim(np.array([0.0, 0.0, -1.0]))


@pytest.mark.timeout(60)
def test_rotation_sigma_is_honest_for_draws_from_its_covariance():
    """Parameters drawn from the covariance give rotation errors whose squared
    Mahalanobis norm averages 3 (chi-squared, 3 degrees of freedom) and whose per-axis
    spread is the reported sigma: the first-order propagation holds at these sizes."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(5, 5)) * math.radians(0.2)
    cov = A @ A.T
    geometry = HeadGeometry(mount_rotvec=np.radians([0.5, -0.4, 0.2]),
                            roll_tilts=np.radians([0.3, 0.1]), rotation_covariance=cov)
    angles = (math.radians(20), math.radians(-15), math.radians(30))
    draws = rng.multivariate_normal(geometry.rotation_params(), cov, size=2000)
    m2, errors = [], []
    for x in draws:
        R_true = geometry.rotation_from_home(angles, x)
        z = geometry.rotation_error_z(angles, R_true)
        m2.append(z[3] ** 2)
        errors.append(R_to_rotvec(geometry.rotation_from_home(angles) @ R_true.T))
    assert np.mean(m2) == pytest.approx(3.0, rel=0.1)
    spread = np.std(np.array(errors), axis=0)
    assert np.allclose(spread, geometry.rotation_sigma_rad(angles), rtol=0.1)


@pytest.mark.timeout(60)
def test_the_record_round_trips_and_bad_records_are_named():
    geometry = HeadGeometry(mount_rotvec=np.radians([0.5, -0.4, 0.2]),
                            roll_tilts=np.radians([0.3, 0.1]),
                            offset_m=np.array([0.001, 0.0, -0.002]), offset_estimated=True,
                            offset_sigma_m=np.full(3, 4e-4),
                            rotation_covariance=np.diag([1e-6, 2e-6, 3e-6, 4e-6, 5e-6]))
    again = head_model.from_result({"head_geometry": geometry.as_dict()})
    angles = (0.3, -0.2, 1.0)
    assert np.allclose(again.T_home_cam(angles), geometry.T_home_cam(angles), atol=1e-15)
    assert np.allclose(again.rotation_covariance, geometry.rotation_covariance)
    assert again.offset_estimated
    with pytest.raises(SolveError, match="run 7: no head_geometry"):
        head_model.from_result({"fx": 1000.0}, "run 7")
    broken = geometry.as_dict()
    del broken["roll_axis_tilts_rad"]
    with pytest.raises(SolveError, match=r"head_geometry is malformed.*roll_axis_tilts_rad"):
        head_model.from_result({"head_geometry": broken})
