"""ChArUco boards: detection on the simulated camera's images against its truth, partial
views corner by corner, a board that is not the configured one refused by name, and the
solvers on the corners a view has (id order, NaN where not seen)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from rigctl.calib import handeye, robot
from rigctl.calib.board import board_points, detect_target, target_key
from rigctl.calib.intrinsics_check import board_intrinsics
from rigctl.config import parse_rig
from rigctl.errors import ConfigError
from rigctl.geometry.transforms import inv_T, look_at, make_T, rotvec_to_R
from rigctl.mocks.random_world import random_world
from rigctl.mocks.world import WORLDS, World, WorldFile, load_world
from rigctl.records import Capture

pytestmark = pytest.mark.timeout(300)

CHARUCO = {"type": "charuco", "dictionary": "DICT_5X5_100", "marker_mm": 22.0}


def _world(base: str = "ideal", **target) -> World:
    data = yaml.safe_load((WORLDS / f"{base}.yaml").read_text())
    data["target"].update({**CHARUCO, **target})
    return World(WorldFile.model_validate(data))


def _config(world: World, **override) -> SimpleNamespace:
    """The rig file's target as the detector reads it (``TargetConfig``'s keys)."""
    tg = world.spec.target
    return SimpleNamespace(**{"type": tg.type, "rows": tg.rows, "cols": tg.cols,
                              "square_mm": tg.square_mm, "dictionary": tg.dictionary,
                              "marker_mm": tg.marker_mm, "legacy_pattern": tg.legacy_pattern,
                              **override})


def _centre(world: World, offset=(0.0, 0.0)) -> np.ndarray:
    tg = world.spec.target
    s = tg.square_mm / 1000.0
    local = [tg.cols * s / 2 + offset[0], tg.rows * s / 2 + offset[1], 0.0]
    return world.T_base_target[:3, :3] @ local + world.T_base_target[:3, 3]


def _views(world: World, n: int = 10, distance_m: float = 0.45) -> list[np.ndarray]:
    """Cameras 10-35 deg off the board's normal, looking at its centre, turned about
    their own axis."""
    T = world.T_base_target
    normal, inplane = -T[:3, 2], T[:3, 0]
    rng = np.random.default_rng(3)
    out = []
    for k in range(n):
        tilt, azimuth = math.radians(10 + 25 * k / (n - 1)), 2 * math.pi * k / n
        side = math.cos(azimuth) * inplane + math.sin(azimuth) * np.cross(normal, inplane)
        eye = _centre(world) + distance_m * (math.cos(tilt) * normal + math.sin(tilt) * side)
        spin = rng.uniform(-0.6, 0.6)
        up = math.cos(spin) * inplane + math.sin(spin) * np.cross(normal, inplane)
        out.append(look_at(eye, _centre(world), up))
    return out


@pytest.mark.parametrize("base", ["ideal", "default"])
def test_corners_land_on_the_renderers_truth(base):
    """Sharp views (ideal world, and the default one with distortion and 0.5 grey levels
    of noise): every corner identified, at its id, within 0.13 px on average and 0.45 px
    at worst of where the renderer put it (the checkerboard's, on the same views: 0.10
    and 0.24 px), and no view's corners share an offset (mean within 0.05 px)."""
    world = _world(base)
    target = _config(world)
    errors = []
    for k, T_base_cam in enumerate(_views(world)):
        found = detect_target(world.render(T_base_cam, frame_index=k), target)
        assert found.corners is not None, f"view {k}: {found.note}"
        truth = world.target_corner_pixels(T_base_cam)
        seen = np.isfinite(found.corners[:, 0])
        assert seen.sum() >= 50, f"view {k}: {seen.sum()} of 54 corners"
        error = found.corners[seen] - truth[seen]
        assert np.linalg.norm(error.mean(axis=0)) < 0.05, f"view {k}: shared offset"
        errors.append(np.linalg.norm(error, axis=1))
    errors = np.concatenate(errors)
    assert errors.mean() < 0.13 and errors.max() < 0.45, \
        f"corners {errors.mean():.3f} px off on average, {errors.max():.3f} at worst"


