"""``robot-kinematics``: link-by-link robot calibration with the eye-in-hand camera
(thesis 4.3) and a joint refinement of every identifiable parameter.

Sequence (head held at home): single-joint sweeps, last joint first, each from the planned
view of the target that keeps the board in sight over the widest range of that joint
(``sweep_bases=widest``; ``common`` sweeps every joint from one base view, as the thesis
does), with offsets spread over that range up to +-60 degrees; D-optimal (or random)
views for the refinement; held-out views for validation. Poses are planned with the
controller's own (factory) model when it reports one on its primary interface
(``use_controller_model``), else with the nominal model; ``inputs.json`` records which
(``arm_model``).

Solve: board poses (Tsai + LM) with the intrinsics of the latest accepted active-camera
run (or a parameter); hand-eye (OpenCV closed forms, then a joint refinement of X and W
on pixels) with the nominal model and with the controller's; link-by-link from the
sweeps; the joint refinement over all training captures on pixels from each start
(link-by-link, nominal, axis-based, the controller's model), the lowest cost winning
(``summary.refinement_start``); errors on the held-out views for nominal, factory and
calibrated, and how far the calibration moved the camera from the controller's model.

With ``poses_file`` (a YAML list of joint angles in degrees, one list of six per pose, as
``rigctl runs poses`` writes) nothing is planned: every pose of the file is a training
view (no sweeps, so no link-by-link start; nothing held out: ``validate-arm`` checks the
result), each checked against the soft limits before anything moves, and the plan and
the result report the set's identifiability against the planner's D-optimal choice of
as many views (``pose_set``), with a warning when it cannot determine the model.
"""

from __future__ import annotations

from typing import Any, Literal

import cv2
import numpy as np
from pydantic import Field

from rigctl.calib import robot
from rigctl.calib.active_angles import head_encoder_sigmas
from rigctl.calib.board import target_points
from rigctl.calib.intrinsics_check import board_intrinsics
from rigctl.calib.robot_pipeline import (
    MIN_TRAINING_VIEWS,
    BoardView,
    RobotSolution,
    solve_robot,
)
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.geometry.transforms import R_to_rotvec
from rigctl.teach import teach_plan

from .active_camera import servo_models
from .base import (
    MoveArmJoints,
    MoveHead,
    Note,
    Params,
    Procedure,
    SolveContext,
)
from .intrinsics import camera_model, default_prior_sigma, head_geometry
from .planning import (
    CLOSER,
    aligned_spin,
    arm_model,
    board_visible,
    closest_plan,
    eye_to_hand,
    fit_distance,
    informative_views,
    load_pose_file,
    plan_sweeps,
    plan_target_views,
    planning_arm,
    planning_K,
    pose_file_steps,
    pose_set_note,
    pose_set_report,
    poses_out_of_view,
    visible_views,
)
from .planning_e2h import HEAD_STATIONS_NOTE, HEAD_STILL_NOTE
from .robot_common import (
    arm_view_inputs,
    board_observations,
    capture_steps,
    capture_use,
    controller_model,
    export_model,
    frame_names,
    left_out_views,
    sweep_steps,
)
from .robot_e2h import plan_eye_to_hand

# A refined model that leaves more than this on the board corners (their noise is a few
# tenths of a pixel) explains the views badly: the run fails rather than export it
MAX_RESIDUAL_PX = 3.0

class RobotKinematicsParams(Params):
    intrinsics: dict[str, Any] | None = None
    # use intrinsics calibrated at another camera size or focus (recorded in the inputs)
    allow_settings_change: bool = False
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
    # the arm's own (factory) model from its controller: the model the views are planned
    # with (read when the run is planned, in inputs.json), and as recorded in
    # versions.json a start of the joint refinement and a held-out baseline beside
    # nominal; off: nominal throughout (the robot's hash is recorded either way)
    use_controller_model: bool = True
    seed: int = 0
    # the operator's poses instead of planned ones: a YAML list of 6 joint angles (deg)
    poses_file: str | None = Field(None, min_length=1, max_length=4096)
    # the operator's poses taken by hand: free drive, capture on each press (rigctl.teach)
    teach: bool = False
    # the head beside the arm: training views from several head stations when the
    # intrinsics in use came with the head's calibrated geometry; off: the head stays home
    head_stations: bool = True


