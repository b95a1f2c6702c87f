"""How far a new calibration is from the last accepted one, where it matters, and how
much of that its uncertainty explains.

* Intrinsics: the projection difference across the image (mrcal's ``projection_diff``
  idea). Each pixel of a grid is unprojected with the old camera and projected with the
  new one; the heat map is the distance in pixels. An optional best-fit rotation of the
  camera absorbs the part of a change that an extrinsic recalibration would take up
  (a principal point shift looks like a small turn in the far field).
* Arm models: the camera's position in the base frame, ``T_base_link0 FK(q) X``, with
  each model, over the configurations the new run visited.

Each difference is divided by its own first-order 1-sigma (both calibrations
independent): ``|diff| / sqrt(sigma_new^2 + sigma_old^2)``. A ratio above 3 is a change
the measurements resolve; below, it is within their noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from rigctl.calib.robot import camera_position_sigma
from rigctl.geometry.camera import camera_matrix
from rigctl.geometry.kinematics import KinematicModel
from rigctl.geometry.transforms import rotvec_to_R


@dataclass
class ProjectionDifference:
    """The grid (pixel centres), the difference (px) and its 1-sigma (px) at each."""

    u: np.ndarray  # (rows, cols)
    v: np.ndarray
    diff_px: np.ndarray
    sigma_px: np.ndarray | None
    fitted_rotation_deg: float

    @property
    def z(self) -> np.ndarray | None:
        return None if self.sigma_px is None else self.diff_px / np.maximum(self.sigma_px, 1e-12)

    def summary(self) -> dict[str, Any]:
        out = {"max_px": float(self.diff_px.max()), "median_px": float(np.median(self.diff_px)),
               "fitted_rotation_deg": self.fitted_rotation_deg}
        if self.sigma_px is not None:
            out["max_z"] = float(self.z.max())
        return out


def _camera(intr: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    K = camera_matrix(intr["fx"], intr["fy"], intr["cx"], intr["cy"])
    return K, np.asarray(intr.get("distortion") or [0.0] * 5, float)


def _projection_sigma(intr: dict[str, Any], xd: np.ndarray, yd: np.ndarray) -> np.ndarray | None:
    """1-sigma (px) of projecting a fixed ray whose distorted normalised coordinates are
    (xd, yd): u = fx xd + cx, v = fy yd + cy, from the diagonal sigma of fx, fy, cx, cy
    (what results report; correlations and distortion terms left out)."""
    s = intr.get("sigma") or {}
    if not all(s.get(k) is not None for k in ("fx", "fy", "cx", "cy")):
        return None
    su = np.hypot(xd * s["fx"], s["cx"])
    sv = np.hypot(yd * s["fy"], s["cy"])
    return np.hypot(su, sv)


def projection_difference(new: dict[str, Any], old: dict[str, Any], width: int, height: int,
                          cols: int = 48, rows: int = 27,
                          fit_rotation: bool = False) -> ProjectionDifference:
    """The projection difference between two pinhole-plus-Brown cameras (the intrinsics
    of eq. 2.1 with OpenCV's distortion) over a ``cols`` x ``rows`` grid of the image.
    With ``fit_rotation``, the rotation of the ray bundle that best aligns them is
    removed first (least squares over the grid)."""
    u, v = np.meshgrid((np.arange(cols) + 0.5) * width / cols,
                       (np.arange(rows) + 0.5) * height / rows)
    pts = np.stack([u.ravel(), v.ravel()], axis=1)
    K_old, d_old = _camera(old)
    K_new, d_new = _camera(new)
    xy = cv2.undistortPoints(pts.reshape(-1, 1, 2), K_old, d_old).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])

    def project(rotvec: np.ndarray) -> np.ndarray:
        out, _ = cv2.projectPoints(rays @ rotvec_to_R(rotvec).T, np.zeros(3), np.zeros(3),
                                   K_new, d_new)
        return out.reshape(-1, 2)

    rotvec = np.zeros(3)
    if fit_rotation:
        rotvec = least_squares(lambda r: (project(r) - pts).ravel(), rotvec).x
    diff = np.linalg.norm(project(rotvec) - pts, axis=1).reshape(u.shape)
    # distorted normalised coordinates, for the sigma of u = fx xd + cx
    xd_old = ((pts[:, 0] - old["cx"]) / old["fx"]).reshape(u.shape)
    yd_old = ((pts[:, 1] - old["cy"]) / old["fy"]).reshape(u.shape)
    s_old = _projection_sigma(old, xd_old, yd_old)
    s_new = _projection_sigma(new, xd_old, yd_old)
    sigma = None if s_old is None or s_new is None else np.hypot(s_old, s_new)
    return ProjectionDifference(u, v, diff, sigma, float(np.degrees(np.linalg.norm(rotvec))))


@dataclass
class ArmDifference:
    """Per configuration: the camera position difference (mm) and its 1-sigma (mm)."""

    q: np.ndarray
    diff_mm: np.ndarray
    sigma_mm: np.ndarray | None

    def summary(self) -> dict[str, Any]:
        out = {"configurations": len(self.q), "max_mm": float(self.diff_mm.max()),
               "median_mm": float(np.median(self.diff_mm))}
        if self.sigma_mm is not None:
            out["max_z"] = float((self.diff_mm / np.maximum(self.sigma_mm, 1e-12)).max())
        return out


def _base_frame_sigma_m(result: dict[str, Any], model: KinematicModel, X: np.ndarray,
                        q: np.ndarray) -> np.ndarray | None:
    """1-sigma norm (m) of the camera's base-frame position at each q, from the result's
    covariance of the arm and hand-eye terms (``linkN.*``, ``X.*``); the target pose and
    the camera intrinsics do not move the camera."""
    cov = result.get("covariance") or {}
    names, matrix = cov.get("names"), cov.get("matrix")
    if not names or matrix is None:
        return None
    keep = [i for i, n in enumerate(names) if n.startswith(("link", "X."))]
    sub = np.asarray(matrix, float)[np.ix_(keep, keep)]
    sig = camera_position_sigma(model, X, np.eye(4), [names[i] for i in keep], sub, q)
    return np.linalg.norm(sig, axis=1)


def arm_difference(new: dict[str, Any], old: dict[str, Any], q_list) -> ArmDifference:
    """The camera position ``T_base_link0 FK(q) X`` (eq. 4.11's chain) of two
    robot-kinematics results at each configuration of ``q_list``, and the difference's
    1-sigma from both covariances (first order)."""
    q = np.atleast_2d(np.asarray(q_list, float))
    positions, sigmas = [], []
    for result in (new, old):
        model = KinematicModel.from_export(result)
        X = np.asarray(result["T_flange_cam"], float)
        positions.append((model.fk_batch(q) @ X)[:, :3, 3])
        sigmas.append(_base_frame_sigma_m(result, model, X, q))
    diff = 1000 * np.linalg.norm(positions[0] - positions[1], axis=1)
    sigma = None if sigmas[0] is None or sigmas[1] is None else \
        1000 * np.hypot(sigmas[0], sigmas[1])
    return ArmDifference(q, diff, sigma)


def hand_eye_difference(new: dict[str, Any], old: dict[str, Any]) -> dict[str, Any]:
    """The hand-eye translation change (mm) and rotation change (deg) between two
    results with ``T_flange_cam``, and the translation change over its 1-sigma where
    both report ``sigma`` (rotvec X, t X, rotvec W, t W; metres and radians)."""
    A, B = np.asarray(new["T_flange_cam"], float), np.asarray(old["T_flange_cam"], float)
    dt = A[:3, 3] - B[:3, 3]
    cos = np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2, -1.0, 1.0)
    out = {"translation_mm": float(1000 * np.linalg.norm(dt)),
           "rotation_deg": float(np.degrees(np.arccos(cos)))}
    sn, so = new.get("sigma"), old.get("sigma")
    if isinstance(sn, list) and isinstance(so, list) and len(sn) >= 6 and len(so) >= 6:
        s = np.hypot(np.asarray(sn[3:6], float), np.asarray(so[3:6], float))
        out["translation_z"] = float(np.max(np.abs(dt) / np.maximum(s, 1e-12)))
    return out
