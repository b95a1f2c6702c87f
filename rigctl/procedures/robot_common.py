"""Shared pieces of the robot procedures' solves: the controller's arm model as the run
recorded it, the board observations of the captures, the export format."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from rigctl.calib.board import is_charuco, orient_to_prediction, target_points
from rigctl.calib.extrinsic import estimate_pose, stray_corners
from rigctl.config import RigConfig
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from rigctl.geometry.transforms import inv_T

from .base import CaptureStep, MoveArmJoint, MoveArmJoints, Settle
from .intrinsics import camera_model, head_geometry, intrinsics_from
from .planning import (
    controller_dh_model,
    eye_to_hand,
    load_pose_file,
    nominal_cam_target,
    planning_arm,
    pose_file_record,
)

log = logging.getLogger(__name__)
# a view whose own pose misses more than this share of its corners is not mended corner
# by corner (``_without_stray_corners``)
MAX_STRAY_SHARE = 0.25


def controller_model(ctx) -> tuple[KinematicModel | None, str | None]:
    """The controller's own DH table and hash, as the run recorded them, or (None, None):
    ``versions.json`` (read when the arm was opened for the run), else the model the run
    was planned with when that was the controller's (``inputs.json``: ``arm_model``).
    Both are in the run directory, so a re-solve reads the same. A controller that
    reported a hash without its table gives (None, hash)."""
    versions = ctx.run.versions() or {}
    arm = (versions.get("devices") or {}).get("arm") or {}
    k = arm.get("controller_kinematics")
    if not k:
        planned = ctx.inputs.get("arm_model") or {}
        k = planned.get("controller_kinematics") if planned.get("source") == "controller" \
            else None
    if not k:
        return None, arm.get("kinematics_hash")
    return controller_dh_model(k), k.get("hash") or arm.get("kinematics_hash")


def board_observations(ctx, intr: dict) -> list[dict]:
    """Per capture with the board found: label, kind, capture index, joints, corners (id
    order, NaN where not seen) and T_cam_target; per capture without: its index and the
    note saying why (a ChArUco board that is not the configured one is named there)."""
    tg = ctx.config.target
    obj = target_points(tg)
    K, dist = camera_model(intr)
    # with the head beside the arm and its geometry known, a capture's camera is seen
    # from home at its recorded head angles (``head_model``)
    geometry = head_geometry(intr) if eye_to_hand(ctx.config) else None
    out = []
    for capture in ctx.captures():
        if capture.image_path is None or "arm" not in capture.meta:
            continue
        found = capture.board_detection(tg)
        corners = found.corners
        extra = capture.meta.get("extra", {})
        if corners is None:
            if found.note and "view left out" in found.note:
                log.warning("capture %s: %s", capture.meta["label"], found.note)
            out.append({"label": capture.meta["label"], "kind": extra.get("kind"),
                        "index": capture.index, "found": False,
                        "note": found.note})
            continue
        q = np.asarray(capture.meta["arm"]["q"], float)
        head = _head_angles(capture.meta)
        if not is_charuco(tg):  # a ChArUco corner's id leaves no turn of the board open
            station = None if head is None or geometry is None else geometry.T_home_cam(head)
            predicted = _predicted_corners(ctx.config, q, obj, K, station)
            corners = orient_to_prediction(corners, predicted, tg.rows, tg.cols)
        try:
            pose = estimate_pose(obj, corners, K, dist)
            corners, pose, stray = _without_stray_corners(obj, corners, K, dist, pose)
        except SolveError as exc:  # a ChArUco view whose few corners lie on one line
            note = f"no board pose from the corners seen ({exc}); the view is not used"
            log.warning("capture %s: %s", capture.meta["label"], note)
            out.append({"label": capture.meta["label"], "kind": extra.get("kind"),
                        "index": capture.index, "found": False, "note": note})
            continue
        if len(stray):
            log.info("capture %s: corners %s off the view's own board pose, left out",
                     capture.meta["label"], stray.tolist())
        out.append({"label": capture.meta["label"], "kind": extra.get("kind"),
                    "index": capture.index, "joint": extra.get("joint"), "found": True,
                    "q": q, "corners": corners, "stray_corners": stray.tolist(),
                    "C": pose.T_cam_target, "rms_px": pose.rms_px, "pnp": pose.method,
                    "station": int(extra.get("station") or 0), "head": head})
    return out


def _head_angles(meta: dict) -> tuple[float, float, float] | None:
    """The head's angles (rad) a capture recorded, or None."""
    head = meta.get("head")
    if not isinstance(head, dict):
        return None
    try:
        return tuple(float(head[k]) for k in ("pan", "tilt", "roll"))
    except (KeyError, TypeError, ValueError):
        return None


def _without_stray_corners(obj, corners, K, dist, pose):
    """The view's corners without those its own board pose misses by far
    (``extrinsic.stray_corners``: one detected on a shape in front of the board), and the
    pose again without them; unchanged when there are none, or when they are more than
    ``MAX_STRAY_SHARE`` of the view (then the view is wrong as a whole: the solvers' view
    checks decide)."""
    stray = stray_corners(obj, corners, K, dist, pose.T_cam_target)
    seen = int(np.all(np.isfinite(np.reshape(corners, (-1, 2))), axis=1).sum())
    if not len(stray) or len(stray) > MAX_STRAY_SHARE * seen:
        return corners, pose, np.array([], int)
    kept = np.array(corners, float).reshape(-1, 2)
    kept[stray] = np.nan
    return kept, estimate_pose(obj, kept, K, dist), stray


