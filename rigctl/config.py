"""The rig file: a YAML description of the devices, records, procedures and service.

Validated with pydantic. Degrees and millimetres live here, at the edge; the
``*_rad`` helpers convert once. Every error names the file, the key path and the
reason, e.g. ``rig.yaml: devices.head.limits.pan: max 200 deg exceeds the servo
range of 180 deg``.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from rigctl.errors import ConfigError
from rigctl.redaction import redact_rig_text

HEAD_AXES = ("pan", "tilt", "roll")
SERVO_RANGE_DEG = 180.0  # position mode: 4096 pulses over one turn, centred at 2048
UR_JOINT_RANGE_DEG = 363.0  # UR joints turn +-363 deg (controller software limit)
MAX_RETRY_BUDGET_S = 5.0  # one head bus transaction, all retries included


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _check_range(value: list[float], limit: float) -> list[float]:
    if len(value) != 2:
        raise ValueError("expected [min, max]")
    lo, hi = float(value[0]), float(value[1])
    if lo >= hi:
        raise ValueError(f"min {lo:g} deg must be below max {hi:g} deg")
    if hi > limit:
        raise ValueError(f"max {hi:g} deg exceeds the servo range of {limit:g} deg")
    if lo < -limit:
        raise ValueError(f"min {lo:g} deg exceeds the servo range of -{limit:g} deg")
    return [lo, hi]


class HeadLimits(_Strict):
    """Soft limits per axis, degrees, in the head's own (offset and direction applied) frame."""

    pan: list[float] = Field([-90.0, 90.0], description="[min, max] soft limits of pan, degrees; "
                             "every planned move is checked before anything moves")
    tilt: list[float] = Field([-45.0, 45.0], description="[min, max] soft limits of tilt, degrees")
    roll: list[float] = Field([-180.0, 180.0], description="[min, max] soft limits of roll, "
                              "degrees")

    @field_validator("pan", "tilt", "roll")
    @classmethod
    def _in_servo_range(cls, value: list[float]) -> list[float]:
        return _check_range(value, SERVO_RANGE_DEG)


class AxisMap(_Strict):
    pan: int = Field(1, description="Dynamixel ID of the pan servo")
    tilt: int = Field(2, description="Dynamixel ID of the tilt servo")
    roll: int = Field(3, description="Dynamixel ID of the roll servo")


class AxisFloat(_Strict):
    pan: float = Field(0.0, description="pan, degrees")
    tilt: float = Field(0.0, description="tilt, degrees")
    roll: float = Field(0.0, description="roll, degrees")


class AxisSign(_Strict):
    pan: Literal[1, -1] = Field(1, description="1 or -1: the pan servo's direction")
    tilt: Literal[1, -1] = Field(1, description="1 or -1: the tilt servo's direction")
    roll: Literal[1, -1] = Field(1, description="1 or -1: the roll servo's direction")


class AxisModel(_Strict):
    pan: str | None = Field(None, description="servo model of the pan axis (null: read from the "
                            "servo)")
    tilt: str | None = Field(None, description="servo model of the tilt axis (null: read from the "
                             "servo)")
    roll: str | None = Field(None, description="servo model of the roll axis (null: read from the "
                             "servo)")


def _known_servo(value: str | None) -> str | None:
    from rigctl.drivers.dynamixel_models import MODEL_NAMES

    if value is not None and value.lower() not in MODEL_NAMES:
        raise ValueError(f"unknown servo model {value!r}; known: {', '.join(MODEL_NAMES)}")
    return value.lower() if value is not None else None


class HeadPark(_Strict):
    policy: Literal["hold", "home", "torque_off", "home_then_torque_off"] = Field(
        "home", description="what the head does when a run ends or stops: hold, home, "
        "torque_off or home_then_torque_off")
    angles_deg: list[float] = Field([0.0, 0.0, 0.0], description="where home parks it: [pan, tilt, "
                                    "roll], degrees")