def test_a_board_running_off_the_image_gives_the_corners_in_view():
    """The camera looks at a corner of the board from 0.25 m: part of the board lies
    outside the image. The corners in view come back, each at its id (one neighbouring
    marker in view identifies a corner), and none of those outside."""
    world = _world()
    s = world.spec.target.square_mm / 1000.0
    aim = _centre(world, (4.0 * s, 2.5 * s))
    T = world.T_base_target
    eye = aim + 0.25 * (-T[:3, 2] * math.cos(0.3) + T[:3, 0] * math.sin(0.3))
    T_base_cam = look_at(eye, aim, T[:3, 1])
    truth = world.target_corner_pixels(T_base_cam)
    w, h = world.size
    in_image = (truth[:, 0] > 2) & (truth[:, 0] < w - 3) & (truth[:, 1] > 2) & \
        (truth[:, 1] < h - 3)
    assert 12 <= in_image.sum() < 45  # the view is partial
    found = detect_target(world.render(T_base_cam), _config(world))
    assert found.corners is not None, found.note
    seen = np.isfinite(found.corners[:, 0])
    assert not np.any(seen & ~in_image)
    assert seen.sum() >= 0.9 * in_image.sum()
    error = np.linalg.norm(found.corners[seen] - truth[seen], axis=1)
    assert error.max() < 0.4, f"{error.max():.2f} px"


@pytest.mark.parametrize("printed, configured, said", [
    ({"dictionary": "DICT_6X6_250"}, {}, "markers of DICT_6X6_50"),
    ({"dictionary": "DICT_APRILTAG_36h11"}, {}, "markers of DICT_APRILTAG_36h11"),
    ({}, {"dictionary": "DICT_4X4_50"}, "markers of DICT_5X5_50"),
    ({}, {"rows": 5, "cols": 6}, "not on the configured board (DICT_5X5_100, 5 x 6 squares"),
    ({"rows": 5, "cols": 7}, {}, "not where the configured board (DICT_5X5_100, 7 x 10"),
    ({"rows": 6, "legacy_pattern": True}, {"rows": 6},
     "lie as on a board with legacy_pattern: true"),
])
def test_a_board_that_is_not_the_configured_one_is_refused_by_name(printed, configured, said):
    """Another dictionary, ids beyond the board's, another size or layout: no corners,
    and a note saying what was seen."""
    world = _world(**printed)
    config = _config(world, **{"rows": 7, "cols": 10, "dictionary": "DICT_5X5_100",
                               "legacy_pattern": False, **configured})
    found = detect_target(world.render(_views(world)[2]), config)
    assert found.corners is None
    assert said in found.note and "view left out" in found.note, found.note


def test_markers_too_small_to_decode_are_not_called_another_board():
    """Random world 99403's 9.8 mm 6x6 markers at 0.9 m: too small to decode, a few of them
    read as scattered DICT_4X4_1000 ids (24 and 852). The note says the outlines did not
    decode, and names no other dictionary, as the old note did."""
    world = World(WorldFile.model_validate(random_world(99403, "charuco")))
    found = detect_target(world.render(_views(world, 3, 0.9)[0]), _config(world))
    assert found.corners is None
    assert "DICT_4X4" not in found.note, found.note
    assert "square outlines did not decode" in found.note and "board not found" in found.note


def test_rig_and_world_files_name_an_unknown_dictionary_and_the_known_ones():
    rig = "target: {type: charuco, rows: 7, cols: 10, square_mm: 30, marker_mm: 22, " \
          "dictionary: DICT_5X5_99}\n"
    with pytest.raises(ConfigError) as bad:
        parse_rig(rig)
    assert "rig.yaml: target.dictionary: unknown ArUco dictionary 'DICT_5X5_99'" in \
        str(bad.value) and "DICT_5X5_100" in str(bad.value)
    with pytest.raises(ConfigError, match="needs dictionary and marker_mm"):
        parse_rig("target: {type: charuco, rows: 7, cols: 10}\n")
    with pytest.raises(ConfigError, match="DICT_4X4_50 has 50 markers; a board of 11 x 11"):
        parse_rig("target: {type: charuco, rows: 11, cols: 11, square_mm: 20, "
                  "marker_mm: 15, dictionary: DICT_4X4_50}\n")
    config = parse_rig(rig.replace("DICT_5X5_99", "DICT_5X5_100"))
    assert config.target.type == "charuco" and config.target.marker_mm == 22
    data = yaml.safe_load((WORLDS / "ideal.yaml").read_text())
    data["target"].update(CHARUCO, dictionary="DICT_9X9")
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_9X9'; known: DICT_4X4"):
        WorldFile.model_validate(data)


