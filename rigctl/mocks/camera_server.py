"""A simulated camera: renders the world at the stand-ins' current head angles and arm
joints and streams MJPEG over HTTP on loopback::

    python -m rigctl.mocks.camera_server --world W.yaml [--host 127.0.0.1] [--port 18080]
        [--head-control SOCK] [--arm-control SOCK] [--control SOCK]

Endpoints: ``/stream.mjpg`` (multipart/x-mixed-replace), ``/snapshot.jpg``, ``/state``.
The head and arm poses come from the stand-ins' control sockets (the true shaft angles
and joint positions), so the camera sees what the simulated hardware is doing.
Control socket (JSON lines): ``{"cmd": "stall", "seconds": S}``, ``{"cmd": "dump"}``.
"""

from __future__ import annotations

import argparse
import http.server
import json
import os
import signal
import socket
import socketserver
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from rigctl.mocks.jsonlines import Client, listen, serve_stream
from rigctl.mocks.world import World, load_world

# A real camera's frame reaches the host within tens of milliseconds of its exposure. A
# stand-in descheduled on a busy host could publish a frame rendered from a state sampled
# a second earlier; such a frame is dropped instead (as a camera drops frames when its
# bus is busy), so that no frame older than this is ever sent. Seen once at load 7 on
# 2 cores: a frame sampled >1 s before a joint move ended passed the driver's arrival
# and stillness rules and showed the previous pose.
MAX_FRAME_AGE_S = 0.5

# Pixel noise comes from a few fields drawn once, each frame a window at a random offset
# into one of them: drawing 0.9 M normals per frame cost as much as the rendering. Windows
# at random offsets into random fields are uncorrelated pixel for pixel, which is all that
# detection and the stillness check see. Each field is kept rounded, as its positive and
# its negative part in uint8, so that a frame's noise is two saturating additions: the
# same pixels as rounding image + noise and clipping to 0..255 (the image is whole grey
# levels), at a fifth of the cost of doing it in floating point.
NOISE_FIELDS = 4
NOISE_MARGIN_PX = 64


