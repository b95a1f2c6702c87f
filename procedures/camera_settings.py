"""The camera settings intrinsics were calibrated at, and the check that a procedure
using them runs the camera the same way.

Intrinsics hold only for the image size and focus they were measured at. An
``active-camera`` result records them (``camera_settings``, from the run's
``versions.json``); a procedure that takes those intrinsics refuses to plan when the rig
file now asks for another size or focus, unless ``allow_settings_change`` is given, and
then records the difference in its inputs.
"""

from __future__ import annotations

from typing import Any

from rigctl.errors import ConfigError

FOCUS = ("focus_absolute", "focus_automatic_continuous", "focus_auto")


def settings_of_run(run) -> dict[str, Any] | None:
    """Size and focus the run's camera delivered (its recorded ``versions.json``)."""
    versions = run.versions() or {}
    camera = (versions.get("devices") or {}).get("camera") or {}
    settings = camera.get("settings") or {}
    if "width" not in settings:
        return None
    out = {"width": int(settings["width"]), "height": int(settings["height"])}
    v4l2 = settings.get("v4l2") or {}
    out |= {k: v4l2[k] for k in FOCUS if k in v4l2}
    return out


def settings_now(config) -> dict[str, Any]:
    """Size and focus the rig file asks of the camera."""
    camera = config.devices.camera
    out: dict[str, Any] = {"width": camera.width, "height": camera.height}
    out |= {k: v for k, v in camera.v4l2_controls.items() if k in FOCUS}
    return out


def check_settings(intrinsics: dict[str, Any], config, allow_change: bool) -> dict[str, Any]:
    """``intrinsics``, refused (``ConfigError``, exit 2) when the camera's size or focus
    now differs from what they were calibrated at; with ``allow_change`` they pass and
    carry ``settings_change_allowed`` (calibrated at, now)."""
    then = intrinsics.get("settings")
    if not then or config.devices.camera is None:
        return intrinsics
    now = settings_now(config)
    keys = ["width", "height"] + [k for k in FOCUS if k in then or k in now]
    differ = {k: {"calibrated": then.get(k), "now": now.get(k)} for k in keys
              if then.get(k) != now.get(k)}
    if not differ:
        return intrinsics
    text = "; ".join(f"{k} {d['calibrated']} at calibration, {d['now']} now"
                     for k, d in differ.items())
    if not allow_change:
        raise ConfigError(f"intrinsics from {intrinsics.get('source')} were calibrated with "
                          f"other camera settings ({text}): recalibrate (active-camera), or "
                          "give --param allow_settings_change=true to use them anyway")
    return {**intrinsics, "settings_change_allowed": differ}
