"""Board detection: a checkerboard (OpenCV ``findChessboardCornersSB``) or a ChArUco
board (``rigctl.calib.charuco``), corners refined by ``cornerSubPix``.

Both give the same form, the board's corners with their ids: an array of the inner
corners in id order (``board_points`` order, row-major), N x 2 pixels, a row of NaN for a
corner not seen. A checkerboard is found whole or not at all; a ChArUco board may be
seen in part. ``seen`` and ``visible`` pick the corners a view has."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def board_points(rows: int, cols: int, square_m: float) -> np.ndarray:
    """Inner corners in the target frame (x along columns, y along rows), row-major,
    in the order ``detect_board`` returns them."""
    return np.array([[(j + 1) * square_m, (i + 1) * square_m, 0.0]
                     for i in range(rows - 1) for j in range(cols - 1)])


def target_points(target) -> np.ndarray:
    """``board_points`` of a rig file's target (``TargetConfig``: rows, cols, square_mm):
    a checkerboard's inner corners, or a ChArUco board's (the same points, by id)."""
    return board_points(target.rows, target.cols, target.square_mm / 1000.0)


def seen(corners: np.ndarray) -> np.ndarray:
    """Which corners of an id-ordered corner array a view has (not NaN)."""
    return np.all(np.isfinite(np.reshape(corners, (-1, 2))), axis=1)


def visible(obj: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The board points ``obj`` and pixels of the corners a view has."""
    pixels = np.reshape(corners, (-1, 2))
    mask = seen(pixels)
    return np.asarray(obj)[mask], pixels[mask]


def is_charuco(target) -> bool:
    """Is the rig file's target a ChArUco board?"""
    return getattr(target, "type", "checkerboard") == "charuco"


def target_key(target) -> dict:
    """What identifies a target's detections (a saved ``NNN.board.json`` is reused only
    for the same board)."""
    key = {"type": getattr(target, "type", "checkerboard"), "rows": target.rows,
           "cols": target.cols}
    if is_charuco(target):
        key |= {"dictionary": target.dictionary, "square_mm": target.square_mm,
                "marker_mm": target.marker_mm, "legacy_pattern": target.legacy_pattern}
    return key


@dataclass
class Detection:
    """A view's board corners (id order, NaN where not seen; None: not found) and, when
    the view is not used, why (``note``)."""

    corners: np.ndarray | None
    note: str | None = None


def detect_target(image: np.ndarray, target) -> Detection:
    """The rig file's target (``TargetConfig``) in ``image``: a checkerboard
    (``detect_board``) or a ChArUco board (``charuco.detect_charuco``, refined like a
    checkerboard's corners). A ChArUco board that is not the configured one is refused
    with a note naming what was seen."""
    if not is_charuco(target):
        corners = detect_board(image, target.rows, target.cols)
        return Detection(corners, None if corners is not None else
                         f"checkerboard of {target.rows} x {target.cols} squares not found")
    from rigctl.calib import charuco

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    found = charuco.detect_charuco(gray, charuco.CharucoSpec.of(target))
    if found.corners is None:
        return Detection(None, found.note)
    # the half window stays inside the white gap between a corner and the nearest marker
    gap = (target.square_mm - target.marker_mm) / (2 * target.square_mm)
    fraction = min(SUBPIX_WINDOW_FRACTION, CHARUCO_WINDOW_SHARE * gap)
    return Detection(refine_corners(gray, found.corners, target.rows, target.cols, fraction))


CHARUCO_WINDOW_SHARE = 0.8  # of the gap between a ChArUco corner and its markers' corners


# The first search runs on the image scaled by this: on 160 views of 16 random worlds
# (1280 x 720 to 1280 x 960), 0.05 s of CPU a view instead of 0.12 s, with the refined
# corners as far from the truth (0.107 px RMS, median over the views, against 0.106).
LOCATE_SCALE = 0.5


