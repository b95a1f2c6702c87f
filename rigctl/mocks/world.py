"""The simulated rig's ground truth, and the renderer of what its camera sees.

The world file (YAML) is documented key by key in ``rigctl/mocks/worlds/README.md``. This module
is the simulator's forward model: projection and distortion by OpenCV's
``projectPoints``, arm kinematics by ``rigctl.mocks.ur_kinematics``. It shares no code with the
solvers in ``rigctl.calib`` / ``rigctl.geometry``, so a bug cannot hide in both.

Frames (``T_a_b`` maps points of b into a): ``base`` (arm base = world), ``flange``,
``head`` (head mount), ``cam`` (optical: z forward, x right, y down), ``target``.
Head motion: ``T_head_cam = Ry(pan) Rx(tilt) R_axis(roll) T(offset)``, where the roll
axis is the camera z axis tilted by ``roll_axis_tilt_deg`` (about camera x, then y).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from rigctl.errors import ConfigError
from rigctl.mocks.ur_kinematics import ArmModel
from rigctl.mocks.view_clip import clip_to_view

WORLDS = Path(__file__).resolve().parent / "worlds"
# The renderer fills polygons at this many samples per pixel side and averages them (area
# sampling): OpenCV's anti-aliased fill drew every shape about 0.65 px larger than its
# outline, with 0.18 px RMS of orientation-dependent ripple along the edges.
SUPERSAMPLE = 4
NEAR_M = 0.02  # nothing nearer the camera is drawn


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CameraTruth(_Strict):
    width: int = Field(1280, gt=0, description="image width, pixels")
    height: int = Field(720, gt=0, description="image height, pixels")
    fx: float = Field(900.0, gt=0, description="focal length along x, pixels")
    fy: float = Field(905.0, gt=0, description="focal length along y, pixels")
    cx: float = Field(652.3, description="principal point x, pixels")
    cy: float = Field(371.8, description="principal point y, pixels")
    distortion: list[float] = Field(default_factory=lambda: [0.0] * 5, description="[k1, k2, p1, "
                                    "p2, k3], OpenCV's convention")
    pixel_noise: float = Field(0.5, ge=0, description="sigma of additive Gaussian noise, grey "
                               "levels")
    jpeg_quality: int = Field(95, ge=10, le=100, description="quality of the MJPEG frames")
    fps: float = Field(15.0, gt=0, le=120, description="frame rate of the stream")
    blur_sigma: float = Field(0.6, ge=0, description="Gaussian blur (optics), pixels")

    @field_validator("distortion")
    @classmethod
    def _five(cls, v: list[float]) -> list[float]:
        if len(v) != 5:
            raise ValueError(f"expected [k1, k2, p1, p2, k3], got {len(v)} values")
        return v


class HeadTruth(_Strict):
    mount: Literal["flange", "fixed"] = Field("flange", description="flange (head on the arm's "
                                              "flange through hand_eye) or fixed")
    roll_axis_tilt_deg: list[float] = Field(default_factory=lambda: [0.0, 0.0], description="the "
                                            "roll axis is the camera z axis tilted about camera x, "
                                            "then y, degrees")
    camera_offset_mm: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, 0.0],
        description="centre of projection off the rotation axes, in the camera frame, millimetres")
    encoder_noise_deg: float = Field(0.0, ge=0, description="sigma of the head encoder readings, "
                                     "degrees")
    fixed_xyz_mm: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, 500.0],
        description="T_base_head translation when mount is fixed, millimetres")
    fixed_rpy_deg: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, 0.0],
        description="T_base_head rotation [roll, pitch, yaw] when mount is fixed, degrees")
    # pan, tilt, roll servo models the bus stand-in plays (its own tables, dxl_models);
    # encoder "hardware": the true angle continuous, readings quantized to the model's
    # pulse with its noise; "ideal": every move ends on its goal pulse, read exactly
    models: list[str] = Field(default_factory=lambda: ["xm430-w350"] * 3, description="pan, tilt, "
                              "roll servo models the bus stand-in plays")
    encoder: Literal["ideal", "hardware"] = Field("ideal", description="ideal (moves end on the "
                                                  "goal pulse, read exactly) or hardware (the true "
                                                  "angle continuous, readings quantized to the "
                                                  "model's pulse with its noise)")

    @field_validator("models")
    @classmethod
    def _known_models(cls, value: list[str]) -> list[str]:
        from rigctl.mocks.dxl_models import SPEC_BY_NAME

        if len(value) != 3:
            raise ValueError(f"expected [pan, tilt, roll] servo models, got {len(value)}")
        for name in value:
            if name not in SPEC_BY_NAME:
                raise ValueError(f"unknown servo model {name!r}; known: "
                                 f"{', '.join(sorted(SPEC_BY_NAME))}")
        return value


class ArmErrors(_Strict):
    theta_deg: list[float] = Field(default_factory=lambda: [0.0] * 6, description="encoder offsets "
                                   "per joint: true joint angle = reading + offset, degrees")
    d_mm: list[float] = Field(default_factory=lambda: [0.0] * 6, description="DH d deviations from "
                              "nominal, per link, millimetres")
    a_mm: list[float] = Field(default_factory=lambda: [0.0] * 6, description="DH a deviations from "
                              "nominal, per link, millimetres")
    alpha_deg: list[float] = Field(default_factory=lambda: [0.0] * 6, description="DH alpha "
                                   "deviations from nominal, per link, degrees")
    beta_deg: list[float] = Field(default_factory=lambda: [0.0] * 6, description="Hayati rotation "
                                  "about y, per link, degrees")


class FactoryErrors(_Strict):
    """What the controller believes (its factory calibration), as errors from nominal.
    Plain DH: a UR controller's kinematics have no beta."""

    theta_deg: list[float] = Field(default_factory=lambda: [0.0] * 6, description="the "
                                   "controller's encoder offsets per joint, degrees")
    d_mm: list[float] = Field(default_factory=lambda: [0.0] * 6, description="the controller's d "
                              "deviations from nominal, millimetres")
    a_mm: list[float] = Field(default_factory=lambda: [0.0] * 6, description="the controller's a "
                              "deviations from nominal, millimetres")
    alpha_deg: list[float] = Field(default_factory=lambda: [0.0] * 6, description="the "
                                   "controller's alpha deviations from nominal, degrees")


