"""Shared pieces of the robot procedures: intrinsics, board poses, visibility, planning."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.calib.board import board_points, orient_to_prediction
from rigctl.calib.extrinsic import estimate_pose
from rigctl.config import RigConfig
from rigctl.errors import ConfigError
from rigctl.geometry.camera import camera_matrix
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from rigctl.geometry.transforms import inv_T
from rigctl.records import RecordIndex, RunDirectory

from .camera_settings import check_settings
from .planning import (
    MIN_CLEARANCE_M,
    board_visible,
    clearance_m,
    nominal_flange_cam,
    target_centre,
)


def intrinsics_from(config: RigConfig, given: dict | None,
                    allow_settings_change: bool = False) -> dict[str, Any]:
    """``given`` (fx, fy, cx, cy, distortion, optionally sigma and settings) or the result
    of the latest accepted (or succeeded) ``active-camera`` run of this rig, with its
    1-sigma and the camera settings it was calibrated at (``check_settings`` refuses them
    for another size or focus). Read when a run is planned, never while solving
    (``Procedure.resolve_inputs``)."""
    return check_settings(_intrinsics(config, given), config, allow_settings_change)


def _intrinsics(config: RigConfig, given: dict | None) -> dict[str, Any]:
    if given:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in given]
        if missing:
            raise ConfigError(f"intrinsics parameter lacks {missing}")
        out = {"fx": given["fx"], "fy": given["fy"], "cx": given["cx"], "cy": given["cy"],
               "distortion": list(given.get("distortion", [0.0] * 5)), "source": "parameter"}
        if "sigma" in given:
            out["sigma"] = {k: float(given["sigma"][k]) for k in ("fx", "fy", "cx", "cy")}
        if given.get("settings"):
            out["settings"] = dict(given["settings"])
        return out
    row = RecordIndex(config.database_url()).latest("active-camera", config.name)
    if row is None:
        raise ConfigError(f"{config.name}: no intrinsics: run active-camera first, or give "
                          "--param intrinsics='{fx: ..., fy: ..., cx: ..., cy: ...}'")
    result = RunDirectory(row["run_dir"]).result()
    out = {k: result[k] for k in ("fx", "fy", "cx", "cy")} | {
        "distortion": result.get("distortion", [0.0] * 5), "source": f"run {row['run_id']}"}
    if "sigma" in result:
        out["sigma"] = {k: float(result["sigma"][k]) for k in ("fx", "fy", "cx", "cy")}
    if result.get("camera_settings"):
        out["settings"] = result["camera_settings"]
    return out


def controller_model(ctx) -> tuple[KinematicModel | None, str | None]:
    """The controller's own DH table and hash, as the run recorded them (``versions.json``
    of the run directory, so a re-solve reads the same), or (None, None)."""
    versions = ctx.run.versions() or {}
    arm = (versions.get("devices") or {}).get("arm") or {}
    k = arm.get("controller_kinematics")
    if not k:
        return None, None
    model = KinematicModel(np.array(k["d"]), np.array(k["a"]), np.array(k["alpha"]),
                           theta_offset=np.array(k["theta"]))
    return model, k.get("hash")


def default_prior_sigma(intr: dict) -> dict[str, float]:
    """The 1-sigma given to intrinsics that came without one (a ``--param intrinsics``
    without ``sigma``): a rough guess, 0.5 % on the focal lengths and 10 px on the centre,
    so that the board views decide."""
    return {"fx": 0.005 * intr["fx"], "fy": 0.005 * intr["fy"], "cx": 10.0, "cy": 10.0}


def camera_model(intr: dict) -> tuple[np.ndarray, np.ndarray]:
    """K and the distortion coefficients of resolved intrinsics (``intrinsics_from``)."""
    return (camera_matrix(intr["fx"], intr["fy"], intr["cx"], intr["cy"]),
            np.asarray(intr["distortion"], float))


def board_observations(ctx, intr: dict) -> list[dict]:
    """Per capture with the board found: label, kind, joints, corners and T_cam_target."""
    tg = ctx.config.target
    obj = board_points(tg.rows, tg.cols, tg.square_mm / 1000.0)
    K, dist = camera_model(intr)
    out = []
    for capture in ctx.captures():
        if capture.image_path is None or "arm" not in capture.meta:
            continue
        corners = capture.board_corners(tg.rows, tg.cols)
        extra = capture.meta.get("extra", {})
        if corners is None:
            out.append({"label": capture.meta["label"], "kind": extra.get("kind"),
                        "found": False})
            continue
        q = np.asarray(capture.meta["arm"]["q"], float)
        corners = orient_to_prediction(corners, _predicted_corners(ctx.config, q, obj, K),
                                       tg.rows, tg.cols)
        pose = estimate_pose(obj, corners, K, dist)
        out.append({"label": capture.meta["label"], "kind": extra.get("kind"),
                    "joint": extra.get("joint"), "found": True,
                    "q": q, "corners": corners,
                    "C": pose.T_cam_target, "rms_px": pose.rms_px, "pnp": pose.method})
    return out


def _predicted_corners(config: RigConfig, q, obj: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Where the nominal arm, head mount and target pose put the board's corners (pixels,
    no distortion): enough to tell a symmetric board's half and quarter turns apart."""
    T_base_target, _ = target_centre(config)
    T_cam_target = inv_T(nominal_ur(config.devices.arm.model).fk(q)
                         @ nominal_flange_cam(config)) @ T_base_target
    cam = (T_cam_target[:3, :3] @ obj.T).T + T_cam_target[:3, 3]
    px = (K @ cam.T).T
    return px[:, :2] / px[:, 2:3]


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
    the nominal camera keeps the whole board in view, the joint stays inside its soft
    limits and the arm clear of the target plane (``clearance_m``), scanned outwards from 0
    in ``resolution_deg`` steps up to ``max_deg``."""
    limits = config.devices.arm.joint_limits_rad()[joint]

    def allowed(q) -> bool:
        return (limits[0] <= q[joint] <= limits[1] and board_visible(config, model, q, K)
                and clearance_m(config, model, q) >= MIN_CLEARANCE_M)

    if not allowed(np.asarray(q_base, float)):
        return 0.0, 0.0
    ends = []
    for sign in (-1.0, 1.0):
        reached = 0.0
        while reached + resolution_deg <= max_deg + 1e-9:
            q = np.array(q_base, float)
            q[joint] += math.radians(sign * (reached + resolution_deg))
            if not allowed(q):
                break
            reached += resolution_deg
        ends.append(sign * reached)
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
                max_deg: float = 60.0) -> tuple[dict[int, SweepPlan], list[str]]:
    """Single-joint sweeps, last joint first. Each joint starts from the configuration of
    ``bases`` in which the board stays in view over the widest range of that joint (the
    first wins ties), and takes ``steps`` offsets spread over that range (up to
    +-``max_deg``) out to both ends: the axis is located to sigma / (angle swept), so the
    widest sweep the view allows is the most informative. Link-by-link and the axis lines
    need only joint j to move within a sweep, not a base common to all sweeps."""
    model = nominal_ur(config.devices.arm.model)
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


def export_model(model: KinematicModel, X, W, uncertainty: dict, heldout: dict) -> dict:
    """The export format of the robot issue."""
    return {"convention": "A_i = Rz(theta_i + theta_offset) Tz(d) Tx(a) Rx(alpha) Ry(beta)",
            "units": {"length": "m", "angle": "rad"}, "links": model.links(),
            "T_base_link0": model.T_base_link0.tolist(), "T_flange_cam": np.asarray(X).tolist(),
            "T_base_target": np.asarray(W).tolist(), "uncertainty": uncertainty,
            "heldout": heldout}

