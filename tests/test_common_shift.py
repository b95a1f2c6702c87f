"""One shift for every predicted contour at once (``rigctl.vision.tracking.common_shift``).

A roll predicted about a centre ``e`` px off is off by ``(I - R) e`` over the whole image:
2 e at 180 degrees, beyond any per-contour search window when the pans left the centre
20-30 px off (random worlds 70038 and 24). Searched for all contours together, the shift
is found, and a periodic scene, where a shift by one period fits nearly as well, gives
none rather than a wrong one."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from rigctl.vision.contours import edge_map, extract_contours
from rigctl.vision.tracking import common_shift, track_by_prediction

SIZE = (960, 720)


def _render(shapes: list[np.ndarray], shift=(0.0, 0.0)) -> np.ndarray:
    """Dark polygons (px) on a light ground, moved by ``shift``, blurred and noisy."""
    w, h = SIZE
    img = np.full((h, w), 220, np.uint8)
    for poly in shapes:
        pts = np.round((poly + shift) * 16).astype(np.int32)
        cv2.fillPoly(img, [pts], 30, cv2.LINE_AA, shift=4)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    noise = np.random.default_rng(3).standard_normal(img.shape) * 1.0
    return np.clip(img + noise + 0.5, 0, 255).astype(np.uint8)


def _scattered_shapes() -> list[np.ndarray]:
    """Twelve polygons of different sizes and turns, spread over the image."""
    rng = np.random.default_rng(11)
    shapes = []
    for k in range(12):
        centre = np.array([120 + (k % 4) * 230, 140 + (k // 4) * 220]) + rng.uniform(-30, 30, 2)
        sides = 3 + k % 4
        angles = np.linspace(0, 2 * np.pi, sides, endpoint=False) + rng.uniform(0, np.pi)
        radius = rng.uniform(35, 70)
        shapes.append(centre + radius * np.c_[np.cos(angles), np.sin(angles)])
    return shapes


def test_the_whole_scene_shift_is_found_beyond_the_per_contour_window():
    shapes = _scattered_shapes()
    ref = _render(shapes)
    contours = extract_contours(ref, 0.95, 40)
    assert len(contours) >= 10
    truth = np.array([41.0, -33.0])  # 53 px: far beyond a 24 px per-contour window
    moved = edge_map(_render(shapes, shift=truth))

    # each contour alone, searched +-24 px around the unshifted prediction, is lost
    alone = [track_by_prediction(c, moved, lambda p: p, window=24.0) for c in contours]
    assert sum(m.ok for m in alone) <= len(contours) // 4

    shift = common_shift([c.points for c in contours], moved, window=80.0)
    assert shift is not None
    assert np.hypot(*(np.array(shift) - truth)) <= 1.0  # whole pixels, then per contour
    after = [track_by_prediction(c, moved, lambda p, s=np.array(shift): p + s, window=24.0)
             for c in contours]
    assert sum(m.ok for m in after) >= 0.9 * len(contours)
    for contour, match in zip(contours, after, strict=True):
        if match.ok:  # the tracked edge points lie on the contour moved by the truth
            moved_truth = contour.points + truth
            _, nearest = cKDTree(moved_truth).query(match.points)
            across = np.sum((match.points - moved_truth[nearest]) * contour.normals[nearest],
                            axis=1)
            assert np.median(np.abs(across)) < 0.25  # px; a wrong match: >= 1


def test_a_periodic_scene_gives_no_shift_rather_than_a_wrong_one():
    # a grid of identical squares every 60 px: shifted by one period it fits as well
    squares = [np.array([[x, y], [x + 30, y], [x + 30, y + 30], [x, y + 30]], float)
               for x in range(60, 900, 60) for y in range(60, 660, 60)]
    ref = _render(squares)
    contours = extract_contours(ref, 0.95, 40)
    assert len(contours) >= 50
    moved = edge_map(_render(squares, shift=(12.0, 7.0)))
    assert common_shift([c.points for c in contours], moved, window=80.0) is None
    # within a quarter of a period (a shift by half of it lays every edge on another
    # square's) the shift is unambiguous again
    shift = common_shift([c.points for c in contours], moved, window=15.0)
    assert shift is not None and np.hypot(shift[0] - 12.0, shift[1] - 7.0) <= 1.0


def test_nothing_to_lay_on_the_edges_gives_no_shift():
    blank = edge_map(np.full((SIZE[1], SIZE[0]), 128, np.uint8))
    contour = np.array([[100.0 + i, 200.0] for i in range(50)])
    assert common_shift([contour], blank, window=40.0) is None
    assert common_shift([], blank, window=40.0) is None
