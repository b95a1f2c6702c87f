"""``validate-arm``: held-out views of the target; camera position and orientation error
before calibration (nominal model) and after (the latest robot-kinematics result)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field

from rigctl.errors import SolveError
from rigctl.geometry.kinematics import KinematicModel, nominal_ur
from rigctl.geometry.transforms import R_to_rotvec, inv_T
from rigctl.records import RecordIndex, RunDirectory

from .base import Params, Procedure, SolveContext
from .planning import view_steps
from .robot_common import board_observations, intrinsics_from


class ValidateArmParams(Params):
    intrinsics: dict[str, Any] | None = None
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

    def plan(self, params: ValidateArmParams, config) -> list:
        return view_steps(config, params.poses, params.view_distance_m, params.max_tilt_deg,
                          params.seed, "check", "heldout", params.settle_s)

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        params: ValidateArmParams = ctx.params
        index = RecordIndex(ctx.config.database_url())
        row = index.get(params.calibration_run) if params.calibration_run else \
            index.latest("robot-kinematics", ctx.config.name)
        if row is None:
            raise SolveError("validate-arm: no robot-kinematics calibration recorded")
        cal = RunDirectory(row["run_dir"]).result()
        intr = intrinsics_from(ctx.config, params.intrinsics or cal.get("intrinsics"))
        found = [o for o in board_observations(ctx, intr) if o["found"]]
        if not found:
            raise SolveError("validate-arm: the board was not found in any view")
        links = cal["links"]
        model = KinematicModel(*(np.array([lk[k] for lk in links]) for k in ("d", "a", "alpha")),
                               beta=np.array([lk["beta"] for lk in links]),
                               theta_offset=np.array([lk["theta_offset"] for lk in links]),
                               T_base_link0=np.array(cal["T_base_link0"]))
        nominal = nominal_ur(ctx.config.devices.arm.model)
        states = {"before": (nominal, np.array(cal["before"]["T_flange_cam"]),
                             np.array(cal["before"]["T_base_target"])),
                  "after": (model, np.array(cal["T_flange_cam"]), np.array(cal["T_base_target"]))}
        out: dict[str, Any] = {"calibration_run": row["run_id"], "views": len(found)}
        for name, (m, X, W) in states.items():
            pos, rot = [], []
            for o in found:
                T_pred = inv_T(W) @ m.fk(o["q"]) @ X
                T_meas = inv_T(o["C"])
                pos.append(np.linalg.norm(T_pred[:3, 3] - T_meas[:3, 3]))
                rot.append(np.linalg.norm(R_to_rotvec(T_pred[:3, :3].T @ T_meas[:3, :3])))
            out[name] = {"position_rms_mm": 1000 * float(np.sqrt(np.mean(np.square(pos)))),
                         "position_max_mm": 1000 * float(np.max(pos)),
                         "rotation_rms_deg": math.degrees(float(np.sqrt(np.mean(np.square(rot)))))}
        out["summary"] = {"before_mm": out["before"]["position_rms_mm"],
                          "after_mm": out["after"]["position_rms_mm"], "views": len(found)}
        return out


PROCEDURE = ValidateArm()
