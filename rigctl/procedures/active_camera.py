"""``active-camera``: intrinsics from known head rotations (thesis chapter 3), automated.

Sequence: home; reference capture; with an arm, the camera moved ``shift_mm`` sideways
and captured (scene depths, for the parallax), then home again; pan +-theta_p, tilt
+-theta_t; the wide pans and tilts (``wide_deg``); rolls (``rolls_deg``, every 45 deg); each
captured after settling, with the encoder angles actually reached.

Solve (``rigctl.calib.active_pipeline``): extract contours in the reference image; track
them through pan+ and tilt+ with the thesis's shift search; estimate K by Strategy B;
track the small, then the wide motions, then the rolls, each tier by prediction from a
refinement on the ones before; then Strategies A-D and the nonlinear refinement. Writes
``result.json``, plots, and OpenCV / ROS exports.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field

from rigctl.calib.active_angles import head_encoder_sigmas
from rigctl.calib.active_pipeline import (
    SHIFT,
    STATION_PREFIX,
    ActiveSettings,
    ActiveSolution,
    PanTiltStage,
    pan_tilt_stage,
    solve_active,
)
from rigctl.calib.active_plots import draw_active_plots
from rigctl.calib.active_tracking import roll_tiers
from rigctl.calib.threads import map_in_threads
from rigctl.errors import SolveError
from rigctl.procedures.plot_import import import_matplotlib_in_background
from rigctl.vision.tracking import searchable

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
from .camera_settings import settings_of_run

log = logging.getLogger(__name__)

# The head's rotations repeated at the second station (``second_station_mm``): the
# pans and tilts the centre of projection's offset shifts (its component along the axis
# trades with the focal length) and the rolls it swings (its component across trades
# with the centre). Synthetic correspondences of random world 62019's rig (25 contours
# on a board at 0.56 m, one at 1.9 m; 0.16 m closer at the second station): sigma of
# fx 0.62 -> 0.11 px, cx 1.11 -> 0.33 px; with every pose repeated 0.08 / 0.26 px.
SECOND_STATION_POSES = {"pan+8": (8.0, 0.0, 0.0), "pan-8": (-8.0, 0.0, 0.0),
                        "tilt+8": (0.0, 8.0, 0.0), "tilt-8": (0.0, -8.0, 0.0),
                        "roll+90": (0.0, 0.0, 90.0), "roll-180": (0.0, 0.0, -180.0),
                        "roll-90": (0.0, 0.0, -90.0)}


class ActiveCameraParams(Params):
    pan_deg: float = Field(3.0, ge=0.5, le=10.0)
    tilt_deg: float = Field(3.0, ge=0.5, le=10.0)
    # Wider pans and tilts, tracked by prediction from the small ones: the centre's
    # information grows with the angle, and contours that leave a narrow lens's view at
    # the widest are dropped. Unseen worlds 6000-6019 (bench active-worlds): [15] ->
    # [15, 25]: centre median 0.76 -> 0.63 px, worst 3.8 -> 3.0 px (none: 1.2 / 169 px
    # on worlds 5000-5019). [15, 25] -> [8, 12, 16, 20, 25]: a narrow lens (f > 1300 px)
    # keeps most of a sparse scene at the middle angles, which it loses at 25 deg; four
    # sets of 20 worlds (seeds 5000, 6000, 14000, 16000; centre errors in px):
    # median 0.29/0.30/0.49/0.26 -> 0.27/0.27/0.40/0.25, p90 1.11/1.17/1.52/1.18 ->
    # 1.03/0.81/1.40/1.24, worst 2.00/1.66/4.00/3.32 -> 1.36/1.29/2.86/2.54; solve +2-3 s.
    wide_deg: list[Annotated[float, Field(gt=0, le=45)]] = Field(
        default_factory=lambda: [8.0, 12.0, 16.0, 20.0, 25.0],
                                  description="wider pan and tilt angles, each captured "
                                  "at + and -; contours that leave the image are dropped")
    # -180 rather than +180: position-mode servos span 0..4095 pulses, so +180 deg from the
    # centre (4096) is one pulse out of range; the image rotation is the same. Rolls tell
    # the centre from the tangential terms (a shift against a quadratic field), so every
    # 45 deg: six sets of 20 unseen worlds (bench active-worlds, seeds 5000-12019), centre
    # error p90 0.70-1.48 -> 0.74-1.17 px, worst 1.20-2.09 -> 1.13-2.00 px, against
    # [90, -180, -90]; every 30 deg did no better. Up to +135, back to -45, then down
    # to -180: each tier of rolls (+-45, +-90, ...; ``roll_tiers``) is complete as soon
    # as its second roll is in, so a live run tracks it while the head rolls on
    # (``PanTiltStage.take_roll``); the roll travels 630 deg, as the sweep +45 .. +135,
    # -180 .. -45 did (position mode cannot pass through +-180).
    rolls_deg: list[float] = Field(
        default_factory=lambda: [45.0, 90.0, 135.0, -45.0, -90.0, -135.0, -180.0])
    settle_s: float = Field(0.3, ge=0)
    # The centre is told from how the image's own warps (perspective, tangential terms)
    # differ, which grows with the contours' distance from the centre: 0.8 -> 0.95 on 72
    # unseen worlds (bench active-worlds harness, seeds 40003-40036 narrow lenses,
    # 40040-40059, 40060-40099): centre error RMS 0.77/0.45/0.57 -> 0.66/0.38/0.52 px, p90
    # 1.37/0.77/1.00 -> 1.04/0.53/0.99 px, worst 1.45/0.82/1.41 -> 1.45/0.82/1.38 px;
    # better by > 0.02 px on 29 worlds, worse on 7; |error/sigma| > 3 unchanged (0-0.6 %).
    window: float = Field(0.95, gt=0.1, le=0.95, description="central window for contours")
    min_points: int = Field(40, ge=10)
    # None: k1, k2, p1, p2 when the arm's move measured the scene's depths, else k1, k2.
    # Random worlds 2000-2011: with depths, an unmodelled tangential term of a few 1e-4
    # moved the centre by 2-12 px with a sigma of 0.1-0.3 px, and estimating p1, p2 put
    # 96 % of the errors within 3 sigma; without depths, p1, p2 trade against the centre
    # (median centre error 2.6 -> 4.8 px, worst 126 px), so they stay out.
    distortion_terms: Literal[0, 1, 2, 3, 4, 5] | None = Field(
        None, description="None: automatic (5 with scene depths, else 2); 0; 1: k1; "
        "2: k1, k2; 3: k1, k2, k3; 4: k1, k2, p1, p2 (tangential); 5: all five")
    assumed_centre: list[float] | None = Field(None, description="default: image centre")
    nodal_offset_mm: float = Field(
        3.0, ge=0, le=100, description="how far the camera's centre of projection may be "
        "off the head's axes: enters the reported sigma (parallax under rotation)")
    scene_depth_m: float = Field(
        1.0, ge=0.1, le=100, description="typical distance of the scene the camera sees")
    shift_mm: float = Field(
        10.0, ge=0, le=50, description="with an arm: move the camera this far sideways "
        "(head at home) for one more capture, which measures each contour's depth so that "
        "the centre of projection's offset from the head's axes is estimated instead of "
        "only bounded; 0 skips it")
    # bench active-worlds, 80 unseen worlds (70000-70039, 71000-71039), without -> with
    # 200 mm: centre p90 0.53/1.02 -> 0.39/0.74 px, worst 1.57/1.91 -> 1.69/1.40 px, focal
    # worst 0.056/0.044 -> 0.047/0.028 %, none beyond 3 sigma either way; random world
    # 62019 through the stand-ins 0.156 % / 3.2 px -> 0.062 % / 0.54 px. Off by default
    # until the whole chain (bench worlds) has run with it on fresh worlds.
    second_station_mm: float = Field(
        0.0, ge=0, le=500, description="with an arm: after the head's rotations, move the "
        "camera this far back along its optical axis (away from the scene) and repeat a "
        "few of them there, with their own sideways move: the scene's depths then differ "
        "between the two stations, which tells the centre of projection's offset apart "
        "from the centre and focal length where one station's scene lies at one depth "
        "(e.g. a board filling the view); 0 skips it")


class ActiveCamera(Procedure):
    name = "active-camera"
    summary = "Camera intrinsics from known pan/tilt/roll head rotations (thesis ch. 3)."
    params_model = ActiveCameraParams
    devices = ("head", "camera")
    optional_devices = ("arm",)
    moves = ("head", "arm")  # whose settle_s is the default wait before a capture

    def plan(self, params: ActiveCameraParams, config) -> list:
        steps: list = []
        home = None
        if config.devices.arm is not None:
            home = tuple(math.radians(v) for v in config.devices.arm.home_deg)
            steps.append(MoveArmJoints(home, "arm home"))
        if home is not None and config.devices.head.fixed:
            # the head stands beside the arm: the arm cannot move the camera
            steps.append(Note("head beside the arm (devices.head.mount: fixed): the arm does "
                              "not move the camera, so no sideways move measures the scene's "
                              "depths; the parallax is not identifiable"))
            home = None
        for label, pan, tilt, roll in head_poses(params, config.devices.head.limits_rad()):
            steps += [MoveHead(pan, tilt, roll, label), Settle(params.settle_s),
                      CaptureStep(label)]
            if label == "ref" and home is not None and params.shift_mm > 0:
                steps += _shift_steps(config, home, params)
        if params.second_station_mm > 0:
            if home is not None and params.shift_mm > 0:
                steps += _second_station_steps(config, home, params)
            else:
                steps.append(Note("second station: skipped, it needs an arm and its sideways "
                                  "move (shift_mm > 0) for the depths there"))
        steps.append(MoveHead(0.0, 0.0, 0.0, "home"))
        return steps

    def capture_work(self, params: ActiveCameraParams):
        """Each capture's edge map, taken while the head moves on to the next pose; the
        solve's stages up to the rolls, and then the rolls' tiers, taken while the head
        rolls (``WorkWhileMoving``)."""
        return WorkWhileMoving(params)

    uses_solve_process = True

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        """Thesis chapter 3 on the run's captures (``rigctl.calib.active_pipeline``)."""
        params: ActiveCameraParams = ctx.params
        with ctx.stage("load images"):
            caps = {c.meta["label"]: c for c in ctx.captures() if c.image_path is not None}
            # in a live run, the images and their edge maps taken while the rig moved on
            # (``capture_work``); the others read from disk, side by side (decoding
            # releases the interpreter)
            prefetched = {label: ctx.prefetched[c.index] for label, c in caps.items()
                          if c.index in ctx.prefetched}
            to_load = [label for label in caps if label not in prefetched]
            loaded = dict(zip(to_load, map_in_threads(lambda lb: caps[lb].load_image(),
                                                      to_load), strict=True))
            images = {label: prefetched[label][0] if label in prefetched else loaded[label]
                      for label in caps}
            emaps = {label: outcome[1] for label, outcome in prefetched.items()}
            ahead = next((outcome[2] for outcome in prefetched.values() if len(outcome) > 2),
                         None)
        if ctx.prefetched:
            log.info("active-camera: %d of %d captures' edge maps taken while the rig "
                     "moved", len(prefetched), len(caps))
        angles = {k: tuple(c.meta["head"][a] for a in ("pan", "tilt", "roll"))
                  for k, c in caps.items()}
        settings = _run_settings(params, (c.meta for c in caps.values()), ctx.config)
        with ctx.stage("pipeline"):
            solution = solved_after_captures(ctx.after_captures, images, angles, settings)
            if solution is None:
                # a live run started the solve's second process while the rig moved, and
                # took the stages up to the rolls while it rolled; a re-solve starts the
                # process as the rolls' tiers begin, and takes every stage (and so does a
                # run whose solve after the last capture did not fit: that solve went on
                # from the stages taken ahead, whose tracker it moved on)
                if ctx.after_captures is not None:
                    ahead = None
                solution = solve_active(images, angles, settings, emaps, ctx.solve_process,
                                        ahead=ahead)
        ctx.timings_s.update({f"pipeline: {k}": v for k, v in solution.timings_s.items()})
        # the size and focus these intrinsics hold for (checked by procedures using them)
        solution.result["camera_settings"] = settings_of_run(ctx.run)
        with ctx.stage("exports"):
            _exports(ctx, solution.result)
        ctx.defer("plots", lambda: _plots(ctx, images, solution.contours, solution.matches,
                                          solution.refined, solution.order))
        return solution.result


