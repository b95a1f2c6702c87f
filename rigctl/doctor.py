"""``rigctl doctor``: connect each configured device, report it and its round-trip time."""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path
from typing import Any

from rigctl.config import RigConfig
from rigctl.errors import ConfigError
from rigctl.rig import Rig

PROBES = {
    "head": lambda d: d.read_angles(),
    "arm": lambda d: d.read_state(),
    "camera": lambda d: d.capture(),
}


UDEV_RULE = ('ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", '
             'ATTR{latency_timer}="1"')


def serial_latency(port: str, sysfs: Path = Path("/sys")) -> dict[str, Any]:
    """The USB-serial latency timer of the head's port (``latency_timer`` in sysfs, ms),
    and what to do when it is not 1 ms: an FTDI adapter holds every short servo reply
    until it expires (16 ms by default)."""
    real = Path(os.path.realpath(port))
    timer = sysfs / "bus" / "usb-serial" / "devices" / real.name / "latency_timer"
    if not timer.exists():
        return {"latency_timer_ms": None, "hint": None,
                "latency_timer_note": f"{port} ({real}) has no USB-serial latency timer "
                                      f"({timer} is missing): nothing to set"}
    try:
        value = int(timer.read_text().strip())
    except (OSError, ValueError) as exc:
        return {"latency_timer_ms": None, "hint": f"{timer}: cannot read it: {exc}"}
    if value <= 1:
        return {"latency_timer_ms": value, "hint": None}
    return {"latency_timer_ms": value,
            "hint": f"{port} ({real.name}): the USB-serial latency timer is {value} ms, so "
                    f"every servo reply waits up to {value} ms. Set 1 ms now with "
                    f"`echo 1 | sudo tee {timer}`, and for good with the udev rule "
                    f"`{UDEV_RULE}` in /etc/udev/rules.d/99-usb-serial-latency.rules "
                    "(then `sudo udevadm control --reload` and replug)"}


TEMPERATURE_MARGIN_C = 10.0  # warn this close to a servo's Temperature Limit
VOLTAGE_MARGIN = 0.05  # warn within 5 % of a servo's voltage limits


def servo_warnings(head) -> list[str]:
    """Each servo's present temperature and input voltage against its own limits
    (Temperature Limit, Min/Max Voltage Limit) and its model's operating range, and any
    hardware error: what is near or past a limit."""
    from rigctl.drivers.dynamixel_models import by_name

    warnings = []
    for axis, h in head.health().items():
        name = f"servo {h['id']} ({axis}, {h['model']})"
        model, t = by_name(h["model"]), h["temperature_c"]
        t_limit = min(h["temperature_limit_c"] or model.max_temperature_c,
                      model.max_temperature_c)
        if t >= t_limit - TEMPERATURE_MARGIN_C:
            warnings.append(f"{name}: temperature {t} C is within {TEMPERATURE_MARGIN_C:g} C "
                            f"of its limit {t_limit:g} C")
        v, (lo, hi) = h["voltage_v"], h["voltage_limits_v"] or model.voltage_v
        lo, hi = max(lo, model.voltage_v[0] * 0.9), min(hi, model.voltage_v[1] * 1.1)
        if v <= lo * (1 + VOLTAGE_MARGIN) or v >= hi * (1 - VOLTAGE_MARGIN):
            warnings.append(f"{name}: input voltage {v:.1f} V is near or past its limits "
                            f"{lo:.1f}-{hi:.1f} V (rated {model.voltage_v[0]:g}-"
                            f"{model.voltage_v[1]:g} V)")
        if h["hardware_error"]:
            from rigctl.drivers.dynamixel import hw_error_text

            warnings.append(f"{name}: alert: {hw_error_text(h['hardware_error'])} "
                            "(`rigctl head reboot` clears it once the cause is fixed)")
    return warnings


def check_rig(config: RigConfig, factories: dict | None = None, samples: int = 20) -> list[dict]:
    """One row per device: ``ok`` with description and median latency, ``missing`` when not
    configured, ``refused`` when the device is another than the rig file says (the arm's
    controller reports another model: ``rigctl doctor`` exits 2), or ``error`` with what
    went wrong. Never moves anything."""
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
            warnings = servo_warnings(device) if hasattr(device, "health") else []
            report.append({"device": kind, "state": "ok", "describe": info,
                           "message": ", ".join(f"{k}={v}" for k, v in info.items()
                                                if not isinstance(v, (dict, list)))[:160]
                           + "".join(f"; WARNING {w}" for w in warnings),
                           "warnings": warnings,
                           "latency_ms": 1000 * statistics.median(times)})
        except ConfigError as exc:  # the device is not what the rig file says
            report.append({"device": kind, "state": "refused", "message": str(exc)})
        except Exception as exc:
            report.append({"device": kind, "state": "error",
                           "message": f"{type(exc).__name__}: {exc}"})
        if kind == "head":
            report[-1] |= serial_latency(config.devices.head.port)
    rig.close_all()
    return report
