"""What the console's pages show, assembled from the index and the run directories: pure
reads, no drawing and no HTML."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rigctl.errors import RigError
from rigctl.records import RunDirectory

LOG_TAIL_LINES = 60


@dataclass
class Row:
    """One line of a result table: a value with its 1-sigma, in display units."""

    name: str
    value: float | str
    sigma: float | None = None
    unit: str = ""


def _num(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) \
        and math.isfinite(value)


def _intrinsics_rows(r: dict[str, Any]) -> list[Row]:
    sigma = r.get("sigma") or {}
    rows = [Row(k, r[k], sigma.get(k), "px") for k in ("fx", "fy", "cx", "cy") if k in r]
    for name, value in zip(("k1", "k2", "p1", "p2", "k3"), r.get("distortion") or [],
                           strict=False):
        rows.append(Row(name, value))
    refined = (r.get("strategies") or {}).get("refined") or {}
    if _num(refined.get("rms_px")):
        rows.append(Row("reprojection rms", refined["rms_px"], None, "px"))
    return rows


def _hand_eye_rows(r: dict[str, Any]) -> list[Row]:
    T = r["T_flange_cam"]
    sigma = r.get("sigma") if isinstance(r.get("sigma"), list) else None
    params = (r.get("uncertainty") or {}).get("parameters") or {}
    rows = []
    for i, axis in enumerate("xyz"):
        s = sigma[3 + i] if sigma else params.get(f"X.{axis}")
        rows.append(Row(f"camera on flange {axis}", 1000 * T[i][3],
                        None if s is None else 1000 * s, "mm"))
    return rows


def _link_rows(r: dict[str, Any]) -> list[Row]:
    params = (r.get("uncertainty") or {}).get("parameters") or {}
    rows = []
    for i, link in enumerate(r.get("links") or []):
        for key, value in link.items():
            name = f"link{i + 1}.{key}"
            s = params.get(name)
            if key in ("d", "a"):
                rows.append(Row(name, 1000 * value, None if s is None else 1000 * s, "mm"))
            else:
                rows.append(Row(name, math.degrees(value),
                                None if s is None else math.degrees(s), "deg"))
    return rows


def result_rows(procedure: str, result: dict[str, Any]) -> list[Row]:
    """The calibrated quantities of a result with their 1-sigma where it reports one."""
    if procedure == "active-camera":
        return _intrinsics_rows(result)
    rows = []
    if "T_flange_cam" in result:
        rows += _hand_eye_rows(result)
    if procedure == "robot-kinematics":
        rows += _link_rows(result)
    return rows


def summary_rows(result: dict[str, Any]) -> list[Row]:
    """The result's ``summary`` (or its top-level numbers), flattened one level."""
    source = result.get("summary") if isinstance(result.get("summary"), dict) else result
    rows = []
    for key, value in source.items():
        if _num(value) or (isinstance(value, str) and len(value) < 80):
            rows.append(Row(key, value))
        elif isinstance(value, dict):
            rows += [Row(f"{key}.{k}", v) for k, v in value.items() if _num(v)]
    return rows


def capture_use(result: dict[str, Any]) -> dict[str, Any] | None:
    """The result's captures by use: ``used``, ``excluded`` by the operator and
    ``rejected`` by the solver (index, label, reason); None when it names none."""
    use = result.get("captures")
    if not isinstance(use, dict):
        return None
    rejected = use.get("rejected") or []
    if isinstance(rejected, dict):
        rejected = [{"index": k, "label": "", "reason": v} for k, v in rejected.items()]
    return {"used": list(use.get("used") or []), "excluded": list(use.get("excluded") or []),
            "rejected": [r for r in rejected if isinstance(r, dict)]}


def log_tail(run: RunDirectory, lines: int = LOG_TAIL_LINES) -> str:
    path = run.path / "run.log"
    if not path.is_file():
        return ""
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])


def captures(run: RunDirectory) -> list[dict[str, Any]]:
    """The run's complete captures (sidecar written) that have an image."""
    try:
        return [{"index": c.index, "label": c.meta.get("label", "")}
                for c in run.captures() if c.image_path is not None]
    except RigError:
        return []


def plots(run: RunDirectory) -> list[str]:
    return sorted(p.name for p in run.plots_dir.glob("*.png")) if run.plots_dir.is_dir() else []


def read_optional(run: RunDirectory, name: str) -> Any:
    """A JSON file of the run directory, or None when it is missing or unreadable (a run
    refused before it wrote one)."""
    if not (run.path / name).is_file():
        return None
    try:
        return run.read_json(name)
    except RigError:
        return None


def run_directory(row: dict[str, Any]) -> RunDirectory | None:
    return RunDirectory(row["run_dir"]) if row.get("run_dir") and \
        Path(row["run_dir"]).is_dir() else None
