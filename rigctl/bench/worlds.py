"""``rigctl bench worlds``: the whole calibration chain through the stand-ins, on random
worlds, against each world's truth.

For each seed, ``rigctl.mocks.random_world`` draws a rig; `sim up` serves it (head bus over a
pty, UR controller over TCP, camera over HTTP); the runner drives the real clients
through ``active-camera``, ``hand-eye``, ``robot-kinematics`` and ``validate-arm`` with
their default parameters, exactly as an operator would. Reports per world and as a
distribution:

- focal error (%) and centre error (px) of ``active-camera``, and error / sigma of each
  intrinsic;
- error / sigma of each identified link parameter of ``robot-kinematics``;
- the exported arm model against the world's forward kinematics over configurations the
  run never saw (``rigctl.bench.truth.model_against_truth``), the held-out error and
  ``validate-arm``'s;
- motion, solve and run time of every procedure.

A world counts as failed when any procedure is refused or does not succeed.

Each seed's target and mounting (``COMBINATIONS``, by seed mod 4 unless one is asked
for): a checkerboard or a ChArUco board, the head on the flange or beside the arm (the
board then on the flange). The summary reports every
combination apart (``by_combination``), with the image coverage of robot-kinematics'
board corners (``truth.image_coverage``) and the final camera's focal and centre error.
"""

from __future__ import annotations

import json
import math
import re
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml
from rich.console import Console

from rigctl.bench.truth import (
    image_coverage,
    intrinsics_errors,
    link_z,
    model_against_truth,
    position_z,
)
from rigctl.config import load_rig, parse_rig
from rigctl.errors import AbortedError, ConfigError, RigError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.mocks.random_world import random_world
from rigctl.mocks.world import World, WorldFile
from rigctl.runner import Runner
from rigctl.simrig import SimulatedRig

PIPELINE = ("active-camera", "hand-eye", "robot-kinematics", "validate-arm")
# (target, mount) of each seed, by seed mod 4
COMBINATIONS = (("checkerboard", "flange"), ("charuco", "flange"), ("checkerboard", "fixed"),
                ("charuco", "fixed"))


def chain_until(last: str | None = None) -> tuple[str, ...]:
    """The procedures run on each world: ``PIPELINE`` up to and including ``last``
    (None: all of it). ``--until active-camera`` runs that procedure alone, the
    quickest way to the distribution of its solve over its motion (issue 43)."""
    if last is None:
        return PIPELINE
    if last not in PIPELINE:
        raise ConfigError(f"--until {last!r}: expected one of {', '.join(PIPELINE)}")
    return PIPELINE[:PIPELINE.index(last) + 1]


def combination(seed: int, only: str | None = None) -> tuple[str, str]:
    """World ``seed``'s (target, mount): ``COMBINATIONS[seed % 4]``, or ``only``
    ("checkerboard-flange", ...) for every seed."""
    if only is None or only == "each":
        return COMBINATIONS[seed % len(COMBINATIONS)]
    target, _, mount = only.partition("-")
    if (target, mount) not in COMBINATIONS:
        raise ConfigError(f"--combination {only!r}: expected each or one of "
                          + ", ".join(f"{t}-{m}" for t, m in COMBINATIONS))
    return target, mount


def _write_world(seed: int, folder: Path, only: str | None = None) -> tuple[Path, World]:
    target, mount = combination(seed, only)
    spec = random_world(seed, target=target, mount=mount)
    path = folder / f"world-{seed}.yaml"
    path.write_text(f"# rigctl sim world --random {seed}\n"
                    + yaml.safe_dump(spec, sort_keys=False, default_flow_style=None))
    return path, World(WorldFile.model_validate(spec))