class MountPose(_Strict):
    """A nominal transform, mm and degrees (rpy = Rz(yaw) Ry(pitch) Rx(roll))."""

    xyz_mm: list[float] = Field(default_factory=lambda: [0.0, 0.0, 50.0], description="translation "
                                "[x, y, z], millimetres")
    rpy_deg: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0], description="rotation "
                                 "[roll, pitch, yaw], degrees: Rz(yaw) Ry(pitch) Rx(roll)")

    @field_validator("xyz_mm", "rpy_deg")
    @classmethod
    def _three(cls, value: list[float]) -> list[float]:
        if len(value) != 3:
            raise ValueError(f"expected 3 values, got {len(value)}")
        return value


class HeadConfig(_Strict):
    port: str = Field(description="serial port of the servo bus: the U2D2 (/dev/ttyUSB0, or a "
                      "/dev/serial/by-id/ path)")
    mount: MountPose | Literal["flange", "fixed"] = Field(
        MountPose(), description="nominal T_flange_head (the head on the arm's flange), for "
        "planning views; or fixed: the head stands beside the arm (eye-to-hand) at fixed_pose, "
        "watching a board held by the flange (target.mount: flange)")
    fixed_pose: MountPose | None = Field(None, description="mount fixed only: the approximate "
                                         "T_base_head, for planning views (the calibration "
                                         "estimates the camera's pose)")
    baud: int = Field(1_000_000, description="bus baud rate; every servo must be set to it")
    # One servo model for all axes, one per axis, or None: read from each servo when the
    # driver pings it. A named model that differs from the servo's refuses the run.
    model: str | AxisModel | None = Field(None, description="servo model for all axes, or per axis "
                                          "({pan, tilt, roll}); null: read from each servo. A "
                                          "named model that differs from the servo's refuses the "
                                          "run")
    ids: AxisMap = Field(AxisMap(), description="Dynamixel IDs of the pan, tilt and roll servos "
                         "(distinct, 0-252)")
    limits: HeadLimits = Field(HeadLimits(), description="soft limits per axis, degrees, in the "
                               "head's own frame (offset and direction applied)")
    zero_offset_deg: AxisFloat = Field(AxisFloat(), description="servo angle (degrees from the "
                                       "servo's centre) at the head's zero, per axis")
    direction: AxisSign = Field(AxisSign(), description="1 or -1 per axis: head angle = direction "
                                "* (servo angle - zero_offset_deg)")
    speed_cap_dps: float = Field(60.0, gt=0, le=300, description="top speed of every head move "
                                 "(Profile Velocity), degrees per second")
    accel_cap_dps2: float = Field(240.0, gt=0, le=5000, description="acceleration of every head "
                                  "move (Profile Acceleration), degrees per second squared")
    move_timeout_s: float = Field(15.0, gt=0, description="longest time one head move may take "
                                  "before it fails")
    settle_s: float | None = Field(None, ge=0, description="wait after a head move before a "
                                   "capture, seconds; a procedure that moves the head takes "
                                   "the longest wait of the devices it moves as its settle_s "
                                   "default; null: the procedure's own default")
    # Bus timing. ``packet_timeout_ms`` None keeps the SDK's own per-packet timeout (a few
    # ms plus twice the USB latency timer), right for servos that answer in microseconds;
    # a stand-in process on a loaded host needs a longer one. A failed transaction is
    # retried ``retries`` times, pausing ``retry_backoff_s`` before the first retry and
    # twice as long before each next one.
    packet_timeout_ms: float | None = Field(None, gt=0, le=2000, description="wait for one status "
                                            "packet, ms; null: the SDK's own (about 34 ms with a "
                                            "16 ms latency timer)")
    retries: int = Field(3, ge=0, le=10, description="retries of a failed bus transaction")
    retry_backoff_s: float = Field(0.0, ge=0, le=1.0, description="pause before the first retry, "
                                   "doubling before each next one, seconds")
    park: HeadPark = Field(HeadPark(), description="what the head does when a run ends or stops")

    @field_validator("baud")
    @classmethod
    def _supported_baud(cls, value: int) -> int:
        allowed = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000, 4_500_000)
        if value not in allowed:
            raise ValueError(f"{value} is not a Dynamixel baud rate (one of {allowed})")
        return value

    @field_validator("model")
    @classmethod
    def _known_models(cls, value):
        if isinstance(value, AxisModel):
            for axis in HEAD_AXES:
                setattr(value, axis, _known_servo(getattr(value, axis)))
            return value
        return _known_servo(value)

    def model_of(self, axis: str) -> str | None:
        """The servo model the rig file names for ``axis`` (None: read it from the servo)."""
        if isinstance(self.model, AxisModel):
            return getattr(self.model, axis)
        return self.model

    @model_validator(mode="after")
    def _fixed_pose_given(self) -> HeadConfig:
        if self.mount == "flange":
            self.mount = MountPose()
        if self.mount == "fixed" and self.fixed_pose is None:
            raise ValueError("mount: fixed needs fixed_pose, the approximate T_base_head "
                             "({xyz_mm: [...], rpy_deg: [...]}) the views are planned with")
        if self.mount != "fixed" and self.fixed_pose is not None:
            raise ValueError("fixed_pose is a key of a head standing beside the arm "
                             "(mount: fixed)")
        return self

    @property
    def fixed(self) -> bool:
        """True when the head stands beside the arm (``mount: fixed``)."""
        return self.mount == "fixed"

    @model_validator(mode="after")
    def _distinct_ids(self) -> HeadConfig:
        ids = [self.ids.pan, self.ids.tilt, self.ids.roll]
        if len(set(ids)) != 3:
            raise ValueError(f"ids: pan, tilt and roll need distinct servo IDs, got {ids}")
        if not all(0 <= i <= 252 for i in ids):
            raise ValueError(f"ids: servo IDs must be 0-252, got {ids}")
        return self

    @model_validator(mode="after")
    def _bounded_retry_budget(self) -> HeadConfig:
        budget = self.retry_budget_s()
        if budget > MAX_RETRY_BUDGET_S:
            raise ValueError(f"packet_timeout_ms, retries and retry_backoff_s allow {budget:.1f} s "
                             f"per transaction; keep it under {MAX_RETRY_BUDGET_S:g} s so a dead "
                             "servo is reported promptly")
        return self

    def retry_budget_s(self, sdk_timeout_ms: float = 34.0) -> float:
        """Longest time one bus transaction may take before it is reported as failed."""
        timeout_s = max(self.packet_timeout_ms or 0.0, sdk_timeout_ms) / 1000.0
        backoff = sum(self.retry_backoff_s * 2 ** i for i in range(self.retries))
        return (self.retries + 1) * timeout_s + backoff

    def limits_rad(self) -> dict[str, tuple[float, float]]:
        return {
            axis: (math.radians(getattr(self.limits, axis)[0]),
                   math.radians(getattr(self.limits, axis)[1]))
            for axis in HEAD_AXES
        }


