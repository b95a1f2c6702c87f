"""Pose planning: views of the target that keep it in sight, the single-joint sweeps of
robot-kinematics, and the intrinsics planning assumes.

The arm model the planner predicts the camera with (``planning_arm``) is the controller's
own, factory-calibrated DH table when the controller reports one on its primary interface
(read-only, port 30001), else the nominal table of the rig file's arm model. The arm
procedures read it when the run is planned and record it in ``inputs.json``."""

from __future__ import annotations

import hashlib
import math
import threading
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from rigctl.calib import pose_selection, robot
from rigctl.calib.board import is_charuco, target_points
from rigctl.calib.charuco import dictionary
from rigctl.config import RigConfig
from rigctl.drivers.ur_primary import PrimaryInfo, read_primary_info
from rigctl.errors import ConfigError, DeviceError, SolveError
from rigctl.geometry.camera import camera_matrix
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from rigctl.geometry.transforms import inv_T, look_at, make_T, xyz_rpy_to_T
from rigctl.geometry.ur_reach import surely_unreachable

from .base import CaptureStep, MoveArmJoints, MoveHead, Note, Settle
from .intrinsics import camera_model, intrinsics_from

# a coarse guard against driving the arm into the table the target lies on: the elbow,
# wrists, flange and camera stay this far on the camera's side of the target plane
MIN_CLEARANCE_M = 0.05
VIEW_SEEDS_DEG = ([0, -100, -100, -70, 90, 0], [0, -80, -110, -80, 90, 0],
                  [30, -100, -100, -70, 90, 0], [-30, -100, -100, -70, 90, 0])


# How long the controller's answer read by a plan serves the ``resolve_inputs`` that follows
# it (the runner plans, then resolves the inputs): what the plan used is what is recorded.
PRIMARY_REUSE_S = 600.0
_primary_reads: dict[str, tuple[float, PrimaryInfo | Exception]] = {}
_primary_lock = threading.Lock()
_identities: dict[str, tuple[float, Any]] = {}  # host -> (when, ControllerIdentity or None)


def controller_dh_model(kinematics: dict) -> KinematicModel:
    """The arm model of a controller's DH table (``KinematicsInfo.as_dict()``: theta, a,
    d, alpha in radians and metres; plain DH, no beta)."""
    return KinematicModel(np.array(kinematics["d"], float), np.array(kinematics["a"], float),
                          np.array(kinematics["alpha"], float),
                          theta_offset=np.array(kinematics["theta"], float))


@dataclass(frozen=True)
class PlanningArm:
    """The arm model a plan predicts the camera with: the controller's own (``source``
    "controller", its hash and version) or the nominal table ("nominal", ``note`` says
    why)."""

    model: KinematicModel
    source: str
    robot_hash: str | None = None
    controller_version: str | None = None
    kinematics: dict | None = None  # the controller's DH table as it reported it
    note: str = ""

    def record(self) -> dict[str, Any]:
        """What ``inputs.json`` keeps of it."""
        return {"source": self.source, "robot_hash": self.robot_hash,
                "controller_version": self.controller_version,
                "controller_kinematics": self.kinematics, "note": self.note}


def _primary_info(host: str, timeout_s: float, fresh: bool) -> PrimaryInfo | Exception:
    """The controller's primary-interface answer (or the error reading it), read now, or
    with ``fresh=False`` the one the last plan read within ``PRIMARY_REUSE_S``."""
    with _primary_lock:
        cached = _primary_reads.get(host)
    if not fresh and cached is not None and time.monotonic() - cached[0] < PRIMARY_REUSE_S:
        return cached[1]
    try:
        info: PrimaryInfo | Exception = read_primary_info(host, timeout_s=timeout_s)
    except DeviceError as exc:  # ProtocolError too
        info = exc
    with _primary_lock:
        _primary_reads[host] = (time.monotonic(), info)
    return info


def planning_arm(config: RigConfig, use_controller: bool = True, fresh: bool = True
                 ) -> PlanningArm:
    """The controller's own DH table when it reports one (``use_controller``), else the
    nominal table of ``devices.arm.model``. Reads the controller's primary interface (a
    read-only connection; nothing moves); ``fresh=False`` reuses what the last plan read
    (``resolve_inputs`` records the model the plan used)."""
    arm = config.devices.arm
    if arm is None:
        raise SolveError("planning needs devices.arm in the rig file")
    nominal = nominal_ur(arm.model)
    if not use_controller:
        return PlanningArm(nominal, "nominal", note="the controller's model is not used "
                           "(use_controller_model=false); planned with the nominal "
                           f"{arm.model} table")
    info = _primary_info(arm.host, arm.primary_timeout_s, fresh)
    if isinstance(info, Exception):
        return PlanningArm(nominal, "nominal", note=f"no controller model ({info}); planned "
                           f"with the nominal {arm.model} table")
    _check_controller_model(arm, fresh)
    version = info.version.text if info.version else None
    if info.kinematics is None:
        return PlanningArm(nominal, "nominal", controller_version=version,
                           note="the controller reports no KINEMATICS_INFO; planned with "
                                f"the nominal {arm.model} table")
    kinematics = info.kinematics.as_dict()
    model = controller_dh_model(kinematics)
    mm = 1000 * float(np.max(np.abs(np.r_[model.d - nominal.d, model.a - nominal.a])))
    deg = math.degrees(float(np.max(np.abs(np.r_[model.theta_offset - nominal.theta_offset,
                                                   model.alpha - nominal.alpha]))))
    return PlanningArm(model, "controller", kinematics["hash"], version, kinematics,
                       note=f"planned with the controller's own kinematics ({kinematics['hash']}"
                            f", controller {version}): up to {mm:.2f} mm and {deg:.3f} deg "
                            f"from the nominal {arm.model} table")


def _check_controller_model(arm, fresh: bool) -> None:
    """``ConfigError`` (before anything moves) when the controller that answered says it is
    another model than ``devices.arm.model`` (its dashboard, read once per plan)."""
    from rigctl.drivers.ur import read_identity
    from rigctl.hardware.ur_models import check_model

    with _primary_lock:
        cached = _identities.get(arm.host)
    if fresh or cached is None or time.monotonic() - cached[0] >= PRIMARY_REUSE_S:
        cached = (time.monotonic(), read_identity(arm.host))
        with _primary_lock:
            _identities[arm.host] = cached
    if cached[1] is not None:
        check_model(arm.model, cached[1], arm.host)


def arm_model(config: RigConfig, model: KinematicModel | None) -> KinematicModel:
    """``model``, or the nominal table of the rig file's arm when None."""
    return model if model is not None else nominal_ur(config.devices.arm.model)


