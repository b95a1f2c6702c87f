"""The active-camera solve as a pure pipeline: images and head angles in, intrinsics out.

Called by the ``active-camera`` procedure (on a run's captures) and by the benchmarks (on
images rendered from a world), so both measure the same code.

Stages (thesis chapter 3, automated):

1. contours in the reference image; the thesis's shift search through pan+ and tilt+;
   Strategy B for a first K (eqs. 3.19-3.22);
2. every pan/tilt motion tracked again by prediction from that K, a refinement on them
   alone, then the rolls tracked by prediction from the refined K, 45 degrees of roll
   at a time (``active_tracking.roll_tiers``);
3. Strategies A-D (eqs. 3.14-3.35) on the tracked contours;
4. the nonlinear refinement over every motion (``active_refine.refine``), started from
   D (or C, or the first K).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from rigctl.calib import active, head_model
from rigctl.calib.active_depth import SceneDepths, contour_shift, fit_depths, rigid_shifts
from rigctl.calib.active_jacobian import N_BASE
from rigctl.calib.active_refine import (
    DepthPrior,
    Motion,
    RefineResult,
    _undistort,
    param_names,
    refine,
    timed_refine,
)
from rigctl.calib.active_tracking import SHIFT, WIDE_WINDOW, Tracker, roll_tiers, tier_key, tiers
from rigctl.calib.blas_threads import with_one_blas_thread
from rigctl.calib.solve_process import SolveProcess, start_if_useful
from rigctl.calib.threads import map_in_threads, serial_here
from rigctl.errors import SolveError
from rigctl.timing import stage_timer
from rigctl.vision.tracking import track_in_range

log = logging.getLogger(__name__)

NEAREST_SCENE_M = 0.25  # the shift capture's search window covers contours this close
SHIFT_CROSS = 0.15  # and reaches this far across the move, per pixel along it
# Reference points used per contour in the refinements: edge points a pixel apart share
# most of their error (the covariance clusters them per contour anyway), so every second
# one carries nearly all the information at half the cost.
REFINE_STRIDE = 2
PREDICTION_STRIDE = 4
PREDICTION_ROUNDS = 2  # outlier rounds of a refinement that only predicts the next tier
TIER_WINDOW_PX = 24.0  # search window around a tier's prediction (the first K's: 12 px)
# Model error the refinement's covariance cannot see (edge localisation of blurred
# contours under perspective and distortion, terms beyond the five), added in quadrature
# to the reported intrinsics. Chosen on random worlds 5000-5019 and 6000-6019 (area-
# sampled renders): 71 % of |error / sigma| within 1 and 99.4 % within 3 (without a
# floor 56 % and 97 %); held-out worlds 7000-7019: 78 % and 100 %. (The 0.015 % and
# 0.2 px chosen before covered a renderer that drew every shape 0.65 px too large.)
MODEL_ERROR_FOCAL = 1.0e-4   # relative, per focal length
MODEL_ERROR_CENTRE_PX = 0.15  # per coordinate
DISTINCT_START_PX = 3.0  # the final refinement also starts from centres this far apart
# the final refinement's starts are refined side by side in up to this many threads, on
# every COARSE_FACTOR-th point (``_refine_from_starts``)
FINAL_THREADS = 2
COARSE_FACTOR = 4
SAME_END_PX = 1.0  # a coarse refinement ending this close to a basin's first is in it
# ... and, with the scene's depths, with the centre of projection's offset this close to
# that basin's (m): a refinement from zero offset can stop where the captures' angle
# offsets carry the parallax, a centre only 0.5 px from the true minimum's (random world
# 130046: offset 0.02 mm against a true 1.4 mm, claimed to 0.03 mm; the rolls' start,
# scouted into that basin by its centre, ends at the true offset at a lower cost)
SAME_END_OFFSET_M = 0.0005
# A start whose coarse refinement's robust cost is over this many times the least of the
# coarse stage's is not refined on all points (``_refine_from_starts``). Random worlds
# 130000-130059: 9 of 60 ended in two basins; each of the 6 coarse ends over 100 times
# the least was either not chosen or refined to where the chosen one was, while ends
# under 3 times the least did reverse (130013: 2.4 times, chosen).
HOPELESS_COARSE_RATIO = 10.0
# the starts after the first are scouted on every SCOUT_FACTOR-th point in SCOUT_ROUNDS
# outlier rounds (``_refine_from_starts``)
SCOUT_FACTOR = 16
SCOUT_ROUNDS = 2
# A roll predicted about a centre e px off is off by (I - R) e, one shift for the whole
# image (2 e at 180 degrees): searched for all contours at once within this many px
# before each is searched in TIER_WINDOW_PX. The pans' centre of a narrow or strongly
# distorted lens can be 20-30 px off (random worlds 70038, 24).
ROLL_JOINT_WINDOW_PX = 80.0
# The result names a contour that carries the intrinsics when it holds this share of the
# delete-one-contour jackknife's variance and the jackknife's sigma is this many times
# the refinement's own (``_carried_by``). Seed 26, an ordinary world, has 0.59 and 2.1;
# random world 62019, whose one far contour carries the offset, 0.98 and 6.1.
CARRIED_SHARE = 0.75
CARRIED_RATIO = 3.0
# The captures of a second station (the arm moved the camera along its optical axis, the
# head's rotations repeated there) carry this prefix; its own SHIFT capture measures the
# depths there. The scene's depths then differ between the stations even where they do
# not within one (a board filling the view), which tells the centre of projection's
# offset apart from the centre and the focal length.
STATION_PREFIX = "far:"


@dataclass
class ActiveSettings:
    """The solve's knobs (the procedure's parameters without the motion plan)."""

    window: float = WIDE_WINDOW  # see ``ActiveCameraParams.window``
    min_points: int = 40
    distortion_terms: int | None = None  # None: 4 with scene depths, else 2 (see below)
    assumed_centre: list[float] | None = None
    nodal_offset_mm: float = 3.0   # how far the centre of projection may be off the axes
    scene_depth_m: float = 1.0     # the scene's (inverse-mean) depth from the camera
    shift_m: float = 0.0           # the arm's sideways move before the SHIFT capture
    # sigma (rad) of the recorded pan, tilt and roll (``active_angles.encoder_sigma_rad``
    # of the head's servos): the final refinement estimates each capture's offset from
    # its reading; None: the recorded angles are exact
    encoder_sigma_rad: tuple[float, float, float] | None = None

    @property
    def parallax_sigma(self) -> float:
        """Per-axis sigma of the consider parameter ``s = o / depth`` of the refinement."""
        return self.nodal_offset_mm / 1000.0 / self.scene_depth_m


@dataclass
class ActiveSolution:
    result: dict[str, Any]
    refined: RefineResult
    contours: list
    matches: dict[str, list]
    order: list[str]
    timings_s: dict[str, float] = field(default_factory=dict)


def _strategies(tr: Tracker, roll_labels: list[str]) -> dict[str, Any]:
    """Strategies A-D of the thesis (eqs. 3.14-3.35) on the tracked contours."""
    th_p, th_t = tr.rel["pan+"][0], tr.rel["tilt+"][1]
    pt = tr.ok_in("pan+", "tilt+")
    ref, tilt, pan = tr.stats("ref", pt), tr.stats("tilt+", pt), tr.stats("pan+", pt)
    out: dict[str, Any] = {}

    def record(name: str, fn) -> None:
        try:
            est = fn()
            out[name] = {"fx": est["fx"], "fy": est["fy"], "cx": tr.centre[0] + est["dx"],
                         "cy": tr.centre[1] + est["dy"]}
        except SolveError as exc:
            out[name] = {"error": str(exc)}

    record("A", lambda: active.strategy_a(ref, tilt, pan, th_t, th_p))
    record("B", lambda: active.strategy_b(ref, tilt, pan, th_t, th_p))
    roll_pairs = []
    for label in roll_labels:
        idx = tr.ok_in(label)
        roll_pairs += list(zip(tr.stats("ref", idx), tr.stats(label, idx),
                               [tr.rel[label][2]] * len(idx), strict=True))
    record("C", lambda: active.strategy_c(ref, tilt, pan, th_t, th_p, roll_pairs))
    half = [m for m in roll_labels if abs(abs(tr.rel[m][2]) - math.pi) < math.radians(2)]
    if half:
        idx = tr.ok_in(half[0])
        record("D", lambda: active.strategy_d(
            ref, tilt, pan, th_t, th_p,
            list(zip(tr.stats("ref", idx), tr.stats(half[0], idx), strict=True))))
    else:
        out["D"] = {"error": "no 180-degree roll captured"}
    return out


def _as_start(K: RefineResult) -> dict:
    return {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy}


def _camera_start(K: RefineResult) -> dict:
    """A predicting refinement's start where the one before it ended: every camera
    parameter (its focal lengths, centre, mounting, roll axis, parallax and distortion).
    Started from its intrinsics alone, each refinement found the mounting and the roll
    axis again, in two to five times the evaluations (the demo's run: 82 where 12 do)."""
    return {**_as_start(K), "camera_x": K.x[:N_BASE + K.n_dist]}


def _final_start(K1: dict | RefineResult, strategies: dict, K0: dict) -> dict:
    """Where the final refinement starts: the refinement on every pan and tilt (its
    focal lengths, distortion and mounting; the centre from Strategy D or C, the image
    of the roll axis, when they solved), else D or C, else the first K. Strategies B-D
    fail on wide lenses (their quadratics ignore distortion); starting there from the
    first K left world 6007 (f 631 px, k1 -0.24) 40 % outliers and 6 px off."""
    closed = next((strategies[s] for s in ("D", "C") if "error" not in strategies[s]), None)
    if not isinstance(K1, RefineResult):
        return closed or K0
    start = _where_ended(K1)
    if closed is not None:
        start.update(cx=closed["cx"], cy=closed["cy"])
    return start


def _predicting_refinement(motions, start: dict, settings: ActiveSettings,
                           depths: SceneDepths | None) -> RefineResult:
    """A refinement that only predicts the next tier: k1, k2 and a quarter of the points,
    with the scene's depths when measured (a near scene turned away from the camera,
    moving by its parallax, biases the pans' centre otherwise: random world 11015, 33 px).
    It ends on its robust solve (no least-squares end): a tier is searched +-24 px
    around the prediction, far beyond what that end moves it. With ``_camera_start``
    the predicting refinements took 36 % less time on random worlds 81000-81019."""
    return refine(motions, start, n_dist=_distortion_terms(settings, None),
                  outer_iterations=PREDICTION_ROUNDS,
                  depths=None if depths is None else depths.prior(),
                  offset_sigma_m=settings.nodal_offset_mm / 1000.0, uncertainty=False,
                  least_squares_end=False, robust_cost=False)


def _measured_depths(tr: Tracker, K: RefineResult, settings: ActiveSettings, images: dict
                     ) -> SceneDepths | None:
    """The scene's depths from the SHIFT capture (reported), or None without one."""
    if SHIFT not in images or settings.shift_m <= 0:
        return None
    try:
        depths = _scene_depths(tr, K, settings.shift_m)
    except SolveError as exc:
        tr.report["scene_depth"] = f"not used: {exc}"
        return None
    tr.report["scene_depth"] = depths.as_dict()
    tr.inv_depth = depths.filled()
    return depths


def _starts(start: dict, K1: dict | RefineResult, K0: dict,
            K_last: dict | RefineResult | None = None) -> dict[str, dict]:
    """The final refinement's starts: ``_final_start``'s; the same with the roll axis's
    tilts and the centre's offset where the last predicting refinement put them
    (``K_last``, on every tier but the last: ``rolls``); and the same with the centre of
    the refinement on the pans and tilts (``K1``) and of the first K (the image's centre
    or the assumed one), those more than ``DISTINCT_START_PX`` from the ones before.

    The pans and tilts tell neither the roll axis nor the offset, and from zero a
    refinement can stop in a local minimum: random world 140052 (scene at 1.4-3.8 m,
    camera 2.2 mm off the axes) stopped with the offset at 0.08 mm, cy 1.2 px off (z
    -5.0); from the rolls' offset it ends 0.4 px off at a third less robust cost. Yet
    from there, random world 130023 ended 4 px off at 20 times the robust cost of the
    start from zero: both are tried.

    The roll centre and the pans' centre both carry the parallax of a camera off the
    axes (the rolls swing it round the roll axis; the pans see a near, turned scene at
    varying depth), and a refinement from there can stop in a local minimum: random
    world 11015 (UR3e, scene at 0.25 m, camera 2.6 mm off) ended 26 px off with the
    offset near 0; from the image's centre it finds the offset and the centre within
    0.1 px, at a lower cost."""
    out = {"final start": start}
    if isinstance(K_last, RefineResult) and K_last is not K1:
        rolls = {**start, "roll_tilts": K_last.x[7:9].copy()}
        if K_last.with_depths:
            rolls["offset_m"] = np.asarray(K_last.parallax, float).copy()
        out["rolls"] = rolls
    for name, centre in (("pans", _centre_of(K1)), ("first K", _centre_of(K0))):
        if all(math.dist(centre, (s["cx"], s["cy"])) > DISTINCT_START_PX
               for s in out.values()):
            out[name] = {**start, "cx": centre[0], "cy": centre[1]}
    return out


def _centre_of(K: dict | RefineResult) -> tuple[float, float]:
    return (K["cx"], K["cy"]) if isinstance(K, dict) else (K.cx, K.cy)


def _coarse(motions: list[Motion], factor: int) -> list[Motion]:
    """Every ``factor``-th reference point of each motion (the moved curves stay whole; a
    point correspondence keeps its partner)."""
    return [replace(m, ref_points=m.ref_points[::factor],
                    moved_points=m.moved_points if m.curve_mode else m.moved_points[::factor],
                    groups=None if m.groups is None else m.groups[::factor])
            for m in motions]


def _refine_from_starts(motions, starts: dict[str, dict], kwargs: dict,
                        timings: dict[str, float] | None = None,
                        helper: SolveProcess | None = None) -> tuple[RefineResult, dict]:
    """The refinement from the best of ``starts``. The first start is refined on every
    ``COARSE_FACTOR``-th point (``_coarse``, no covariance); the others, side by side
    with it, are first scouted: refined on every ``SCOUT_FACTOR``-th point in
    ``SCOUT_ROUNDS`` outlier rounds. A scout that ends where the first start's coarse
    refinement ended (``_same_end``: the centre within ``SAME_END_PX`` and, with depths,
    the centre of projection's offset within ``SAME_END_OFFSET_M``) is in its basin
    (``basin_of``); any other start is refined on every ``COARSE_FACTOR``-th point too,
    from where it was (the result is then the one without scouts: from the scout's end,
    random world 99209 ended 0.2 sigma elsewhere, another path to other outliers). Taken
    in their given order, a start whose coarse refinement ends where a basin's first
    start's did (``_same_end``) is in that basin; each basin is refined again on all
    points from where its first start ended,
    and a start whose coarse refinement failed from where it was. Of those, the one of
    least ``robust_cost`` (comparable across starts: every point counts, whatever each
    run rejected) is the result. Each stage's seconds, and the parts of the refinements
    on all points, go into ``timings``; each stage's error into the report
    (``scout_error``, ``coarse_error``, ``error``, ``fallback_error``).

    A start whose coarse refinement ended with a robust cost over
    ``HOPELESS_COARSE_RATIO`` times the least of them all (``hopeless`` in the report)
    is not refined on all points, nor is it a basin: an end that far behind is a local
    minimum or a run misled by mistracked points, and refining it on all points cost up
    to three times as long as the others (random world 130059: 6.2 s, against 0.9 s).

    Most worlds' starts end in one basin, refined on all points once: refining every
    start on all points took 2-3 times as long, and scouting the other starts instead of
    refining them on the coarse points halves the coarse stage (the demo's run: 4.0 s of
    refinements to 1.1 s). Where they part (a start near the roll centre can stop in a
    local minimum, ``_starts``; a scene of many mistracked contours, random world 43004),
    every basin is refined on all points, as the coarse costs do not rank them reliably.
    Should no refinement on all points succeed, every start is refined on all points
    from where it was (``fallback``), as before the coarse stage; if that fails too, its
    first error is raised. The refinements of each stage run side by side in up to
    ``FINAL_THREADS`` threads (``calib.threads``: serial with ``RIGCTL_SOLVE_THREADS=1``;
    each is independent and spends its time in numpy, which releases the interpreter),
    or, with a ``helper`` process, the first here and the others there
    (``_refine_each``); the first start's refinement on all points then begins here as
    soon as its coarse one ends, while the helper still scouts (it is always refined on
    all points: the first basin is its own). The same numbers either way."""
    timings = {} if timings is None else timings
    report: dict[str, dict] = {name: {"centre": [start["cx"], start["cy"]]}
                               for name, start in starts.items()}
    coarse, errors, early = _coarse_stage(motions, starts, kwargs, timings, report, helper)
    least = min((r.robust_cost for r in coarse.values()), default=math.inf)
    basins: dict[str, dict] = {}
    for name, start in starts.items():  # in their order: the same basins on a re-solve
        if "basin_of" in report[name]:
            continue
        if name not in coarse:
            report[name]["coarse_error"] = str(errors[name])
            basins[name] = start
            continue
        r = coarse[name]
        report[name].update(ended_at=[r.cx, r.cy], coarse_robust_cost=r.robust_cost)
        if _hopeless(r, least):
            report[name]["hopeless"] = r.robust_cost / least
            continue
        same = next((b for b in basins if b in coarse and _same_end(r, coarse[b])), None)
        if same is not None:
            report[name]["basin_of"] = same
        else:
            basins[name] = _basin_start(r)
    rest = {name: start for name, start in basins.items() if name not in early}
    later, errors = _refine_each({name: (motions, kwargs) for name in rest}, rest,
                                 "final refinement from", timings, helper)
    full = _with_early(basins, later, errors, early, timings)
    for name, exc in errors.items():
        report[name]["error"] = str(exc)
    if not full:  # as before the coarse stage: every start on all points from where it was
        full, errors = _refine_each({name: (motions, kwargs) for name in starts}, starts,
                                    "fallback refinement from", timings, helper)
        for name, exc in errors.items():
            report[name]["fallback_error"] = str(exc)
        for name in full:
            report[name]["fallback"] = True
        if not full:
            raise next(iter(errors.values()))
    for name, r in full.items():
        report[name].update(refined_to=[r.cx, r.cy], robust_cost=r.robust_cost,
                            rms_px=r.rms_px)
        stage = "fallback" if report[name].get("fallback") else "final"
        timings.update({f"{stage} refinement from {name}: {part}": sec
                        for part, sec in r.timings_s.items()})
    best = min(full, key=lambda name: full[name].robust_cost)
    report[best]["chosen"] = True
    return full[best], report


def _same_end(a: RefineResult, b: RefineResult) -> bool:
    """Whether two refinements of the same motions ended in one basin: their centres
    within ``SAME_END_PX`` and their centre-of-projection offsets (zero without depths)
    within ``SAME_END_OFFSET_M``."""
    if math.dist((a.cx, a.cy), (b.cx, b.cy)) > SAME_END_PX:
        return False
    if not (a.with_depths and b.with_depths):
        return True
    return float(np.linalg.norm(np.subtract(a.parallax, b.parallax))) <= SAME_END_OFFSET_M


def _hopeless(coarse: RefineResult, least: float) -> bool:
    """Whether a start's coarse refinement ended too far behind the least robust cost
    of the coarse stage to be refined on all points (``HOPELESS_COARSE_RATIO``)."""
    return coarse.robust_cost > HOPELESS_COARSE_RATIO * least


def _with_early(basins: dict, later: dict[str, RefineResult], errors: dict[str, SolveError],
                early: dict[str, tuple], timings: dict[str, float]) -> dict[str, RefineResult]:
    """The refinements on all points, in the basins' order: those taken after the
    coarse stage (``later``) and those taken during it (``early``: outcome and seconds,
    a ``SolveError`` into ``errors``)."""
    for name, (outcome, seconds) in early.items():
        timings[f"final refinement from {name}"] = seconds
        if isinstance(outcome, SolveError):
            errors[name] = outcome
        else:
            later[name] = outcome
    return {name: later[name] for name in basins if name in later}


def _coarse_stage(motions, starts: dict[str, dict], kwargs: dict, timings: dict[str, float],
                  report: dict[str, dict], helper: SolveProcess | None = None
                  ) -> tuple[dict[str, RefineResult], dict[str, SolveError], dict]:
    """``_refine_from_starts``' coarse refinements: the first start's, the others'
    scouts, and the coarse refinements of those whose scout ended elsewhere (the
    scouts' outcome into ``report``). The results and errors by name; a start scouted
    into the first start's basin has neither. Third, with a ``helper`` and more than
    one start (``_coarse_stage_shared``): the first start's refinement on all points
    from its coarse end (``timed_refine``'s outcome and seconds, by its name)."""
    if helper is not None and len(starts) > 1:
        return _coarse_stage_shared(motions, starts, kwargs, timings, report, helper)
    quiet = {**kwargs, "uncertainty": False}
    first = next(iter(starts))
    coarse_motions = _coarse(motions, COARSE_FACTOR)
    coarse, errors = _refine_each(
        {name: (coarse_motions, quiet) if name == first else
         (_coarse(motions, SCOUT_FACTOR), {**quiet, "outer_iterations": SCOUT_ROUNDS})
         for name in starts}, starts, "coarse refinement from", timings, helper)
    confirm: dict[str, dict] = {}
    for name, start in starts.items():
        if name == first:
            continue
        scout = coarse.pop(name) if name in coarse else errors.pop(name)
        if _scouted_elsewhere(name, scout, first, coarse.get(first), report):
            confirm[name] = start
    confirmed, confirm_errors = _refine_each(
        {name: (coarse_motions, quiet) for name in confirm}, confirm,
        "coarse refinement (after scouting) from", timings, helper)
    coarse.update(confirmed)
    errors.update(confirm_errors)
    return coarse, errors, {}


def _scouted_elsewhere(name: str, scout: RefineResult | SolveError, first: str,
                       first_coarse: RefineResult | None, report: dict[str, dict]) -> bool:
    """Whether start ``name`` must be refined on the coarse points (from where it was, as
    if never scouted): its scout failed or did not end where the first start's
    (``first``) coarse refinement did (``_same_end``; ``first_coarse`` None: that
    failed). The outcome into ``report``."""
    if isinstance(scout, SolveError):
        report[name]["scout_error"] = str(scout)
        return True
    if first_coarse is not None and _same_end(scout, first_coarse):
        report[name].update(scouted_to=[scout.cx, scout.cy], basin_of=first)
        return False
    report[name].update(scouted_to=[scout.cx, scout.cy], scout_robust_cost=scout.robust_cost)
    return True


def _coarse_stage_shared(motions, starts: dict[str, dict], kwargs: dict,
                         timings: dict[str, float], report: dict[str, dict],
                         helper: SolveProcess
                         ) -> tuple[dict[str, RefineResult], dict[str, SolveError], dict]:
    """``_coarse_stage`` with a helper process: the other starts' scouts there while the
    first start's coarse refinement runs here; each scout then decided on (those done
    at once, the others in a thread as they come back, so that a start to be refined on
    the coarse points goes to the helper as soon as its scout is in), and the first
    start's refinement on all points taken here while the helper works, unless a scout
    to be confirmed ended with a robust cost (scaled by the points, as if on the coarse
    ones) that makes the first start's coarse end ``_hopeless``: a start the strategies
    put far off can take several times as long as the others (random world 130059:
    4.3 s coarse, 7.1 s on all points, then dropped). Only a saving: which basins are
    refined on all points is decided once every coarse refinement has ended. The same
    stages, outcomes and report as without the helper."""
    quiet = {**kwargs, "uncertainty": False}
    scout_kwargs = {**quiet, "outer_iterations": SCOUT_ROUNDS}
    names = list(starts)
    first = names[0]
    coarse_motions = _coarse(motions, COARSE_FACTOR)
    scout_motions = _coarse(motions, SCOUT_FACTOR)
    scouts = {name: helper.submit(timed_refine, scout_motions, starts[name], scout_kwargs)
              for name in names[1:]}
    with serial_here():
        first_coarse, seconds = timed_refine(coarse_motions, starts[first], quiet)
    timings[f"coarse refinement from {first}"] = seconds
    coarse: dict[str, RefineResult] = {}
    errors: dict[str, SolveError] = {}
    if isinstance(first_coarse, SolveError):
        errors[first] = first_coarse
    else:
        coarse[first] = first_coarse
    confirming: dict[str, Any] = {}
    ahead: list[float] = []  # the robust costs of the scouts to be confirmed, as if coarse
    per_point = _point_count(coarse_motions) / _point_count(scout_motions)

    def decide(name: str) -> None:
        scout, sec = helper.run(scouts[name], timed_refine, scout_motions, starts[name],
                                scout_kwargs)
        timings[f"coarse refinement from {name}"] = sec
        if _scouted_elsewhere(name, scout, first, coarse.get(first), report):
            confirming[name] = helper.submit(timed_refine, coarse_motions, starts[name],
                                             quiet)
            if isinstance(scout, RefineResult):
                ahead.append(scout.robust_cost * per_point)

    later: list[str] = []  # the scouts not back yet
    for name in names[1:]:
        if scouts[name].done():
            decide(name)
        else:
            later.append(name)
    take_early = first in coarse and not any(_hopeless(coarse[first], cost) for cost in ahead)
    early: dict[str, tuple] = {}
    # the scouts still out are decided as they come back, in a thread, while the first
    # start's refinement on all points runs here: a start to be refined on the coarse
    # points goes to the helper then, not once that refinement has ended
    with ThreadPoolExecutor(1, thread_name_prefix="scouts") as decider:
        deciding = decider.submit(lambda: [decide(name) for name in later])
        if take_early:
            with serial_here():
                early[first] = timed_refine(motions, _basin_start(coarse[first]), kwargs)
        deciding.result()
    order = sorted(confirming, key=names.index)  # in the starts' order
    outcomes = _taken_back(helper, {name: confirming[name] for name in order},
                           {name: (coarse_motions, starts[name], quiet) for name in order})
    confirmed, confirm_errors = _by_outcome(outcomes, order,
                                            "coarse refinement (after scouting) from", timings)
    coarse.update(confirmed)
    errors.update(confirm_errors)
    return coarse, errors, early


def _point_count(motions: list[Motion]) -> int:
    return sum(len(m.ref_points) for m in motions)


def _basin_start(r: RefineResult) -> dict:
    """A basin's start for its refinement on all points: where its coarse one ended,
    with every parameter (``x_all``) and the captures' angle offsets."""
    return {**_where_ended(r), "x_all": r.x_all, "angle_delta": r.angle_delta}


def _where_ended(r: RefineResult) -> dict:
    """A start where ``r`` ended: its intrinsics, distortion and mounting."""
    return {**_as_start(r), "distortion": [r.k1, r.k2, r.p1, r.p2, r.k3],
            "mount_rotvec": r.mount_rotvec}


def _refine_each(jobs: dict[str, tuple[list, dict]], starts: dict[str, dict], label: str,
                 timings: dict[str, float], helper: SolveProcess | None = None
                 ) -> tuple[dict[str, RefineResult], dict[str, SolveError]]:
    """``refine`` of each start's motions with its keyword arguments (``jobs``, by name)
    from that start: the results and the errors, by name (each start's seconds into
    ``timings``). With a ``helper`` process and more than one start, the first is
    refined here, serially, and the others there, one after another (``solve_process``:
    side by side for real); once the first is done, those the helper has not begun are
    taken back and refined here, the last first (``SolveProcess.take_back``). Else side
    by side in up to ``FINAL_THREADS`` threads (``map_in_threads``). Either way the
    same numbers."""
    def refine_from(name: str) -> tuple[RefineResult | SolveError, float]:
        return timed_refine(jobs[name][0], starts[name], jobs[name][1])

    if not starts:
        return {}, {}
    names = list(starts)
    if helper is not None and len(names) > 1:
        futures = {name: helper.submit(timed_refine, jobs[name][0], starts[name],
                                       jobs[name][1]) for name in names[1:]}
        with serial_here():
            done = {names[0]: refine_from(names[0])}
        done.update(_taken_back(helper, futures, {name: (jobs[name][0], starts[name],
                                                         jobs[name][1])
                                                  for name in names[1:]}))
    else:
        done = dict(zip(names, map_in_threads(refine_from, names, FINAL_THREADS),
                        strict=True))
    return _by_outcome(done, names, label, timings)


def _taken_back(helper: SolveProcess, futures: dict[str, Any], jobs: dict[str, tuple]
                ) -> dict[str, tuple]:
    """Each ``timed_refine(*jobs[name])`` submitted to the helper (``futures``, by name,
    in the order queued): the last queued first, so that one the helper has not begun
    is taken back and refined here, serially (``SolveProcess.take_back``)."""
    with serial_here():
        return {name: helper.take_back(futures[name], timed_refine, *jobs[name])
                for name in reversed(futures)}


def _by_outcome(done: dict[str, tuple], names: list[str], label: str,
                timings: dict[str, float]
                ) -> tuple[dict[str, RefineResult], dict[str, SolveError]]:
    """``timed_refine``'s outcomes (``done``, by name) split into results and errors, in
    ``names``' order, each one's seconds into ``timings`` under ``label``."""
    results: dict[str, RefineResult] = {}
    errors: dict[str, SolveError] = {}
    for name in names:
        outcome, seconds = done[name]
        timings[f"{label} {name}"] = seconds
        if isinstance(outcome, SolveError):
            errors[name] = outcome
        else:
            results[name] = outcome
    return results, errors


def _distortion_terms(settings: ActiveSettings, depths: SceneDepths | None) -> int:
    """The distortion terms to estimate: the setting, or automatically all five (k1, k2,
    p1, p2, k3) when the scene's depths pin the parallax (then the tangential terms are
    identifiable and leaving them out biases the centre; without k3 a wide lens biases
    the focal length: random worlds 5000-5019, focal error p90 0.15 -> 0.05 %), else k1,
    k2 (without depths p1, p2 trade against the centre and the parallax)."""
    if settings.distortion_terms is not None:
        return settings.distortion_terms
    return 5 if depths is not None else 2


def _scene_depths(tr: Tracker, K: dict | RefineResult, baseline_m: float) -> SceneDepths:
    """Each contour's inverse depth from its shift in the SHIFT capture (``active_depth``),
    in image coordinates normalised and undistorted with ``K``."""
    if isinstance(K, RefineResult):
        fx, fy, cx, cy = K.fx, K.fy, K.cx, K.cy
        k = np.array([K.k1, K.k2, K.p1, K.p2, K.k3])
    else:
        fx, fy, cx, cy, k = K["fx"], K["fy"], K["cx"], K["cy"], np.zeros(5)
    # The camera moved along its own +x (``camera_shift_joints``, nominal hand-eye): the
    # scene moves towards -x, a little across for the hand-eye's error. Searching that
    # side only keeps a periodic pattern (a board's squares) from matching a neighbour.
    window = min(max(fx, fy) * baseline_m / NEAREST_SCENE_M + 8.0, 96.0)
    cross = 4.0 + SHIFT_CROSS * window
    tr.matches[SHIFT] = [track_in_range(c.points, tr.emaps[SHIFT], (-window, 2.0),
                                        (-cross, cross)) for c in tr.contours]
    ids = [i for i, m in enumerate(tr.matches[SHIFT]) if m.ok]
    fits = [contour_shift(tr.contours[i].points, tr.matches[SHIFT][i].points,
                          tr.matches[SHIFT][i].normals, tr.matches[SHIFT][i].offset)
            for i in ids]
    ids = np.array(ids, int)
    shifts = np.array([d for d, _ in fits]).reshape(-1, 2)
    rms = np.array([r for _, r in fits])
    rigid = rigid_shifts(rms)
    tr.report["motions"][SHIFT] = {
        "tracked": len(ids), "window_px": window,
        "not_rigid": [{"contour": int(i), "rms_px": round(float(r), 3)}
                      for i, r in zip(ids[~rigid], rms[~rigid], strict=True)]}
    ids = ids[rigid]
    centres = np.array([tr.contours[i].points.mean(axis=0) for i in ids]).reshape(-1, 2)
    moved = centres + shifts[rigid]
    c_n = _undistort(centres, fx, fy, cx, cy, k)
    m_n = _undistort(moved, fx, fy, cx, cy, k)
    return fit_depths(c_n, m_n - c_n, baseline_m, len(tr.contours), ids)


def _with_model_error(refined: RefineResult) -> tuple[list[str], np.ndarray]:
    """The refinement's covariance of the camera parameters, with the model error the
    rotation model cannot see added to the intrinsics' variances (``MODEL_ERROR_*``)."""
    names = param_names(refined.n_dist)
    cov = np.array(refined.covariance, float)
    floor = {"fx": MODEL_ERROR_FOCAL * refined.fx, "fy": MODEL_ERROR_FOCAL * refined.fy,
             "cx": MODEL_ERROR_CENTRE_PX, "cy": MODEL_ERROR_CENTRE_PX}
    for key, value in floor.items():
        i = names.index(key)
        cov[i, i] += value ** 2
    return names, cov


def centre_identifiability(names: list[str], cov: np.ndarray) -> dict:
    """What limits the principal point from rotations: for cx and cy, the sigma, the
    sigma were the tangential distortion (p1, p2) known (the conditional sigma
    ``sqrt(S_cc - S_cp S_pp^-1 S_pc)``) and the parameter it is most correlated with.
    A decentring term moves the image as a principal-point shift does, plus a field that
    only the differences between views at large angles off the axis show: on a narrow
    lens they trade (random world 7001, f 1461 px: cx sigma 0.88 px, 0.16 px with p1, p2
    known, correlation with p2 0.98). Empty without a covariance."""
    if cov is None or not len(cov):
        return {}
    sigma = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sigma, sigma)
    tangential = [names.index(n) for n in ("p1", "p2") if n in names]
    out: dict[str, Any] = {}
    for key in ("cx", "cy"):
        i = names.index(key)
        others = [j for j in range(len(names)) if j != i]
        j = max(others, key=lambda k: abs(corr[i, k]))
        entry = {"sigma_px": float(sigma[i]),
                 "most_correlated": {"with": names[j], "correlation": float(corr[i, j])}}
        if tangential:
            g = tangential
            conditional = cov[i, i] - cov[i, g] @ np.linalg.solve(cov[np.ix_(g, g)], cov[g, i])
            entry["sigma_if_tangential_known_px"] = float(np.sqrt(max(conditional, 0.0)))
        out[key] = entry
    if tangential and all(out[k]["sigma_if_tangential_known_px"] < 0.5 * out[k]["sigma_px"]
                          for k in ("cx", "cy")):
        out["note"] = ("the principal point trades with the tangential distortion (p1, p2): "
                       "rotations alone pin it to the sigma above; a calibration that "
                       "fixes p1, p2 (e.g. board views at large tilts) would reach the "
                       "'if tangential known' sigma")
    return out