def _predicted_corners(config: RigConfig, q, obj: np.ndarray, K: np.ndarray,
                       station: np.ndarray | None = None) -> np.ndarray:
    """Where the nominal arm, head mount and target pose put the board's corners (pixels,
    no distortion): enough to tell a symmetric board's half and quarter turns apart.
    ``station``: the camera of a re-aimed head beside the arm, seen from home."""
    T_cam_target = nominal_cam_target(config, nominal_ur(config.devices.arm.model), q)
    if station is not None:
        T_cam_target = inv_T(station) @ T_cam_target
    cam = (T_cam_target[:3, :3] @ obj.T).T + T_cam_target[:3, 3]
    px = (K @ cam.T).T
    return px[:, :2] / px[:, 2:3]


def left_out_views(observations: list[dict]) -> dict[str, str]:
    """The views left out because they showed another board than the configured one
    (label: the note naming what they showed)."""
    return {o["label"]: o["note"] for o in observations
            if not o["found"] and o.get("note") and "view left out" in o["note"]}


def frame_names(fixed: bool) -> tuple[str, str]:
    """The result's names of the solvers' X and W: ``T_flange_cam`` and ``T_base_target``,
    or with the head beside the arm (``fixed``) ``T_base_cam`` and ``T_flange_target``."""
    return ("T_base_cam", "T_flange_target") if fixed else ("T_flange_cam", "T_base_target")


def export_model(model: KinematicModel, X, W, uncertainty: dict, heldout: dict,
                 fixed: bool = False) -> dict:
    """The export format of the robot issue; with the head beside the arm (``fixed``) X
    and W are ``T_base_cam`` (the camera with the head at home) and ``T_flange_target``."""
    x_name, w_name = frame_names(fixed)
    return {"convention": "A_i = Rz(theta_i + theta_offset) Tz(d) Tx(a) Rx(alpha) Ry(beta)",
            "units": {"length": "m", "angle": "rad"}, "links": model.links(),
            "T_base_link0": model.T_base_link0.tolist(), x_name: np.asarray(X).tolist(),
            w_name: np.asarray(W).tolist(), "uncertainty": uncertainty,
            "heldout": heldout, **({"mounting": "eye-to-hand"} if fixed else {})}



def capture_use(ctx, obs: list[dict], rejected: dict[int, str] | None = None
                ) -> dict[str, list]:
    """Every capture of the run by index: ``used`` by the solve, ``excluded`` by the
    operator (``rigctl solve --exclude``: the run directory the solve read leaves them
    out) and ``rejected`` by the solver (``rejected``: index -> why; a capture without
    the board found is rejected as such)."""
    why = {o["index"]: "board not found" for o in obs if not o["found"]} | dict(rejected or {})
    labels = {o["index"]: o["label"] for o in obs}
    return {"used": [o["index"] for o in obs if o["found"] and o["index"] not in why],
            "excluded": sorted(getattr(ctx.run, "excluded", ())),
            "rejected": [{"index": i, "label": labels.get(i), "reason": r}
                         for i, r in sorted(why.items())]}


def arm_view_inputs(params, config) -> dict[str, Any]:
    """What hand-eye and robot-kinematics resolve before they move: the intrinsics, the
    arm model the plan used (``planning.planning_arm``), and the pose file's poses when
    there is one."""
    inputs = {"intrinsics": intrinsics_from(config, params.intrinsics,
                                            params.allow_settings_change),
              "arm_model": planning_arm(config, params.use_controller_model,
                                        fresh=False).record()}
    if params.poses_file:
        inputs["pose_file"] = pose_file_record(
            params.poses_file, load_pose_file(params.poses_file, config))
    return inputs


def capture_steps(settle_s: float, label: str, **extra) -> list:
    """Settle, then capture ``label`` (``extra``: what the solve reads of it)."""
    return [Settle(settle_s), CaptureStep(label, extra=extra)]


def sweep_steps(sweeps: dict, settle_s: float) -> tuple[list, list[np.ndarray]]:
    """The moves and captures of the joint sweeps (``plan_sweeps``; thesis ch. 4: one
    joint moved at a time): one capture at each distinct sweep base (``joint`` None;
    sweeps that share a base move back to it), then one at each offset of the swept
    joint. Also every configuration captured, in order (the D-optimal views are chosen
    to add to them)."""
    steps: list = []
    sweep_q: list[np.ndarray] = []
    base_q: list[np.ndarray] = []

    def capture(label: str, **extra) -> list:
        return capture_steps(settle_s, label, **extra)

    for j, sweep in sweeps.items():
        q0 = sweep.q_base
        if not any(np.allclose(q0, q, atol=1e-9) for q in base_q):
            base_q.append(q0)
            sweep_q.append(q0)
            label = f"sweep base {len(base_q)}"
            steps.append(MoveArmJoints(tuple(float(v) for v in q0), label))
            steps += capture(label, kind="sweep", joint=None)
        else:
            steps.append(MoveArmJoints(tuple(float(v) for v in q0), f"joint {j + 1} base"))
        for off in sweep.offsets:
            label = f"joint {j + 1} {off:+g} deg"
            steps.append(MoveArmJoint(j, float(q0[j] + math.radians(off)), label))
            steps += capture(label, kind="sweep", joint=j)
            sweep_q.append(q0 + np.eye(6)[j] * math.radians(off))
    return steps, sweep_q