BASE_LEANS_DEG = (15.0, 30.0, 45.0)  # sweep-base leans tried when no straight view is reachable
# With the run's intrinsics, when no sweep base at the asked distance or nearer shows the
# whole board: bases just beyond the distance at which the board fits the image
# (``fit_distance``), then farther than asked (a long lens, a large board)
FIT_DISTANCE_MARGIN = 1.03
FARTHER = (1.15, 1.3, 1.5)


def _base_view(config, params: RobotKinematicsParams, model, K, distance_m: float,
               lean: float) -> tuple[list, list[str]]:
    """The first sweep base at ``distance_m`` (leaning ``lean`` deg toward the arm): a
    reachable view that, with ``K``, shows the whole board; spun freely, else with the
    board's longer side along the image's (``aligned_spin``: a long lens close up)."""
    notes: list[str] = []
    for spin in ({}, aligned_spin(config)):
        base, notes = plan_target_views(config, 1, distance_m, 0.0, params.seed,
                                        model=model, lean_deg=lean, **spin)
        if base and (K is None or board_visible(config, arm_model(config, model), base[0], K)):
            return base, notes
    return [], notes


def _scaled_to_reach(config, params: RobotKinematicsParams, model=None, K=None):
    """The parameters with the sweep and view distances brought closer (``CLOSER``)
    when the arm (``model``, nominal when None) cannot reach a straight view of the
    target from the asked ones (a small arm such as a UR3e), the first sweep base, and a
    note saying so. When no straight view is reachable at all (a board at the edge of
    the reach), the base leans toward the arm's shoulder, by up to ``max_tilt_deg``
    (``BASE_LEANS_DEG``). With ``K`` the base must also show the whole board: random
    world 13003 (UR3e, f 1600 px, camera turned 92 deg on the flange) reached a base only
    at 0.35 m, where the board fits the image only aligned with it; the unaligned base
    showed none of it, no joint could be swept, and the plan failed. Then, with ``K``,
    farther bases (``FARTHER``): random world 19002 (UR10e, f 1483 px, a 7x7 board of
    54 mm squares) showed the whole board from no reachable base nearer than 0.80 m,
    and the plan was refused."""
    leans = (0.0, *(t for t in BASE_LEANS_DEG if t <= params.max_tilt_deg))
    for lean in leans:
        (base, notes), used, _ = closest_plan(
            lambda d, lean=lean: _base_view(config, params, model, K, d, lean),
            params.sweep_distance_m, 1)
        if base:
            break
    if not base and K is not None:
        base, notes, used, lean = _farther_base(config, params, model, K, leans)
    if not base:
        how = f"straight or leaning up to {leans[-1]:g} deg toward the arm" \
            if len(leans) > 1 else "straight (max_tilt_deg allows no lean)"
        seen = "" if K is None else \
            (f" or farther (up to {params.sweep_distance_m * FARTHER[-1]:.2f} m), {how}, with "
             f"the whole board in view (it fits from {fit_distance(config, K):.2f} m)")
        raise SolveError("robot-kinematics: no reachable view of the target from "
                         f"{params.sweep_distance_m:.2f} m or closer (down to "
                         f"{params.sweep_distance_m * CLOSER[-1]:.2f} m)"
                         f"{seen or ', ' + how}; move the target within the arm's reach or "
                         "change sweep_distance_m")
    factor = used / params.sweep_distance_m
    if factor != 1.0:
        params = params.model_copy(update={
            "sweep_distance_m": params.sweep_distance_m * factor,
            "view_distance_m": params.view_distance_m * factor})
        why = "no straight view of the target is reachable from the asked distances" \
            if factor < 1 else "the whole board is in view from no reachable base as near as " \
            "asked"
        notes = [f"{why}: sweeps at {params.sweep_distance_m:.2f} m and views at "
                 f"{params.view_distance_m:.2f} m ({factor:g} times)"]
    if lean:
        notes = [*notes, "no straight view of the target is reachable: the sweeps start "
                 f"from a view leaning {lean:g} deg toward the arm"]
    return params, base, notes


def _farther_base(config, params: RobotKinematicsParams, model, K, leans
                  ) -> tuple[list, list[str], float, float]:
    """A first sweep base showing the whole board with ``K`` beyond the asked distance:
    just beyond where the board fits the image (when that is nearer than asked), then at
    ``FARTHER`` times the asked distance, straight before leaning. ``([], notes, ...)``
    when none is reachable."""
    asked = params.sweep_distance_m
    fits_from = fit_distance(config, K) * FIT_DISTANCE_MARGIN
    distances = ([fits_from] if fits_from < asked else []) + [asked * f for f in FARTHER]
    notes: list[str] = []
    for distance in distances:
        for lean in leans:
            base, notes = _base_view(config, params, model, K, distance, lean)
            if base:
                return base, notes, distance, lean
    return [], notes, asked, 0.0


