"""``validate-arm``: held-out views of the target; camera position and orientation error
before calibration (nominal model) and after (the latest robot-kinematics result). With
the head beside the arm (eye-to-hand) the views hold the flange's board in the fixed
camera's view (``planning_e2h.board_views``) and the models are ``T_base_cam`` and
``T_flange_target`` (the head stays at home).

Three measures per state, RMS over the views:

- the camera's position and orientation in the target frame against the board pose from
  PnP. This carries PnP's own rotation error times the distance: on the simulated rig,
  with 0.17 px corners, single views are off the truth by about 0.5 mm at 0.5 m even
  with the true intrinsics, so this is a floor the arm model cannot go below;
- the target's position in the camera frame (no lever arm on PnP's rotation);
- the predicted board corners reprojected against the detected ones (px), which needs
  no PnP at all.

The views are planned with the controller's own (factory) arm model when it reports one,
else with the nominal model (``inputs.json``: ``arm_model``).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from rigctl.calib import robot
from rigctl.calib.board import target_points
from rigctl.errors import ConfigError, SolveError
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from rigctl.geometry.transforms import R_to_rotvec, inv_T
from rigctl.records import RunDirectory

from .base import Params, Procedure, SolveContext
from .intrinsics import camera_model, intrinsics_from
from .planning import eye_to_hand, planning_arm, planning_K, view_steps, visit_steps
from .planning_e2h import HEAD_STILL_NOTE, board_views
from .robot_common import board_observations, frame_names, left_out_views


class ValidateArmParams(Params):
    intrinsics: dict[str, Any] | None = None
    # use intrinsics calibrated at another camera size or focus (recorded in the inputs)
    allow_settings_change: bool = False
    calibration_run: str | None = Field(None, description="default: latest robot-kinematics")
    poses: int = Field(8, ge=1, le=100)
    view_distance_m: float = Field(0.5, gt=0.2, le=1.0)
    max_tilt_deg: float = Field(30.0, ge=0, le=50)
    settle_s: float = Field(0.2, ge=0)
    seed: int = 2024


class ValidateArm(Procedure):
    name = "validate-arm"
    summary = "Held-out views: camera pose error before and after arm calibration."
    params_model = ValidateArmParams
    devices = ("arm", "camera")
    optional_devices = ("head",)
    moves = ("arm",)  # whose settle_s is the default wait before a capture
    detects_board = True

    def plan(self, params: ValidateArmParams, config) -> list:
        K, arm = planning_K(config, params.intrinsics), planning_arm(config)
        if eye_to_hand(config):  # the fixed camera watching the board on the flange
            poses, notes = board_views(config, params.poses, params.view_distance_m,
                                       params.max_tilt_deg, params.seed, K, arm.model)
            return visit_steps(config, poses, [HEAD_STILL_NOTE, arm.note, *notes], "check",
                               "heldout", params.settle_s)
        return view_steps(config, params.poses, params.view_distance_m, params.max_tilt_deg,
                          params.seed, "check", "heldout", params.settle_s, K=K, arm=arm)

    def resolve_inputs(self, params: ValidateArmParams, config) -> dict[str, Any]:
        """The calibration to check (given run, else this rig's latest robot-kinematics)
        and the intrinsics (given, else the calibration's own)."""
        from rigctl.record_index import RecordIndex  # SQLAlchemy: only when planned

        index = RecordIndex(config.database_url())
        row = index.get(params.calibration_run) if params.calibration_run else \
            index.latest("robot-kinematics", config.name)
        if row is None:
            raise ConfigError(f"validate-arm: no robot-kinematics calibration recorded for rig "
                              f"{config.name}; run robot-kinematics first")
        if row["rig_name"] != config.name:
            raise ConfigError(f"validate-arm: calibration_run {row['run_id']} belongs to rig "
                              f"{row['rig_name']}, not {config.name}")
        cal = RunDirectory(row["run_dir"]).result()
        return {"calibration_run": row["run_id"], "calibration": cal,
                "intrinsics": intrinsics_from(config, params.intrinsics or cal.get("intrinsics"),
                                              params.allow_settings_change),
                "arm_model": planning_arm(config, fresh=False).record()}

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        cal = ctx.input("calibration")
        intr = ctx.input("intrinsics")
        obs = board_observations(ctx, intr)
        found, left_out = [o for o in obs if o["found"]], left_out_views(obs)
        if not found:
            raise SolveError("validate-arm: the board was not found in any view"
                             + "".join(f"; {k}: {v}" for k, v in list(left_out.items())[:2]))
        model = KinematicModel.from_export(cal)
        nominal = nominal_ur(ctx.config.devices.arm.model)
        fixed = eye_to_hand(ctx.config)
        x_name, w_name = frame_names(fixed)
        if x_name not in cal:
            raise SolveError(f"validate-arm: calibration run {ctx.input('calibration_run')} "
                             f"has no {x_name} (calibrated with the head mounted otherwise)")
        states = {"before": (nominal, np.array(cal["before"][x_name]),
                             np.array(cal["before"][w_name])),
                  "after": (model, np.array(cal[x_name]), np.array(cal[w_name]))}
        K, dist = camera_model(intr)
        tg = ctx.config.target
        obj = target_points(tg)
        out: dict[str, Any] = {"calibration_run": ctx.input("calibration_run"),
                               "views": len(found), "left_out_views": left_out}

        def rms(values) -> float:
            return float(np.sqrt(np.mean(np.square(values))))

        for name, (m, X, W) in states.items():
            pos, rot = robot.pose_deviations(m, X, W, [o["q"] for o in found],
                                             [inv_T(o["C"]) for o in found], fixed)
            target, px = [], []
            for o in found:
                C_pred = inv_T(robot.target_cam(m, X, W, o["q"], fixed))  # T_cam_target
                target.append(np.linalg.norm(C_pred[:3, 3] - o["C"][:3, 3]))
                proj, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), R_to_rotvec(C_pred[:3, :3]),
                                            C_pred[:3, 3], K, dist)
                miss = np.linalg.norm(proj.reshape(-1, 2) - o["corners"].reshape(-1, 2), axis=1)
                px.append(rms(miss[np.isfinite(miss)]))  # the corners the view has
            out[name] = {"position_rms_mm": 1000 * rms(pos),
                         "position_max_mm": 1000 * float(np.max(pos)),
                         "rotation_rms_deg": math.degrees(rms(rot)),
                         "target_in_camera_rms_mm": 1000 * rms(target),
                         "reprojection_rms_px": rms(px)}
        out["summary"] = {"before_mm": out["before"]["position_rms_mm"],
                          "after_mm": out["after"]["position_rms_mm"],
                          "before_px": out["before"]["reprojection_rms_px"],
                          "after_px": out["after"]["reprojection_rms_px"], "views": len(found)}
        return out


PROCEDURE = ValidateArm()