@lru_cache(maxsize=32)
def _fixed_pose(xyz_mm: tuple[float, ...], rpy_deg: tuple[float, ...]) -> np.ndarray:
    """``xyz_rpy_to_T`` of a rig-file pose, built once: the planners ask for the target
    and mount poses thousands of times per plan (read-only; callers copy to change it)."""
    T = xyz_rpy_to_T(list(xyz_mm), list(rpy_deg))
    T.flags.writeable = False
    return T


def target_centre(config: RigConfig) -> tuple[np.ndarray, np.ndarray]:
    """``T_base_target`` (nominal) and the board centre in the base frame."""
    tg = config.target
    T = _fixed_pose(tuple(tg.pose.xyz_mm), tuple(tg.pose.rpy_deg)).copy()
    s = tg.square_mm / 1000.0
    centre = T @ np.array([tg.cols * s / 2, tg.rows * s / 2, 0.0, 1.0])
    return T, centre[:3]


def clearance_m(config: RigConfig, model, q) -> float:
    """The smallest height of the elbow, wrist, flange and camera frames (arm ``model``)
    above the target plane, on the side the camera looks from. Frame origins only, and
    only at the planned configurations, not along the moves between them. With the
    board on the flange (``eye_to_hand``): the elbow, wrist and flange frames' and the
    board centre's height above the base's plane (the table the arm stands on)."""
    return float(clearances_m(config, model, np.asarray(q, float)[None])[0])


def clearances_m(config: RigConfig, model, Q: np.ndarray) -> np.ndarray:
    """``clearance_m`` at each configuration of ``Q`` (N, 6), at once: (N,) metres."""
    frames = model.frames_batch(Q)
    if eye_to_hand(config):
        board = frames[:, -1] @ (nominal_flange_target(config) @ np.r_[board_centre(config), 1.0])
        return np.minimum(np.min(frames[:, 2:, 2, 3], axis=1), board[:, 2])
    T_base_target, _ = target_centre(config)
    normal = -T_base_target[:3, 2]
    camera = (frames[:, -1] @ nominal_flange_cam(config))[:, None, :3, 3]
    points = np.concatenate([frames[:, 2:, :3, 3], camera], axis=1)
    return np.min((points - T_base_target[:3, 3]) @ normal, axis=1)


def eye_to_hand(config: RigConfig) -> bool:
    """True when the head stands beside the arm (``devices.head.mount: fixed``) watching
    a board on the flange (``target.mount: flange``); False for the head on the flange
    and the board in the world. ``ConfigError`` (naming the keys) for the combinations
    in which no arm motion moves the board in the camera's view."""
    head = config.devices.head
    fixed = head is not None and head.fixed
    on_flange = config.target.mount == "flange"
    if fixed and not on_flange:
        raise ConfigError("devices.head.mount: fixed with target.mount: world: the camera and "
                          "the board both stand still, so there is nothing for the arm to "
                          "move; hold the board on the flange (target.mount: flange, pose: "
                          "its approximate T_flange_target)")
    if on_flange and not fixed:
        raise ConfigError("target.mount: flange with the camera on the flange (devices.head "
                          "missing or its mount a T_flange_head): the board rides with the "
                          "camera, so no arm motion moves it in view; stand the head beside "
                          "the arm (devices.head.mount: fixed, fixed_pose: its T_base_head)")
    return fixed


def nominal_base_cam(config: RigConfig) -> np.ndarray:
    """Nominal ``T_base_cam`` of a head standing beside the arm, at head home: its
    ``fixed_pose`` (the camera on the head axes)."""
    pose = config.devices.head.fixed_pose
    return _fixed_pose(tuple(pose.xyz_mm), tuple(pose.rpy_deg)).copy()


def nominal_flange_target(config: RigConfig) -> np.ndarray:
    """Nominal ``T_flange_target`` of a board on the flange (``target.pose``)."""
    tg = config.target
    return _fixed_pose(tuple(tg.pose.xyz_mm), tuple(tg.pose.rpy_deg)).copy()


def board_centre(config: RigConfig) -> np.ndarray:
    """The board centre in the target frame (m)."""
    tg = config.target
    s = tg.square_mm / 1000.0
    return np.array([tg.cols * s / 2, tg.rows * s / 2, 0.0])


def nominal_frames(config: RigConfig) -> tuple[np.ndarray, np.ndarray]:
    """The nominal (X, W) of the solvers' loop for the rig's mounting: ``T_flange_cam``
    and ``T_base_target``, or with the head beside the arm ``T_base_cam`` and
    ``T_flange_target`` (``robot.cam_target_batch``)."""
    if eye_to_hand(config):
        return nominal_base_cam(config), nominal_flange_target(config)
    return nominal_flange_cam(config), target_centre(config)[0]


def nominal_cam_target(config: RigConfig, model: KinematicModel, q) -> np.ndarray:
    """``T_cam_target`` at joints ``q`` (arm ``model``) with the rig file's nominal
    mount and target, for either mounting."""
    fixed = eye_to_hand(config)
    X, W = nominal_frames(config)
    return robot.cam_target_batch(model, X, W, np.asarray(q, float)[None], fixed)[0]


def nominal_flange_cam(config: RigConfig) -> np.ndarray:
    """Nominal ``T_flange_cam`` at head home: the head mount, camera on the head axes."""
    mount = config.devices.head.mount if config.devices.head else None
    if mount is None or mount == "fixed":  # (a fixed head: ``nominal_base_cam``)
        return make_T(t=[0, 0, 0.05])
    return _fixed_pose(tuple(mount.xyz_mm), tuple(mount.rpy_deg)).copy()


def reach_sphere(model: KinematicModel, T_flange_cam: np.ndarray) -> tuple[np.ndarray, float]:
    """A sphere that holds every camera position the arm can reach: centred on joint 2's
    origin at zero joint 1 rotation, with radius |a1| + sum over the later links of
    hypot(d_i, a_i), plus the flange-to-tool and flange-to-camera offsets (the triangle
    inequality on the D-H chain of thesis eq. 1.3). Views outside it have no IK solution,
    so the planner skips them without the (slow, failing) iterative search."""
    base = model.T_base_link0[:3, 3] + model.T_base_link0[:3, :3] @ [0.0, 0.0, model.d[0]]
    radius = abs(model.a[0]) + float(np.sum(np.hypot(model.d[1:], model.a[1:]))) + \
        float(np.linalg.norm(model.T_flange_tool[:3, 3])) + \
        float(np.linalg.norm(np.asarray(T_flange_cam)[:3, 3]))
    return base, radius


