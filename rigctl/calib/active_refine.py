"""Refinement of active calibration beyond the thesis: nonlinear least squares over all
motions with the exact rotation model (Lemma 3.1 with no translation, ``x' ~ K R^T
K^-1 x``) and the head's geometry.

Camera orientation in the head frame at head angles (pan, tilt, roll)::

    C(p, t, r) = Ry(p) Rx(t) N R_a(r)

``N`` is the camera's mounting rotation relative to the pan/tilt axes and ``a`` the roll
axis in the camera frame (a tilted roll axis, thesis 3.4 and Figs 5.19-5.20). The motion
between a reference capture 0 and capture 1 is ``R = C0^T C1``. Estimated: fx, fy, cx,
cy, N (rotation vector), a (two tilt angles), optionally k1 (radial distortion).

Observations come per motion either as point correspondences (synthetic data) or as
reference contour points with the tracked contour's points and normals in the moved
image (images): then the residual is the point-to-curve distance along the normal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from rigctl.calib.synthetic import rot_axis, rot_x, rot_y
from rigctl.errors import SolveError

PARAM_NAMES = ["fx", "fy", "cx", "cy", "n_x", "n_y", "n_z", "a_x", "a_y", "k1", "k2", "p1",
               "p2"]


@dataclass
class Motion:
    """One reference/moved image pair with the head angles (rad) of both captures."""

    angles0: tuple[float, float, float]
    angles1: tuple[float, float, float]
    ref_points: np.ndarray                   # (N, 2) pixels in image 0
    moved_points: np.ndarray                 # (N, 2) correspondences, or curve points
    moved_normals: np.ndarray | None = None  # (M, 2) unit normals: curve mode
    label: str = ""
    _tree: cKDTree | None = field(default=None, repr=False)

    @property
    def curve_mode(self) -> bool:
        return self.moved_normals is not None

    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.moved_points)
        return self._tree


def camera_orientation(angles, N: np.ndarray, a: np.ndarray) -> np.ndarray:
    p, t, r = angles
    return rot_y(p) @ rot_x(t) @ N @ rot_axis(a, r)


def _unpack(x: np.ndarray, n_dist: int):
    fx, fy, cx, cy = x[:4]
    N = rot_axis(x[4:7], np.linalg.norm(x[4:7])) if np.linalg.norm(x[4:7]) > 0 else np.eye(3)
    a = rot_x(x[7]) @ rot_y(x[8]) @ np.array([0.0, 0.0, 1.0])
    k = np.zeros(4)  # k1, k2, p1, p2 (OpenCV's convention)
    k[:n_dist] = x[9:9 + n_dist]
    return fx, fy, cx, cy, N, a, k


def _radial(r2, k):
    return 1 + k[0] * r2 + k[1] * r2 * r2


def _distort(xn, k):
    """OpenCV's radial (k1, k2) and tangential (p1, p2) model on normalised points."""
    x, y = xn[:, :1], xn[:, 1:2]
    r2 = x * x + y * y
    radial = _radial(r2, k)
    dx = 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
    dy = k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
    return np.c_[x * radial + dx, y * radial + dy]


def _undistort(pts, fx, fy, cx, cy, k):
    xn = np.c_[(pts[:, 0] - cx) / fx, (pts[:, 1] - cy) / fy]
    if not np.any(k):
        return xn
    und = xn.copy()
    for _ in range(10):  # fixed point of xn = und * radial(und) + tangential(und)
        x, y = und[:, :1], und[:, 1:2]
        r2 = x * x + y * y
        tangential = np.c_[2 * k[2] * x * y + k[3] * (r2 + 2 * x * x),
                           k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y]
        und = (xn - tangential) / _radial(r2, k)
    return und


def predict(motion: Motion, x: np.ndarray, n_dist: int) -> np.ndarray:
    """Where the reference points land in the moved image under parameters ``x``
    (thesis eq. 3.3: back-project through K and the distortion, rotate by the head's
    motion, project again)."""
    return predict_many([motion], x, n_dist)[0]


def predict_many(motions: list[Motion], x: np.ndarray, n_dist: int,
                 refs: np.ndarray | None = None) -> list[np.ndarray]:
    """``predict`` for several motions at once: the reference points of all of them
    (``refs``, their concatenation, if already built) are undistorted and distorted in
    one pass each; only the rotation differs per motion."""
    fx, fy, cx, cy, N, a, k = _unpack(x, n_dist)
    if refs is None:
        refs = np.concatenate([m.ref_points for m in motions])
    rays = np.c_[_undistort(refs, fx, fy, cx, cy, k), np.ones(len(refs))]
    moved, start = np.empty_like(rays), 0
    for motion in motions:
        R = camera_orientation(motion.angles0, N, a).T @ \
            camera_orientation(motion.angles1, N, a)
        end = start + len(motion.ref_points)
        moved[start:end] = rays[start:end] @ R
        start = end
    # A trial step may turn points behind the camera: keep the residuals finite (and
    # large) so the optimiser backs off instead of failing.
    xn = moved[:, :2] / np.maximum(moved[:, 2:3], 1e-3)
    if n_dist:
        xn = _distort(xn, k)
    pixels = np.c_[fx * xn[:, 0] + cx, fy * xn[:, 1] + cy]
    return np.split(pixels, np.cumsum([len(m.ref_points) for m in motions])[:-1])