def _sweep_bases(config, params: RobotKinematicsParams, model, q_base) -> list:
    """The first base, and with ``sweep_bases="widest"`` the candidates for each joint's
    base: views spun freely, and views with the board's longer side along the image's
    (a long lens close up sees the whole board only so: random world 13003)."""
    bases = [q_base]
    if params.sweep_bases == "widest":
        for k, spin in enumerate(({}, aligned_spin(config))):
            more, _ = plan_target_views(config, params.sweep_base_candidates,
                                        params.sweep_distance_m, params.max_tilt_deg,
                                        params.seed + 7 + k, model=model, **spin)
            bases += more
    return bases


def _whole_board_views(config, params: RobotKinematicsParams, kind: str, n: int, seed: int,
                       model, K: np.ndarray) -> tuple[list[np.ndarray], list[str]]:
    """``n`` random views (held-out, or training without pose selection), each with the
    whole board in view (``visible_views``: never nearer than the board fits, farther or
    nearer when too few are). Planned at ``view_distance_m`` with no such check, the
    held-out views of 15 of 40 random worlds (61000-61019, 62000-62019) cut the board in
    some views, in 4 in all six: no held-out error was reported there. Held-out views
    too few to plan are noted, not refused: they check the result, they do not make it."""
    try:
        label = "held-out view" if kind == "heldout" else "training view"
        return visible_views(config, n, params.view_distance_m, params.max_tilt_deg, seed,
                             label, K, model)
    except SolveError as exc:
        if kind != "heldout":
            raise
        return [], [f"no held-out views: {exc}"]