def joints_within_limits(model: KinematicModel, T_base_flange: np.ndarray, seeds, limits,
                         accept=None) -> np.ndarray | None:
    """Joints (wrapped to [-pi, pi)) reaching ``T_base_flange`` inside ``limits`` (and
    passing ``accept``), from the first IK seed that gets there; None if none does, at
    once when the closed form says no seed can (``ur_reach.surely_unreachable``: 99 % of
    the failed searches of a robot-kinematics plan, three quarters of its IK steps)."""
    if surely_unreachable(model, T_base_flange):
        return None
    for seed_q in seeds:
        try:
            q = model.ik(T_base_flange, seed_q)
        except SolveError:
            continue
        q = (q + np.pi) % (2 * np.pi) - np.pi
        if all(lo <= v <= hi for v, (lo, hi) in zip(q, limits, strict=True)) and \
                (accept is None or accept(q)):
            return q
    return None


def plan_target_views(config: RigConfig, n: int, distance_m: float = 0.45,
                      max_tilt_deg: float = 25.0, seed: int = 0,
                      up_axis: np.ndarray | None = None, max_spin_deg: float = 60.0,
                      model: KinematicModel | None = None, lean_deg: float = 0.0,
                      ) -> tuple[list[np.ndarray], list[str]]:
    """Joint configurations whose camera (arm ``model``, the nominal one when None)
    looks at the board centre from ``distance_m``, tilted up to ``max_tilt_deg`` off the
    board normal, with varied roll about the viewing axis (up to ``max_spin_deg`` either
    way from ``up_axis``, a direction in the board's plane, when given). The first view
    looks straight at the board, or leans ``lean_deg`` off its normal toward the arm's
    shoulder (a board at the edge of a small arm's reach). Returns the reachable ones and
    notes for the skipped."""
    arm = config.devices.arm
    if arm is None:
        raise SolveError("planning target views needs devices.arm in the rig file")
    if eye_to_hand(config):  # (and the combinations it refuses, by their keys)
        raise ConfigError("these views look at a board in the world; with the head beside "
                          "the arm (devices.head.mount: fixed, target.mount: flange) this "
                          "procedure is not supported yet (hand-eye and robot-kinematics are)")
    model = arm_model(config, model)
    T_base_target, centre = target_centre(config)
    normal = -T_base_target[:3, 2]  # board z points into the board; the camera is outside
    T_cam_flange = inv_T(nominal_flange_cam(config))
    shoulder, reach = reach_sphere(model, nominal_flange_cam(config))
    limits = arm.joint_limits_rad()
    rng = np.random.default_rng(seed)
    # a ChArUco board may run off the image: each view but the first aims at a point of
    # the board drawn from a stream of its own, so that its corners reach the image's
    aim = _aim_points(config, seed) if is_charuco(config.target) else None
    poses, notes = [], []
    previous = None
    attempts = 0
    while len(poses) < n and attempts < 6 * n:
        attempts += 1
        tilt = math.radians(max_tilt_deg) * math.sqrt(rng.uniform()) if len(poses) else 0.0
        azimuth = rng.uniform(0, 2 * math.pi)
        helper = np.cross(normal, [1.0, 0.0, 0.0]) if up_axis is None else \
            up_axis - np.dot(up_axis, normal) * normal
        if np.linalg.norm(helper) < 1e-6:
            helper = np.cross(normal, [0.0, 1.0, 0.0])
        u = helper / np.linalg.norm(helper)
        v = np.cross(normal, u)
        direction = math.cos(tilt) * normal + math.sin(tilt) * (math.cos(azimuth) * u +
                                                                 math.sin(azimuth) * v)
        if not poses and lean_deg:
            direction = _leaning(normal, shoulder - centre, math.radians(lean_deg))
        eye = centre + distance_m * rng.uniform(0.9, 1.1) * direction
        spin = math.radians(rng.uniform(-max_spin_deg, max_spin_deg))
        up = math.cos(spin) * u + math.sin(spin) * v
        if np.linalg.norm(eye - shoulder) > reach:  # no IK solution exists: skip the search
            notes.append(f"view {attempts}: eye {np.round(eye, 3).tolist()} m beyond the "
                         f"arm's reach ({reach:.2f} m from the shoulder); skipped")
            continue
        looked_at = centre if aim is None or not poses else next(aim)
        T_base_flange = look_at(eye, looked_at, up) @ T_cam_flange
        seeds = ([previous] if previous is not None else []) + \
            [np.radians(s) for s in VIEW_SEEDS_DEG]
        q = joints_within_limits(
            model, T_base_flange, seeds, limits,
            accept=lambda q: clearance_m(config, model, q) >= MIN_CLEARANCE_M)
        if q is None:
            notes.append(f"view {attempts}: eye {np.round(eye, 3).tolist()} m unreachable, "
                         "outside the soft limits or closer than "
                         f"{100 * MIN_CLEARANCE_M:.0f} cm to the target plane; skipped")
            continue
        poses.append(q)
        previous = q
    return poses, notes


def _aim_points(config: RigConfig, seed: int):
    """Endless points (base frame) spread over a ChArUco board's corner grid, for views
    that look at part of the board."""
    tg = config.target
    T_base_target, _ = target_centre(config)
    s = tg.square_mm / 1000.0
    rng = np.random.default_rng([seed, 41])
    while True:
        p = [rng.uniform(s, (tg.cols - 1) * s), rng.uniform(s, (tg.rows - 1) * s), 0.0, 1.0]
        yield (T_base_target @ p)[:3]


def _leaning(normal: np.ndarray, toward: np.ndarray, lean: float) -> np.ndarray:
    """The unit direction ``lean`` radians off ``normal`` toward ``toward``'s component
    in the plane normal to it (``normal`` itself when ``toward`` lies along it)."""
    side = toward - np.dot(toward, normal) * normal
    if np.linalg.norm(side) < 1e-9:
        return normal
    return math.cos(lean) * normal + math.sin(lean) * side / np.linalg.norm(side)


MIN_VIEWS = 3
CLOSER = (0.8, 0.65, 0.5)  # viewing distances tried when too few views are reachable
FARTHER = (1.2, 1.45)      # ... and, when the whole board must stay in sight, further out
ALIGNED_SPIN_DEG = 15.0    # spin about the viewing axis when the board only fits aligned


def closest_plan(plan_at, distance_m: float, want: int):
    """``plan_at(distance)`` -> (poses, notes) at ``distance_m``, then at the ``CLOSER``
    distances in turn until ``want`` poses are planned (a small arm, a far target).
    Returns the plan with the most poses (the farthest of equals), its distance, and how
    many poses the asked distance gave."""
    best, used, first = None, distance_m, 0
    for factor in (1.0, *CLOSER):
        plan = plan_at(distance_m * factor)
        if factor == 1.0:
            first = len(plan[0])
        if best is None or len(plan[0]) > len(best[0]):
            best, used = plan, distance_m * factor
        if len(best[0]) >= want:
            break
    return best, used, first


