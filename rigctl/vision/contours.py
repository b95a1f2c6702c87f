"""Edges and contours for active calibration (thesis 5.1.2, automated).

Edges come from Canny; each connected set of edge pixels is a contour candidate. Every
edge pixel is moved to sub-pixel precision along its gradient (parabola through the
gradient magnitude at -1, 0, +1 pixel), and carries its unit normal.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import map_coordinates


@dataclass
class Contour:
    """Sub-pixel edge points (N x 2, x right, y down), unit normals and mean contrast."""

    points: np.ndarray
    normals: np.ndarray
    contrast: float
    pixels: np.ndarray  # integer (x, y) of the Canny pixels, for masks

    @property
    def n(self) -> int:
        return len(self.points)


@dataclass
class EdgeMap:
    edges: np.ndarray      # uint8 Canny map
    gx: np.ndarray
    gy: np.ndarray
    magnitude: np.ndarray


def edge_map(image: np.ndarray, low: float = 30, high: float = 90) -> EdgeMap:
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    smooth = cv2.GaussianBlur(gray, (0, 0), 1.0)
    edges = cv2.Canny(smooth, low, high, L2gradient=True)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    return EdgeMap(edges, gx, gy, gradient_magnitude(gx, gy))


def gradient_magnitude(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """``sqrt(gx^2 + gy^2)`` from correctly rounded operations only, so that it is the
    same bit for bit wherever the arrays lie in memory. ``cv2.magnitude`` is not: the
    same gradients gave 7 of 921,600 values different in the last bit by where its
    output landed, which moved sub-pixel points 5e-7 px from one solve of the same
    captures to the next; on a world with two near basins (random world 99321) the
    solve then ended in either."""
    out = gx * gx
    out += gy * gy
    return np.sqrt(out, out=out)


def subpixel(emap: EdgeMap, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel positions, unit normals and gradient magnitudes of edge pixels (x, y)."""
    x, y = pixels[:, 0].astype(float), pixels[:, 1].astype(float)
    gx = emap.gx[pixels[:, 1], pixels[:, 0]]
    gy = emap.gy[pixels[:, 1], pixels[:, 0]]
    mag = gradient_magnitude(gx, gy) + 1e-9
    nx, ny = gx / mag, gy / mag
    samples = [map_coordinates(emap.magnitude, [y + k * ny, x + k * nx], order=1,
                               mode="nearest") for k in (-1.0, 0.0, 1.0)]
    m_minus, m0, m_plus = samples
    denom = m_minus - 2 * m0 + m_plus
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom < -1e-6, 0.5 * (m_minus - m_plus) / denom, 0.0)
    s = np.clip(s, -0.5, 0.5)
    pts = np.c_[x + s * nx, y + s * ny]
    return pts, np.c_[nx, ny], mag


def extract_contours(image: np.ndarray, window: float = 0.6, min_points: int = 60,
                     min_contrast: float = 40.0, emap: EdgeMap | None = None,
                     max_contours: int = 60, tile: int | None = None) -> list[Contour]:
    """Stable contours in the central ``window`` of the image: long enough
    (``min_points``), good contrast (mean gradient), entirely inside the window, and not
    touching another contour (connected components of the edge map).

    With ``tile`` (px), an edge network that reaches beyond the window (a board filling
    the view, whose squares' outlines join at their corners into one component) is cut
    along a grid of that size, and each piece inside the window is a contour too: a piece
    of a grid of lines is a distinct shape at shifts below the tile size."""
    emap = emap or edge_map(image)
    h, w = emap.edges.shape
    count, labels, stats, _ = cv2.connectedComponentsWithStats(emap.edges, connectivity=8)
    x0, x1 = w * (0.5 - window / 2), w * (0.5 + window / 2)
    y0, y1 = h * (0.5 - window / 2), h * (0.5 + window / 2)
    candidates = []

    def add(pixels: np.ndarray) -> None:
        pts, normals, mag = subpixel(emap, pixels)
        contrast = float(np.mean(mag))
        if contrast >= min_contrast:
            candidates.append(Contour(pts, normals, contrast, pixels))

    for label in range(1, count):
        left, top, bw, bh, area = stats[label]
        if area < min_points:
            continue
        inside = left >= x0 and top >= y0 and left + bw <= x1 and top + bh <= y1
        if not inside and tile is None:
            continue
        ys, xs = np.nonzero(labels[top:top + bh, left:left + bw] == label)
        pixels = np.c_[xs + left, ys + top]
        if inside:
            add(pixels)
            continue
        keep = (pixels[:, 0] >= x0) & (pixels[:, 0] < x1) & (pixels[:, 1] >= y0) & \
            (pixels[:, 1] < y1)
        pixels = pixels[keep]
        cells = (pixels[:, 0] // tile) * (w // tile + 1) + pixels[:, 1] // tile
        for cell in np.unique(cells):
            piece = pixels[cells == cell]
            if len(piece) >= min_points:
                add(piece)
    candidates.sort(key=lambda c: -c.n * c.contrast)
    return candidates[:max_contours]
