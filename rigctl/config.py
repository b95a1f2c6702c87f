"""The rig file: a YAML description of the devices, records, procedures and service.

Validated with pydantic. Degrees and millimetres live here, at the edge; the
``*_rad`` helpers convert once. Every error names the file, the key path and the
reason, e.g. ``rig.yaml: devices.head.limits.pan: max 200 deg exceeds the servo
range of 180 deg``.
"""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from rigctl.errors import ConfigError

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

    pan: list[float] = [-90.0, 90.0]
    tilt: list[float] = [-45.0, 45.0]
    roll: list[float] = [-180.0, 180.0]

    @field_validator("pan", "tilt", "roll")
    @classmethod
    def _in_servo_range(cls, value: list[float]) -> list[float]:
        return _check_range(value, SERVO_RANGE_DEG)


class AxisMap(_Strict):
    pan: int = 1
    tilt: int = 2
    roll: int = 3


class AxisFloat(_Strict):
    pan: float = 0.0
    tilt: float = 0.0
    roll: float = 0.0


class AxisSign(_Strict):
    pan: Literal[1, -1] = 1
    tilt: Literal[1, -1] = 1
    roll: Literal[1, -1] = 1


class AxisModel(_Strict):
    pan: str | None = None
    tilt: str | None = None
    roll: str | None = None


def _known_servo(value: str | None) -> str | None:
    from rigctl.drivers.dynamixel_models import MODEL_NAMES

    if value is not None and value.lower() not in MODEL_NAMES:
        raise ValueError(f"unknown servo model {value!r}; known: {', '.join(MODEL_NAMES)}")
    return value.lower() if value is not None else None


class HeadPark(_Strict):
    policy: Literal["hold", "home", "torque_off", "home_then_torque_off"] = "home"
    angles_deg: list[float] = [0.0, 0.0, 0.0]


class MountPose(_Strict):
    """A nominal transform, mm and degrees (rpy = Rz(yaw) Ry(pitch) Rx(roll))."""

    xyz_mm: list[float] = Field(default_factory=lambda: [0.0, 0.0, 50.0])
    rpy_deg: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0])

    @field_validator("xyz_mm", "rpy_deg")
    @classmethod
    def _three(cls, value: list[float]) -> list[float]:
        if len(value) != 3:
            raise ValueError(f"expected 3 values, got {len(value)}")
        return value


class HeadConfig(_Strict):
    port: str
    mount: MountPose = MountPose()  # nominal T_flange_head (head on the flange), planning
    baud: int = 1_000_000
    # One servo model for all axes, one per axis, or None: read from each servo when the
    # driver pings it. A named model that differs from the servo's refuses the run.
    model: str | AxisModel | None = None
    ids: AxisMap = AxisMap()
    limits: HeadLimits = HeadLimits()
    zero_offset_deg: AxisFloat = AxisFloat()
    direction: AxisSign = AxisSign()
    speed_cap_dps: float = Field(60.0, gt=0, le=300)
    accel_cap_dps2: float = Field(240.0, gt=0, le=5000)
    move_timeout_s: float = Field(15.0, gt=0)
    settle_s: float = Field(0.2, ge=0)
    # Bus timing. ``packet_timeout_ms`` None keeps the SDK's own per-packet timeout (a few
    # ms plus twice the USB latency timer), right for servos that answer in microseconds;
    # a stand-in process on a loaded host needs a longer one. A failed transaction is
    # retried ``retries`` times, pausing ``retry_backoff_s`` before the first retry and
    # twice as long before each next one.
    packet_timeout_ms: float | None = Field(None, gt=0, le=2000)
    retries: int = Field(3, ge=0, le=10)
    retry_backoff_s: float = Field(0.0, ge=0, le=1.0)
    park: HeadPark = HeadPark()

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
    policy: Literal["hold", "home"] = "hold"
    joints_deg: list[float] | None = None