def reachable_views(config: RigConfig, count: int, distance_m: float, max_tilt_deg: float,
                    seed: int, label: str, model: KinematicModel | None = None
                    ) -> tuple[list[np.ndarray], list[str]]:
    """``plan_target_views`` at ``distance_m`` or closer (``closest_plan``), keeping the
    plan with the most views. Fewer than ``MIN_VIEWS`` is refused here, before any
    motion."""
    (poses, notes), used, first = closest_plan(
        lambda d: plan_target_views(config, count, d, max_tilt_deg, seed, model=model),
        distance_m, count)
    if used != distance_m:
        notes = [f"{label}s: only {first} "
                 f"of {count} views reachable at {distance_m:.2f} m; planned at {used:.2f} m "
                 f"instead ({len(poses)} views)"]
    if len(poses) < MIN_VIEWS:
        raise SolveError(f"{label}s: only {len(poses)} of {count} views of the target are "
                         f"reachable at {distance_m:.2f} m or closer (down to "
                         f"{distance_m * CLOSER[-1]:.2f} m) within the soft limits; move the "
                         "target within the arm's reach or change view_distance_m")
    return poses, notes


# A ChArUco marker is decoded reliably when each of its cells (its bits and their black
# border) spans at least this many pixels, seen square-on. Measured on the simulated camera
# (JPEG, blur 0.3-1.2 px, views tilted up to 35 deg; random worlds 99500-99513, both
# mountings): from 3.6 px every view was found, with at least 92 % of its corners; at
# 2.4 px one blurred view in five was lost, and those found kept about half their corners.
# OpenCV samples a marker at 4 px per cell (``perspectiveRemovePixelPerCell``). Applied to
# the board views of a head beside the arm only (``planning_e2h.board_views``): with the head
# on the flange, views planned nearer gave three random worlds slightly worse arm models.
MIN_MARKER_CELL_PX = 3.5


def marker_cell_px(config: RigConfig, K: np.ndarray, distance_m: float) -> float:
    """The pixels a ChArUco marker's cell spans at ``distance_m``, seen square-on (pinhole
    ``K``, the smaller focal length); infinite for a checkerboard, which has no markers."""
    tg = config.target
    if not is_charuco(tg):
        return math.inf
    cells = dictionary(tg.dictionary).markerSize + 2  # the bits and their black border
    return min(K[0, 0], K[1, 1]) * tg.marker_mm / 1000.0 / (cells * distance_m)


def resolved_distance(config: RigConfig, K: np.ndarray, distance_m: float
                      ) -> tuple[float, str | None]:
    """``distance_m``, or nearer when the board's markers would be too small to decode
    there (under ``MIN_MARKER_CELL_PX`` per cell), with a note saying so (None when
    unchanged)."""
    px = marker_cell_px(config, K, distance_m)
    if px >= MIN_MARKER_CELL_PX:
        return distance_m, None
    farthest = distance_m * px / MIN_MARKER_CELL_PX
    return farthest, (f"the board's {config.target.marker_mm:g} mm markers span {px:.1f} px "
                      f"per cell at {distance_m:.2f} m, too few to decode: planned from "
                      f"{farthest:.2f} m, where they span {MIN_MARKER_CELL_PX:g}")


def fit_distance(config: RigConfig, K: np.ndarray, margin: float = 0.03) -> float:
    """The nearest viewing distance at which the board's corner grid, seen square-on and
    aligned with the image, fits inside ``margin`` of the image's edges (pinhole ``K``);
    for a ChArUco board, at which the share of it that ``board_visible`` needs does."""
    tg = config.target
    span_x, span_y = (tg.cols - 2) * tg.square_mm / 1000.0, (tg.rows - 2) * tg.square_mm / 1000.0
    w, h = config.devices.camera.width, config.devices.camera.height
    usable = 1.0 - 2.0 * margin
    aligned = max(span_x * K[0, 0] / (w * usable), span_y * K[1, 1] / (h * usable))
    crossed = max(span_y * K[0, 0] / (w * usable), span_x * K[1, 1] / (h * usable))
    # a ChArUco board needs only a share of its corners in view (``board_visible``)
    return min(aligned, crossed) * (math.sqrt(CHARUCO_MIN_SHARE) if is_charuco(tg) else 1.0)


def aligned_spin(config: RigConfig) -> dict:
    """``plan_target_views`` keywords that keep the board's longer side along the image's
    longer side, turned up to ``ALIGNED_SPIN_DEG``: for a board that fits the image only
    so."""
    T_base_target, _ = target_centre(config)
    tg, cam = config.target, config.devices.camera
    along = (tg.cols >= tg.rows) == (cam.width >= cam.height)
    return {"up_axis": T_base_target[:3, 1 if along else 0], "max_spin_deg": ALIGNED_SPIN_DEG}


def visible_views(config: RigConfig, count: int, distance_m: float, max_tilt_deg: float,
                  seed: int, label: str, K: np.ndarray, model: KinematicModel | None = None
                  ) -> tuple[list[np.ndarray], list[str]]:
    """Up to ``count`` reachable views in which the camera (``K``, arm ``model``, the
    nominal one when None) sees the whole board: planned at ``distance_m`` unless the
    board cannot fit in the image from there (a large board, a long lens), then further
    out; when too few are reachable, at the other distances of ``FARTHER`` and ``CLOSER``
    (never nearer than the board fits), keeping the plan with the most views. Fewer than
    ``MIN_VIEWS`` is refused here."""
    model = arm_model(config, model)
    nearest = fit_distance(config, K)
    start = max(distance_m, nearest)
    ladder = [start] + [d for d in sorted({start * f for f in (*FARTHER, *CLOSER)},
                                          key=lambda d: abs(d - start)) if d >= nearest]
    aligned = aligned_spin(config)
    best: tuple[list, float] = ([], start)
    reached = 0
    for d in ladder:
        for spin in ({}, aligned):  # free spin first; aligned when that loses the board
            poses, _ = plan_target_views(config, 2 * count, d, max_tilt_deg, seed,
                                         model=model, **spin)
            reached = max(reached, len(poses))
            seen = [q for q in poses if board_visible(config, model, q, K)][:count]
            if len(seen) > len(best[0]):
                best = (seen, d)
            if len(seen) >= count:
                break
        if len(best[0]) >= count:
            break
    poses, used = best
    notes = []
    if abs(used - distance_m) > 1e-9:
        notes.append(f"{label}s: planned at {used:.2f} m instead of {distance_m:.2f} m "
                     f"({len(poses)} of {count} views with the whole board in sight; the "
                     f"board fits the image from {nearest:.2f} m)")
    if reached < MIN_VIEWS:
        raise SolveError(f"{label}s: only {reached} of {count} views of the target are "
                         f"reachable at {min(ladder):.2f}-{max(ladder):.2f} m within the soft "
                         "limits; move the target within the arm's reach or change "
                         "view_distance_m")
    if len(poses) < MIN_VIEWS:
        raise SolveError(
            f"{label}s: only {len(poses)} of {count} views show the whole board "
            f"({(config.target.cols - 2) * config.target.square_mm:.0f} x "
            f"{(config.target.rows - 2) * config.target.square_mm:.0f} mm of corners; with "
            f"this lens it fits the image from {nearest:.2f} m) at a reachable distance "
            f"({min(ladder):.2f}-{max(ladder):.2f} m tried); move the target, use a smaller "
            "board, or change view_distance_m")
    return poses, notes


