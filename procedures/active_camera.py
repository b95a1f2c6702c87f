"""``active-camera``: intrinsics from known head rotations (thesis chapter 3), automated.

Sequence: home; reference capture; pan +-theta_p, tilt +-theta_t; rolls (90, 180, -90
deg); each captured after settling, with the encoder angles actually reached.

Solve: extract contours in the reference image; track them through pan+ and tilt+ with
the thesis's shift search; estimate K by Strategy B; track every motion again by
prediction from that K (rolls with the centre refined from the 90-degree roll); then
Strategies A-D and the nonlinear refinement (started from D). Writes ``result.json``,
plots, and OpenCV / ROS exports.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import Field

from rigctl.calib import active
from rigctl.calib.active import ContourStats
from rigctl.calib.active_refine import Motion, refine
from rigctl.errors import SolveError
from rigctl.vision.contours import edge_map, extract_contours
from rigctl.vision.tracking import track_by_prediction, track_by_shift

from .base import CaptureStep, MoveArmJoints, MoveHead, Params, Procedure, Settle, SolveContext


class ActiveCameraParams(Params):
    pan_deg: float = Field(3.0, ge=0.5, le=10.0)
    tilt_deg: float = Field(3.0, ge=0.5, le=10.0)
    # -180 rather than +180: position-mode servos span 0..4095 pulses, so +180 deg from the
    # centre (4096) is one pulse out of range; the image rotation is the same.
    rolls_deg: list[float] = Field(default_factory=lambda: [90.0, -180.0, -90.0])
    settle_s: float = Field(0.3, ge=0)
    window: float = Field(0.8, gt=0.1, le=0.95, description="central window for contours")
    min_points: int = Field(40, ge=10)
    # k1, k2 by default: from rotations alone the tangential terms are nearly degenerate
    # with the principal point (on the default world, 4 terms moved cx by -1.5 px).
    distortion_terms: Literal[0, 1, 2, 4] = Field(
        2, description="0; 1: k1; 2: k1, k2; 4: k1, k2, p1, p2 (tangential)")
    assumed_centre: list[float] | None = Field(None, description="default: image centre")


MOTIONS = ("pan+", "pan-", "tilt+", "tilt-")


class ActiveCamera(Procedure):
    name = "active-camera"
    summary = "Camera intrinsics from known pan/tilt/roll head rotations (thesis ch. 3)."
    params_model = ActiveCameraParams
    devices = ("head", "camera")
    optional_devices = ("arm",)

    def plan(self, params: ActiveCameraParams, config) -> list:
        steps: list = []
        if config.devices.arm is not None:
            home = tuple(math.radians(v) for v in config.devices.arm.home_deg)
            steps.append(MoveArmJoints(home, "arm home"))
        p, t = math.radians(params.pan_deg), math.radians(params.tilt_deg)
        poses = [("ref", 0.0, 0.0, 0.0), ("pan+", p, 0.0, 0.0), ("pan-", -p, 0.0, 0.0),
                 ("tilt+", 0.0, t, 0.0), ("tilt-", 0.0, -t, 0.0)]
        poses += [(f"roll{r:+g}", 0.0, 0.0, math.radians(r)) for r in params.rolls_deg]
        for label, pan, tilt, roll in poses:
            steps += [MoveHead(pan, tilt, roll, label), Settle(params.settle_s),
                      CaptureStep(label)]
        steps.append(MoveHead(0.0, 0.0, 0.0, "home"))
        return steps

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        params: ActiveCameraParams = ctx.params
        caps = {c.meta["label"]: c for c in ctx.captures() if c.image_path is not None}
        if "ref" not in caps:
            raise SolveError("active-camera: no reference capture recorded")
        missing = [m for m in ("pan+", "tilt+") if m not in caps]
        if missing:
            raise SolveError(f"active-camera: captures missing: {missing}")
        images = {k: c.load_image() for k, c in caps.items()}
        angles = {k: tuple(c.meta["head"][a] for a in ("pan", "tilt", "roll"))
                  for k, c in caps.items()}
        h, w = images["ref"].shape[:2]
        centre = np.array(params.assumed_centre or [(w - 1) / 2, (h - 1) / 2], float)
        emaps = {k: edge_map(img) for k, img in images.items()}
        contours = extract_contours(images["ref"], params.window, params.min_points,
                                    emap=emaps["ref"])
        if len(contours) < 3:
            raise SolveError(f"active-camera: too few contours in the reference image "
                             f"({len(contours)}; need 3)")
        rel = {k: tuple(np.subtract(v, angles["ref"])) for k, v in angles.items()}
        tracking: dict[str, Any] = {"contours": len(contours), "motions": {}}

        # 1. thesis tracking (shift search) through pan+ and tilt+, Strategy B for a first K
        thesis: dict[str, list] = {}
        for label, direction, theta in (("pan+", "x", rel["pan+"][0]),
                                        ("tilt+", "y", rel["tilt+"][1])):
            max_shift = abs(theta) * 2.0 * w + 10
            thesis[label] = [track_by_shift(c, emaps[label], direction, max_shift)
                             for c in contours]
        both = [i for i in range(len(contours))
                if thesis["pan+"][i].ok and thesis["tilt+"][i].ok]
        if len(both) < 2:
            raise SolveError("active-camera: contours lost in the pan/tilt images "
                             f"({len(both)} tracked through both)")
        stats0 = [ContourStats.of(contours[i].points, centre) for i in both]
        first = active.strategy_b(stats0, [ContourStats.of(thesis["tilt+"][i].points, centre)
                                           for i in both],
                                  [ContourStats.of(thesis["pan+"][i].points, centre)
                                   for i in both], rel["tilt+"][1], rel["pan+"][0])
        tracking["thesis_shift_tracked"] = len(both)
        K0 = {"fx": first["fx"], "fy": first["fy"], "cx": centre[0], "cy": centre[1]}

        # 2. predictive tracking of pan/tilt from K0; a refinement on those motions alone
        #    gives K1; the rolls are then predicted from K1 (rotation about its centre).
        matches: dict[str, list] = {}
        order = [m for m in (*MOTIONS, *(f"roll{r:+g}" for r in params.rolls_deg))
                 if m in caps]
        roll_labels = [m for m in order if m.startswith("roll")]

        def track(label: str, K: dict, window: float) -> list[int]:
            predictor = _predictor(K, rel[label])
            matches[label] = [track_by_prediction(c, emaps[label], predictor, window=window)
                              for c in contours]
            ok = [i for i, m in enumerate(matches[label]) if m.ok]
            rejected: dict[str, int] = {}
            for m in matches[label]:
                if not m.ok:
                    key = m.reason.split(" (")[0]
                    rejected[key] = rejected.get(key, 0) + 1
            tracking["motions"][label] = {"tracked": len(ok), "rejected": rejected,
                                          "angles_deg": np.degrees(rel[label]).tolist()}
            return ok

        def motion(label: str) -> Motion | None:
            idx = [i for i, m in enumerate(matches[label]) if m.ok]
            if not idx:
                return None
            return Motion(angles["ref"], angles[label],
                          np.concatenate([contours[i].points for i in idx]),
                          np.concatenate([matches[label][i].points for i in idx]),
                          np.concatenate([matches[label][i].normals for i in idx]),
                          label=label)

        for label in (m for m in order if not m.startswith("roll")):
            track(label, K0, 12.0)
        pan_tilt = [m for m in (motion(lb) for lb in order if not lb.startswith("roll")) if m]
        K1 = dict(K0)
        if len(pan_tilt) >= 2:
            first_refine = refine(pan_tilt, K0, n_dist=params.distortion_terms)
            K1 = {"fx": first_refine.fx, "fy": first_refine.fy, "cx": first_refine.cx,
                  "cy": first_refine.cy}
        tracking["K_for_rolls"] = K1
        for label in roll_labels:
            track(label, K1, 24.0)

        def stats(label: str, idx: list[int]) -> list[ContourStats]:
            if label == "ref":
                return [ContourStats.of(contours[i].points, centre) for i in idx]
            return [ContourStats.of(matches[label][i].points, centre) for i in idx]

        def ok_in(*labels: str) -> list[int]:
            return [i for i in range(len(contours))
                    if all(lb in matches and matches[lb][i].ok for lb in labels)]

        th_p, th_t = rel["pan+"][0], rel["tilt+"][1]
        pt = ok_in("pan+", "tilt+")
        strategies: dict[str, Any] = {}

        def record(name: str, fn) -> None:
            try:
                est = fn()
                strategies[name] = {"fx": est["fx"], "fy": est["fy"],
                                    "cx": centre[0] + est["dx"], "cy": centre[1] + est["dy"]}
            except SolveError as exc:
                strategies[name] = {"error": str(exc)}

        record("A", lambda: active.strategy_a(stats("ref", pt), stats("tilt+", pt),
                                              stats("pan+", pt), th_t, th_p))
        record("B", lambda: active.strategy_b(stats("ref", pt), stats("tilt+", pt),
                                              stats("pan+", pt), th_t, th_p))
        roll_pairs = []
        for label in roll_labels:
            idx = ok_in(label)
            roll_pairs += list(zip(stats("ref", idx), stats(label, idx),
                                   [rel[label][2]] * len(idx), strict=True))
        record("C", lambda: active.strategy_c(stats("ref", pt), stats("tilt+", pt),
                                              stats("pan+", pt), th_t, th_p, roll_pairs))
        half = [m for m in roll_labels if abs(abs(rel[m][2]) - math.pi) < math.radians(2)]
        if half:
            idx = ok_in(half[0])
            record("D", lambda: active.strategy_d(
                stats("ref", pt), stats("tilt+", pt), stats("pan+", pt), th_t, th_p,
                list(zip(stats("ref", idx), stats(half[0], idx), strict=True))))
        else:
            strategies["D"] = {"error": "no 180-degree roll captured"}
        start = strategies.get("D") if "error" not in strategies.get("D", {"error": 1}) \
            else strategies.get("C") if "error" not in strategies.get("C", {"error": 1}) \
            else {"fx": K0["fx"], "fy": K0["fy"], "cx": K0["cx"], "cy": K0["cy"]}

        # 3. refinement over every motion, in curve mode
        motions = [m for m in (motion(lb) for lb in order) if m is not None]
        refined = refine(motions, start, n_dist=params.distortion_terms)
        strategies["refined"] = refined.as_dict()
        result = {
            "fx": refined.fx, "fy": refined.fy, "cx": refined.cx, "cy": refined.cy,
            "sigma": {k: refined.sigma[k] for k in ("fx", "fy", "cx", "cy")},
            "width": w, "height": h,
            "distortion": [refined.k1, refined.k2, refined.p1, refined.p2, 0.0],
            "roll_axis_in_cam": refined.roll_axis.tolist(),
            "assumed_centre": centre.tolist(),
            "strategies": strategies, "tracking": tracking,
            "summary": {"fx": refined.fx, "fy": refined.fy, "cx": refined.cx,
                        "cy": refined.cy, "rms_px": refined.rms_px,
                        "contours": len(contours)},
        }
        _plots(ctx, images, contours, matches, refined, order)
        _exports(ctx, result)
        return result


def _predictor(K: dict, rel_angles):
    """Maps reference pixels to the moved image with the nominal head (pure rotation)."""
    from rigctl.calib.synthetic import intrinsics, rot_x, rot_y, rot_z

    Km = intrinsics(K["fx"], K["fy"], K["cx"], K["cy"])
    Kinv = np.linalg.inv(Km)
    p, t, r = rel_angles
    R = rot_y(p) @ rot_x(t) @ rot_z(r)

    def predict(points: np.ndarray) -> np.ndarray:
        rays = (Kinv @ np.c_[points, np.ones(len(points))].T).T
        moved = (Km @ (R.T @ rays.T)).T
        return moved[:, :2] / moved[:, 2:3]

    return predict


def _plots(ctx: SolveContext, images, contours, matches, refined, order) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(14, 4.5))
    axes[0].imshow(images["ref"], cmap="gray")
    for c in contours:
        axes[0].plot(c.points[:, 0], c.points[:, 1], ".", ms=1)
    axes[0].set_title(f"reference: {len(contours)} contours")
    show = next((m for m in ("roll-180", "roll+180") if m in matches), order[0])
    axes[1].imshow(images[show], cmap="gray")
    for m in matches[show]:
        if m.ok:
            axes[1].plot(m.points[:, 0], m.points[:, 1], ".", ms=1)
    axes[1].set_title(f"{show}: tracked {sum(m.ok for m in matches[show])}")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(ctx.plots_dir / "contours.png", dpi=80)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    labels = list(refined.residuals_by_motion)
    ax.bar(labels, [refined.residuals_by_motion[k] for k in labels])
    ax.set_ylabel("RMS point-to-contour residual (px)")
    ax.set_title(f"refinement residuals (overall {refined.rms_px:.3f} px)")
    fig.tight_layout()
    fig.savefig(ctx.plots_dir / "residuals.png", dpi=80)
    plt.close(fig)


def _exports(ctx: SolveContext, result: dict) -> None:
    from rigctl.exports import export_opencv, export_ros

    export_opencv(result, ctx.run.path / "camera.opencv.yaml", ctx.run.run_id)
    export_ros(result, ctx.run.path / "camera_info.yaml", ctx.run.run_id)


PROCEDURE = ActiveCamera()
