"""``rigctl demo`` (and ``make demo``): the main job on the simulated rig.

Starts the whole simulated rig (`rigctl sim up` on the shipped world ``default``: lens
distortion, 0.5 px noise, a 0.3 deg roll-axis tilt, mm-level arm errors), then runs
through the runner, recorded under ``demo-records/`` in the current folder:

1. ``active-camera``: intrinsics from head rotations (thesis ch. 3), printed against the
   world's truth;
2. ``hand-eye``: T_flange_cam with the arm model the controller reports (its factory
   calibration; nominal when it reports none);
3. ``robot-kinematics``: sweeps (link-by-link) and random views (joint refinement),
   held out against the nominal and the controller's factory model, and exported for the
   UR ROS 2 driver (kinematics YAML) and as a URDF;
4. ``validate-arm``: held-out views, camera pose error before and after;

and prints every estimate against the world's truth.

``--quick`` runs a short chain instead: active-camera on fewer rotations
(``QUICK_CAMERA``), then hand-eye on a few views (``QUICK_HAND_EYE``), each printed
against the truth. The simulated rig needs the ``arm`` extra (ur-rtde, the arm's client).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from rigctl.bench.truth import model_against_truth
from rigctl.config import load_rig
from rigctl.errors import RigError
from rigctl.exports import SUFFIXES, export_result
from rigctl.extras import require
from rigctl.mocks.world import load_world, world_file
from rigctl.records import RunDirectory
from rigctl.runner import Runner
from rigctl.simrig import SimulatedRig

console = Console(stderr=True)
# --quick: pans and tilts of 3, 12 and 25 deg and three rolls (17 captures instead of 33)
QUICK_CAMERA = {"wide_deg": [12.0, 25.0], "rolls_deg": [90.0, -180.0, -90.0]}
QUICK_HAND_EYE = {"poses": 8}


def camera_table(result: dict, truth: dict) -> Table:
    table = Table(title="active-camera: estimated vs true")
    for col in ("", "true", "refined (1 sigma)", "Strategy D", "Strategy B"):
        table.add_column(col, justify="right")
    strategies = result["strategies"]
    for key in ("fx", "fy", "cx", "cy"):
        d = strategies.get("D", {}).get(key)
        b = strategies.get("B", {}).get(key)
        table.add_row(key, f"{truth[key]:.2f}",
                      f"{result[key]:.2f} ({result['sigma'][key]:.2f})",
                      "-" if d is None else f"{d:.2f}", "-" if b is None else f"{b:.2f}")
    return table


def robot_table(result: dict, truth: dict) -> Table:
    """Identified link parameters against the truth (links 2-5: the ones the minimal set
    estimates directly; link 1's offset and d and link 6 live in T_base_target and
    T_flange_cam)."""
    table = Table(title="robot-kinematics: link parameters, estimated vs true")
    for col in ("link", "a mm", "alpha deg", "theta_off deg", "d mm / beta deg"):
        table.add_column(col, justify="right")
    for i, (est, tru) in enumerate(zip(result["links"], truth["arm"]["links"], strict=True)):
        if i in (0, 5):
            continue
        last = (f"beta {np.degrees(est['beta']):+.3f} / {np.degrees(tru['beta']):+.3f}"
                if abs(est["beta"]) > 0 or (abs(tru["beta"]) > 0 and i in (1, 2))
                else f"{1000 * est['d']:.2f} / {1000 * tru['d']:.2f}")
        table.add_row(str(i + 1), f"{1000 * est['a']:.2f} / {1000 * tru['a']:.2f}",
                      f"{np.degrees(est['alpha']):.3f} / {np.degrees(tru['alpha']):.3f}",
                      f"{np.degrees(est['theta_offset']):+.3f} / "
                      f"{np.degrees(tru['theta_offset']):+.3f}", last)
    return table


def hand_eye_line(result: dict, truth: dict) -> str:
    """T_flange_cam's translation and rotation against the truth."""
    X = np.array(result["T_flange_cam"])
    X_true = np.array(truth["T_flange_cam"])
    d = X_true[:3, :3].T @ X[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1.0, 1.0)))
    return (f"T_flange_cam translation (mm): estimated {np.round(1000 * X[:3, 3], 2).tolist()}, "
            f"true {np.round(1000 * X_true[:3, 3], 2).tolist()}, error "
            f"{1000 * np.linalg.norm(X[:3, 3] - X_true[:3, 3]):.2f} mm and {angle:.3f} deg "
            f"(with the {result.get('arm_model_used', 'nominal')} arm model)")


