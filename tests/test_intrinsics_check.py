"""The intrinsics check (Zhang on board views) on synthetic views with known truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigctl.calib.board import board_points
from rigctl.calib.intrinsics_check import board_intrinsics
from rigctl.errors import SolveError
from rigctl.geometry.transforms import look_at

K = np.array([[900.0, 0, 652.3], [0, 905.0, 371.8], [0, 0, 1]])
DIST = np.array([-0.08, 0.05, 0.0004, -0.0003, -0.01])  # the default world's lens
OBJ = board_points(7, 10, 0.03)


def views(n: int, seed: int = 0, sigma_px: float = 0.2) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    centre = np.array([0.15, 0.105, 0.0])
    out = []
    while len(out) < n:
        tilt, az = np.radians(rng.uniform(10, 45)), rng.uniform(0, 2 * np.pi)
        eye = centre + rng.uniform(0.35, 0.6) * np.array(
            [np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        spin = rng.uniform(0, 2 * np.pi)
        T_cam_target = np.linalg.inv(look_at(eye, centre, [np.cos(spin), np.sin(spin), 0]))
        px, _ = cv2.projectPoints(OBJ.reshape(-1, 1, 3), cv2.Rodrigues(T_cam_target[:3, :3])[0],
                                  T_cam_target[:3, 3], K, DIST)
        px = px.reshape(-1, 2)
        if np.all((px > 20) & (px < [1260, 700])):
            out.append(px + rng.normal(0, sigma_px, px.shape))
    return out


def test_board_views_recover_the_principal_point_and_flag_a_biased_one():
    truth = {"fx": 900.0, "fy": 905.0, "cx": 652.3, "cy": 371.8}
    board_views = views(60)
    check = board_intrinsics(OBJ, board_views, (1280, 720), truth)
    for key in ("cx", "cy"):
        assert abs(check["board"][key] - truth[key]) < 3 * check["sigma"][key]
        assert 0.1 < check["sigma"][key] < 1.0
        assert abs(check["used_minus_board_sigma"][key]) < 3
    assert abs(check["board"]["fx"] / 900.0 - 1) < 0.003
    assert check["agrees"] and check["rms_px"] == pytest.approx(0.2 * np.sqrt(2), abs=0.03)
    # intrinsics in use that are 3 px off in cy are flagged
    flagged = board_intrinsics(OBJ, board_views, (1280, 720), truth | {"cy": 368.8})
    assert not flagged["agrees"] and "cy" in flagged["note"]
    assert flagged["used_minus_board_px"]["cy"] == pytest.approx(
        check["used_minus_board_px"]["cy"] - 3.0, abs=1e-4)
    with pytest.raises(SolveError, match="need 10"):
        board_intrinsics(OBJ, views(5), (1280, 720), truth)