class ArmTruth(_Strict):
    model: str = Field("ur5e", description="the arm's model, as ur_description spells it")

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        from rigctl.mocks.ur_models import MODEL_NAMES

        if value not in MODEL_NAMES:
            raise ValueError(f"unknown UR model {value!r}; known: {', '.join(MODEL_NAMES)}")
        return value

    home_deg: list[float] = Field(
        default_factory=lambda: [0.0, -90.0, 90.0, -90.0, -90.0, 0.0],
        description="joints at start, degrees; the scene is laid out around the camera at this "
        "pose")
    errors: ArmErrors = Field(ArmErrors(), description="the true arm's deviations from the nominal "
                              "model")
    factory_errors: FactoryErrors | None = Field(None, description="what the controller believes "
                                                 "(its factory calibration), as deviations from "
                                                 "nominal; plain DH, no beta. Null: the controller "
                                                 "uses nominal")


class PoseTruth(_Strict):
    xyz_mm: list[float] = Field(default_factory=lambda: [0.0, 0.0, 50.0], description="translation "
                                "[x, y, z], millimetres")
    rpy_deg: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0], description="rotation "
                                 "[roll, pitch, yaw], degrees: Rz(yaw) Ry(pitch) Rx(roll)")


class TargetTruth(_Strict):
    type: Literal["checkerboard", "charuco"] = Field(
        "checkerboard", description="checkerboard, or charuco (a ChArUco board: needs "
        "dictionary and marker_mm)")
    rows: int = Field(7, ge=3, description="squares of the board along its rows direction "
                      "(a checkerboard's inner corners: rows - 1)")
    cols: int = Field(10, ge=3, description="squares along its columns direction (inner corners: "
                      "cols - 1)")
    square_mm: float = Field(30.0, gt=0, description="square size, millimetres")
    dictionary: str | None = Field(None, description="ChArUco only: OpenCV's name of the "
                                   "markers' dictionary, e.g. DICT_5X5_100")
    marker_mm: float | None = Field(None, gt=0, description="ChArUco only: a marker's side, "
                                    "millimetres")
    legacy_pattern: bool = Field(False, description="ChArUco only: OpenCV's layout before 4.6")
    mount: Literal["world", "flange"] = Field(
        "world", description="world (the board stands still; xyz_mm, rpy_deg are T_base_target) "
        "or flange (the arm's flange holds it; they are T_flange_target)")
    xyz_mm: list[float] = Field(
        default_factory=lambda: [600.0, 0.0, 0.0],
        description="T_base_target translation (T_flange_target with mount: flange), "
        "millimetres; the target frame is at the outer board corner")
    rpy_deg: list[float] = Field(
        default_factory=lambda: [180.0, 0.0, 0.0],
        description="T_base_target rotation (T_flange_target with mount: flange) [roll, pitch, "
        "yaw], degrees; x along columns, y along rows, z into the board")

    @field_validator("dictionary")
    @classmethod
    def _known_dictionary(cls, value: str | None) -> str | None:
        names = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        if value is not None and value not in names:
            raise ValueError(f"unknown ArUco dictionary {value!r}; known: {', '.join(names)}")
        return value

    @model_validator(mode="after")
    def _charuco_keys(self) -> TargetTruth:
        if self.type == "charuco":
            if self.dictionary is None or self.marker_mm is None:
                raise ValueError("a ChArUco target (type: charuco) needs dictionary and "
                                 "marker_mm")
            if self.marker_mm >= self.square_mm:
                raise ValueError(f"marker_mm {self.marker_mm:g} must be below square_mm "
                                 f"{self.square_mm:g}")
            have = _dictionary(self.dictionary).bytesList.shape[0]
            if self.rows * self.cols // 2 > have:
                raise ValueError(f"{self.dictionary} has {have} markers; a board of "
                                 f"{self.rows} x {self.cols} squares needs "
                                 f"{self.rows * self.cols // 2}")
        elif self.dictionary is not None or self.marker_mm is not None:
            raise ValueError("dictionary and marker_mm are keys of a ChArUco target "
                             "(type: charuco)")
        return self