def _parallax_report(refined: RefineResult, depths: SceneDepths | None,
                     settings: ActiveSettings, second: SecondStation | None = None) -> dict:
    """What the result says about the centre of projection off the head's axes."""
    names = ("s_x", "s_y", "s_z")
    if depths is None:
        cause = "no arm move captured" if settings.shift_m <= 0 else \
            "the arm's move gave none"
        return {"estimated": False,
                "why": f"no scene depths ({cause}): the parallax s = o / depth is not "
                       "identifiable from rotations and enters the sigma as a consider term "
                       f"({settings.nodal_offset_mm} mm at {settings.scene_depth_m} m)"}
    out = {"estimated": True,
           "centre_offset_mm": (1000 * refined.parallax).tolist(),
           "sigma_mm": [1000 * refined.sigma[n] for n in names],
           "influence": refined.influence}
    inv = depths.inv_depth if second is None else \
        np.r_[depths.inv_depth, second.depths.inv_depth]
    carried = _carried_by(refined.influence, inv, len(depths.inv_depth))
    if carried:
        out["carried_by"] = carried
    return out


def _carried_by(influence: dict, inv_depth: np.ndarray, first_station: int) -> dict:
    """The one contour that carries the intrinsics, if there is one: over fx, fy, cx,
    cy, the largest share of the delete-one-contour jackknife's variance, when it is at
    least ``CARRIED_SHARE`` and the jackknife's sigma at least ``CARRIED_RATIO`` times
    the refinement's own (sandwich or classical, the larger); with the parameters that
    contour carries so and its measured depth (``inv_depth``, indexed by contour id)
    against the others'. Ids from ``first_station`` on are the second station's,
    named ``far: contour k`` (its own reference image's contour k); one object seen at
    both stations is two contours, each its own jackknife cluster. The centre of
    projection's offset is told by how contours at different depths move apart, so a
    scene with one contour off the others' depth rests on that contour (random world
    62019: one at 1.9 m, 25 on a board at 0.56 m)."""
    heavy = {k: v for k, v in influence.items()
             if v["share"] >= CARRIED_SHARE and v["sigma_ratio"] >= CARRIED_RATIO}
    if not heavy:
        return {}
    key = max(heavy, key=lambda k: heavy[k]["share"])
    contour = heavy[key]["contour"]
    own = float(inv_depth[contour]) if contour < len(inv_depth) else float("nan")
    others = np.delete(inv_depth, contour) if contour < len(inv_depth) else inv_depth
    others = others[np.isfinite(others)]
    name = f"contour {contour}" if contour < first_station else \
        f"far: contour {contour - first_station}"
    entry = {"contour": contour, "name": name,
             "parameters": sorted(k for k, v in heavy.items() if v["contour"] == contour),
             "share": heavy[key]["share"], "sigma_ratio": heavy[key]["sigma_ratio"],
             "depth_m": 1.0 / own if np.isfinite(own) and own > 0 else None,
             "others_median_depth_m": float(1.0 / np.median(others)) if len(others) else None}
    own_m, others_m = entry["depth_m"], entry["others_median_depth_m"]
    where = "" if own_m is None else f" at {own_m:.2f} m" + (
        "" if others_m is None else f" (the others' median {others_m:.2f} m)")
    short = "" if own_m is None else f" ({own_m:.2f} m" + (
        ")" if others_m is None else f"; others {others_m:.2f} m)")
    entry["summary"] = f"{name}{short} carries {', '.join(entry['parameters'])}: see parallax"
    entry["note"] = (f"{name}{where} carries {', '.join(entry['parameters'])}: "
                     f"{100 * entry['share']:.0f} % of the delete-one-contour jackknife's "
                     f"variance, whose sigma is {entry['sigma_ratio']:.1f} times the "
                     "refinement's own; the reported sigma includes it. The centre of "
                     "projection's offset from the head's axes is told by how contours at "
                     "different depths move apart, here mostly by this one: objects in view "
                     "nearer or farther than the rest, or a second station "
                     "(second_station_mm), would firm it up.")
    return entry


