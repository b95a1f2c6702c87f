"""Robot kinematic calibration with an eye-in-hand camera (thesis 4.3), generalised.

Measurement model: the target is fixed, so for every capture k with joints q_k

    W = T_base_target = FK(q_k) X C_k,   X = T_flange_cam,  C_k = T_cam_target

With the camera standing beside the arm and the board on the flange (eye-to-hand,
``Measurements.fixed``) the same loop closes the other way round:
``C_k = X^-1 FK(q_k) W`` with ``X = T_base_cam`` and ``W = T_flange_target``
(``cam_target_batch``); the joint refinement, its covariance and the held-out errors
take either, link-by-link only the first.

**Link-by-link (4.11)-(4.35), for n links.** Moving joint i alone between captures 0
and 1 gives (4.12)/(4.30)

    A_i(theta_1)^-1 A_i(theta_0) = S C_1 C_0^-1 S^-1,   S = A_{i+1} ... A_n X

whose left side is a rotation about joint i's axis expressed in frame i: direction
``Ry(-beta) Rx(-alpha) z``, through ``(-a, 0, 0)`` (for DH, the line meets the x axis at a
right angle, at x = -a). ``S`` is known from the links calibrated before (n first),
except the offset and d of link i+1: ``A_{i+1} = Rz(theta_off) Tz(d) [...]``. Requiring the
measured axis to have that form fixes theta_off_{i+1} and d_{i+1} (so an encoder offset
becomes observable one step later in the chain, erratum 11) and then gives a_i, alpha_i
(4.27)-(4.28) with the quadrant of (4.28) from atan2 (erratum 10). For (nearly) parallel
consecutive axes (alpha_i = 0) d_{i+1} is unobservable and Hayati's beta_i replaces it
(erratum 12). The base link's offset and d_1 follow from (4.35) when ``W`` is known.

**Joint refinement.** Least squares over every capture of an identifiable parameter set
(``identifiable_mask``): redundant parameters are absorbed into ``X`` and ``W``; parameter
estimates come with 1-sigma (cluster-robust over board views: a view's corners share
its detection bias and the arm's pose, so they are not independent; the delete-one-view
jackknife, ``covariance.robust_covariance``), the condition
number of the scaled identification Jacobian, and errors on held-out captures.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq, least_squares

from rigctl.calib import robot_jacobian, robot_stations
from rigctl.calib.covariance import robust_covariance, view_clusters
from rigctl.errors import SolveError
from rigctl.geometry.camera import camera_matrix, invert_batch, project_batch
from rigctl.geometry.kinematics import LINK_KEYS, KinematicModel, link_transform
from rigctl.geometry.transforms import R_to_rotvec, inv_T, make_T, rotvec_to_R

PARALLEL_ALPHA = math.radians(5.0)


def cam_target_batch(model: KinematicModel, X, W, Q: np.ndarray, fixed: bool = False
                     ) -> np.ndarray:
    """``T_cam_target`` predicted at each configuration of ``Q`` (P, 6): with the camera on
    the flange ``(FK(q) X)^-1 W`` (X = T_flange_cam, W = T_base_target); with the camera
    standing beside the arm (``fixed``, eye-to-hand) ``X^-1 FK(q) W`` (X = T_base_cam,
    W = T_flange_target). The same loop (4.11) closed through the other end."""
    F = model.fk_batch(np.asarray(Q, float))
    if fixed:
        return inv_T(X) @ F @ W
    return invert_batch(F @ X) @ W


def target_cam(model: KinematicModel, X, W, q, fixed: bool = False) -> np.ndarray:
    """The camera's pose in the target frame at joints ``q`` (the inverse of
    ``cam_target_batch``'s), for either mounting."""
    if fixed:
        return inv_T(W) @ inv_T(model.fk(q)) @ X
    return inv_T(W) @ model.fk(q) @ X


