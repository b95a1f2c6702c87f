"""Contours when a board fills the view: its squares' outlines join at the corners into
one edge network that reaches the image's border, so the closed-contour extraction finds
nothing; cut into tiles it gives pieces that track a known shift to a small fraction of a
pixel (random world 9001, a UR3e close to its board, failed with "too few contours")."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from rigctl.vision.contours import edge_map, extract_contours
from rigctl.vision.tracking import track_by_prediction

SIZE = (1280, 720)
SUPERSAMPLE = 4


def _board_image(shift=(0.0, 0.0), square=97.0, angle_deg=8.0) -> np.ndarray:
    """A checkerboard larger than the image, turned, area-sampled, blurred and noisy."""
    w, h = SIZE
    big = np.full((h * SUPERSAMPLE, w * SUPERSAMPLE), 235, np.uint8)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    R = np.array([[c, -s], [s, c]])
    origin = np.array([-300.0, -300.0]) + shift
    for i in range(-2, 22):
        for j in range(-2, 22):
            if (i + j) % 2:
                continue
            corners = np.array([[j, i], [j + 1, i], [j + 1, i + 1], [j, i + 1]]) * square
            px = corners @ R.T + origin
            fine = (px + 0.5) * SUPERSAMPLE - 0.5
            cv2.fillPoly(big, [np.round(fine * 16).astype(np.int32)], 20, cv2.LINE_8, shift=4)
    img = cv2.resize(big, SIZE, interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 1.1)
    noise = np.random.default_rng(7).standard_normal(img.shape) * 0.5
    return np.clip(img + noise + 0.5, 0, 255).astype(np.uint8)


def test_a_board_filling_the_view_is_taken_piece_by_piece():
    image = _board_image()
    emap = edge_map(image)
    closed = extract_contours(image, 0.95, 40, emap=emap)
    tiled = extract_contours(image, 0.95, 40, emap=emap, tile=160)
    assert len(closed) < 3  # the whole board is one edge network
    assert len(tiled) >= 20
    moved_by = (7.3, -4.6)
    moved = edge_map(_board_image(shift=moved_by))
    distances = []
    for contour in tiled:
        # a prediction 5 px off, as from a first focal length
        match = track_by_prediction(contour, moved, lambda p: p + np.array([3.0, 0.0]), window=12.0)
        if match.ok:
            # the tracked edge points lie on the reference contour moved by the truth
            truth = contour.points + moved_by
            _, nearest = cKDTree(truth).query(match.points)
            across = np.sum((match.points - truth[nearest]) * contour.normals[nearest], axis=1)
            distances.append(np.median(np.abs(across)))
    assert len(distances) >= 0.8 * len(tiled)
    assert max(distances) < 0.25  # px across the edge (median 0.09; a wrong match: >= 1)