def detect_board(image: np.ndarray, rows: int, cols: int,
                 locate_scale: float = LOCATE_SCALE) -> np.ndarray | None:
    """Inner corners (N x 2 pixels, row-major like ``board_points``) or None: found by
    ``findChessboardCornersSB`` (the planar target's corners of the Tsai and Zhang steps),
    put in the board's order (``_checked``), then refined (``refine_corners``).
    ``locate_scale``: the scale of the first search (1 skips it)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    # the quick search on the image at half scale first: the refinement below takes its
    # corners to within 0.001 px of where it takes the full image's search's
    pts = _checked(gray, _located(gray, rows, cols, locate_scale), rows, cols) \
        if locate_scale < 1 else None
    if pts is not None:
        return refine_corners(gray, pts, rows, cols)
    # the quick search on the whole image: its corners end within 1e-4 px (median; 0.01
    # px at most) of where the slower accurate search's do, at a fifth of the cost (40
    # views of the default world: 4.6 s instead of 20.7 s); the accurate and the
    # exhaustive searches take the boards it misses
    found, corners = cv2.findChessboardCornersSB(gray, (cols - 1, rows - 1))
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, (cols - 1, rows - 1),
                                                     flags=cv2.CALIB_CB_ACCURACY)
    if not found:
        # the exhaustive search finds boards the quick one misses (a wide lens's strongly
        # bent board at the image's edge), at about the same cost
        found, corners = cv2.findChessboardCornersSB(
            gray, (cols - 1, rows - 1), flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE)
    if not found:
        return None
    pts = _checked(gray, corners.reshape(-1, 2).astype(float), rows, cols)
    return None if pts is None else refine_corners(gray, pts, rows, cols)


def _located(gray: np.ndarray, rows: int, cols: int, scale: float) -> np.ndarray | None:
    """Where ``findChessboardCornersSB``'s quick search finds the inner corners in the
    image scaled by ``scale`` (N x 2 full-resolution pixels), or None."""
    small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    found, corners = cv2.findChessboardCornersSB(small, (cols - 1, rows - 1))
    if not found:
        return None
    # pixel centres: x_full + 0.5 = (x_small + 0.5) / scale
    return (corners.reshape(-1, 2).astype(float) + 0.5) / scale - 0.5


def _checked(gray: np.ndarray, pts: np.ndarray | None, rows: int,
             cols: int) -> np.ndarray | None:
    """A found grid ``pts`` in the board's order, or None when its squares do not
    alternate as the board's do.

    OpenCV may return the grid in either of its two 180-degree orders. The square
    enclosed by the first 2x2 inner corners is square (1, 1) of the board, which is black
    (the origin square (0, 0) is black); in the reversed order it would be square
    (rows-2, cols-2), white when rows + cols is odd. So a bright first square means the
    order is reversed, and we flip it."""
    if pts is None:
        return None
    if (rows + cols) % 2 == 1:
        w = cols - 1
        quad = np.array([pts[0], pts[1], pts[w + 1], pts[w]], np.float32)
        mask = np.zeros(gray.shape, np.uint8)
        centre = quad.mean(axis=0)
        shrunk = centre + 0.6 * (quad - centre)
        cv2.fillConvexPoly(mask, np.round(shrunk).astype(np.int32), 255)
        inside = float(cv2.mean(gray, mask)[0])
        ring = float(np.mean(gray))
        if inside > ring:
            pts = pts[::-1].copy()
    return pts if squares_alternate(gray, pts, rows, cols) else None


# cornerSubPix's half window: this fraction of the distance to the nearest neighbouring
# corner (so that no other corner's edges enter it), within these bounds (pixels)
SUBPIX_WINDOW_FRACTION = 0.3
SUBPIX_HALF_WINDOW = (2, 8)


def refine_corners(gray: np.ndarray, pts: np.ndarray, rows: int, cols: int,
                   fraction: float = SUBPIX_WINDOW_FRACTION) -> np.ndarray:
    """The inner corners ``pts`` of ``detect_board`` moved to where the image's gradients
    meet (``cv2.cornerSubPix``, each corner's window scaled to its grid spacing). A
    corner whose window would leave the image, or that moves by more than its half
    window, keeps its place; a corner not seen (NaN) stays NaN, and one with no seen
    neighbour gets the widest window. ``fraction``: the half window's share of the
    corner spacing (smaller on a ChArUco board, whose markers must stay out of it).

    ``findChessboardCornersSB``'s own corners carry a shared error per view: on 825
    views of 40 random worlds 0.029 px RMS for a view's mean corner (0.022 px after this),
    and its exhaustive search, which finds a board seen far off its normal, left corners
    0.6 px off on average. The arm model (thesis 4.11) fits poses to whole views, so a
    view's shared error is what it cannot average away."""
    nodes = pts.reshape(rows - 1, cols - 1, 2)
    spacing = np.full(nodes.shape[:2], np.inf)
    along = np.linalg.norm(np.diff(nodes, axis=1), axis=2)
    across = np.linalg.norm(np.diff(nodes, axis=0), axis=2)
    spacing[:, :-1] = np.fmin(spacing[:, :-1], along)  # fmin: a missing neighbour, no limit
    spacing[:, 1:] = np.fmin(spacing[:, 1:], along)
    spacing[:-1, :] = np.fmin(spacing[:-1, :], across)
    spacing[1:, :] = np.fmin(spacing[1:, :], across)
    lo, hi = SUBPIX_HALF_WINDOW
    half = np.clip(np.floor(fraction * spacing.ravel()), lo, hi).astype(int)
    height, width = gray.shape[:2]
    out = pts.copy()
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    for w in np.unique(half):
        inside = (half == w) & np.all(pts >= w + 1, axis=1) & \
            (pts[:, 0] < width - w - 2) & (pts[:, 1] < height - w - 2)
        if not inside.any():
            continue
        start = pts[inside].astype(np.float32).reshape(-1, 1, 2)
        moved = cv2.cornerSubPix(gray, start.copy(), (int(w), int(w)), (-1, -1),
                                 criteria).reshape(-1, 2).astype(float)
        keep = np.all(np.isfinite(moved), axis=1) & \
            (np.linalg.norm(moved - pts[inside], axis=1) <= w)
        rows_in = np.flatnonzero(inside)
        out[rows_in[keep]] = moved[keep]
    return out


def squares_alternate(gray: np.ndarray, pts: np.ndarray, rows: int, cols: int) -> bool:
    """Do the board's squares, where the detected inner corners put them, alternate in
    colour, the outer ring of squares included? A grid found one square off (its outer
    nodes on the white margin) puts margin where a border square should be, and its pose
    is one square off.

    Each square is sampled through a homography of the 3 x 3 inner corners nearest to
    it, which follows lens distortion locally. An outer square whose sample reaches
    outside the image is sampled in its quarter next to the inner corners instead
    (``_toward_grid``), and counts against the grid only where it clearly shows the
    other colour (``CLEAR``; a margin seen where a dark square should be), since that far
    out the local homography is a coarse guide; squares still outside are not judged.
    Either colouring is accepted (a square board may come back turned a quarter). Every
    inner square must fall on its side of the midpoint between the median dark and the
    median light square, and all but one of the outer ring (a corner square shaded, or
    cut by the lens's edge); a grid one square off puts at least two of a border
    column's squares on the margin."""
    nodes = pts.reshape(rows - 1, cols - 1, 2)
    inset = ((0.3, 0.3), (0.7, 0.3), (0.7, 0.7), (0.3, 0.7))
    homographies: dict[tuple[int, int], np.ndarray | None] = {}  # one per 3 x 3 block
    means, parity, ring, near = [], [], [], []
    for r in range(rows):
        for s in range(cols):
            i0, j0 = min(max(r, 1), rows - 3), min(max(s, 1), cols - 3)  # node coordinates
            if (i0, j0) not in homographies:
                block = [(j, i) for i in range(i0, i0 + 3) for j in range(j0, j0 + 3)]
                homographies[i0, j0] = cv2.findHomography(
                    np.array(block, float), np.array([nodes[i - 1, j - 1] for j, i in block]))[0]
            H = homographies[i0, j0]
            if H is None:
                return False
            outer = r in (0, rows - 1) or s in (0, cols - 1)
            mean = _square_mean(gray, H, r, s, inset)
            fallback = mean is None and outer
            if fallback:
                mean = _square_mean(gray, H, r, s, _toward_grid(inset, r, s, rows, cols))
            if mean is not None:
                means.append(mean)
                parity.append((r + s) % 2)
                ring.append(outer)
                near.append(fallback)
    means, parity = np.array(means), np.array(parity)
    ring, near = np.array(ring, bool), np.array(near, bool)
    if len(set(parity.tolist())) < 2:
        return True  # too little of the board in the image to judge
    for dark in (0, 1):
        is_dark = parity == dark
        low, high = np.median(means[is_dark]), np.median(means[~is_dark])
        middle, margin = (low + high) / 2, CLEAR * abs(high - low)
        wrong = np.where(is_dark, means >= middle, means <= middle)
        clearly = np.where(is_dark, means >= middle + margin, means <= middle - margin)
        wrong = np.where(near, clearly, wrong)
        if not np.any(wrong & ~ring) and np.sum(wrong & ring) <= 1:
            return True
    return False


CLEAR = 0.25  # of the dark-light contrast past the midpoint: a quarter-square sample's "clearly"


def _square_mean(gray: np.ndarray, H: np.ndarray, r: int, s: int, inset) -> float | None:
    """Mean grey of square (r, s) over ``inset`` (cell fractions) mapped by ``H``, or None
    when that reaches outside the image."""
    height, width = gray.shape[:2]
    cell = np.array([[s + u, r + v] for u, v in inset])
    quad = cv2.perspectiveTransform(cell[None], H)[0]
    if quad.min() < 0 or np.any(quad[:, 0] > width - 1) or np.any(quad[:, 1] > height - 1):
        return None
    corners = np.round(quad).astype(np.int32)
    x, y, w, h = cv2.boundingRect(corners)
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, corners - [x, y], 255)
    return cv2.mean(gray[y:y + h, x:x + w], mask)[0] if mask.any() else None