class ArmPark(_Strict):
    policy: Literal["hold", "home"] = Field("hold", description="what the arm does when a run ends "
                                            "or stops: hold (stay) or home (move to joints_deg, "
                                            "else home_deg)")
    joints_deg: list[float] | None = Field(None, description="where home parks it, six joint "
                                           "angles in degrees; null: home_deg")


class ArmConfig(_Strict):
    host: str = Field("127.0.0.1", description="address of the UR controller (RTDE 30004, "
                      "dashboard 29999, primary 30001)")
    model: str = Field("ur5e", description="the arm's model as ur_description spells it (ur5e, "
                       "ur10e, ...); checked against what the controller reports")
    joint_limits_deg: list[list[float]] = Field(
        default_factory=lambda: [[-360.0, 360.0]] * 6,
        description="six [min, max] soft limits, degrees, within the model's own limits")
    home_deg: list[float] = Field([0.0, -90.0, 90.0, -90.0, -90.0, 0.0], description="the six "
                                  "joint angles of home, degrees: the start of every arm procedure")
    speed_cap_dps: float = Field(60.0, gt=0, le=180, description="top joint speed of moveJ, "
                                 "degrees per second")
    accel_cap_dps2: float = Field(80.0, gt=0, le=800, description="joint acceleration of moveJ, "
                                  "degrees per second squared")
    linear_speed_mm_s: float = Field(100.0, gt=0, le=1000, description="tool speed of moveL, "
                                     "millimetres per second")
    linear_accel_mm_s2: float = Field(300.0, gt=0, le=3000, description="tool acceleration of "
                                      "moveL, millimetres per second squared")
    move_timeout_s: float = Field(30.0, gt=0, description="longest time one arm move may take "
                                  "before it fails")
    settle_s: float | None = Field(None, ge=0, description="wait after an arm move before a "
                                   "capture, seconds; a procedure that moves the arm takes "
                                   "the longest wait of the devices it moves as its settle_s "
                                   "default; null: the procedure's own default")
    connect_retries: int = Field(3, ge=1, le=20, description="attempts to connect the RTDE "
                                 "interfaces")
    # A calibration reads the arm at rest and watches its moves for faults: 125 Hz (every
    # controller's rate; e-Series and UR-Series offer up to 500) costs the host and the
    # controller's RTDE link a fraction of 500 Hz's.
    rtde_frequency_hz: float = Field(125.0, ge=10, le=500, description="rate of the RTDE "
                                     "state stream, Hz: 10 to 125 on CB3, to 500 on e-Series "
                                     "and UR-Series")
    # The RTDE stream (rtde_frequency_hz) silent this long: connection lost. ur_rtde itself
    # drops the link after 2.5 s of silence (drivers.ur.UR_RTDE_READ_DEADLINE_S).
    stream_timeout_s: float = Field(1.0, gt=0, le=30, description="the RTDE stream silent this "
                                    "long means the connection is lost, seconds (ur_rtde "
                                    "itself drops the link after 2.5 s of silence, so a "
                                    "longer limit ends there)")
    # Bound on each teardown call (stopScript, stopJ) into ur_rtde.
    teardown_timeout_s: float = Field(3.0, gt=0, le=60, description="bound on each teardown call "
                                      "(stopScript, stopJ) into ur_rtde, seconds")
    # Reading the version and the controller's kinematics from the primary interface.
    primary_timeout_s: float = Field(5.0, gt=0, le=60, description="bound on reading the version "
                                     "and the controller's own kinematics (primary interface), "
                                     "seconds")
    park: ArmPark = Field(ArmPark(), description="what the arm does when a run ends or stops")

    @field_validator("joint_limits_deg")
    @classmethod
    def _six_ranges(cls, value: list[list[float]]) -> list[list[float]]:
        if len(value) != 6:
            raise ValueError(f"expected 6 [min, max] pairs, got {len(value)}")
        out = []
        for i, pair in enumerate(value):
            try:
                out.append(_check_range(pair, UR_JOINT_RANGE_DEG))
            except ValueError as exc:
                raise ValueError(f"joint {i + 1}: {exc}") from None
        return out

    @field_validator("home_deg")
    @classmethod
    def _six_values(cls, value: list[float]) -> list[float]:
        if len(value) != 6:
            raise ValueError(f"expected 6 joint angles, got {len(value)}")
        return value

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        from rigctl.hardware.ur_models import MODEL_NAMES

        if value not in MODEL_NAMES:
            raise ValueError(f"unknown UR arm model {value!r}; known: {', '.join(MODEL_NAMES)}")
        return value

    @model_validator(mode="after")
    def _within_model_limits(self) -> ArmConfig:
        from rigctl.hardware.ur_models import MODELS

        for i, (pair, limit) in enumerate(zip(self.joint_limits_deg,
                                              MODELS[self.model].position_limits_deg,
                                              strict=True)):
            if limit is not None and (pair[0] < limit[0] or pair[1] > limit[1]):
                raise ValueError(f"joint_limits_deg: joint {i + 1} [{pair[0]:g}, {pair[1]:g}] "
                                 f"deg exceeds the {self.model}'s limits [{limit[0]:g}, "
                                 f"{limit[1]:g}] deg")
        top = MODELS[self.model].rtde_max_hz
        if self.rtde_frequency_hz > top:
            raise ValueError(f"rtde_frequency_hz: {self.rtde_frequency_hz:g} Hz exceeds the "
                             f"{self.model}'s RTDE stream, at most {top:g} Hz")
        return self

    def joint_limits_rad(self) -> list[tuple[float, float]]:
        return [(math.radians(lo), math.radians(hi)) for lo, hi in self.joint_limits_deg]

    def home_rad(self) -> tuple[float, ...]:
        """The home joints (``home_deg``) in radians."""
        return tuple(math.radians(v) for v in self.home_deg)

    def park_rad(self) -> tuple[float, ...]:
        """Where the ``home`` park policy moves the arm: ``park.joints_deg`` in radians,
        else home."""
        if self.park.joints_deg:
            return tuple(math.radians(v) for v in self.park.joints_deg)
        return self.home_rad()


