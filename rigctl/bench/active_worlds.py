"""``rigctl bench active-worlds``: the active-camera pipeline on random worlds.

For each seed, ``mocks.random_world`` draws a rig; the world's own renderer
(``mocks.world``, OpenCV's projection and distortion, then JPEG at the world's quality)
draws what the camera sees at the procedure's head angles, with the arm at home; the
same pipeline the procedure runs (``rigctl.calib.active_pipeline``) solves it. No stand-in
processes: this judges the solver, fast, on many rigs. ``rigctl bench worlds`` runs the
whole procedure chain through the stand-ins.

Reports per world and as a distribution: focal error (%), centre error (px) and each
intrinsic's error divided by its reported sigma (|z| > 3 means the sigma is too small).
"""

from __future__ import annotations

import math
from concurrent.futures import ProcessPoolExecutor

import cv2
import numpy as np

from mocks.random_world import random_world
from mocks.world import World, WorldFile
from procedures.active_camera import ActiveCameraParams, head_poses
from rigctl.calib.active_depth import camera_shift_joints
from rigctl.calib.active_pipeline import SHIFT, ActiveSettings, solve_active
from rigctl.errors import SolveError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.geometry.transforms import xyz_rpy_to_T

# the procedure's own default plan, so the bench judges what an operator runs
POSES_DEG = {label: tuple(math.degrees(a) for a in angles)
             for label, *angles in head_poses(ActiveCameraParams())}
KEYS = ("fx", "fy", "cx", "cy")


def _delivered(image: np.ndarray, quality: int) -> np.ndarray:
    """A rendered image as the stand-in camera delivers it: JPEG at the world's quality,
    decoded to grey."""
    _, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def render_views(world: World, poses_deg: dict) -> tuple[dict, dict]:
    """What the stand-in camera would deliver at each head pose (arm at home)."""
    images, angles = {}, {}
    quality = world.spec.camera.jpeg_quality
    for k, (label, deg) in enumerate(poses_deg.items()):
        a = tuple(math.radians(v) for v in deg)
        images[label] = _delivered(world.render(world.T_base_cam(world.home_q, a),
                                                frame_index=k), quality)
        angles[label] = a
    return images, angles


def render_shift(world: World, shift_m: float) -> tuple:
    """The procedure's sideways move: planned, as on the simulated rig, with the nominal
    arm and the head mount rounded as ``rigctl sim up`` writes it; rendered with the
    true arm."""
    he = world.spec.hand_eye
    T_flange_cam = xyz_rpy_to_T([round(v, -1) for v in he.xyz_mm],
                                [round(v) for v in he.rpy_deg])
    q = camera_shift_joints(nominal_ur(world.spec.arm.model), world.home_q, T_flange_cam,
                            shift_m)
    img = world.render(world.T_base_cam(q, (0.0, 0.0, 0.0)), frame_index=99)
    return _delivered(img, world.spec.camera.jpeg_quality), (0.0, 0.0, 0.0)


def world_trial(args) -> dict:
    seed, distortion_terms, shift_m = args
    spec = WorldFile.model_validate(random_world(seed))
    world = World(spec)
    cam = spec.camera
    row = {"seed": seed, "model": spec.arm.model, "fx_true": cam.fx,
           "k": cam.distortion, "camera_offset_mm": spec.head.camera_offset_mm}
    images, angles = render_views(world, POSES_DEG)
    if shift_m > 0:
        images[SHIFT], angles[SHIFT] = render_shift(world, shift_m)
    try:
        sol = solve_active(images, angles, ActiveSettings(distortion_terms=distortion_terms,
                                                          shift_m=shift_m))
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
    row["scene_depth"] = res["tracking"].get("scene_depth")
    row["timings_s"] = sol.timings_s
    return row


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
    return out


def run(n: int = 20, first_seed: int = 0, distortion_terms: int | None = None,
        workers: int = 1, shift_m: float = 0.010) -> dict:
    jobs = [(first_seed + i, distortion_terms, shift_m) for i in range(n)]
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            rows = list(pool.map(world_trial, jobs))
    else:
        rows = [world_trial(j) for j in jobs]
    return {"distortion_terms": distortion_terms, "seeds": [first_seed, first_seed + n - 1],
            "summary": summarise(rows), "worlds": rows}
