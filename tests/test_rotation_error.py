"""The rotation vector of one matrix (``transforms.R_to_rotvec``, the IK's pose error)
against scipy's."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rigctl.geometry.kinematics import nominal_ur
from rigctl.geometry.transforms import R_to_rotvec


def test_rotation_error_is_scipys_rotation_vector():
    rotations = list(Rotation.random(3000, random_state=7).as_matrix())
    # each of Shepperd's four branches, tiny angles (the series) and angles near pi
    for angle in (1e-9, 1e-5, 9e-4, 1.1e-3, 0.5, 2.0, np.pi - 1e-3):
        for axis in (*np.eye(3), np.ones(3) / np.sqrt(3)):
            rotations.append(Rotation.from_rotvec(angle * axis).as_matrix())
    for R in rotations:
        expected = Rotation.from_matrix(R).as_rotvec()
        assert np.allclose(R_to_rotvec(R), expected, rtol=1e-12, atol=1e-14), R


def test_ik_reaches_random_poses_of_a_ur5e():
    model = nominal_ur("ur5e")
    rng = np.random.default_rng(3)
    for _ in range(20):
        q_true = rng.uniform(-2.5, 2.5, 6)
        q = model.ik(model.fk(q_true), q_true + rng.normal(0, 0.2, 6))
        assert np.allclose(model.fk(q), model.fk(q_true), atol=1e-9)
