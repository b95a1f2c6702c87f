"""The camera settings intrinsics were calibrated at, and the check that a procedure
using them runs the camera the same way.

Intrinsics hold only for the image size and focus they were measured at. An
``active-camera`` result records them (``camera_settings``, from the run's
``versions.json``: what the camera driver read back from the device); a procedure that
takes those intrinsics refuses to plan when the camera would now run at another size or
focus, unless ``allow_settings_change`` is given, and then records the difference in its
inputs.

Like is compared with like. The record holds the device's own control names and every
value the driver set, including the automatic focus that ``auto_off`` turned off; what
the camera runs with now is the rig file's ``v4l2_controls`` plus what ``auto_off``
implies. Names are compared under their Linux >= 5.16 form
(``rigctl.drivers.v4l2_controls.canonical``), so a rig file's ``focus_auto`` matches a device's
``focus_automatic_continuous``. An automatic that ``auto_off`` turns off is set only on a
device that has it, which the rig file cannot tell: it is compared only where the
calibration recorded it (a camera without autofocus records none).
"""

from __future__ import annotations

from typing import Any

from rigctl.drivers.v4l2_controls import AUTO_OFF, canonical, device_path
from rigctl.errors import ConfigError

# the focus controls, by their canonical names
FOCUS = ("focus_absolute", "focus_automatic_continuous")


def _focus(controls: dict[str, Any]) -> dict[str, Any]:
    """The focus controls among ``controls``, under their canonical names."""
    return {canonical(k): v for k, v in controls.items() if canonical(k) in FOCUS}


def settings_of_run(run) -> dict[str, Any] | None:
    """Size and focus the run's camera delivered (its recorded ``versions.json``), focus
    controls under the names the device reported."""
    versions = run.versions() or {}
    camera = (versions.get("devices") or {}).get("camera") or {}
    settings = camera.get("settings") or {}
    if "width" not in settings:
        return None
    out = {"width": int(settings["width"]), "height": int(settings["height"])}
    v4l2 = settings.get("v4l2") or {}
    out |= {k: v for k, v in v4l2.items() if canonical(k) in FOCUS}
    return out


def _auto_off_focus(camera) -> dict[str, int]:
    """The focus automatics the camera driver turns off (``auto_off``, on a V4L2 device
    node), canonical names and their "off" values."""
    if not camera.auto_off or device_path(camera.device) is None:
        return {}
    return {k: v for k, v in AUTO_OFF.items() if k in FOCUS}


def settings_now(config) -> dict[str, Any]:
    """Size and focus the camera will run with under the rig file: its size, what
    ``auto_off`` turns off, and its ``v4l2_controls`` (which win, as in the driver),
    canonical names."""
    camera = config.devices.camera
    out: dict[str, Any] = {"width": camera.width, "height": camera.height}
    return out | _auto_off_focus(camera) | _focus(camera.v4l2_controls)


def check_settings(intrinsics: dict[str, Any], config, allow_change: bool) -> dict[str, Any]:
    """``intrinsics``, refused (``ConfigError``, exit 2) when the camera's size or focus
    now differs from what they were calibrated at; with ``allow_change`` they pass and
    carry ``settings_change_allowed`` (calibrated at, now; canonical names)."""
    then = intrinsics.get("settings")
    camera = config.devices.camera
    if not then or camera is None:
        return intrinsics
    calibrated = {k: then.get(k) for k in ("width", "height")} | _focus(then)
    now = settings_now(config)
    # implied by auto_off alone: the device may not have it; compared where recorded
    implied_only = set(_auto_off_focus(camera)) - set(_focus(camera.v4l2_controls))
    keys = ["width", "height"] + [k for k in FOCUS if k in calibrated
                                  or (k in now and k not in implied_only)]
    differ = {k: {"calibrated": calibrated.get(k), "now": now.get(k)} for k in keys
              if calibrated.get(k) != now.get(k)}
    if not differ:
        return intrinsics

    def shown(value):
        return "unset" if value is None else value

    text = "; ".join(f"{k} {shown(d['calibrated'])} at calibration, {shown(d['now'])} now"
                     for k, d in differ.items())
    if not allow_change:
        raise ConfigError(f"intrinsics from {intrinsics.get('source')} were calibrated with "
                          f"other camera settings ({text}): recalibrate (active-camera), or "
                          "give --param allow_settings_change=true to use them anyway")
    return {**intrinsics, "settings_change_allowed": differ}