def _metrics(name: str, result: dict, truth: dict, config, world: World) -> dict:
    if name == "active-camera":
        return {**intrinsics_errors(result, truth), "rms_px": result["summary"]["rms_px"]}
    if name == "hand-eye":
        key = "T_base_cam" if "T_base_cam" in result else "T_flange_cam"
        X, X_true = np.array(result[key]), np.array(truth[key])
        # with the arm model hand-eye used: the controller's own, or nominal without one
        return {"t_mm": 1000 * float(np.linalg.norm(X[:3, 3] - X_true[:3, 3])),
                "arm_model_used": result.get("arm_model_used", "nominal")}
    if name == "robot-kinematics":
        rms, worst, count = model_against_truth(result, config, world)
        s = result["summary"]
        # the same check for the models the calibration started from: nominal and the
        # controller's own (each with the hand-eye solved for it)
        nominal = {"links": nominal_ur(config.devices.arm.model).links(), **{
            k: v for k, v in result["before"].items() if k.startswith("T_")}}
        factory = result.get("factory")
        return {"model_rms_mm": rms, "model_max_mm": worst, "model_configs": count,
                "heldout_mm_before": s["heldout_mm_before"],
                "heldout_mm_after": s["heldout_mm_after"],
                # the controller's own (factory) model with its hand-eye, when it has one
                "heldout_mm_factory": s.get("heldout_mm_factory"),
                "nominal_model_rms_mm": model_against_truth(nominal, config, world)[0],
                "factory_model_rms_mm": model_against_truth(factory, config, world)[0]
                if factory else None,
                "training_views": s["training_views"], "z": link_z(result, truth),
                "intrinsics_agree": result.get("intrinsics_check", {}).get("agrees"),
                # the camera model the arm model was fitted with (free in the final bundle
                # adjustment unless refine_camera=false)
                "camera": intrinsics_errors(result["intrinsics"], truth),
                "position_z": position_z(result, config, world),
                "position_sigma_mm": result["uncertainty"].get("camera_position_sigma_mm")}
    return {"position_rms_mm_before": result["before"]["position_rms_mm"],
            "position_rms_mm_after": result["after"]["position_rms_mm"]}


def _row(seed: int, spec) -> dict:
    """A world's row before any procedure ran."""
    return {"seed": seed, "model": spec.arm.model, "fx_true": spec.camera.fx,
            "target": spec.target.type, "mount": spec.head.mount,
            "size": [spec.camera.width, spec.camera.height],
            "distortion": list(spec.camera.distortion), "procedures": {}}


def _failed(row: dict, chain: tuple[str, ...] = PIPELINE) -> bool:
    """Any procedure not succeeded, or the chain stopped before its end."""
    return any(p["status"] != "succeeded" for p in row["procedures"].values()) \
        or len(row["procedures"]) < len(chain)


def _values(rows: list[dict], proc: str, key: str) -> list[float]:
    """``key`` of procedure ``proc`` over the worlds that have it (a run without held-out
    views has None there, and is left out: it is no number)."""
    return [r["procedures"][proc][key] for r in rows
            if r["procedures"].get(proc, {}).get(key) is not None]


LAST_LINE = re.compile(r"run (?P<run>\S+) (?P<status>succeeded|failed|aborted)(: (?P<reason>.*?))?"
                       r"( \((?P<timings>[^()]*)\))?$")


def _from_run_dir(name: str, run_dir: Path, truth: dict, world: World) -> dict:
    """One procedure's entry of a row, read back from its run directory (the run log's
    last line has the status, reason and times; the result its numbers)."""
    lines = (run_dir / "run.log").read_text().strip().splitlines() if \
        (run_dir / "run.log").exists() else []
    match = LAST_LINE.search(lines[-1].split("rigctl.run: ", 1)[-1]) if lines else None
    entry = {"status": match["status"] if match else "unfinished",
             "reason": match["reason"] if match else None, "timings_s": {}}
    if match and match["timings"]:
        for part in match["timings"].split(", "):
            key, value, _unit = part.split(" ")
            entry["timings_s"][f"{key}_s"] = float(value)
    if (run_dir / "result.json").exists():
        config = parse_rig((run_dir / "rig.yaml").read_text(), name=str(run_dir / "rig.yaml"))
        result = json.loads((run_dir / "result.json").read_text())
        entry.update(_metrics(name, result, truth, config, world))
        if name == "robot-kinematics":
            entry["image_coverage"] = _run_coverage(run_dir, truth)
    return entry


def _run_coverage(run_dir: Path, truth: dict) -> float:
    """The image coverage of a run's board corners (``truth.image_coverage``)."""
    corners = [json.loads(p.read_text()).get("corners") or []
               for p in sorted(run_dir.glob("captures/*.board.json"))]
    return image_coverage(corners, truth["width"], truth["height"])


