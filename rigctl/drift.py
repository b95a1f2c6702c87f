"""Drift of a new calibration against the last accepted one, with the rig file's
thresholds (focal %, principal point px, link mm/deg, hand-eye mm/deg)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rigctl.config import DriftThresholds
from rigctl.geometry.transforms import rotation_angle

CALIBRATIONS = ("active-camera", "hand-eye", "robot-kinematics")
LENGTH_KEYS = ("d", "a")
ANGLE_KEYS = ("theta_offset", "alpha", "beta")


def _transform_delta(a, b) -> tuple[float, float]:
    A, B = np.asarray(a, float), np.asarray(b, float)
    return (1000 * float(np.linalg.norm(A[:3, 3] - B[:3, 3])),
            math.degrees(rotation_angle(A[:3, :3].T @ B[:3, :3])))


def compare(procedure: str, new: dict[str, Any], old: dict[str, Any],
            limits: DriftThresholds) -> tuple[list[str], dict[str, float]]:
    """(breaches as operator messages, the measured changes)."""
    breaches, metrics = [], {}
    if procedure == "active-camera":
        focal = 100 * max(abs(new["fx"] / old["fx"] - 1), abs(new["fy"] / old["fy"] - 1))
        pp = max(abs(new["cx"] - old["cx"]), abs(new["cy"] - old["cy"]))
        metrics = {"focal_pct": focal, "principal_point_px": pp}
        if focal > limits.focal_pct:
            breaches.append(f"focal length changed {focal:.3f} % (limit {limits.focal_pct} %)")
        if pp > limits.principal_point_px:
            breaches.append(f"principal point moved {pp:.2f} px "
                            f"(limit {limits.principal_point_px} px)")
    if procedure in ("hand-eye", "robot-kinematics") and "T_flange_cam" in new \
            and "T_flange_cam" in old:
        mm, deg = _transform_delta(new["T_flange_cam"], old["T_flange_cam"])
        metrics |= {"hand_eye_mm": mm, "hand_eye_deg": deg}
        if mm > limits.hand_eye_mm:
            breaches.append(f"hand-eye moved {mm:.2f} mm (limit {limits.hand_eye_mm} mm)")
        if deg > limits.hand_eye_deg:
            breaches.append(f"hand-eye turned {deg:.3f} deg (limit {limits.hand_eye_deg} deg)")
    if procedure == "robot-kinematics" and "links" in new and "links" in old \
            and len(new["links"]) != len(old["links"]):
        breaches.append(f"the arm model changed: {len(new['links'])} links, "
                        f"{len(old['links'])} before")
    elif procedure == "robot-kinematics" and "links" in new and "links" in old:
        mm = max(1000 * abs(n[k] - o[k]) for n, o in zip(new["links"], old["links"],
                                                         strict=True) for k in LENGTH_KEYS)
        deg = max(math.degrees(abs(n[k] - o[k])) for n, o in zip(new["links"], old["links"],
                                                                 strict=True)
                  for k in ANGLE_KEYS)
        metrics |= {"link_mm": mm, "link_deg": deg}
        if mm > limits.link_mm:
            breaches.append(f"a link length changed {mm:.3f} mm (limit {limits.link_mm} mm)")
        if deg > limits.link_deg:
            breaches.append(f"a link angle changed {deg:.4f} deg (limit {limits.link_deg} deg)")
    return breaches, metrics
