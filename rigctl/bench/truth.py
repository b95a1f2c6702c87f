"""Calibration results against a simulated world's truth (benchmarks, demo and tests)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from rigctl.geometry.kinematics import KinematicModel
from rigctl.geometry.transforms import inv_T
from rigctl.procedures.planning import eye_to_hand, planning_K, reachable_views

INTRINSICS = ("fx", "fy", "cx", "cy")


def check_configurations(config) -> list[np.ndarray]:
    """34 planned views (35 deg tilt, 0.5 m or closer when the arm cannot reach that
    far) with the wrist joints each perturbed three times (sigma 0.2 rad): configurations
    no run visits. With the head beside the arm: 34 board views of the fixed camera
    (``planning_e2h.board_views``, 35 deg tilt), the wrists perturbed alike."""
    if eye_to_hand(config):
        from rigctl.procedures.planning_e2h import board_views

        views, _ = board_views(config, 34, 0.45, 35.0, 4242, planning_K(config, None))
    else:
        views, _ = reachable_views(config, 34, 0.5, 35.0, seed=4242, label="check view")
    rng = np.random.default_rng(0)
    return [np.array(q) + np.r_[np.zeros(3), rng.normal(0, 0.2, 3)]
            for q in views for _ in range(3)]


def frames_of(result: dict) -> tuple[np.ndarray, np.ndarray, bool]:
    """A result's X and W and whether its camera stands beside the arm: (T_flange_cam,
    T_base_target, False) or (T_base_cam, T_flange_target, True)."""
    if "T_base_cam" in result:
        return np.array(result["T_base_cam"]), np.array(result["T_flange_target"]), True
    return np.array(result["T_flange_cam"]), np.array(result["T_base_target"]), False


def _position_errors(result: dict, world, qs) -> np.ndarray:
    """Camera position in the target frame, ``W^-1 FK(q) X`` from the exported model
    (``robot.target_cam``, either mounting), minus the world's truth (m, target frame),
    per configuration."""
    from rigctl.calib.robot import target_cam

    model = KinematicModel.from_export(result)
    X, W, fixed = frames_of(result)
    out = []
    for q in qs:
        est = target_cam(model, X, W, q, fixed)
        true = inv_T(world.T_base_target_at(q)) @ world.T_base_cam(q, (0.0, 0.0, 0.0))
        out.append(est[:3, 3] - true[:3, 3])
    return np.array(out)


def model_against_truth(result: dict, config, world) -> tuple[float, float, int]:
    """The exported model's camera position against the world's truth over
    ``check_configurations``: RMS and max (mm), and the count."""
    errors = 1000 * np.linalg.norm(_position_errors(result, world,
                                                    check_configurations(config)), axis=1)
    return float(np.sqrt(np.mean(np.square(errors)))), float(np.max(errors)), len(errors)


def position_z(result: dict, config, world) -> list[float]:
    """Per axis and configuration (``check_configurations``), the camera position's error
    against the truth over its predicted sigma (``robot.camera_position_sigma`` from the
    result's covariance); empty when the result has no covariance."""
    from rigctl.calib.robot import camera_position_sigma

    cov = result.get("covariance")
    if not cov:
        return []
    names = [n for n in cov["names"] if not n.startswith("camera.")]
    qs = check_configurations(config)
    X, W, fixed = frames_of(result)
    sigma = camera_position_sigma(KinematicModel.from_export(result), X, W, names,
                                  np.array(cov["matrix"]), qs, fixed)
    error, sigma = _position_errors(result, world, qs).ravel(), np.asarray(sigma).ravel()
    usable = sigma > 1e-9  # m; an axis the model does not move (no claim to check)
    return (error[usable] / sigma[usable]).tolist()


def intrinsics_errors(result: dict, truth: dict) -> dict:
    """Focal error (%, the worse axis), centre error (px) and each intrinsic's error over
    its reported sigma."""
    sigma = result.get("sigma", {})
    return {
        "focal_pct": 100 * max(abs(result[k] / truth[k] - 1) for k in ("fx", "fy")),
        "centre_px": float(np.hypot(result["cx"] - truth["cx"], result["cy"] - truth["cy"])),
        "z": {k: (result[k] - truth[k]) / sigma[k] for k in INTRINSICS
              if sigma.get(k, 0) > 0},
    }


def identified_value(links: list[dict], key: str) -> float:
    """The value of an identified link parameter ``linkN.field`` in ``links`` (the
    truth's, or an estimate's), in the gauge the minimal parameter set uses: offsets
    along the parallel joints 2-4 cannot be told apart, so ``link4.d`` is the sum
    d2 + d3 + d4."""
    link, field = key.split(".")
    i = int(link.removeprefix("link")) - 1
    if (i, field) == (3, "d"):
        return sum(links[j]["d"] for j in (1, 2, 3))
    return links[i][field]


def link_z(result: dict, truth: dict) -> dict[str, float]:
    """(estimate - truth) / sigma for each identified link parameter of a
    robot-kinematics result (the hand-eye and target poses' deltas are left out: their
    gauge absorbs link 1 and link 6)."""
    sigma = result["uncertainty"]["parameters"]
    out = {}
    for key, s in sigma.items():
        if not key.startswith("link") or s <= 0:
            continue
        # the estimate in the same gauge: d2 and d3 stay where the start put them (not
        # identified), so link4.d is compared as the sum d2 + d3 + d4 on both sides
        out[key] = (identified_value(result["links"], key)
                    - identified_value(truth["arm"]["links"], key)) / s
    return out


def image_coverage(corner_sets, width: int, height: int, cells: int = 10) -> float:
    """The share of a ``cells`` x ``cells`` grid over the image with at least one board
    corner of any view in it (NaN rows, corners not seen, are left out)."""
    hit = np.zeros((cells, cells), bool)
    for corners in corner_sets:
        px = np.asarray(corners, float).reshape(-1, 2)
        px = px[np.all(np.isfinite(px), axis=1)]
        i = np.clip((px[:, 1] * cells / height).astype(int), 0, cells - 1)
        j = np.clip((px[:, 0] * cells / width).astype(int), 0, cells - 1)
        hit[i, j] = True
    return float(hit.mean())


def contour_inverse_depths(world, contours: list[np.ndarray], T_base_cam: np.ndarray,
                           within_px: float = 1.5, samples: int = 20) -> np.ndarray:
    """The true inverse depth (1/m, camera frame) of each contour seen from
    ``T_base_cam``: the scene shape whose projected outline (``samples`` points an edge,
    those in front of the camera) most of the contour's points (pixels) lie within
    ``within_px`` of, at the mean depth of those outline points; NaN for a contour that
    traces no shape so (the board's). Occlusion is not checked: a contour along the
    edge where a nearer shape covers a farther one gets the depth of whichever shape's
    outline it follows more."""
    outlines, depths = [], []
    T_cam_base = inv_T(T_base_cam)
    for shape in world.scene_shapes():
        ends = np.roll(shape, -1, axis=0)
        f = np.linspace(0.0, 1.0, samples, endpoint=False)[None, :, None]
        dense = (shape[:, None] + f * (ends - shape)[:, None]).reshape(-1, 3)
        z = (T_cam_base[:3, :3] @ dense.T + T_cam_base[:3, 3:4])[2]
        dense, z = dense[z > 0], z[z > 0]  # behind the camera, projections mirror
        outlines.append(world.project(dense, T_base_cam) if len(dense) else np.zeros((0, 2)))
        depths.append(z)
    owner = np.concatenate([np.full(len(o), i) for i, o in enumerate(outlines)])
    index = np.concatenate([np.arange(len(o)) for o in outlines])
    tree = cKDTree(np.concatenate(outlines))
    out = np.full(len(contours), np.nan)
    for c, points in enumerate(contours):
        distance, nearest = tree.query(points)
        near = distance < within_px
        if near.sum() < 0.5 * len(points):
            continue
        shape = np.bincount(owner[nearest[near]]).argmax()
        on = near & (owner[nearest] == shape)
        out[c] = 1.0 / float(np.mean(depths[shape][index[nearest[on]]]))
    return out
