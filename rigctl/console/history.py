"""The calibration history as series of (time, value, 1-sigma, decision) per quantity, and
the drift band each quantity has around the last accepted value (the rig file's
``service.drift`` thresholds, as ``rigctl.drift.compare`` applies them)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rigctl.config import DriftThresholds

Extract = Callable[[dict[str, Any]], tuple[float | None, float | None]]
Band = Callable[[DriftThresholds, float], float]


@dataclass(frozen=True)
class Quantity:
    key: str
    label: str
    unit: str
    extract: Extract
    band: Band | None = None  # half-width of the drift band around the accepted value


def _intrinsic(key: str) -> Extract:
    return lambda r: (r.get(key), (r.get("sigma") or {}).get(key))


def _hand_eye_t(axis: int) -> Extract:
    """T_flange_cam's translation (mm); sigma from hand-eye's ``sigma`` (rotvec X, t X,
    ...) or robot-kinematics' ``uncertainty.parameters`` (X.x, X.y, X.z)."""
    def extract(r: dict[str, Any]) -> tuple[float | None, float | None]:
        T = r.get("T_flange_cam")
        if T is None:
            return None, None
        sigma = r.get("sigma")
        if isinstance(sigma, list) and len(sigma) >= 6:
            s = sigma[3 + axis]
        else:
            s = ((r.get("uncertainty") or {}).get("parameters") or {}).get("X." + "xyz"[axis])
        return 1000 * T[axis][3], None if s is None else 1000 * s
    return extract


def _summary(key: str) -> Extract:
    return lambda r: ((r.get("summary") or {}).get(key), None)


FOCAL = lambda lim, value: abs(value) * lim.focal_pct / 100  # noqa: E731
CENTRE = lambda lim, value: lim.principal_point_px  # noqa: E731
HAND_EYE = lambda lim, value: lim.hand_eye_mm  # noqa: E731

HAND_EYE_T = [Quantity(f"t{a}", f"camera on the flange, {a}", "mm", _hand_eye_t(i), HAND_EYE)
              for i, a in enumerate("xyz")]

QUANTITIES: dict[str, list[Quantity]] = {
    "active-camera": [Quantity("fx", "focal length fx", "px", _intrinsic("fx"), FOCAL),
                      Quantity("fy", "focal length fy", "px", _intrinsic("fy"), FOCAL),
                      Quantity("cx", "principal point cx", "px", _intrinsic("cx"), CENTRE),
                      Quantity("cy", "principal point cy", "px", _intrinsic("cy"), CENTRE)],
    "hand-eye": HAND_EYE_T,
    "robot-kinematics": [*HAND_EYE_T,
                         Quantity("heldout", "held-out camera error after", "mm",
                                  _summary("heldout_mm_after"))],
}


@dataclass
class Series:
    quantity: Quantity
    times: list[dt.datetime] = field(default_factory=list)
    values: list[float] = field(default_factory=list)
    sigmas: list[float | None] = field(default_factory=list)
    decisions: list[str] = field(default_factory=list)
    run_ids: list[str] = field(default_factory=list)
    accepted: float | None = None  # the newest accepted value
    band: float | None = None


def series(procedure: str, rows: list[dict[str, Any]],
           results: dict[str, dict[str, Any]], limits: DriftThresholds) -> list[Series]:
    """One ``Series`` per quantity of ``procedure`` from its index rows (any order) and
    their results by run id; a row whose result lacks a quantity is left out of it."""
    out = []
    ordered = sorted(rows, key=lambda r: r["started_at"])
    for q in QUANTITIES.get(procedure, []):
        s = Series(q)
        for row in ordered:
            result = results.get(row["run_id"])
            value, sigma = q.extract(result) if result else (None, None)
            if value is None:
                continue
            s.times.append(row["started_at"])
            s.values.append(float(value))
            s.sigmas.append(None if sigma is None else float(sigma))
            s.decisions.append(row.get("decision") or "pending")
            s.run_ids.append(row["run_id"])
            if row.get("decision") == "accepted":
                s.accepted = float(value)
        if s.accepted is not None and q.band is not None:
            s.band = q.band(limits, s.accepted)
        out.append(s)
    return out