def view_steps(config: RigConfig, count: int, distance_m: float, max_tilt_deg: float,
               seed: int, label: str, kind: str, settle_s: float,
               K: np.ndarray | None = None, arm: PlanningArm | None = None) -> list:
    """Steps visiting ``count`` planned views of the target (head at home first when there
    is a head), each settled and captured, then back to the arm's home; skipped views are
    reported as notes. With intrinsics ``K`` every view keeps the whole board in sight
    (``visible_views``), else views are only checked for reach (``reachable_views``).
    ``arm``: the model planned with (``planning_arm``; nominal when None), noted."""
    model = arm.model if arm is not None else None
    if K is not None:
        poses, notes = visible_views(config, count, distance_m, max_tilt_deg, seed, label, K,
                                     model)
    else:
        poses, notes = reachable_views(config, count, distance_m, max_tilt_deg, seed, label,
                                       model)
    return visit_steps(config, poses, [arm.note, *notes] if arm is not None else notes,
                       label, kind, settle_s)


def visit_steps(config: RigConfig, poses: list, notes: list[str], label: str, kind: str,
                settle_s: float) -> list:
    """The head at home (when the rig has one), ``notes``, then each pose visited,
    settled and captured (``"{label} {k}"``, of ``kind``), then the arm's home."""
    steps: list = []
    if config.devices.head is not None:
        steps.append(MoveHead(0.0, 0.0, 0.0, "head home"))
    steps += [Note(n) for n in notes]
    for k, q in enumerate(poses):
        name = f"{label} {k + 1}"
        steps += [MoveArmJoints(tuple(float(v) for v in q), name), Settle(settle_s),
                  CaptureStep(name, extra={"kind": kind})]
    steps.append(MoveArmJoints(config.devices.arm.home_rad(), "arm home"))
    return steps


def informative_views(config: RigConfig, params, K: np.ndarray, planned_q: list, n: int,
                      seed: int, model: KinematicModel | None = None
                      ) -> tuple[list[np.ndarray], list[str]]:
    """``n`` training views chosen for observability (``rigctl.calib.pose_selection``):
    candidates at 0.8, 1 and 1.25 times ``params.view_distance_m``, tilted up to
    ``params.max_tilt_deg``, every one reachable, inside the soft limits and with the whole
    board in view; the D-optimal subset together with the views already planned
    (``planned_q``), ordered for short travel, all predicted with the arm ``model`` (the
    nominal one when None). Notes report the predicted condition number against that of
    plain random views."""

    model = arm_model(config, model)
    X = nominal_flange_cam(config)
    W, _ = target_centre(config)
    notes: list[str] = []
    candidates, base = view_candidates(config, K, n, params.view_distance_m,
                                       params.max_tilt_deg, seed, model)
    if len(candidates) < n:
        notes.append(f"pose selection: only {len(candidates)} candidate views; using "
                     "random views")
        poses, more = plan_target_views(config, n, base, params.max_tilt_deg, seed,
                                        model=model)
        return poses, notes + more
    tg = config.target
    obj = target_points(tg)

    def jacobians(qs):
        return pose_selection.view_jacobians(model, X, W, qs, obj=obj, K=K)

    J_cand = jacobians(candidates)
    p = J_cand.shape[2]
    J_fixed = jacobians(planned_q).reshape(-1, p) if len(planned_q) else np.zeros((0, p))
    chosen = pose_selection.select_informative(J_cand, n, J_fixed)
    random_q, _ = plan_target_views(config, n, params.view_distance_m, params.max_tilt_deg,
                                    seed, model=model)
    cond_chosen = pose_selection.scaled_condition(np.r_[J_fixed, J_cand[chosen].reshape(-1, p)])
    cond_random = pose_selection.scaled_condition(np.r_[J_fixed,
                                                        jacobians(random_q).reshape(-1, p)])
    notes.append(f"pose selection: {n} of {len(candidates)} candidate views (D-optimal); "
                 f"predicted condition number {cond_chosen:.0f} (random views: "
                 f"{cond_random:.0f})")
    poses = [candidates[i] for i in chosen]
    start = planned_q[-1] if planned_q else poses[0]
    return [poses[i] for i in pose_selection.order_by_travel(poses, start)], notes


def view_candidates(config: RigConfig, K: np.ndarray, n: int, distance_m: float,
                    max_tilt_deg: float, seed: int, model: KinematicModel
                    ) -> tuple[list[np.ndarray], float]:
    """The candidate views of ``informative_views``: reachable, inside the soft limits,
    the whole board in view, at 0.8, 1 and 1.25 times ``distance_m`` (never nearer than
    the board fits the image), spun freely and aligned; and the base distance used."""
    candidates = []
    nearest = fit_distance(config, K)
    base = max(distance_m, nearest)  # never nearer than the board fits
    for k, factor in enumerate((0.8, 1.0, 1.25)):
        if base * factor < nearest:
            continue
        for spin in ({}, aligned_spin(config)):
            qs, _ = plan_target_views(config, 3 * n, base * factor, max_tilt_deg,
                                      seed + 17 * k, model=model, **spin)
            candidates += [q for q in qs if board_visible(config, model, q, K)]
    return candidates, base


# A ChArUco board may run off the image: a view needs this share of its corners, and at
# least CHARUCO_MIN_CORNERS, inside the margin (each corner is identified on its own)
CHARUCO_MIN_SHARE = 0.4
CHARUCO_MIN_CORNERS = 12


def board_visible(config: RigConfig, model: KinematicModel, q, K: np.ndarray,
                  margin: float = 0.03, station: np.ndarray | None = None) -> bool:
    """Does the camera at joints q (arm ``model``) see every board corner, inside a
    margin? A ChArUco board needs only ``CHARUCO_MIN_SHARE`` of them (and
    ``CHARUCO_MIN_CORNERS``). ``station``: the camera of a head beside the arm re-aimed,
    seen from the camera at home (``robot_stations``)."""
    return bool(boards_visible(config, model, np.asarray(q, float)[None], K, margin,
                               station)[0])


