"""Views of a board held by the flange, for a head standing beside the arm (eye-to-hand).

The camera stands still (``devices.head.mount: fixed``, approximate ``T_base_cam`` from
``fixed_pose``); the arm brings the board (``target.mount: flange``, approximate
``T_flange_target`` from ``target.pose``) into its view. A view is drawn in the camera's
frame: the board centre along a ray through the image (so that views spread over the
image), at the viewing distance, the board facing the camera (its normal within
``max_tilt_deg`` of the ray) and spun freely about it. The flange pose that puts the
board there is solved for joints (several IK seeds), kept when inside the soft limits,
clear of the table (``planning.clearance_m``) and with the board in view
(``planning.board_visible``). From a head station (the head re-aimed, ``head_stations``)
the same, with the camera there.
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.calib import pose_selection
from rigctl.calib.board import target_points
from rigctl.config import RigConfig
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import KinematicModel
from rigctl.geometry.transforms import inv_T, make_T

from .planning import (
    MIN_CLEARANCE_M,
    MIN_VIEWS,
    VIEW_SEEDS_DEG,
    arm_model,
    board_centre,
    board_visible,
    clearance_m,
    fit_distance,
    joints_within_limits,
    nominal_base_cam,
    nominal_flange_target,
    reach_sphere,
    resolved_distance,
)

HEAD_STILL_NOTE = "head beside the arm: the head stays at home for every view"
NO_HEAD_GEOMETRY_NOTE = (f"{HEAD_STILL_NOTE} (re-aiming it needs the head's calibrated "
                         "geometry, which the intrinsics in use came without: run "
                         "active-camera on this rig first, or give the intrinsics parameter "
                         "its head_geometry)")
HEAD_STATIONS_NOTE = ("head beside the arm: the training views are taken from head stations "
                      "(home, pan and tilt each way), the head's calibrated geometry "
                      "predicting each station's pose (refined with the arm); the sweeps "
                      "and held-out views at home")
# the share of the image (about its centre) the board centre's rays are drawn from
RAY_SHARE = 0.6
DISTANCES = (1.0, 1.2, 0.85, 1.45)  # times the viewing distance, tried in turn


def _ray(rng: np.random.Generator, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A unit ray in the camera frame through a pixel drawn over ``RAY_SHARE`` of the
    image about its centre."""
    w, h = size
    u = w / 2 + (rng.uniform() - 0.5) * RAY_SHARE * w
    v = h / 2 + (rng.uniform() - 0.5) * RAY_SHARE * h
    r = np.linalg.solve(K, [u, v, 1.0])
    return r / np.linalg.norm(r)


def _board_in_camera(rng: np.random.Generator, ray: np.ndarray, distance: float,
                     tilt_deg: float, centre: np.ndarray) -> np.ndarray:
    """``T_cam_target`` with the board centre on ``ray`` at ``distance``, the board's z
    (into the board) within ``tilt_deg`` of the ray, spun freely about it."""
    helper = np.cross(ray, [0.0, 1.0, 0.0] if abs(ray[1]) < 0.9 else [1.0, 0.0, 0.0])
    u = helper / np.linalg.norm(helper)
    v = np.cross(ray, u)
    tilt = math.radians(tilt_deg) * math.sqrt(rng.uniform())
    azimuth = rng.uniform(0, 2 * math.pi)
    z = math.cos(tilt) * ray + math.sin(tilt) * (math.cos(azimuth) * u + math.sin(azimuth) * v)
    spin = rng.uniform(0, 2 * math.pi)
    x0 = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(z, x0)
    x = math.cos(spin) * x0 + math.sin(spin) * y0
    R = np.column_stack([x, np.cross(z, x), z])
    return make_T(R, distance * ray - R @ centre)


