"""Tracking contours across a known head motion.

Two ways, as the issue asks:

- ``track_by_shift``: the thesis's method (5.1.2). Dilate the reference contour's edge
  pixels, shift the mask along the direction the motion moves contours (pan: mostly
  horizontal, tilt: mostly vertical), AND it with the moved image's edges, and keep the
  shift with the most overlap; the tracked contour is the moved edges under the mask.
- ``track_by_prediction``: predict where each point must land from the known rotation
  and the current estimate of K (``predict`` callback), then search a small window
  around the prediction (chamfer score on the distance transform of the moved edges).
  Rolls (thesis future work 6.1.2) use this with the rotated prediction.

Match hygiene: a match is rejected, with the reason, when it is partial (too few
predicted points find an edge), ambiguous (a second, separate peak scores nearly as
well), or leaves the image.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from rigctl.vision.contours import Contour, EdgeMap, subpixel

RADIUS = 2.0
PLATEAU = 0.98  # share of the best joint score still on its plateau (``common_shift``)


@dataclass
class Match:
    ok: bool
    reason: str
    points: np.ndarray | None = None   # sub-pixel moved points
    normals: np.ndarray | None = None
    offset: tuple[float, float] = (0.0, 0.0)
    coverage: float = 0.0


def _distance(emap: EdgeMap) -> np.ndarray:
    if not hasattr(emap, "_dt"):
        emap._dt = cv2.distanceTransform(255 - emap.edges, cv2.DIST_L2, 3)
    return emap._dt


def _collect(emap: EdgeMap, template: np.ndarray, radius: float = RADIUS):
    """Moved edge pixels within ``radius`` of the template points."""
    h, w = emap.edges.shape
    pts = np.round(template).astype(int)
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h)
    pts = pts[inside]
    if not len(pts):
        return np.zeros((0, 2), int)
    r = int(np.ceil(radius))
    # only the template's bounding box, grown by the radius, can hold a collected pixel
    x0, y0 = max(pts[:, 0].min() - r, 0), max(pts[:, 1].min() - r, 0)
    x1, y1 = min(pts[:, 0].max() + r + 1, w), min(pts[:, 1].max() + r + 1, h)
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    mask[pts[:, 1] - y0, pts[:, 0] - x0] = 255
    mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))
    ys, xs = np.nonzero(mask & emap.edges[y0:y1, x0:x1])
    return np.c_[xs + x0, ys + y0]


def _score(dt: np.ndarray, pts: np.ndarray, cap: float = RADIUS) -> float:
    d = map_coordinates(dt, [pts[:, 1], pts[:, 0]], order=1, mode="constant", cval=cap * 4)
    return float(np.mean(d <= cap))


def _finish(emap: EdgeMap, template: np.ndarray, offset, min_coverage: float,
            best: float, second: float, ambiguity: float) -> Match:
    h, w = emap.edges.shape
    if np.any(template[:, 0] < 2) or np.any(template[:, 0] > w - 3) or \
            np.any(template[:, 1] < 2) or np.any(template[:, 1] > h - 3):
        return Match(False, "leaves the image", offset=offset, coverage=best)
    if best < min_coverage:
        return Match(False, f"partial match (coverage {best:.2f} < {min_coverage:.2f})",
                     offset=offset, coverage=best)
    if second >= ambiguity * best:
        return Match(False, f"ambiguous (second peak {second:.2f} vs {best:.2f})",
                     offset=offset, coverage=best)
    pixels = _collect(emap, template)
    if len(pixels) < 0.5 * len(template):
        return Match(False, "too few edge points under the matched template", offset=offset,
                     coverage=best)
    pts, normals, _ = subpixel(emap, pixels)
    return Match(True, "ok", pts, normals, offset, best)


def _search(dt, base: np.ndarray, xs, ys, cap: float = RADIUS):
    """``_score`` of ``base`` shifted by every (xs[j], ys[i]), in one interpolation pass:
    scores[i, j] is the fraction of shifted points within ``cap`` of an edge."""
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    px = base[None, None, :, 0] + xs[None, :, None]
    py = base[None, None, :, 1] + ys[:, None, None]
    px, py = np.broadcast_arrays(px, py)
    d = map_coordinates(dt, [py.ravel(), px.ravel()], order=1, mode="constant",
                        cval=cap * 4).reshape(px.shape)
    return np.mean(d <= cap, axis=2)


def _near(emap: EdgeMap) -> np.ndarray:
    """1 where an edge is within ``RADIUS`` px, else 0 (float32, for correlation)."""
    if not hasattr(emap, "_near"):
        emap._near = (_distance(emap) <= RADIUS).astype(np.float32)
    return emap._near


def searchable(emap: EdgeMap) -> EdgeMap:
    """``emap`` with what every search in it needs taken now, not at its first search:
    its edges' distance transform and near-edge map (the same maps either way). Taken
    with each capture's edge map, side by side or while the rig moves, instead of on
    the solve's path (14 captures: 0.2 s of one core)."""
    _near(emap)
    return emap


