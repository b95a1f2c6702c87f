"""``rigctl bench active-worlds``: the active-camera pipeline on random worlds.

For each seed, ``rigctl.mocks.random_world`` draws a rig; the world's own renderer
(``rigctl.mocks.world``, OpenCV's projection and distortion, then JPEG at the world's quality)
draws what the camera sees at the procedure's head angles, with the arm at home; the
same pipeline the procedure runs (``rigctl.calib.active_pipeline``) solves it. No stand-in
processes: this judges the solver, fast, on many rigs. ``rigctl bench worlds`` runs the
whole procedure chain through the stand-ins.

Reports per world and as a distribution: focal error (%), centre error (px) and each
intrinsic's error divided by its reported sigma (|z| > 3 means the sigma is too small).
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ProcessPoolExecutor

import cv2
import numpy as np

from rigctl.calib import head_model
from rigctl.calib.active_angles import head_encoder_sigmas
from rigctl.calib.active_depth import camera_shift_joints
from rigctl.calib.active_pipeline import SHIFT, STATION_PREFIX, ActiveSettings, solve_active
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.geometry.transforms import R_to_rotvec, xyz_rpy_to_T
from rigctl.mocks.dxl_models import SPEC_BY_NAME as SERVO_SPECS
from rigctl.mocks.random_world import random_world
from rigctl.mocks.sim import rig_mount
from rigctl.mocks.world import World, WorldFile
from rigctl.procedures.active_camera import (
    SECOND_STATION_POSES,
    ActiveCameraParams,
    head_poses,
    second_station_joints,
)

# the procedure's own default plan, so the bench judges what an operator runs
POSES_DEG = {label: tuple(math.degrees(a) for a in angles)
             for label, *angles in head_poses(ActiveCameraParams())}
KEYS = ("fx", "fy", "cx", "cy")
# how the head's encoders read (``encoder_reading``)
ENCODER_MODES = ("ideal", "hardware", "quantized", "noisy", "true")
# head angles (deg) at which the calibrated head geometry's rotation from home is checked
# against the world's (``head_check``): pans and tilts a head beside the arm would re-aim
# by, and rolls
HEAD_CHECK_DEG = ((20.0, 0.0, 0.0), (-20.0, 0.0, 0.0), (0.0, 15.0, 0.0), (0.0, -15.0, 0.0),
                  (20.0, 15.0, 0.0), (-20.0, -15.0, 0.0), (0.0, 0.0, 90.0), (0.0, 0.0, 180.0))
# the soft limits of the rig file ``rigctl sim up`` writes (the config's default)
SIM_RIG_JOINT_LIMITS = [(-2 * math.pi, 2 * math.pi)] * 6


def _delivered(image: np.ndarray, quality: int) -> np.ndarray:
    """A rendered image as the stand-in camera delivers it: JPEG at the world's quality,
    decoded to grey."""
    _, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def render_views(world: World, poses_deg: dict, rng=None, ideal_encoders: bool | str = False,
                 true_angles: dict | None = None) -> tuple[dict, dict]:
    """What the stand-in camera would deliver at each head pose (arm at home), and the
    head angles the procedure would record there (``encoder_reading``; ``rng`` draws
    where each move ends and the readings' noise; ``ideal_encoders``: True, or one of
    ``ENCODER_MODES``). ``true_angles``, when given, is filled with where the head
    really stood at each pose (rad), e.g. for the sideways move from ``ref``
    (``render_shift``)."""
    images, angles = {}, {}
    quality = world.spec.camera.jpeg_quality
    rng = np.random.default_rng(0) if rng is None else rng
    for k, (label, deg) in enumerate(poses_deg.items()):
        goal = tuple(math.radians(v) for v in deg)
        true, read = encoder_reading(world, goal, rng, ideal_encoders)
        images[label] = _delivered(world.render(world.T_base_cam(world.home_q, true),
                                                frame_index=k), quality)
        angles[label] = read
        if true_angles is not None:
            true_angles[label] = true
    return images, angles


def encoder_reading(world: World, goal: tuple, rng, ideal: bool | str = False
                    ) -> tuple[tuple, tuple]:
    """Where the head is and what its encoders read after a move to ``goal`` (rad), as the
    bus stand-in plays servos with hardware encoders (``head.encoder: hardware``): the
    shaft stops within half a pulse of the goal, its reading is that angle plus the
    model's noise and the world's (``encoder_noise_deg``), quantized to one pulse (0.088
    deg on the X series). An ideal encoder (or ``ideal``) reads the goal exactly.

    ``ideal`` may instead name one of ``ENCODER_MODES`` (the controlled experiment of
    issue 40): ``quantized`` (no noise), ``noisy`` (noise, no quantization) or ``true``
    (the shaft where the hardware puts it, read exactly)."""
    head = world.spec.head
    mode = "ideal" if ideal is True else ("hardware" if ideal is False else ideal)
    if mode not in ENCODER_MODES:
        raise ValueError(f"encoder mode: one of {ENCODER_MODES}, got {mode!r}")
    if mode == "ideal" or head.encoder != "hardware":
        return goal, goal
    true, read = [], []
    for angle, model in zip(goal, head.models, strict=True):
        spec = SERVO_SPECS[model]
        pulse = 2 * math.pi / spec.pulses_per_rev
        sigma = math.hypot(spec.noise_ticks, math.radians(head.encoder_noise_deg) / pulse)
        shaft = angle + rng.uniform(-0.5, 0.5) * pulse
        noise = rng.normal(0.0, sigma)
        true.append(shaft)
        ticks = shaft / pulse + (0.0 if mode in ("quantized", "true") else noise)
        read.append((round(ticks) if mode in ("hardware", "quantized") else ticks) * pulse)
    return tuple(true), tuple(read)


def _nominal_flange_cam(world: World) -> np.ndarray:
    """The head mount as ``rigctl sim up`` writes it into the rig file."""
    mount = rig_mount(world)
    return xyz_rpy_to_T(mount["xyz_mm"], mount["rpy_deg"])


def render_shift(world: World, shift_m: float, head_true: tuple, head_read: tuple) -> tuple:
    """The procedure's sideways move: planned, as on the simulated rig, with the nominal
    arm and the head mount rounded as ``rigctl sim up`` writes it; rendered with the
    true arm. The procedure takes it right after ``ref`` without moving the head, so the
    head stands where it stood for ``ref`` (``head_true``, read as ``head_read``): drawn
    at the commanded home instead, the bench turned the camera by up to half an encoder
    pulse between the two (0.04 deg on the X series, 0.7 px at 1000 px), which the depth
    fit took for parallax (random world 130046: depths 10-37 % off, 0-5 % here). The
    reading is ``ref``'s, where the procedure reads the encoders again (the solve reads
    no angle of this capture)."""
    q = camera_shift_joints(nominal_ur(world.spec.arm.model), world.home_q,
                            _nominal_flange_cam(world), shift_m)
    img = world.render(world.T_base_cam(q, head_true), frame_index=99)
    return _delivered(img, world.spec.camera.jpeg_quality), tuple(head_read)


def render_second_station(world: World, back_m: float, shift_m: float) -> tuple[dict, dict]:
    """The procedure's second station (``second_station_mm``, planned as the procedure
    plans it: ``second_station_joints``): the reference, the sideways move from there and
    ``SECOND_STATION_POSES``, rendered with the true arm; labels with ``STATION_PREFIX``.
    Empty when no station is within reach."""
    plan = second_station_joints(nominal_ur(world.spec.arm.model), world.home_q,
                                 _nominal_flange_cam(world), 1000.0 * back_m,
                                 1000.0 * shift_m, SIM_RIG_JOINT_LIMITS)
    if plan is None:
        return {}, {}
    _, q_far, q_shift = plan
    quality = world.spec.camera.jpeg_quality
    views = {"ref": (q_far, (0.0, 0.0, 0.0)), SHIFT: (q_shift, (0.0, 0.0, 0.0)),
             **{label: (q_far, tuple(math.radians(v) for v in deg))
                for label, deg in SECOND_STATION_POSES.items()}}
    images, angles = {}, {}
    for k, (label, (q, a)) in enumerate(views.items()):
        img = world.render(world.T_base_cam(q, a), frame_index=200 + k)
        images[STATION_PREFIX + label], angles[STATION_PREFIX + label] = \
            _delivered(img, quality), a
    return images, angles


def world_trial(args) -> dict:
    """One world's active-camera solve against its truth; ``args``: seed, distortion
    terms, the sideways move (m), optionally the second station (m) and whether the head's
    encoders read the commanded angles exactly (else as the world's servos do)."""
    seed, distortion_terms, shift_m, *rest = args
    back_m = rest[0] if rest else 0.0
    ideal_encoders = rest[1] if len(rest) > 1 else False
    estimate_angles = bool(rest[2]) if len(rest) > 2 else True
    ideal_encoders = ideal_encoders if isinstance(ideal_encoders, str) else bool(ideal_encoders)
    spec = WorldFile.model_validate(random_world(seed))
    world = World(spec)
    cam = spec.camera
    row = {"seed": seed, "model": spec.arm.model, "fx_true": cam.fx,
           "k": cam.distortion, "camera_offset_mm": spec.head.camera_offset_mm}
    true_angles: dict = {}
    images, angles = render_views(world, POSES_DEG, np.random.default_rng([seed, 7]),
                                  ideal_encoders, true_angles)
    row["encoders"] = ideal_encoders if isinstance(ideal_encoders, str) else \
        "ideal" if ideal_encoders else spec.head.encoder
    if shift_m > 0:
        images[SHIFT], angles[SHIFT] = render_shift(world, shift_m, true_angles["ref"],
                                                    angles["ref"])
    if back_m > 0 and shift_m > 0:
        far, far_angles = render_second_station(world, back_m, shift_m)
        images.update(far)
        angles.update(far_angles)
        if not far:
            row["second_station"] = "not planned: out of reach"
    try:
        # the solver knows the servo models (as the procedure reads them from the
        # captures), not whether this run's encoders are ideal
        sigma = head_encoder_sigmas(dict(zip(("pan", "tilt", "roll"), spec.head.models,
                                             strict=True))) if estimate_angles else None
        wall, cpu = time.perf_counter(), time.process_time()
        sol = solve_active(images, angles, ActiveSettings(distortion_terms=distortion_terms,
                                                          shift_m=shift_m,
                                                          encoder_sigma_rad=sigma))
        # the solve's own seconds: on the wall, and of CPU in this process (the render
        # before it excluded; CPU is steadier than the wall on a shared machine)
        row["solve_s"] = time.perf_counter() - wall
        row["solve_cpu_s"] = time.process_time() - cpu
    except SolveError as exc:
        return {**row, "error": str(exc)}
    res = sol.result
    truth = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
    row["focal_pct"] = 100 * max(abs(res["fx"] - cam.fx) / cam.fx,
                                 abs(res["fy"] - cam.fy) / cam.fy)
    row["centre_px"] = math.hypot(res["cx"] - cam.cx, res["cy"] - cam.cy)
    row["z"] = {k: (res[k] - truth[k]) / max(res["sigma"][k], 1e-12) for k in KEYS}
    row["sigma"] = res["sigma"]
    row["rms_px"] = res["summary"]["rms_px"]
    row["parallax"] = res["parallax"]
    station = res["tracking"].get("second_station")
    if isinstance(station, dict):
        row["second_station"] = {"contours": station["contours"],
                                 "tracked": {k: v["tracked"]
                                             for k, v in station["motions"].items()}}
    elif station is not None:
        row["second_station"] = station
    row["scene_depth"] = res["tracking"].get("scene_depth")
    row["head_geometry"] = head_check(world, res)
    row["timings_s"] = sol.timings_s
    row["final_starts"] = res["tracking"].get("final_starts")
    return row


def head_check(world: World, result: dict) -> dict:
    """The recorded head geometry (``head_model``) against the world's: at each of
    ``HEAD_CHECK_DEG``, the rotation from home's error (deg) and its Mahalanobis norm
    under the reported covariance (squared, chi-squared with 3 degrees of freedom when
    honest), the largest of each over the pans and tilts (``pan_tilt``, what re-aiming
    a head beside the arm needs) and over the rolls (``roll``); the centre's offset
    error (mm) when it was estimated."""
    geometry = head_model.from_result(result)
    T0 = world.T_head_cam(0.0, 0.0, 0.0)
    out: dict = {}
    for part in ("pan_tilt", "roll"):
        errors, norms = [], []
        for deg in HEAD_CHECK_DEG:
            if (part == "roll") != (deg[2] != 0.0):
                continue
            angles = tuple(math.radians(v) for v in deg)
            R_true = (np.linalg.inv(T0) @ world.T_head_cam(*angles))[:3, :3]
            R = geometry.rotation_from_home(angles)
            errors.append(math.degrees(np.linalg.norm(R_to_rotvec(R @ R_true.T))))
            norms.append(float(geometry.rotation_error_z(angles, R_true)[3]))
        out[part] = {"rotation_error_deg": max(errors), "mahalanobis": max(norms),
                     "mahalanobis_all": norms}
    if geometry.offset_estimated:
        out["offset_error_mm"] = 1000 * float(np.linalg.norm(geometry.offset_m
                                                             - world.cam_offset))
    return out


def summarise(rows: list[dict]) -> dict:
    ok = [r for r in rows if "error" not in r]
    out = {"worlds": len(rows), "failed": len(rows) - len(ok)}
    if not ok:
        return out
    f = np.array([r["focal_pct"] for r in ok])
    c = np.array([r["centre_px"] for r in ok])
    z = np.array([[abs(r["z"][k]) for k in KEYS] for r in ok])
    out.update({
        "focal_pct": {"median": float(np.median(f)), "p90": float(np.percentile(f, 90)),
                      "max": float(f.max())},
        "centre_px": {"median": float(np.median(c)), "p90": float(np.percentile(c, 90)),
                      "max": float(c.max())},
        "abs_z": {"median": float(np.median(z)), "p90": float(np.percentile(z, 90)),
                  "max": float(z.max()), "share_over_3": float(np.mean(z > 3)),
                  "rms": float(np.sqrt(np.mean(z ** 2)))},
    })
    heads = [r["head_geometry"] for r in ok if "head_geometry" in r]
    if heads:
        out["head_geometry"] = {}
        for part in ("pan_tilt", "roll"):
            rot = np.array([h[part]["rotation_error_deg"] for h in heads])
            m2 = np.array([m ** 2 for h in heads for m in h[part]["mahalanobis_all"]])
            out["head_geometry"][part] = {
                "rotation_error_deg": {"median": float(np.median(rot)),
                                       "p90": float(np.percentile(rot, 90)),
                                       "max": float(rot.max())},
                # mean 3 and 0.1 % over 16.3 for an honest covariance (chi-squared, 3 dof)
                "mahalanobis_sq": {"mean": float(m2.mean()),
                                   "share_over_16": float(np.mean(m2 > 16.27)),
                                   "max": float(m2.max())}}
    for key in ("solve_s", "solve_cpu_s"):
        seconds = np.array([r[key] for r in ok])
        out[key] = {"median": float(np.median(seconds)),
                    "p90": float(np.percentile(seconds, 90)), "max": float(seconds.max())}
    return out


def run(n: int = 20, first_seed: int = 0, distortion_terms: int | None = None,
        workers: int = 1, shift_m: float = 0.010, second_station_m: float = 0.0,
        ideal_encoders: bool | str = False, estimate_angles: bool = True) -> dict:
    """``n`` worlds from ``first_seed`` (``world_trial``); ``estimate_angles``: the solve
    takes the recorded head angles as readings of the servos' encoder sigma (False: as
    exact, as before issue 40)."""
    jobs = [(first_seed + i, distortion_terms, shift_m, second_station_m, ideal_encoders,
             estimate_angles) for i in range(n)]
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            rows = list(pool.map(world_trial, jobs))
    else:
        rows = [world_trial(j) for j in jobs]
    return {"distortion_terms": distortion_terms, "seeds": [first_seed, first_seed + n - 1],
            "summary": summarise(rows), "worlds": rows}