def rows_from_kept(folder: Path, chain: tuple[str, ...] = PIPELINE) -> list[dict]:
    """The benchmark's rows rebuilt from a ``--keep`` folder (world files and records),
    also of a benchmark that was stopped part-way (a world whose last run had not
    finished is left out); ``chain``: the procedures that benchmark ran."""
    rows = []
    for path in sorted(folder.glob("world-*.yaml"), key=lambda p: int(p.stem.split("-")[1])):
        seed = int(path.stem.split("-")[1])
        spec = WorldFile.model_validate(yaml.safe_load(path.read_text()))
        world = World(spec)
        truth = world.truth()
        row = _row(seed, spec)
        for name in chain:
            runs = sorted((folder / f"records-{seed}").glob(f"*-{name}-*"))
            if not runs:
                break
            row["procedures"][name] = _from_run_dir(name, runs[-1], truth, world)
        if any(p["status"] == "unfinished" for p in row["procedures"].values()):
            continue
        row["failed"] = _failed(row, chain)
        rows.append(row)
    return rows


def world_run(seed: int, folder: Path, say: Callable[[str], None],
              only: str | None = None, chain: tuple[str, ...] = PIPELINE) -> dict:
    """The chain (``chain_until``) on world ``seed`` (its ``combination``); one row of
    the benchmark."""
    path, world = _write_world(seed, folder, only)
    spec, truth = world.spec, world.truth()
    row = _row(seed, spec)
    with SimulatedRig(path, records=folder / f"records-{seed}",
                      log=folder / f"sim-up-{seed}.log") as sim:
        config = load_rig(sim.rig_path)
        runner = Runner(config, show_progress=False, operator="bench-worlds")
        for name in chain:
            try:
                outcome = runner.run(name, {})
            except RigError as exc:  # refused before anything moved
                row["procedures"][name] = {"status": "refused",
                                           "reason": f"{type(exc).__name__}: {exc}"}
                say(f"world {seed} ({spec.arm.model}): {name} refused: {exc}")
                break
            except Exception as exc:  # a bug: the world fails, the benchmark goes on
                row["procedures"][name] = {"status": "crashed",
                                           "reason": f"{type(exc).__name__}: {exc}"}
                say(f"world {seed} ({spec.arm.model}): {name} crashed: "
                    f"{type(exc).__name__}: {exc}")
                break
            entry = {"status": outcome.status, "reason": outcome.reason,
                     "timings_s": outcome.timings_s}
            if outcome.result is not None:
                entry.update(_metrics(name, outcome.result, truth, config, world))
                runs = sorted((folder / f"records-{seed}").glob(f"*-{name}-*"))
                if name == "robot-kinematics" and runs:
                    entry["image_coverage"] = _run_coverage(runs[-1], truth)
            row["procedures"][name] = entry
            say(f"world {seed} ({spec.arm.model}): {name} {outcome.status} in "
                f"{outcome.timings_s.get('run_s', 0):.0f} s"
                + (f": {outcome.reason}" if outcome.reason else ""))
            if outcome.operator_stop:  # the operator stopped the benchmark, not one world
                raise AbortedError(f"world {seed}: {outcome.reason}")
            if outcome.status != "succeeded":
                break
    if sim.crash:  # a stand-in died: the world's failure is the simulation's, not the rig's
        row["simulation_crashed"] = sim.crash
        say(f"world {seed}: {sim.crash.splitlines()[0]}")
    row["failed"] = _failed(row, chain)
    return row


def _dist(values: list[float]) -> dict | None:
    if not values:
        return None
    arr = np.asarray(values, float)
    return {"median": float(np.median(arr)), "p90": float(np.percentile(arr, 90)),
            "max": float(arr.max()), "n": len(arr)}


def _coverage(z: list[float]) -> dict | None:
    if not z:
        return None
    a = np.abs(np.asarray(z, float))
    return {"within_1sigma": float(np.mean(a <= 1)), "within_3sigma": float(np.mean(a <= 3)),
            "max_abs_z": float(a.max()), "n": len(a)}


