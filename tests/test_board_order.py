"""A board whose pattern is unchanged by a half turn (rows + cols even), or by a quarter
turn when square, gives its corners in an order the image cannot settle: the order is
taken from where the nominal arm predicts the corners (random world 3010's 7 x 7 board
gave hand-eye closed forms 34-97 deg apart before)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigctl.calib.board import (
    board_points,
    detect_board,
    orient_to_prediction,
    squares_alternate,
    symmetric,
)


def _pixels(obj: np.ndarray, rvec, tvec) -> np.ndarray:
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    out, _ = cv2.projectPoints(obj, np.asarray(rvec, float), np.asarray(tvec, float), K,
                               np.zeros(5))
    return out.reshape(-1, 2)


@pytest.mark.parametrize(("rows", "cols", "turns"), [(7, 7, 1), (7, 7, 2), (7, 7, 3),
                                                      (8, 10, 2), (6, 6, 2)])
def test_the_detected_order_is_turned_back_to_the_predicted_one(rows, cols, turns):
    obj = board_points(rows, cols, 0.02)
    truth = _pixels(obj, [0.1, -0.2, 0.3], [-0.05, -0.04, 0.5])
    grid = truth.reshape(rows - 1, cols - 1, 2)
    detected = (np.rot90(grid, turns) if rows == cols else grid[::-1, ::-1]).reshape(-1, 2)
    # the prediction (nominal arm, rounded mounts) is off by a few degrees and centimetres
    predicted = _pixels(obj, [0.13, -0.17, 0.36], [-0.03, -0.05, 0.52])
    assert symmetric(rows, cols)
    assert np.allclose(orient_to_prediction(detected, predicted, rows, cols), truth)


def test_a_board_the_image_orders_is_left_as_detected():
    obj = board_points(7, 8, 0.02)
    truth = _pixels(obj, [0.1, -0.2, 0.3], [-0.05, -0.04, 0.5])
    reversed_ = truth[::-1].copy()
    assert not symmetric(7, 8)
    assert np.array_equal(orient_to_prediction(reversed_, truth, 7, 8), reversed_)


@pytest.mark.parametrize("seed", [4015, 3010])
def test_a_grid_found_one_square_off_is_refused(seed):
    """The board rendered by a random world's own renderer: its detection is kept; the
    same grid moved one square along a row (outer nodes on the white margin, as
    ``findChessboardCornersSB`` once returned it) is refused, and so is the grid moved
    one square along a column."""
    from mocks.random_world import random_world
    from mocks.world import World, WorldFile, transform

    world = World(WorldFile.model_validate(random_world(seed)))
    tg = world.spec.target
    width_m, height_m = tg.cols * tg.square_mm / 1000, tg.rows * tg.square_mm / 1000
    distance = 2.2 * width_m * world.K[0, 0] / world.size[0]  # the board across half the image
    view = transform(cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0])  # turned a little
    view[:3, 3] = [width_m / 2, height_m / 2, 0] - view[:3, :3] @ [0, 0, distance]
    image = world.render(world.T_base_target @ view, noise=True)
    found = detect_board(image, tg.rows, tg.cols)
    assert found is not None
    truth = world.target_corner_pixels(world.T_base_target @ view)
    assert np.max(np.linalg.norm(found - truth, axis=1)) < 1.0
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    assert squares_alternate(gray, found, tg.rows, tg.cols)
    grid = np.array([[j + 1.0, i + 1.0] for i in range(tg.rows - 1) for j in range(tg.cols - 1)])
    H, _ = cv2.findHomography(grid, found)
    for shift in ([-1.0, 0.0], [0.0, 1.0]):
        moved = cv2.perspectiveTransform((grid + shift)[None], H)[0]
        assert not squares_alternate(gray, moved, tg.rows, tg.cols), shift