class RobotKinematics(Procedure):
    name = "robot-kinematics"
    summary = "UR kinematic calibration: sweeps (link-by-link) + joint refinement."
    params_model = RobotKinematicsParams
    devices = ("arm", "camera")
    optional_devices = ("head",)
    moves = ("arm",)  # whose settle_s is the default wait before a capture
    detects_board = True

    def plan(self, params: RobotKinematicsParams, config) -> list:
        if eye_to_hand(config):  # the head beside the arm, the board on the flange
            return plan_eye_to_hand(params, config)
        return self._plan_on_flange(params, config)

    def _plan_on_flange(self, params: RobotKinematicsParams, config) -> list:
        """The plan with the head on the flange (module note)."""
        if params.poses_file or params.teach:
            return plan_from_file(params, config)
        steps: list = []
        if config.devices.head is not None:
            steps.append(MoveHead(0.0, 0.0, 0.0, "head home"))
        arm = planning_arm(config, params.use_controller_model)
        model = arm.model
        # the sweeps start from a farther view, so the board stays in sight longer
        K = planning_K(config, params.intrinsics)
        params, base, notes = _scaled_to_reach(config, params, model, K)
        q_base = base[0]
        bases = _sweep_bases(config, params, model, q_base)
        sweeps, sweep_notes = plan_sweeps(config, bases, K, params.sweep_steps, model=model)
        if not sweeps:
            raise SolveError("robot-kinematics: no joint can be swept with the whole board "
                             f"in view from any of {len(bases)} sweep bases at "
                             f"{params.sweep_distance_m:.2f} m; " + "; ".join(sweep_notes))
        steps += [Note(n) for n in [arm.note, *notes, *sweep_notes]]

        swept, sweep_q = sweep_steps(sweeps, params.settle_s)
        steps += swept
        for kind, n, seed in (("train", params.random_poses, params.seed + 1),
                              ("heldout", params.heldout_poses, params.seed + 1000)):
            if n == 0:
                continue
            if kind == "train" and params.pose_selection == "d-optimal":
                poses, more = informative_views(config, params, K, sweep_q, n, seed, model)
            else:
                poses, more = _whole_board_views(config, params, kind, n, seed, model, K)
            steps += [Note(m) for m in more]
            for k, q in enumerate(poses):
                steps.append(MoveArmJoints(tuple(float(v) for v in q), f"{kind} {k + 1}"))
                steps += capture_steps(params.settle_s, f"{kind} {k + 1}", kind=kind)
        steps.append(MoveArmJoints(config.devices.arm.home_rad(), "arm home"))
        return steps

    def resolve_inputs(self, params: RobotKinematicsParams, config) -> dict[str, Any]:
        return arm_view_inputs(params, config)

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        """Thesis 4.3 on the run's board views (``rigctl.calib.robot_pipeline``)."""
        intr = ctx.input("intrinsics")
        K, dist = camera_model(intr)
        tg = ctx.config.target
        obj = target_points(tg)
        with ctx.stage("board poses"):
            obs = board_observations(ctx, intr)
        views = [BoardView(o["label"], o["kind"], o["joint"], o["q"], o["corners"], o["C"],
                           o.get("station", 0), o.get("head")) for o in obs if o["found"]]
        controller, robot_hash = controller_model(ctx)
        if not ctx.params.use_controller_model:
            controller = None  # its hash is still recorded: the drift check compares it
        fixed = eye_to_hand(ctx.config)
        sol = solve_robot(views, nominal_ur(ctx.config.devices.arm.model), obj, K, dist,
                          intr.get("sigma") or default_prior_sigma(intr),
                          ctx.params.refine_camera, controller=controller, fixed=fixed,
                          head=head_geometry(intr) if fixed else None,
                          encoder_sigma_rad=head_encoder_sigmas(
                              servo_models((c.meta for c in ctx.captures()),
                                           ctx.config)) if fixed else None)
        if sol.ref.rms > MAX_RESIDUAL_PX:
            # a refinement stuck in a wrong minimum still "converges"; its residual says so
            # (unseen random world 4015: 20.7 px, the exported model 12 mm off the truth)
            raise SolveError(f"robot-kinematics: the refined model leaves {sol.ref.rms:.1f} px "
                             f"RMS on the board corners (more than {MAX_RESIDUAL_PX:g} px): "
                             "the solve did not find a model that explains the views; "
                             "nothing exported")
        ctx.timings_s.update(sol.timings_s)
        with ctx.stage("intrinsics check"):
            used = sol.camera.intrinsics() if sol.camera else intr
            device = ctx.config.devices.camera
            try:
                check = board_intrinsics(obj, [v.corners for v in views],
                                         (device.width, device.height), used)
            except (SolveError, cv2.error) as exc:
                check = {"error": str(exc)}
        ctx.defer("plots", lambda: _plot(ctx, sol.ref, sol.meas))
        exported = _export(sol, intr)
        if exported["factory"] is not None:
            exported["factory"]["links"] = controller.links()
        summary, extra = _summary(sol), {}
        if fixed:
            stations = head_stations_report(sol)
            note = HEAD_STATIONS_NOTE if stations else HEAD_STILL_NOTE
            summary["note"] = note
            extra["notes"] = [note]
            if stations:
                extra["head_stations"] = stations
        if (ctx.params.poses_file or ctx.params.teach) and not fixed:
            with ctx.stage("pose set"):
                extra = _pose_set(ctx, sol, K, summary)
        by_label = {o["label"]: o["index"] for o in obs}
        used = capture_use(ctx, obs, {by_label[label]: f"outlier: {rms:.1f} px RMS"
                                      for label, rms in sol.rejected_views.items()})
        return {**exported, **extra, "captures": used, "excluded": used["excluded"],
                "arm_model": ctx.config.devices.arm.model,
                "robot_hash": robot_hash, "planned_with": _planned_with(ctx),
                "intrinsics_check": check, "summary": summary,
                "lost_views": [o["label"] for o in obs if not o["found"]],
                # views showing another board than the configured one (label: what)
                "left_out_views": left_out_views(obs),
                # training views the refined model missed by far, left out (label: RMS px)
                "rejected_views": sol.rejected_views,
                # board corners of training views the refined model missed by far, left
                # out (label: corner indices)
                "rejected_corners": sol.rejected_corners,
                # corners each view's own board pose missed by far, left out before the
                # solve (label: corner indices; ``robot_common.board_observations``)
                "stray_corners": {o["label"]: o["stray_corners"] for o in obs
                                  if o.get("stray_corners")}}