def screw_axis(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Axis of a rigid motion: unit direction u, the axis point closest to the origin,
    and the rotation angle (rad, about u, right-handed)."""
    rv = R_to_rotvec(M[:3, :3])
    angle = float(np.linalg.norm(rv))
    if angle < math.radians(0.5):
        raise SolveError(f"robot: a joint motion of {math.degrees(angle):.2f} deg is too "
                         "small to locate its axis")
    u = rv / angle
    t = M[:3, 3]
    # points p on the axis satisfy (I - R) p = t - (u.t) u ; least squares, min norm
    A = np.eye(3) - M[:3, :3]
    p, *_ = np.linalg.lstsq(A, t - (u @ t) * u, rcond=None)
    p = p - (p @ u) * u
    return u, p, angle


def average_axis(axes: list[tuple[np.ndarray, np.ndarray, float]]):
    """Mean line of several measurements of one axis (weights: rotation angle)."""
    us, ps, ws = [], [], []
    for u, p, angle in axes:
        us.append(u)
        ps.append(p)
        ws.append(angle)
    w = np.array(ws) / np.sum(ws)
    u = np.sum(np.array(us) * w[:, None], axis=0)
    u /= np.linalg.norm(u)
    # point: least-squares closest point to all lines, then made perpendicular to u
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for ui, pi, wi in zip(us, ps, w, strict=True):
        P = np.eye(3) - np.outer(ui, ui)
        A += wi * P
        b += wi * P @ pi
    A += 1e-9 * np.eye(3)
    p = np.linalg.solve(A, b)
    return u, p - (p @ u) * u


@dataclass
class Sweep:
    """Captures of one joint moving alone (0-based ``joint``): joints and camera poses."""

    joint: int
    q: list[np.ndarray]
    C: list[np.ndarray]  # T_cam_target


def _motions(sweep: Sweep, S: np.ndarray, min_angle: float = math.radians(5.0)):
    """Screw axes (in the frame after the moving link) of every pair of captures whose
    joint angles differ by at least ``min_angle``; the largest differences first."""
    Sinv = inv_T(S)
    pairs = []
    k = len(sweep.q)
    for a in range(k):
        for b in range(a + 1, k):
            dq = sweep.q[b][sweep.joint] - sweep.q[a][sweep.joint]
            if abs(dq) >= min_angle:
                pairs.append((abs(dq), a, b))
    if not pairs:
        raise SolveError(f"robot: joint {sweep.joint + 1} moved less than "
                         f"{math.degrees(min_angle):.0f} deg in its sweep")
    pairs.sort(reverse=True)
    out = []
    for _, a, b in pairs:
        M = S @ sweep.C[b] @ inv_T(sweep.C[a]) @ Sinv  # A_i(q_b)^-1 A_i(q_a), (4.12)
        u, p, angle = screw_axis(M)
        # M rotates by q_a - q_b about the joint axis: orient u along the axis's +z
        if sweep.q[b][sweep.joint] > sweep.q[a][sweep.joint]:
            u = -u
        out.append((u, p, angle))
    return out


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclass
class LinkByLink:
    model: KinematicModel
    identified: dict[str, list[str]] = field(default_factory=dict)  # link -> parameters
    notes: list[str] = field(default_factory=list)


def link_by_link(sweeps: dict[int, Sweep], X: np.ndarray, nominal: KinematicModel,
                 W: np.ndarray | None = None) -> LinkByLink:
    """The thesis's incremental calibration, last joint first (algorithm 4.3.2), with
    ``X = T_flange_cam`` known. Returns the model with every parameter the sweeps can
    determine; the others keep their nominal values (listed in ``notes``)."""
    model = nominal.copy()
    n = model.n
    identified: dict[str, list[str]] = {f"link{i + 1}": [] for i in range(n)}
    notes: list[str] = []
    missing = [i + 1 for i in range(n) if i not in sweeps]
    if missing:
        raise SolveError(f"link-by-link: no sweep for joint(s) {missing}")
    for i in range(n - 1, -1, -1):
        sweep = sweeps[i]
        qbar = sweep.q[0]
        # S0 = [Rz(q) Tx(a) Rx(alpha) Ry(beta)]_{i+1} A_{i+2} ... A_n X, without link i+1's
        # unknown offset and d (they form G = Rz(theta_off) Tz(d), solved below).
        S0 = X.copy()
        for j in range(n - 1, i + 1, -1):
            S0 = model.link(j, qbar[j]) @ S0
        if i + 1 < n:
            j = i + 1
            S0 = link_transform(qbar[j], 0.0, model.a[j], model.alpha[j], model.beta[j]) @ S0
        u0, p0 = average_axis(_motions(sweep, S0))
        parallel = abs(_wrap(nominal.alpha[i])) < PARALLEL_ALPHA or \
            abs(abs(_wrap(nominal.alpha[i])) - math.pi) < PARALLEL_ALPHA
        if i + 1 < n:
            if not parallel:
                # rotate about z so the axis direction has no x component (two branches:
                # take the offset nearest zero)
                base = math.atan2(u0[0], u0[1])
                off = min((_wrap(base), _wrap(base + math.pi)), key=abs)
            else:
                # the axis is ~parallel to z: rotate so it crosses the plane z = 0 on the
                # x axis (the line lies in the x-z plane)
                t = -p0[2] / u0[2]
                q0 = p0 + t * u0
                base = -math.atan2(q0[1], q0[0])
                off = min((_wrap(base), _wrap(base + math.pi)),
                          key=lambda v: abs(_wrap(v - nominal.theta_offset[i + 1])))
            Rz = np.array([[math.cos(off), -math.sin(off), 0], [math.sin(off), math.cos(off), 0],
                           [0, 0, 1.0]])
            u, p = Rz @ u0, Rz @ p0
            model.theta_offset[i + 1] = off
            identified[f"link{i + 2}"].append("theta_offset")
        else:
            u, p = u0, p0
        if not parallel:
            if abs(u[1]) < 1e-9:
                raise SolveError(f"link-by-link: joint {i + 1} axis is parallel to the next")
            t = -p[1] / u[1]
            d_next = -(p[2] + t * u[2])
            a_i = -(p[0] + t * u[0])
            alpha_i = math.atan2(u[1], u[2])
            if i + 1 < n:
                model.d[i + 1] = d_next
                identified[f"link{i + 2}"].append("d")
            model.a[i], model.alpha[i], model.beta[i] = a_i, alpha_i, 0.0
            identified[f"link{i + 1}"] += ["a", "alpha"]
        else:
            # direction (-sin b cos al, sin al, cos b cos al), line through x = -a/cos b
            beta = math.atan2(-u[0], u[2])
            alpha_i = math.atan2(u[1], math.hypot(u[0], u[2]))
            t = -p[2] / u[2]
            x_cross = p[0] + t * u[0]
            model.a[i] = -x_cross * math.cos(beta)
            model.alpha[i], model.beta[i] = alpha_i, beta
            identified[f"link{i + 1}"] += ["a", "alpha", "beta"]
            if i + 1 < n:
                notes.append(f"link{i + 2}.d: unobservable from joint {i + 1}'s sweep "
                             f"(axes {i} and {i + 1} parallel); kept at {model.d[i + 1]:.4f}")
    if W is not None:
        _base_from_target(sweeps[0], X, W, model)
        identified["link1"] += ["theta_offset", "d"]
    else:
        notes.append("link1.theta_offset, link1.d: absorbed into T_base_target (W unknown)")
    return LinkByLink(model, identified, notes)


def _base_from_target(sweep: Sweep, X, W, model: KinematicModel) -> None:
    """Eq. (4.35): with W known, link 1's offset and d_1 from ``W = A_1 ... A_n X C``."""

    def residual(p):
        model.theta_offset[0], model.d[0] = p
        out = []
        for q, C in zip(sweep.q, sweep.C, strict=True):
            E = inv_T(W) @ model.fk(q) @ X @ C
            out.append(np.r_[R_to_rotvec(E[:3, :3]), E[:3, 3]])
        return np.concatenate(out)

    sol = least_squares(residual, [model.theta_offset[0], model.d[0]])
    model.theta_offset[0], model.d[0] = sol.x


# a sweep moves one joint; the others may differ by encoder jitter (measured joint angles)
OTHER_JOINTS_TOL = 1e-3  # rad


def axis_lines(sweeps: dict[int, Sweep]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each swept joint's axis line in the target frame, from the camera poses alone:
    joint j -> (the sweep's base configuration ``sweep.q[0]``, unit direction, closest
    point to the origin). Beyond the thesis, whose (4.12) needs X: with
    ``T_target_cam = C^-1``, the motion ``C_b^-1 C_a`` rotates about joint j's axis, fixed
    in the target frame while only joint j moves, by ``q_b - q_a``; X never enters. The
    line depends only on joints 1..j-1, so each sweep may start from its own
    configuration (the others may be set to keep the board in view longest)."""
    lines = {}
    for j, sweep in sweeps.items():
        q_base = np.asarray(sweep.q[0], float)
        moved = [k for k, q in enumerate(sweep.q)
                 if np.any(np.abs(np.delete(np.asarray(q) - q_base, j)) > OTHER_JOINTS_TOL)]
        if moved:
            raise SolveError(f"axis lines: joint {j + 1}'s sweep moves other joints "
                             f"(capture {moved[0] + 1})")
        axes = []
        for a in range(len(sweep.q)):
            for b in range(a + 1, len(sweep.q)):
                dq = sweep.q[b][j] - sweep.q[a][j]
                if abs(dq) < math.radians(5.0):
                    continue
                u, p, angle = screw_axis(inv_T(sweep.C[b]) @ sweep.C[a])
                axes.append((u if dq > 0 else -u, p, angle))
        if not axes:
            raise SolveError(f"axis lines: joint {j + 1} moved less than 5 deg in its sweep")
        lines[j] = (q_base, *average_axis(axes))
    return lines


def axis_based(sweeps: dict[int, Sweep], nominal: KinematicModel, W0: np.ndarray
               ) -> tuple[KinematicModel, np.ndarray]:
    """Link parameters and ``W = T_base_target`` fitted to the measured axis lines
    (``axis_lines``): the minimal set of ``identifiable_mask`` for links 1..n-1 (the last
    link only moves the flange, so it and X stay for the hand-eye step). Six lines give
    24 constraints for 18 link parameters and W's 6: exactly determined, with no X."""
    if sorted(sweeps) != list(range(nominal.n)):
        raise SolveError(f"axis-based calibration needs a sweep of every joint; have "
                         f"{[j + 1 for j in sorted(sweeps)]}")
    lines = axis_lines(sweeps)
    mask = identifiable_mask(nominal)
    p_full, _ = _pack(nominal, np.eye(4), W0, mask, True)
    n_links = len(p_full) - 12

    def unpack(p):
        model, _, W = _unpack(np.r_[p[:n_links], np.zeros(6), p[n_links:]], nominal,
                              np.eye(4), W0, mask, True)
        return model, W

    def fun(p):
        model, W = unpack(p)
        Winv = inv_T(W)
        out = []
        for j, (q_base, u, point) in lines.items():
            T = Winv @ model.frames(q_base)[j]  # joint j turns about this frame's z
            u_pred = T[:3, 2]
            off = point - T[:3, 3]
            out.append(np.r_[u_pred - u, (off - (off @ u_pred) * u_pred) / 0.1])
        return np.concatenate(out)  # 1 mrad of direction weighs as 0.1 mm of position

    sol = least_squares(fun, np.r_[p_full[:n_links], p_full[n_links + 6:]], x_scale="jac")
    return unpack(sol.x)


# -- joint refinement -------------------------------------------------------------------


def identifiable_mask(nominal: KinematicModel, absorb: bool = True) -> dict[str, np.ndarray]:
    """Which link parameters are estimated. With ``absorb`` (X and W unknown): link 1's
    offset and d go into W, the last link's parameters into X; Hayati's beta replaces d
    for (nearly) parallel consecutive axes. Without ``absorb`` (X, W known), all but d or
    beta by that rule."""
    n = nominal.n
    mask = {k: np.ones(n, bool) for k in LINK_KEYS}
    for i in range(n):
        parallel = abs(_wrap(nominal.alpha[i])) < PARALLEL_ALPHA or \
            abs(abs(_wrap(nominal.alpha[i])) - math.pi) < PARALLEL_ALPHA
        mask["beta"][i] = parallel
        mask["d"][i] = not parallel
    if absorb:
        mask["theta_offset"][0] = mask["d"][0] = False
        for k in LINK_KEYS:
            mask[k][n - 1] = False
    return mask


def dh_mask(nominal: KinematicModel, absorb: bool = True) -> dict[str, np.ndarray]:
    """Plain D-H (no beta): d everywhere, to show the rank deficiency of parallel axes."""
    mask = identifiable_mask(nominal, absorb)
    n = nominal.n
    mask["beta"] = np.zeros(n, bool)
    mask["d"] = np.ones(n, bool)
    if absorb:
        mask["d"][0] = False
        mask["d"][n - 1] = False
    return mask


@dataclass
class Measurements:
    """Captures for the refinement: joints, and either camera poses (with sigmas) or board
    corners (pixels) with the board points, K and distortion."""

    q: list[np.ndarray]
    C: list[np.ndarray] | None = None
    corners: list[np.ndarray] | None = None
    obj: np.ndarray | None = None
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    sigma_rot: float = 0.001
    sigma_t: float = 0.001
    # the camera stands beside the arm (eye-to-hand): X = T_base_cam, W = T_flange_target
    fixed: bool = False
    # with ``fixed``, the head re-aimed between views (``robot_stations``): each view's
    # station and each station's predicted pose from home with its prior; None: all home
    stations: robot_stations.Stations | None = None

    @property
    def station_count(self) -> int:
        return 0 if self.stations is None else self.stations.count


@dataclass
class RefineResult:
    model: KinematicModel
    X: np.ndarray
    W: np.ndarray
    names: list[str]
    values: np.ndarray
    sigma: np.ndarray
    condition: float
    singular_values: np.ndarray
    rms: float
    condition_kinematic: float = float("nan")  # link parameters only, X and W projected out
    covariance: np.ndarray | None = None  # of every refined parameter (camera too, if free)
    # the head's stations after the first (``robot_stations``): each one's refined pose
    # from home; their parameters follow X and W in ``names``
    stations: list[np.ndarray] = field(default_factory=list)


def _pack(model, X, W, mask, free_XW):
    vals, names = [], []
    for k in LINK_KEYS:
        for i in np.flatnonzero(mask[k]):
            vals.append(getattr(model, k)[i])
            names.append(f"link{i + 1}.{k}")
    if free_XW:
        vals += list(np.r_[R_to_rotvec(X[:3, :3]), X[:3, 3], R_to_rotvec(W[:3, :3]), W[:3, 3]])
        names += [f"X.{c}" for c in ("rx", "ry", "rz", "x", "y", "z")]
        names += [f"W.{c}" for c in ("rx", "ry", "rz", "x", "y", "z")]
    return np.array(vals, float), names


def _unpack(p, model0, X0, W0, mask, free_XW):
    model = model0.copy()
    k0 = 0
    for k in LINK_KEYS:
        idx = np.flatnonzero(mask[k])
        getattr(model, k)[idx] = p[k0:k0 + len(idx)]
        k0 += len(idx)
    if free_XW:
        X = make_T(rotvec_to_R(p[k0:k0 + 3]), p[k0 + 3:k0 + 6])
        W = make_T(rotvec_to_R(p[k0 + 6:k0 + 9]), p[k0 + 9:k0 + 12])
    else:
        X, W = X0, W0
    return model, X, W


def residuals(model, X, W, meas: Measurements, K: np.ndarray | None = None,
              dist: np.ndarray | None = None, stations: list[np.ndarray] | None = None
              ) -> np.ndarray:
    """Pose residuals (scaled by the sigmas) or pixel residuals for every capture. A pose
    residual is ``log(C_k W^-1 FK(q_k) X)``: measured times predicted-inverse, in the
    camera frame, where a camera's pose error lives (the loop of (4.11) closed at the
    camera). Taken in the target frame instead, a rotation error would leak into
    translation times the camera-to-target distance and the sigmas would weight it
    wrongly. A view taken with the head re-aimed (``meas.stations``) is seen from its
    station, ``D_s^-1`` times the home camera's (``stations``: each station's pose, by
    default as predicted)."""
    from scipy.spatial.transform import Rotation

    Q = _cached(meas, "_Q", lambda: np.array(meas.q, float))
    T_cam_target = cam_target_batch(model, X, W, Q, meas.fixed)
    if meas.stations is not None and meas.stations.count:
        T_cam_target = robot_stations.view_inverses(
            meas.stations, meas.stations.predicted if stations is None else stations) \
            @ T_cam_target
    if meas.corners is None:  # pose residuals, every capture at once
        E = _cached(meas, "_C", lambda: np.array(meas.C)) @ invert_batch(T_cam_target)
        rv = Rotation.from_matrix(E[:, :3, :3]).as_rotvec()
        return np.c_[rv / meas.sigma_rot, E[:, :3, 3] / meas.sigma_t].ravel()
    corners = _cached(meas, "_corners",
                      lambda: np.array([np.asarray(c, float).reshape(-1, 2) for c in meas.corners]))
    proj = project_batch(T_cam_target, meas.obj,
                         meas.K if K is None else K, meas.dist if dist is None else dist)
    seen = _seen(meas)
    if seen is None:  # every view has every corner
        return (proj - corners).ravel()
    return (proj - corners)[seen].ravel()  # view by view, the corners each view has


def _seen(meas: Measurements) -> np.ndarray | None:
    """Which corners each view has (views x corners; NaN rows of the id-ordered corner
    arrays are corners not seen), or None when every view has all of them."""
    def build():
        ok = np.array([np.all(np.isfinite(np.reshape(c, (-1, 2))), axis=1)
                       for c in meas.corners])
        return None if ok.all() else ok
    return _cached(meas, "_seen_mask", build)


def rows_per_view(meas: Measurements) -> list[int]:
    """How many residual rows ``residuals`` gives each view: 6 (a pose), or 2 per corner
    the view has."""
    if meas.corners is None:
        return [6] * len(meas.q)
    seen = _seen(meas)
    if seen is None:
        return [2 * len(np.reshape(meas.corners[0], (-1, 2)))] * len(meas.q)
    return (2 * seen.sum(axis=1)).tolist()


def _cached(meas, name: str, build):
    """Arrays built once per measurement set (the residuals run thousands of times)."""
    if not hasattr(meas, name):
        setattr(meas, name, build())
    return getattr(meas, name)


def refine(model0: KinematicModel, X0, W0, meas: Measurements, mask=None,
           free_XW: bool = True, robust: bool = True, max_nfev: int = 60,
           extra_starts: Sequence[tuple[KinematicModel, np.ndarray, np.ndarray]] = ()
           ) -> RefineResult:
    """Least squares of the masked link parameters (and X, W) over every capture.
    ``max_nfev`` bounds the iterations: a well-posed set converges in about ten, and a
    rank-deficient one (plain D-H on parallel joints) would otherwise run on.
    ``extra_starts`` (model, X, W) are solved from as well and the lowest cost wins
    (the first of equals, ``first_of_least``): a
    link-by-link start that noisy sweeps threw degrees off can fall into a local minimum
    that the nominal model's start avoids. With ``meas.stations`` (the head beside the
    arm re-aimed) each station's pose from home is refined too, from its prediction and
    with its prior (``robot_stations``); the prior's rows stay out of the view clusters
    and enter the covariance as prior information."""
    mask = mask or identifiable_mask(model0, absorb=free_XW)
    p0, names = _pack(model0, X0, W0, mask, free_XW)
    n_base = len(p0)
    stations = meas.stations if meas.station_count and free_XW else None
    if stations is not None:
        names = names + robot_stations.names(stations.count)
    n_params = n_base + (0 if stations is None else 6 * stations.count)
    if len(meas.q) * 6 < n_params:
        raise SolveError(f"robot refinement: {len(meas.q)} captures cannot determine "
                         f"{n_params} parameters")
    scale = robot_stations.PRIOR_PIXEL_SCALE if meas.corners is not None else 1.0

    def solve(base, X_base, W_base):
        def fun(p):
            model, X, W = _unpack(p[:n_base], base, X_base, W_base, mask, free_XW)
            if stations is None:
                return residuals(model, X, W, meas)
            D = robot_stations.unpack(p[n_base:])
            return np.r_[residuals(model, X, W, meas, stations=D),
                         robot_stations.prior_rows(stations, D, scale)]

        def jac(p):
            model, X, W = _unpack(p[:n_base], base, X_base, W_base, mask, free_XW)
            return _pixel_jacobian(p, n_base, model, X, W, mask, free_XW, meas, stations,
                                   scale)

        start = _pack(base, X_base, W_base, mask, free_XW)[0]
        if stations is not None:
            start = np.r_[start, robot_stations.pack(stations.predicted)]
        # pose residuals keep scipy's finite differences
        jacobian = jac if meas.corners is not None else "2-point"
        sol = least_squares(fun, start, jac=jacobian,
                            loss="soft_l1" if robust else "linear", f_scale=3.0,
                            x_scale="jac", max_nfev=max_nfev)
        sol = least_squares(fun, sol.x, jac=jacobian, loss="linear", x_scale="jac",
                            max_nfev=max_nfev // 2)
        return sol, _unpack(sol.x[:n_base], base, X_base, W_base, mask, free_XW)

    found = [solve(*start) for start in [(model0, X0, W0), *extra_starts]]
    sol, (model, X, W) = found[first_of_least({k: f[0].cost for k, f in enumerate(found)})]
    n_prior = 0 if stations is None else 6 * stations.count
    n_rows = len(sol.fun) - n_prior
    J, r = sol.jac[:n_rows], sol.fun[:n_rows]
    sv = scaled_singular_values(J)
    condition = condition_number(sv)
    P = np.zeros((len(sol.x), len(sol.x)))
    if n_prior:
        # the prior's information in the residuals' units (``robust_covariance``): its
        # rows were scaled for a pixel of ``scale``, the residuals have their own variance
        J_prior = sol.jac[n_rows:]
        s2 = float(np.sum(r ** 2) / max(n_rows - len(sol.x), 1))
        P = J_prior.T @ J_prior * (s2 / scale ** 2)
    cov = _view_robust(J, r, rows_per_view(meas), P)
    sigma = np.sqrt(np.clip(np.diag(cov), 0, None))
    result = RefineResult(model, X, W, names, sol.x, sigma, condition, sv,
                          float(np.sqrt(np.mean(r ** 2))),
                          _kinematic_condition(J, (12 if free_XW else 0) + n_prior), cov)
    if stations is not None:
        result.stations = robot_stations.unpack(sol.x[n_base:])
    return result


# refinements whose costs (or RMS) agree within this fraction ended in one minimum: the
# starts of random world 99400 ended within 1e-14 of each other, least_squares stops
# within its ftol (1e-8) of a minimum, and distinct minima differ by far more
SAME_END_RELATIVE = 1e-6


def first_of_least(costs: dict) -> object:
    """The first key (in ``costs``' order) whose cost is within ``SAME_END_RELATIVE`` of
    the least. Starts that end in one minimum differ only in the parameters the mask
    holds (absorbed into X and W, the same arm); the least cost alone would choose
    among them by rounding, and a re-solve could report another equivalent table."""
    least = min(costs.values())
    return next(key for key, cost in costs.items()
                if cost <= least + SAME_END_RELATIVE * abs(least))


def _pixel_jacobian(p: np.ndarray, n_base: int, model: KinematicModel, X, W, mask,
                    free_XW: bool, meas: Measurements, stations, scale: float,
                    K: np.ndarray | None = None, dist=None, camera: bool = False
                    ) -> np.ndarray:
    """The analytic Jacobian (``robot_jacobian``) of ``residuals`` with board corners by
    the packed parameters ``p`` (``_pack``'s, then each station's six when
    ``stations``, then with ``camera`` fx fy cx cy k1 k2 p1 p2 k3 at ``K``, ``dist``),
    followed by the stations' prior rows (``robot_stations.prior_rows`` times ``scale``;
    their columns by central differences of those rows alone)."""
    n_link = n_base - (12 if free_XW else 0)
    T, dT = robot_jacobian.pose_jacobian(
        model, X, W, _cached(meas, "_Q", lambda: np.array(meas.q, float)), mask, free_XW,
        meas.fixed, p[n_link:n_link + 3], p[n_link + 6:n_link + 9])
    n_station = 0 if stations is None else 6 * stations.count
    if stations is not None:
        q_station = p[n_base:n_base + n_station]
        D = robot_stations.unpack(q_station)
        T, dT = robot_jacobian.station_jacobian(
            T, dT, stations.index, D, [q_station[6 * s:6 * s + 3]
                                       for s in range(stations.count)])
    J = robot_jacobian.pixel_jacobian(T, dT, meas.obj, meas.K if K is None else K,
                                      meas.dist if dist is None else dist, _seen(meas),
                                      camera)
    if stations is None:
        return J
    prior = np.zeros((n_station, J.shape[1]))
    for j in range(n_station):
        h = 1e-6 * max(1.0, abs(q_station[j]))
        step = np.zeros(n_station)
        step[j] = h
        prior[:, n_base + j] = (
            robot_stations.prior_rows(stations, robot_stations.unpack(q_station + step), scale)
            - robot_stations.prior_rows(stations, robot_stations.unpack(q_station - step),
                                        scale)) / (2 * h)
    return np.r_[J, prior]


def _view_robust(J: np.ndarray, r: np.ndarray, rows: list[int], P: np.ndarray,
                 s2: float | None = None) -> np.ndarray:
    """Covariance of a refinement over captures whose residual rows are laid out view by
    view (``rows``: each view's count, ``rows_per_view``) with prior information ``P``:
    cluster-robust with one cluster per view, since a view's corners share its error
    (detection bias, the arm's pose), by the delete-one-view jackknife
    (``covariance.robust_covariance``)."""
    if len(r) != sum(rows):
        raise SolveError(f"robot refinement: {len(r)} residual rows do not split into "
                         f"{len(rows)} views of {sum(rows)} rows")
    return robust_covariance(J, r, view_clusters(len(rows), rows), P, s2)


CAMERA_KEYS = ("fx", "fy", "cx", "cy")
DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")


@dataclass
class CameraRefinement:
    """The camera model the joint refinement ended with, against the prior it started
    from (``prior_sigma`` is that prior's 1-sigma)."""

    K: np.ndarray
    dist: np.ndarray
    sigma: dict[str, float]
    prior: dict[str, float]
    prior_sigma: dict[str, float]  # as used: the given sigma times ``prior_inflation``
    prior_inflation: float = 1.0
    board_only: dict[str, float] | None = None  # the board views' estimate, no prior

    def intrinsics(self) -> dict:
        return {"fx": float(self.K[0, 0]), "fy": float(self.K[1, 1]),
                "cx": float(self.K[0, 2]), "cy": float(self.K[1, 2]),
                "distortion": self.dist.tolist()}

    def moved(self) -> dict[str, float]:
        now = self.intrinsics()
        return {k: now[k] - self.prior[k] for k in CAMERA_KEYS}


# a prior whose Mahalanobis distance (4 dof) from the board views' own estimate exceeds
# this (chi-square's 99 % point) is inconsistent with them: its sigma is inflated
PRIOR_CONSISTENT_CHI2 = 13.28


def prior_inflation(board: np.ndarray, board_cov: np.ndarray, prior: np.ndarray,
                    prior_sigma: np.ndarray) -> float:
    """The factor by which the prior's sigma must grow so that the prior and the board
    views' own estimate of the same intrinsics (``board``, covariance ``board_cov``)
    agree: 1 while their Mahalanobis distance m^2 stays within ``PRIOR_CONSISTENT_CHI2``,
    else the factor k at which ``d^T (board_cov + k^2 diag(prior_sigma^2))^-1 d`` equals
    its expectation, 4 (Birge's ratio: two independent estimates that differ by more than
    their sigmas allow claim too little uncertainty between them). Only the prior's sigma
    grows: the board views' covariance is cluster-robust per view (``_view_robust``),
    while the prior's (the active-camera solve) can miss a model error of that solve."""
    d = board - prior

    def excess(log_k: float) -> float:
        S = board_cov + np.diag((np.exp(log_k) * prior_sigma) ** 2)
        return float(d @ np.linalg.solve(S, d)) - len(d)

    m2 = excess(0.0) + len(d)
    if not np.isfinite(m2) or m2 <= PRIOR_CONSISTENT_CHI2:
        return 1.0
    top = 12.0  # a factor of 1.6e5: beyond it the prior carries no weight anyway
    return float(np.exp(brentq(excess, 0.0, top, xtol=1e-9) if excess(top) < 0 else top))


def refine_with_camera(ref: RefineResult, meas: Measurements, prior_sigma: dict[str, float],
                       mask=None, max_nfev: int = 40) -> tuple[RefineResult, CameraRefinement]:
    """The joint refinement of ``refine`` (pixel residuals of every capture) with the
    camera free as well: fx, fy, cx, cy and the distortion terms k1 k2 p1 p2 k3 (eq. 2.3),
    starting from ``ref`` (the same solve with the camera held). The intrinsics the
    refinement started from (the active-camera result) enter as a prior with their
    1-sigma ``prior_sigma``; distortion has no prior, the board views determine it. The
    prior's rows are scaled by the pixel noise of ``ref`` so that both weigh as they
    should. The board views' own estimate (no prior) is solved first: a prior that
    disagrees with it beyond its sigmas has its sigma inflated (``prior_inflation``).
    Returns the refinement (sigma now includes the camera's uncertainty) and the camera
    model with its sigma."""
    mask = mask or identifiable_mask(ref.model, absorb=True)
    p_arm, names = _pack(ref.model, ref.X, ref.W, mask, True)
    n_frames = len(p_arm)
    stations = meas.stations if meas.station_count else None
    if stations is not None:
        p_arm = np.r_[p_arm, robot_stations.pack(ref.stations or stations.predicted)]
        names = names + robot_stations.names(stations.count)
    n_arm = len(p_arm)
    K0, dist0 = meas.K, np.zeros(5)
    dist0[:min(5, len(meas.dist))] = np.asarray(meas.dist, float)[:5]
    prior = np.array([K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]])
    sig = np.array([max(float(prior_sigma.get(k, 0.0)), 1e-6) for k in CAMERA_KEYS])
    scale = max(ref.rms, 0.02)

    def camera(p):
        c = p[n_arm:]
        return camera_matrix(*c[:4]), c[4:]

    def pixels(p):
        model, X, W = _unpack(p[:n_frames], ref.model, ref.X, ref.W, mask, True)
        if stations is None:
            return residuals(model, X, W, meas, *camera(p))
        D = robot_stations.unpack(p[n_frames:n_arm])
        return np.r_[residuals(model, X, W, meas, *camera(p), stations=D),
                     robot_stations.prior_rows(stations, D, scale)]

    def pixels_jacobian(p):
        model, X, W = _unpack(p[:n_frames], ref.model, ref.X, ref.W, mask, True)
        return _pixel_jacobian(p, n_frames, model, X, W, mask, True, meas, stations, scale,
                               *camera(p), camera=True)

    board = least_squares(pixels, np.r_[p_arm, prior, dist0], jac=pixels_jacobian,
                          x_scale="jac", max_nfev=max_nfev)
    n_station_rows = 0 if stations is None else 6 * stations.count
    n_px = len(board.fun) - n_station_rows
    s2_board = float(np.sum(board.fun[:n_px] ** 2) / max(n_px - len(board.x), 1))
    station_info = board.jac[n_px:].T @ board.jac[n_px:]
    board_cov = _view_robust(board.jac[:n_px], board.fun[:n_px], rows_per_view(meas),
                             station_info, s2_board)
    inflation = prior_inflation(board.x[n_arm:n_arm + 4],
                                board_cov[n_arm:n_arm + 4, n_arm:n_arm + 4], prior, sig)
    sig = sig * inflation

    def fun(p):
        return np.r_[pixels(p), (p[n_arm:n_arm + 4] - prior) / sig * scale]

    def jac(p):
        rows = np.zeros((4, len(p)))
        rows[np.arange(4), n_arm + np.arange(4)] = scale / sig
        return np.r_[pixels_jacobian(p), rows]

    sol = least_squares(fun, board.x, jac=jac, x_scale="jac", max_nfev=max_nfev)
    model, X, W = _unpack(sol.x[:n_frames], ref.model, ref.X, ref.W, mask, True)
    K, dist = camera(sol.x)
    J = sol.jac
    J_prior = J[n_px:]
    s2 = float(np.sum(sol.fun[:n_px] ** 2) / max(n_px - len(sol.x), 1))
    cov = _view_robust(J[:n_px], sol.fun[:n_px], rows_per_view(meas), J_prior.T @ J_prior,
                       s2)
    sigma = np.sqrt(np.clip(np.diag(cov), 0, None))
    sv = scaled_singular_values(J[:n_px, :n_arm])
    result = RefineResult(model, X, W, names, sol.x[:n_arm], sigma[:n_arm],
                          condition_number(sv), sv,
                          float(np.sqrt(np.mean(sol.fun[:n_px] ** 2))),
                          _kinematic_condition(J[:n_px, :n_arm], 12 + n_station_rows))
    result.covariance = cov
    if stations is not None:
        result.stations = robot_stations.unpack(sol.x[n_frames:n_arm])
    cam = CameraRefinement(K, dist, dict(zip(CAMERA_KEYS + DIST_KEYS,
                                             sigma[n_arm:].tolist(), strict=True)),
                           dict(zip(CAMERA_KEYS, prior.tolist(), strict=True)),
                           dict(zip(CAMERA_KEYS, sig.tolist(), strict=True)),
                           prior_inflation=inflation,
                           board_only=dict(zip(CAMERA_KEYS, board.x[n_arm:n_arm + 4].tolist(),
                                               strict=True)))
    return result, cam


def _perturbed(model: KinematicModel, X, W, name: str, h: float):
    """(model, X, W) with the parameter ``name`` (``linkN.field``, ``X.rx`` ... ``W.z``,
    as ``_pack`` names them) moved by ``h``."""
    if name.startswith("link"):
        link, key = name.split(".")
        model = model.copy()
        getattr(model, key)[int(link.removeprefix("link")) - 1] += h
        return model, X, W
    frame, comp = name.split(".")
    T = (X if frame == "X" else W).copy()
    if comp in ("x", "y", "z"):
        T[:3, 3] += h * np.eye(3)["xyz".index(comp)]
    else:
        rv = R_to_rotvec(T[:3, :3]) + h * np.eye(3)["xyz".index(comp[1])]
        T[:3, :3] = rotvec_to_R(rv)
    return (model, T, W) if frame == "X" else (model, X, T)


def camera_position_sigma(model: KinematicModel, X, W, names: list[str], cov: np.ndarray,
                          q_list, fixed: bool = False) -> np.ndarray:
    """Predicted 1-sigma (m, per axis of the target frame) of the camera's position
    ``W^-1 FK(q) X`` at each configuration, from the refinement's covariance of the
    parameters ``names`` (first-order propagation, central differences): mrcal's
    projection uncertainty carried over to an arm. Returns (len(q_list), 3)."""
    # the configurations are the head's at home: its stations' parameters do not move them
    keep = [i for i, name in enumerate(names) if not name.startswith("station")]
    names = [names[i] for i in keep]
    n = len(names)
    cov = np.asarray(cov, float)[np.ix_(keep, keep)]

    def position(m, x, w):
        return invert_batch(cam_target_batch(m, x, w, np.asarray(q_list, float), fixed))[:, :3, 3]

    J = np.zeros((len(q_list), 3, n))
    for i, name in enumerate(names):
        h = 1e-7
        J[:, :, i] = (position(*_perturbed(model, X, W, name, h))
                      - position(*_perturbed(model, X, W, name, -h))) / (2 * h)
    var = np.einsum("kai,ij,kaj->ka", J, cov, J)
    return np.sqrt(np.clip(var, 0, None))


def jacobian_singular_values(model, X, W, meas: Measurements, mask) -> np.ndarray:
    """Scaled singular values (``scaled_singular_values``) of the identification Jacobian
    of the ``mask``ed link parameters with X and W, at (model, X, W): one central-
    difference Jacobian of the residuals of (4.11), no solve. Enough to show a
    parameterisation's rank deficiency (plain D-H on parallel joints) without iterating
    on it to the evaluation limit. With board corners the Jacobian is the analytic one
    (``_pixel_jacobian``, the stations held where predicted)."""
    p0, _ = _pack(model, X, W, mask, True)
    if meas.corners is not None:
        stations = meas.stations if meas.station_count else None
        p = p0 if stations is None else np.r_[p0, robot_stations.pack(stations.predicted)]
        J = _pixel_jacobian(p, len(p0), model, X, W, mask, True, meas, stations, 1.0)
        return scaled_singular_values(J[:len(J) - (len(p) - len(p0)), :len(p0)])

    def fun(p):
        return residuals(*_unpack(p, model, X, W, mask, True), meas)

    columns = []
    for i in range(len(p0)):
        h = 1e-6 * max(1.0, abs(p0[i]))
        step = np.zeros_like(p0)
        step[i] = h
        columns.append((fun(p0 + step) - fun(p0 - step)) / (2 * h))
    return scaled_singular_values(np.column_stack(columns))


def scaled_singular_values(J: np.ndarray) -> np.ndarray:
    """Singular values of a Jacobian with its columns scaled to unit norm, so that
    metres and radians compare (largest first)."""
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    return np.linalg.svd(J / norms, compute_uv=False)


def condition_number(sv: np.ndarray) -> float:
    """Largest over smallest singular value (inf when rank-deficient)."""
    return float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")


def frames_only_mask(model: KinematicModel) -> dict[str, np.ndarray]:
    """A mask that estimates no link parameter: ``refine`` then fits X and W alone."""
    return {k: np.zeros(model.n, bool) for k in LINK_KEYS}


def _kinematic_condition(J: np.ndarray, n_nuisance: int) -> float:
    """Condition number of the link-parameter columns once the last ``n_nuisance``
    columns (X, W) are projected out: the identification Jacobian proper, which Schroer's
    guideline (below 100) is about."""
    A = J[:, :J.shape[1] - n_nuisance]
    if A.shape[1] == 0:
        return float("nan")
    if n_nuisance:
        Q, _ = np.linalg.qr(J[:, -n_nuisance:])
        A = A - Q @ (Q.T @ A)
    return condition_number(scaled_singular_values(A))


def pose_deviations(model, X, W, q_list, T_target_cam, fixed: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per configuration, position (m) and rotation (rad) error of the predicted camera
    pose in the target frame (``target_cam``: ``W^-1 FK(q) X``, or with a ``fixed``
    camera ``W^-1 FK(q)^-1 X``), against ``T_target_cam`` (one 4x4 each)."""
    pos, rot = [], []
    for q, T_ref in zip(q_list, T_target_cam, strict=True):
        T = target_cam(model, X, W, q, fixed)
        pos.append(np.linalg.norm(T[:3, 3] - T_ref[:3, 3]))
        rot.append(np.linalg.norm(R_to_rotvec(T[:3, :3].T @ T_ref[:3, :3])))
    return np.array(pos), np.array(rot)


def pose_errors(model, X, W, q_list, truth_fn) -> tuple[float, float]:
    """RMS of ``pose_deviations`` against ``truth_fn(q)`` (a 4x4 ``T_target_cam``)."""
    pos, rot = pose_deviations(model, X, W, q_list, [truth_fn(q) for q in q_list])
    return float(np.sqrt(np.mean(pos ** 2))), float(np.sqrt(np.mean(rot ** 2)))