def split_stations(images: dict, angles: dict) -> tuple[dict, dict, dict, dict]:
    """The first station's captures and the second's (``STATION_PREFIX``, removed)."""
    first = {k: v for k, v in images.items() if not k.startswith(STATION_PREFIX)}
    second = {k.removeprefix(STATION_PREFIX): v for k, v in images.items()
              if k.startswith(STATION_PREFIX)}
    return (first, {k: angles[k] for k in first}, second,
            {k: angles[STATION_PREFIX + k] for k in second})


@dataclass
class SecondStation:
    """The second station's motions (contour ids after the first station's) and the
    depths of its contours."""

    motions: list[Motion]
    depths: SceneDepths
    report: dict[str, Any]


def second_station(images: dict, angles: dict, K: RefineResult, settings: ActiveSettings,
                   first_ids: int, emaps: dict | None = None) -> SecondStation:
    """The second station's contours, their depths from its own SHIFT capture, and every
    other capture there tracked by prediction from ``K`` (a refinement with the first
    station's depths: the head's geometry is the same at both). ``SolveError`` when it
    has no reference, no depths or too few tracked motions."""
    if "ref" not in images or SHIFT not in images:
        raise SolveError("no reference or no shift capture")
    tr = Tracker(images, angles, settings.window, settings.min_points, settings.assumed_centre,
                 emaps)
    depths = _measured_depths(tr, K, settings, images)
    if depths is None:
        raise SolveError(f"no depths measured ({tr.report.get('scene_depth')})")
    labels = sorted((k for k in images if k not in ("ref", SHIFT)),
                    key=lambda k: (k.startswith("roll"), abs(math.degrees(tr.rel[k][2]))))
    tr.track_all([lb for lb in labels if not lb.startswith("roll")], K, TIER_WINDOW_PX)
    tr.track_all([lb for lb in labels if lb.startswith("roll")], K, TIER_WINDOW_PX,
                 ROLL_JOINT_WINDOW_PX)
    motions = [replace(m, label=STATION_PREFIX + m.label, groups=m.groups + first_ids,
                       reference=STATION_PREFIX + m.reference)
               for m in (tr.motion(lb, REFINE_STRIDE) for lb in labels) if m is not None]
    if len(motions) < 2:
        raise SolveError(f"{len(motions)} motions tracked (need 2)")
    return SecondStation(motions, depths, tr.report)