@dataclass
class RefineResult:
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    k2: float
    p1: float
    p2: float
    mount_rotvec: np.ndarray
    roll_axis: np.ndarray
    sigma: dict[str, float]
    rms_px: float
    inliers: int
    outliers: int
    residuals_by_motion: dict[str, float]

    def as_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "k1": self.k1,
                "k2": self.k2, "p1": self.p1, "p2": self.p2,
                "mount_rotvec": self.mount_rotvec.tolist(), "roll_axis": self.roll_axis.tolist(),
                "sigma": self.sigma, "rms_px": self.rms_px, "inliers": self.inliers,
                "outliers": self.outliers, "residuals_by_motion": self.residuals_by_motion}


def _residuals(x, motions, n_dist, masks, associations, refs=None):
    out = []
    for m, (motion, predicted) in enumerate(zip(motions, predict_many(motions, x, n_dist, refs),
                                                strict=True)):
        pred = predicted[masks[m]]
        if motion.curve_mode:
            idx = associations[m]
            q = motion.moved_points[idx]
            n = motion.moved_normals[idx]
            out.append(np.sum((pred - q) * n, axis=1))
        else:
            out.append((pred - motion.moved_points[masks[m]]).ravel())
    return np.concatenate(out)


def refine(motions: list[Motion], initial: dict[str, float], n_dist: int = 0,
           outlier_sigmas: float = 3.0, outer_iterations: int = 4,
           prior_deg: float = 5.0) -> RefineResult:
    """Joint refinement of fx, fy, cx, cy, the mounting rotation and the roll axis
    (and ``n_dist`` distortion terms: k1; k1, k2; or k1, k2, p1, p2) over all motions,
    from ``initial`` (fx, fy, cx, cy; e.g. Strategy D), with a soft-L1 robust loss,
    then 3-sigma outlier rejection. 1-sigma uncertainties come from the Jacobian at the
    solution, scaled by the residual variance."""
    if len(motions) < 2:
        raise SolveError("refinement: needs at least two motions")
    if sum(len(m.ref_points) for m in motions) < 20:
        raise SolveError("refinement: too few contour points")
    if n_dist not in (0, 1, 2, 4):
        raise SolveError(f"refinement: n_dist must be 0, 1, 2 or 4, got {n_dist}")
    n_params = 9 + n_dist
    x = np.zeros(n_params)
    x[:4] = [initial["fx"], initial["fy"], initial["cx"], initial["cy"]]
    masks = [np.ones(len(m.ref_points), bool) for m in motions]
    prior = np.radians(prior_deg)
    refs = np.concatenate([m.ref_points for m in motions])

    def associate(xv):
        out = []
        for m, (motion, predicted) in enumerate(zip(motions, predict_many(motions, xv, n_dist,
                                                                          refs), strict=True)):
            if motion.curve_mode:
                _, idx = motion.tree().query(predicted[masks[m]])
                out.append(idx)
            else:
                out.append(None)
        return out

    def fun(xv, assoc):
        r = _residuals(xv, motions, n_dist, masks, assoc, refs)
        # weak priors keep the rotation parameters near the nominal head (5 deg sigma)
        return np.concatenate([r, xv[4:9] / prior])

    result = None
    for _ in range(outer_iterations):
        assoc = associate(x)
        result = least_squares(fun, x, args=(assoc,), loss="soft_l1", f_scale=1.0,
                               x_scale="jac", max_nfev=200)
        x = result.x
        r = _residuals(x, motions, n_dist, masks, assoc, refs)
        scale = 1.4826 * np.median(np.abs(r)) + 1e-9
        changed = False
        offset = 0
        for m, motion in enumerate(motions):
            count = int(masks[m].sum()) * (1 if motion.curve_mode else 2)
            rm = r[offset:offset + count]
            offset += count
            per_point = np.abs(rm) if motion.curve_mode else np.hypot(rm[0::2], rm[1::2])
            keep = per_point <= outlier_sigmas * scale * (1 if motion.curve_mode else 1.5)
            if not keep.all():
                idx = np.flatnonzero(masks[m])
                masks[m][idx[~keep]] = False
                changed = True
        if not changed:
            break
    assoc = associate(x)
    final = least_squares(fun, x, args=(assoc,), loss="linear", x_scale="jac", max_nfev=100)
    x = final.x
    r = _residuals(x, motions, n_dist, masks, assoc, refs)
    if not np.all(np.isfinite(x)) or not np.all(np.isfinite(r)):
        raise SolveError("refinement diverged (non-finite parameters)")
    dof = max(len(r) - n_params, 1)
    s2 = float(np.sum(r ** 2) / dof)
    J = final.jac[:len(r)]
    JtJ = J.T @ J + np.diag(np.r_[np.zeros(4), np.full(5, 1 / prior ** 2),
                                  np.zeros(n_params - 9)])
    try:
        cov = np.linalg.inv(JtJ) * s2
    except np.linalg.LinAlgError:
        raise SolveError("refinement: singular normal equations (degenerate motions)") from None
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    fx, fy, cx, cy, _, a, k = _unpack(x, n_dist)
    by_motion, offset = {}, 0
    for m, motion in enumerate(motions):
        count = int(masks[m].sum()) * (1 if motion.curve_mode else 2)
        rm = r[offset:offset + count]
        offset += count
        rms = float(np.sqrt(np.mean(rm ** 2))) if count else 0.0
        by_motion[motion.label or f"motion {m}"] = rms
    total = sum(len(m.ref_points) for m in motions)
    inliers = int(sum(mk.sum() for mk in masks))
    return RefineResult(float(fx), float(fy), float(cx), float(cy), float(k[0]), float(k[1]),
                        float(k[2]), float(k[3]), x[4:7].copy(),
                        a, {name: float(s) for name, s in zip(PARAM_NAMES, sig, strict=False)},
                        float(np.sqrt(np.mean(r ** 2))), inliers, total - inliers, by_motion)