def boards_visible(config: RigConfig, model: KinematicModel, Q: np.ndarray, K: np.ndarray,
                   margin: float = 0.03, station: np.ndarray | None = None) -> np.ndarray:
    """``board_visible`` at each configuration of ``Q`` (N, 6), at once: (N,) bools."""
    tg = config.target
    X, W = nominal_frames(config)
    T_cam_target = robot.cam_target_batch(model, X, W, Q, eye_to_hand(config))
    if station is not None:
        T_cam_target = inv_T(station) @ T_cam_target
    ok = np.ones(len(Q), bool)
    if eye_to_hand(config):
        ok &= faces_camera_batch(config, T_cam_target)
    pts = target_points(tg)
    cam = np.einsum("nij,pj->npi", T_cam_target[:, :3, :3], pts) + T_cam_target[:, None, :3, 3]
    partial = is_charuco(tg)
    front = cam[..., 2] >= 0.1
    if not partial:
        ok &= np.all(front, axis=1)
    px = np.einsum("ij,npj->npi", K, cam)
    px = px[..., :2] / np.where(front, px[..., 2], 1.0)[..., None]
    w, h = config.devices.camera.width, config.devices.camera.height
    inside = front & (px[..., 0] > margin * w) & (px[..., 0] < (1 - margin) * w) & \
        (px[..., 1] > margin * h) & (px[..., 1] < (1 - margin) * h)
    if partial:
        return ok & (inside.sum(axis=1) >= max(CHARUCO_MIN_SHARE * len(pts), CHARUCO_MIN_CORNERS))
    return ok & np.all(inside, axis=1)


# A board on the flange turned further than this from the fixed camera's line of sight
# is not planned: the sweeps of random world 300003 (ChArUco, UR10) lost 5 of 47 views
# at +-60 deg of joints 3-5, where the board was seen edge-on
MAX_FACING_DEG = 55.0


def faces_camera(config: RigConfig, T_cam_target: np.ndarray) -> bool:
    """Is the board's normal within ``MAX_FACING_DEG`` of the line of sight to its centre
    (the board's z, into the board, pointing away from the camera)?"""
    return bool(faces_camera_batch(config, np.asarray(T_cam_target)[None])[0])


def faces_camera_batch(config: RigConfig, T_cam_target: np.ndarray) -> np.ndarray:
    """``faces_camera`` of each of N poses ``T_cam_target`` (N, 4, 4): (N,) bools."""
    centre = T_cam_target[:, :3, :3] @ board_centre(config) + T_cam_target[:, :3, 3]
    ray = centre / np.linalg.norm(centre, axis=1)[:, None]
    return np.sum(ray * T_cam_target[:, :3, 2], axis=1) >= math.cos(math.radians(MAX_FACING_DEG))


def planning_K(config: RigConfig, given: dict | None) -> np.ndarray:
    """Intrinsics for planning: given, else the latest active-camera result, else a
    60-degree field of view guess."""
    try:
        return camera_model(intrinsics_from(config, given, allow_settings_change=True))[0]
    except ConfigError:
        w, h = config.devices.camera.width, config.devices.camera.height
        f = w / (2 * math.tan(math.radians(30)))
        return camera_matrix(f, f, w / 2, h / 2)


def visible_range(config: RigConfig, model: KinematicModel, q_base, joint: int,
                  K: np.ndarray, max_deg: float = 60.0, resolution_deg: float = 1.0
                  ) -> tuple[float, float]:
    """The interval of offsets (deg, lo <= 0 <= hi) of one joint from ``q_base`` over which
    the camera (arm ``model``) keeps the whole board in view, the joint stays inside its soft
    limits and the arm clear of the target plane (``clearance_m``), scanned outwards from 0
    in ``resolution_deg`` steps up to ``max_deg``."""
    limits = config.devices.arm.joint_limits_rad()[joint]
    # every offset the scan may test, each side outwards from 0, checked in one batch
    steps = []
    reached = 0.0
    while reached + resolution_deg <= max_deg + 1e-9:
        reached += resolution_deg
        steps.append(reached)
    offsets = [0.0] + [sign * d for sign in (-1.0, 1.0) for d in steps]
    Q = np.repeat(np.asarray(q_base, float)[None], len(offsets), axis=0)
    Q[:, joint] += np.radians(offsets)
    allowed = (limits[0] <= Q[:, joint]) & (Q[:, joint] <= limits[1])
    allowed &= boards_visible(config, model, Q, K)
    allowed &= clearances_m(config, model, Q) >= MIN_CLEARANCE_M
    if not allowed[0]:
        return 0.0, 0.0
    ends = []
    for side, sign in enumerate((-1.0, 1.0)):
        run = allowed[1 + side * len(steps):1 + (side + 1) * len(steps)]
        n = len(run) if run.all() else int(np.argmin(run))  # up to the first refused
        ends.append(sign * (steps[n - 1] if n else 0.0))
    return ends[0], ends[1]


def spread_offsets(lo: float, hi: float, steps: int, min_deg: float = 2.0) -> list[float]:
    """``steps`` offsets (deg) spread over [lo, hi], shared between the two sides in
    proportion to their length (a side shorter than ``min_deg`` gets none), evenly spaced
    out to each end, rounded to 0.5 deg; offsets closer to 0 than ``min_deg`` are dropped."""
    sides = [side for side in (hi, lo) if abs(side) >= min_deg]
    if not sides:
        return []
    total = sum(abs(side) for side in sides)
    counts = [max(1, round(steps * abs(side) / total)) for side in sides]
    while sum(counts) > steps and max(counts) > 1:
        counts[counts.index(max(counts))] -= 1
    offsets = []
    for side, count in zip(sides, counts, strict=True):
        for k in range(1, count + 1):
            off = round(2 * side * k / count) / 2
            if abs(off) >= min_deg and off not in offsets:
                offsets.append(off)
    return offsets


@dataclass
class SweepPlan:
    """One joint's sweep: its base configuration, the offsets (deg) and the range (deg) in
    which the board stays in view."""

    joint: int
    q_base: np.ndarray
    offsets: list[float]
    visible: tuple[float, float]