class CameraConfig(_Strict):
    device: str | int = Field(description="/dev/videoN, a camera index, or a stream URL (http://, "
                              "rtsp://)")
    width: int = Field(1280, gt=0, le=16384, description="image width, pixels; frames of another "
                       "size are refused")
    height: int = Field(720, gt=0, le=16384, description="image height, pixels")
    fourcc: str = Field("MJPG", description="pixel format asked of the camera (four characters, "
                        "e.g. MJPG, YUYV)")
    fps: float | None = Field(None, gt=0, description="frame rate asked of the camera; null: the "
                              "camera's default")
    controls: dict[str, float] = Field(default_factory=dict, description="OpenCV capture "
                                       "properties: exposure, gain, focus, white_balance, "
                                       "brightness, contrast")
    # V4L2 controls by their v4l2-ctl names (either side of Linux 5.16's renames, e.g.
    # focus_absolute, exposure_time_absolute or exposure_absolute), set through the
    # kernel's ioctls on a /dev/video device and read back
    v4l2_controls: dict[str, int] = Field(default_factory=dict, description="V4L2 controls by "
                                          "their v4l2-ctl names (focus_absolute, "
                                          "exposure_time_absolute, ...), set through the kernel "
                                          "and read back")
    # turn automatic focus, exposure and white balance off (calibration needs them fixed)
    auto_off: bool = Field(True, description="turn automatic focus, exposure and white balance off "
                           "(calibration needs them fixed)")
    timeout_s: float = Field(3.0, gt=0, description="wait to open the camera, and for a fresh "
                             "frame, seconds")
    # longest time from exposure to a frame's arrival beyond one frame period (encode,
    # transport, decode): a frame counts as taken after a motion only if it arrived this
    # much later than one period after the motion ended
    latency_s: float = Field(0.0, ge=0, le=5, description="longest exposure-to-arrival time beyond "
                             "one frame period; a frame after a motion counts only if it arrived "
                             "this much later, seconds")
    open_retries: int = Field(0, ge=0, le=10, description="reopen attempts after a failed open")
    # after a motion a frame counts only once the next frame differs from it by less than
    # this mean grey level (8x downsampled): the image is still. 0 turns the check off.
    still_threshold: float = Field(1.0, ge=0, le=50, description="after a motion a frame counts "
                                   "only once the next differs from it by less than this mean grey "
                                   "level (8x downsampled); 0: off")

    @field_validator("fourcc")
    @classmethod
    def _four_chars(cls, value: str) -> str:
        if len(value) != 4:
            raise ValueError(f"FOURCC must have 4 characters, got {value!r}")
        return value

    @field_validator("controls")
    @classmethod
    def _known_controls(cls, value: dict[str, float]) -> dict[str, float]:
        known = {"exposure", "gain", "focus", "white_balance", "brightness", "contrast"}
        unknown = sorted(set(value) - known)
        if unknown:
            raise ValueError(f"unknown camera control(s) {unknown}; known: {sorted(known)}")
        return value

    @field_validator("v4l2_controls")
    @classmethod
    def _v4l2_names(cls, value: dict[str, int]) -> dict[str, int]:
        bad = sorted(k for k in value if not re.fullmatch(r"[a-z0-9_]+", k))
        if bad:
            raise ValueError(f"V4L2 control names are v4l2-ctl's (lower case, underscores): "
                             f"{bad}")
        return value


