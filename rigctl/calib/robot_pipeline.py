"""The robot-kinematics solve as a pure pipeline: board views in, arm model out.

The procedure (``rigctl/procedures/robot_kinematics.py``) reads the run's captures into
``BoardView``s and calls ``solve_robot``; benchmarks can call it on views of their own,
or call one stage's function to measure that stage alone. Stages (thesis 4.3,
generalised; ``rigctl.calib.robot``):

1. ``hand_eye`` with the nominal arm model (the "before calibration" state);
2. link-by-link from the single-joint sweeps (4.11)-(4.35), X from step 1, and
3. axis-based: each swept joint's axis line in the target frame, no X
   (``single_methods``);
4. ``joint_refinement`` (4.11) of the minimal parameter set over every training view,
   from each of those starts, the nominal model's and the controller's own model's
   (when it reports one), the lowest cost winning (``joint_refinement_from`` names the
   start that won), and plain D-H's Jacobian there (its rank deficiency);
   a training view that the refined model misses by far more than the others (a board
   found one square off, a wrong correspondence) is left out and stages 1-4 run again
   without it (``outlier_views``);
5. ``free_camera``: the camera free as well (``refine_with_camera``), the intrinsics in
   use as a prior;
6. held-out errors of every model (``heldout_table``, ``moved_from_controller``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from rigctl.calib import handeye, robot, robot_stations
from rigctl.calib.blas_threads import with_one_blas_thread
from rigctl.calib.extrinsic import CORNER_FACTOR, CORNER_MIN_PX, estimate_pose
from rigctl.calib.head_model import HeadGeometry
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import KinematicModel
from rigctl.timing import stage_timer

MIN_TRAINING_VIEWS = 8
MIN_HOME_VIEWS = 6  # the hand-eye stage's views at home, with the head re-aimed (``_home_views``)
# A training view is an outlier when its corners' RMS residual exceeds both this many
# times the median view's and OUTLIER_MIN_PX. At a correct solution views sit at the
# corner noise, ~0.1-0.3 px. A view with wrong corners pulls the solve and spreads its
# error over the others: a board found one square off left 206 px against a median of
# 6 px (unseen world 4015), a synthetic one 47 px against 5 px (tests/test_robot_math.py).
OUTLIER_FACTOR = 5.0
OUTLIER_MIN_PX = 3.0
# A single corner is an outlier when its residual at the refined model exceeds both
# CORNER_FACTOR times the median corner's and CORNER_MIN_PX (``extrinsic``'s limits for a
# corner off its own view's pose): a corner the detector placed on something in front of
# the board (random world 400008: a scene shape over the board put one corner of a view
# 5-25 px off while the others sat at 0.2 px; the arm model came out 0.41 mm off the
# truth).
# a view left with fewer corners than this after its outlying ones is left out whole
MIN_CORNERS = 6


@dataclass
class BoardView:
    """One capture with the board found: joints, corners, the board pose measured with
    the intrinsics in use, and what the plan took it for (``sweep``, ``train``,
    ``heldout``; ``joint`` is the swept joint, None for a sweep's base)."""

    label: str
    kind: str
    joint: int | None
    q: np.ndarray
    corners: np.ndarray
    C: np.ndarray
    # the head beside the arm re-aimed: the view's head station (0: home) and the head's
    # angles as recorded (rad; None: not recorded)
    station: int = 0
    head: tuple[float, float, float] | None = None


@dataclass
class RobotSolution:
    ref: robot.RefineResult
    camera: robot.CameraRefinement | None
    hand_eye: Any
    closed_form: dict[str, np.ndarray]
    heldout: dict[str, dict | None]
    link_by_link: Any
    link_by_link_error: str | None
    axis: robot.RefineResult | None
    axis_error: str | None
    plain_dh_singular_values: np.ndarray
    sweep_span_deg: dict[str, float]
    meas: robot.Measurements
    training_views: int = 0
    heldout_views: int = 0
    timings_s: dict[str, float] = field(default_factory=dict)
    camera_note: str | None = None  # why the camera stayed held, when it was to be free
    views: list[BoardView] = field(default_factory=list)
    rejected_views: dict[str, float] = field(default_factory=dict)  # label: RMS px
    # label: the board corners (indices) left out of a training view (``outlier_corners``)
    rejected_corners: dict[str, list[int]] = field(default_factory=dict)
    # the controller's own model, when given: its hand-eye, and how far the calibrated
    # model's camera (in the target frame) lies from that model's over the held-out
    # configurations
    controller_hand_eye: Any = None
    moved_from_controller: dict[str, float] | None = None
    # the joint refinement's starts (name: RMS px where each ended) and the one that won
    refinement_start: str | None = None
    refinement_starts_rms_px: dict[str, float] = field(default_factory=dict)


def _sweeps(train: list[BoardView]) -> dict[int, robot.Sweep]:
    """Each swept joint's captures, starting with the base capture it moved away from."""
    bases = [v for v in train if v.kind == "sweep" and v.joint is None]
    sweeps = {}
    for j in range(6):
        moved = [v for v in train if v.kind == "sweep" and v.joint == j]
        if not moved:
            continue
        own = [b for b in bases if np.all(np.abs(np.delete(b.q - moved[0].q, j))
                                          < robot.OTHER_JOINTS_TOL)]
        members = own[:1] + moved
        if len(members) >= 3:
            sweeps[j] = robot.Sweep(j, [v.q for v in members], [v.C for v in members])
    return sweeps


def heldout_errors(model: KinematicModel, X, W, held: list[BoardView], fixed: bool = False
                   ) -> dict | None:
    """RMS camera position (m) and rotation (rad) error on the held-out views (in the
    target frame; ``fixed``: the camera beside the arm, ``robot.target_cam``), and the
    RMS error of the board's position in the camera frame (m), which carries no lever
    arm on PnP's rotation: on a small board that rotation is off by tenths of a degree,
    and the camera's position in the board frame by millimetres with it (random world
    400010: 2.0 mm against 0.14 mm)."""
    if not held:
        return None
    pos, rot = robot.pose_deviations(model, X, W, [v.q for v in held],
                                     [np.linalg.inv(v.C) for v in held], fixed)
    target = [np.linalg.norm(np.linalg.inv(robot.target_cam(model, X, W, v.q, fixed))[:3, 3]
                             - v.C[:3, 3]) for v in held]
    return {"position_rms_m": float(np.sqrt(np.mean(pos ** 2))),
            "rotation_rms_rad": float(np.sqrt(np.mean(rot ** 2))),
            "target_in_camera_rms_m": float(np.sqrt(np.mean(np.square(target)))),
            "views": len(held)}


def split_views(views: list[BoardView]) -> tuple[list[BoardView], list[BoardView]]:
    """The training views (sweeps and training views) and the held-out ones; too few
    training views is a ``SolveError``."""
    train = [v for v in views if v.kind in ("sweep", "train")]
    held = [v for v in views if v.kind == "heldout"]
    if len(train) < MIN_TRAINING_VIEWS:
        raise SolveError(f"robot-kinematics: only {len(train)} training views with the "
                         f"board found (need {MIN_TRAINING_VIEWS})")
    return train, held


def hand_eye(model: KinematicModel, meas: robot.Measurements):
    """Stage 1 with the arm model ``model``: OpenCV's closed forms on the training views'
    board poses, the best of them refined on pixels (with the head re-aimed between
    views: on the views at home, ``_home_views``). Returns the closed forms and the
    refined hand-eye (X, W)."""
    C_home = home_C(meas)
    home = _home_views(meas)
    if home is None:  # too few views at home: every view, seen from home, on its pose
        F = handeye.flange_poses([model.fk(q) for q in meas.q], meas.fixed)
        closed = handeye.closed_form(F, C_home)
        return closed, handeye.refine_poses(F, C_home, handeye.best_closed_form(closed))
    F = handeye.flange_poses([model.fk(meas.q[k]) for k in home], meas.fixed)
    C = [C_home[k] for k in home]
    closed = handeye.closed_form(F, C)
    refined = handeye.refine_pixels(F, [meas.corners[k] for k in home], meas.obj, meas.K,
                                    meas.dist, handeye.best_closed_form(closed), C=C)
    return closed, refined


def _home_views(meas: robot.Measurements) -> list[int] | None:
    """The views the hand-eye stage refines on pixels: every one, or with the head
    re-aimed between views those taken at home (the sweeps' at least); None when fewer
    than ``MIN_HOME_VIEWS`` were (then ``hand_eye`` takes every view seen from home as
    the head geometry predicts, ``home_C``, on poses: a start for the joint refinement,
    which refines the stations)."""
    if not meas.station_count:
        return list(range(len(meas.q)))
    home = [k for k, s in enumerate(meas.stations.index) if s == 0]
    return home if len(home) >= MIN_HOME_VIEWS else None


def home_C(meas: robot.Measurements) -> list[np.ndarray]:
    """Each view's board pose seen from the camera at home: ``D_s C_k`` with each station's
    predicted pose (``robot_stations``); ``meas.C`` when the head stayed at home."""
    if not meas.station_count:
        return meas.C
    D = [np.eye(4), *meas.stations.predicted]
    return [D[s] @ C for s, C in zip(meas.stations.index, meas.C, strict=True)]


def single_methods(sweeps: dict[int, robot.Sweep], X, W, nominal: KinematicModel,
                   meas: robot.Measurements):
    """Stages 2 and 3: link-by-link (with the hand-eye ``X``) and axis-based (no X; ``W``
    only starts the axis lines' frame, then X and W are fitted with the links held),
    each alone, and as starts of the joint refinement. A method that cannot run says
    why: (link-by-link, its error, axis-based, its error)."""
    lbl, lbl_error = None, None
    if meas.fixed:
        why = ("needs the camera on the flange; with the head beside the arm the joint "
               "refinement starts from the nominal and the controller's models")
        return None, f"link-by-link {why}", None, f"axis-based {why}"
    try:
        lbl = robot.link_by_link(sweeps, X, nominal)
    except SolveError as exc:
        lbl_error = str(exc)
    axis, axis_error = None, None
    try:
        axis_model, W_axis = robot.axis_based(sweeps, nominal, W)
        axis = robot.refine(axis_model, X, W_axis, meas, mask=robot.frames_only_mask(nominal))
    except SolveError as exc:
        axis_error = str(exc)
    return lbl, lbl_error, axis, axis_error


def joint_refinement(meas: robot.Measurements, start: KinematicModel, X,
                     other_starts: list[tuple[KinematicModel, np.ndarray, np.ndarray]]
                     ) -> robot.RefineResult:
    """Stage 4: the joint refinement (4.11) of the minimal parameter set over every
    training view, from ``start`` (the link-by-link model, when it ran) with X and W
    averaged over the views, and from each of ``other_starts``; the lowest cost wins
    (the first of equals)."""
    W = handeye.average_W(handeye.flange_poses([start.fk(q) for q in meas.q], meas.fixed),
                          home_C(meas), X)
    return robot.refine(start, X, W, meas, extra_starts=other_starts)


def joint_refinement_from(meas: robot.Measurements,
                          starts: dict[str, tuple[KinematicModel, np.ndarray, np.ndarray]]
                          ) -> tuple[robot.RefineResult, str, dict[str, float]]:
    """Stage 4 from named starts (model, X, W), each refined with the first start's
    parameter set, as ``joint_refinement`` does; the lowest cost wins, the first of
    equals (``robot.first_of_least``). Returns the refinement, the name of the start it
    came from, and the RMS residual (px) each start ended at."""
    first = next(iter(starts.values()))[0]
    mask = robot.identifiable_mask(first)
    results = {name: robot.refine(model, X, W, meas, mask=mask)
               for name, (model, X, W) in starts.items()}
    won = robot.first_of_least({name: r.rms for name, r in results.items()})
    return results[won], won, {name: r.rms for name, r in results.items()}


def outlier_views(ref: robot.RefineResult, meas: robot.Measurements) -> dict[int, float]:
    """Training views (index into the measurements: RMS px) whose corner residual at the
    refined model exceeds ``OUTLIER_FACTOR`` times the median view's and
    ``OUTLIER_MIN_PX``."""
    per_view = view_rms(ref, meas)
    limit = max(OUTLIER_FACTOR * float(np.median(per_view)), OUTLIER_MIN_PX)
    return {k: float(e) for k, e in enumerate(per_view) if e > limit}


def view_rms(ref: robot.RefineResult, meas: robot.Measurements) -> np.ndarray:
    """Each training view's RMS corner residual (px) at the refined model."""
    r = robot.residuals(ref.model, ref.X, ref.W, meas, stations=ref.stations or None)
    ends = np.cumsum(robot.rows_per_view(meas))[:-1]
    return np.array([np.sqrt(2 * np.mean(v ** 2)) for v in np.split(r, ends)])


def outlier_corners(ref: robot.RefineResult, meas: robot.Measurements
                    ) -> dict[int, np.ndarray]:
    """Per training view (index into the measurements), the board corners (indices into
    the board's points) whose residual at the refined model exceeds ``CORNER_FACTOR``
    times the median corner's and ``CORNER_MIN_PX``; views without any are not listed.
    Empty for pose measurements (no corners)."""
    if meas.corners is None:
        return {}
    r = robot.residuals(ref.model, ref.X, ref.W, meas,
                        stations=ref.stations or None).reshape(-1, 2)
    miss = np.linalg.norm(r, axis=1)
    limit = max(CORNER_FACTOR * float(np.median(miss)), CORNER_MIN_PX)
    out, start = {}, 0
    for k, corners in enumerate(meas.corners):
        seen = np.flatnonzero(np.all(np.isfinite(np.reshape(corners, (-1, 2))), axis=1))
        bad = seen[miss[start:start + len(seen)] > limit]
        start += len(seen)
        if len(bad):
            out[k] = bad
    return out


def free_camera(ref: robot.RefineResult, meas: robot.Measurements,
                prior_sigma: dict[str, float] | None, held: list[BoardView]):
    """Stage 5: the refinement with the camera free as well, the intrinsics in use as a
    prior. Returns the refinement, the camera model (None when it stays held), a note
    saying why it stayed held, and the held-out views, measured again with the camera
    model the arm model now uses."""
    free, cam = robot.refine_with_camera(ref, meas, prior_sigma or {})
    if free.rms > 1.05 * ref.rms + 0.01:  # a superset of ref's model cannot fit worse
        note = (f"the refinement with the camera free ended worse ({free.rms:.3f} px RMS) "
                f"than with it held ({ref.rms:.3f} px); the camera is held as given")
        return ref, None, note, held
    held = [replace(v, C=estimate_pose(meas.obj, v.corners, cam.K, cam.dist).T_cam_target)
            for v in held]
    return free, cam, None, held


def heldout_table(nominal: KinematicModel, he, ref: robot.RefineResult, lbl,
                  axis: robot.RefineResult | None, meas: robot.Measurements,
                  held: list[BoardView]) -> dict[str, dict | None]:
    """Stage 6: the held-out errors before calibration (nominal model with its hand-eye),
    after, and of link-by-link and axis-based alone (None when they did not run)."""
    fixed = meas.fixed
    heldout = {"before": heldout_errors(nominal, he.X, he.W, held, fixed),
               "after": heldout_errors(ref.model, ref.X, ref.W, held, fixed),
               "link_by_link": None, "axis_based": None}
    if lbl is not None:
        W_lbl = handeye.average_W([lbl.model.fk(q) for q in meas.q], meas.C, he.X)
        heldout["link_by_link"] = heldout_errors(lbl.model, he.X, W_lbl, held)
    if axis is not None:
        heldout["axis_based"] = heldout_errors(axis.model, axis.X, axis.W, held)
    return heldout


def moved_from_controller(controller: KinematicModel, he_controller, ref: robot.RefineResult,
                          qs: list[np.ndarray], fixed: bool = False) -> dict[str, float]:
    """How far the calibrated model puts the camera from where the controller's own model
    (with its hand-eye) does, over the configurations ``qs``: the camera in the target
    frame under each, free of the base frame's gauge."""
    gap = [np.linalg.norm(robot.target_cam(ref.model, ref.X, ref.W, q, fixed)[:3, 3]
                          - robot.target_cam(controller, he_controller.X, he_controller.W, q,
                                             fixed)[:3, 3]) for q in qs]
    return {"position_rms_m": float(np.sqrt(np.mean(np.square(gap)))),
            "position_max_m": float(np.max(gap)), "configurations": len(qs)}


def _sweep_spans(sweeps: dict[int, robot.Sweep]) -> dict[str, float]:
    return {f"joint{j + 1}": float(np.degrees(np.ptp([q[j] for q in sw.q])))
            for j, sw in sweeps.items()}


def _again_without(views: list[BoardView], train: list[BoardView], rejected: dict[int, float],
                   corners: dict[int, np.ndarray], rms: np.ndarray, timings: dict[str, float],
                   **solve_args) -> RobotSolution:
    """The whole solve again without the training views ``rejected`` (``outlier_views``)
    and the outlying ``corners`` of others (``outlier_corners``; their board pose
    measured again without them), once; the solution names both, and its timings keep
    the first pass's. A view left with fewer than ``MIN_CORNERS`` is rejected whole
    (``rms``: each view's RMS px, what ``rejected_views`` records)."""
    obj, K, dist = solve_args["obj"], solve_args["K"], solve_args["dist"]
    rejected = dict(rejected)
    replaced: dict[int, BoardView] = {}
    for k, bad in corners.items():
        if k in rejected:
            continue
        view = train[k]
        kept = np.array(view.corners, float).reshape(-1, 2)
        kept[bad] = np.nan
        if np.all(np.isfinite(kept), axis=1).sum() < MIN_CORNERS:
            rejected[k] = float(rms[k])
            continue
        try:
            C = estimate_pose(obj, kept, K, dist).T_cam_target
        except SolveError:
            rejected[k] = float(rms[k])
            continue
        replaced[id(view)] = replace(view, corners=kept, C=C)
    dropped = {id(train[k]) for k in rejected}
    again = solve_robot([replaced.get(id(v), v) for v in views if id(v) not in dropped],
                        reject_outliers=False, **solve_args)
    again.rejected_views = {train[k].label: e for k, e in rejected.items()}
    again.rejected_corners = {train[k].label: [int(i) for i in bad]
                              for k, bad in corners.items() if k not in rejected}
    again.timings_s = {f"{k} (with outliers)": t for k, t in timings.items()} | again.timings_s
    return again


def station_measurements(train: list[BoardView], head: HeadGeometry | None,
                         encoder_sigma_rad: tuple[float, float, float] | None
                         ) -> robot_stations.Stations | None:
    """The training views' head stations for the refinement (``robot_stations``): each
    station's head angles as recorded (the mean over its views), its pose from home as
    ``head`` predicts it from the home views' angles, and the prior's information. None
    when every view is at home; a ``SolveError`` when views were taken elsewhere with
    no head geometry, or without their angles recorded."""
    away = sorted({v.station for v in train if v.station})
    if not away:
        return None
    if head is None:
        raise SolveError(f"robot-kinematics: views at head stations {away} but no head "
                         "geometry to see them from home (the intrinsics in use came "
                         "without head_geometry)")

    def angles(station: int) -> tuple[float, float, float]:
        read = [v.head for v in train if v.station == station and v.head is not None]
        if not read:
            return (0.0, 0.0, 0.0) if station == 0 else _no_angles(station)
        return tuple(float(a) for a in np.mean(np.array(read, float), axis=0))

    home = angles(0)
    number = {s: k + 1 for k, s in enumerate(away)}
    out = robot_stations.Stations(np.array([number.get(v.station, 0) for v in train]))
    for s in away:
        D, info = robot_stations.predicted_station(head, home, angles(s), encoder_sigma_rad)
        out.angles.append(angles(s))
        out.predicted.append(D)
        out.information.append(info)
    return out


def _no_angles(station: int):
    raise SolveError(f"robot-kinematics: the captures at head station {station} recorded "
                     "no head angles")


@with_one_blas_thread
def solve_robot(views: list[BoardView], nominal: KinematicModel, obj: np.ndarray,
                K: np.ndarray, dist: np.ndarray, prior_sigma: dict[str, float] | None,
                refine_camera: bool = True, reject_outliers: bool = True,
                controller: KinematicModel | None = None, fixed: bool = False,
                head: HeadGeometry | None = None,
                encoder_sigma_rad: tuple[float, float, float] | None = None
                ) -> RobotSolution:
    """Stages 1-6 above on the board views. ``prior_sigma``: 1-sigma of the intrinsics
    ``K`` (their prior weight when ``refine_camera``). With ``reject_outliers``, training
    views the refined model misses by far (``outlier_views``) are left out once and the
    solve runs again; the solution lists them in ``rejected_views``. ``controller``: the
    arm's own (factory) model, when it reports one: a start of the joint refinement, and
    held out like the nominal model. ``fixed``: the camera stands beside the arm and the
    flange holds the board (X = T_base_cam, W = T_flange_target; no link-by-link or
    axis-based start); with ``head``, its calibrated geometry, training views taken with
    the head re-aimed (``BoardView.station``) are seen from their station, each station's
    pose refined from the geometry's prediction (``station_measurements``;
    ``encoder_sigma_rad``: the head's readings' sigma, None: exact)."""
    timings: dict[str, float] = {}
    stage = stage_timer(timings)
    train, held = split_views(views)
    meas = robot.Measurements([v.q for v in train], C=[v.C for v in train],
                              corners=[v.corners for v in train], obj=obj, K=K, dist=dist,
                              fixed=fixed,
                              stations=station_measurements(train, head, encoder_sigma_rad)
                              if fixed else None)
    with stage("hand-eye (nominal arm)"):
        closed, he = hand_eye(nominal, meas)
    he_controller = None
    if controller is not None:
        with stage("hand-eye (controller's arm model)"):
            he_controller = hand_eye(controller, meas)[1]
    sweeps = _sweeps(train)
    with stage("link-by-link and axis-based"):
        lbl, lbl_error, axis, axis_error = single_methods(sweeps, he.X, he.W, nominal, meas)
    with stage("joint refinement"):
        # the starts of ``joint_refinement``, in its order, named
        first = lbl.model if lbl is not None else nominal
        named = {"link-by-link" if lbl is not None else "nominal (W averaged)": (
            first, he.X, handeye.average_W(handeye.flange_poses(
                [first.fk(q) for q in meas.q], fixed), home_C(meas), he.X))}
        named["nominal"] = (nominal, he.X, he.W)
        if axis is not None:
            named["axis-based"] = (axis.model, axis.X, axis.W)
        if controller is not None:
            named["controller"] = (controller, he_controller.X, he_controller.W)
        ref, won, start_rms = joint_refinement_from(meas, named)
    rejected = outlier_views(ref, meas) if reject_outliers else {}
    corners = outlier_corners(ref, meas) if reject_outliers else {}
    if (rejected or corners) and len(train) - len(rejected) >= MIN_TRAINING_VIEWS:
        return _again_without(views, train, rejected, corners, view_rms(ref, meas), timings,
                              nominal=nominal,
                              obj=obj, K=K, dist=dist, prior_sigma=prior_sigma,
                              refine_camera=refine_camera, controller=controller,
                              fixed=fixed, head=head, encoder_sigma_rad=encoder_sigma_rad)
    with stage("plain D-H"):  # its rank deficiency, at the refined solution
        dh_sv = robot.jacobian_singular_values(ref.model, ref.X, ref.W, meas,
                                               robot.dh_mask(nominal))
    cam, camera_note = None, None
    if refine_camera:
        with stage("camera free"):
            ref, cam, camera_note, held = free_camera(ref, meas, prior_sigma, held)
    with stage("held-out"):
        heldout = heldout_table(nominal, he, ref, lbl, axis, meas, held)
        moved = None
        if controller is not None:
            heldout["factory"] = heldout_errors(controller, he_controller.X, he_controller.W,
                                                held, fixed)
            moved = moved_from_controller(controller, he_controller, ref,
                                          [v.q for v in (held or train)], fixed)
    return RobotSolution(ref, cam, he, closed, heldout, lbl, lbl_error, axis, axis_error, dh_sv,
                         _sweep_spans(sweeps), meas, len(train), len(held), timings,
                         camera_note, views, controller_hand_eye=he_controller,
                         moved_from_controller=moved, refinement_start=won,
                         refinement_starts_rms_px=start_rms)