@dataclass
class SolvedAfterCaptures:
    """The whole solve, taken on the capture worker once the last capture was in
    (``WorkWhileMoving.after_last_capture``), and the inputs it was taken from."""

    images: dict[str, np.ndarray]
    angles: dict[str, tuple[float, float, float]]
    settings: ActiveSettings
    outcome: ActiveSolution | SolveError
    seconds: float

    def differs(self, images: dict, angles: dict, settings: ActiveSettings) -> str | None:
        """Why the solve of the recorded captures would not be this one, or None: it
        must hold the same captures (labels in order, the same image objects, the same
        angles) and the same settings."""
        if list(images) != list(self.images):
            return f"the captures differ ({len(images)} against {len(self.images)})"
        if any(images[label] is not self.images[label] or
               tuple(angles[label]) != tuple(self.angles[label]) for label in images):
            return "a capture differs"
        if settings != self.settings:
            return "the settings differ"
        return None


def solved_after_captures(after: Any, images: dict, angles: dict,
                           settings: ActiveSettings) -> ActiveSolution | None:
    """The solve taken after the last capture (``after``: a ``SolvedAfterCaptures``),
    when it was taken from these captures and settings (its ``SolveError`` raised
    again); else None (why, logged), and the solve takes every stage itself."""
    if not isinstance(after, SolvedAfterCaptures):
        return None
    why = after.differs(images, angles, settings)
    if why is not None:
        log.info("active-camera: the solve taken after the last capture is not used "
                 "(%s); solving again", why)
        return None
    log.info("active-camera: solved from the last capture on, while the rig made its "
             "last moves (%.1f s)", after.seconds)
    if isinstance(after.outcome, SolveError):
        raise after.outcome
    solution = after.outcome
    solution.timings_s = {k if k.startswith("while moving: ") else
                          f"after the last capture: {k}": v
                          for k, v in solution.timings_s.items()}
    return solution