def _dictionary(name: str):
    """OpenCV's predefined ArUco dictionary ``name`` (its marker bits)."""
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


class SceneTruth(_Strict):
    depth_m: list[float] = Field(default_factory=lambda: [1.5, 6.0], description="depth range of "
                                 "the planar scene shapes from the camera at home, metres")
    shapes: int = Field(40, ge=0, le=500, description="how many shapes (rectangles, triangles, "
                        "ellipses)")
    cone_deg: float = Field(40.0, gt=0, le=80, description="half-angle of the cone around the home "
                            "optical axis where shapes lie, degrees")


class WorldFile(_Strict):
    seed: int = Field(1, description="seeds the scene layout and the per-frame pixel noise")
    camera: CameraTruth = Field(CameraTruth(), description="the camera's true intrinsics and image "
                                "quality")
    head: HeadTruth = Field(HeadTruth(), description="the head's true geometry and servos")
    arm: ArmTruth = Field(ArmTruth(), description="the true arm and what its controller believes")
    hand_eye: PoseTruth = Field(PoseTruth(), description="T_flange_head, the head on the arm's "
                                "flange")
    target: TargetTruth = Field(TargetTruth(), description="the checkerboard and its true pose")
    scene: SceneTruth = Field(SceneTruth(), description="the planar shapes the active-camera "
                              "calibration tracks")

    @model_validator(mode="after")
    def _mountings(self) -> WorldFile:
        if self.head.mount == "flange" and self.target.mount == "flange":
            raise ValueError("head.mount: flange with target.mount: flange: the camera and the "
                             "board both ride the flange, so no arm motion moves one against "
                             "the other; stand the head beside the arm (head.mount: fixed) or "
                             "the board in the world (target.mount: world)")
        return self