def test_the_shipped_charuco_world_is_the_default_world_with_markers():
    charuco, default = load_world("charuco"), load_world("default")
    truth = charuco.truth()
    assert truth["target"]["type"] == "charuco"
    assert truth["target"]["dictionary"] == "DICT_5X5_100"
    assert np.allclose(charuco.T_base_target, default.T_base_target)
    assert charuco.truth()["T_flange_cam"] == default.truth()["T_flange_cam"]


def test_random_worlds_draw_a_charuco_board_of_the_same_squares():
    """The same seed's world with either target: only the target's markers differ."""
    for seed in (100_003, 100_004, 7):
        plain, marked = random_world(seed), random_world(seed, target="charuco")
        assert {k: v for k, v in marked.items() if k != "target"} == \
            {k: v for k, v in plain.items() if k != "target"}
        tg = marked["target"]
        assert tg["type"] == "charuco" and tg["xyz_mm"] == plain["target"]["xyz_mm"]
        assert 0.6 * tg["square_mm"] <= tg["marker_mm"] <= 0.8 * tg["square_mm"]
        WorldFile.model_validate(marked)
    with pytest.raises(ValueError, match="expected checkerboard, charuco or either"):
        random_world(1, target="dots")


def test_saved_detections_keep_ids_and_are_reused_for_the_same_board_only(tmp_path):
    world = _world()
    target = _config(world)
    image = world.render(_views(world)[0])
    path = tmp_path / "000.png"
    import cv2

    cv2.imwrite(str(path), image)
    capture = Capture(0, path, {})
    capture.save_board_corners(target)
    saved = yaml.safe_load(capture.board_path.read_text())
    assert saved["target"] == target_key(target) and len(saved["ids"]) == len(saved["corners"])
    again = capture.board_detection(target).corners
    assert np.allclose(again, detect_target(image, target).corners, equal_nan=True)
    # another configured board: detected again (and refused by name), not read back
    other = capture.board_detection(_config(world, dictionary="DICT_4X4_50"))
    assert other.corners is None and "DICT_5X5_50" in other.note


# -- the solvers on partial views ---------------------------------------------------------

