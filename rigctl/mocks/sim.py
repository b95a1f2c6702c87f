"""``rigctl sim up``: the whole rig on stand-ins sharing one world.

Starts the Dynamixel bus (pty), the UR controller and the camera server, writes a rig file
pointing at them, prints one JSON ready line, and runs until SIGTERM; then it stops every
child by PID and removes its links and sockets. ``rigctl sim down`` stops a running one.
When a stand-in ends on its own (a crash), the others are stopped the same way, the
stand-in is named on stderr (where the stand-ins' own tracebacks go too) and the exit
status is 1 instead of 0.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

from rigctl.childproc import ChildProcess, stop_all
from rigctl.errors import ConfigError, DeviceError
from rigctl.mocks.world import load_world
from rigctl.mocks.world import world_file as resolve_world

STATE_DIR = Path(tempfile.gettempdir())


# Timing for stand-in processes, which a busy host deschedules for hundreds of ms; real
# hardware keeps the rig file's defaults. Head: 6 tries of 100 ms with 20-320 ms pauses,
# about 1.2 s per transaction before a servo is reported dead (a 300 ms stall costs three
# tries). Arm: the RTDE stream may pause 5 s before the link counts as lost. Camera: 10 s
# for a frame, three more tries to open the stream, and 0.15 s for a rendered frame to
# arrive (a busy host slows the renderer: a frame sampled before a move ended arrived
# after it, 57 px off, in one loaded run).
# The wait after a move before a capture (every procedure's settle_s on this rig): the
# stand-ins do not ring after a move, and the camera driver already waits for a frame
# exposed after the motion ended and still.
SIM_SETTLE_S = 0.05

STAND_IN_TIMING = {
    "head": {"packet_timeout_ms": 100, "retries": 5, "retry_backoff_s": 0.02},
    # 50 Hz instead of the default 125: ur_rtde's receive and control interfaces cost
    # the run about 5 % of a core each at 125 Hz (2 % at 50), and the stand-in's packing
    # as much again; a calibration reads the arm at rest, and 20 ms is still far under
    # every move's duration
    "arm": {"stream_timeout_s": 5.0, "move_timeout_s": 60, "rtde_frequency_hz": 50.0},
    "camera": {"timeout_s": 10.0, "open_retries": 3, "latency_s": 0.15},
}


def state_path(host: str) -> Path:
    return STATE_DIR / f"rigctl-sim-{host}.json"


def _child(name: str, args: list[str]) -> ChildProcess:
    try:
        return ChildProcess(["-m", *args], timeout=20.0, name=f"sim {name}")
    except RuntimeError as exc:
        raise DeviceError(f"sim: {name} stand-in did not start: {exc}") from None


def rig_mount(world) -> dict:
    """The head mount the rig file states: the world's hand-eye rounded as an operator
    would measure it (10 mm, 1 deg), so that hand-eye has something to find."""
    he = world.spec.hand_eye
    return {"xyz_mm": [round(v, -1) for v in he.xyz_mm], "rpy_deg": [round(v) for v in he.rpy_deg]}


def rig_text(world_path: Path, host: str, workdir: Path, camera_url: str, records: str,
             world) -> dict:
    cam = world.spec.camera
    return {
        "name": f"sim-{host.replace('.', '-')}",
        "world": str(world_path),
        "devices": {
            "head": {"port": str(workdir / "dxl"), "baud": 1_000_000,
                     "model": dict(zip(("pan", "tilt", "roll"), world.spec.head.models,
                                       strict=True)),
                     "limits": {"pan": [-45, 45], "tilt": [-30, 30], "roll": [-180, 180]},
                     "speed_cap_dps": 120, "accel_cap_dps2": 600, "settle_s": SIM_SETTLE_S,
                     **STAND_IN_TIMING["head"], "park": {"policy": "home"},
                     **_head_mount_keys(world)},
            "arm": {"host": host, "model": world.spec.arm.model,
                    "home_deg": list(world.spec.arm.home_deg),
                    "speed_cap_dps": 170, "accel_cap_dps2": 720, "settle_s": SIM_SETTLE_S,
                    **STAND_IN_TIMING["arm"]},
            "camera": {"device": camera_url, "width": cam.width, "height": cam.height,
                       "fps": cam.fps, **STAND_IN_TIMING["camera"]},
        },
        "target": {"rows": world.spec.target.rows, "cols": world.spec.target.cols,
                   "square_mm": world.spec.target.square_mm, **_charuco_keys(world),
                   **({"mount": "flange"} if world.spec.target.mount == "flange" else {}),
                   "pose": {"xyz_mm": [round(v, -1) for v in world.spec.target.xyz_mm],
                            "rpy_deg": list(world.spec.target.rpy_deg)}},
        "records": {"directory": records},
    }


def _head_mount_keys(world) -> dict:
    """The rig file's head mount: the hand-eye as measured (``rig_mount``), or for a head
    standing beside the arm ``mount: fixed`` and its ``T_base_head`` rounded alike."""
    head = world.spec.head
    if head.mount != "fixed":
        return {"mount": rig_mount(world)}
    return {"mount": "fixed", "fixed_pose": {
        "xyz_mm": [round(v, -1) for v in head.fixed_xyz_mm],
        "rpy_deg": [round(v) for v in head.fixed_rpy_deg]}}


def _charuco_keys(world) -> dict:
    """The rig file's ChArUco keys for a world's ChArUco target (none for a checkerboard,
    whose rig file stays as it was)."""
    tg = world.spec.target
    if tg.type != "charuco":
        return {}
    return {"type": "charuco", "dictionary": tg.dictionary, "marker_mm": tg.marker_mm,
            "legacy_pattern": tg.legacy_pattern}


def up(world_file: str, rig_out: str, host: str = "127.0.0.1", records: str = "records",
       port: int = 18080, ready_out=None, workdir: str | None = None) -> int:
    world_path = resolve_world(world_file)
    world = load_world(world_path)
    if not host.startswith("127."):
        raise ConfigError(f"--host {host}: the simulated rig binds loopback addresses only")
    if state_path(host).exists():
        old = json.loads(state_path(host).read_text())
        try:
            os.kill(old["pid"], 0)
            raise DeviceError(f"sim: a simulated rig already runs on {host} (pid {old['pid']});"
                              " stop it with `rigctl sim down`")
        except ProcessLookupError:
            state_path(host).unlink()
    own_dir = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix=f"rigctl-sim-{host}-")) if own_dir else Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    children: list[ChildProcess] = []
    stop = threading.Event()
    crashed: list[str] = []  # stand-ins that ended on their own
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        head = world.spec.head
        children.append(_child("head", ["rigctl.mocks.dynamixel_bus",
                                        "--link", str(workdir / "dxl"),
                                        "--control", str(workdir / "dxl.sock"),
                                        "--model", *head.models, "--encoder", head.encoder,
                                        "--position-noise-deg", str(head.encoder_noise_deg)]))
        children.append(_child("arm", ["rigctl.mocks.ur_controller", "--host", host,
                                       "--world", str(world_path),
                                       "--control", str(workdir / "ur.sock")]))
        children.append(_child("camera", ["rigctl.mocks.camera_server", "--world", str(world_path),
                                         "--host", host, "--port", str(port),
                                         "--head-control", str(workdir / "dxl.sock"),
                                         "--arm-control", str(workdir / "ur.sock"),
                                         "--control", str(workdir / "camera.sock")]))
        rig = rig_text(world_path, host, workdir, children[2].ready["url"], records, world)
        rig_path = Path(rig_out).resolve()
        rig_path.write_text("# written by `rigctl sim up`; points at the stand-ins\n"
                            + yaml.safe_dump(rig, sort_keys=False))
        ready = {"pid": os.getpid(), "rig": str(rig_path), "world": str(world_path),
                 "host": host, "workdir": str(workdir),
                 "head": children[0].ready, "arm": children[1].ready,
                 "camera": children[2].ready,
                 "children": [c.proc.pid for c in children]}
        state_path(host).write_text(json.dumps(ready))
        print(json.dumps(ready), file=ready_out or sys.stdout, flush=True)
        while not stop.is_set():
            for child in children:
                if child.proc.poll() is not None:
                    crashed.append(child.name)
                    print(json.dumps({"error": f"{child.name} stand-in exited "
                                               f"({child.proc.returncode})"}), file=sys.stderr)
                    stop.set()
            stop.wait(0.5)
    finally:
        # asked together, so that a slow one does not push the others past the caller's
        # own wait (SimulatedRig waits 20 s before it kills `sim up`)
        stop_all(list(reversed(children)), timeout=8.0)
        if own_dir:
            shutil.rmtree(workdir, ignore_errors=True)
        else:  # a given workdir is kept; only what the stand-ins made goes
            for name in ("dxl", "dxl.sock", "ur.sock", "camera.sock"):
                (workdir / name).unlink(missing_ok=True)
        state_path(host).unlink(missing_ok=True)
    return 1 if crashed else 0


def _alive(pid: int) -> bool:
    """True while ``pid`` runs; a zombie (exited, not yet reaped by its parent) is not."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return True


def down(host: str = "127.0.0.1", timeout: float = 20.0) -> dict:
    path = state_path(host)
    if not path.exists():
        raise DeviceError(f"sim: no simulated rig is running on {host}")
    state = json.loads(path.read_text())
    try:
        os.kill(state["pid"], signal.SIGTERM)
    except ProcessLookupError:
        path.unlink(missing_ok=True)
        return {"stopped": False, "reason": "was not running"}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not _alive(state["pid"]):
            return {"stopped": True, "pid": state["pid"]}
        time.sleep(0.1)
    raise DeviceError(f"sim: pid {state['pid']} did not stop within {timeout:.0f} s")
