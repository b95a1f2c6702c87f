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


def _following(values: np.ndarray) -> np.ndarray:
    """Each row's successor around the polygon (the first after the last)."""
    return np.concatenate((values[1:], values[:1]))


def _clip_one(points: np.ndarray, normal: np.ndarray, c: float) -> np.ndarray:
    """One Sutherland-Hodgman pass: the part of the polygon where ``n . p >= c``. Each
    vertex in order: itself when inside, then where its edge to the next one crosses
    the plane (``a + (b - a) sa / (sa - sb)``), all edges at once."""
    s = points @ normal - c
    following, s_following = _following(points), _following(s)
    inside = s >= 0
    crosses = np.flatnonzero(inside != (s_following >= 0))
    candidates = np.empty((len(points), 2, 3))  # (n, 2, 3): each vertex, then its cut
    candidates[:, 0] = points
    a, b, sa, sb = points[crosses], following[crosses], s[crosses], s_following[crosses]
    candidates[crosses, 1] = a + (b - a) * (sa / (sa - sb))[:, None]
    keep = np.zeros((len(points), 2), bool)
    keep[:, 0] = inside
    keep[crosses, 1] = True
    return candidates[keep]


def _densify(points: np.ndarray) -> np.ndarray:
    """Points inserted along each edge (the cut ones are long), as many as its length in
    normalised image coordinates needs to bend with the distortion: edge ``a -> b`` in
    ``m`` steps, ``a + (b - a) j / m`` for j = 0 .. m - 1."""
    following = _following(points)
    step = following[:, :2] / following[:, 2:3] - points[:, :2] / points[:, 2:3]
    length = np.hypot(step[:, 0], step[:, 1])
    m = np.maximum(np.ceil(length * CUT_EDGE_DENSITY).astype(int), 1)
    edge = np.repeat(np.arange(len(points)), m)
    j = np.arange(len(edge)) - np.repeat(np.cumsum(m) - m, m)
    f = j / m[edge]
    a = points[edge]
    return a + (following[edge] - a) * f[:, None]


def clip_to_view(points: np.ndarray, lim_x: float, lim_y: float, near: float) -> np.ndarray:
    """The polygon ``points`` (camera frame, N x 3, in order) cut to the drawable pyramid
    and resampled; unchanged when it lies inside, empty (0 x 3) when nothing of it does."""
    inside = (points[:, 2] >= near) & (np.abs(points[:, 0]) <= lim_x * points[:, 2]) & \
        (np.abs(points[:, 1]) <= lim_y * points[:, 2])
    if inside.all():
        return points
    planes = _planes(lim_x, lim_y, near)
    # wholly outside one of the planes: nothing of it is left after all of them (most of
    # a ChArUco board's cells, near the camera)
    if any(np.all(points @ normal - c < 0) for normal, c in planes):
        return np.empty((0, 3))
    for normal, c in planes:
        points = _clip_one(points, normal, c)
        if len(points) < 3:
            return np.empty((0, 3))
    return _densify(points)