def _run_settings(params: ActiveCameraParams, metas, config) -> ActiveSettings:
    """``_settings`` with the encoder sigmas of the head's servos, as the captures'
    metadata (``metas``) or the rig file (``config``) name them (``servo_models``)."""
    return _settings(params, head_encoder_sigmas(servo_models(metas, config)))


def _settings(params: ActiveCameraParams, encoder_sigma_rad) -> ActiveSettings:
    """The solve's settings: the procedure's parameters without the motion plan, and the
    head's encoder sigmas (rad; None: the recorded angles are exact)."""
    return ActiveSettings(window=params.window, min_points=params.min_points,
                          distortion_terms=params.distortion_terms,
                          assumed_centre=params.assumed_centre,
                          nodal_offset_mm=params.nodal_offset_mm,
                          scene_depth_m=params.scene_depth_m,
                          shift_m=params.shift_mm / 1000.0,
                          encoder_sigma_rad=encoder_sigma_rad)


class WorkWhileMoving:
    """A live run's work on each capture as it comes in (``capture_work``): its edge map
    (``image_and_edge_map``); when the first roll comes in, the solve's stages up to the
    rolls on the captures before it (``active_pipeline.pan_tilt_stage``), which then run
    while the head rolls (about 10 s of the demo's motion); and with each roll, the
    rolls' tiers it completes (``PanTiltStage.take_roll``, tiers planned from
    ``rolls_deg``). That outcome goes with the first roll's; the solve uses it when it
    fits the recorded captures (``PanTiltStage.fits``) and takes the stages itself
    otherwise, to the same numbers. A ``SolveError`` there is left for the solve to
    raise. matplotlib, for the plots after the result, is imported on a thread as the
    run begins (``plot_import``)."""

    def __init__(self, params: ActiveCameraParams) -> None:
        self.params = params
        # every labelled capture with its head angles, in the captures' order: image,
        # angles, edge map and metadata, by label
        self.captures: dict[str, tuple[np.ndarray, tuple, Any, dict]] = {}
        self.started = False
        self.ahead: PanTiltStage | None = None
        # the rolls' tiers as planned (the recorded angles group the same way, checked
        # by ``PanTiltStage.fits``)
        rolls = {label: (pan, tilt, roll) for label, pan, tilt, roll in head_poses(params)
                 if label.startswith("roll")}
        self.roll_plan = roll_tiers(list(rolls), rolls)
        import_matplotlib_in_background()  # for the plots after the result

    def __call__(self, image: np.ndarray, meta: dict) -> tuple:
        image, emap = image_and_edge_map(image)
        label, head = meta.get("label"), meta.get("head")
        if not label or head is None:
            return image, emap
        angle = tuple(head[a] for a in ("pan", "tilt", "roll"))
        self.captures[label] = (image, angle, emap, meta)
        if label.startswith(STATION_PREFIX):
            return image, emap
        if label != "ref":  # searched by the tracking: its search maps now, off the solve
            searchable(emap)
        if self.started:  # a roll after the first: the rolls' stages go on
            if self.ahead is not None and label.startswith("roll"):
                self._take_roll(label, image, angle, emap)
            return image, emap
        if not label.startswith("roll"):
            return image, emap
        self.started = True
        before = [lb for lb in self.captures if not lb.startswith(("roll", STATION_PREFIX))]
        try:
            # the encoders' sigmas only enter the final refinement: checked there
            images, angles, emaps = self._of(before)
            ahead = pan_tilt_stage(images, angles, _settings(self.params, None), emaps,
                                   rolls_follow=True)
        except SolveError as exc:
            log.info("active-camera: the stages up to the rolls, taken while the rig "
                     "rolls, failed (%s); the solve takes them again", exc)
            return image, emap
        log.info("active-camera: the stages up to the rolls taken while the rig rolls "
                 "(%.1f s)", sum(ahead.timings.values()))
        self.ahead = ahead
        ahead.roll_plan = self.roll_plan
        self._take_roll(label, image, angle, emap)
        return image, emap, ahead

    def after_last_capture(self, ctx: SolveContext) -> SolvedAfterCaptures:
        """The whole solve on the captures, taken on the capture worker as soon as the
        last is in, while the rig makes its last moves (the head's return home, a 180 deg
        roll: 3-4 s of motion in which the solve would otherwise wait), with the run's
        second process; ``ActiveCamera.solve`` uses it when it fits the recorded
        captures. The same call as the solve's, so the same numbers."""
        images, angles, emaps = self._of(list(self.captures))
        settings = _run_settings(self.params, (c[3] for c in self.captures.values()),
                                 ctx.config)
        started = time.perf_counter()
        try:
            outcome = solve_active(images, angles, settings, emaps, ctx.solve_process,
                                   ahead=self.ahead)
        except SolveError as exc:
            outcome = exc
        return SolvedAfterCaptures(images, angles, settings, outcome,
                                   time.perf_counter() - started)

    def _of(self, labels: list[str]) -> tuple[dict, dict, dict]:
        """The images, angles and edge maps of the captures ``labels``, by label."""
        return tuple({lb: self.captures[lb][i] for lb in labels} for i in range(3))

    def _take_roll(self, label: str, image: np.ndarray, angle: tuple, emap) -> None:
        """The rolls' stages that this roll capture completes (``take_roll``); after a
        failure there, none."""
        if self.ahead.failed is not None:
            return
        tracked = self.ahead.rolls_tracked
        self.ahead.take_roll(label, image, angle, emap)
        if self.ahead.failed is not None:
            log.info("active-camera: %s; the solve takes them again", self.ahead.failed)
        elif self.ahead.rolls_tracked > tracked:
            log.info("active-camera: roll tiers tracked while the rig rolls: %d of %d",
                     self.ahead.rolls_tracked, len(self.ahead.roll_plan))