def by_combination(rows: list[dict]) -> dict[str, dict]:
    """Per target x mounting: worlds, failed runs, the exported model's RMS against the
    truth (median, worst), the share of reported parameters within 3 sigma, the image
    coverage of robot-kinematics' corners and the final camera's focal and centre
    error."""
    out = {}
    for target, mount in COMBINATIONS:
        mine = [r for r in rows if (r.get("target", "checkerboard"), r.get("mount", "flange"))
                == (target, mount)]
        if not mine:
            continue
        arm = [r["procedures"].get("robot-kinematics", {}) for r in mine]
        cams = [a["camera"] for a in arm if "camera" in a]
        z = [v for r in mine for p in ("active-camera", "robot-kinematics")
             for v in r["procedures"].get(p, {}).get("z", {}).values()] + \
            [v for c in cams for v in c["z"].values()]
        out[f"{target}-{mount}"] = {
            "worlds": len(mine), "failed": sum(r["failed"] for r in mine),
            "failed_seeds": [r["seed"] for r in mine if r["failed"]],
            "model_rms_mm": _dist(_values(mine, "robot-kinematics", "model_rms_mm")),
            "within_3sigma": (_coverage(z) or {}).get("within_3sigma"),
            "image_coverage": _dist(_values(mine, "robot-kinematics", "image_coverage")),
            "final_camera": {"focal_pct": _dist([c["focal_pct"] for c in cams]),
                             "centre_px": _dist([c["centre_px"] for c in cams])},
            "hand_eye_t_mm": _dist(_values(mine, "hand-eye", "t_mm"))}
    return out


def by_arm_model(rows: list[dict]) -> dict[str, dict]:
    """Per UR model (issue 40's targets stand for each): worlds, failed runs and the
    exported model's RMS against the truth (median, worst)."""
    out = {}
    for model in sorted({r.get("model", "?") for r in rows}):
        mine = [r for r in rows if r.get("model", "?") == model]
        out[model] = {"worlds": len(mine), "failed": sum(r["failed"] for r in mine),
                      "failed_seeds": [r["seed"] for r in mine if r["failed"]],
                      "model_rms_mm": _dist(_values(mine, "robot-kinematics",
                                                    "model_rms_mm"))}
    return out


def solve_over_motion(rows: list[dict], name: str) -> dict | None:
    """Each world's ``name`` solve time over its motion time in the run (issue 43: the
    active-camera solve should take at most 0.1 of the motion)."""
    ratios = [t["solve_s"] / t["motion_s"] for r in rows
              if (t := r["procedures"].get(name, {}).get("timings_s", {}))
              and t.get("motion_s") and "solve_s" in t]
    return _dist(ratios)


def summarise(rows: list[dict], chain: tuple[str, ...] = PIPELINE) -> dict:
    z_cam = [v for r in rows for v in r["procedures"].get("active-camera", {})
             .get("z", {}).values()]
    z_arm = [v for r in rows for v in r["procedures"].get("robot-kinematics", {})
             .get("z", {}).values()]
    cams = [r["procedures"]["robot-kinematics"]["camera"] for r in rows
            if "camera" in r["procedures"].get("robot-kinematics", {})]
    z_final = [v for c in cams for v in c["z"].values()]
    z_position = [v for r in rows for v in r["procedures"].get("robot-kinematics", {})
                  .get("position_z", [])]
    times = {name: {kind: _dist([r["procedures"][name]["timings_s"][kind] for r in rows
                                 if kind in r["procedures"].get(name, {}).get("timings_s", {})])
                    for kind in ("motion_s", "solve_s", "run_s")} for name in chain}
    return {
        "worlds": len(rows), "failed": sum(r["failed"] for r in rows),
        "failed_seeds": [r["seed"] for r in rows if r["failed"]],
        "focal_pct": _dist(_values(rows, "active-camera", "focal_pct")),
        "centre_px": _dist(_values(rows, "active-camera", "centre_px")),
        "final_camera": {"focal_pct": _dist([c["focal_pct"] for c in cams]),
                         "centre_px": _dist([c["centre_px"] for c in cams])},
        "model_rms_mm": _dist(_values(rows, "robot-kinematics", "model_rms_mm")),
        "model_max_mm": _dist(_values(rows, "robot-kinematics", "model_max_mm")),
        # the same check for the models the calibration started from
        "nominal_model_rms_mm": _dist(_values(rows, "robot-kinematics", "nominal_model_rms_mm")),
        "factory_model_rms_mm": _dist(_values(rows, "robot-kinematics", "factory_model_rms_mm")),
        "hand_eye_t_mm": _dist(_values(rows, "hand-eye", "t_mm")),
        "heldout_mm_after": _dist(_values(rows, "robot-kinematics", "heldout_mm_after")),
        "validate_mm_after": _dist(_values(rows, "validate-arm", "position_rms_mm_after")),
        "coverage": {"intrinsics": _coverage(z_cam), "links": _coverage(z_arm),
                     "final_camera": _coverage(z_final),
                     "camera_position": _coverage(z_position),
                     "all": _coverage(z_cam + z_arm + z_final)},
        "times_s": times,
        "by_combination": by_combination(rows),
        "by_arm_model": by_arm_model(rows),
        "solve_over_motion": {name: solve_over_motion(rows, name) for name in chain},
    }