def plan_sweeps(config: RigConfig, bases: list[np.ndarray], K: np.ndarray, steps: int,
                max_deg: float = 60.0, model: KinematicModel | None = None
                ) -> tuple[dict[int, SweepPlan], list[str]]:
    """Single-joint sweeps, last joint first. Each joint starts from the configuration of
    ``bases`` in which the board stays in view over the widest range of that joint (the
    first wins ties), and takes ``steps`` offsets spread over that range (up to
    +-``max_deg``) out to both ends: the axis is located to sigma / (angle swept), so the
    widest sweep the view allows is the most informative. Link-by-link and the axis lines
    need only joint j to move within a sweep, not a base common to all sweeps. Predicted
    with the arm ``model`` (the nominal one when None)."""
    model = arm_model(config, model)
    plan, notes = {}, []
    for j in range(5, -1, -1):
        ranges = [visible_range(config, model, q, j, K, max_deg) for q in bases]
        best = max(range(len(bases)), key=lambda k: ranges[k][1] - ranges[k][0])
        lo, hi = ranges[best]
        offsets = spread_offsets(lo, hi, steps)
        if hi - lo < 5.0 or len(offsets) < 2:
            notes.append(f"joint {j + 1}: the board stays in view only from {lo:+g} to "
                         f"{hi:+g} deg; sweep skipped")
            continue
        plan[j] = SweepPlan(j, np.asarray(bases[best], float), offsets, (lo, hi))
        notes.append(f"joint {j + 1}: from base {best + 1} of {len(bases)}, board in view "
                     f"from {lo:+g} to {hi:+g} deg; sweep "
                     f"{', '.join(f'{o:+g}' for o in offsets)} deg")
    return plan, notes


# -- poses the operator chooses (``poses_file``) and what they determine -----------------

# A pose set whose scaled identification Jacobian has a condition number above this
# cannot determine the model: some combination of its parameters moves no board corner
# in any of the views (the views leave it free).
UNDETERMINED_CONDITION = 1e4
PLANNING_PIXEL_SIGMA = 0.3  # px: the corner noise assumed when predicting uncertainty
MAX_FILE_POSES = 500
_SAME_JOINT_RAD = 1e-4  # joints closer than this in every pose count as not moved


def load_pose_file(path: str | Path, config: RigConfig, min_poses: int = 1
                   ) -> list[np.ndarray]:
    """The joint configurations (rad) of a pose file: a YAML list with one list of six
    joint angles in degrees per pose (``rigctl runs poses`` writes one from any run).
    Each is checked against the rig file's soft limits and kept clear of the target
    plane (``clearance_m``) before anything moves; ``ConfigError`` names the file, the
    line and the pose (1-based) otherwise."""
    arm = config.devices.arm
    if arm is None:
        raise ConfigError(f"{path}: a pose file needs devices.arm in the rig file")
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the pose file "
                          f"({getattr(exc, 'strerror', None) or exc})") from None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        # where the broken construct began (a pose's "["), else where parsing stopped
        mark = getattr(exc, "context_mark", None) or getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        raise ConfigError(f"{where}: not a YAML pose file "
                          f"({getattr(exc, 'problem', None) or 'malformed'})") from None
    if not isinstance(data, list) or not data:
        raise ConfigError(f"{path}: expected a YAML list of poses, each a list of 6 joint "
                          "angles in degrees (as `rigctl runs poses` writes)")
    if len(data) > MAX_FILE_POSES:
        raise ConfigError(f"{path}: {len(data)} poses; at most {MAX_FILE_POSES}")
    if len(data) < min_poses:
        raise ConfigError(f"{path}: {len(data)} poses; the procedure needs at least "
                          f"{min_poses}")
    limits = arm.joint_limits_rad()
    model = nominal_ur(arm.model)
    poses = []
    for k, entry in enumerate(data):
        where = f"{path}:{node.value[k].start_mark.line + 1}: pose {k + 1}"
        poses.append(_pose_entry(config, model, limits, entry, where))
    return poses


def _pose_entry(config: RigConfig, model: KinematicModel, limits, entry, where: str
                ) -> np.ndarray:
    """One pose file entry in radians, checked (``load_pose_file``)."""
    numbers = isinstance(entry, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in entry)
    if not numbers or len(entry) != 6:
        raise ConfigError(f"{where}: expected a list of 6 joint angles in degrees, got "
                          f"{str(entry)[:80]}")
    if not all(math.isfinite(v) for v in entry):
        raise ConfigError(f"{where}: joint angles must be finite numbers (degrees)")
    q = np.radians(np.asarray(entry, float))
    for i, (value, (lo, hi)) in enumerate(zip(q, limits, strict=True)):
        if not lo <= value <= hi:
            raise ConfigError(f"{where}: joint {i + 1} at {math.degrees(value):.2f} deg is "
                              f"outside the soft limits [{math.degrees(lo):.1f}, "
                              f"{math.degrees(hi):.1f}] deg (devices.arm.joint_limits_deg)")
    clearance = clearance_m(config, model, q)
    if clearance < MIN_CLEARANCE_M:
        raise ConfigError(f"{where}: the arm would come {100 * clearance:.1f} cm from the "
                          f"target plane (at least {100 * MIN_CLEARANCE_M:.0f} cm on the "
                          "camera's side; nominal model)")
    return q


def pose_file_record(path: str | Path, poses: list[np.ndarray]) -> dict[str, Any]:
    """What ``inputs.json`` keeps of a pose file: its path, digest and the poses (deg)."""
    path = Path(path)
    return {"path": str(path.resolve()),
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "poses_deg": [np.degrees(q).round(6).tolist() for q in poses]}


def pose_file_steps(config: RigConfig, poses: list[np.ndarray], kind: str, settle_s: float,
                    notes: list[str]) -> list:
    """Steps visiting the poses of a pose file in its order (``notes`` first, logged
    before anything moves; then the head at home when there is a head), each settled and
    captured as ``pose N`` of ``kind``, then back to the arm's home."""
    steps: list = [Note(n) for n in notes]
    if config.devices.head is not None:
        steps.append(MoveHead(0.0, 0.0, 0.0, "head home"))
    for k, q in enumerate(poses):
        name = f"pose {k + 1}"
        steps += [MoveArmJoints(tuple(float(v) for v in q), name), Settle(settle_s),
                  CaptureStep(name, extra={"kind": kind, "pose": k + 1})]
    steps.append(MoveArmJoints(config.devices.arm.home_rad(), "arm home"))
    return steps


def poses_out_of_view(config: RigConfig, model: KinematicModel, poses, K: np.ndarray
                      ) -> list[int]:
    """The poses (1-based) at which the nominal mount and target put part of the board
    outside the image (``board_visible``)."""
    return [k + 1 for k, q in enumerate(poses) if not board_visible(config, model, q, K)]


