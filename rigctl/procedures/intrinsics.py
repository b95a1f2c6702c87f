"""The camera intrinsics the arm procedures use: resolved when a run is planned (given as a
parameter, or this rig's latest active-camera result) and recorded in its inputs, so
that a solve never reads the index."""

from __future__ import annotations

from typing import Any

import numpy as np

from rigctl.calib import head_model
from rigctl.config import RigConfig
from rigctl.errors import ConfigError, SolveError
from rigctl.geometry.camera import camera_matrix
from rigctl.records import RunDirectory

from .camera_settings import check_settings


def intrinsics_from(config: RigConfig, given: dict | None,
                    allow_settings_change: bool = False) -> dict[str, Any]:
    """``given`` (fx, fy, cx, cy, distortion, optionally sigma, settings and head_geometry)
    or the result of the latest accepted (or succeeded) ``active-camera`` run of this rig,
    with its 1-sigma, the camera settings it was calibrated at (``check_settings`` refuses
    them for another size or focus) and the head's geometry. Read when a run is planned,
    never while solving (``Procedure.resolve_inputs``)."""
    return check_settings(_intrinsics(config, given), config, allow_settings_change)


def _intrinsics(config: RigConfig, given: dict | None) -> dict[str, Any]:
    if given:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in given]
        if missing:
            raise ConfigError(f"intrinsics parameter lacks {missing}")
        out = {"fx": given["fx"], "fy": given["fy"], "cx": given["cx"], "cy": given["cy"],
               "distortion": list(given.get("distortion", [0.0] * 5)), "source": "parameter"}
        if "sigma" in given:
            out["sigma"] = {k: float(given["sigma"][k]) for k in ("fx", "fy", "cx", "cy")}
        if given.get("settings"):
            out["settings"] = dict(given["settings"])
        if given.get("head_geometry") is not None:
            out["head_geometry"] = _checked_head(given["head_geometry"], "intrinsics parameter")
        return out
    from rigctl.record_index import RecordIndex  # SQLAlchemy: only when none is given

    row = RecordIndex(config.database_url()).latest("active-camera", config.name)
    if row is None:
        raise ConfigError(f"{config.name}: no intrinsics: run active-camera first, or give "
                          "--param intrinsics='{fx: ..., fy: ..., cx: ..., cy: ...}'")
    result = RunDirectory(row["run_dir"]).result()
    out = {k: result[k] for k in ("fx", "fy", "cx", "cy")} | {
        "distortion": result.get("distortion", [0.0] * 5), "source": f"run {row['run_id']}"}
    if "sigma" in result:
        out["sigma"] = {k: float(result["sigma"][k]) for k in ("fx", "fy", "cx", "cy")}
    if result.get("camera_settings"):
        out["settings"] = result["camera_settings"]
    if isinstance(result.get("head_geometry"), dict):
        out["head_geometry"] = result["head_geometry"]
    return out


def _checked_head(entry, where: str) -> dict:
    """A given ``head_geometry`` (as an active-camera result records it), checked."""
    try:
        head_model.from_result({"head_geometry": entry}, where)
    except SolveError as exc:
        raise ConfigError(str(exc)) from exc
    return dict(entry)


def head_geometry(intr: dict) -> head_model.HeadGeometry | None:
    """The head's calibrated geometry that came with resolved intrinsics (an active-camera
    result's ``head_geometry``), or None."""
    entry = intr.get("head_geometry")
    return None if entry is None else head_model.from_result(intr, "intrinsics")


def default_prior_sigma(intr: dict) -> dict[str, float]:
    """The 1-sigma given to intrinsics that came without one (a ``--param intrinsics``
    without ``sigma``): a rough guess, 0.5 % on the focal lengths and 10 px on the centre,
    so that the board views decide."""
    return {"fx": 0.005 * intr["fx"], "fy": 0.005 * intr["fy"], "cx": 10.0, "cy": 10.0}


def camera_model(intr: dict) -> tuple[np.ndarray, np.ndarray]:
    """K and the distortion coefficients of resolved intrinsics (``intrinsics_from``)."""
    return (camera_matrix(intr["fx"], intr["fy"], intr["cx"], intr["cy"]),
            np.asarray(intr["distortion"], float))