def rpy_matrix(rpy_deg) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) from [roll, pitch, yaw] in degrees."""
    r, p, y = np.radians(rpy_deg)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def transform(R=None, t=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def axis_angle(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def world_file(world: str | Path) -> Path:
    """A world file: a path (``.yaml``/``.yml``, or any existing file), or the name of
    one shipped with the package in ``rigctl/mocks/worlds`` ("default", "ideal", ...).
    ``ConfigError`` names the shipped worlds when neither fits."""
    path = Path(world)
    if path.suffix in (".yaml", ".yml") or path.exists():
        return path.resolve()
    shipped = WORLDS / f"{world}.yaml"
    if shipped.exists():
        return shipped
    names = ", ".join(sorted(p.stem for p in WORLDS.glob("*.yaml")))
    raise ConfigError(f"world {world!r}: no such file, and no shipped world of that name "
                      f"(shipped: {names})")


def load_world(path: str | Path) -> World:
    """The world of a file path or a shipped world's name (``world_file``)."""
    path = world_file(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{path}: world file not found") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path.name}: not valid YAML: {exc}") from None
    try:
        spec = WorldFile.model_validate(data)
    except ValidationError as exc:
        lines = [f"{path.name}: {'.'.join(map(str, e['loc']))}: "
                 f"{e['msg'].removeprefix('Value error, ')}" for e in exc.errors()]
        raise ConfigError("\n".join(lines)) from None
    return World(spec, path)


