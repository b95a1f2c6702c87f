"""Exports of a recorded result: JSON, OpenCV FileStorage YAML, ROS camera_info YAML,
UR-style DH deltas, and (``rigctl.exports_ur``) the UR ROS 2 driver's kinematics YAML,
a URDF, and a fixed camera's pose as a ROS static transform YAML."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from rigctl.errors import ConfigError, RigError
from rigctl.geometry.camera import camera_matrix

FORMATS = ("json", "opencv", "ros", "ur", "ur-kinematics", "urdf", "ros-static")
SUFFIXES = {"json": ".json", "opencv": ".opencv.yaml", "ros": ".camera_info.yaml",
            "ur": ".ur_calibration.yaml", "ur-kinematics": ".ur_kinematics.yaml",
            "urdf": ".urdf", "ros-static": ".static_transform.yaml"}


def _intrinsics(result: dict[str, Any], run_id: str) -> tuple[np.ndarray, np.ndarray, int, int]:
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in result]
    if missing:
        raise RigError(f"run {run_id}: result has no camera intrinsics to export "
                       f"(missing {', '.join(missing)})")
    K = camera_matrix(result["fx"], result["fy"], result["cx"], result["cy"])
    dist = np.array(result.get("distortion") or [0.0] * 5, dtype=float)
    return K, dist, int(result["width"]), int(result["height"])


def export_opencv(result: dict[str, Any], path: Path, run_id: str) -> None:
    """OpenCV FileStorage YAML, readable with ``cv2.FileStorage(path, READ)``."""
    import cv2

    K, dist, width, height = _intrinsics(result, run_id)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", width)
    fs.write("image_height", height)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.write("run_id", run_id)
    fs.release()


def export_ros(result: dict[str, Any], path: Path, run_id: str,
               camera_name: str = "rigctl") -> None:
    """ROS ``camera_info`` YAML (camera_calibration_parsers layout, plumb_bob model)."""
    K, dist, width, height = _intrinsics(result, run_id)
    P = np.hstack([K, np.zeros((3, 1))])
    doc = {
        "image_width": width,
        "image_height": height,
        "camera_name": camera_name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": len(dist), "data": dist.tolist()},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
        "projection_matrix": {"rows": 3, "cols": 4, "data": P.ravel().tolist()},
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def export_ur(result: dict[str, Any], path: Path, run_id: str) -> None:
    """UR-style DH deltas relative to the nominal model (delta_theta, delta_a, delta_d,
    delta_alpha; radians and metres) with Hayati beta alongside."""
    from rigctl.geometry.kinematics import nominal_ur

    if "links" not in result or "arm_model" not in result:
        raise RigError(f"run {run_id}: result has no arm kinematics to export")
    nominal = nominal_ur(result["arm_model"])
    links = result["links"]
    doc = {"model": result["arm_model"], "run_id": run_id,
           "delta_theta": [lk["theta_offset"] for lk in links],
           "delta_a": [float(lk["a"] - nominal.a[i]) for i, lk in enumerate(links)],
           "delta_d": [float(lk["d"] - nominal.d[i]) for i, lk in enumerate(links)],
           "delta_alpha": [float(lk["alpha"] - nominal.alpha[i]) for i, lk in enumerate(links)],
           "beta": [lk["beta"] for lk in links],
           "note": "T_base_link0 and T_flange_cam carry what the minimal parameter set "
                   "absorbs (link 1 offset and d, the last link's parameters)"}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def export_result(result: dict[str, Any], fmt: str, path: Path, run_id: str,
                  versions: dict | None = None) -> Path:
    """Write ``result`` in ``fmt``; ``versions`` (the run's ``versions.json``) carries the
    robot's own kinematics hash for ``ur-kinematics``."""
    from rigctl.exports_ur import export_ros_static, export_ur_kinematics, export_urdf

    if fmt == "json":
        keys = ("convention", "units", "links", "T_base_link0", "T_flange_cam",
                "T_base_target", "T_base_cam", "T_flange_target", "mounting", "uncertainty",
                "heldout")
        doc = {k: result[k] for k in keys if k in result} if "convention" in result else result
        path.write_text(json.dumps(doc, indent=2) + "\n")
    elif fmt == "opencv":
        export_opencv(result, path, run_id)
    elif fmt == "ros":
        export_ros(result, path, run_id)
    elif fmt == "ur":
        export_ur(result, path, run_id)
    elif fmt == "ur-kinematics":
        export_ur_kinematics(result, path, run_id, versions)
    elif fmt == "urdf":
        export_urdf(result, path, run_id, versions)
    elif fmt == "ros-static":
        export_ros_static(result, path, run_id)
    else:
        raise ConfigError(f"--format: unknown export format {fmt!r}; known: {', '.join(FORMATS)}")
    return path
