"""The renderer cuts polygons to the drawable pyramid instead of dropping them: a board
close to the camera and reaching far outside the view is drawn where it is seen (random
world 40031's board vanished at home and filled the view after the arm's 10 mm move)."""

from __future__ import annotations

import numpy as np

from rigctl.mocks.view_clip import clip_to_view
from rigctl.mocks.world import WORLDS, World, load_world, transform


def _square(x0, x1, y0, y1, z, n=8):
    t = np.arange(n) / n
    edges = [np.c_[x0 + (x1 - x0) * t, np.full(n, y0)], np.c_[np.full(n, x1), y0 + (y1 - y0) * t],
             np.c_[x1 - (x1 - x0) * t, np.full(n, y1)], np.c_[np.full(n, x0), y1 - (y1 - y0) * t]]
    xy = np.concatenate(edges)
    return np.c_[xy, np.full(len(xy), z)]


def test_a_polygon_inside_is_returned_unchanged():
    sq = _square(-0.1, 0.1, -0.1, 0.1, 1.0)
    assert clip_to_view(sq, 0.5, 0.4, 0.02) is sq


def test_a_polygon_across_a_side_is_cut_on_it_and_keeps_its_inside_part():
    sq = _square(-0.2, 1.0, -0.1, 0.1, 1.0)  # x/z from -0.2 to 1.0; the side at 0.5
    cut = clip_to_view(sq, 0.5, 0.4, 0.02)
    assert np.isclose(cut[:, 0].max(), 0.5) and np.isclose(cut[:, 0].min(), -0.2)
    assert np.allclose(cut[:, 2], 1.0) and np.allclose(np.abs(cut[:, 1]).max(), 0.1)
    # the cut edge (x = 0.5, y from -0.1 to 0.1) is sampled finely, not one long segment
    on_cut = cut[np.isclose(cut[:, 0], 0.5)]
    assert len(on_cut) >= 8


def test_a_polygon_behind_the_camera_or_outside_is_dropped():
    assert len(clip_to_view(_square(-0.1, 0.1, -0.1, 0.1, -1.0), 0.5, 0.4, 0.02)) == 0
    assert len(clip_to_view(_square(2.0, 3.0, -0.1, 0.1, 1.0), 0.5, 0.4, 0.02)) == 0


def test_a_polygon_reaching_behind_the_camera_keeps_the_part_in_front():
    pts = np.array([[0.0, -0.1, 1.0], [0.0, 0.1, 1.0], [0.0, 0.1, -1.0], [0.0, -0.1, -1.0]])
    cut = clip_to_view(pts, 0.5, 0.4, 0.02)
    assert len(cut) >= 3 and cut[:, 2].min() >= 0.02 - 1e-12
    assert np.all(np.abs(cut[:, 1]) <= 0.4 * cut[:, 2] + 1e-12)


def _board_reaching_out_of_view(world: World, distance: float) -> np.ndarray:
    """Camera pose looking straight at the board from ``distance``, above the centre of
    its first column of squares (the rest runs far beyond the right edge, past twice the
    half-width)."""
    s = world.spec.target.square_mm / 1000.0
    view = transform(None, [0.5 * s, world.spec.target.rows / 2 * s, -distance])
    return world.T_base_target @ view


def test_a_board_reaching_far_out_of_view_is_drawn_where_it_is_seen():
    spec = load_world(WORLDS / "default.yaml").spec.model_copy(deep=True)
    spec.target.cols, spec.target.square_mm = 10, 80.0  # 0.8 m wide, seen from 0.3 m
    world = World(spec)
    T_base_cam = _board_reaching_out_of_view(world, 0.3)
    T_cam_target = np.linalg.inv(T_base_cam) @ world.T_base_target
    far_corner = T_cam_target[:3, :3] @ [0.8, 0.0, 0.0] + T_cam_target[:3, 3]
    assert far_corner[0] / far_corner[2] > 2.6 * world.size[0] / 2 / world.K[0, 0]
    image = world.render(T_base_cam, noise=False)
    s = spec.target.square_mm / 1000.0
    h = spec.target.rows
    # the centres of a black square (row 0, col 0 is black) and of the white one beside it
    for (col, row), shade in (((0, h // 2 - 1 + (h // 2 - 1) % 2), 20),
                              ((1, h // 2 - 1 + (h // 2 - 1) % 2), 235)):
        centre = world.T_base_target @ [(col + 0.5) * s, (row + 0.5) * s, 0.0, 1.0]
        u, v = world.project(centre[:3][None], T_base_cam)[0]
        assert 0 <= u < world.size[0] and 0 <= v < world.size[1]
        assert abs(int(image[round(float(v)), round(float(u))]) - shade) < 12, (col, row)
