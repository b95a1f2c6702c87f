"""Hand-eye calibration: ``X = T_flange_cam`` (and ``W = T_base_target``) from arm poses
``F_k = T_base_flange`` and camera measurements ``C_k = T_cam_target``, with
``W = F_k X C_k`` for every sample k.

- ``closed_form``: OpenCV ``calibrateHandEye``, every method, on samples ordered by
  ``order_samples`` (large, non-parallel relative rotations; independent of input order).
- ``refine_pixels``: joint least squares of X and W on board-corner reprojection error.
- ``refine_poses``: maximum likelihood on pose measurements, camera poses compared in the
  camera frame and, optionally, noisy arm poses as errors in variables (for pose-level
  noise models such as OpenCV's own tests).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rigctl.calib.covariance import robust_covariance, view_clusters
from rigctl.errors import SolveError
from rigctl.geometry.transforms import R_to_rotvec, inv_T, make_T, rotation_angle, rotvec_to_R

log = logging.getLogger(__name__)

METHODS = {"tsai": cv2.CALIB_HAND_EYE_TSAI, "park": cv2.CALIB_HAND_EYE_PARK,
           "horaud": cv2.CALIB_HAND_EYE_HORAUD, "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
           "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS}
MIN_PAIR_ANGLE = np.radians(5.0)
MAX_AXIS_COS = np.cos(np.radians(15.0))


def _relative_axis(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, np.ndarray]:
    R = Ta[:3, :3].T @ Tb[:3, :3]
    rv = R_to_rotvec(R)
    angle = float(np.linalg.norm(rv))
    return angle, (rv / angle if angle > 1e-12 else np.zeros(3))


def order_samples(F: list[np.ndarray]) -> list[int]:
    """A deterministic order of the samples in which consecutive motions rotate by at
    least 5 deg about axes at least 15 deg apart from the previous motion's: start from
    the canonically smallest pose, then greedily take the largest admissible rotation.
    Samples that never qualify are appended at the end. The order depends only on the
    poses, so the result does not depend on the order the samples came in."""
    n = len(F)
    if n < 3:
        raise SolveError(f"hand-eye: {n} samples; need at least 3")
    keys = [tuple(np.round(T[:3, 3], 6)) + tuple(np.round(T[:3, :3].ravel(), 6)) for T in F]
    current = min(range(n), key=lambda i: keys[i])
    order, left, last_axis = [current], set(range(n)) - {current}, None
    while left:
        best, best_angle = None, -1.0
        for j in sorted(left, key=lambda i: keys[i]):
            angle, axis = _relative_axis(F[current], F[j])
            if angle < MIN_PAIR_ANGLE:
                continue
            if last_axis is not None and abs(float(axis @ last_axis)) > MAX_AXIS_COS:
                continue
            if angle > best_angle:
                best, best_angle = j, angle
        if best is None:
            break
        last_axis = _relative_axis(F[current], F[best])[1]
        order.append(best)
        left.remove(best)
        current = best
    return order + sorted(left, key=lambda i: keys[i])


def closed_form(F: list[np.ndarray], C: list[np.ndarray]) -> dict[str, np.ndarray]:
    """X by every OpenCV method (``calibrateHandEye``), on ordered samples. A method that
    fails on these motions (OpenCV raises, e.g. "Rotation normalization issue" from Park
    on a UR3e's near-parallel rotation axes, or returns NaN) is left out."""
    idx = order_samples(F)
    R_g2b = [F[i][:3, :3] for i in idx]
    t_g2b = [F[i][:3, 3] for i in idx]
    R_t2c = [C[i][:3, :3] for i in idx]
    t_t2c = [C[i][:3, 3] for i in idx]
    out = {}
    for name, method in METHODS.items():
        try:
            R, t = cv2.calibrateHandEye(R_g2b, t_g2b, R_t2c, t_t2c, method=method)
        except cv2.error as exc:
            log.warning("hand-eye: %s failed: %s", name, str(exc).strip().splitlines()[-1])
            continue
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))) or \
                abs(np.linalg.det(R) - 1.0) > 1e-3:
            log.warning("hand-eye: %s gave no rotation (NaN or det %.3f)", name,
                        float(np.linalg.det(R)) if np.all(np.isfinite(R)) else float("nan"))
            continue
        out[name] = make_T(R, t.ravel())
    if not out:
        raise SolveError("hand-eye: every closed-form method failed (degenerate motions)")
    return out