def plan_from_file(params: RobotKinematicsParams, config) -> list:
    """Every pose of ``params.poses_file`` as a training view, in the file's order, with
    the set's identifiability (``pose_set_report``: link parameters, X and W) and the
    poses predicted to cut the board as notes. Fewer poses than the solve needs
    (``MIN_TRAINING_VIEWS``) is refused here. With ``teach``: the operator's poses,
    taken by hand (``rigctl.teach``), as training views."""
    if params.teach:
        return teach_plan(params, config, "train", MIN_TRAINING_VIEWS, 200)
    poses = load_pose_file(params.poses_file, config, min_poses=MIN_TRAINING_VIEWS)
    K = planning_K(config, params.intrinsics)
    arm = planning_arm(config, params.use_controller_model)
    report = pose_set_report(config, poses, K, arm.model, True, params.view_distance_m,
                             params.max_tilt_deg, params.seed)
    notes = [arm.note, f"poses from {params.poses_file}: {pose_set_note(report)}",
             "poses from a file: no sweeps (no link-by-link start) and no held-out views"]
    cut = poses_out_of_view(config, arm.model, poses, K)
    if cut:
        notes.append(f"poses {', '.join(map(str, cut))} of {params.poses_file}: part of "
                     "the board predicted outside the image (nominal mount and target)")
    return pose_file_steps(config, poses, "train", params.settle_s, notes)


def _pose_set(ctx: SolveContext, sol: RobotSolution, K, summary: dict) -> dict[str, Any]:
    """The identifiability of the training views the solve used (``pose_set_report``,
    at the refined model, with its residual as the corner noise), into ``summary`` as
    well; with its warning when the set cannot determine the model."""
    ref, p = sol.ref, ctx.params
    report = pose_set_report(ctx.config, list(sol.meas.q), K, ref.model, True,
                             p.view_distance_m, p.max_tilt_deg, p.seed, ref.X, ref.W,
                             max(ref.rms, 0.1))
    summary["pose_set"] = pose_set_note(report)
    if report["warning"]:
        summary["warning"] = report["warning"]
        return {"pose_set": report, "warnings": [report["warning"]]}
    return {"pose_set": report}


def _planned_with(ctx: SolveContext) -> dict[str, Any] | None:
    """Which arm model the views were planned with (``inputs.json``; None for a run
    recorded before it was)."""
    arm = ctx.inputs.get("arm_model")
    return None if arm is None else {k: arm.get(k) for k in ("source", "robot_hash", "note")}


def _mm(errors: dict | None, key: str = "position_rms_m") -> float | None:
    return None if errors is None else 1000 * errors[key]


def _summary(sol: RobotSolution) -> dict[str, Any]:
    ref, held = sol.ref, sol.heldout
    return {"training_views": sol.training_views, "heldout_views": sol.heldout_views,
            "heldout_mm_before": _mm(held["before"]), "heldout_mm_after": _mm(held["after"]),
            # the board's position in the camera frame: no lever arm on PnP's rotation
            "heldout_target_mm_before": _mm(held["before"], "target_in_camera_rms_m"),
            "heldout_target_mm_after": _mm(held["after"], "target_in_camera_rms_m"),
            "heldout_mm_link_by_link": _mm(held["link_by_link"]),
            "heldout_mm_axis_based": _mm(held["axis_based"]),
            "heldout_mm_factory": _mm(held.get("factory")),
            "moved_from_controller_mm": _mm(sol.moved_from_controller),
            # the joint refinement's start that ended lowest, and where each ended (px)
            "refinement_start": sol.refinement_start,
            "refinement_starts_rms_px": sol.refinement_starts_rms_px,
            "condition_number": ref.condition,
            "condition_number_kinematic": ref.condition_kinematic,
            "residual_rms_px": ref.rms, "sweep_span_deg": sol.sweep_span_deg}


def head_stations_report(sol: RobotSolution) -> list[dict[str, Any]]:
    """Each head station after home, when the head was re-aimed: its recorded angles
    (deg), its training views, its refined pose from home (``T_home_station``), where the
    head geometry predicted it (rotation deg and translation mm apart) and the refined
    pose's 1-sigma (deg, mm)."""
    stations, ref = sol.meas.stations, sol.ref
    if stations is None or not stations.count:
        return []
    sigma = dict(zip(ref.names, ref.sigma.tolist(), strict=True))
    out = []
    for s, (D, D_pred) in enumerate(zip(ref.stations, stations.predicted, strict=True)):
        rot = np.linalg.norm(R_to_rotvec(D[:3, :3] @ D_pred[:3, :3].T))
        name = f"station{s + 1}"
        out.append({"angles_deg": np.degrees(stations.angles[s]).tolist(),
                    "views": int(np.sum(stations.index == s + 1)),
                    "T_home_station": D.tolist(),
                    "from_prediction": {"deg": float(np.degrees(rot)),
                                        "mm": 1000 * float(np.linalg.norm(D[:3, 3]
                                                                          - D_pred[:3, 3]))},
                    "sigma": {"deg": [float(np.degrees(sigma[f"{name}.r{c}"])) for c in "xyz"],
                              "mm": [1000 * sigma[f"{name}.{c}"] for c in "xyz"]}})
    return out


