"""``rigctl doctor``: connect each configured device, report it and its round-trip time."""

from __future__ import annotations

import statistics
import time
from typing import Any

from rigctl.config import RigConfig
from rigctl.rig import Rig

PROBES = {
    "head": lambda d: d.read_angles(),
    "arm": lambda d: d.read_state(),
    "camera": lambda d: d.capture(),
}


def check_rig(config: RigConfig, factories: dict | None = None, samples: int = 20) -> list[dict]:
    """One row per device: ``ok`` with description and median latency, ``missing`` when not
    configured, or ``error`` with what went wrong. Never moves anything."""
    rig = Rig(config, factories)
    report: list[dict[str, Any]] = []
    for kind in ("head", "arm", "camera"):
        if getattr(config.devices, kind) is None:
            report.append({"device": kind, "state": "missing",
                           "message": f"no devices.{kind} section in the rig file"})
            continue
        try:
            device = rig.open(kind)
            n = 3 if kind == "camera" else samples
            times = []
            for _ in range(n):
                t0 = time.perf_counter()
                PROBES[kind](device)
                times.append(time.perf_counter() - t0)
            info = device.describe()
            report.append({"device": kind, "state": "ok", "describe": info,
                           "message": ", ".join(f"{k}={v}" for k, v in info.items()
                                                if not isinstance(v, (dict, list)))[:160],
                           "latency_ms": 1000 * statistics.median(times)})
        except Exception as exc:
            report.append({"device": kind, "state": "error",
                           "message": f"{type(exc).__name__}: {exc}"})
    rig.close_all()
    return report