def main(quick: bool = False, records: str | Path = "demo-records",
         world: str = "default") -> int:
    """Run the demo on the simulated rig of ``world`` (a shipped world's name or a file),
    recording under ``records``; 0 when every run succeeded."""
    require("arm")  # the simulated arm is driven through ur-rtde, as a real one
    records = Path(records).resolve()
    world_path = world_file(world)
    truth = load_world(world_path).truth()
    status = 0
    with SimulatedRig(world_path, records=records) as sim:
        rig_path = sim.rig_path
        runner = Runner(load_rig(rig_path))
        console.rule("1. active-camera on the simulated rig " + (
            "(quick: pan/tilt 3, 12 and 25 deg, three rolls)" if quick else
            "(default plan: pan/tilt 3, 8 to 25 deg, rolls every 45 deg)"))
        outcome = runner.run("active-camera", QUICK_CAMERA if quick else {})
        console.print(f"run {outcome.run_id}: {outcome.status}"
                      + (f" ({outcome.reason})" if outcome.reason else ""))
        if outcome.result:
            console.print(camera_table(outcome.result, truth))
            f_err = max(abs(outcome.result[k] / truth[k] - 1) for k in ("fx", "fy")) * 100
            pp = max(abs(outcome.result[k] - truth[k]) for k in ("cx", "cy"))
            console.print(f"focal error {f_err:.3f} %, principal point error {pp:.2f} px")
        status |= outcome.status != "succeeded"
        chain = ((("hand-eye", QUICK_HAND_EYE),) if quick else
                 (("hand-eye", {}), ("robot-kinematics", {}), ("validate-arm", {})))
        for name, params in chain:
            console.rule(name)
            outcome = runner.run(name, params)
            console.print(f"run {outcome.run_id}: {outcome.status}"
                          + (f" ({outcome.reason})" if outcome.reason else ""))
            status |= outcome.status != "succeeded"
            if outcome.result is None:
                continue
            if name == "hand-eye":
                console.print(hand_eye_line(outcome.result, truth))
            elif name == "robot-kinematics":
                console.print(robot_table(outcome.result, truth))
                s = outcome.result["summary"]
                factory = (f", the controller's factory model {s['heldout_mm_factory']:.2f} mm"
                           if s.get("heldout_mm_factory") is not None else "")
                console.print(f"held-out camera position RMS: nominal {s['heldout_mm_before']:.2f}"
                              f" mm{factory}, calibrated {s['heldout_mm_after']:.3f} mm; "
                              "condition number "
                              f"{s['condition_number']:.0f} (link parameters alone, X and W "
                              f"projected out: {s['condition_number_kinematic']:.0f})")
                singles = ", ".join(f"{label} {s[key]:.2f} mm" for label, key in (
                    ("link-by-link (thesis 4.3, X from hand-eye)", "heldout_mm_link_by_link"),
                    ("axis-based (no X)", "heldout_mm_axis_based")) if s.get(key) is not None)
                spans = s.get("sweep_span_deg") or {}
                span = (f" (sweeps spanning {min(spans.values()):.0f}-"
                        f"{max(spans.values()):.0f} deg)" if spans else "")
                console.print(f"held-out, single methods before the joint refinement: "
                              f"{singles}{span}")
                check = outcome.result.get("intrinsics_check", {})
                if "board" in check:
                    b, sd, used = check["board"], check["sigma"], outcome.result["intrinsics"]
                    console.print(
                        f"intrinsics check, Zhang on the {check['views']} board views (k1 k2 p1 "
                        f"p2): cx, cy = {b['cx']:.2f} +- {sd['cx']:.2f}, {b['cy']:.2f} +- "
                        f"{sd['cy']:.2f} px; in use {used['cx']:.2f}, {used['cy']:.2f}; true "
                        f"{truth['cx']:.2f}, {truth['cy']:.2f}. {check['note']}")
                rms, worst, count = model_against_truth(outcome.result, load_rig(rig_path),
                                                        load_world(world_path))
                console.print(f"exported model against the world's forward kinematics, {count} "
                              f"configurations never seen: camera position RMS {rms:.3f} mm, "
                              f"max {worst:.3f} mm")
                if s.get("moved_from_controller_mm") is not None:
                    moved = s["moved_from_controller_mm"]
                    console.print(f"the calibration moved the camera {moved:.2f} mm RMS from "
                                  "where the controller's own model puts it")
                run_dir = RunDirectory(outcome.run_dir)
                for fmt in ("ur-kinematics", "urdf"):
                    try:
                        path = export_result(outcome.result, fmt, run_dir.path /
                                             f"export{SUFFIXES[fmt]}", run_dir.run_id,
                                             run_dir.versions())
                        console.print(f"exported {fmt}: {path}")
                    except RigError as exc:
                        console.print(f"[red]export {fmt} failed: {exc}[/red]")
                        status = 1
            else:
                r = outcome.result
                b, a = r["before"], r["after"]
                console.print(f"validate-arm ({r['views']} new views), before -> after: camera "
                              f"in the target frame {b['position_rms_mm']:.2f} -> "
                              f"{a['position_rms_mm']:.3f} mm / {b['rotation_rms_deg']:.3f} -> "
                              f"{a['rotation_rms_deg']:.4f} deg (PnP's floor here is ~0.5 mm); "
                              f"target in the camera frame {b['target_in_camera_rms_mm']:.2f} -> "
                              f"{a['target_in_camera_rms_mm']:.3f} mm; predicted board "
                              f"{b['reprojection_rms_px']:.2f} -> "
                              f"{a['reprojection_rms_px']:.2f} px")
    console.print(f"records in {records}")
    return status


if __name__ == "__main__":
    try:
        sys.exit(main())
    except RigError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        sys.exit(2)