def _toward_grid(inset, r: int, s: int, rows: int, cols: int):
    """The sampling quad of square (r, s) of the outer ring drawn into its quarter next
    to the inner corners: that part is in the image even when the rest of the square is
    not (a grid found one square off, its outer corners on the margin at the image's
    edge, puts margin there where the border squares should be)."""
    def squeeze(t: float, index: int, last: int) -> float:
        if index == 0:
            return 0.7 + 0.25 * (t - 0.3) / 0.4   # the ring's side nearer the grid: 0.7-0.95
        if index == last:
            return 0.05 + 0.25 * (t - 0.3) / 0.4  # 0.05-0.3
        return t
    return [(squeeze(u, s, cols - 1), squeeze(v, r, rows - 1)) for u, v in inset]


def symmetric(rows: int, cols: int) -> bool:
    """Is the board's pattern unchanged by a half turn (rows + cols even), so that no
    image alone tells its corner order from the reversed one (and, when square, from the
    quarter turns)?"""
    return (rows + cols) % 2 == 0


def orient_to_prediction(corners: np.ndarray, predicted: np.ndarray, rows: int,
                         cols: int) -> np.ndarray:
    """The detected ``corners`` in the order (of those the board's symmetry allows: the
    half turn, and the quarter turns of a square grid) that lies closest to ``predicted``
    pixels of the same corners (e.g. from the nominal arm and hand-eye), for boards whose
    pattern cannot tell (``symmetric``). Others are returned unchanged."""
    if not symmetric(rows, cols):
        return corners
    r, c = rows - 1, cols - 1
    grid = corners.reshape(r, c, 2)
    options = [grid, grid[::-1, ::-1]]
    if r == c:
        options += [np.rot90(grid, 1), np.rot90(grid, 3)]
    costs = [float(np.mean(np.linalg.norm(o.reshape(-1, 2) - predicted, axis=1)))
             for o in options]
    return options[int(np.argmin(costs))].reshape(-1, 2).copy()
