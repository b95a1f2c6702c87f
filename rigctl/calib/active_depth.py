"""Scene depth for the active-camera parallax, from one sideways move of the arm.

Beyond the thesis, which assumes the centre of projection on the head's rotation axes.
With the centre at ``o`` (camera frame) off the axes, a contour at inverse depth ``rho``
moves under a head rotation as if seen along ``x + rho o`` (``active_refine``). With one
``rho`` for the whole scene, ``o`` is not separable from the focal length (pan/tilt) and
the principal point (rolls); with each contour's own ``rho`` measured, and contours at
different depths, it is. The arm supplies the depths: it moves the camera sideways by a
known distance ``b`` without turning it (the head at home), and each contour shifts by
its disparity (thesis eq. 3.3 with a translation instead of a rotation)::

    x' = (x - rho t_xy) / (1 - rho t_z),   |t| = b

``t`` (the move in the camera frame: its direction depends on the unknown hand-eye
rotation) and every ``rho`` are fitted to the contours' shifts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from rigctl.calib.active_refine import DepthPrior
from rigctl.errors import SolveError

MIN_CONTOURS = 3
# prior sigma of an unmeasured contour's inverse depth, in units of the nearest measured
UNMEASURED_SPAN = 3.0
# a contour's shift fit this many times worse than the median, and worse than the floor
# (px), did not move as one piece
NONRIGID_RATIO = 3.0
NONRIGID_FLOOR_PX = 0.3
# How far a measured inverse depth may be off beyond what the fit's residual tells
# (relative, per contour), and how far all of them together (the move's length, set by
# the nominal arm: the true move was 9.88-9.99 mm of a planned 10 on random worlds).
# Random worlds 130000-130019, each contour against the depth of the shape it traces
# (``bench.truth.contour_inverse_depths``): median error 1 %, largest 9 %, while the
# fit's residual alone claimed a median of 0.6 %. Held as exact in the refinement, the
# centre of projection's offset claimed a sigma of a few micrometres on far scenes
# (error / sigma up to 8 on random worlds 120000-140059).
DEPTH_CONTOUR_SIGMA = 0.015
DEPTH_SCALE_SIGMA = 0.01


def camera_shift_joints(model, q_home, T_flange_cam: np.ndarray, distance_m: float,
                        axis: int = 0) -> np.ndarray:
    """Joints that move the camera ``distance_m`` along its own (nominal) x axis (or
    ``axis``: 2 along its optical axis) with the flange's orientation unchanged (nominal
    model and IK; ``SolveError`` if out of reach). Between two nearby configurations the
    model's errors barely turn the flange, so the true move is a translation of nearly
    ``distance_m``."""
    T = np.array(model.fk(q_home), float)
    direction = (T @ T_flange_cam)[:3, axis]
    target = T.copy()
    target[:3, 3] += distance_m * direction
    return np.asarray(model.ik(target, list(q_home)), float)


def contour_shift(ref_points: np.ndarray, moved_points: np.ndarray,
                  moved_normals: np.ndarray, start, iterations: int = 8
                  ) -> tuple[np.ndarray, float]:
    """The 2-D shift (px) that lays a reference contour onto its tracked edge points:
    Gauss-Newton on the point-to-curve distances along the moved edges' normals,
    from the tracker's ``start`` offset; points beyond 3 robust sigmas are dropped.
    Returns the shift and the RMS (px) of the kept points' distances: a contour that
    does not move as one rigid piece (two shapes at different depths traced as one, or
    one partly hidden) leaves far more than the others."""
    tree = cKDTree(moved_points)
    d = np.asarray(start, float).copy()
    for _ in range(iterations):
        _, idx = tree.query(ref_points + d)
        n = moved_normals[idx]
        r = np.sum((ref_points + d - moved_points[idx]) * n, axis=1)
        keep = np.abs(r) <= 3 * 1.4826 * np.median(np.abs(r)) + 1e-6
        step, *_ = np.linalg.lstsq(n[keep], -r[keep], rcond=None)
        d += step
        if np.hypot(*step) < 1e-4:
            break
    return d, float(np.sqrt(np.mean(r[keep] ** 2)))


def rigid_shifts(rms_px: np.ndarray) -> np.ndarray:
    """Which contours moved as one piece under the arm's move: all but those whose shift
    RMS (``contour_shift``) exceeds both ``NONRIGID_RATIO`` times the contours' median and
    ``NONRIGID_FLOOR_PX``. Those depths are left unmeasured (free in the refinement):
    random world 14003's contour traced over two shapes fitted 1.3 px RMS against the
    others' 0.05-0.13 px and its depth came out 12 % off."""
    rms_px = np.asarray(rms_px, float)
    if not len(rms_px):
        return np.zeros(0, bool)
    return rms_px <= max(NONRIGID_RATIO * float(np.median(rms_px)), NONRIGID_FLOOR_PX)