class TargetConfig(_Strict):
    """The calibration target and its approximate placement (for planning views; the
    calibration estimates the exact pose): a checkerboard, or a ChArUco board as OpenCV's
    ``CharucoBoard`` takes it (``dictionary``: OpenCV's name, e.g. DICT_5X5_100;
    ``marker_mm``; ``legacy_pattern``: the layout OpenCV printed before 4.6)."""

    type: Literal["checkerboard", "charuco"] = Field(
        "checkerboard", description="checkerboard, or charuco (a ChArUco board: needs "
        "dictionary and marker_mm)")
    rows: int = Field(7, ge=3, description="squares of the board along its rows direction "
                      "(a checkerboard's inner corners: rows - 1)")
    cols: int = Field(10, ge=3, description="squares along its columns direction (inner corners: "
                      "cols - 1)")
    square_mm: float = Field(30.0, gt=0, description="side of one square, millimetres, as measured "
                             "on the print")
    dictionary: str | None = Field(None, description="ChArUco only: OpenCV's name of the "
                                   "markers' dictionary, e.g. DICT_5X5_100")
    marker_mm: float | None = Field(None, gt=0, description="ChArUco only: side of one marker, "
                                    "millimetres, as measured on the print")
    legacy_pattern: bool = Field(False, description="ChArUco only: the layout OpenCV printed "
                                 "before 4.6 (CharucoBoard.setLegacyPattern)")
    mount: Literal["world", "flange"] = Field(
        "world", description="world: the board is fixed beside the arm (pose is T_base_target); "
        "flange: the arm's flange holds it, in view of a head standing beside the arm "
        "(devices.head.mount: fixed; pose is T_flange_target)")
    pose: MountPose = Field(
        MountPose(xyz_mm=[350.0, 100.0, 0.0], rpy_deg=[180.0, 0.0, 0.0]),
        description="approximate T_base_target, or T_flange_target with mount: flange (for "
        "planning views; the calibration estimates it)")

    @field_validator("dictionary")
    @classmethod
    def _known_dictionary(cls, value: str | None) -> str | None:
        from rigctl.calib.charuco import check_dictionary

        return None if value is None else check_dictionary(value)

    @model_validator(mode="after")
    def _charuco_keys(self) -> TargetConfig:
        if self.type != "charuco":
            if self.dictionary is not None or self.marker_mm is not None:
                raise ValueError("dictionary and marker_mm are keys of a ChArUco target "
                                 "(type: charuco)")
            return self
        if self.dictionary is None or self.marker_mm is None:
            raise ValueError("a ChArUco target (type: charuco) needs dictionary and marker_mm")
        if self.marker_mm >= self.square_mm:
            raise ValueError(f"marker_mm {self.marker_mm:g} must be below square_mm "
                             f"{self.square_mm:g}")
        from rigctl.calib.charuco import CharucoSpec, board

        board(CharucoSpec.of(self))  # a dictionary too small for the board: named
        return self


