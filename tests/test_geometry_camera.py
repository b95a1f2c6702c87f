"""The vectorised projection against OpenCV's own projectPoints (an independent
implementation of the same model): random poses, points and distortion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigctl.errors import SolveError
from rigctl.geometry.camera import camera_matrix, invert_batch, project_batch


def _random_pose(rng):
    rvec = rng.normal(scale=0.3, size=3)
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [rng.normal(scale=0.05), rng.normal(scale=0.05), 0.5]
    return T, rvec


@pytest.mark.parametrize("dist", [None, [-0.2, 0.08, 0.001, -0.002, -0.01],
                                  [0.1, -0.05, 0.002, 0.001, 0.01, 0.02, -0.01, 0.005]])
def test_project_batch_matches_opencv(dist):
    rng = np.random.default_rng(7)
    K = camera_matrix(910.0, 905.0, 641.0, 362.0)
    pts = rng.uniform(-0.1, 0.1, size=(30, 3)) * [1, 1, 0.2]
    poses = [_random_pose(rng) for _ in range(6)]
    ours = project_batch(np.array([T for T, _ in poses]), pts, K, dist)
    d = np.zeros(5) if dist is None else np.asarray(dist, float)
    for (T, rvec), got in zip(poses, ours, strict=True):
        ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, T[:3, 3], K, d)
        assert np.max(np.abs(got - ref.reshape(-1, 2))) < 1e-8


def test_invert_batch_and_unsupported_terms():
    rng = np.random.default_rng(3)
    T = np.array([_random_pose(rng)[0] for _ in range(4)])
    assert np.allclose(invert_batch(T) @ T, np.eye(4), atol=1e-12)
    with pytest.raises(SolveError, match="thin-prism"):
        project_batch(T, np.array([[0, 0, 0.1]]), np.eye(3), np.r_[np.zeros(8), 0.1])
