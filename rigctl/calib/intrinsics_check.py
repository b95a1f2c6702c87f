"""An independent check of the intrinsics in use: Zhang's planar calibration
(``cv2.calibrateCameraExtended``, k1 k2 p1 p2; k3 held at 0) on the board views a robot run
already took. Beyond the thesis, whose active calibration uses rotations alone: there the
principal point and tangential distortion are nearly degenerate, while many tilted board
views separate them. Reported beside the intrinsics used; nothing is replaced. Its
resolution is the board calibration's own 1-sigma (0.3-0.6 px for the principal point
with 40-55 views at 0.2 px), so it catches errors of a pixel or more, not less."""

from __future__ import annotations

import cv2
import numpy as np

from rigctl.errors import SolveError

MIN_VIEWS = 10
FLAG_SIGMA = 3.0
KEYS = ("fx", "fy", "cx", "cy")


def board_intrinsics(obj: np.ndarray, corners: list[np.ndarray], image_size: tuple[int, int],
                     used: dict) -> dict:
    """Intrinsics from ``corners`` (one N x 2 array per view of the board ``obj``, id
    order, NaN where a view has not the corner) with
    their 1-sigma, and the difference ``used - board`` in pixels and in sigmas, for each
    of fx, fy, cx, cy. ``image_size`` is (width, height)."""
    if len(corners) < MIN_VIEWS:
        raise SolveError(f"intrinsics check: {len(corners)} board views; need {MIN_VIEWS}")
    # each view's corners with their board points (NaN rows: corners a view has not)
    seen = [np.all(np.isfinite(np.reshape(c, (-1, 2))), axis=1) for c in corners]
    object_points = [np.asarray(obj, np.float32)[m].reshape(-1, 1, 3) for m in seen]
    image_points = [np.asarray(c, np.float32).reshape(-1, 2)[m].reshape(-1, 1, 2)
                    for c, m in zip(corners, seen, strict=True)]
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # OpenCV's threaded sums differ in the last digits run to run
    try:  # one thread: a re-solve of the run reproduces the check exactly
        rms, K, dist, *_, std_intrinsics, _, _ = cv2.calibrateCameraExtended(
            object_points, image_points, tuple(int(v) for v in image_size), None, None,
            flags=cv2.CALIB_FIX_K3)
    finally:
        cv2.setNumThreads(threads)
    board = dict(zip(KEYS, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), strict=True))
    sigma = dict(zip(KEYS, std_intrinsics.ravel()[:4], strict=True))
    z = {k: float((used[k] - board[k]) / max(sigma[k], 1e-9)) for k in KEYS}
    off = [k for k in KEYS if abs(z[k]) > FLAG_SIGMA]
    return {"agrees": not off,
            "note": (f"the intrinsics in use differ from the board views' by more than "
                     f"{FLAG_SIGMA:g} sigma in {off}" if off else
                     f"the intrinsics in use agree with the board views' within "
                     f"{FLAG_SIGMA:g} sigma"),"views": len(corners), "rms_px": float(rms),
            "board": {k: float(v) for k, v in board.items()},
            "sigma": {k: float(v) for k, v in sigma.items()},
            "distortion": dist.ravel().tolist(),
            "used_minus_board_px": {k: float(used[k] - board[k]) for k in KEYS},
            "used_minus_board_sigma": z}