class PixelNoise:
    """Gaussian pixel noise of ``sigma`` grey levels for images of ``shape`` (h, w)."""

    def __init__(self, shape: tuple[int, int], sigma: float, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        h, w = shape
        self.shape = shape
        self.fields: list[tuple[np.ndarray, np.ndarray]] = []
        for _ in range(NOISE_FIELDS if sigma > 0 else 0):
            field = self.rng.standard_normal((h + NOISE_MARGIN_PX, w + NOISE_MARGIN_PX),
                                             np.float32) * np.float32(sigma)
            whole = np.floor(field + np.float32(0.5))
            self.fields.append((np.clip(whole, 0, 255).astype(np.uint8),
                                np.clip(-whole, 0, 255).astype(np.uint8)))

    def add(self, image: np.ndarray) -> np.ndarray:
        """``image`` (uint8) with a fresh window of noise added, rounded and clipped."""
        if not self.fields:
            return image
        h, w = self.shape
        up, down = self.fields[int(self.rng.integers(len(self.fields)))]
        dy, dx = (int(v) for v in self.rng.integers(0, NOISE_MARGIN_PX + 1, size=2))
        return cv2.subtract(cv2.add(image, up[dy:dy + h, dx:dx + w]),
                            down[dy:dy + h, dx:dx + w])


class Camera:
    """Renders frames at the world's fps from the live head and arm state, while someone
    watches (a stream client or a snapshot): a camera nobody reads costs nothing. The
    noiseless picture is rendered again only when the head or the arm moved."""

    def __init__(self, world: World, head: Client, arm: Client,
                 head_ids: list[int]) -> None:
        self.world, self.head, self.arm, self.head_ids = world, head, arm, head_ids
        self.cond = threading.Condition()
        self.frame: dict | None = None
        self.stall_until = 0.0
        self.running = True
        self.rendered = 0
        self.dropped = 0
        self.render_s: list[float] = []
        self.viewers = 0
        self._still: tuple[tuple, np.ndarray] | None = None  # (state, noiseless image)
        self._still_jpeg: bytes | None = None  # that image encoded, in a noiseless world
        self.noise = PixelNoise((world.size[1], world.size[0]), world.spec.camera.pixel_noise,
                                world.spec.seed)

    def watch(self, change: int) -> None:
        """One viewer more (``+1``) or fewer (``-1``); rendering runs while any watch."""
        with self.cond:
            self.viewers += change
            self.cond.notify_all()

    def picture(self, angles: tuple, q: np.ndarray, moving: bool = False) -> np.ndarray:
        """The frame at head ``angles`` and joints ``q``: noiseless render (reused while
        nothing moved) plus fresh pixel noise. A frame taken while the head or the arm
        moves is rendered without anti-aliasing: a real camera blurs it, and no client may
        use it (the driver waits for a still frame after a motion)."""
        key = (tuple(angles), tuple(np.asarray(q, float).tolist()), moving)
        if self._still is None or self._still[0] != key:
            image = self.world.render(self.world.T_base_cam(q, angles), noise=False, q=q,
                                      **({"supersample": 1} if moving else {}))
            self._still = (key, image)
            self._still_jpeg = None
        return self.noise.add(self._still[1])

    def jpeg(self, angles: tuple, q: np.ndarray, moving: bool, quality: list[int]) -> bytes:
        """``picture`` as JPEG. A world without pixel noise gives the same frame again
        while nothing moves: it is encoded once."""
        image = self.picture(angles, q, moving)
        if self.noise.fields:
            return cv2.imencode(".jpg", image, quality)[1].tobytes()
        if self._still_jpeg is None:
            self._still_jpeg = cv2.imencode(".jpg", image, quality)[1].tobytes()
        return self._still_jpeg

    def state(self) -> tuple[tuple[float, float, float], np.ndarray, bool]:
        """Head angles and arm joints now (the stand-ins' true values), and whether
        either is moving."""
        angles = [0.0, 0.0, 0.0]
        moving = False
        dump = self.head.ask({"cmd": "dump"})
        if dump and dump.get("ok"):
            by_id = {s["id"]: s for s in dump["servos"]}
            for axis, dxl_id in enumerate(self.head_ids):
                if dxl_id in by_id:
                    angles[axis] = by_id[dxl_id]["actual_rad"]
                    moving = moving or bool(by_id[dxl_id].get("moving"))
        q = self.world.home_q
        dump = self.arm.ask({"cmd": "dump"})
        if dump and dump.get("ok"):
            q = np.array(dump["q"])
            moving = moving or any(dump.get("qd", ()))
        return (angles[0], angles[1], angles[2]), q, moving

    def loop(self) -> None:
        period = 1.0 / self.world.spec.camera.fps
        quality = [cv2.IMWRITE_JPEG_QUALITY, self.world.spec.camera.jpeg_quality]
        next_t = time.monotonic()
        index = 0
        while self.running:
            with self.cond:
                if self.viewers <= 0:  # nobody reads: wait for a viewer, render nothing
                    self.cond.wait_for(lambda: self.viewers > 0 or not self.running, 0.5)
                    next_t = time.monotonic()
                    continue
            next_t += period
            if time.monotonic() >= self.stall_until:
                t_sample = time.time()
                angles, q, moving = self.state()
                t0 = time.perf_counter()
                jpeg = self.jpeg(angles, q, moving, quality)
                self.render_s.append(time.perf_counter() - t0)
                self.render_s = self.render_s[-200:]
                if time.time() - t_sample > MAX_FRAME_AGE_S:
                    self.dropped += 1
                else:
                    with self.cond:
                        self.frame = {"seq": index, "t_sample": t_sample,
                                      "jpeg": jpeg, "head": angles, "q": q.tolist()}
                        self.cond.notify_all()
                index += 1
                self.rendered = index
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()

    def wait_frame(self, after_seq: int, timeout: float = 2.0) -> dict | None:
        with self.cond:
            self.cond.wait_for(lambda: self.frame is not None and self.frame["seq"] > after_seq,
                               timeout)
            return self.frame


def make_handler(camera: Camera):
    class Handler(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

        def do_GET(self) -> None:
            if self.path.startswith("/stream"):
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.send_header("Cache-Control", "no-cache")
                self.end_headers()
                seq = -1
                camera.watch(+1)
                try:
                    while camera.running:
                        frame = camera.wait_frame(seq, timeout=1.0)
                        if frame is None or frame["seq"] == seq:
                            continue
                        seq = frame["seq"]
                        if time.time() - frame["t_sample"] > MAX_FRAME_AGE_S:
                            camera.dropped += 1
                            continue
                        part = (b"--frame\r\nContent-Type: image/jpeg\r\n"
                                b"Content-Length: %d\r\nX-Sequence: %d\r\n"
                                b"X-Timestamp: %.6f\r\n\r\n"
                                % (len(frame["jpeg"]), seq, frame["t_sample"]))
                        try:
                            self.wfile.write(part + frame["jpeg"] + b"\r\n")
                            self.wfile.flush()
                        except OSError:
                            return
                finally:
                    camera.watch(-1)
            elif self.path.startswith("/snapshot"):
                last = camera.frame["seq"] if camera.frame is not None else -1
                camera.watch(+1)
                try:  # a frame rendered for this request, not one left from long ago
                    frame = camera.wait_frame(last, timeout=5.0)
                finally:
                    camera.watch(-1)
                if frame is None:
                    self.send_error(503, "no frame rendered within 5 s")
                    return
                self.send_response(200)
                self.send_header("Content-Type", "image/jpeg")
                self.send_header("Content-Length", str(len(frame["jpeg"])))
                self.end_headers()
                self.wfile.write(frame["jpeg"])
            elif self.path.startswith("/state"):
                frame = camera.frame or {}
                body = json.dumps({k: v for k, v in frame.items() if k != "jpeg"}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
            else:
                self.send_error(404, "unknown path; try /stream.mjpg")

    return Handler


class ThreadingServer(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True
    allow_reuse_address = True


def serve_control(path: Path, camera: Camera) -> socket.socket:
    server = listen(path)

    def control(req: dict) -> dict:
        if req.get("cmd") == "stall":
            camera.stall_until = time.monotonic() + float(req.get("seconds", 5))
            return {"ok": True}
        if req.get("cmd") == "dump":
            times = camera.render_s or [0.0]
            return {"ok": True, "rendered": camera.rendered, "dropped_stale": camera.dropped,
                    "render_ms_median": 1000 * float(np.median(times))}
        return {"ok": False, "error": f"unknown cmd {req.get('cmd')!r}"}

    def accept() -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            threading.Thread(target=serve_stream, args=(conn, control), daemon=True).start()

    threading.Thread(target=accept, daemon=True).start()
    return server


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="camera_server", description=__doc__.split("\n")[0])
    parser.add_argument("--world", required=True)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=18080)
    parser.add_argument("--head-control", default=None)
    parser.add_argument("--head-ids", type=int, nargs=3, default=[1, 2, 3])
    parser.add_argument("--arm-control", default=None)
    parser.add_argument("--control", type=Path, default=None)
    args = parser.parse_args(argv)
    if not args.host.startswith("127."):
        print(json.dumps({"error": "the camera stand-in binds loopback only"}))
        return 2
    world = load_world(args.world)
    camera = Camera(world, Client(args.head_control), Client(args.arm_control),
                    args.head_ids)
    threading.Thread(target=camera.loop, daemon=True, name="render").start()
    httpd = ThreadingServer((args.host, args.port), make_handler(camera))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    control = serve_control(args.control, camera) if args.control else None
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    port = httpd.server_address[1]  # --port 0 binds an ephemeral port
    print(json.dumps({"url": f"http://{args.host}:{port}/stream.mjpg", "host": args.host,
                      "port": port, "pid": os.getpid(),
                      "control": str(args.control) if args.control else None}), flush=True)
    done.wait()
    camera.running = False
    httpd.shutdown()
    httpd.server_close()
    if control is not None:
        control.close()
        args.control.unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
