"""Random plausible rigs: worlds nobody tuned the solvers for.

``random_world(seed)`` draws one world file (as a dict, validated by ``WorldFile``), so
that every solver and planner can be judged on a distribution of rigs rather than on
``default.yaml``. The ranges are those of lab rigs:

- camera: 1280x720, 1024x768 or 1280x960, focal 600-1600 px, aspect within +-2 %,
  principal point within 30 px of the image centre; radial k1, k2, k3 and small
  tangential terms (rejected if the distortion folds over inside the image); blur and
  noise;
- head: roll axis tilted up to 0.5 deg, centre of projection off the axes by up to 3 mm;
  servos of one family (X, MX, P) or a mixed bus, with hardware encoders (readings
  quantized to the model's pulse, about a pulse of noise, plus up to half a pulse more);
- arm: any of the thirteen UR models (``rigctl.mocks.ur_models``): seeds from
  ``ALL_MODELS_FROM`` on take them in turn (seed mod 13, so any 26 consecutive seeds hold
  each twice); seeds below keep the UR3e, UR5e or UR10e they always drew, so that every
  recorded benchmark and regression seed still gives its world. Kinematic errors at
  the spread of factory variation
  (encoder offsets ~0.1 deg, lengths ~1 mm, twists ~0.08 deg; Hayati beta on the
  parallel joints 2-3 and 3-4); the controller's factory calibration (``factory_errors``)
  is the truth's plain-DH part up to a third of that spread;
- hand-eye: any yaw, a few degrees of tilt, tens of millimetres of offset;
- scene: shapes from 0.6-2 m out to 2-5 times that, in a cone just wider than the view;
- target: a checkerboard sized for the arm, on or near the table anywhere in the arm's
  comfortable reach around the front half, turned about its normal and tilted; or
  (``target="charuco"``) a ChArUco board of the same squares (``_charuco``);
- mounting (``mount="fixed"``, eye-to-hand): the head stands beside the arm, 0.5-0.9 m
  (scaled with the reach) from a point of the arm's front workspace and looking at it,
  and the flange holds a smaller board, 10-40 mm off the flange, turned and tilted a
  few degrees (``_eye_to_hand``).
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.mocks.ur_models import MODEL_NAMES
from rigctl.mocks.ur_models import REACH_M as REACH_M
from rigctl.mocks.world import WorldFile, rpy_matrix

ALL_MODELS_FROM = 100_000  # seeds from here on draw every UR model (see the module note)
SIZES = ((1280, 720), (1280, 720), (1024, 768), (1280, 960))


def _distortion(rng: np.random.Generator, fx: float, size: tuple[int, int]) -> list[float]:
    """[k1, k2, p1, p2, k3] whose radial map stays monotonic past the image corner."""
    r_max = 1.15 * math.hypot(size[0] / 2, size[1] / 2) / fx
    while True:
        k1, k2, k3 = rng.uniform(-0.30, 0.08), rng.uniform(-0.05, 0.15), rng.uniform(-0.05, 0.05)
        p1, p2 = rng.normal(0, 5e-4, 2)
        r = np.linspace(0, r_max, 200)
        slope = 1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4 + 7 * k3 * r ** 6
        factor = 1 + k1 * r ** 2 + k2 * r ** 4 + k3 * r ** 6
        if slope.min() > 0.3 and factor.min() > 0.75 and factor.max() < 1.25:
            return [round(float(v), 7) for v in (k1, k2, p1, p2, k3)]


def _camera(rng: np.random.Generator) -> dict:
    width, height = SIZES[rng.integers(len(SIZES))]
    fx = rng.uniform(600, 1600)
    fy = fx * (1 + rng.uniform(-0.02, 0.02))
    return {"width": int(width), "height": int(height), "fx": round(fx, 2), "fy": round(fy, 2),
            "cx": round((width - 1) / 2 + rng.uniform(-30, 30), 2),
            "cy": round((height - 1) / 2 + rng.uniform(-30, 30), 2),
            "distortion": _distortion(rng, fx, (width, height)),
            "pixel_noise": round(rng.uniform(0.2, 1.5), 2),
            "jpeg_quality": int(rng.integers(85, 99)), "fps": 15,
            "blur_sigma": round(rng.uniform(0.3, 1.2), 2)}


def _within(rng: np.random.Generator, radius: float, dims: int) -> list[float]:
    """A vector of length up to ``radius``, uniform in direction."""
    v = rng.normal(size=dims)
    return (v / np.linalg.norm(v) * radius * rng.uniform() ** (1 / dims)).tolist()


def _arm_errors(rng: np.random.Generator) -> dict:
    beta = np.zeros(6)
    beta[1:3] = rng.normal(0, 0.08, 2)  # joints 2-3 and 3-4 are parallel on a UR
    return {"theta_deg": rng.normal(0, 0.1, 6).round(4).tolist(),
            "d_mm": rng.normal(0, 1.0, 6).round(3).tolist(),
            "a_mm": rng.normal(0, 1.2, 6).round(3).tolist(),
            "alpha_deg": rng.normal(0, 0.08, 6).round(4).tolist(),
            "beta_deg": beta.round(4).tolist()}


def _factory_errors(rng: np.random.Generator, truth: dict) -> dict:
    """What the controller believes: its factory calibration found the truth's plain-DH
    part up to a residual of about a third of the factory spread, and cannot hold beta."""
    spread = {"theta_deg": 0.1, "d_mm": 1.0, "a_mm": 1.2, "alpha_deg": 0.08}
    digits = {"theta_deg": 4, "d_mm": 3, "a_mm": 3, "alpha_deg": 4}
    return {k: (np.asarray(truth[k]) + rng.normal(0, spread[k] / 3, 6)).round(digits[k]).tolist()
            for k in spread}


def _target(rng: np.random.Generator, model: str) -> dict:
    reach = REACH_M[model]
    square = rng.uniform(0.025, 0.045) * reach  # 12-22 mm on a UR3e, 33-58 mm on a UR10e
    rows, cols = int(rng.integers(5, 9)), int(rng.integers(6, 11))
    radius = rng.uniform(0.45, 0.75) * reach
    azimuth = rng.uniform(-math.pi / 2, math.pi / 2) + math.pi  # in front: -x side
    centre = np.array([radius * math.cos(azimuth), radius * math.sin(azimuth),
                       rng.uniform(-0.02, 0.08) * reach])
    # Board facing up (z into the board points down), turned about its normal, tilted.
    yaw = rng.uniform(-180, 180)
    tilt = _within(rng, 15.0, 2)
    rpy = [180.0 + tilt[0], tilt[1], yaw]
    R = rpy_matrix(rpy)
    half = np.array([cols * square / 2, rows * square / 2, 0.0])
    origin = centre - R @ half
    return {"rows": rows, "cols": cols, "square_mm": round(1000 * square, 2),
            "xyz_mm": (1000 * origin).round(1).tolist(), "rpy_deg": np.round(rpy, 3).tolist()}


# ChArUco dictionaries of printed lab boards (OpenCV's names), by the smallest that holds
# a board's markers
CHARUCO_DICTIONARIES = ("DICT_4X4_50", "DICT_5X5_100", "DICT_6X6_250")


def _charuco(rng: np.random.Generator, target: dict) -> dict:
    """The checkerboard ``target`` made a ChArUco board of the same squares and place:
    a dictionary of ``CHARUCO_DICTIONARIES``, markers 60-80 % of the square, OpenCV's
    current layout or (a board with an even row count, one in four) its pre-4.6 one."""
    name = CHARUCO_DICTIONARIES[rng.integers(len(CHARUCO_DICTIONARIES))]
    legacy = bool(target["rows"] % 2 == 0 and rng.uniform() < 0.25)
    return {**target, "type": "charuco", "dictionary": name,
            "marker_mm": round(target["square_mm"] * rng.uniform(0.6, 0.8), 2),
            "legacy_pattern": legacy}


# Pan/tilt and roll servos of lab heads: one family, or a mixed bus
HEAD_SETS = (
    (("xm430-w350", "xh430-w350", "xm540-w270", "xh540-w270", "xw540-t260"),
     ("xm430-w350", "xm430-w210", "xh430-w210", "xl430-w250", "xc430-w240")),
    (("mx-64", "mx-106"), ("mx-28", "mx-64")),
    (("ph54-200-s500-r", "ph54-100-s500-r", "pm54-060-s250-r", "pm54-040-s250-r"),
     ("ph42-020-s300-r", "pm42-010-s260-r")),
    (("xh540-w270", "xm540-w270", "ph54-100-s500-r"), ("xm430-w350", "xh430-w350")),
)


def _head_servos(rng: np.random.Generator) -> dict:
    """The head's servo models (one family or mixed) and hardware encoders, with extra
    reading noise of up to half the pan servo's pulse (sigma)."""
    pan_tilt, roll = HEAD_SETS[rng.integers(len(HEAD_SETS))]
    big = str(pan_tilt[rng.integers(len(pan_tilt))])
    models = [big, big, str(roll[rng.integers(len(roll))])]
    from rigctl.mocks.dxl_models import SPEC_BY_NAME

    pulse_deg = 360.0 / SPEC_BY_NAME[big].pulses_per_rev
    return {"models": models, "encoder": "hardware",
            "encoder_noise_deg": round(float(rng.uniform(0.0, 0.5)) * pulse_deg, 6)}