class DevicesConfig(_Strict):
    head: HeadConfig | None = Field(None, description="the Dynamixel pan/tilt/roll head; leave out "
                                    "for a rig without one")
    arm: ArmConfig | None = Field(None, description="the Universal Robots arm; leave out for a rig "
                                  "without one")
    camera: CameraConfig | None = Field(None, description="the camera; leave out for a rig without "
                                        "one")


class RecordsConfig(_Strict):
    directory: str = Field("records", description="where run directories go; relative to the rig "
                           "file")
    database_url: str | None = Field(None, description="SQLAlchemy URL of the run index "
                                     "(postgresql+psycopg://... for a lab-wide one); null: "
                                     "sqlite:///<directory>/index.sqlite")


def parse_duration(text: str) -> int:
    """'1h', '30m', '45s', '2h30m' -> seconds (a schedule's max_delay); ``ValueError``
    for anything else."""
    total, pos = 0, 0
    for m in re.finditer(r"(\d+)\s*([hms])", text):
        if m.start() != pos:
            break
        total += int(m.group(1)) * {"h": 3600, "m": 60, "s": 1}[m.group(2)]
        pos = m.end()
    if pos != len(text.strip()) or total <= 0:
        raise ValueError(f"cannot read duration {text!r} (use e.g. 1h, 30m, 45s)")
    return total


