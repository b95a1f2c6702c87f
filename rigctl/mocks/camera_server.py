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


class Camera:
    """Renders frames at the world's fps from the live head and arm state."""

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

    def state(self) -> tuple[tuple[float, float, float], np.ndarray]:
        angles = [0.0, 0.0, 0.0]
        dump = self.head.ask({"cmd": "dump"})
        if dump and dump.get("ok"):
            by_id = {s["id"]: s for s in dump["servos"]}
            for axis, dxl_id in enumerate(self.head_ids):
                if dxl_id in by_id:
                    angles[axis] = by_id[dxl_id]["actual_rad"]
        q = self.world.home_q
        dump = self.arm.ask({"cmd": "dump"})
        if dump and dump.get("ok"):
            q = np.array(dump["q"])
        return (angles[0], angles[1], angles[2]), q

    def loop(self) -> None:
        period = 1.0 / self.world.spec.camera.fps
        quality = [cv2.IMWRITE_JPEG_QUALITY, self.world.spec.camera.jpeg_quality]
        next_t = time.monotonic()
        index = 0
        while self.running:
            next_t += period
            if time.monotonic() >= self.stall_until:
                t_sample = time.time()
                angles, q = self.state()
                t0 = time.perf_counter()
                image = self.world.render(self.world.T_base_cam(q, angles), index, q=q)
                _ok, jpeg = cv2.imencode(".jpg", image, quality)
                self.render_s.append(time.perf_counter() - t0)
                self.render_s = self.render_s[-200:]
                if time.time() - t_sample > MAX_FRAME_AGE_S:
                    self.dropped += 1
                else:
                    with self.cond:
                        self.frame = {"seq": index, "t_sample": t_sample,
                                      "jpeg": jpeg.tobytes(), "head": angles, "q": q.tolist()}
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
                while camera.running:
                    frame = camera.wait_frame(seq, timeout=1.0)
                    if frame is None or frame["seq"] == seq:
                        continue
                    seq = frame["seq"]
                    if time.time() - frame["t_sample"] > MAX_FRAME_AGE_S:
                        camera.dropped += 1
                        continue
                    part = (b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n"
                            b"X-Sequence: %d\r\nX-Timestamp: %.6f\r\n\r\n"
                            % (len(frame["jpeg"]), seq, frame["t_sample"]))
                    try:
                        self.wfile.write(part + frame["jpeg"] + b"\r\n")
                        self.wfile.flush()
                    except OSError:
                        return
            elif self.path.startswith("/snapshot"):
                frame = camera.wait_frame(-1)
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