def image_and_edge_map(image: np.ndarray) -> tuple[np.ndarray, Any]:
    """One capture's image and its edge map (``vision.contours.edge_map``): what the
    solve takes of each capture before anything else (``ActiveCamera.capture_work``)."""
    from rigctl.vision.contours import edge_map

    return image, edge_map(image)


def servo_models(metas, config) -> dict[str, str]:
    """The head's servo model per axis: as the captures' metadata (``metas``) recorded
    them (each servo's health, read from the servo), else as the rig file names them;
    axes with neither are left out."""
    for meta in metas:
        health = meta.get("head_health") or {}
        models = {axis: h.get("model") for axis, h in health.items() if isinstance(h, dict)}
        if all(models.get(axis) for axis in ("pan", "tilt", "roll")):
            return models
    head = getattr(getattr(config, "devices", None), "head", None)
    if head is None or not hasattr(head, "model_of"):
        return {}
    return {axis: m for axis in ("pan", "tilt", "roll") if (m := head.model_of(axis))}


def head_poses(params: ActiveCameraParams, limits_rad: dict | None = None
               ) -> list[tuple[str, float, float, float]]:
    """The captures' labels and head angles (rad): the reference, the small pans and
    tilts, the wide ones, then the rolls (``active_pipeline`` tracks them in that
    order). A wide pose beyond the head's soft limits (``limits_rad``) is left out; the
    others are checked against them by the runner."""
    p, t = math.radians(params.pan_deg), math.radians(params.tilt_deg)
    poses = [("ref", 0.0, 0.0, 0.0), ("pan+", p, 0.0, 0.0), ("pan-", -p, 0.0, 0.0),
             ("tilt+", 0.0, t, 0.0), ("tilt-", 0.0, -t, 0.0)]

    for w in params.wide_deg:
        a = math.radians(w)
        poses += [(f"pan{s * w:+g}", s * a, 0.0, 0.0) for s in (1, -1)
                  if _within(limits_rad, "pan", s * a)]
        poses += [(f"tilt{s * w:+g}", 0.0, s * a, 0.0) for s in (1, -1)
                  if _within(limits_rad, "tilt", s * a)]
    return poses + [(f"roll{r:+g}", 0.0, 0.0, math.radians(r)) for r in params.rolls_deg]


