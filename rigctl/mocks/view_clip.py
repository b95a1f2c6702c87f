"""Polygons clipped to the part of space the simulated camera can draw.

The renderer projects polygon outlines through OpenCV's distortion, which folds back
beyond a few times the image's half-width: a point far outside the view would land
inside the image. A polygon that reaches that far used to be dropped whole, so a board
close to the camera vanished in one view and filled the next after a 10 mm move. Each
polygon is instead cut (Sutherland-Hodgman, in the camera frame) to the pyramid
``z >= near``, ``|x| <= lim_x z``, ``|y| <= lim_y z``; the cut edges lie outside the
image and are sampled as finely as a straight edge needs to bend with the distortion.
"""

from __future__ import annotations

import numpy as np

# points per unit of normalised image length along the edges of a cut polygon
CUT_EDGE_DENSITY = 40.0


def _planes(lim_x: float, lim_y: float, near: float) -> list[tuple[np.ndarray, float]]:
    """Half-spaces ``n . p >= c`` bounding the drawable pyramid: the four sides (which
    already exclude ``z < 0``), then the near plane."""
    return [(np.array([-1.0, 0.0, lim_x]), 0.0), (np.array([1.0, 0.0, lim_x]), 0.0),
            (np.array([0.0, -1.0, lim_y]), 0.0), (np.array([0.0, 1.0, lim_y]), 0.0),
            (np.array([0.0, 0.0, 1.0]), near)]


def _clip_one(points: np.ndarray, normal: np.ndarray, c: float) -> np.ndarray:
    """One Sutherland-Hodgman pass: the part of the polygon where ``n . p >= c``."""
    s = points @ normal - c
    out = []
    n = len(points)
    for k in range(n):
        a, b = points[k], points[(k + 1) % n]
        sa, sb = s[k], s[(k + 1) % n]
        if sa >= 0:
            out.append(a)
        if (sa >= 0) != (sb >= 0):
            out.append(a + (b - a) * (sa / (sa - sb)))
    return np.array(out).reshape(-1, 3)


def _densify(points: np.ndarray) -> np.ndarray:
    """Points inserted along each edge (the cut ones are long), as many as its length in
    normalised image coordinates needs to bend with the distortion."""
    out = []
    n = len(points)
    for k in range(n):
        a, b = points[k], points[(k + 1) % n]
        length = np.hypot(*(b[:2] / b[2] - a[:2] / a[2]))
        m = max(int(np.ceil(length * CUT_EDGE_DENSITY)), 1)
        out += [a + (b - a) * f for f in np.arange(m) / m]
    return np.array(out)


def clip_to_view(points: np.ndarray, lim_x: float, lim_y: float, near: float) -> np.ndarray:
    """The polygon ``points`` (camera frame, N x 3, in order) cut to the drawable pyramid
    and resampled; unchanged when it lies inside, empty (0 x 3) when nothing of it does."""
    inside = (points[:, 2] >= near) & (np.abs(points[:, 0]) <= lim_x * points[:, 2]) & \
        (np.abs(points[:, 1]) <= lim_y * points[:, 2])
    if inside.all():
        return points
    for normal, c in _planes(lim_x, lim_y, near):
        points = _clip_one(points, normal, c)
        if len(points) < 3:
            return np.empty((0, 3))
    return _densify(points)
