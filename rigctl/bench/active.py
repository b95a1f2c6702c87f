"""``rigctl bench active``: Monte Carlo of active calibration against truth.

Cases: every strategy and the refinement; noise sigma in {0.2, 0.5, 1.0} px; pan/tilt in
{3, 10} deg; roll-axis tilt in {0, 0.5} deg; at least 200 trials each with fixed seeds.
Camera: 1280x720, fx, fy = 900, 905, principal point (652.3, 371.8); the assumed centre is
the image centre. The same noise goes through OpenCV ``calibrateCamera`` on a 9x6
checkerboard with 10 and 20 views (tilts 10-45 deg), the pattern-based method users
would otherwise pick. Reports median and p95 of |focal error| (%) and principal-point
error (px), and writes a plot of error against noise.

It measures the solver's stages one at a time on synthetic contours (no images, no
tracking): Strategies A-D (``rigctl.calib.active``) and the refinement
(``rigctl.calib.active_refine.refine``) started from Strategy D. The whole pipeline
(``rigctl.calib.active_pipeline.solve_active``: tracking, tiers, scene depths and the
start it chooses) runs on rendered worlds in ``bench active-worlds``.
"""

from __future__ import annotations

import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from rigctl.calib import active
from rigctl.calib.active import ContourStats
from rigctl.calib.active_refine import Motion, refine
from rigctl.calib.synthetic import (
    intrinsics,
    make_contours,
    observe,
    project,
    rot_axis,
    rot_x,
    rot_y,
)
from rigctl.errors import SolveError

FX, FY, CX, CY = 900.0, 905.0, 652.3, 371.8
SIZE = (1280, 720)
C0 = (639.5, 359.5)
SIGMAS = (0.2, 0.5, 1.0)
ANGLES = (3.0, 10.0)
TILTS = (0.0, 0.5)
METHODS = ("A", "B", "C", "D", "refined")


def _errors(est: dict) -> tuple[float, float]:
    f_err = 100 * max(abs(est["fx"] - FX) / FX, abs(est["fy"] - FY) / FY)
    pp_err = math.hypot(est["cx"] - CX, est["cy"] - CY)
    return f_err, pp_err


def active_trial(args) -> dict:
    sigma, theta_deg, tilt_deg, seed = args
    rng = np.random.default_rng(seed)
    K = intrinsics(FX, FY, CX, CY)
    th = math.radians(theta_deg)
    a = rot_x(math.radians(tilt_deg)) @ np.array([0.0, 0.0, 1.0])
    contours = make_contours(rng, 15, 40, K, SIZE)
    poses = {"ref": (0, 0, 0), "pan+": (th, 0, 0), "pan-": (-th, 0, 0), "tilt+": (0, th, 0),
             "tilt-": (0, -th, 0), "roll+90": (0, 0, math.pi / 2),
             "roll-180": (0, 0, -math.pi), "roll-90": (0, 0, -math.pi / 2)}
    obs = {k: [observe(project(X, K, rot_y(p) @ rot_x(t) @ rot_axis(a, r)), rng, sigma,
                       rounding=False) for X in contours] for k, (p, t, r) in poses.items()}
    st = {k: [ContourStats.of(o, C0) for o in v] for k, v in obs.items()}
    out = {}
    ref, tilt, pan = st["ref"], st["tilt+"], st["pan+"]
    rolls = [(r, o, math.pi / 2) for r, o in zip(ref, st["roll+90"], strict=True)]
    half = list(zip(ref, st["roll-180"], strict=True))
    calls = {"A": lambda: active.strategy_a(ref, tilt, pan, th, th),
             "B": lambda: active.strategy_b(ref, tilt, pan, th, th),
             "C": lambda: active.strategy_c(ref, tilt, pan, th, th, rolls),
             "D": lambda: active.strategy_d(ref, tilt, pan, th, th, half)}
    for name, fn in calls.items():
        try:
            e = fn()
            out[name] = _errors({"fx": e["fx"], "fy": e["fy"], "cx": C0[0] + e["dx"],
                                 "cy": C0[1] + e["dy"]})
        except SolveError:
            out[name] = (float("inf"), float("inf"))
    try:
        d = calls["D"]()
        start = {"fx": d["fx"], "fy": d["fy"], "cx": C0[0] + d["dx"], "cy": C0[1] + d["dy"]}
        motions = [Motion(poses["ref"], poses[k], np.concatenate(obs["ref"]),
                          np.concatenate(obs[k]), label=k) for k in poses if k != "ref"]
        res = refine(motions, start)
        out["refined"] = _errors({"fx": res.fx, "fy": res.fy, "cx": res.cx, "cy": res.cy})
    except SolveError:
        out["refined"] = (float("inf"), float("inf"))
    return out