def _within(limits_rad: dict | None, axis: str, angle: float) -> bool:
    """Is the head ``angle`` (rad) on ``axis`` inside its soft limits (none: any)?"""
    lo, hi = (limits_rad or {}).get(axis, (-math.inf, math.inf))
    return lo <= angle <= hi


def _shift_steps(config, home: tuple, params: ActiveCameraParams) -> list:
    """The arm moves the camera ``shift_mm`` sideways (nominal model; head at home) for the
    SHIFT capture that measures the scene's depths, then returns home."""
    from rigctl.calib.active_depth import camera_shift_joints
    from rigctl.geometry.kinematics import nominal_ur
    from rigctl.procedures.planning import nominal_flange_cam

    q = camera_shift_joints(nominal_ur(config.devices.arm.model), home,
                            nominal_flange_cam(config), params.shift_mm / 1000.0)
    return [MoveArmJoints(tuple(float(v) for v in q), f"arm {params.shift_mm:g} mm sideways"),
            Settle(params.settle_s), CaptureStep(SHIFT), MoveArmJoints(home, "arm home")]


def second_station_joints(model, home, T_flange_cam: np.ndarray, back_mm: float,
                          shift_mm: float, joint_limits: list[tuple[float, float]]):
    """The second station's joints: the camera ``back_mm`` back along its (nominal)
    optical axis, and from there ``shift_mm`` sideways; 3/4 or 1/2 as far back when out
    of reach or ``joint_limits``. ``(back_mm, q_far, q_shift)``, or None when none is."""
    from rigctl.calib.active_depth import camera_shift_joints

    def inside(q) -> bool:
        return all(lo <= v <= hi for v, (lo, hi) in zip(q, joint_limits, strict=True))

    for back in (back_mm * f for f in (1.0, 0.75, 0.5)):
        try:
            q_far = camera_shift_joints(model, home, T_flange_cam, -back / 1000.0, axis=2)
            q_shift = camera_shift_joints(model, q_far, T_flange_cam, shift_mm / 1000.0)
        except SolveError:
            continue
        if inside(q_far) and inside(q_shift):
            return back, q_far, q_shift
    return None