def board_views(config: RigConfig, n: int, distance_m: float, max_tilt_deg: float,
                seed: int, K: np.ndarray, model: KinematicModel | None = None,
                attempts_per_view: int = 8, station: np.ndarray | None = None
                ) -> tuple[list[np.ndarray], list[str]]:
    """Up to ``n`` joint configurations that hold the board in the fixed camera's view
    (module note), at ``distance_m`` (never nearer than the board fits the image with
    ``K``, ``planning.fit_distance``; never farther than a ChArUco board's markers decode,
    ``planning.resolved_distance``) or, when too few are reachable there, at the other
    ``DISTANCES``. Returns them and notes; fewer than ``MIN_VIEWS`` is a ``SolveError``
    naming what to change. ``station``: the head re-aimed, the camera there seen from the
    camera at home (``head_stations``)."""
    arm = config.devices.arm
    model = arm_model(config, model)
    T_base_cam, T_target_flange = nominal_base_cam(config), inv_T(nominal_flange_target(config))
    if station is not None:
        T_base_cam = T_base_cam @ station
    centre = board_centre(config)
    size = (config.devices.camera.width, config.devices.camera.height)
    limits = arm.joint_limits_rad()
    shoulder, reach = reach_sphere(model, make_T())
    seeds = [np.asarray(arm.home_rad(), float)] + [np.radians(s) for s in VIEW_SEEDS_DEG]
    decodable, why = resolved_distance(config, K, distance_m)
    start = max(decodable, 1.1 * fit_distance(config, K))
    best: tuple[list, float] = ([], start)
    for factor in DISTANCES:
        rng = np.random.default_rng([seed, int(1000 * factor)])
        poses: list[np.ndarray] = []
        previous = None
        for _ in range(attempts_per_view * n):
            if len(poses) >= n:
                break
            d = start * factor * rng.uniform(0.9, 1.1)
            T_cam_target = _board_in_camera(rng, _ray(rng, K, size), d, max_tilt_deg, centre)
            T_base_flange = T_base_cam @ T_cam_target @ T_target_flange
            if np.linalg.norm(T_base_flange[:3, 3] - shoulder) > reach:
                continue
            q = joints_within_limits(model, T_base_flange,
                                     ([previous] if previous is not None else []) + seeds,
                                     limits)
            if q is None or clearance_m(config, model, q) < MIN_CLEARANCE_M or \
                    not board_visible(config, model, q, K, station=station):
                continue
            poses.append(q)
            previous = q
        if len(poses) > len(best[0]):
            best = (poses, start * factor)
        if len(best[0]) >= n:
            break
    poses, used = best
    notes = [] if abs(used - distance_m) < 1e-9 else [
        f"board views: planned at {used:.2f} m from the camera instead of {distance_m:.2f} m "
        f"({len(poses)} of {n} views)" + (f"; {why}" if why else "")]
    if len(poses) < MIN_VIEWS:
        raise SolveError(f"board views{'' if station is None else ' (head re-aimed)'}: only "
                         f"{len(poses)} of {n} views hold the board in the "
                         f"fixed camera's view at {start * min(DISTANCES):.2f}-"
                         f"{start * max(DISTANCES):.2f} m within the soft limits; check "
                         "devices.head.fixed_pose (the camera must look at the arm's "
                         "workspace) and target.pose, or change view_distance_m")
    return poses, notes


def informative_board_views(config: RigConfig, params, K: np.ndarray, planned_q: list,
                            n: int, seed: int, model: KinematicModel | None = None,
                            links: bool = True) -> tuple[list[np.ndarray], list[str]]:
    """``n`` views chosen D-optimally (``pose_selection.select_informative``) from
    ``board_views`` candidates at 0.85, 1 and 1.2 times ``params.view_distance_m``,
    together with the views already planned (``planned_q``), for the eye-to-hand model
    (``T_base_cam``, ``T_flange_target`` and, with ``links``, the arm's identifiable link
    parameters); ordered for short travel. The head stays at home
    (``informative_station_views`` re-aims it)."""
    poses, _, notes = informative_station_views(config, params, K, planned_q, n, seed,
                                                model, links)
    return poses, notes