def identifiability(config: RigConfig, qs, K: np.ndarray, model: KinematicModel,
                    links: bool, workspace, X: np.ndarray | None = None,
                    W: np.ndarray | None = None, sigma_px: float = PLANNING_PIXEL_SIGMA
                    ) -> dict[str, Any]:
    """How well the views at ``qs`` determine the model: ``T_flange_cam`` and
    ``T_base_target`` (``X``, ``W``; the rig file's nominal ones when None), with
    ``links`` the arm's identifiable link parameters too (``robot.identifiable_mask``).
    From the board corners' pixel Jacobian (``pose_selection.view_jacobians``): the
    condition number of its scaled columns, and with corner noise ``sigma_px`` the
    predicted 1-sigma of the camera's position over the ``workspace`` configurations
    (median and max, mm; None when the views leave a direction free). ``free`` names
    the parameters the weakest direction moves most."""
    X = nominal_flange_cam(config) if X is None else np.asarray(X, float)
    W = target_centre(config)[0] if W is None else np.asarray(W, float)
    mask = robot.identifiable_mask(model) if links else robot.frames_only_mask(model)
    names = robot._pack(model, X, W, mask, True)[1]
    J = pose_selection.view_jacobians(model, X, W, list(qs), mask, obj=target_points(
        config.target), K=K)
    J = J.reshape(-1, J.shape[2])
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    _, sv, vt = np.linalg.svd(J / scale, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    determined = cond < UNDETERMINED_CONDITION
    weakest = np.abs(vt[-1])
    free = [names[i] for i in np.argsort(weakest)[::-1][:4] if weakest[i] > 0.2]
    sigma_mm = None
    if determined:
        cov = sigma_px ** 2 * np.linalg.inv((J / scale).T @ (J / scale)) / np.outer(scale,
                                                                                   scale)
        sig = robot.camera_position_sigma(model, X, W, names, cov, list(workspace))
        norm = 1000 * np.linalg.norm(sig, axis=1)
        sigma_mm = {"median": float(np.median(norm)), "max": float(norm.max()),
                    "configurations": len(norm)}
    return {"views": len(qs), "condition_number": cond if math.isfinite(cond) else None,
            "determined": determined, "camera_position_sigma_mm": sigma_mm,
            "weakest_direction": free}


def d_optimal_views(config: RigConfig, K: np.ndarray, n: int, distance_m: float,
                    max_tilt_deg: float, seed: int, model: KinematicModel, links: bool
                    ) -> list[np.ndarray]:
    """The planner's D-optimal choice of ``n`` views (``view_candidates``,
    ``pose_selection.select_informative``) for the same model as ``identifiability``."""
    candidates, _ = view_candidates(config, K, n, distance_m, max_tilt_deg, seed, model)
    if len(candidates) < n:
        return []
    mask = robot.identifiable_mask(model) if links else robot.frames_only_mask(model)
    J = pose_selection.view_jacobians(model, nominal_flange_cam(config),
                                      target_centre(config)[0], candidates, mask,
                                      obj=target_points(config.target), K=K)
    return [candidates[i] for i in pose_selection.select_informative(J, n)]


def pose_set_report(config: RigConfig, qs, K: np.ndarray, model: KinematicModel, links: bool,
                    distance_m: float, max_tilt_deg: float, seed: int,
                    X: np.ndarray | None = None, W: np.ndarray | None = None,
                    sigma_px: float = PLANNING_PIXEL_SIGMA) -> dict[str, Any]:
    """The identifiability of the operator's pose set ``qs`` against the planner's
    D-optimal plan of as many views (``d_optimal_views``), the camera's predicted
    uncertainty compared over the configurations of both; ``warning`` says when the set
    cannot determine the model (None otherwise)."""
    qs = [np.asarray(q, float) for q in qs]
    reference = d_optimal_views(config, K, len(qs), distance_m, max_tilt_deg, seed, model,
                                links)
    workspace = qs + reference
    own = identifiability(config, qs, K, model, links, workspace, X, W, sigma_px)
    best = identifiability(config, reference, K, model, links, workspace, X, W, sigma_px) \
        if reference else None
    return {**own, "d_optimal": best, "sigma_px": sigma_px,
            "warning": identifiability_warning(own, best, qs)}


def pose_set_note(report: dict[str, Any]) -> str:
    """One line on a pose set's identifiability (``pose_set_report``) for plans and
    summaries: its warning, or its numbers against the D-optimal plan's."""
    if report["warning"]:
        return "WARNING: " + report["warning"]
    sig, best = report["camera_position_sigma_mm"], report["d_optimal"]
    text = (f"{report['views']} views, condition number {report['condition_number']:.0f}, "
            f"camera position 1-sigma {sig['median']:.2f} mm median, {sig['max']:.2f} mm "
            f"max (predicted, {report['sigma_px']:.2f} px corners)")
    if best and best["camera_position_sigma_mm"]:
        text += (f"; the D-optimal plan of {best['views']} views: "
                 f"{best['condition_number']:.0f}, "
                 f"{best['camera_position_sigma_mm']['median']:.2f} mm")
    return text


def identifiability_warning(own: dict, best: dict | None, qs) -> str | None:
    """The operator's warning when a pose set cannot determine the model, naming why."""
    if own["determined"]:
        return None
    moved = [j + 1 for j in range(6) if np.ptp([q[j] for q in qs]) > _SAME_JOINT_RAD]
    why = ("every pose differs from the others in joint "
           f"{moved[0]} only" if len(moved) == 1 else
           "the poses do not move the arm" if not moved else
           f"the poses vary joints {', '.join(map(str, moved))} in too few directions")
    cond = own["condition_number"]
    ref = f"; the D-optimal plan of {best['views']} views: {best['condition_number']:.0f}" \
        if best and best["condition_number"] else ""
    return (f"the pose set cannot determine the model: {why} (condition number "
            f"{'infinite' if cond is None else f'{cond:.3g}'}{ref}); the views leave "
            f"{', '.join(own['weakest_direction']) or 'a direction'} free: add poses that "
            "turn the camera about other axes")


def pose_file_text(run, exclude=()) -> str:
    """A pose file (``load_pose_file``) of the joints each capture of the recorded
    ``run`` (a ``RunDirectory``) was taken at, as the arm reported them, in capture
    order; captures in ``exclude`` or without arm joints are left out. Each pose names
    its capture in a comment. ``ConfigError`` when no capture has arm joints."""
    lines = []
    for capture in run.captures():
        q = (capture.meta.get("arm") or {}).get("q")
        if capture.index in exclude or not q or len(q) != 6:
            continue
        angles = ", ".join(f"{math.degrees(v):.4f}" for v in q)
        label = " ".join(str(capture.meta.get("label", "")).split())
        lines.append(f"- [{angles}]  # capture {capture.index:03d}: {label}")
    if not lines:
        raise ConfigError(f"{run.captures_dir}: no capture with the arm's joints; nothing "
                          "to write")
    head = (f"# {len(lines)} poses of run {run.run_id}: joint angles in degrees, one list "
            "of six per pose\n# (rigctl runs poses; use with --param poses_file=THIS_FILE)\n")
    return head + "\n".join(lines) + "\n"