class World:
    """Ground truth: camera, head, arm, hand-eye, target and scene."""

    def __init__(self, spec: WorldFile, path: Path | None = None) -> None:
        self.spec, self.path = spec, path
        cam = spec.camera
        self.K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
        self.dist = np.array(cam.distortion, float)
        self.size = (cam.width, cam.height)
        self.arm_true = ArmModel.nominal(spec.arm.model).with_errors(**spec.arm.errors.model_dump())
        tx, ty = np.radians(spec.head.roll_axis_tilt_deg)
        self.roll_axis = axis_angle([1, 0, 0], tx) @ axis_angle([0, 1, 0], ty) @ [0, 0, 1.0]
        self.cam_offset = np.array(spec.head.camera_offset_mm) / 1000.0
        he = spec.hand_eye
        self.T_flange_head = transform(rpy_matrix(he.rpy_deg), np.array(he.xyz_mm) / 1000.0)
        self.T_base_head_fixed = transform(rpy_matrix(spec.head.fixed_rpy_deg),
                                           np.array(spec.head.fixed_xyz_mm) / 1000.0)
        tg = spec.target
        # T_base_target for a board in the world; T_flange_target for one on the flange
        self.T_mount_target = transform(rpy_matrix(tg.rpy_deg), np.array(tg.xyz_mm) / 1000.0)
        self.target_on_flange = tg.mount == "flange"
        self.T_base_target = self.T_base_target_at(np.radians(spec.arm.home_deg))
        self.home_q = np.radians(spec.arm.home_deg)
        self._scene = self._make_scene()
        self._board = self._make_board()

    # -- kinematic chain -------------------------------------------------------------

    def T_head_cam(self, pan: float, tilt: float, roll: float) -> np.ndarray:
        R = axis_angle([0, 1, 0], pan) @ axis_angle([1, 0, 0], tilt) @ \
            axis_angle(self.roll_axis, roll)
        return transform(R) @ transform(None, self.cam_offset)

    def T_base_head(self, q) -> np.ndarray:
        if self.spec.head.mount == "fixed":
            return self.T_base_head_fixed
        return self.arm_true.flange(q) @ self.T_flange_head

    def T_base_cam(self, q, head_angles) -> np.ndarray:
        return self.T_base_head(q) @ self.T_head_cam(*head_angles)

    def T_base_target_at(self, q) -> np.ndarray:
        """The board's pose at joints ``q``: fixed in the world, or carried by the flange."""
        if self.target_on_flange:
            return self.arm_true.flange(q) @ self.T_mount_target
        return self.T_mount_target

    # -- objects ---------------------------------------------------------------------

    def target_corners(self) -> np.ndarray:
        """Inner corners in the target frame, row-major ((rows-1) x (cols-1), metres)."""
        s = self.spec.target.square_mm / 1000.0
        rows, cols = self.spec.target.rows, self.spec.target.cols
        return np.array([[(j + 1) * s, (i + 1) * s, 0.0]
                         for i in range(rows - 1) for j in range(cols - 1)])

    @staticmethod
    def _polygon(corners: np.ndarray, per_edge: int) -> np.ndarray:
        pts = []
        for k in range(len(corners)):
            a, b = corners[k], corners[(k + 1) % len(corners)]
            for f in np.linspace(0, 1, per_edge, endpoint=False):
                pts.append(a + f * (b - a))
        return np.array(pts)

    def _make_board(self) -> list[tuple[np.ndarray, int]]:
        s = self.spec.target.square_mm / 1000.0
        rows, cols = self.spec.target.rows, self.spec.target.cols
        T = self.T_base_target
        items = []
        margin = s
        outline = np.array([[-margin, -margin, 0], [cols * s + margin, -margin, 0],
                            [cols * s + margin, rows * s + margin, 0],
                            [-margin, rows * s + margin, 0]])
        items.append((self._polygon(outline, 16), 235))
        tg = self.spec.target
        # a ChArUco board printed by OpenCV before 4.6 with an even number of rows starts
        # with a white square (opencv/opencv issue 23152); every other board with a black
        dark = 1 if tg.type == "charuco" and tg.legacy_pattern and rows % 2 == 0 else 0
        marker = 0
        for i in range(rows):
            for j in range(cols):
                if (i + j) % 2 == dark:
                    sq = np.array([[j * s, i * s, 0], [(j + 1) * s, i * s, 0],
                                   [(j + 1) * s, (i + 1) * s, 0], [j * s, (i + 1) * s, 0]])
                    items.append((self._polygon(sq, 4), 20))
                elif tg.type == "charuco":  # white squares carry the markers, row by row
                    items += self._marker(marker, j * s, i * s)
                    marker += 1
        return [((T[:3, :3] @ pts.T).T + T[:3, 3], shade) for pts, shade in items]

    def board_at(self, q) -> list[tuple[np.ndarray, int]]:
        """The board's polygons in the base frame at joints ``q`` (a board on the flange
        moves with it; one in the world is where it was built)."""
        if not self.target_on_flange or q is None:
            return self._board
        T = self.T_base_target_at(q) @ np.linalg.inv(self.T_base_target)
        return [((T[:3, :3] @ pts.T).T + T[:3, 3], shade) for pts, shade in self._board]

    def _marker(self, marker_id: int, x0: float, y0: float) -> list[tuple[np.ndarray, int]]:
        """ArUco marker ``marker_id`` centred in the square at (x0, y0) (target frame,
        metres): a black square of ``marker_mm``, then a white cell for each 1 bit of the
        dictionary's code (a run of white cells in a row as one polygon), one black cell
        of border around them; the marker's bit rows run along the board's y."""
        tg = self.spec.target
        d = _dictionary(tg.dictionary)
        bits = cv2.aruco.Dictionary.getBitsFromByteList(d.bytesList[marker_id:marker_id + 1],
                                                       d.markerSize)
        side = tg.marker_mm / 1000.0
        cell = side / (d.markerSize + 2)
        left = x0 + (tg.square_mm / 1000.0 - side) / 2
        top = y0 + (tg.square_mm / 1000.0 - side) / 2

        def rect(x_a, y_a, x_b, y_b, per_edge):
            return self._polygon(np.array([[x_a, y_a, 0], [x_b, y_a, 0], [x_b, y_b, 0],
                                           [x_a, y_b, 0]]), per_edge)

        items = [(rect(left, top, left + side, top + side, 4), 20)]
        for r in range(d.markerSize):
            row = np.r_[0, bits[r].astype(int), 0]
            starts = np.flatnonzero(np.diff(row) == 1)
            ends = np.flatnonzero(np.diff(row) == -1)
            for a, b in zip(starts, ends, strict=True):
                items.append((rect(left + (a + 1) * cell, top + (r + 1) * cell,
                                   left + (b + 1) * cell, top + (r + 2) * cell, 2), 235))
        return items

    def scene_shapes(self) -> list[np.ndarray]:
        """The scene's planar shapes: each one's outline points in the base frame (m), as
        drawn (the truth a benchmark holds contours against)."""
        return [pts.copy() for pts, _ in self._scene]

    def _make_scene(self) -> list[tuple[np.ndarray, int]]:
        """Planar shapes at random directions and depths around the camera at home."""
        rng = np.random.default_rng(self.spec.seed)
        sc = self.spec.scene
        T_home = self.T_base_cam(self.home_q, (0.0, 0.0, 0.0))
        shapes = []
        for _ in range(sc.shapes):
            depth = rng.uniform(*sc.depth_m)
            theta = math.radians(sc.cone_deg) * math.sqrt(rng.uniform())
            phi = rng.uniform(0, 2 * math.pi)
            direction = np.array([math.sin(theta) * math.cos(phi),
                                  math.sin(theta) * math.sin(phi), math.cos(theta)])
            centre = direction * depth
            size = depth * rng.uniform(0.04, 0.10)
            kind = rng.integers(3)
            if kind == 0:  # rectangle
                w, h = size, size * rng.uniform(0.5, 1.5)
                local = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
                local = self._polygon(np.c_[local, np.zeros(4)], 8)[:, :2]
            elif kind == 1:  # triangle
                ang = rng.uniform(0, 2 * math.pi) + np.array([0, 2.1, 4.2])
                local = np.c_[np.cos(ang), np.sin(ang)] * size / 1.5
                local = self._polygon(np.c_[local, np.zeros(3)], 10)[:, :2]
            else:  # ellipse
                t = np.linspace(0, 2 * math.pi, 48, endpoint=False)
                local = np.c_[np.cos(t) * size / 2, np.sin(t) * size / 2 * rng.uniform(0.5, 1)]
            # plane facing the camera, tilted by up to 25 deg
            normal = -direction
            tilt = axis_angle(rng.normal(size=3), math.radians(rng.uniform(0, 25)))
            normal = tilt @ normal
            u = np.cross(normal, [0.3, 1.0, 0.1])
            u /= np.linalg.norm(u)
            v = np.cross(normal, u)
            spin = rng.uniform(0, 2 * math.pi)
            u, v = math.cos(spin) * u + math.sin(spin) * v, -math.sin(spin) * u + math.cos(spin) * v
            pts_cam = centre + local[:, :1] * u + local[:, 1:2] * v
            pts = (T_home[:3, :3] @ pts_cam.T).T + T_home[:3, 3]
            shade = int(rng.choice([rng.uniform(15, 70), rng.uniform(180, 245)]))
            shapes.append((pts, shade))
        return shapes

    # -- rendering -------------------------------------------------------------------

    def project(self, points_base: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates of base-frame points (OpenCV projectPoints, with distortion)."""
        T_cam_base = np.linalg.inv(T_base_cam)
        rvec, _ = cv2.Rodrigues(T_cam_base[:3, :3])
        px, _ = cv2.projectPoints(points_base.reshape(-1, 1, 3), rvec, T_cam_base[:3, 3],
                                  self.K, self.dist)
        return px.reshape(-1, 2)

    def target_corner_pixels(self, T_base_cam: np.ndarray, q=None) -> np.ndarray:
        corners = self.target_corners()
        T = self.T_base_target if q is None else self.T_base_target_at(q)
        pts = (T[:3, :3] @ corners.T).T + T[:3, 3]
        return self.project(pts, T_base_cam)

    def render(self, T_base_cam: np.ndarray, frame_index: int = 0,
               noise: bool = True, supersample: int = SUPERSAMPLE, q=None) -> np.ndarray:
        """An 8-bit grey image of what the camera sees (before JPEG); each pixel the mean
        of ``supersample``^2 samples (1: no anti-aliasing, for frames taken in motion).
        ``q``: the arm's joints, where a board on the flange is (the home pose when None)."""
        w, h = self.size
        img = np.full((h * supersample, w * supersample), 118, np.uint8)
        T_cam_base = np.linalg.inv(T_base_cam)
        R, t = T_cam_base[:3, :3], T_cam_base[:3, 3]
        limit_x = 1.3 * max(self.K[0, 2], w - self.K[0, 2]) / self.K[0, 0]
        limit_y = 1.3 * max(self.K[1, 2], h - self.K[1, 2]) / self.K[1, 1]
        # Groups are painted far to near; the board is one group (outline, then squares).
        groups = [[item] for item in self._scene] + [self.board_at(q)]
        drawables = []
        for group in groups:
            cam_polys = []
            for pts, shade in group:
                # cut away what is behind the camera, or where distortion folds back
                pc = clip_to_view((R @ pts.T).T + t, 2 * limit_x, 2 * limit_y, NEAR_M)
                if len(pc) == 0:
                    continue
                xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
                if np.all(np.abs(xn) > limit_x) or np.all(np.abs(yn) > limit_y):
                    continue
                cam_polys.append((pc, shade))
            if cam_polys:
                drawables.append((float(np.mean(cam_polys[0][0][:, 2])), cam_polys))
        drawables.sort(key=lambda d: -d[0])
        polys = [p for _, group in drawables for p in group]
        if polys:
            allpts = np.concatenate([pc for pc, _ in polys])
            px, _ = cv2.projectPoints(allpts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                      self.K, self.dist)
            px = px.reshape(-1, 2)
            start = 0
            for pc, shade in polys:
                poly = px[start:start + len(pc)]
                start += len(pc)
                # pixel centres at integer coordinates, at the supersampled resolution;
                # shift=4 is 1/16 of a supersampled pixel
                fine = (poly + 0.5) * supersample - 0.5
                fixed = np.round(fine * 16).astype(np.int32)
                cv2.fillPoly(img, [fixed], int(shade), lineType=cv2.LINE_8, shift=4)
        # each pixel the mean of its supersample^2 samples: the light its area receives
        if supersample > 1:
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        cam = self.spec.camera
        if cam.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), cam.blur_sigma)
        if noise and cam.pixel_noise > 0:
            rng = np.random.default_rng(self.spec.seed * 1_000_003 + frame_index)
            noisy = img.astype(np.float32) + rng.standard_normal(img.shape, np.float32) * \
                cam.pixel_noise
            img = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
        return img

    # -- truth report ----------------------------------------------------------------

    def truth(self) -> dict:
        cam = self.spec.camera
        T_flange_cam = self.T_flange_head @ self.T_head_cam(0.0, 0.0, 0.0)
        links = [{"theta_offset": float(self.arm_true.theta_offset[i]),
                  "d": float(self.arm_true.d[i]), "a": float(self.arm_true.a[i]),
                  "alpha": float(self.arm_true.alpha[i]), "beta": float(self.arm_true.beta[i])}
                 for i in range(6)]
        return {
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "width": cam.width, "height": cam.height, "distortion": list(cam.distortion),
            "roll_axis_in_cam": self.roll_axis.tolist(),
            "camera_offset_m": self.cam_offset.tolist(),
            "arm": {"model": self.spec.arm.model,
                    "convention": "A_i = Rz(theta_i + theta_offset) Tz(d) Tx(a) Rx(alpha) Ry(beta)",
                    "units": {"length": "m", "angle": "rad"}, "links": links,
                    "T_base_link0": np.eye(4).tolist()},
            "head_mount": self.spec.head.mount,
            "target_mount": self.spec.target.mount,
            **({"T_base_cam": (self.T_base_head_fixed @ self.T_head_cam(0.0, 0.0, 0.0)).tolist(),
                "T_flange_target": self.T_mount_target.tolist()}
               if self.spec.head.mount == "fixed" else {}),
            "T_flange_cam": T_flange_cam.tolist(),
            "T_base_target": self.T_base_target.tolist(),
            "target": {"rows": self.spec.target.rows, "cols": self.spec.target.cols,
                       "square_m": self.spec.target.square_mm / 1000.0,
                       "type": self.spec.target.type,
                       **({"dictionary": self.spec.target.dictionary,
                           "marker_m": self.spec.target.marker_mm / 1000.0,
                           "legacy_pattern": self.spec.target.legacy_pattern}
                          if self.spec.target.type == "charuco" else {})},
        }