def informative_station_views(config: RigConfig, params, K: np.ndarray, planned_q: list,
                              n: int, seed: int, model: KinematicModel | None = None,
                              links: bool = True, stations: list[np.ndarray] | None = None
                              ) -> tuple[list[np.ndarray], list[int], list[str]]:
    """``informative_board_views`` from the head's ``stations`` (each camera seen from the
    camera at home, the first at home; None: home only): candidates from every station
    whose views are reachable, the D-optimal choice among all of them (each candidate's
    Jacobian with the camera at its station; the stations' own pose parameters are left
    out of the criterion). Returns the views grouped by station (home first, each group
    ordered for short travel), each view's station, and notes."""
    model = arm_model(config, model)
    stations = [np.eye(4)] if stations is None else stations
    X, W = nominal_base_cam(config), nominal_flange_target(config)
    candidates, owner, notes = [], [], []
    for s, station in enumerate(stations):
        found = 0
        for k, factor in enumerate((1.0, 0.85, 1.2)):
            try:
                more, _ = board_views(config, 3 * n, params.view_distance_m * factor,
                                      params.max_tilt_deg, seed + 17 * k + 101 * s, K, model,
                                      station=None if s == 0 else station)
            except SolveError:
                continue
            candidates += more
            owner += [s] * len(more)
            found += len(more)
        if s and not found:
            notes.append(f"head station {s}: no reachable view holds the board in view there; "
                         "left out")
    if len(candidates) < n:
        poses, more = board_views(config, n, params.view_distance_m, params.max_tilt_deg,
                                  seed, K, model)
        return poses, [0] * len(poses), [f"pose selection: only {len(candidates)} candidate "
                                         "views; using random views", *more]
    from rigctl.calib import robot

    mask = None if links else robot.frames_only_mask(model)
    obj = target_points(config.target)
    owner_arr = np.array(owner)
    J_cand = None
    for s in sorted(set(owner)):
        idx = np.flatnonzero(owner_arr == s)
        J_s = pose_selection.view_jacobians(model, X @ stations[s], W,
                                            [candidates[i] for i in idx], mask, obj=obj, K=K,
                                            fixed=True)
        if J_cand is None:
            J_cand = np.zeros((len(candidates), *J_s.shape[1:]))
        J_cand[idx] = J_s
    J_fixed = pose_selection.view_jacobians(model, X, W, planned_q, mask, obj=obj, K=K,
                                            fixed=True).reshape(-1, J_cand.shape[2]) \
        if planned_q else None
    chosen = pose_selection.select_informative(J_cand, n, J_fixed)
    rows = J_cand[chosen].reshape(-1, J_cand.shape[2])
    cond = pose_selection.scaled_condition(rows if J_fixed is None else np.r_[J_fixed, rows])
    used = sorted({owner[i] for i in chosen})
    where = "" if len(stations) == 1 else \
        f" from {len(used)} of {len(stations)} head stations"
    notes.append(f"pose selection: {n} of {len(candidates)} candidate board views "
                 f"(D-optimal){where}; predicted condition number {cond:.0f}")
    poses, station_of = [], []
    start = planned_q[-1] if planned_q else candidates[chosen[0]]
    for s in used:
        group = [candidates[i] for i in chosen if owner[i] == s]
        order = pose_selection.order_by_travel(group, start)
        poses += [group[i] for i in order]
        station_of += [s] * len(group)
        start = poses[-1]
    return poses, station_of, notes


# A head station turns the head by this share of the camera's field of view, at most
# STATION_MAX_DEG: the views there overlap the home view's edge and reach past it
STATION_SHARE = 0.5
STATION_MAX_DEG = (25.0, 20.0)  # pan, tilt


def head_stations(config: RigConfig, K: np.ndarray) -> list[tuple[float, float, float]]:
    """The head's angles (rad) at each station: home, then pan right and left, tilt up and
    down by ``STATION_SHARE`` of the field of view (at most ``STATION_MAX_DEG``), each
    kept within the head's soft limits."""
    cam, limits = config.devices.camera, config.devices.head.limits
    half_fov = (math.atan(cam.width / (2 * K[0, 0])), math.atan(cam.height / (2 * K[1, 1])))
    pan, tilt = (min(math.degrees(STATION_SHARE * 2 * h), top)
                 for h, top in zip(half_fov, STATION_MAX_DEG, strict=True))
    out = [(0.0, 0.0, 0.0)]
    for p, t in ((pan, 0.0), (-pan, 0.0), (0.0, tilt), (0.0, -tilt)):
        if limits.pan[0] <= p <= limits.pan[1] and limits.tilt[0] <= t <= limits.tilt[1]:
            out.append((math.radians(p), math.radians(t), 0.0))
    return out