def _second_station_if_any(images: dict, angles: dict, K: dict | RefineResult,
                           depths: SceneDepths | None, settings: ActiveSettings,
                           tr: Tracker, timings: dict, emaps: dict | None = None
                           ) -> SecondStation | None:
    """``second_station`` when there are its captures and the first station's depths;
    its report (or why it was not used) goes into the first station's."""
    if not images:
        return None
    if depths is None:
        tr.report["second_station"] = "not used: the first station measured no depths"
        return None
    if not isinstance(K, RefineResult):
        tr.report["second_station"] = ("not used: no refinement of the first station to "
                                       "predict it from (no wide or roll captures)")
        return None
    t0 = time.perf_counter()
    try:
        second = second_station(images, angles, K, settings, len(tr.contours), emaps)
    except SolveError as exc:
        tr.report["second_station"] = f"not used: {exc}"
        return None
    finally:
        timings["second_station"] = time.perf_counter() - t0
    tr.report["second_station"] = second.report
    return second


def _with_second_station(motions: list[Motion], prior: DepthPrior | None,
                         second: SecondStation | None) -> tuple[list[Motion], DepthPrior | None]:
    """The refinement's motions and depth prior with the second station's appended (a
    second station is used only with the first station's depths, so ``prior`` then
    exists)."""
    if second is None:
        return motions, prior
    far = second.depths.prior()
    measured = [np.zeros(len(p.mean)) if p.measured_sigma is None else p.measured_sigma
                for p in (prior, far)]
    return motions + second.motions, DepthPrior(
        np.r_[prior.mean, far.mean], np.r_[prior.sigma, far.sigma], np.r_[tuple(measured)],
        max(prior.scale_sigma, far.scale_sigma))