def _second_station_steps(config, home: tuple, params: ActiveCameraParams) -> list:
    """The arm moves the camera ``second_station_mm`` back along its (nominal) optical
    axis (or 3/4 or 1/2 of that when out of reach or the soft limits; none, noted, when
    all are); there a reference capture, the sideways move's capture, and the head at
    ``SECOND_STATION_POSES`` (within the head's soft limits), each labelled with
    ``STATION_PREFIX``; then the head and the arm home."""
    from rigctl.geometry.kinematics import nominal_ur
    from rigctl.procedures.planning import nominal_flange_cam

    plan = second_station_joints(nominal_ur(config.devices.arm.model), home,
                                 nominal_flange_cam(config), params.second_station_mm,
                                 params.shift_mm, config.devices.arm.joint_limits_rad())
    if plan is None:
        return [Note(f"second station: the camera {params.second_station_mm:g} mm back (or "
                     f"3/4 or 1/2 of that) is out of the {config.devices.arm.model}'s reach "
                     "or soft limits; skipped")]
    back_mm, q_far, q_shift = plan
    notes = [] if back_mm == params.second_station_mm else [Note(
        f"second station: {back_mm:g} mm back instead of {params.second_station_mm:g} mm "
        "(out of reach or the soft limits)")]
    limits = config.devices.head.limits_rad()
    far = tuple(float(v) for v in q_far)
    steps: list = [*notes, MoveHead(0.0, 0.0, 0.0, "home"),
                   MoveArmJoints(far, f"arm {back_mm:g} mm back"),
                   Settle(params.settle_s), CaptureStep(STATION_PREFIX + "ref"),
                   MoveArmJoints(tuple(float(v) for v in q_shift),
                                 f"arm {params.shift_mm:g} mm sideways"),
                   Settle(params.settle_s), CaptureStep(STATION_PREFIX + SHIFT),
                   MoveArmJoints(far, f"arm {back_mm:g} mm back")]
    for label, deg in SECOND_STATION_POSES.items():
        angles = dict(zip(("pan", "tilt", "roll"), (math.radians(v) for v in deg), strict=True))
        outside = [axis for axis, a in angles.items() if not _within(limits, axis, a)]
        if outside:
            steps.append(Note(f"second station: {label} left out (beyond the head's soft "
                              f"limits in {', '.join(outside)})"))
            continue
        pan, tilt, roll = angles["pan"], angles["tilt"], angles["roll"]
        steps += [MoveHead(pan, tilt, roll, STATION_PREFIX + label), Settle(params.settle_s),
                  CaptureStep(STATION_PREFIX + label)]
    return [*steps, MoveHead(0.0, 0.0, 0.0, "home"), MoveArmJoints(home, "arm home")]


def _plots(ctx: SolveContext, images, contours, matches, refined, order) -> None:
    """The run's plots (``active_plots``): in the solve's second process when a re-solve
    started it with matplotlib imported (``SolveProcess.plots``), else here."""
    shown = next((m for m in ("roll-180", "roll+180") if m in matches), order[0])
    args = (ctx.plots_dir, images["ref"], [c.points for c in contours], shown, images[shown],
            [m.points for m in matches[shown] if m.ok], dict(refined.residuals_by_motion),
            refined.rms_px)
    process = ctx.solve_process
    if process is not None and process.plots:
        process.run(process.submit(draw_active_plots, *args), draw_active_plots, *args)
    else:
        draw_active_plots(*args)


def _exports(ctx: SolveContext, result: dict) -> None:
    from rigctl.exports import export_opencv, export_ros

    export_opencv(result, ctx.run.path / "camera.opencv.yaml", ctx.run.run_id)
    export_ros(result, ctx.run.path / "camera_info.yaml", ctx.run.run_id)


PROCEDURE = ActiveCamera()