def best_closed_form(closed: dict[str, np.ndarray]) -> np.ndarray:
    """The start for the refinement: Park's X when it succeeded, else the first that did."""
    return closed.get("park", next(iter(closed.values())))


def average_W(F, C, X) -> np.ndarray:
    """Mean of ``F_k X C_k`` (rotations by chordal mean, translations by mean)."""
    Ts = [F_k @ X @ C_k for F_k, C_k in zip(F, C, strict=True)]
    R = Rotation.from_matrix(np.array([T[:3, :3] for T in Ts])).mean().as_matrix()
    return make_T(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def _params(X, W):
    return np.r_[R_to_rotvec(X[:3, :3]), X[:3, 3], R_to_rotvec(W[:3, :3]), W[:3, 3]]


def _unpack(p):
    return make_T(rotvec_to_R(p[:3]), p[3:6]), make_T(rotvec_to_R(p[6:9]), p[9:12])


@dataclass
class HandEyeResult:
    X: np.ndarray
    W: np.ndarray
    rms: float
    sigma: np.ndarray  # 1-sigma of (rotvec X, t X, rotvec W, t W), residual-scaled
    cov_model: np.ndarray | None = None  # 12x12 covariance from the stated sigmas alone


def refine_poses(F, C, X0, sigma_rot: float = 0.002, sigma_t: float = 0.005,
                 W0: np.ndarray | None = None, sigma_rot_arm: float = 0.0,
                 sigma_t_arm: float = 0.0) -> HandEyeResult:
    """Maximum-likelihood X and W from pose measurements (the loop ``W = F_k X C_k``).

    Each camera pose is compared where its error lives: the predicted
    ``C_k = (F_k X)^-1 W`` against the measured one, rotation as ``log(R_pred R_meas^T)``
    over ``sigma_rot`` and the target's position in the camera frame over ``sigma_t``.
    With arm sigmas, the arm poses are noisy too (errors in variables): each ``F_k`` gets
    a correction (rotation vector and position in the base frame) with a prior of those
    sigmas, solved jointly with X and W on a sparse Jacobian. A residual on the whole loop
    ``W^-1 F_k X C_k`` would instead mix camera rotation error, times the target
    distance, into translation and weight it as if it were translation noise."""
    W0 = average_W(F, C, X0) if W0 is None else W0
    n = len(F)
    eiv = sigma_rot_arm > 0 and sigma_t_arm > 0
    if (sigma_rot_arm > 0) != (sigma_t_arm > 0):
        raise SolveError("hand-eye refinement: give both arm sigmas (rotation and "
                         f"translation) or neither; got {sigma_rot_arm}, {sigma_t_arm}")
    rv_F = Rotation.from_matrix(np.array([T[:3, :3] for T in F])).as_rotvec()
    t_F = np.array([T[:3, 3] for T in F])
    R_C = np.array([T[:3, :3] for T in C])
    t_C = np.array([T[:3, 3] for T in C])

    def fun(p):
        X, W = _unpack(p[:12])
        d = p[12:].reshape(n, 6) if eiv else np.zeros((n, 6))
        R_F = Rotation.from_rotvec(rv_F + d[:, :3]).as_matrix()
        tF = t_F + d[:, 3:]
        # C_pred = X^-1 F^-1 W
        R_FX = R_F @ X[:3, :3]
        t_FX = np.einsum("kij,j->ki", R_F, X[:3, 3]) + tF
        R_pred = np.transpose(R_FX, (0, 2, 1)) @ W[:3, :3]
        t_pred = np.einsum("kji,kj->ki", R_FX, W[:3, 3] - t_FX)
        rot = Rotation.from_matrix(R_pred @ np.transpose(R_C, (0, 2, 1))).as_rotvec()
        res = np.c_[rot / sigma_rot, (t_pred - t_C) / sigma_t]
        if eiv:
            res = np.c_[res, d[:, :3] / sigma_rot_arm, d[:, 3:] / sigma_t_arm]
        return res.ravel()

    p0 = _params(X0, W0)
    sparsity = None
    if eiv:
        p0 = np.r_[p0, np.zeros(6 * n)]
        sparsity = np.zeros((12 * n, 12 + 6 * n), bool)
        for k in range(n):
            sparsity[12 * k:12 * k + 6, :12] = True
            sparsity[12 * k:12 * k + 12, 12 + 6 * k:18 + 6 * k] = True
    sol = least_squares(fun, p0, method="trf", jac_sparsity=sparsity, x_scale="jac")
    X, W = _unpack(sol.x[:12])
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else sol.jac
    dof = max(len(sol.fun) - len(p0), 1)
    cov_model = np.linalg.pinv(J.T @ J)  # the Cramer-Rao bound when the sigmas are right
    cov = cov_model * float(np.sum(sol.fun ** 2) / dof)
    return HandEyeResult(X, W, float(np.sqrt(np.mean(sol.fun ** 2))),
                         np.sqrt(np.clip(np.diag(cov)[:12], 0, None)), cov_model[:12, :12])


def refine_pixels(F, corners: list[np.ndarray], obj: np.ndarray, K, dist, X0,
                  W0: np.ndarray | None = None, C: list[np.ndarray] | None = None
                  ) -> HandEyeResult:
    """Least squares of X and W on board-corner reprojection error over every sample,
    with 1-sigma cluster-robust over the samples (``covariance.robust_covariance``).
    ``corners``: each sample's in the order of ``obj``, NaN rows for corners not seen."""
    if W0 is None:
        if C is None:
            raise SolveError("hand-eye refinement: give W0 or the camera poses C")
        W0 = average_W(F, C, X0)
    dist = np.zeros(5) if dist is None else np.asarray(dist, float)
    # each view's corners with their board points (id order; NaN: a corner not seen)
    views = []
    for c in corners:
        px = np.reshape(np.asarray(c, float), (-1, 2))
        seen = np.all(np.isfinite(px), axis=1)
        views.append((np.asarray(obj, float)[seen].reshape(-1, 1, 3), px[seen]))

    def fun(p):
        X, W = _unpack(p)
        res = []
        for F_k, (pts, px) in zip(F, views, strict=True):
            T_cam_target = inv_T(F_k @ X) @ W
            rv = R_to_rotvec(T_cam_target[:3, :3])
            proj, _ = cv2.projectPoints(pts, rv, T_cam_target[:3, 3], K, dist)
            res.append((proj.reshape(-1, 2) - px).ravel())
        return np.concatenate(res)

    sol = least_squares(fun, _params(X0, W0), loss="soft_l1", f_scale=1.0, x_scale="jac")
    X, W = _unpack(sol.x)
    # a view's corners share its error (the arm's pose, detection bias): one cluster each
    clusters = view_clusters(len(corners), [2 * len(px) for _, px in views])
    # scipy returns the Jacobian weighted by the soft_l1 loss (sqrt rho'); weigh the
    # residuals alike so the sandwich pairs rows that match
    weight = (1.0 + sol.fun ** 2) ** -0.25
    cov = robust_covariance(sol.jac, sol.fun * weight, clusters)
    return HandEyeResult(X, W, float(np.sqrt(np.mean(sol.fun ** 2))),
                         np.sqrt(np.clip(np.diag(cov), 0, None)))


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error deg, translation error mm)."""
    return (float(np.degrees(rotation_angle(T_est[:3, :3].T @ T_true[:3, :3]))),
            float(1000 * np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])))


# -- eye-to-hand: the camera beside the arm, the board on the flange ---------------------


def flange_poses(F: list[np.ndarray], fixed: bool) -> list[np.ndarray]:
    """The arm poses the solvers above take: ``F_k = T_base_flange`` with the camera on the
    flange; with the camera standing beside the arm (``fixed``) their inverses
    ``T_flange_base``. The eye-to-hand loop ``T_base_cam C_k = F_k T_flange_target`` is
    ``T_flange_target = F_k^-1 T_base_cam C_k``: the eye-in-hand loop ``W = F X C`` with
    ``F_k^-1`` for ``F_k``, ``X = T_base_cam`` and ``W = T_flange_target``. OpenCV's
    ``calibrateHandEye`` documents the same substitution (base2gripper in, cam2base out)."""
    return [inv_T(T) for T in F] if fixed else list(F)


def eye_to_hand(F, C, corners: list[np.ndarray], obj: np.ndarray, K, dist
                ) -> tuple[dict[str, np.ndarray], HandEyeResult]:
    """``T_base_cam`` (X) and ``T_flange_target`` (W) from arm poses ``F_k =
    T_base_flange`` and board poses ``C_k = T_cam_target`` of a fixed camera watching the
    flange's board: OpenCV's closed forms (``closed_form``) on the inverted arm poses
    (``flange_poses``), then the same pixel refinement (``refine_pixels``). Returns the
    closed forms (each a ``T_base_cam``) and the refined result."""
    G = flange_poses(F, True)
    closed = closed_form(G, C)
    refined = refine_pixels(G, corners, obj, K, dist, best_closed_form(closed), C=C)
    return closed, refined
