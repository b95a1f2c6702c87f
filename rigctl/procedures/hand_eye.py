"""``hand-eye``: T_flange_cam and T_base_target from N diverse views of the target (head
held at home): OpenCV ``calibrateHandEye`` (every method), then a joint refinement of both
transforms on pixel reprojection error, with the arm's own model as its controller reports
it (the nominal model when the run recorded none). The views are planned with that model
too, read from the controller when the run is planned (``inputs.json``: ``arm_model``).

With ``poses_file`` (a YAML list of joint angles in degrees, one list of six per pose, as
``rigctl runs poses`` writes from any run) the views are the operator's, not planned:
each is checked against the soft limits before anything moves, and the plan and the
result report how well the set determines ``T_flange_cam`` and ``T_base_target``
against the planner's D-optimal choice of as many views (``pose_set``), with a warning
when it cannot (every pose turned about one joint, say). With ``teach`` the operator moves
the arm by hand and presses capture (``rigctl.teach``), up to ``poses`` views; the
result reports the taught set the same way.

With the head standing beside the arm (``devices.head.mount: fixed``) and the board on
the flange (``target.mount: flange``) the result is ``T_base_cam`` (the camera with the
head at home) and ``T_flange_target`` instead: the views hold the board in the fixed
camera's view (``planning_e2h.board_views``), and the solve is OpenCV's closed forms on
the inverted arm poses, then the same pixel refinement (``handeye.eye_to_hand``)."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from rigctl.calib import handeye
from rigctl.calib.board import target_points
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.teach import teach_plan

from .base import (
    CaptureStep,
    MoveArmJoints,
    MoveHead,
    Note,
    Params,
    Procedure,
    Settle,
    SolveContext,
)
from .intrinsics import camera_model
from .planning import (
    eye_to_hand,
    load_pose_file,
    planning_arm,
    planning_K,
    pose_file_steps,
    pose_set_note,
    pose_set_report,
    poses_out_of_view,
    view_steps,
)
from .robot_common import (
    arm_view_inputs,
    board_observations,
    capture_use,
    controller_model,
    left_out_views,
)


class HandEyeParams(Params):
    intrinsics: dict[str, Any] | None = None
    # use intrinsics calibrated at another camera size or focus (recorded in the inputs)
    allow_settings_change: bool = False
    # the controller's own (factory) arm model: planned with, and solved with as the run
    # recorded it; off: nominal (the robot's hash is recorded either way)
    use_controller_model: bool = True
    poses: int = Field(12, ge=3, le=100)
    view_distance_m: float = Field(0.45, gt=0.2, le=1.0)
    max_tilt_deg: float = Field(30.0, ge=0, le=50)
    settle_s: float = Field(0.2, ge=0)
    seed: int = 10
    # the operator's poses instead of planned ones: a YAML list of 6 joint angles (deg)
    poses_file: str | None = Field(None, min_length=1, max_length=4096)
    # the operator's poses taken by hand: free drive, capture on each press (rigctl.teach)
    teach: bool = False


class HandEye(Procedure):
    name = "hand-eye"
    summary = "T_flange_cam by OpenCV calibrateHandEye (all methods) and joint refinement."
    params_model = HandEyeParams
    devices = ("arm", "camera")
    optional_devices = ("head",)
    moves = ("arm",)  # whose settle_s is the default wait before a capture
    detects_board = True

    def plan(self, params: HandEyeParams, config) -> list:
        if eye_to_hand(config):
            return self._plan_eye_to_hand(params, config)
        if params.teach:
            return teach_plan(params, config, "view", 3, params.poses)
        if params.poses_file:
            return self._plan_from_file(params, config)
        return view_steps(config, params.poses, params.view_distance_m, params.max_tilt_deg,
                          params.seed, "view", "view", params.settle_s,
                          K=planning_K(config, params.intrinsics),
                          arm=planning_arm(config, params.use_controller_model))

    def _plan_eye_to_hand(self, params: HandEyeParams, config) -> list:
        """Views holding the flange's board in the fixed camera's view (head at home)."""
        from .planning_e2h import HEAD_STILL_NOTE, board_views

        if params.poses_file:
            poses = load_pose_file(params.poses_file, config, min_poses=3)
            notes = [f"poses from {params.poses_file}"]
        else:
            arm = planning_arm(config, params.use_controller_model)
            poses, notes = board_views(config, params.poses, params.view_distance_m,
                                       params.max_tilt_deg, params.seed,
                                       planning_K(config, params.intrinsics), arm.model)
            notes = [arm.note, *notes]
        steps: list = [MoveHead(0.0, 0.0, 0.0, "head home"), Note(HEAD_STILL_NOTE)]
        steps += [Note(n) for n in notes]
        for k, q in enumerate(poses):
            name = f"view {k + 1}"
            steps += [MoveArmJoints(tuple(float(v) for v in q), name), Settle(params.settle_s),
                      CaptureStep(name, extra={"kind": "view"})]
        steps.append(MoveArmJoints(config.devices.arm.home_rad(), "arm home"))
        return steps

    def _plan_from_file(self, params: HandEyeParams, config) -> list:
        """The pose file's poses in its order, with the pose set's identifiability
        (``pose_set_report``) and the poses predicted to cut the board as notes."""
        poses = load_pose_file(params.poses_file, config, min_poses=3)
        K = planning_K(config, params.intrinsics)
        arm = planning_arm(config, params.use_controller_model)
        report = pose_set_report(config, poses, K, arm.model, False, params.view_distance_m,
                                 params.max_tilt_deg, params.seed)
        notes = [arm.note, f"poses from {params.poses_file}: {pose_set_note(report)}"]
        cut = poses_out_of_view(config, arm.model, poses, K)
        if cut:
            notes.append(f"poses {', '.join(map(str, cut))} of {params.poses_file}: part of "
                         "the board predicted outside the image (nominal mount and target)")
        return pose_file_steps(config, poses, "view", params.settle_s, notes)

    def resolve_inputs(self, params: HandEyeParams, config) -> dict[str, Any]:
        return arm_view_inputs(params, config)

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        intr = ctx.input("intrinsics")
        K, dist = camera_model(intr)
        obs = board_observations(ctx, intr)
        found, left_out = [o for o in obs if o["found"]], left_out_views(obs)
        if len(found) < 3:
            raise SolveError(f"hand-eye: the board was found in {len(found)} views (need 3)"
                             + "".join(f"; {k}: {v}" for k, v in list(left_out.items())[:2]))
        controller, robot_hash = controller_model(ctx)
        if not ctx.params.use_controller_model:
            controller = None  # its hash is still recorded: the drift check compares it
        arm = controller or nominal_ur(ctx.config.devices.arm.model)
        F = [arm.fk(o["q"]) for o in found]
        C = [o["C"] for o in found]
        tg = ctx.config.target
        obj = target_points(tg)
        if eye_to_hand(ctx.config):
            return _solve_eye_to_hand(ctx, obs, found, F, C, obj, K, dist, intr, controller,
                                      robot_hash, left_out)
        closed = handeye.closed_form(F, C)
        refined = handeye.refine_pixels(F, [o["corners"] for o in found], obj, K, dist,
                                        handeye.best_closed_form(closed), C=C)
        spread = {name: handeye.transform_error(X, refined.X) for name, X in closed.items()}
        summary = {"views": len(found), "residual_rms_px": refined.rms,
                   "t_mm": (1000 * refined.X[:3, 3]).tolist()}
        used = capture_use(ctx, obs)
        extra: dict[str, Any] = {}
        if ctx.params.poses_file or ctx.params.teach:
            with ctx.stage("pose set"):
                extra["pose_set"] = pose_set_report(
                    ctx.config, [o["q"] for o in found], K, arm, False,
                    ctx.params.view_distance_m, ctx.params.max_tilt_deg, ctx.params.seed,
                    refined.X, refined.W, max(refined.rms, 0.1))
            summary["pose_set"] = pose_set_note(extra["pose_set"])
            if extra["pose_set"]["warning"]:
                summary["warning"] = extra["pose_set"]["warning"]
                extra["warnings"] = [extra["pose_set"]["warning"]]
        return {**extra, "captures": used, "excluded": used["excluded"],
                "T_flange_cam": refined.X.tolist(), "T_base_target": refined.W.tolist(),
                "sigma": refined.sigma.tolist(), "residual_rms_px": refined.rms,
                "closed_form": {k: v.tolist() for k, v in closed.items()},
                "closed_form_vs_refined_deg_mm": spread, "intrinsics": intr,
                "order": handeye.order_samples(F), "summary": summary,
                "arm_model_used": "controller" if controller else "nominal",
                "robot_hash": robot_hash, "left_out_views": left_out}


def _solve_eye_to_hand(ctx, obs, found, F, C, obj, K, dist, intr, controller, robot_hash,
                       left_out) -> dict[str, Any]:
    """``T_base_cam`` and ``T_flange_target`` of a fixed camera watching the flange's board
    (``handeye.eye_to_hand``), in the result's usual shape."""
    from .planning_e2h import HEAD_STILL_NOTE

    closed, refined = handeye.eye_to_hand(F, C, [o["corners"] for o in found], obj, K, dist)
    spread = {name: handeye.transform_error(X, refined.X) for name, X in closed.items()}
    used = capture_use(ctx, obs)
    return {"captures": used, "excluded": used["excluded"], "mounting": "eye-to-hand",
            "T_base_cam": refined.X.tolist(), "T_flange_target": refined.W.tolist(),
            "sigma": refined.sigma.tolist(), "residual_rms_px": refined.rms,
            "closed_form": {k: v.tolist() for k, v in closed.items()},
            "closed_form_vs_refined_deg_mm": spread, "intrinsics": intr,
            "order": handeye.order_samples(handeye.flange_poses(F, True)),
            "summary": {"views": len(found), "residual_rms_px": refined.rms,
                        "t_mm": (1000 * refined.X[:3, 3]).tolist(), "note": HEAD_STILL_NOTE},
            "notes": [HEAD_STILL_NOTE],
            "arm_model_used": "controller" if controller else "nominal",
            "robot_hash": robot_hash, "left_out_views": left_out}


PROCEDURE = HandEye()
