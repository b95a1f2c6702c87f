"""Shared pieces of the robot procedures: intrinsics, board poses, visibility, planning."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rigctl.calib.board import board_points, detect_board
from rigctl.calib.extrinsic import estimate_pose
from rigctl.config import RigConfig
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from rigctl.geometry.transforms import inv_T
from rigctl.records import RecordIndex, RunDirectory

from .planning import nominal_flange_cam, target_centre


def intrinsics_from(config: RigConfig, given: dict | None) -> dict[str, Any]:
    """``given`` (fx, fy, cx, cy, distortion) or the result of the latest accepted (or
    succeeded) ``active-camera`` run of this rig."""
    if given:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in given]
        if missing:
            raise SolveError(f"intrinsics parameter lacks {missing}")
        return {"fx": given["fx"], "fy": given["fy"], "cx": given["cx"], "cy": given["cy"],
                "distortion": list(given.get("distortion", [0.0] * 5)), "source": "parameter"}
    row = RecordIndex(config.database_url()).latest("active-camera", config.name)
    if row is None:
        raise SolveError("no intrinsics: run active-camera first, or give "
                         "--param intrinsics='{fx: ..., fy: ..., cx: ..., cy: ...}'")
    result = RunDirectory(row["run_dir"]).result()
    return {k: result[k] for k in ("fx", "fy", "cx", "cy")} | {
        "distortion": result.get("distortion", [0.0] * 5), "source": f"run {row['run_id']}"}


def camera_matrix(intr: dict) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1.0]])
    return K, np.asarray(intr["distortion"], float)


def board_observations(ctx, intr: dict) -> list[dict]:
    """Per capture with the board found: label, kind, joints, corners and T_cam_target."""
    tg = ctx.config.target
    obj = board_points(tg.rows, tg.cols, tg.square_mm / 1000.0)
    K, dist = camera_matrix(intr)
    out = []
    for capture in ctx.captures():
        if capture.image_path is None or "arm" not in capture.meta:
            continue
        corners = detect_board(capture.load_image(), tg.rows, tg.cols)
        extra = capture.meta.get("extra", {})
        if corners is None:
            out.append({"label": capture.meta["label"], "kind": extra.get("kind"),
                        "found": False})
            continue
        pose = estimate_pose(obj, corners, K, dist)
        out.append({"label": capture.meta["label"], "kind": extra.get("kind"),
                    "joint": extra.get("joint"), "found": True,
                    "q": np.asarray(capture.meta["arm"]["q"], float), "corners": corners,
                    "C": pose.T_cam_target, "rms_px": pose.rms_px, "pnp": pose.method})
    return out


def board_visible(config: RigConfig, model: KinematicModel, q, K: np.ndarray,
                  margin: float = 0.03) -> bool:
    """Does the nominal camera at joints q see every board corner, inside a margin?"""
    tg = config.target
    T_base_target, _ = target_centre(config)
    T_cam_target = inv_T(model.fk(q) @ nominal_flange_cam(config)) @ T_base_target
    pts = board_points(tg.rows, tg.cols, tg.square_mm / 1000.0)
    cam = (T_cam_target[:3, :3] @ pts.T).T + T_cam_target[:3, 3]
    if np.any(cam[:, 2] < 0.1):
        return False
    px = (K @ cam.T).T
    px = px[:, :2] / px[:, 2:3]
    w, h = config.devices.camera.width, config.devices.camera.height
    return bool(np.all((px[:, 0] > margin * w) & (px[:, 0] < (1 - margin) * w) &
                       (px[:, 1] > margin * h) & (px[:, 1] < (1 - margin) * h)))


def planning_K(config: RigConfig, given: dict | None) -> np.ndarray:
    """Intrinsics for planning: given, else the latest active-camera result, else a
    60-degree field of view guess."""
    try:
        return camera_matrix(intrinsics_from(config, given))[0]
    except SolveError:
        w, h = config.devices.camera.width, config.devices.camera.height
        f = w / (2 * math.tan(math.radians(30)))
        return np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])


def plan_sweeps(config: RigConfig, q_base, K: np.ndarray, steps: int, max_deg: float = 60.0,
                step_deg: float = 10.0) -> tuple[dict[int, list[float]], list[str]]:
    """Single-joint offsets from ``q_base``, last joint first: +-step, +-2 step, ... up to
    ``max_deg``, keeping those where the board stays in view and the joint inside its soft
    limits. Joints that move the view fast get 5 and then 2.5 degree steps."""
    model = nominal_ur(config.devices.arm.model)
    limits = config.devices.arm.joint_limits_rad()
    plan, notes = {}, []
    for j in range(5, -1, -1):
        chosen: list[float] = []
        for step in (step_deg, step_deg / 2, step_deg / 4):
            chosen = []
            for k in range(1, int(max_deg / step) + 1):
                for sign in (1.0, -1.0):
                    off = sign * k * step
                    q = np.array(q_base, float)
                    q[j] += math.radians(off)
                    if limits[j][0] <= q[j] <= limits[j][1] and \
                            board_visible(config, model, q, K):
                        chosen.append(off)
                if len(chosen) >= steps:
                    break
            if len(chosen) >= 2:
                break
        if len(chosen) < 2:
            notes.append(f"joint {j + 1}: the board leaves the view within "
                         f"{step_deg / 4:.1f} deg; sweep skipped")
            continue
        plan[j] = chosen[:steps]
    return plan, notes


def export_model(model: KinematicModel, X, W, uncertainty: dict, heldout: dict) -> dict:
    """The export format of the robot issue."""
    return {"convention": "A_i = Rz(theta_i + theta_offset) Tz(d) Tx(a) Rx(alpha) Ry(beta)",
            "units": {"length": "m", "angle": "rad"}, "links": model.links(),
            "T_base_link0": model.T_base_link0.tolist(), "T_flange_cam": np.asarray(X).tolist(),
            "T_base_target": np.asarray(W).tolist(), "uncertainty": uncertainty,
            "heldout": heldout}

