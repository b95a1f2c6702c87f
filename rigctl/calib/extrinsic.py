"""Planar extrinsic calibration after Tsai (thesis 4.2, eqs. 4.1-4.10), then a
Levenberg-Marquardt refinement of the pose on reprojection error.

Input: board points (X, Y, 0) in the target frame, their pixels, the intrinsics K and
distortion. Output: ``T_cam_target`` (the thesis's ``T_cw``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from rigctl.errors import SolveError
from rigctl.geometry.transforms import R_to_rotvec, make_T, rotvec_to_R

MIN_TILT_DEG = 3.0


@dataclass
class PoseEstimate:
    T_cam_target: np.ndarray
    rms_px: float
    closed_form: np.ndarray  # the closed-form pose before refinement
    method: str = "tsai"     # tsai, or ippe where Tsai refused a fronto-parallel view


def _normalised(pixels: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    """Undistorted pixel coordinates measured from the principal point (x_i, y_i)."""
    und = cv2.undistortPoints(pixels.reshape(-1, 1, 2).astype(np.float64), K,
                              np.asarray(dist, float) if dist is not None else None)
    und = und.reshape(-1, 2)
    return np.c_[und[:, 0] * K[0, 0], und[:, 1] * K[1, 1]]


def tsai_planar(obj: np.ndarray, pixels: np.ndarray, K: np.ndarray, dist=None) -> np.ndarray:
    """Closed-form pose of a planar target (Z_w = 0), thesis eqs. (4.1)-(4.10).

    1. Five unknowns ``[r11, r12, Tx, r21, r22] / Ty`` from the linear system obtained by
       equating the denominators of (4.1) and (4.2), least squares over all points.
    2. ``Ty^2`` from (4.3); the sign of Ty from a point far from the centre (step 4).
    3. The rotation completed from its upper-left 2x2 block; the sign of the out-of-plane
       components is chosen so that the focal length solved from (4.1) is positive (the
       thesis's test on the sign of theta).
    4. ``Tz`` from (4.1)-(4.2) by least squares.

    A fronto-parallel view (tilt under ``MIN_TILT_DEG``) leaves that sign undetermined and
    raises ``SolveError`` (erratum 8)."""
    obj = np.asarray(obj, float)
    if obj.shape[0] < 6:
        raise SolveError(f"extrinsic: {obj.shape[0]} points; need at least 6")
    if np.any(np.abs(obj[:, 2]) > 1e-9):
        raise SolveError("extrinsic: target points must lie in the plane Z = 0")
    X, Y = obj[:, 0], obj[:, 1]
    if np.linalg.matrix_rank(np.c_[X - X.mean(), Y - Y.mean()], tol=1e-9) < 2:
        raise SolveError("extrinsic: target points are collinear")
    xy = _normalised(pixels, K, dist)
    x, y = xy[:, 0], xy[:, 1]
    fx, fy = K[0, 0], K[1, 1]
    A = np.c_[fx * X * y, fx * Y * y, fx * y, -fy * X * x, -fy * Y * x]
    b = fy * x
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    r1, r2, tx_, r3, r4 = sol  # r11/Ty, r12/Ty, Tx/Ty, r21/Ty, r22/Ty
    S = r1 ** 2 + r2 ** 2 + r3 ** 2 + r4 ** 2
    det = r1 * r4 - r3 * r2
    if abs(det) < 1e-12:
        raise SolveError("extrinsic: degenerate linear system (det of C is zero)")
    Ty2 = (S - math.sqrt(max(S * S - 4 * det * det, 0.0))) / (2 * det * det)     # (4.3)
    Ty = math.sqrt(Ty2)                                                            # (4.4)
    far = int(np.argmax(x * x + y * y))
    r11, r12, r21, r22, Tx = r1 * Ty, r2 * Ty, r3 * Ty, r4 * Ty, tx_ * Ty          # (4.5)-(4.9)
    xc = r11 * X[far] + r12 * Y[far] + Tx
    yc = r21 * X[far] + r22 * Y[far] + Ty
    if not (np.sign(xc) == np.sign(x[far]) and np.sign(yc) == np.sign(y[far])):
        Ty = -Ty
        r11, r12, r21, r22, Tx = r1 * Ty, r2 * Ty, r3 * Ty, r4 * Ty, tx_ * Ty
    # complete the rotation: r13, r23 from unit rows, third row from the cross product
    r13 = math.sqrt(max(1 - r11 ** 2 - r12 ** 2, 0.0))
    r23 = math.sqrt(max(1 - r21 ** 2 - r22 ** 2, 0.0))
    tilt = math.degrees(math.asin(min(math.hypot(r13, r23), 1.0)))
    if tilt < MIN_TILT_DEG:
        raise SolveError(f"extrinsic: view is fronto-parallel (tilt {tilt:.1f} deg < "
                         f"{MIN_TILT_DEG} deg): the rotation's sign is undetermined")
    if r11 * r21 + r12 * r22 > 0:
        r23 = -r23
    candidates = []
    for sign in (1.0, -1.0):
        row1 = np.array([r11, r12, sign * r13])
        row2 = np.array([r21, r22, sign * r23])
        R = np.vstack([row1, row2, np.cross(row1, row2)])
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
        # f_x and Tz from (4.1) by least squares: x (r31 X + r32 Y + Tz) = f (r11 X + ...)
        num = R[0, 0] * X + R[0, 1] * Y + Tx
        M = np.c_[num, -x]
        rhs = x * (R[2, 0] * X + R[2, 1] * Y)
        (f_est, tz_est), *_ = np.linalg.lstsq(M, rhs, rcond=None)
        if f_est > 0 and tz_est > 0:  # the thesis's test on the sign of theta
            candidates.append((float(np.sum((M @ [f_est, tz_est] - rhs) ** 2)), R))
    if not candidates:
        raise SolveError("extrinsic: no rotation gives a positive focal length")
    R = min(candidates, key=lambda c: c[0])[1]
    # Tz by least squares from (4.1) and (4.2) with the known focal lengths
    den = R[2, 0] * X + R[2, 1] * Y
    num_x = fx * (R[0, 0] * X + R[0, 1] * Y + Tx)
    num_y = fy * (R[1, 0] * X + R[1, 1] * Y + Ty)
    lhs = np.r_[x, y]
    Tz = float(np.sum(lhs * (np.r_[num_x, num_y] - lhs * np.r_[den, den])) / np.sum(lhs * lhs))
    if Tz <= 0:
        raise SolveError("extrinsic: target behind the camera (Tz <= 0)")
    return make_T(R, [Tx, Ty, Tz])


def refine_pose(T0: np.ndarray, obj: np.ndarray, pixels: np.ndarray, K: np.ndarray,
                dist=None) -> tuple[np.ndarray, float]:
    """Levenberg-Marquardt on the reprojection error (6 pose parameters)."""
    dist = np.zeros(5) if dist is None else np.asarray(dist, float)

    def residual(p):
        proj, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), p[:3], p[3:], K, dist)
        return (proj.reshape(-1, 2) - pixels).ravel()

    p0 = np.r_[R_to_rotvec(T0[:3, :3]), T0[:3, 3]]
    sol = least_squares(residual, p0, method="lm")
    r = sol.fun
    return make_T(rotvec_to_R(sol.x[:3]), sol.x[3:]), float(np.sqrt(np.mean(r ** 2)) * math.sqrt(2))


def estimate_pose(obj: np.ndarray, pixels: np.ndarray, K: np.ndarray, dist=None,
                  fallback: bool = True) -> PoseEstimate:
    """Tsai's closed form, refined by LM. ``rms_px`` is the RMS corner distance. Where
    Tsai refuses the view (fronto-parallel, or no consistent sign), OpenCV's planar IPPE
    solver starts the LM instead (``fallback``); the estimate records which method.
    Corners not seen (NaN rows of an id-ordered array, a ChArUco board seen in part) are
    left out with their board points."""
    seen = np.all(np.isfinite(np.reshape(pixels, (-1, 2))), axis=1)
    obj, pixels = np.asarray(obj)[seen], np.reshape(pixels, (-1, 2))[seen]
    method = "tsai"
    try:
        T0 = tsai_planar(obj, pixels, K, dist)
    except SolveError as exc:
        bad_input = any(k in str(exc) for k in ("collinear", "need at least", "plane Z"))
        if not fallback or bad_input:
            raise
        ok, rvec, tvec = cv2.solvePnP(obj.astype(np.float64), pixels.astype(np.float64), K,
                                      None if dist is None else np.asarray(dist, float),
                                      flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            raise SolveError("extrinsic: IPPE failed on a fronto-parallel view") from None
        T0 = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        method = "ippe"
    T, rms = refine_pose(T0, obj, pixels, K, dist)
    return PoseEstimate(T, rms, T0, method)


# A corner the view's own board pose misses by more than this many times the view's median
# corner, and by CORNER_MIN_PX, was put on something else than the board's corner (a shape
# in front of it: random worlds 400008, 400023). Good corners (0.1-0.3 px) sit 8 sigma and
# more below it.
CORNER_FACTOR = 6.0
CORNER_MIN_PX = 1.5


def stray_corners(obj: np.ndarray, pixels: np.ndarray, K: np.ndarray, dist,
                  T_cam_target: np.ndarray) -> np.ndarray:
    """Indices of the corners seen (finite rows of ``pixels``) that the board pose
    ``T_cam_target`` (the view's own, ``estimate_pose``) reprojects more than
    ``CORNER_FACTOR`` times the median corner's distance and ``CORNER_MIN_PX`` away from
    where they were detected."""
    pixels = np.reshape(pixels, (-1, 2))
    seen = np.flatnonzero(np.all(np.isfinite(pixels), axis=1))
    rvec = cv2.Rodrigues(np.ascontiguousarray(T_cam_target[:3, :3]))[0]
    proj, _ = cv2.projectPoints(np.asarray(obj, float)[seen].reshape(-1, 1, 3), rvec,
                                T_cam_target[:3, 3].astype(float), K,
                                None if dist is None else np.asarray(dist, float))
    miss = np.linalg.norm(proj.reshape(-1, 2) - pixels[seen], axis=1)
    limit = max(CORNER_FACTOR * float(np.median(miss)), CORNER_MIN_PX)
    return seen[miss > limit]