@with_one_blas_thread
def solve_active(images: dict[str, np.ndarray], angles: dict[str, tuple[float, float, float]],
                 settings: ActiveSettings | None = None,
                 emaps: dict | None = None, helper: SolveProcess | None = None,
                 start_helper: bool = True, ahead: PanTiltStage | None = None
                 ) -> ActiveSolution:
    """Intrinsics from images taken at known head angles (radians; labels ``ref``,
    ``pan+``, ``pan-``, ``tilt+``, ``tilt-``, ``roll...``, ``SHIFT``; those with
    ``STATION_PREFIX`` are a second station's, ``second_station``): thesis chapter 3 with
    the refinement beyond it. ``emaps``: edge maps already taken of some images, by
    label (``vision.contours.edge_map``; the same as taken here). ``helper``: a
    ``calib.solve_process`` for the final refinements' starts; without one, one is
    started here when the rolls' tiers begin (when ``start_helper`` and the solve may use
    two threads) and stopped at the end. ``ahead``: ``pan_tilt_stage`` of the captures
    before the rolls, taken while the rig rolled, with the rolls' tiers it took as their
    captures came in (``PanTiltStage.take_roll``); used when it fits these captures
    (``PanTiltStage.fits``), else taken again here. Raises ``SolveError`` with the stage
    that failed."""
    holder = _Helper(helper, start_helper)
    try:
        return _solve_active(images, angles, settings, emaps, holder, ahead)
    finally:
        holder.close()


