"""``robot-kinematics`` with the head standing beside the arm (eye-to-hand): the plan.

The fixed camera watches the board on the flange. Single-joint sweeps start from the
board view (``planning_e2h.board_views``) that keeps the board in view over the widest
range of each joint (``planning.plan_sweeps``, whose visibility and clearance checks
follow the rig's mounting); the training views are the D-optimal choice among board
views for the eye-to-hand model (``planning_e2h.informative_station_views``, with the
sweeps' views already planned), the held-out views random board views. When the
intrinsics in use came with the head's calibrated geometry (an active-camera result's
``head_geometry``) and ``head_stations`` is on, the training views are drawn from
several head stations (``planning_e2h.head_stations``: home, pan and tilt each way),
the head turned before each station's views and home again after them; each capture
records its station, and the solve refines each station's pose from home with the
geometry's prediction as its prior (``calib.robot_stations``). Otherwise the head stays
at home throughout (``planning_e2h.HEAD_STILL_NOTE``). The solve is the procedure's own,
with ``solve_robot(..., fixed=True)``: the same minimal model, covariance and held-out
check, from the nominal and the controller's models (link-by-link and the axis lines
need the camera on the flange).
"""

from __future__ import annotations

from rigctl.calib.head_model import HeadGeometry
from rigctl.errors import ConfigError, SolveError

from .base import MoveArmJoints, MoveHead, Note
from .intrinsics import head_geometry, intrinsics_from
from .planning import load_pose_file, plan_sweeps, planning_arm, planning_K, pose_file_steps
from .planning_e2h import (
    HEAD_STATIONS_NOTE,
    HEAD_STILL_NOTE,
    NO_HEAD_GEOMETRY_NOTE,
    board_views,
    head_stations,
    informative_station_views,
)
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
    geometry, head_note = _head_geometry(config, params)
    steps: list = [MoveHead(0.0, 0.0, 0.0, "head home"), Note(head_note), Note(arm.note)]
    bases, notes = board_views(config, params.sweep_base_candidates, params.view_distance_m,
                               params.max_tilt_deg, params.seed + 7, K, model)
    steps += [Note(n) for n in notes]
    sweeps, sweep_notes = plan_sweeps(config, bases, K, params.sweep_steps, model=model) \
        if params.sweep_steps else ({}, [])
    steps += [Note(n) for n in sweep_notes]

    swept, sweep_q = sweep_steps(sweeps, params.settle_s)
    steps += swept
    angles = head_stations(config, K) if geometry is not None else [(0.0, 0.0, 0.0)]
    stations = [geometry.T_home_cam(a) for a in angles] if geometry is not None else None
    for kind, n, seed in (("train", params.random_poses, params.seed + 1),
                          ("heldout", params.heldout_poses, params.seed + 1000)):
        if n == 0:
            continue
        try:
            if kind == "train" and params.pose_selection == "d-optimal":
                poses, station_of, more = informative_station_views(
                    config, params, K, sweep_q, n, seed, model, stations=stations)
            else:
                poses, more = board_views(config, n, params.view_distance_m,
                                          params.max_tilt_deg, seed, K, model)
                station_of = [0] * len(poses)
        except SolveError as exc:
            if kind != "heldout":
                raise
            poses, station_of, more = [], [], [f"no held-out views: {exc}"]
        steps += [Note(m) for m in more]
        here = 0
        for k, (q, s) in enumerate(zip(poses, station_of, strict=True)):
            if s != here:
                pan, tilt, roll = angles[s]
                steps.append(MoveHead(pan, tilt, roll, f"head station {s}"))
                here = s
            steps.append(MoveArmJoints(tuple(float(v) for v in q), f"{kind} {k + 1}"))
            steps += capture_steps(params.settle_s, f"{kind} {k + 1}", kind=kind, station=s)
        if here:
            steps.append(MoveHead(0.0, 0.0, 0.0, "head home"))
    steps.append(MoveArmJoints(config.devices.arm.home_rad(), "arm home"))
    return steps


def _head_geometry(config, params) -> tuple[HeadGeometry | None, str]:
    """The head's calibrated geometry when the training views may re-aim the head
    (``head_stations`` on, and the intrinsics in use came with it), and the plan's note."""
    if not params.head_stations:
        return None, f"{HEAD_STILL_NOTE} (head_stations is off)"
    try:
        geometry = head_geometry(intrinsics_from(config, params.intrinsics,
                                                 allow_settings_change=True))
    except ConfigError:
        geometry = None
    if geometry is None:
        return None, NO_HEAD_GEOMETRY_NOTE
    return geometry, HEAD_STATIONS_NOTE