def _search_shifts(emap: EdgeMap, base: np.ndarray, xs: np.ndarray, ys: np.ndarray):
    """``_search`` over the integer shifts from xs[0] to xs[-1] and ys[0] to ys[-1], with
    the template's points rounded to whole pixels: one correlation of the template's
    raster with the near-edge map (``cv2.matchTemplate``) instead of an interpolation per
    point and shift. Returns the scores and the shifts they are for.

    Points that no shift in the range brings into the image score nothing and are left
    out of the correlation (they still count in the mean): a prediction far off the image
    (a point turned behind the camera by a wrong model) would otherwise size the raster
    by its own coordinates."""
    near = _near(emap)
    h, w = near.shape
    n_points = len(base)
    reach = (base[:, 0] + xs[-1] >= -1) & (base[:, 0] + xs[0] <= w) \
        & (base[:, 1] + ys[-1] >= -1) & (base[:, 1] + ys[0] <= h)
    x0, x1 = int(np.floor(xs[0])), int(np.ceil(xs[-1]))
    y0, y1 = int(np.floor(ys[0])), int(np.ceil(ys[-1]))
    if not reach.any():
        return (np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.float32),
                np.arange(x0, x1 + 1, dtype=float), np.arange(y0, y1 + 1, dtype=float))
    pts = np.round(base[reach]).astype(int)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    kernel = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), np.float32)
    np.add.at(kernel, (pts[:, 1] - lo[1], pts[:, 0] - lo[0]), 1.0)
    top, left = lo[1] + y0, lo[0] + x0
    bottom, right = hi[1] + y1 + 1, hi[0] + x1 + 1
    region = np.zeros((bottom - top, right - left), np.float32)  # zero beyond the image
    sy0, sx0 = max(top, 0), max(left, 0)
    sy1, sx1 = min(bottom, h), min(right, w)
    if sy1 > sy0 and sx1 > sx0:
        region[sy0 - top:sy1 - top, sx0 - left:sx1 - left] = near[sy0:sy1, sx0:sx1]
    scores = cv2.matchTemplate(region, kernel, cv2.TM_CCORR) / n_points
    return scores, np.arange(x0, x1 + 1, dtype=float), np.arange(y0, y1 + 1, dtype=float)


def _best_and_second(scores: np.ndarray, xs, ys, exclusion: float):
    i, j = np.unravel_index(np.argmax(scores), scores.shape)
    best = scores[i, j]
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    far = np.hypot(yy - ys[i], xx - xs[j]) > exclusion
    second = float(scores[far].max()) if far.any() else 0.0
    return (float(xs[j]), float(ys[i])), float(best), second


def track_in_range(template: np.ndarray, moved: EdgeMap, x_range, y_range,
                   min_coverage: float = 0.75, ambiguity: float = 0.85) -> Match:
    """The shift of ``template`` (points, px) within ``x_range`` x ``y_range`` (min, max)
    with the best chamfer score: every whole-pixel shift, then half a pixel around the
    best; the match keeps the moved edge points under the shifted template."""
    dt = _distance(moved)
    scores, xs, ys = _search_shifts(moved, template, np.asarray(x_range, float),
                                    np.asarray(y_range, float))
    offset, best, second = _best_and_second(scores, xs, ys, exclusion=6.0)
    fine = np.arange(-1, 1.01, 0.5)
    fx, fy = offset[0] + fine, offset[1] + fine
    grid = _search(dt, template, fx, fy)
    i, j = np.unravel_index(np.argmax(grid), grid.shape)
    offset = (float(fx[j]), float(fy[i]))
    return _finish(moved, template + offset, offset, min_coverage, max(best, grid.max()),
                   second, ambiguity)


def track_by_shift(contour: Contour, moved: EdgeMap, direction: str, max_shift: float,
                   cross: float = 4.0, min_coverage: float = 0.75,
                   ambiguity: float = 0.85) -> Match:
    """Thesis tracking: search a shift along ``direction`` ('x' for pan, 'y' for tilt) up
    to ``max_shift`` pixels (either sign), with a little slack across it."""
    along, across = (-max_shift, max_shift), (-cross, cross)
    x_range, y_range = (along, across) if direction == "x" else (across, along)
    return track_in_range(contour.points, moved, x_range, y_range, min_coverage, ambiguity)


def track_by_prediction(contour: Contour, moved: EdgeMap,
                        predict: Callable[[np.ndarray], np.ndarray], window: float = 12.0,
                        min_coverage: float = 0.75, ambiguity: float = 0.85) -> Match:
    """Predict the contour's points in the moved image, then search +-``window`` pixels
    around the prediction for the best chamfer score."""
    return track_in_range(predict(contour.points), moved, (-window, window),
                          (-window, window), min_coverage, ambiguity)


def common_shift(templates: list[np.ndarray], moved: EdgeMap, window: float,
                 ambiguity: float = 0.9) -> tuple[float, float] | None:
    """One shift of every predicted contour together (``templates``, px), within
    +-``window`` px, that best lays them on the moved image's edges (the chamfer
    coverage of all their points at once); None when no shift covers any point or a
    second, separate peak scores nearly as well (a periodic scene). A prediction that
    is off by one shift for the whole image, e.g. a roll predicted about a wrong centre
    (the error of a rotation about a centre ``e`` off is the translation
    ``(I - R) e``), is corrected so, before each contour is searched in a small window."""
    pts = np.concatenate([t for t in templates if len(t)]) if templates else np.zeros((0, 2))
    if not len(pts):
        return None
    scores, xs, ys = _search_shifts(moved, pts, np.array([-window, window]),
                                    np.array([-window, window]))
    offset, best, second = _best_and_second(scores, xs, ys, exclusion=6.0)
    if best <= 0 or second >= ambiguity * best:
        return None
    # a point counts within RADIUS of an edge, so the best score is a plateau a few px
    # wide around the true shift: its middle, not its first pixel
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    top = (scores >= PLATEAU * best) & (np.hypot(xx - offset[0], yy - offset[1]) <= 6.0)
    return float(xx[top].mean()), float(yy[top].mean())