class _Helper:
    """The solve's helper process: the one given, or one started here by ``start`` and
    stopped by ``close``. Started as the rolls' tiers begin: its interpreter's start (0.4
    s of CPU) then overlaps the predicting refinements, which use the second core less
    than the edge maps and tracking before them (the demo's run re-solved: started at
    the beginning, loading the images took 0.12 -> 0.24 s and the tracking 3.4 -> 3.7
    s, a third of what the helper gained)."""

    def __init__(self, given: SolveProcess | None, may_start: bool) -> None:
        self.process, self._may_start, self._own = given, may_start and given is None, None

    def start(self) -> SolveProcess | None:
        if self._may_start:
            self._may_start = False
            self._own = self.process = start_if_useful()
        return self.process

    def close(self) -> None:
        """Stops a helper started here, in a thread of its own: the solve's result need
        not wait for the child's interpreter to end (60 ms on the demo's re-solve). Not a
        daemon thread, so this process waits for it when it ends: the child is always
        stopped and waited for by PID (``SolveProcess.close``)."""
        if self._own is not None:
            threading.Thread(target=self._own.close, name="solve-process-close").start()


@dataclass
class PanTiltStage:
    """The solve's first stages, which need only the reference, the scene-depth capture
    (``SHIFT``) and the pan and tilt captures (``pan_tilt_stage``): the tracker, the first
    K, the last refinement (the one predicting the first rolls, ``K_for_rolls``, when
    rolls follow; else the wide tier's, or the first K), the scene's depths, the labels
    tracked, and the inputs they came from (to check that a solve of all the captures
    would have taken the same)."""

    tracker: Tracker
    K0: dict
    K1: dict | RefineResult
    depths: SceneDepths | None
    done: list[str]
    images: dict[str, np.ndarray]
    angles: dict[str, tuple[float, float, float]]
    settings: ActiveSettings
    timings: dict[str, float]
    rolls_predicted: bool = False  # K1 is the refinement predicting the first rolls
    # the rolls' stages taken as their captures came in (``take_roll``): the tiers as
    # planned, the roll captures taken, how many tiers were tracked and how many
    # predicted (the first tier's prediction is ``K_for_rolls``), the refinement that
    # predicted the first tier (the pans' K, a start of the final refinement), and why
    # the rolls' stages stopped, if they failed
    roll_plan: list[list[str]] = field(default_factory=list)
    roll_images: dict[str, np.ndarray] = field(default_factory=dict)
    roll_angles: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    rolls_tracked: int = 0
    rolls_predicted_tiers: int = 0
    K_pans: dict | RefineResult | None = None
    failed: str | None = None

    def fits(self, images: dict, angles: dict, settings: ActiveSettings) -> str | None:
        """Why a solve of ``images`` (one station's) would not start from this stage, or
        None: it must hold the same captures before the rolls (the same image objects,
        the same angles) and the same settings but the encoders' sigmas (used only by the
        final refinement); with rolls taken ahead, the rolls' tiers must be the planned
        ones and the rolls taken the recorded ones."""
        before = [label for label in images if not label.startswith("roll")]
        if before != list(self.images):
            return f"the captures before the rolls differ ({len(before)} against " \
                   f"{len(self.images)})"
        if any(images[label] is not self.images[label] or
               tuple(angles[label]) != tuple(self.angles[label]) for label in before):
            return "a capture before the rolls differs"
        if replace(settings, encoder_sigma_rad=None) != \
                replace(self.settings, encoder_sigma_rad=None):
            return "the settings differ"
        rolls = [label for label in images if label.startswith("roll")]
        if self.rolls_predicted != bool(rolls):
            return "the rolls were not foreseen"
        if self.failed is not None:
            return self.failed
        if self.roll_images:  # the tracker holds them: they must be the recorded ones
            rel = {lb: tuple(np.subtract(angles[lb], angles["ref"])) for lb in rolls}
            if roll_tiers(rolls, rel) != self.roll_plan:
                return "the rolls' tiers differ from the planned ones"
            if any(lb not in images or images[lb] is not image or
                   tuple(angles[lb]) != self.roll_angles[lb]
                   for lb, image in self.roll_images.items()):
                return "a roll capture differs"
        return None

    @with_one_blas_thread  # as the solve: the same numbers, and no BLAS threads spinning
    def take_roll(self, label: str, image: np.ndarray, angle: tuple[float, float, float],
                  emap=None) -> None:
        """While the rig rolls: a roll capture as it comes in (a live run's, in the
        captures' order). Each planned tier (``roll_plan``) is tracked as soon as its
        captures are all in, and the refinement predicting the next tier is taken as
        soon as the tier before it is tracked: the loop of ``_solve_active`` over the
        rolls' tiers, the same computation to the same numbers, so that at most the last
        tier's tracking is left when the motion ends. Any error stops the rolls' stages
        (``failed``, with a half-taken stage in the tracker); the solve then takes every
        stage itself, and raises a ``SolveError`` there."""
        if self.failed is not None or not self.rolls_predicted:
            return
        self.roll_images[label], self.roll_angles[label] = image, tuple(angle)
        self.tracker.add_captures({label: image}, {label: tuple(angle)},
                                  None if emap is None else {label: emap})
        try:
            self.go_on_with_rolls(stage_timer(self.timings),
                                  ready=lambda tier: all(lb in self.roll_images
                                                         for lb in tier))
        except Exception as exc:  # any: the solve takes the stages again
            self.failed = f"the rolls' stages failed while the rig rolled: {exc}"

    def go_on_with_rolls(self, stage, ready=lambda tier: True,
                         before_tier=lambda: None) -> None:
        """The loop over the rolls' tiers (``roll_plan``) from where it stands: the
        refinement predicting each tier (the first tier's came with the first stages and
        is the pans' K, ``K_pans``), then the tier tracked from it, unless ``ready`` says
        its captures are not all in yet (then it stops there, the prediction taken).
        ``before_tier`` is called as each tier's work begins; ``stage`` times each step.
        The solve runs it on whatever was left (``_solve_active``), a live run on each
        roll as it comes in (``take_roll``): the same computation either way."""
        while self.rolls_tracked < len(self.roll_plan):
            i = self.rolls_tracked
            tier = self.roll_plan[i]
            key = tier_key(tier, [], self.roll_plan)
            before_tier()
            if i == 0:
                self.K_pans = self.K1
                self.rolls_predicted_tiers = max(self.rolls_predicted_tiers, 1)
            elif self.rolls_predicted_tiers <= i:
                self.K1, self.depths = _predicting_tier(
                    self.tracker, key, self.done, self.K0, self.K1, self.depths,
                    self.settings, self.images, stage)
                self.rolls_predicted_tiers = i + 1
            if not ready(tier):
                return
            with stage(f"tracking: {key.removeprefix('K_for_')}"):
                self.tracker.track_all(tier, self.K1, TIER_WINDOW_PX, ROLL_JOINT_WINDOW_PX)
            self.done += tier
            self.rolls_tracked += 1


