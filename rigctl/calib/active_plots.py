"""The active-camera run's plots: the contours tracked, and the refinement's residuals.

``draw_active_plots`` takes plain arrays and numbers only, so that it can be drawn in the
solve's second process (``calib.solve_process``, job of a re-solve whose child imported
matplotlib while the parent still imported and loaded) as well as here.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

# matplotlib's figure and Agg backend: 0.6 s of the plots' 0.9 s on the demo's re-solve,
# imported ahead of them (``import_plot_modules``)
PLOT_MODULES = ("matplotlib.figure", "matplotlib.backends.backend_agg")


def import_plot_modules() -> None:
    """Import ``PLOT_MODULES`` ahead of the plots, when matplotlib is installed (the
    ``plots`` extra); without it the plots report the missing extra themselves."""
    import importlib

    try:
        for name in PLOT_MODULES:
            importlib.import_module(name)
    except ImportError:
        pass


def draw_active_plots(plots_dir: Path, ref_image: np.ndarray, contour_points: list,
                      shown: str, shown_image: np.ndarray, tracked_points: list,
                      residuals_by_motion: dict[str, float], rms_px: float) -> None:
    """``contours.png`` (the reference capture's contours, and those tracked in capture
    ``shown``) and ``residuals.png`` (the refinement's RMS point-to-contour residual by
    motion, thesis eq. 3.27's residual) into ``plots_dir``."""
    # matplotlib's object API: no pyplot state (the service solves in its own threads), and
    # pyplot's import (0.24 s of CPU) is not paid. Each image is drawn at half size in its
    # own pixel coordinates: the panels are about 550 px wide at 80 dpi, so the figure
    # looks the same, at half the drawing's cost.
    from matplotlib.figure import Figure

    plots_dir = Path(plots_dir)
    fig = Figure(figsize=(14, 4.5))
    axes = fig.subplots(1, 2)
    _show_image(axes[0], ref_image)
    for points in contour_points:
        axes[0].plot(points[:, 0], points[:, 1], ".", ms=1)
    axes[0].set_title(f"reference: {len(contour_points)} contours")
    _show_image(axes[1], shown_image)
    for points in tracked_points:
        axes[1].plot(points[:, 0], points[:, 1], ".", ms=1)
    axes[1].set_title(f"{shown}: tracked {len(tracked_points)}")
    for ax in axes:  # no ticks either: the layout then measures none (the same picture)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(plots_dir / "contours.png", dpi=80)
    residuals_figure(residuals_by_motion, rms_px).savefig(plots_dir / "residuals.png",
                                                          dpi=80)


def residuals_figure(residuals_by_motion: dict[str, float], rms_px: float):
    """The refinement's RMS point-to-contour residual by motion (thesis eq. 3.27's
    residual): one horizontal bar a motion, named beside it, in the motions' order from
    the top (a run has 30 or more motions, whose names under vertical bars overlapped);
    a matplotlib ``Figure``, laid out."""
    from matplotlib.figure import Figure

    labels = list(residuals_by_motion)
    fig = Figure(figsize=(7, max(3.0, 1.2 + 0.16 * len(labels))))
    ax = fig.subplots()
    ax.barh(labels, [residuals_by_motion[k] for k in labels])
    ax.invert_yaxis()
    ax.tick_params(axis="y", labelsize=7)
    ax.set_xlabel("RMS point-to-contour residual (px)")
    ax.set_title(f"refinement residuals (overall {rms_px:.3f} px)")
    fig.tight_layout()
    return fig


def _show_image(ax, image: np.ndarray) -> None:
    """``image`` (grey) on ``ax`` at half size, its axes still in the full image's pixels."""
    h, w = image.shape[:2]
    half = cv2.resize(image, (max(w // 2, 1), max(h // 2, 1)), interpolation=cv2.INTER_AREA)
    ax.imshow(half, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5))