def plot(rows: list[dict], path: Path, chain: tuple[str, ...] = PIPELINE) -> str:
    """Distributions over the worlds: focal and centre error, the exported model's error,
    |error / sigma| and solve times."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5), layout="constrained")
    panels = [("active-camera", "focal_pct", "focal error (%)", 0.05, 0.15),
              ("active-camera", "centre_px", "centre error (px)", 0.5, 1.5),
              ("robot-kinematics", "model_rms_mm", "exported model vs truth, RMS (mm)", 0.12,
               0.25)]
    for ax, (proc, key, label, median, worst) in zip(axes[0], panels, strict=True):
        data = _values(rows, proc, key)
        ax.plot(sorted(data), np.arange(1, len(data) + 1) / max(len(data), 1), "o-")
        ax.axvline(median, color="tab:red", ls="--", label=f"median target {median}")
        ax.axvline(worst, color="tab:red", ls=":", label=f"worst target {worst}")
        ax.set_xlabel(label)
        ax.set_ylabel("share of worlds")
        ax.legend(loc="lower right")
    ax = axes[1][0]
    for proc, label in (("active-camera", "intrinsics"), ("robot-kinematics", "link params")):
        z = np.abs([v for r in rows for v in r["procedures"].get(proc, {})
                    .get("z", {}).values()])
        if len(z):
            ax.plot(np.sort(z), np.arange(1, len(z) + 1) / len(z), label=label)
    ax.axvline(3, color="tab:red", ls="--", label="3 sigma")
    ax.set_xscale("log")
    ax.set_xlabel("|error / sigma|")
    ax.set_ylabel("share of parameters")
    ax.legend(loc="lower right")
    ax = axes[1][1]
    solve = [[r["procedures"][p]["timings_s"].get("solve_s", math.nan) for r in rows
              if "timings_s" in r["procedures"].get(p, {})] for p in chain]
    ax.boxplot([[v for v in s if not math.isnan(v)] or [0.0] for s in solve])
    ax.set_xticks(range(1, len(chain) + 1), [p.replace("-", "\n") for p in chain])
    ax.set_ylabel("solve time (s)")
    ax = axes[1][2]
    seeds = [r["seed"] for r in rows]
    heldout = [r["procedures"].get("robot-kinematics", {}).get("heldout_mm_after")
               for r in rows]
    ax.bar(range(len(rows)), [math.nan if v is None else v for v in heldout])
    ax.set_xticks(range(len(rows)), [str(s) for s in seeds], rotation=90, fontsize=7)
    ax.set_xlabel("world seed")
    ax.set_ylabel("held-out camera position RMS (mm)")
    fig.suptitle(f"rigctl bench worlds: {len(rows)} random worlds through the stand-ins")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return str(path)


def report(rows: list[dict], plot_path: Path | None,
           chain: tuple[str, ...] = PIPELINE) -> dict:
    out = {"seeds": sorted(r["seed"] for r in rows), "pipeline": list(chain),
           "summary": summarise(rows, chain), "worlds": rows}
    if plot_path is not None and rows:
        out["plot"] = plot(rows, plot_path, chain)
    return out


def run(n: int = 20, first_seed: int = 1000, plot_path: Path | None = None,
        keep: Path | None = None, console: Console | None = None,
        only: str | None = None, chain: tuple[str, ...] = PIPELINE) -> dict:
    """N random worlds from ``first_seed`` (the tests use seeds below 100), each of its
    ``combination`` (``only``: one for all), through the procedures of ``chain``
    (``chain_until``). With ``keep``, the world files and every run's records stay in
    that folder (``rows_from_kept`` reads them back)."""
    console = console or Console(stderr=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-worlds-") as tmp:
        folder = Path(keep) if keep else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        try:
            for seed in range(first_seed, first_seed + n):
                rows.append(world_run(seed, folder, console.print, only, chain))
        except AbortedError as exc:  # the world in progress is left out of the report
            console.print(f"bench stopped ({exc}); the report covers the {len(rows)} "
                          "world(s) finished before it")
            return {**report(rows, plot_path, chain), "stopped": str(exc)}
    return report(rows, plot_path, chain)
