"""Rigid transforms. ``T_a_b`` maps points of frame b into frame a (4x4, metres)."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R=None, t=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def rotvec_to_R(rv) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rv, float)).as_matrix()


def R_to_rotvec(R) -> np.ndarray:
    """The rotation vector of one rotation matrix ``R``, from its unit quaternion by
    Shepperd's choice of the largest diagonal term. scipy's ``Rotation.from_matrix``
    computes the same (within 1e-15 rad on random rotations), at a tenth of the speed
    for one matrix: the IK's every step, and every view of every evaluation of the
    hand-eye and arm refinements."""
    r = np.asarray(R, float).tolist()
    tr = r[0][0] + r[1][1] + r[2][2]
    k = max(range(4), key=(tr, r[0][0], r[1][1], r[2][2]).__getitem__)
    if k == 0:
        w = math.sqrt(1.0 + tr) / 2.0
        x, y, z = ((r[2][1] - r[1][2]) / (4 * w), (r[0][2] - r[2][0]) / (4 * w),
                   (r[1][0] - r[0][1]) / (4 * w))
    elif k == 1:
        x = math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2]) / 2.0
        w, y, z = ((r[2][1] - r[1][2]) / (4 * x), (r[0][1] + r[1][0]) / (4 * x),
                   (r[0][2] + r[2][0]) / (4 * x))
    elif k == 2:
        y = math.sqrt(1.0 - r[0][0] + r[1][1] - r[2][2]) / 2.0
        w, x, z = ((r[0][2] - r[2][0]) / (4 * y), (r[0][1] + r[1][0]) / (4 * y),
                   (r[1][2] + r[2][1]) / (4 * y))
    else:
        z = math.sqrt(1.0 - r[0][0] - r[1][1] + r[2][2]) / 2.0
        w, x, y = ((r[1][0] - r[0][1]) / (4 * z), (r[0][2] + r[2][0]) / (4 * z),
                   (r[1][2] + r[2][1]) / (4 * z))
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    norm = math.sqrt(x * x + y * y + z * z)
    angle = 2.0 * math.atan2(norm, w)
    # angle / sin(angle / 2), by its series near zero
    scale = 2.0 + angle ** 2 / 12.0 + 7.0 * angle ** 4 / 2880.0 if angle < 1e-3 else \
        angle / math.sin(angle / 2.0)
    return np.array([scale * x, scale * y, scale * z])


def rpy_deg_to_R(rpy_deg) -> np.ndarray:
    """``[roll, pitch, yaw]`` in degrees to ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    return Rotation.from_euler("ZYX", np.asarray(rpy_deg, float)[::-1], degrees=True).as_matrix()


def xyz_rpy_to_T(xyz_mm, rpy_deg) -> np.ndarray:
    return make_T(rpy_deg_to_R(rpy_deg), np.asarray(xyz_mm, float) / 1000.0)


def rotation_angle(R) -> float:
    """Angle (rad) of a rotation matrix."""
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def look_at(eye, target, up_hint=(0.0, 1.0, 0.0)) -> np.ndarray:
    """``T_base_cam`` of an optical frame (z forward, y down) at ``eye`` looking at
    ``target``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up_hint, float), z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)
