"""``robot-kinematics`` with the head standing beside the arm (eye-to-hand): the plan.

The fixed camera watches the board on the flange. Single-joint sweeps start from the
board view (``planning_e2h.board_views``) that keeps the board in view over the widest
range of each joint (``planning.plan_sweeps``, whose visibility and clearance checks
follow the rig's mounting); the training views are the D-optimal choice among board
views for the eye-to-hand model (``planning_e2h.informative_board_views``, with the
sweeps' views already planned), the held-out views random board views. The head stays
at home throughout (``planning_e2h.HEAD_STILL_NOTE``). The solve is the procedure's own,
with ``solve_robot(..., fixed=True)``: the same minimal model, covariance and held-out
check, from the nominal and the controller's models (link-by-link and the axis lines
need the camera on the flange).
"""

from __future__ import annotations

from rigctl.errors import SolveError

from .base import MoveArmJoints, MoveHead, Note
from .planning import load_pose_file, plan_sweeps, planning_arm, planning_K, pose_file_steps
from .planning_e2h import HEAD_STILL_NOTE, board_views, informative_board_views
from .robot_common import capture_steps, sweep_steps


def plan_eye_to_hand(params, config) -> list:
    """The steps of a robot-kinematics run with the head beside the arm (module note);
    with ``poses_file`` its poses as training views (no identifiability report)."""
    if params.poses_file:
        from rigctl.calib.robot_pipeline import MIN_TRAINING_VIEWS

        poses = load_pose_file(params.poses_file, config, min_poses=MIN_TRAINING_VIEWS)
        return pose_file_steps(config, poses, "train", params.settle_s,
                               [HEAD_STILL_NOTE, f"poses from {params.poses_file} (head "
                                "beside the arm: no identifiability report)"])
    arm = planning_arm(config, params.use_controller_model)
    model = arm.model
    K = planning_K(config, params.intrinsics)
    steps: list = [MoveHead(0.0, 0.0, 0.0, "head home"), Note(HEAD_STILL_NOTE), Note(arm.note)]
    bases, notes = board_views(config, params.sweep_base_candidates, params.view_distance_m,
                               params.max_tilt_deg, params.seed + 7, K, model)
    steps += [Note(n) for n in notes]
    sweeps, sweep_notes = plan_sweeps(config, bases, K, params.sweep_steps, model=model) \
        if params.sweep_steps else ({}, [])
    steps += [Note(n) for n in sweep_notes]

    swept, sweep_q = sweep_steps(sweeps, params.settle_s)
    steps += swept
    for kind, n, seed in (("train", params.random_poses, params.seed + 1),
                          ("heldout", params.heldout_poses, params.seed + 1000)):
        if n == 0:
            continue
        try:
            if kind == "train" and params.pose_selection == "d-optimal":
                poses, more = informative_board_views(config, params, K, sweep_q, n, seed,
                                                      model)
            else:
                poses, more = board_views(config, n, params.view_distance_m,
                                          params.max_tilt_deg, seed, K, model)
        except SolveError as exc:
            if kind != "heldout":
                raise
            poses, more = [], [f"no held-out views: {exc}"]
        steps += [Note(m) for m in more]
        for k, q in enumerate(poses):
            steps.append(MoveArmJoints(tuple(float(v) for v in q), f"{kind} {k + 1}"))
            steps += capture_steps(params.settle_s, f"{kind} {k + 1}", kind=kind)
    steps.append(MoveArmJoints(config.devices.arm.home_rad(), "arm home"))
    return steps
