"""Head stations: the head beside the arm re-aimed between board views.

With the head standing beside the arm (eye-to-hand), the arm's board can be followed
across the workspace by turning the head: the views are taken from a few head
stations, station 0 being the head at home. The camera at station s, seen from the
camera at home, is ``D_s``, and a view k taken there closes the loop of (4.11) as

    C_k = D_s^-1 X^-1 FK(q_k) W        (X = T_base_cam at home, W = T_flange_target)

``D_s`` is the head's known motion: the active-camera calibration's head geometry
(``head_model``) at the station's recorded angles. Known only as well as the head
geometry, the encoders' readings and the centre's offset from the axes are known, each
``D_s`` (s >= 1) is refined with the arm, 6 parameters a station, and its prediction
enters as a prior with that uncertainty:

- rotation: the geometry's rotation covariance propagated to the station, plus the
  encoders' sigma at the home and the station readings, plus ``ROTATION_FLOOR_RAD``;
- translation: ``(R - I) o`` with the offset ``o`` (estimated, or its prior), plus
  ``TRANSLATION_FLOOR_M`` for axes that do not quite meet (the model's centre of
  rotation is a point).

On random worlds the geometry's rotation from home over pans and tilts of 15-20 deg is
about 0.03 deg off (``rigctl bench active-worlds``), and a fixed head's offset is not
estimated (3 mm prior): at a metre the prior holds a station to about a millimetre, the
board views to a tenth of that, so the views decide and the prior keeps a station with
few views in place.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rigctl.calib.head_model import HeadGeometry
from rigctl.geometry.transforms import R_to_rotvec, inv_T, make_T, rotvec_to_R

ROTATION_FLOOR_RAD = np.radians(0.02)
TRANSLATION_FLOOR_M = 0.001
# a pixel residual's scale for the prior's rows in the least squares (the covariance
# rescales them by the residuals' own variance)
PRIOR_PIXEL_SCALE = 0.3


@dataclass
class Stations:
    """The views' stations: ``index`` per view (0: home), and for each station after
    the first its head angles (rad, as recorded), the predicted ``D_s`` and the prior's
    information matrix (6x6 over the rotation vector's and the translation's errors)."""

    index: np.ndarray
    angles: list[tuple[float, float, float]] = field(default_factory=list)
    predicted: list[np.ndarray] = field(default_factory=list)
    information: list[np.ndarray] = field(default_factory=list)

    @property
    def count(self) -> int:
        """The stations after the first (each one's 6 parameters are refined)."""
        return len(self.predicted)


def names(count: int) -> list[str]:
    return [f"station{s + 1}.{c}" for s in range(count)
            for c in ("rx", "ry", "rz", "x", "y", "z")]


def pack(D: list[np.ndarray]) -> np.ndarray:
    return np.array([v for T in D for v in (*R_to_rotvec(T[:3, :3]), *T[:3, 3])], float)


def unpack(p: np.ndarray) -> list[np.ndarray]:
    return [make_T(rotvec_to_R(p[6 * s:6 * s + 3]), p[6 * s + 3:6 * s + 6])
            for s in range(len(p) // 6)]


def view_inverses(stations: Stations, D: list[np.ndarray]) -> np.ndarray:
    """``D_s^-1`` of each view's station (views x 4 x 4; the identity at home)."""
    inverses = np.stack([np.eye(4)] + [inv_T(T) for T in D])
    return inverses[stations.index]


def prior_rows(stations: Stations, D: list[np.ndarray], scale: float = 1.0) -> np.ndarray:
    """Each station's prior residual ``L^T e`` (``L L^T`` its information; ``e`` the
    rotation vector of ``R R_pred^T`` and ``t - t_pred``), times ``scale`` (the
    residuals' unit: a pixel's for corners)."""
    rows = []
    for T, T_pred, info in zip(D, stations.predicted, stations.information, strict=True):
        e = np.r_[R_to_rotvec(T[:3, :3] @ T_pred[:3, :3].T), T[:3, 3] - T_pred[:3, 3]]
        rows.append(np.linalg.cholesky(info).T @ e)
    return scale * np.concatenate(rows) if rows else np.zeros(0)


def predicted_station(geometry: HeadGeometry, home: tuple, angles: tuple,
                      encoder_sigma_rad: tuple | None) -> tuple[np.ndarray, np.ndarray]:
    """``D_s`` at ``angles`` from the head at ``home`` (both as recorded, rad) and its
    prior's information matrix (module note)."""
    T0, T1 = geometry.T_home_cam(home), geometry.T_home_cam(angles)
    D = inv_T(T0) @ T1
    rot_cov = geometry.rotation_covariance_at(angles, home=home)
    if encoder_sigma_rad is not None:
        J = _angle_jacobian(geometry, home, angles, D)
        rot_cov = rot_cov + J @ np.diag(np.tile(np.square(encoder_sigma_rad), 2)) @ J.T
    rot_cov = rot_cov + np.eye(3) * ROTATION_FLOOR_RAD ** 2
    # the home camera's translation (R - I) o, in the home camera's frame
    A = T0[:3, :3].T @ (T1[:3, :3] - T0[:3, :3])
    t_cov = A @ np.diag(np.square(geometry.offset_sigma_m)) @ A.T \
        + np.eye(3) * TRANSLATION_FLOOR_M ** 2
    cov = np.zeros((6, 6))
    cov[:3, :3], cov[3:, 3:] = rot_cov, t_cov
    return D, np.linalg.inv(cov)


def _angle_jacobian(geometry: HeadGeometry, home, angles, D, step: float = 1e-7
                    ) -> np.ndarray:
    """d log(D(a0, a) D^T) / d (a0, a): the station's rotation against the six readings."""
    J = np.empty((3, 6))
    both = np.r_[home, angles]
    for i in range(6):
        e = np.zeros(6)
        e[i] = step
        plus, minus = both + e, both - e
        Rp = geometry.rotation_from_home(tuple(plus[3:]), home=tuple(plus[:3]))
        Rm = geometry.rotation_from_home(tuple(minus[3:]), home=tuple(minus[:3]))
        J[:, i] = (R_to_rotvec(Rp @ D[:3, :3].T) - R_to_rotvec(Rm @ D[:3, :3].T)) / (2 * step)
    return J