def board_trial(args) -> tuple[float, float]:
    sigma, views, seed = args
    rng = np.random.default_rng(seed)
    K = intrinsics(FX, FY, CX, CY)
    obj = np.array([[j * 0.04, i * 0.04, 0] for i in range(6) for j in range(9)], np.float32)
    centre = obj.mean(axis=0)
    objs, imgs = [], []
    while len(imgs) < views:
        tilt = math.radians(rng.uniform(10, 45))
        R = rot_axis([rng.normal(), rng.normal(), 0.2 * rng.normal()], tilt)
        dist = rng.uniform(0.6, 1.0)
        t = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), dist]) - R @ centre
        cam = (R @ obj.T).T + t
        px = project(cam, K) + rng.normal(0, sigma, (len(obj), 2))
        if np.all((px > 5) & (px < np.array(SIZE) - 5)):
            objs.append(obj)
            imgs.append(px.astype(np.float32))
    _, Kest, *_ = cv2.calibrateCamera(objs, imgs, SIZE, None, None)
    return _errors({"fx": Kest[0, 0], "fy": Kest[1, 1], "cx": Kest[0, 2], "cy": Kest[1, 2]})


def _summary(pairs) -> dict:
    f = np.array([p[0] for p in pairs])
    c = np.array([p[1] for p in pairs])
    return {"focal_pct_median": float(np.median(f)), "focal_pct_p95": float(np.percentile(f, 95)),
            "pp_px_median": float(np.median(c)), "pp_px_p95": float(np.percentile(c, 95)),
            "failed": int(np.sum(~np.isfinite(f)))}


def run(trials: int = 200, workers: int = 2, plot: Path | None = None) -> dict:
    cases = [(s, a, t) for s in SIGMAS for a in ANGLES for t in TILTS]
    jobs = [(s, a, t, 10_000 * i + k) for i, (s, a, t) in enumerate(cases) for k in range(trials)]
    board_jobs = [(s, v, 77_000 + 1000 * i + k) for i, (s, v) in
                  enumerate((s, v) for s in SIGMAS for v in (10, 20)) for k in range(trials)]
    with ProcessPoolExecutor(workers) as pool:
        results = list(pool.map(active_trial, jobs, chunksize=20))
        boards = list(pool.map(board_trial, board_jobs, chunksize=20))
    out = {"trials": trials, "truth": {"fx": FX, "fy": FY, "cx": CX, "cy": CY}, "cases": [],
           "calibrateCamera": []}
    for i, (s, a, t) in enumerate(cases):
        chunk = results[i * trials:(i + 1) * trials]
        out["cases"].append({"sigma_px": s, "pan_tilt_deg": a, "roll_axis_tilt_deg": t,
                             **{m: _summary([r[m] for r in chunk]) for m in METHODS}})
    for i, (s, v) in enumerate((s, v) for s in SIGMAS for v in (10, 20)):
        out["calibrateCamera"].append({"sigma_px": s, "views": v,
                                       **_summary(boards[i * trials:(i + 1) * trials])})
    target = next(c for c in out["cases"] if c["sigma_px"] == 0.5 and c["pan_tilt_deg"] == 10
                  and c["roll_axis_tilt_deg"] == 0.5)
    out["targets"] = {"refined_focal_median_within_0.1pct": target["refined"]["focal_pct_median"]
                      <= 0.1,
                      "refined_pp_median_within_1px": target["refined"]["pp_px_median"] <= 1.0}
    if plot is not None:
        _plot(out, plot)
        out["plot"] = str(plot)
    return out


def _plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for method, style in (("B", "o--"), ("D", "s--"), ("refined", "^-")):
        for tilt in TILTS:
            rows = [c for c in out["cases"] if c["pan_tilt_deg"] == 10
                    and c["roll_axis_tilt_deg"] == tilt]
            label = f"{method}, axis tilt {tilt} deg"
            axes[0].plot([r["sigma_px"] for r in rows],
                         [r[method]["focal_pct_median"] for r in rows], style, label=label)
            axes[1].plot([r["sigma_px"] for r in rows],
                         [r[method]["pp_px_median"] for r in rows], style, label=label)
    for views in (10, 20):
        rows = [c for c in out["calibrateCamera"] if c["views"] == views]
        axes[0].plot([r["sigma_px"] for r in rows], [r["focal_pct_median"] for r in rows],
                     "k:", label=f"calibrateCamera {views} views")
        axes[1].plot([r["sigma_px"] for r in rows], [r["pp_px_median"] for r in rows], "k:")
    axes[0].set(xlabel="noise sigma (px)", ylabel="median |focal error| (%)", yscale="log",
                title="focal length (pan/tilt 10 deg)")
    axes[1].set(xlabel="noise sigma (px)", ylabel="median principal point error (px)",
                yscale="log", title="principal point")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
