"""``robot-kinematics``: link-by-link robot calibration with the eye-in-hand camera
(thesis 4.3) and a joint refinement of every identifiable parameter.

Sequence (head held at home): single-joint sweeps, last joint first, each from the planned
view of the target that keeps the board in sight over the widest range of that joint
(``sweep_bases=widest``; ``common`` sweeps every joint from one base view, as the thesis
does), with offsets spread over that range up to +-60 degrees; D-optimal (or random)
views for the refinement; held-out views for validation. Poses are planned with the
nominal model.

Solve: board poses (Tsai + LM) with the intrinsics of the latest accepted active-camera
run (or a parameter); hand-eye (OpenCV closed forms, then a joint refinement of X and W
on pixels) with the nominal model; link-by-link from the sweeps; the joint refinement
over all training captures on pixels; errors on the held-out views before and after.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import Field

from rigctl.calib import handeye, robot
from rigctl.calib.board import board_points
from rigctl.calib.extrinsic import estimate_pose
from rigctl.calib.intrinsics_check import board_intrinsics
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.geometry.transforms import inv_T

from .base import (
    CaptureStep,
    MoveArmJoint,
    MoveArmJoints,
    MoveHead,
    Note,
    Params,
    Procedure,
    Settle,
    SolveContext,
)
from .planning import CLOSER, informative_views, plan_target_views
from .robot_common import (
    board_observations,
    camera_matrix,
    default_prior_sigma,
    export_model,
    intrinsics_from,
    plan_sweeps,
    planning_K,
)


class RobotKinematicsParams(Params):
    intrinsics: dict[str, Any] | None = None
    sweep_steps: int = Field(4, ge=2, le=6)
    random_poses: int = Field(20, ge=0, le=200)
    heldout_poses: int = Field(6, ge=1, le=100)
    view_distance_m: float = Field(0.45, gt=0.2, le=1.0)
    sweep_distance_m: float = Field(0.7, gt=0.2, le=1.2)
    max_tilt_deg: float = Field(45.0, ge=0, le=50)
    # sweep bases: per joint, the view keeping the board in sight longest; or one for all
    sweep_bases: Literal["widest", "common"] = "widest"
    sweep_base_candidates: int = Field(16, ge=1, le=100)
    # training views: the most informative of many candidates, or plain random ones
    pose_selection: Literal["d-optimal", "random"] = "d-optimal"
    settle_s: float = Field(0.2, ge=0)
    # the final bundle adjustment frees intrinsics and distortion, with the intrinsics in
    # use (and their sigma) as a prior; off: they are held as given
    refine_camera: bool = True
    seed: int = 0


def _scaled_to_reach(config, params: RobotKinematicsParams):
    """The parameters with the sweep and view distances brought closer (``CLOSER``)
    when the arm cannot reach a straight view of the target from the asked ones (a small
    arm such as a UR3e), the first sweep base, and a note saying so."""
    for factor in (1.0, *CLOSER):
        base, notes = plan_target_views(config, 1, params.sweep_distance_m * factor, 0.0,
                                        params.seed)
        if base:
            break
    else:
        raise SolveError("robot-kinematics: no reachable view of the target from "
                         f"{params.sweep_distance_m:.2f} m or closer (down to "
                         f"{params.sweep_distance_m * CLOSER[-1]:.2f} m); move the target "
                         "within the arm's reach or change sweep_distance_m")
    if factor != 1.0:
        params = params.model_copy(update={
            "sweep_distance_m": params.sweep_distance_m * factor,
            "view_distance_m": params.view_distance_m * factor})
        notes = [f"no straight view of the target is reachable from the asked distances: "
                 f"sweeps at {params.sweep_distance_m:.2f} m and views at "
                 f"{params.view_distance_m:.2f} m ({factor:g} times)"]
    return params, base, notes


class RobotKinematics(Procedure):
    name = "robot-kinematics"
    summary = "UR kinematic calibration: sweeps (link-by-link) + joint refinement."
    params_model = RobotKinematicsParams
    devices = ("arm", "camera")
    optional_devices = ("head",)
    detects_board = True

    def plan(self, params: RobotKinematicsParams, config) -> list:
        steps: list = []
        if config.devices.head is not None:
            steps.append(MoveHead(0.0, 0.0, 0.0, "head home"))
        # the sweeps start from a farther view, so the board stays in sight longer
        params, base, notes = _scaled_to_reach(config, params)
        q_base = base[0]
        K = planning_K(config, params.intrinsics)
        bases = [q_base]
        if params.sweep_bases == "widest":
            more, _ = plan_target_views(config, params.sweep_base_candidates,
                                        params.sweep_distance_m, params.max_tilt_deg,
                                        params.seed + 7)
            bases += more
        sweeps, sweep_notes = plan_sweeps(config, bases, K, params.sweep_steps)
        steps += [Note(n) for n in notes + sweep_notes]

        def capture(label, **extra):
            return [Settle(params.settle_s), CaptureStep(label, extra=extra)]

        sweep_q: list[np.ndarray] = []  # every configuration captured in the sweeps
        base_q: list[np.ndarray] = []
        for j, sweep in sweeps.items():
            q0 = sweep.q_base
            # one capture per distinct base (joint None); sweeps that share it move back
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
        for kind, n, seed in (("train", params.random_poses, params.seed + 1),
                              ("heldout", params.heldout_poses, params.seed + 1000)):
            if n == 0:
                continue
            if kind == "train" and params.pose_selection == "d-optimal":
                poses, more = informative_views(config, params, K, sweep_q, n, seed)
            else:
                poses, more = plan_target_views(config, n, params.view_distance_m,
                                                params.max_tilt_deg, seed)
            steps += [Note(m) for m in more]
            for k, q in enumerate(poses):
                steps.append(MoveArmJoints(tuple(float(v) for v in q), f"{kind} {k + 1}"))
                steps += capture(f"{kind} {k + 1}", kind=kind)
        steps.append(MoveArmJoints(tuple(math.radians(v) for v in config.devices.arm.home_deg),
                                   "arm home"))
        return steps

    def resolve_inputs(self, params: RobotKinematicsParams, config) -> dict[str, Any]:
        return {"intrinsics": intrinsics_from(config, params.intrinsics)}

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        intr = ctx.input("intrinsics")
        K, dist = camera_matrix(intr)
        obs = board_observations(ctx, intr)
        lost = [o["label"] for o in obs if not o["found"]]
        found = [o for o in obs if o["found"]]
        train = [o for o in found if o["kind"] in ("sweep", "train")]
        held = [o for o in found if o["kind"] == "heldout"]
        if len(train) < 8:
            raise SolveError(f"robot-kinematics: only {len(train)} training views with the "
                             "board found (need 8)")
        nominal = nominal_ur(ctx.config.devices.arm.model)
        tg = ctx.config.target
        obj = board_points(tg.rows, tg.cols, tg.square_mm / 1000.0)
        meas = robot.Measurements([o["q"] for o in train], C=[o["C"] for o in train],
                                  corners=[o["corners"] for o in train], obj=obj, K=K, dist=dist)

        # hand-eye with the nominal model: the "before calibration" state
        F = [nominal.fk(o["q"]) for o in train]
        closed = handeye.closed_form(F, [o["C"] for o in train])
        he = handeye.refine_pixels(F, meas.corners, obj, K, dist, closed["park"],
                                   C=[o["C"] for o in train])

        # link-by-link from the sweeps (X from the hand-eye); each sweep starts with the
        # base capture (joint None) it moved away from
        bases = [o for o in train if o["kind"] == "sweep" and o["joint"] is None]
        sweeps = {}
        for j in range(6):
            moved = [o for o in train if o["kind"] == "sweep" and o["joint"] == j]
            if not moved:
                continue
            own = [b for b in bases if np.all(np.abs(np.delete(b["q"] - moved[0]["q"], j))
                                              < robot.OTHER_JOINTS_TOL)]
            members = own[:1] + moved
            if len(members) >= 3:
                sweeps[j] = robot.Sweep(j, [o["q"] for o in members], [o["C"] for o in members])
        sweep_span_deg = {f"joint{j + 1}": float(np.degrees(np.ptp([q[j] for q in sw.q])))
                          for j, sw in sweeps.items()}
        lbl, lbl_error = None, None
        try:
            lbl = robot.link_by_link(sweeps, he.X, nominal)
        except SolveError as exc:
            lbl_error = str(exc)
        # axis-based, free of X: every joint's axis line in the target frame, the link
        # parameters fitted to the lines, then X and W alone on every training view
        axis, axis_error = None, None
        try:
            axis_model, W_axis = robot.axis_based(sweeps, nominal, he.W)
            axis = robot.refine(axis_model, he.X, W_axis, meas,
                                mask=robot.frames_only_mask(nominal))
        except SolveError as exc:
            axis_error = str(exc)
        start = lbl.model if lbl is not None else nominal
        W_start = handeye.average_W([start.fk(o["q"]) for o in train], [o["C"] for o in train],
                                    he.X)
        starts = [(nominal, he.X, he.W)] + ([(axis.model, axis.X, axis.W)] if axis else [])
        ref = robot.refine(start, he.X, W_start, meas, extra_starts=starts)
        dh = robot.refine(start, he.X, W_start, meas, mask=robot.dh_mask(nominal))
        cam = None
        if ctx.params.refine_camera:
            ref, cam = robot.refine_with_camera(ref, meas, intr.get("sigma") or
                                                default_prior_sigma(intr))
            # held-out camera poses measured with the camera model the arm model now uses
            held = [{**o, "C": estimate_pose(obj, o["corners"], cam.K, cam.dist).T_cam_target}
                    for o in held]

        def heldout_errors(model, X, W):
            if not held:
                return None
            pos, rot = robot.pose_deviations(model, X, W, [o["q"] for o in held],
                                             [inv_T(o["C"]) for o in held])
            return {"position_rms_m": float(np.sqrt(np.mean(pos ** 2))),
                    "rotation_rms_rad": float(np.sqrt(np.mean(rot ** 2))),
                    "views": len(held)}

        before = heldout_errors(nominal, he.X, he.W)
        after = heldout_errors(ref.model, ref.X, ref.W)
        lbl_err = None
        if lbl is not None:
            W_lbl = handeye.average_W([lbl.model.fk(o["q"]) for o in train],
                                      [o["C"] for o in train], he.X)
            lbl_err = heldout_errors(lbl.model, he.X, W_lbl)
        axis_heldout = heldout_errors(axis.model, axis.X, axis.W) if axis else None
        uncertainty = {"parameters": dict(zip(ref.names, ref.sigma.tolist(), strict=True)),
                       "camera": cam.sigma if cam else None,
                       "condition_number": ref.condition,
                       "condition_number_kinematic": ref.condition_kinematic,
                       "plain_dh_smallest_singular_values": dh.singular_values[-3:].tolist(),
                       "plain_dh_condition_number": dh.condition,
                       "residual_rms_px": ref.rms}
        export = export_model(ref.model, ref.X, ref.W, uncertainty, after or {})
        summary = {"training_views": len(train), "heldout_views": len(held),
                   "heldout_mm_before": None if before is None else
                   1000 * before["position_rms_m"],
                   "heldout_mm_after": None if after is None else 1000 * after["position_rms_m"],
                   "heldout_mm_link_by_link": None if lbl_err is None else
                   1000 * lbl_err["position_rms_m"],
                   "heldout_mm_axis_based": None if axis_heldout is None else
                   1000 * axis_heldout["position_rms_m"],
                   "condition_number": ref.condition,
                   "condition_number_kinematic": ref.condition_kinematic,
                   "residual_rms_px": ref.rms, "sweep_span_deg": sweep_span_deg}
        _plot(ctx, ref, meas)
        device = ctx.config.devices.camera
        try:
            intrinsics_check = board_intrinsics(obj, [o["corners"] for o in found],
                                                (device.width, device.height),
                                                cam.intrinsics() if cam else intr)
        except (SolveError, cv2.error) as exc:
            intrinsics_check = {"error": str(exc)}
        camera = ({"intrinsics": {**cam.intrinsics(), "sigma": {k: cam.sigma[k] for k in
                                                                 robot.CAMERA_KEYS},
                                  "source": f"robot-kinematics joint refinement (prior: "
                                            f"{intr.get('source')})"},
                   "intrinsics_prior": intr, "intrinsics_moved_px": cam.moved(),
                   "covariance": {"names": ref.names + [f"camera.{k}" for k in
                                                        robot.CAMERA_KEYS + robot.DIST_KEYS],
                                  "matrix": ref.covariance.tolist()}}
                  if cam else {"intrinsics": intr})
        return {**export, "arm_model": ctx.config.devices.arm.model, **camera,
                "intrinsics_check": intrinsics_check, "summary": summary,
                "before": {"heldout": before, "T_flange_cam": he.X.tolist(),
                           "T_base_target": he.W.tolist()},
                "axis_based": {"heldout": axis_heldout, "error": axis_error,
                               "links": axis.model.links() if axis else None},
                "link_by_link": {"heldout": lbl_err, "error": lbl_error,
                                 "links": lbl.model.links() if lbl else None,
                                 "identified": lbl.identified if lbl else None,
                                 "notes": lbl.notes if lbl else None},
                "hand_eye_closed_form": {k: v.tolist() for k, v in closed.items()},
                "lost_views": lost}


def _plot(ctx, ref, meas) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = robot.residuals(ref.model, ref.X, ref.W, meas)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.hist(r, bins=60)
    ax.set(xlabel="corner reprojection residual (px)", ylabel="count",
           title=f"robot-kinematics residuals (RMS {ref.rms:.3f} px)")
    fig.tight_layout()
    fig.savefig(ctx.plots_dir / "residuals.png", dpi=80)
    plt.close(fig)


PROCEDURE = RobotKinematics()
