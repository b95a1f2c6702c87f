"""``rigctl bench camera``: render rate of the simulated camera, capture latency after a
settled move, and end-to-end survey time on the simulated rig."""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from pathlib import Path

import cv2

from rigctl.config import load_rig
from rigctl.mocks.world import WORLDS, load_world
from rigctl.rig import Rig
from rigctl.runner import Runner
from rigctl.simrig import SimulatedRig


def render_rate(world_path: Path, frames: int = 60) -> dict:
    world = load_world(world_path)
    T = world.T_base_cam(world.home_q, (0.0, 0.0, 0.0))
    quality = [cv2.IMWRITE_JPEG_QUALITY, world.spec.camera.jpeg_quality]
    t0 = time.perf_counter()
    for i in range(frames):
        cv2.imencode(".jpg", world.render(T, i), quality)
    elapsed = time.perf_counter() - t0
    return {"frames": frames, "size": list(world.size), "fps_one_core": frames / elapsed,
            "ms_per_frame": 1000 * elapsed / frames}


def run(world: str = "default") -> dict:
    world_path = WORLDS / f"{world}.yaml"
    out = {"world": world, "render": render_rate(world_path)}
    with tempfile.TemporaryDirectory() as tmp, \
            SimulatedRig(world_path, records=tmp) as sim:
        config = load_rig(sim.rig_path)
        rig = Rig(config)
        latencies = []
        try:
            head, camera = rig.open("head"), rig.open("camera")
            for k in range(12):
                head.move_to(math.radians(2 * (k % 2)), 0.0, 0.0).wait(10)
                settled = time.time()
                t0 = time.perf_counter()
                camera.capture(not_before=settled)
                latencies.append(time.perf_counter() - t0)
        finally:
            rig.close_all()
        out["capture_after_settle_ms"] = {"median": 1000 * statistics.median(latencies),
                                          "max": 1000 * max(latencies),
                                          "frame_period_ms": 1000 / camera.fps}
        t0 = time.perf_counter()
        outcome = Runner(config, show_progress=False).run("capture-survey", {})
        out["survey"] = {"seconds": time.perf_counter() - t0, "status": outcome.status,
                         "captures": (outcome.result or {}).get("captures")}
    return out
