"""Drift of a new calibration against the last accepted one, with the rig file's
thresholds (focal %, principal point px, link mm/deg, hand-eye mm/deg), and a changed
robot: a calibration whose controller kinematics hash differs from the accepted one's.

Where both calibrations report a 1-sigma for a quantity, a change over its threshold is
drift only if it is also significant: ``|new - old| > SIGNIFICANT * sqrt(s_new^2 +
s_old^2)`` (the difference's own sigma, the two runs independent). A change within that
band is noise of the two measurements, and the metrics say so (``*_z``)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rigctl.config import DriftThresholds
from rigctl.geometry.transforms import rotation_angle

CALIBRATIONS = ("active-camera", "hand-eye", "robot-kinematics")
SIGNIFICANT = 3.0


def _z(new: dict, old: dict, keys, new_sigma: dict | None, old_sigma: dict | None
       ) -> float | None:
    """The largest |difference| / sigma of the difference over ``keys``; None when a
    sigma is missing."""
    if not new_sigma or not old_sigma:
        return None
    zs = []
    for key in keys:
        sn, so = new_sigma.get(key), old_sigma.get(key)
        if sn is None or so is None or sn + so <= 0:
            return None
        zs.append(abs(new[key] - old[key]) / math.hypot(sn, so))
    return max(zs)


def _significant(z: float | None) -> bool:
    return z is None or z > SIGNIFICANT
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
        z_f = _z(new, old, ("fx", "fy"), new.get("sigma"), old.get("sigma"))
        z_c = _z(new, old, ("cx", "cy"), new.get("sigma"), old.get("sigma"))
        if z_f is not None:
            metrics |= {"focal_z": z_f, "principal_point_z": z_c}
        if focal > limits.focal_pct and _significant(z_f):
            breaches.append(f"focal length changed {focal:.3f} % (limit {limits.focal_pct} %"
                            + (f", {z_f:.1f} sigma of the difference)" if z_f else ")"))
        if pp > limits.principal_point_px and _significant(z_c):
            breaches.append(f"principal point moved {pp:.2f} px "
                            f"(limit {limits.principal_point_px} px"
                            + (f", {z_c:.1f} sigma of the difference)" if z_c else ")"))
    if procedure in ("hand-eye", "robot-kinematics") and new.get("robot_hash") \
            and old.get("robot_hash") and new["robot_hash"] != old["robot_hash"]:
        breaches.append(f"robot recalibrated or replaced: the controller's kinematics hash "
                        f"is {new['robot_hash']}, the accepted calibration was made with "
                        f"{old['robot_hash']}")
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
        breaches += _link_drift(new, old, limits, metrics)
    return breaches, metrics


def _link_drift(new: dict, old: dict, limits: DriftThresholds, metrics: dict) -> list[str]:
    """Link lengths and angles over their thresholds; with both models' sigma
    (``uncertainty.parameters``), only the changes beyond 3 sigma of the difference
    count. One message per kind names the largest such change's link (1-based) and
    parameter, with its sigma of the difference when known, and how many more of that
    kind are over the limit. ``metrics`` gets the largest change of each kind (and of
    those, the significant ones' largest z)."""
    sig_new = new.get("uncertainty", {}).get("parameters") or {}
    sig_old = old.get("uncertainty", {}).get("parameters") or {}
    changes = {"length": [], "angle": []}
    for i, (n, o) in enumerate(zip(new["links"], old["links"], strict=True)):
        for k in LENGTH_KEYS + ANGLE_KEYS:
            name = f"link{i + 1}.{k}"
            z = (abs(n[k] - o[k]) / math.hypot(sig_new[name], sig_old[name])
                 if sig_new.get(name) and sig_old.get(name) else None)
            kind = "length" if k in LENGTH_KEYS else "angle"
            value = 1000 * abs(n[k] - o[k]) if kind == "length" else \
                math.degrees(abs(n[k] - o[k]))
            changes[kind].append((value, z, i + 1, k))
    mm, deg = (max(changes[k], key=lambda c: c[0]) for k in ("length", "angle"))
    metrics |= {"link_mm": mm[0], "link_deg": deg[0]}
    out = []
    for kind, limit, unit, fmt in (("length", limits.link_mm, "mm", ".3f"),
                                   ("angle", limits.link_deg, "deg", ".4f")):
        over = [c for c in changes[kind] if c[0] > limit and _significant(c[1])]
        if over:
            value, z, link, key = max(over, key=lambda c: c[0])
            metrics[f"link_{kind}_z"] = z
            others = (f"; {len(over) - 1} other link {kind}{'s' if len(over) > 2 else ''} "
                      "over the limit too" if len(over) > 1 else "")
            out.append(f"link {link} {key} changed {value:{fmt}} {unit} (limit {limit} {unit}"
                       + (f", {z:.1f} sigma of the difference" if z else "") + others + ")")
    return out