def _arm_model(seed: int, rng: np.random.Generator) -> str:
    """The arm of world ``seed``: UR3e, UR5e or UR10e drawn from ``rng`` below
    ``ALL_MODELS_FROM`` (the worlds those seeds always gave), else every model in turn.
    Draws from ``rng`` either way, so that the rest of a world is drawn as before."""
    legacy = ("ur3e", "ur5e", "ur10e")[rng.integers(3)]
    return legacy if seed < ALL_MODELS_FROM else MODEL_NAMES[seed % len(MODEL_NAMES)]


def _rpy_of(R: np.ndarray) -> list[float]:
    """[roll, pitch, yaw] degrees of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    from scipy.spatial.transform import Rotation

    return np.round(Rotation.from_matrix(R).as_euler("ZYX", degrees=True)[::-1], 3).tolist()


def _eye_to_hand(rng: np.random.Generator, model: str, target: dict) -> tuple[dict, dict]:
    """The head beside the arm and the board on the flange (module note): the head's
    ``fixed_xyz_mm``/``fixed_rpy_deg`` (``T_base_head``, the camera on the head axes
    looking at the workspace point, image x level within a few degrees) and the
    target's keys with ``mount: flange`` and ``T_flange_target`` (its squares scaled
    down to what a flange holds)."""
    reach = REACH_M[model]
    look = np.array([-rng.uniform(0.35, 0.55) * reach, rng.uniform(-0.2, 0.2) * reach,
                     rng.uniform(0.25, 0.45) * reach])
    distance = rng.uniform(0.5, 0.9) * max(reach, 0.6)
    azimuth = math.pi + rng.uniform(-0.6, 0.6)  # the camera faces the arm from the front
    elevation = math.radians(rng.uniform(10, 35))
    eye = look + distance * np.array([math.cos(elevation) * math.cos(azimuth),
                                      math.cos(elevation) * math.sin(azimuth),
                                      math.sin(elevation)])
    z = (look - eye) / np.linalg.norm(look - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    roll = math.radians(rng.uniform(-4, 4))
    x = math.cos(roll) * x + math.sin(roll) * np.cross(z, x)
    R_cam = np.column_stack([x, np.cross(z, x), z])
    head = {"mount": "fixed", "fixed_xyz_mm": (1000 * eye).round(1).tolist(),
            "fixed_rpy_deg": _rpy_of(R_cam)}
    square = target["square_mm"] * rng.uniform(0.55, 0.75)
    rows, cols = int(rng.integers(5, 8)), int(rng.integers(6, 9))
    # board z (into the board) along -flange z: the board faces away from the flange
    R = rpy_matrix([180.0 + rng.normal(0, 2), rng.normal(0, 2), rng.uniform(-180, 180)])
    half = np.array([cols * square / 2, rows * square / 2, 0.0]) / 1000.0
    origin = np.array([*rng.uniform(-0.01, 0.01, 2), rng.uniform(0.01, 0.04)]) - R @ half
    board = {**{k: v for k, v in target.items() if k not in ("xyz_mm", "rpy_deg")},
             "rows": rows, "cols": cols, "square_mm": round(square, 2), "mount": "flange",
             "xyz_mm": (1000 * origin).round(1).tolist(), "rpy_deg": _rpy_of(R)}
    if board.get("type") == "charuco":
        board["marker_mm"] = round(square * board["marker_mm"] / target["square_mm"], 2)
    return head, board


def random_world(seed: int, target: str = "checkerboard", mount: str = "flange") -> dict:
    """One plausible rig drawn from ``seed`` (deterministic), as world-file data.
    ``target``: "checkerboard", "charuco" (the same board's squares and place, with
    markers drawn from a stream of their own: the rest of the world is the seed's
    checkerboard world), or "either" (one of them, drawn from that stream too).
    ``mount``: "flange" (the head on the flange, the board in the world), "fixed" (the
    head beside the arm, the board on the flange: ``_eye_to_hand``, drawn from a stream
    of its own), or "either" (one of them, drawn from that stream too)."""
    rng = np.random.default_rng([seed, 20261123])
    model = _arm_model(seed, rng)
    near = rng.uniform(0.6, 2.0)  # the nearest scene shapes, metres from the camera
    cam = _camera(rng)
    # the scene fills the view (a lab has texture everywhere), whatever the lens
    cone = min(75.0, 1.3 * math.degrees(math.atan(math.hypot(cam["width"], cam["height"]) / 2
                                                  / cam["fx"])))
    data = {
        "seed": int(seed),
        "camera": cam,
        "head": {"mount": "flange",
                 "roll_axis_tilt_deg": np.round(_within(rng, 0.5, 2), 4).tolist(),
                 "camera_offset_mm": np.round(_within(rng, 3.0, 3), 3).tolist(),
                 **_head_servos(np.random.default_rng([seed, 40]))},
        "arm": {"model": model, "home_deg": [0.0, -90.0, 90.0, -90.0, -90.0, 0.0],
                "errors": (errors := _arm_errors(rng)),
                # drawn from its own stream: every other draw of a seed stays as it was
                "factory_errors": _factory_errors(np.random.default_rng([seed, 15]), errors)},
        "hand_eye": {"xyz_mm": np.round([*rng.uniform(-30, 30, 2), rng.uniform(30, 90)],
                                        1).tolist(),
                     "rpy_deg": np.round([*_within(rng, 4.0, 2), rng.uniform(-180, 180)],
                                         3).tolist()},
        "target": _target(rng, model),
        "scene": {"depth_m": [round(near, 2), round(near * rng.uniform(2, 5), 2)],
                  "shapes": int(rng.integers(30, 60)), "cone_deg": round(cone, 1)},
    }
    own = np.random.default_rng([seed, 41])  # the target type's draws: nothing else moves
    if target == "either":
        target = ("checkerboard", "charuco")[own.integers(2)]
    if target == "charuco":
        data["target"] = _charuco(own, data["target"])
    elif target != "checkerboard":
        raise ValueError(f"target {target!r}: expected checkerboard, charuco or either")
    mounting = np.random.default_rng([seed, 43])  # the mounting's draws: nothing else moves
    if mount == "either":
        mount = ("flange", "fixed")[mounting.integers(2)]
    if mount == "fixed":
        head, data["target"] = _eye_to_hand(mounting, model, data["target"])
        data["head"].update(head)
    elif mount != "flange":
        raise ValueError(f"mount {mount!r}: expected flange, fixed or either")
    WorldFile.model_validate(data)
    return data
