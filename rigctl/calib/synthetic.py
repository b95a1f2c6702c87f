"""Synthetic data in the thesis's protocol (section 5.1.1): contours are sets of 3-D
points, projected and rounded to whole pixels, optionally with Gaussian noise.

Used by unit tests and benchmarks; ``project`` is the exact model of Lemma 3.1 with no
translation: a camera rotated by ``R`` (camera frame) sees ``X' = R^T X``.
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.geometry.camera import camera_matrix

# K of the synthetic cameras: the one builder of the intrinsic matrix (zero skew)
intrinsics = camera_matrix


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rot_axis(axis, a: float) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def make_contours(rng: np.random.Generator, count: int, points: int, K: np.ndarray,
                  size: tuple[int, int], depth=(2.0, 6.0), window: float = 0.5,
                  radius_px=(25.0, 60.0)) -> list[np.ndarray]:
    """``count`` closed planar contours (ellipses) of ``points`` 3-D points each, in the
    camera frame, whose images lie in the central ``window`` fraction of the image."""
    w, h = size
    Kinv = np.linalg.inv(K)
    out = []
    for _ in range(count):
        u = rng.uniform(w * (0.5 - window / 2), w * (0.5 + window / 2))
        v = rng.uniform(h * (0.5 - window / 2), h * (0.5 + window / 2))
        z = rng.uniform(*depth)
        centre = Kinv @ np.array([u, v, 1.0]) * z
        r = rng.uniform(*radius_px) * z / K[0, 0]
        t = np.linspace(0, 2 * math.pi, points, endpoint=False) + rng.uniform(0, 1)
        ratio = rng.uniform(0.5, 1.0)
        spin = rng.uniform(0, math.pi)
        local = np.c_[np.cos(t) * r, np.sin(t) * r * ratio]
        local = local @ np.array([[math.cos(spin), -math.sin(spin)],
                                  [math.sin(spin), math.cos(spin)]]).T
        tilt = rot_axis(rng.normal(size=3), math.radians(rng.uniform(0, 30)))
        pts = centre + (tilt @ np.c_[local, np.zeros(points)].T).T
        out.append(pts)
    return out


def project(points_cam: np.ndarray, K: np.ndarray, R: np.ndarray = None) -> np.ndarray:
    """Pixels of camera-frame points after the camera rotates by ``R``: ``K R^T X``."""
    X = points_cam if R is None else (R.T @ points_cam.T).T
    p = (K @ X.T).T
    return p[:, :2] / p[:, 2:3]


def observe(pixels: np.ndarray, rng: np.random.Generator, sigma: float = 0.0,
            rounding: bool = True) -> np.ndarray:
    """Add Gaussian noise of ``sigma`` pixels, then round to whole pixels (thesis 5.1.1)."""
    out = pixels + (rng.normal(0.0, sigma, pixels.shape) if sigma > 0 else 0.0)
    return np.round(out) if rounding else out