@dataclass
class SceneDepths:
    """Each contour's inverse depth (1/m; NaN where not measured) and the fitted move."""

    inv_depth: np.ndarray
    t_cam: np.ndarray          # the camera's move in its own frame (m)
    rms_normalised: float      # fit residual (normalised image units)

    def filled(self) -> np.ndarray:
        """Inverse depths with the unmeasured contours at the median."""
        out = self.inv_depth.copy()
        out[~np.isfinite(out)] = float(np.nanmedian(self.inv_depth))
        return out

    def prior(self) -> DepthPrior:
        """The inverse depths for the refinement: a measured one held (freeing them lets
        the offset trade against the centre where the depths are alike); an unmeasured
        one (a contour lost in the move, e.g. on a periodic board) free, anywhere from the
        farthest to a few times nearer than the nearest measured, for the rotations to
        pin down."""
        measured = np.isfinite(self.inv_depth)
        sigma = np.zeros(len(self.inv_depth))
        sigma[~measured] = max(UNMEASURED_SPAN * float(np.max(self.inv_depth[measured])), 1.0)
        return DepthPrior(self.filled(), sigma, self.measurement_sigma(), DEPTH_SCALE_SIGMA)

    def measurement_sigma(self) -> np.ndarray:
        """Each measured inverse depth's sigma (1/m; 0 where not measured): the fit's
        residual over the move's length, with ``DEPTH_CONTOUR_SIGMA`` of the depth, in
        quadrature."""
        fit = self.rms_normalised / max(float(np.linalg.norm(self.t_cam)), 1e-12)
        out = np.hypot(fit, DEPTH_CONTOUR_SIGMA * np.nan_to_num(self.inv_depth))
        return np.where(np.isfinite(self.inv_depth), out, 0.0)

    def as_dict(self) -> dict:
        finite = self.inv_depth[np.isfinite(self.inv_depth)]
        return {"contours_measured": len(finite),
                "depth_m": {"min": float(1 / finite.max()), "median": float(1 / np.median(finite)),
                            "max": float(1 / finite.min())},
                "move_in_camera_mm": (1000 * self.t_cam).tolist(),
                "fit_rms_px_at_f1000": 1000 * self.rms_normalised}


def camera_move(angles, baseline_m: float) -> np.ndarray:
    """The camera's move in its own frame: length ``baseline_m``, direction at azimuth
    ``angles[0]`` and elevation ``angles[1]`` (rad)."""
    a, e = angles
    return baseline_m * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def shift_residuals(p: np.ndarray, centres: np.ndarray, shifts: np.ndarray,
                    baseline_m: float) -> np.ndarray:
    """Predicted minus measured shifts (module docstring: ``x' = (x - rho t_xy) / (1 -
    rho t_z)``, thesis eq. 3.3 with a translation), x then y of each contour; ``p``: the
    move's two angles (``camera_move``), then each contour's inverse depth."""
    t = camera_move(p[:2], baseline_m)
    rho = p[2:]
    predicted = (centres - rho[:, None] * t[:2]) / (1 - rho[:, None] * t[2]) - centres
    return (predicted - shifts).ravel()


def shift_jacobian(p: np.ndarray, centres: np.ndarray, baseline_m: float) -> np.ndarray:
    """d ``shift_residuals`` / d ``p`` in closed form: a contour's two rows depend on the
    move's angles and its own inverse depth only. With the finite differences scipy
    takes otherwise, the fit at its tolerance of 1e-12 crept: random world 120011 (14
    contours) ended at scipy's cap of 1,600 evaluations, 1.4 s a fit, and its depths were
    thrown away; with this it converges in 462 (0.1 s)."""
    a, e = p[:2]
    t = camera_move(p[:2], baseline_m)
    rho = p[2:]
    n = len(rho)
    D = 1 - rho * t[2]
    P = (centres - rho[:, None] * t[:2]) / D[:, None]  # the moved point
    # d P / d t_xy = -rho / D (per axis); d P / d t_z = P rho / D
    dt_da = baseline_m * np.array([-np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), 0.0])
    dt_de = baseline_m * np.array([-np.sin(e) * np.cos(a), -np.sin(e) * np.sin(a), np.cos(e)])
    J = np.zeros((2 * n, 2 + n))
    for column, dt in enumerate((dt_da, dt_de)):
        J[:, column] = (-(rho / D)[:, None] * dt[:2] + P * (rho / D)[:, None] * dt[2]).ravel()
    d_rho = (P * t[2] - t[:2]) / D[:, None]
    rows = 2 * np.arange(n)
    J[rows, 2 + np.arange(n)] = d_rho[:, 0]
    J[rows + 1, 2 + np.arange(n)] = d_rho[:, 1]
    return J


def fit_depths(centres: np.ndarray, shifts: np.ndarray, baseline_m: float,
               n_contours: int, ids: np.ndarray) -> SceneDepths:
    """Inverse depths of contours ``ids`` from their shifts under a camera move of
    length ``baseline_m``: ``centres`` and ``shifts`` in normalised, undistorted image
    coordinates (the model in the module docstring, one ``rho`` per contour and the
    move's direction shared)."""
    if len(ids) < MIN_CONTOURS:
        raise SolveError(f"scene depth: {len(ids)} contours followed through the arm's "
                         f"move (need {MIN_CONTOURS})")
    mean_dir = -np.median(shifts, axis=0)
    mean_dir /= np.linalg.norm(mean_dir) + 1e-12
    rho0 = np.linalg.norm(shifts, axis=1) / baseline_m

    def residuals(p):
        return shift_residuals(p, centres, shifts, baseline_m)

    def jacobian(p):
        return shift_jacobian(p, centres, baseline_m)

    start = np.r_[np.arctan2(mean_dir[1], mean_dir[0]), 0.0, rho0]
    fit = least_squares(residuals, start, jac=jacobian, loss="soft_l1", f_scale=1e-3,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    behind = fit.x[2:] <= 0
    if fit.success and behind.any() and (~behind).sum() >= MIN_CONTOURS:
        # a contour that moved against the others was followed to the wrong edge: fit
        # again without it
        keep = ~behind
        return fit_depths(centres[keep], shifts[keep], baseline_m, n_contours, ids[keep])
    if not fit.success or behind.any():
        raise SolveError("scene depth: the contours' shifts under the arm's move do not fit "
                         "one camera translation (a contour moved against the others)")
    inv_depth = np.full(n_contours, np.nan)
    inv_depth[ids] = fit.x[2:]
    rms = float(np.sqrt(np.mean(residuals(fit.x) ** 2)))
    return SceneDepths(inv_depth, camera_move(fit.x[:2], baseline_m), rms)
