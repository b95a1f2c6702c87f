"""The active-camera run's residuals plot names every motion legibly: each label is a
motion's name, in the motions' order, and no two labels overlap, for as many motions as
the default plan has and more. Pure drawing (matplotlib's Agg canvas), no mocks."""

from __future__ import annotations

import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from rigctl.calib.active_plots import residuals_figure
from rigctl.procedures.active_camera import ActiveCameraParams, head_poses


def _motions(n: int) -> dict[str, float]:
    """``n`` motion names, each with a residual (px): the default plan's motions (its
    captures but the reference), then wider pans and tilts beyond them."""
    names = [label for label, *_ in head_poses(ActiveCameraParams()) if label != "ref"]
    names += [f"{axis}{sign}{deg}" for deg in (30, 35) for axis in ("pan", "tilt")
              for sign in "+-"]
    assert len(names) >= n
    return {name: 0.1 + 0.001 * i for i, name in enumerate(names[:n])}


def _overlaps(boxes) -> list[tuple[int, int]]:
    return [(i, j) for i in range(len(boxes)) for j in range(i + 1, len(boxes))
            if boxes[i].overlaps(boxes[j])]


@pytest.mark.parametrize("n", [5, 31, 39])  # 31: the default plan's motions
def test_every_motion_is_named_once_and_no_two_names_overlap(n):
    residuals = _motions(n)
    fig = residuals_figure(residuals, 0.118)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    (ax,) = fig.axes
    # the motions' names, on whichever axis carries them, each with its extent
    named = [(label.get_text(), label.get_window_extent(renderer))
             for axis in (ax.xaxis, ax.yaxis) for label in axis.get_ticklabels()
             if label.get_text() in residuals]
    top_down = [name for name, box in sorted(named, key=lambda item: -item[1].y0)]
    left_right = [name for name, box in sorted(named, key=lambda item: item[1].x0)]
    assert top_down == list(residuals) or left_right == list(residuals)
    boxes = [box for _, box in named]
    assert _overlaps(boxes) == []
    # every name inside the figure, not cut at its edge
    width, height = canvas.get_width_height()
    assert all(b.x0 >= 0 and b.y0 >= 0 and b.x1 <= width and b.y1 <= height for b in boxes)