class ArmConfig(_Strict):
    host: str = "127.0.0.1"
    model: str = "ur5e"  # any row of rigctl.hardware.ur_models, as ur_description spells it
    joint_limits_deg: list[list[float]] = Field(default_factory=lambda: [[-360.0, 360.0]] * 6)
    home_deg: list[float] = [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]
    speed_cap_dps: float = Field(60.0, gt=0, le=180)
    accel_cap_dps2: float = Field(80.0, gt=0, le=800)
    linear_speed_mm_s: float = Field(100.0, gt=0, le=1000)
    linear_accel_mm_s2: float = Field(300.0, gt=0, le=3000)
    move_timeout_s: float = Field(30.0, gt=0)
    settle_s: float = Field(0.2, ge=0)
    connect_retries: int = Field(3, ge=1, le=20)
    # The RTDE stream (500 Hz on a real controller) silent this long: connection lost.
    stream_timeout_s: float = Field(1.0, gt=0, le=30)
    # Bound on each teardown call (stopScript, stopJ) into ur_rtde.
    teardown_timeout_s: float = Field(3.0, gt=0, le=60)
    # Reading the version and the controller's kinematics from the primary interface.
    primary_timeout_s: float = Field(5.0, gt=0, le=60)
    park: ArmPark = ArmPark()

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
    device: str | int  # /dev/videoN, an index, or a stream URL (http://, rtsp://)
    width: int = Field(1280, gt=0, le=16384)
    height: int = Field(720, gt=0, le=16384)
    fourcc: str = "MJPG"
    fps: float | None = Field(None, gt=0)
    controls: dict[str, float] = Field(default_factory=dict)
    # V4L2 controls by their v4l2-ctl names (either side of Linux 5.16's renames, e.g.
    # focus_absolute, exposure_time_absolute or exposure_absolute), set through the
    # kernel's ioctls on a /dev/video device and read back
    v4l2_controls: dict[str, int] = Field(default_factory=dict)
    # turn automatic focus, exposure and white balance off (calibration needs them fixed)
    auto_off: bool = True
    timeout_s: float = Field(3.0, gt=0)  # open, and wait for a fresh frame
    # longest time from exposure to a frame's arrival beyond one frame period (encode,
    # transport, decode): a frame counts as taken after a motion only if it arrived this
    # much later than one period after the motion ended
    latency_s: float = Field(0.0, ge=0, le=5)
    open_retries: int = Field(0, ge=0, le=10)  # reopen attempts after a failed open
    # after a motion a frame counts only once the next frame differs from it by less than
    # this mean grey level (8x downsampled): the image is still. 0 turns the check off.
    still_threshold: float = Field(1.0, ge=0, le=50)

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

    type: Literal["checkerboard", "charuco"] = "checkerboard"
    rows: int = Field(7, ge=3)
    cols: int = Field(10, ge=3)
    square_mm: float = Field(30.0, gt=0)
    dictionary: str | None = None
    marker_mm: float | None = Field(None, gt=0)
    legacy_pattern: bool = False
    pose: MountPose = MountPose(xyz_mm=[350.0, 100.0, 0.0], rpy_deg=[180.0, 0.0, 0.0])

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
    head: HeadConfig | None = None
    arm: ArmConfig | None = None
    camera: CameraConfig | None = None


class RecordsConfig(_Strict):
    directory: str = "records"
    database_url: str | None = None  # default: sqlite:///<directory>/index.sqlite


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
    procedure: str
    cron: str | None = None
    interval_s: float | None = Field(None, gt=0)
    params: dict[str, Any] = Field(default_factory=dict)
    max_delay: str = "1h"  # a run that cannot start within this long after its time is skipped

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
    focal_pct: float = 0.5
    principal_point_px: float = 3.0
    link_mm: float = 0.5
    link_deg: float = 0.05
    hand_eye_mm: float = 2.0
    hand_eye_deg: float = 0.2


class ServiceConfig(_Strict):
    bind: str = "127.0.0.1"
    port: int = Field(8765, ge=1, le=65535)
    token: str | None = None
    webhook: str | None = None
    auto_accept: bool = False
    schedules: list[Schedule] = Field(default_factory=list)
    drift: DriftThresholds = DriftThresholds()


class RigConfig(_Strict):
    name: str = Field("rig", pattern=r"^[A-Za-z0-9_.-]+$")
    devices: DevicesConfig = DevicesConfig()
    records: RecordsConfig = RecordsConfig()
    target: TargetConfig = TargetConfig()
    procedures: dict[str, dict[str, Any]] = Field(default_factory=dict)
    service: ServiceConfig = ServiceConfig()
    world: str | None = None  # simulated rigs only: the ground-truth world file

    # Filled by ``load_rig``: where the file came from, and its text for provenance.
    source_path: Path | None = Field(None, exclude=True)
    source_text: str = Field("", exclude=True)

    def config_hash(self) -> str:
        return hashlib.sha256(self.source_text.encode()).hexdigest()[:16]

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

