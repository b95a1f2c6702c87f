"""The pan/tilt/roll head's geometry, as the active-camera calibration measures it.

The camera's orientation in the head frame at head angles ``a = (pan, tilt, roll)``
(thesis 3.4, eq. 3.3, with the mounting and the tilted roll axis of Figs 5.19-5.20; the
refinement's model, ``active_rotations``)::

    C(a) = Ry(pan) Rx(tilt) N R_u(roll),   u = Rx(t0) Ry(t1) e_z

and the centre of projection sits ``o`` off the axes' meeting point, in the camera frame.
So the camera at angles ``a`` seen from the camera at home (all angles zero) is::

    T_home_cam(a) = [ R | (R - I) o ],   R = C(0)^T C(a) = N^T Ry Rx N R_u

which is what a head standing beside the arm needs to carry a view taken with the head
re-aimed back to the camera at home. The active-camera result records ``N`` (its
rotation vector), the roll axis's two tilts, ``o`` when the arm's move measured the
scene's depths (else only its prior), and their covariance (``head_geometry``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl.calib.active_rotations import mounting, roll_axis
from rigctl.calib.synthetic import rot_axis, rot_x, rot_y
from rigctl.errors import SolveError
from rigctl.geometry.transforms import R_to_rotvec, make_T

# the order of the rotation parameters in ``HeadGeometry.rotation_covariance`` (the
# active-camera refinement's names, ``active_refine.PARAM_NAMES``)
ROTATION_NAMES = ("n_x", "n_y", "n_z", "a_x", "a_y")
OFFSET_NAMES = ("s_x", "s_y", "s_z")
HOME = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class HeadGeometry:
    """The head's calibrated geometry (module note): the mounting's rotation vector, the
    roll axis's tilts (rad), the centre's offset ``o`` (m, camera frame) and the
    covariance of the five rotation parameters (``ROTATION_NAMES``). Without a measured
    offset, ``offset_m`` is zero and ``offset_sigma_m`` its prior."""

    mount_rotvec: np.ndarray
    roll_tilts: np.ndarray
    offset_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    offset_estimated: bool = False
    offset_sigma_m: np.ndarray = field(default_factory=lambda: np.full(3, 0.003))
    rotation_covariance: np.ndarray = field(default_factory=lambda: np.zeros((5, 5)))

    @property
    def roll_axis(self) -> np.ndarray:
        """The roll axis in the camera frame (a unit vector)."""
        return roll_axis(self.roll_tilts)

    def orientation(self, angles, params: np.ndarray | None = None) -> np.ndarray:
        """``C(a) = Ry(pan) Rx(tilt) N R_u(roll)``, the camera in the head frame (eq. 3.3
        with the mounting and roll axis; ``params``: the five rotation parameters instead
        of this geometry's)."""
        x = self.rotation_params() if params is None else params
        pan, tilt, roll = angles
        return rot_y(pan) @ rot_x(tilt) @ mounting(x[:3]) @ rot_axis(roll_axis(x[3:5]), roll)

    def rotation_params(self) -> np.ndarray:
        return np.r_[self.mount_rotvec, self.roll_tilts]

    def rotation_from_home(self, angles, params: np.ndarray | None = None,
                           home=HOME) -> np.ndarray:
        """``R = C(home)^T C(a)``: the camera at ``angles`` in the frame of the camera at
        ``home`` (all angles zero unless given; thesis Lemma 3.1, eq. 3.3)."""
        return self.orientation(home, params).T @ self.orientation(angles, params)

    def T_home_cam(self, angles) -> np.ndarray:
        """``[R | (R - I) o]``: the camera at ``angles`` in the frame of the camera at
        home, its centre swung round the axes by the offset ``o`` (module note)."""
        R = self.rotation_from_home(angles)
        return make_T(R, (R - np.eye(3)) @ self.offset_m)

    def rotation_covariance_at(self, angles, home=HOME) -> np.ndarray:
        """The 3x3 covariance (rad^2, about the ``home`` camera's axes) of
        ``rotation_from_home(angles, home=home)`` from the rotation parameters' covariance
        (first order)."""
        J = self._rotation_jacobian(angles, home=home)
        return J @ self.rotation_covariance @ J.T

    def rotation_sigma_rad(self, angles) -> np.ndarray:
        """The 1-sigma (rad) of ``rotation_from_home(angles)`` about the home camera's x, y
        and z axes, from the rotation parameters' covariance (first order, central
        differences of ``log(R0^T R(x))``)."""
        return np.sqrt(np.clip(np.diag(self.rotation_covariance_at(angles)), 0.0, None))

    def rotation_error_z(self, angles, R_true: np.ndarray) -> np.ndarray:
        """This geometry's rotation error at ``angles`` against ``R_true`` (the rotation
        vector of ``R R_true^T``, home camera frame) divided by its sigma per axis, and the
        Mahalanobis norm as a fourth entry (its square is chi-squared with 3 degrees of
        freedom when the covariance is honest)."""
        R = self.rotation_from_home(angles)
        error = R_to_rotvec(R @ R_true.T)
        cov = self.rotation_covariance_at(angles)
        sigma = np.sqrt(np.clip(np.diag(cov), 1e-30, None))
        mahalanobis = float(np.sqrt(error @ np.linalg.pinv(cov, rcond=1e-12) @ error))
        return np.r_[error / sigma, mahalanobis]

    def _rotation_jacobian(self, angles, step: float = 1e-7, home=HOME) -> np.ndarray:
        x0 = self.rotation_params()
        R0 = self.rotation_from_home(angles, home=home)
        J = np.empty((3, 5))
        for i in range(5):
            e = np.zeros(5)
            e[i] = step
            plus = R_to_rotvec(self.rotation_from_home(angles, x0 + e, home) @ R0.T)
            minus = R_to_rotvec(self.rotation_from_home(angles, x0 - e, home) @ R0.T)
            J[:, i] = (plus - minus) / (2 * step)
        return J

    def aim(self, point_home: np.ndarray, roll: float = 0.0, rounds: int = 4
            ) -> tuple[float, float]:
        """Pan and tilt (rad) that put ``point_home`` (m, in the frame of the camera at
        home) on the optical axis, at ``roll``: the closed form for ``N = I`` and no
        offset, then Newton steps on the camera's x and y of the point."""
        p = np.asarray(point_home, float)
        if p[2] <= 0 and math.hypot(p[0], p[1]) < 1e-9:
            raise SolveError(f"head aim: point {p.tolist()} is not in front of the camera")
        g = self.orientation(HOME) @ p
        g = g / np.linalg.norm(g)
        angles = np.array([math.atan2(g[0], g[2]), -math.asin(np.clip(g[1], -1, 1))])

        def off_axis(a: np.ndarray) -> np.ndarray:
            T = self.T_home_cam((a[0], a[1], roll))
            q = T[:3, :3].T @ (p - T[:3, 3])
            return q[:2] / q[2]

        for _ in range(rounds):
            f = off_axis(angles)
            J = np.empty((2, 2))
            for i in range(2):
                e = np.zeros(2)
                e[i] = 1e-6
                J[:, i] = (off_axis(angles + e) - off_axis(angles - e)) / 2e-6
            angles = angles - np.linalg.solve(J, f)
        return float(angles[0]), float(angles[1])

    def as_dict(self, names: list[str] | None = None) -> dict[str, Any]:
        """The ``head_geometry`` entry of an active-camera result."""
        return {
            "model": "C(a) = Ry(pan) Rx(tilt) N R_u(roll), u = Rx(t0) Ry(t1) e_z; "
                     "T_home_cam(a) = [R | (R - I) o], R = C(0)^T C(a)",
            "mount_rotvec": self.mount_rotvec.tolist(),
            "roll_axis_tilts_rad": self.roll_tilts.tolist(),
            "roll_axis_in_cam": self.roll_axis.tolist(),
            "centre_offset_m": self.offset_m.tolist(),
            "centre_offset_estimated": self.offset_estimated,
            "centre_offset_sigma_m": self.offset_sigma_m.tolist(),
            "rotation_names": list(ROTATION_NAMES),
            "rotation_covariance": self.rotation_covariance.tolist(),
            "units": {"angle": "rad", "length": "m"},
        }


def from_refinement(x: np.ndarray, names: list[str], cov: np.ndarray, offset_m: np.ndarray,
                    offset_sigma_m: np.ndarray, offset_estimated: bool) -> HeadGeometry:
    """The head geometry an active-camera refinement ended with: its parameter vector
    ``x`` (``active_refine.PARAM_NAMES`` order: x[4:7] the mounting, x[7:9] the roll
    axis's tilts) and the covariance over ``names``."""
    idx = [names.index(n) for n in ROTATION_NAMES]
    return HeadGeometry(mount_rotvec=np.array(x[4:7], float), roll_tilts=np.array(x[7:9], float),
                        offset_m=np.asarray(offset_m, float), offset_estimated=offset_estimated,
                        offset_sigma_m=np.asarray(offset_sigma_m, float),
                        rotation_covariance=np.asarray(cov, float)[np.ix_(idx, idx)])


def from_result(result: dict, where: str = "active-camera result") -> HeadGeometry:
    """The head geometry recorded in an active-camera result (``head_geometry``); a
    ``SolveError`` naming ``where`` when it has none (a result from before it was
    recorded: run active-camera again)."""
    entry = result.get("head_geometry")
    if not isinstance(entry, dict):
        raise SolveError(f"{where}: no head_geometry (a result recorded before the head's "
                         "geometry was: run active-camera again)")
    try:
        return HeadGeometry(
            mount_rotvec=np.array(entry["mount_rotvec"], float).reshape(3),
            roll_tilts=np.array(entry["roll_axis_tilts_rad"], float).reshape(2),
            offset_m=np.array(entry["centre_offset_m"], float).reshape(3),
            offset_estimated=bool(entry["centre_offset_estimated"]),
            offset_sigma_m=np.array(entry["centre_offset_sigma_m"], float).reshape(3),
            rotation_covariance=np.array(entry["rotation_covariance"], float).reshape(5, 5))
    except (KeyError, TypeError, ValueError) as exc:
        raise SolveError(f"{where}: head_geometry is malformed ({exc})") from exc