def _synthetic(n_views: int = 12, seed: int = 5):
    """Views of a 7 x 10 board (30 mm squares) by a camera on an arm: the true X and W,
    arm poses F, camera poses C, and each view's pixels with a third of its corners (a
    random part of the grid) removed."""
    rng = np.random.default_rng(seed)
    obj = board_points(7, 10, 0.03)
    K = np.array([[900.0, 0, 640], [0, 905, 360], [0, 0, 1]])
    X = make_T(rotvec_to_R([0.02, -0.03, 1.2]), [0.01, -0.02, 0.06])
    W = make_T(rotvec_to_R([math.pi, 0, 0.3]), [0.5, 0.1, 0.0])
    F, C, corners = [], [], []
    for _ in range(n_views):
        T_target_cam = look_at(np.r_[rng.uniform(0.03, 0.24), rng.uniform(0.02, 0.16),
                                     -rng.uniform(0.35, 0.5)], [0.135, 0.09, 0.0],
                               [1.0, rng.uniform(-0.5, 0.5), 0.0])
        cam = T_target_cam
        F.append(W @ cam @ inv_T(X))
        C.append(inv_T(cam))
        p = (inv_T(cam)[:3, :3] @ obj.T).T + inv_T(cam)[:3, 3]
        px = (K @ p.T).T
        px = px[:, :2] / px[:, 2:3] + rng.normal(0, 0.1, (len(obj), 2))
        gone = rng.permutation(len(obj))[:len(obj) // 3]
        px[gone] = np.nan
        corners.append(px)
    return obj, K, X, W, F, C, corners


def test_hand_eye_refinement_uses_each_views_corners_by_id():
    obj, K, X, _, F, C, corners = _synthetic()
    X0 = make_T(rotvec_to_R([0.05, -0.01, 1.15]), [0.02, -0.01, 0.05])
    result = handeye.refine_pixels(F, corners, obj, K, np.zeros(5), X0, C=C)
    rot, mm = handeye.transform_error(result.X, X)
    assert rot < 0.05 and mm < 0.3
    assert 0.05 < result.rms < 0.15  # the 0.1 px noise on the corners seen, not diluted


def test_arm_residuals_hold_the_corners_each_view_has():
    """Pixel residuals of the arm model: 2 rows per corner a view has, view by view, and
    at the truth only the corners' noise."""
    from rigctl.geometry.kinematics import nominal_ur

    obj, K, X = _synthetic(6)[:3]
    model = nominal_ur("ur5e")
    qs = [np.radians([10 * k, -100, -100, -70, 90, 0]) for k in range(6)]
    rng = np.random.default_rng(2)
    W = model.fk(qs[0]) @ X @ make_T(rotvec_to_R([0, 0, 0.2]), [-0.13, -0.09, 0.45])
    corners = []
    for q in qs:
        cam = inv_T(model.fk(q) @ X) @ W
        p = (cam[:3, :3] @ obj.T).T + cam[:3, 3]
        px = (K @ p.T).T
        px = px[:, :2] / px[:, 2:3] + rng.normal(0, 0.1, (len(obj), 2))
        px[rng.permutation(len(obj))[:20]] = np.nan
        corners.append(px)
    meas = robot.Measurements(qs, C=None, corners=corners, obj=obj, K=K, dist=np.zeros(5))
    rows = robot.rows_per_view(meas)
    assert rows == [2 * (len(obj) - 20)] * 6
    r = robot.residuals(model, X, W, meas)
    assert len(r) == sum(rows) and np.all(np.isfinite(r))
    assert 0.05 < np.sqrt(np.mean(r ** 2)) < 0.15  # only the corners' noise at the truth


def test_the_intrinsics_check_takes_partial_views():
    obj, corners = _synthetic(14)[0], _synthetic(14)[-1]
    used = {"fx": 900.0, "fy": 905.0, "cx": 640.0, "cy": 360.0}
    check = board_intrinsics(obj, corners, (1280, 720), used)
    assert check["views"] == 14 and check["agrees"], check["note"]
    assert abs(check["board"]["fx"] - 900) < 3 and abs(check["board"]["cx"] - 640) < 3


def test_planned_views_let_a_charuco_board_run_off_the_image_with_enough_corners_in_view():
    """hand-eye's plan on the default world and on its ChArUco twin: every ChArUco view
    keeps 40 % of the corners (and 12) inside the image, some run off it, and together
    they reach more of the image's cells than the checkerboard's whole-board views."""
    from rigctl.geometry.kinematics import nominal_ur
    from rigctl.procedures import get_procedure
    from rigctl.procedures.planning import nominal_flange_cam, target_centre
    from rigctl.runner import check_plan
    from tests.test_e2e_charuco import coverage
    from tests.test_planning_worlds import rig_for

    shares = {}
    for name in ("default", "charuco"):
        data = yaml.safe_load((WORLDS / f"{name}.yaml").read_text())
        config = rig_for(data)
        cam = data["camera"]
        intrinsics = {k: cam[k] for k in ("fx", "fy", "cx", "cy")}
        proc = get_procedure("hand-eye")
        steps = proc.plan(proc.params_model(poses=12, intrinsics=intrinsics), config)
        assert not check_plan(config, steps, proc.devices)
        K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
        obj = board_points(config.target.rows, config.target.cols,
                           config.target.square_mm / 1000.0)
        model, W = nominal_ur("ur5e"), target_centre(config)[0]
        inside = []
        for step in steps[1:]:
            if type(step).__name__ != "MoveArmJoints" or step.label == "arm home":
                continue
            T = inv_T(model.fk(np.array(step.q)) @ nominal_flange_cam(config)) @ W
            px = (K @ ((T[:3, :3] @ obj.T).T + T[:3, 3]).T).T
            px = px[:, :2] / px[:, 2:3]
            ok = (px[:, 0] > 0) & (px[:, 0] < cam["width"]) & (px[:, 1] > 0) & \
                (px[:, 1] < cam["height"])
            inside.append(px[ok])
        assert len(inside) == 12
        counts = [len(p) for p in inside]
        if name == "default":
            assert min(counts) == len(obj)
        else:
            assert min(counts) >= max(0.4 * len(obj), 12) and min(counts) < len(obj)
        shares[name] = coverage(inside, cam["width"], cam["height"])
    assert shares["charuco"] > shares["default"] + 0.15, shares
