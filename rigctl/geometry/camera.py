"""The pinhole camera with OpenCV's distortion model, vectorised over many poses.

``project_batch`` is ``cv2.projectPoints`` for K poses of one point set at once: the
refinements evaluate every capture's projection thousands of times, and one numpy pass
over all captures costs what one ``projectPoints`` call per capture did. Model (OpenCV
calib3d, thesis eq. 2.3 with Brown's radial and tangential terms): x' = X/Z, y' = Y/Z,
r^2 = x'^2 + y'^2,
x'' = x' (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
      + 2 p1 x'y' + p2 (r^2 + 2 x'^2),
y'' = y' (same radial factor) + p1 (r^2 + 2 y'^2) + 2 p2 x'y',
u = fx x'' + cx, v = fy y'' + cy  (zero skew).
"""

from __future__ import annotations

import numpy as np

from rigctl.errors import SolveError


def camera_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The 3x3 intrinsic matrix K (zero skew), thesis eq. (2.2)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def distortion_coefficients(dist) -> tuple[float, ...]:
    """k1 k2 p1 p2 k3 k4 k5 k6 of OpenCV's ``dist`` (zeros where it is shorter); thin-prism
    and tilt terms are refused."""
    d = np.zeros(8)
    dist = np.asarray(dist if dist is not None else [], float).ravel()
    if len(dist) > 8 and np.any(dist[8:] != 0):
        raise SolveError("project_batch: thin-prism and tilt distortion terms are not "
                         "supported (at most k1 k2 p1 p2 k3 k4 k5 k6)")
    d[:min(len(dist), 8)] = dist[:8]
    return tuple(float(v) for v in d)


def project_batch(T_cam_obj: np.ndarray, points_obj: np.ndarray, K: np.ndarray,
                  dist=None) -> np.ndarray:
    """Pixels of ``points_obj`` (N, 3) seen from each pose ``T_cam_obj`` (P, 4, 4):
    (P, N, 2). Same model and result as ``cv2.projectPoints`` (eq. 2.3 with distortion)."""
    T = np.asarray(T_cam_obj, float).reshape(-1, 4, 4)
    pts = np.asarray(points_obj, float).reshape(-1, 3)
    cam = np.einsum("pij,nj->pni", T[:, :3, :3], pts) + T[:, None, :3, 3]
    x, y = cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2]
    k1, k2, p1, p2, k3, k4, k5, k6 = distortion_coefficients(dist)
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xy = x * y
    xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)


def invert_batch(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (P, 4, 4): [R^T, -R^T t]."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("pij,pj->pi", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out