@with_one_blas_thread
def pan_tilt_stage(images: dict[str, np.ndarray],
                   angles: dict[str, tuple[float, float, float]],
                   settings: ActiveSettings, emaps: dict | None = None,
                   rolls_follow: bool | None = None) -> PanTiltStage:
    """The solve's stages up to the rolls (one station's captures, ``split_stations``):
    contours and the first K, the small pans and tilts tracked, the refinement that
    predicts the wide ones, the scene's depths, the wide ones tracked and, when rolls
    follow (``rolls_follow``; None: when ``images`` hold any), the refinement that
    predicts the first rolls. A live run takes it on the captures before the first roll
    while the rig rolls (``solve_active``'s ``ahead``); it is the same computation
    either way, to the same numbers. Raises ``SolveError`` as ``solve_active`` would."""
    if "ref" not in images:
        raise SolveError("active-camera: no reference capture recorded")
    missing = [m for m in ("pan+", "tilt+") if m not in images]
    if missing:
        raise SolveError(f"active-camera: captures missing: {missing}")
    timings: dict[str, float] = {}
    stage = stage_timer(timings)
    with stage("contours and first K"):
        tr = Tracker(images, angles, settings.window, settings.min_points,
                     settings.assumed_centre, emaps)
        K0 = tr.first_K()
    small, wide, _ = tiers(images)
    with stage("tracking: small pans and tilts"):
        tr.track_all(small, K0, 12.0)
    # each tier is tracked by prediction from the model refined on the tiers before it;
    # those refinements only predict: a quarter of the points do
    K1: dict | RefineResult = dict(K0)
    done = list(small)
    depths = None
    if wide:
        K1, depths = _predicting_tier(tr, "K_for_wide", done, K0, K1, depths, settings,
                                      images, stage)
        with stage("tracking: wide"):
            tr.track_all(wide, K1, TIER_WINDOW_PX, 0.0)
        done += wide
    if rolls_follow is None:
        rolls_follow = any(label.startswith("roll") for label in images)
    if rolls_follow:  # ``tier_key`` of the first rolls' tier
        K1, depths = _predicting_tier(tr, "K_for_rolls", done, K0, K1, depths, settings,
                                      images, stage)
    kept = {label: images[label] for label in images if not label.startswith("roll")}
    return PanTiltStage(tr, K0, K1, depths, done, kept,
                        {label: angles[label] for label in kept}, settings, timings,
                        rolls_follow)


