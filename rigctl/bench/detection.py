"""``rigctl bench detection``: checkerboard detection on random worlds, the half-scale
first search (``rigctl.calib.board.LOCATE_SCALE``) against the whole image's.

For each seed, ``rigctl.mocks.random_world`` draws a rig; its renderer draws the board
from cameras around the board's normal (10-40 deg off it, at 1.1-1.8 times the distance
where the board fills the image), JPEG at the world's quality as the stand-in sends it.
Both searches run on every view. Reports, per search: CPU a view, views found, each
view's corner error against the truth (RMS over its corners; median and p90 over the
views) and its shared (mean) error; and the largest difference of a corner between them
(a board with rows + cols even taken in either search's order: it looks the same after a
half turn, and the procedures order it by where the nominal arm predicts it).
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np

from rigctl.calib.board import LOCATE_SCALE, detect_board
from rigctl.geometry.transforms import look_at
from rigctl.mocks.random_world import random_world
from rigctl.mocks.world import World, WorldFile

SEARCHES = {"half_scale_first": LOCATE_SCALE, "whole_image": 1.0}
EDGE_PX = 10  # every corner this far inside the image


def board_views(world: World, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Up to ``n`` cameras (``T_base_cam``) that see every corner of the world's board."""
    tg = world.spec.target
    s = tg.square_mm / 1000.0
    T = world.T_base_target
    centre = T[:3, :3] @ np.array([tg.cols * s / 2, tg.rows * s / 2, 0.0]) + T[:3, 3]
    normal, inplane = -T[:3, 2], T[:3, 0]
    across = np.cross(normal, inplane)
    w, h = world.size
    fills = max(tg.cols * s * world.K[0, 0] / w, tg.rows * s * world.K[1, 1] / h)
    views = []
    for _ in range(40 * n):
        if len(views) == n:
            break
        tilt, azimuth = math.radians(rng.uniform(10, 40)), rng.uniform(0, 2 * math.pi)
        side = math.cos(azimuth) * inplane + math.sin(azimuth) * across
        eye = centre + fills * rng.uniform(1.1, 1.8) * (math.cos(tilt) * normal
                                                        + math.sin(tilt) * side)
        spin = rng.uniform(-math.pi, math.pi)
        T_base_cam = look_at(eye, centre, math.cos(spin) * inplane + math.sin(spin) * across)
        px = world.target_corner_pixels(T_base_cam)
        if np.all((px > EDGE_PX) & (px < [w - EDGE_PX, h - EDGE_PX])):
            views.append(T_base_cam)
    return views


def _error(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Corner errors, the detection taken in whichever of its two 180-degree orders is
    nearer the truth (a board with rows + cols even looks the same after a half turn)."""
    straight, turned = found - truth, found[::-1] - truth
    return turned if np.sum(turned ** 2) < np.sum(straight ** 2) else straight


def world_rows(seed: int, views: int) -> list[dict]:
    """Every view of world ``seed``: each search's CPU seconds, and its corner errors."""
    world = World(WorldFile.model_validate(random_world(seed)))
    tg, quality = world.spec.target, [cv2.IMWRITE_JPEG_QUALITY, world.spec.camera.jpeg_quality]
    rows = []
    for k, T_base_cam in enumerate(board_views(world, views, np.random.default_rng(seed))):
        _ok, jpeg = cv2.imencode(".jpg", world.render(T_base_cam, frame_index=k), quality)
        image = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE)
        truth = world.target_corner_pixels(T_base_cam)
        row: dict = {"seed": seed, "view": k, "size": list(world.size)}
        for name, scale in SEARCHES.items():
            t0 = time.process_time()
            found = detect_board(image, tg.rows, tg.cols, locate_scale=scale)
            row[name] = {"cpu_s": time.process_time() - t0, "corners": found,
                         "error": None if found is None else _error(found, truth)}
        rows.append(row)
    return rows


def summarise(rows: list[dict]) -> dict:
    """Per search: CPU a view, views found, corner error (RMS of a view: median, p90; a
    view's mean error: RMS over views); the largest corner difference between them."""
    out: dict = {"views": len(rows), "worlds": len({r["seed"] for r in rows})}
    for name in SEARCHES:
        errors = [r[name]["error"] for r in rows if r[name]["error"] is not None]
        rms = np.array([math.sqrt(float(np.mean(np.sum(e ** 2, axis=1)))) for e in errors])
        shared = np.array([float(np.linalg.norm(e.mean(axis=0))) for e in errors])
        out[name] = {
            "cpu_s_per_view": float(np.mean([r[name]["cpu_s"] for r in rows])) if rows else None,
            "found": len(errors),
            "rms_px_median": float(np.median(rms)) if len(rms) else None,
            "rms_px_p90": float(np.percentile(rms, 90)) if len(rms) else None,
            "shared_px_rms": float(np.sqrt(np.mean(shared ** 2))) if len(shared) else None}
    a, b = SEARCHES
    both = [(r[a]["corners"], r[b]["corners"]) for r in rows
            if r[a]["corners"] is not None and r[b]["corners"] is not None]
    # a board with rows + cols even may come in either order (``_error``)
    out["largest_change_px"] = max((float(np.abs(_error(x, y)).max()) for x, y in both),
                                   default=None)
    return out


def run(n: int = 16, first_seed: int = 1000, views: int = 10) -> dict:
    """``views`` views of each of ``n`` random worlds from ``first_seed``, one core for
    OpenCV so that the CPU figures compare."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rows = [row for seed in range(first_seed, first_seed + n)
                for row in world_rows(seed, views)]
    finally:
        cv2.setNumThreads(threads)
    return {"first_seed": first_seed, "n": n, "locate_scale": LOCATE_SCALE,
            "summary": summarise(rows)}