class Schedule(_Strict):
    procedure: str = Field(description="the procedure to run")
    cron: str | None = Field(None, description="when, as a five-field cron expression (give this "
                             "or interval_s)")
    interval_s: float | None = Field(None, gt=0, description="every this many seconds (give this "
                                     "or cron)")
    params: dict[str, Any] = Field(default_factory=dict, description="the procedure's parameters "
                                   "for these runs")
    max_delay: str = Field("1h", description="a run that cannot start within this long after its "
                           "time is skipped (1h, 30m, 45s)")

    @field_validator("cron")
    @classmethod
    def _readable_cron(cls, value: str | None) -> str | None:
        if value is not None:
            from rigctl.schedules import cron_trigger

            try:
                cron_trigger(value)
            except ValueError as exc:
                raise ValueError(f"cannot read cron {value!r}: {exc}") from None
        return value

    @field_validator("max_delay")
    @classmethod
    def _readable_duration(cls, value: str) -> str:
        parse_duration(value)
        return value

    @model_validator(mode="after")
    def _one_trigger(self) -> Schedule:
        if (self.cron is None) == (self.interval_s is None):
            raise ValueError("give exactly one of cron or interval_s")
        return self


class DriftThresholds(_Strict):
    focal_pct: float = Field(0.5, description="a focal length changed by more than this, percent, "
                             "is drift (if also beyond 3 sigma)")
    principal_point_px: float = Field(3.0, description="the principal point moved more than this, "
                                      "pixels, is drift (if also beyond 3 sigma)")
    link_mm: float = Field(0.5, description="a link length changed by more than this, millimetres, "
                           "is drift (if also beyond 3 sigma)")
    link_deg: float = Field(0.05, description="a link angle changed by more than this, degrees, is "
                            "drift (if also beyond 3 sigma)")
    hand_eye_mm: float = Field(2.0, description="the hand-eye transform moved more than this, "
                               "millimetres, is drift")
    hand_eye_deg: float = Field(0.2, description="the hand-eye transform turned more than this, "
                                "degrees, is drift")


LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (127.0.0.0/8, ::1, localhost)."""
    return host in LOOPBACK_HOSTS or host.startswith("127.")


class ServiceConfig(_Strict):
    bind: str = Field("127.0.0.1", description="address the service listens on; anything but "
                      "loopback needs a token")
    port: int = Field(8765, ge=1, le=65535, description="TCP port of the service")
    # the bearer token of mutating requests (and of every read when reads are not public);
    # the environment's RIGCTL_TOKEN when not set here. Never written by rigctl: a run
    # directory's copy of the rig file has it redacted.
    token: str | None = Field(None, description="bearer token of changes (and of reads when "
                              "they are not public); default: the environment's RIGCTL_TOKEN")
    # whether anyone who reaches the port may read (runs, captures, the devices'
    # configuration, the console, the event stream) without the token; None: yes on a
    # loopback bind, no elsewhere
    public_read: bool | None = Field(
        None, description="reads (runs, captures, device configuration, the console) without "
        "the token; default: true on a loopback bind, false elsewhere")
    webhook: str | None = Field(None, description="URL that gets a JSON POST when a calibration "
                                "drifts")
    auto_accept: bool = Field(False, description="accept a new calibration within the drift "
                              "thresholds without an operator")
    schedules: list[Schedule] = Field(default_factory=list, description="runs started on a "
                                      "schedule (scheduled recalibration)")
    drift: DriftThresholds = Field(DriftThresholds(), description="thresholds beyond which a new "
                                   "calibration differs from the last accepted one")

    def bearer_token(self) -> str | None:
        """The token in force: ``token``, else the environment's ``RIGCTL_TOKEN``."""
        return self.token or os.environ.get("RIGCTL_TOKEN") or None

    def secrets(self) -> list[str]:
        """What rigctl never writes to a file or sends in an answer."""
        return [s for s in {self.token, os.environ.get("RIGCTL_TOKEN")} if s]

    def reads_public(self, host: str | None = None) -> bool:
        """Whether reads need no token when the service listens on ``host`` (default:
        ``bind``): ``public_read``, or, when unset, whether the bind is loopback."""
        if self.public_read is not None:
            return self.public_read
        return is_loopback(host or self.bind)


class RigConfig(_Strict):
    name: str = Field("rig", pattern=r"^[A-Za-z0-9_.-]+$", description="the rig's name: its lock, "
                      "and its rows in a shared index (unique per rig)")
    devices: DevicesConfig = Field(DevicesConfig(), description="the devices of the rig")
    records: RecordsConfig = Field(RecordsConfig(), description="where runs are recorded")
    target: TargetConfig = Field(TargetConfig(), description="the calibration checkerboard")
    procedures: dict[str, dict[str, Any]] = Field(default_factory=dict, description="per "
                                                  "procedure, default parameters: "
                                                  "procedures.<name>.<parameter>")
    service: ServiceConfig = Field(ServiceConfig(), description="the HTTP service (rigctl serve)")
    world: str | None = Field(None, description="simulated rigs only: the ground-truth world file")
    max_pause_s: float = Field(600.0, ge=0, le=7 * 86400, description="longest a run stays "
                               "paused on a protective stop, a servo alert or over-temperature, "
                               "or a camera stall before it ends aborted, seconds; 0: never "
                               "pause, such a condition ends the run")

    # Filled by ``load_rig``: where the file came from, and its text for provenance.
    source_path: Path | None = Field(None, exclude=True)
    source_text: str = Field("", exclude=True)

    def config_hash(self) -> str:
        """The rig file's hash as records keep it: of its text with the service token
        redacted (``redaction.redact_rig_text``), so that no record narrows the token down."""
        text = redact_rig_text(self.source_text, self.service.secrets())
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def records_dir(self) -> Path:
        base = Path(self.records.directory).expanduser()
        if not base.is_absolute() and self.source_path is not None:
            base = self.source_path.parent / base
        return base

    def database_url(self) -> str:
        return self.records.database_url or f"sqlite:///{self.records_dir() / 'index.sqlite'}"


def _format_loc(loc: tuple) -> str:
    return ".".join(str(part) for part in loc) or "(top level)"


def _format_validation(name: str, exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        msg = err["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        lines.append(f"{name}: {_format_loc(err['loc'])}: {msg}")
    return "\n".join(lines)


def parse_rig(text: str, name: str = "rig.yaml", path: Path | None = None) -> RigConfig:
    """Parse and validate rig-file text; raise ``ConfigError`` naming file, key and reason."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f":{mark.line + 1}:{mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", exc)
        raise ConfigError(f"{name}{where}: not valid YAML: {problem}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{name}: top level must be a mapping, got {type(data).__name__}")
    try:
        config = RigConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation(name, exc)) from None
    config.source_path = path
    config.source_text = text
    return config


def load_rig(path: str | Path) -> RigConfig:
    """Read a rig file; errors name the file, the key path and the reason."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: rig file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read rig file: {exc.strerror}") from None
    return parse_rig(text, name=path.name, path=path.resolve())