def _predicting_tier(tr: Tracker, key: str, done: list[str], K0: dict,
                     K1: dict | RefineResult, depths: SceneDepths | None,
                     settings: ActiveSettings, images: dict, stage
                     ) -> tuple[dict | RefineResult, SceneDepths | None]:
    """The refinement on the tiers ``done`` that predicts the next (``key``), and the
    scene's depths once the pans' K is known (measured once, used from then on)."""
    before = [m for m in (tr.motion(lb, PREDICTION_STRIDE) for lb in done) if m]
    if len(before) < 2:
        return K1, depths
    with stage(f"predicting refinement: {key}"):
        K1 = _predicting_refinement(
            before, K0 if isinstance(K1, dict) else _camera_start(K1), settings, depths)
    if depths is None:
        with stage("depths"):
            depths = _measured_depths(tr, K1, settings, images)
        if depths is not None:
            with stage(f"predicting refinement: {key} with depths"):
                K1 = _predicting_refinement(before, _camera_start(K1), settings, depths)
    tr.report[key] = {"fx": K1.fx, "fy": K1.fy, "cx": K1.cx, "cy": K1.cy,
                      "distortion": [K1.k1, K1.k2, K1.p1, K1.p2, K1.k3]}
    return K1, depths


def _first_stages(images: dict, angles: dict, settings: ActiveSettings, emaps: dict,
                  ahead: PanTiltStage | None) -> tuple[PanTiltStage, dict[str, float]]:
    """``ahead`` when it fits these captures (its stages' seconds as taken while the rig
    moved), else ``pan_tilt_stage`` of them now; and the solve's timings so far."""
    why = "none taken" if ahead is None else ahead.fits(images, angles, settings)
    if why is None:
        ahead.tracker.add_captures(images, angles, emaps)
        return ahead, {f"while moving: {k}": v for k, v in ahead.timings.items()}
    if ahead is not None:
        log.info("active-camera: the stages taken while the rig moved are not used: %s",
                 why)
    first = pan_tilt_stage(images, angles, settings, emaps)
    return first, dict(first.timings)


def _solve_active(images: dict[str, np.ndarray], angles: dict[str, tuple[float, float, float]],
                  settings: ActiveSettings | None, emaps: dict | None,
                  helper: _Helper, ahead: PanTiltStage | None = None) -> ActiveSolution:
    settings = settings or ActiveSettings()
    emaps = emaps or {}
    emaps_far = {k.removeprefix(STATION_PREFIX): v for k, v in emaps.items()
                 if k.startswith(STATION_PREFIX)}
    images, angles, images_far, angles_far = split_stations(images, angles)
    first, timings = _first_stages(images, angles, settings, emaps, ahead)
    stage = stage_timer(timings)
    _, _, roll_groups, order = _tiers(images, first.tracker)
    # the rolls' tiers, but those tracked and predicted while the rig rolled
    # (``PanTiltStage.take_roll``; ``fits`` checked they are these tiers)
    first.roll_plan = roll_groups
    first.go_on_with_rolls(stage, before_tier=helper.start)
    tr, K0, K1, depths = first.tracker, first.K0, first.K1, first.depths
    K_pans = K1 if first.K_pans is None else first.K_pans  # the refinement on the pans

    if SHIFT in images and settings.shift_m > 0:  # again, with the K of every pose
        with stage("depths"):
            depths = _measured_depths(tr, K1, settings, images)

    with stage("strategies A-D"):
        strategies = _strategies(tr, [lb for group in roll_groups for lb in group])
        start = _final_start(K_pans, strategies, K0)

    second = _second_station_if_any(images_far, angles_far, K1, depths, settings, tr, timings,
                                    emaps_far)

    motions, prior = _with_second_station(
        [m for m in (tr.motion(lb, REFINE_STRIDE) for lb in order) if m is not None],
        None if depths is None else depths.prior(), second)
    refined, tr.report["final_starts"] = _refine_from_starts(
        motions, _starts(start, K_pans, K0, K1),
        dict(n_dist=_distortion_terms(settings, depths), parallax_sigma=settings.parallax_sigma,
             depths=prior, offset_sigma_m=settings.nodal_offset_mm / 1000.0,
             angle_sigma=settings.encoder_sigma_rad), timings, helper.start())
    strategies["refined"] = refined.as_dict()
    result = _result(tr, refined, depths, settings, strategies, second)
    return ActiveSolution(result, refined, tr.contours, tr.matches, order, timings)


def _tiers(images: dict, tr: Tracker) -> tuple[list, list, list, list]:
    """The captures' tracking tiers (``active_tracking.tiers``, the rolls in groups
    of ``roll_tiers``) and the order of all of them."""
    small, wide, roll_labels = tiers(images)
    return small, wide, roll_tiers(roll_labels, tr.rel), small + wide + roll_labels


def _result(tr: Tracker, refined: RefineResult, depths: SceneDepths | None,
            settings: ActiveSettings, strategies: dict,
            second: SecondStation | None = None) -> dict[str, Any]:
    """``result.json`` of the active-camera solve: the refined intrinsics with their
    covariance (the model error added), what limits the centre and the parallax, and
    the strategies and tracking behind them."""
    w, h = tr.size
    names, cov = _with_model_error(refined)
    sigma = dict(zip(names, np.sqrt(np.diag(cov)).tolist(), strict=True))
    parallax = _parallax_report(refined, depths, settings, second)
    summary = {"fx": refined.fx, "fy": refined.fy, "cx": refined.cx, "cy": refined.cy,
               "rms_px": refined.rms_px, "contours": len(tr.contours)}
    if "carried_by" in parallax:  # the operator sees it where the run ends
        summary["warning"] = parallax["carried_by"]["summary"]
    if isinstance(tr.report.get("second_station"), str):  # asked for, and not used
        summary["second_station"] = tr.report["second_station"]
    return {
        "fx": refined.fx, "fy": refined.fy, "cx": refined.cx, "cy": refined.cy,
        "sigma": {k: sigma[k] for k in ("fx", "fy", "cx", "cy")},
        "covariance": {"names": names, "matrix": cov.tolist(),
                       "model_error": {"focal_rel": MODEL_ERROR_FOCAL,
                                       "centre_px": MODEL_ERROR_CENTRE_PX}},
        "width": w, "height": h,
        "distortion": [refined.k1, refined.k2, refined.p1, refined.p2, refined.k3],
        "roll_axis_in_cam": refined.roll_axis.tolist(),
        "head_geometry": _head_geometry(refined, names, cov, settings).as_dict(),
        "parallax": parallax,
        "head_angles": _head_angles_report(refined, settings),
        "centre_identifiability": centre_identifiability(names, cov),
        "assumed_centre": tr.centre.tolist(),
        "strategies": strategies, "tracking": tr.report,
        "summary": summary,
    }


def _head_geometry(refined: RefineResult, names: list[str], cov: np.ndarray,
                   settings: ActiveSettings) -> head_model.HeadGeometry:
    """The head's geometry the refinement ended with (``head_model``): the centre's
    offset as estimated when the scene's depths were measured, else zero with the prior
    ``settings.nodal_offset_mm`` as its sigma."""
    if refined.with_depths:
        offset = np.asarray(refined.parallax, float)
        sigma = np.array([refined.sigma[n] for n in head_model.OFFSET_NAMES])
    else:
        offset, sigma = np.zeros(3), np.full(3, settings.nodal_offset_mm / 1000.0)
    return head_model.from_refinement(refined.x, names, cov, offset, sigma, refined.with_depths)


def _head_angles_report(refined: RefineResult, settings: ActiveSettings) -> dict[str, Any]:
    """How the recorded head angles entered: as exact, or as readings of the servos'
    encoder sigma with each capture's estimated offset from its reading (degrees)."""
    if settings.encoder_sigma_rad is None:
        return {"estimated": False,
                "why": "the head's servo models are unknown: the recorded angles are exact"}
    return {"estimated": True,
            "encoder_sigma_deg": [math.degrees(v) for v in settings.encoder_sigma_rad],
            "offsets_deg": refined.angle_offsets_deg}