def _position_sigma_mm(sol: RobotSolution) -> dict[str, float]:
    """The camera position's predicted 1-sigma (norm over the three axes, mm) over the
    run's own configurations (every view, training and held-out): what the arm model
    claims about the camera anywhere in that workspace."""
    q = [v.q for v in sol.views]
    sig = robot.camera_position_sigma(sol.ref.model, sol.ref.X, sol.ref.W, sol.ref.names,
                                      sol.ref.covariance, q, sol.meas.fixed)
    norm = 1000 * np.linalg.norm(sig, axis=1)
    return {"median": float(np.median(norm)), "max": float(norm.max()),
            "configurations": len(q)}


def _export(sol: RobotSolution, intr: dict) -> dict[str, Any]:
    """The arm model (``export_model``), its uncertainty and covariance, the camera model
    it was fitted with, and the single methods and closed forms beside it."""
    ref, cam, lbl, axis = sol.ref, sol.camera, sol.link_by_link, sol.axis
    uncertainty = {"parameters": dict(zip(ref.names, ref.sigma.tolist(), strict=True)),
                   "camera": cam.sigma if cam else None,
                   "condition_number": ref.condition,
                   "condition_number_kinematic": ref.condition_kinematic,
                   "plain_dh_smallest_singular_values": sol.plain_dh_singular_values[-3:].tolist(),
                   "plain_dh_condition_number": robot.condition_number(
                       sol.plain_dh_singular_values),
                   "camera_position_sigma_mm": _position_sigma_mm(sol),
                   "residual_rms_px": ref.rms}
    camera = ({"intrinsics": {**cam.intrinsics(),
                              "sigma": {k: cam.sigma[k] for k in robot.CAMERA_KEYS},
                              "source": "robot-kinematics joint refinement (prior: "
                                        f"{intr.get('source')})",
                              "settings": intr.get("settings")},
               "intrinsics_prior": intr, "intrinsics_moved_px": cam.moved(),
               # the board views' own intrinsics (no prior), and the factor the prior's
               # sigma grew by to agree with them (1: they agreed)
               "intrinsics_board_only": cam.board_only,
               "intrinsics_prior_inflation": cam.prior_inflation}
              if cam else {"intrinsics": intr, "camera_note": sol.camera_note})
    names = ref.names + ([f"camera.{k}" for k in robot.CAMERA_KEYS + robot.DIST_KEYS]
                         if cam else [])
    fixed = sol.meas.fixed
    x_name, w_name = frame_names(fixed)
    return {**export_model(ref.model, ref.X, ref.W, uncertainty, sol.heldout["after"] or {},
                           fixed),
            **camera, "covariance": {"names": names, "matrix": ref.covariance.tolist()},
            "before": {"heldout": sol.heldout["before"], x_name: sol.hand_eye.X.tolist(),
                       w_name: sol.hand_eye.W.tolist()},
            "factory": None if sol.controller_hand_eye is None else {
                "heldout": sol.heldout.get("factory"),
                x_name: sol.controller_hand_eye.X.tolist(),
                w_name: sol.controller_hand_eye.W.tolist(),
                "moved": sol.moved_from_controller},
            "axis_based": {"heldout": sol.heldout["axis_based"], "error": sol.axis_error,
                           "links": axis.model.links() if axis else None},
            "link_by_link": {"heldout": sol.heldout["link_by_link"],
                             "error": sol.link_by_link_error,
                             "links": lbl.model.links() if lbl else None,
                             "identified": lbl.identified if lbl else None,
                             "notes": lbl.notes if lbl else None},
            "hand_eye_closed_form": {k: v.tolist() for k, v in sol.closed_form.items()}}


def _plot(ctx, ref, meas) -> None:
    # matplotlib's object API: no pyplot state in the service's threads, nor its import
    from matplotlib.figure import Figure

    r = robot.residuals(ref.model, ref.X, ref.W, meas)
    fig = Figure(figsize=(6, 3.5))
    ax = fig.subplots()
    ax.hist(r, bins=60)
    ax.set(xlabel="corner reprojection residual (px)", ylabel="count",
           title=f"robot-kinematics residuals (RMS {ref.rms:.3f} px)")
    fig.tight_layout()
    fig.savefig(ctx.plots_dir / "residuals.png", dpi=80)


PROCEDURE = RobotKinematics()
