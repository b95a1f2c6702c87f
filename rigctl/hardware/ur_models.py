"""Universal Robots arm models: nominal DH, joint limits, joint speeds, reach, and what the
controller says it is. One row per model; adding a model means adding a row.

Sources (read for this table; the stand-in's ``rigctl.mocks.ur_models`` is typed apart):

- Nominal DH: ur_description's ``config/<model>/default_kinematics.yaml``
  (UniversalRobots/Universal_Robots_ROS2_Description 2.4.5, commit 2221ec0) for UR3, UR5,
  UR10, UR3e, UR5e, UR10e, UR16e, UR20, UR30. UR7e and UR12e have no files of their own
  there: ros-industrial/universal_robot's ``ur_description/config/ur7e`` and ``ur12e`` are
  links to ``ur5e`` and ``ur10e`` (the ur12e file it later gained is byte-identical to
  ur10e's, hash calib_5119701370761913513), and the UR Client Library maps ur7e to UR5 and
  ur12e to UR10 "matching what the robot reports". UR15 and UR18: ros-industrial/
  universal_robot ``ur_description/config/ur15|ur18/default_kinematics.yaml`` (the same
  maintainers' files; the ROS 2 repository's copies were not in the index read here).
  The file's entries give the DH values as d1 = shoulder.z, a2 = forearm.x,
  a3 = wrist_1.x, d4 = wrist_1.z, d5 = -wrist_2.y, d6 = wrist_3.y, with UR's twists
  alpha = (pi/2, 0, 0, pi/2, -pi/2, 0) (UR's article "DH parameters for calculations of
  kinematics and dynamics" lists the same e-Series, UR20 and UR30 values).
- Joint speeds and efforts: ``config/<model>/joint_limits.yaml`` (its header cites the
  model's user manual: UR3/UR5/UR10 CB3 manual 3.13, e-Series manuals 5.8, UR20 manual
  5.14; UR15 from ros-industrial/universal_robot, UR18 from the ROS 2 repository; UR7e as
  UR5e, UR12e's own file equal to UR10e's).
- Joint position limits: the controller's, +-360 deg on every joint, the UR3's and UR3e's
  last joint unlimited (``has_position_limits: false`` in joint_limits.yaml). ur_description
  halves the elbow to +-180 deg for planners ("impossible to rotate the elbow over more than
  approx +-1 pi"); that is ``ELBOW_PLANNING_LIMIT_DEG``, used in the URDF export.
- Reach: UR's published working radius (product pages and manuals: 500, 850, 1300, 900,
  1300, 1750 and 1300 mm). It equals |a2| + |a3| + d5 for UR10, UR10e, UR15, UR20 and UR30;
  the UR18's row uses that sum (no UR18 data sheet was read).
- What the controller reports: dashboard ``get robot model`` answers "UR" + size (CB3 from
  3.12, e-Series from 5.6; UR Client Library ``dashboard_client_implementation_g5.cpp``),
  the same for an e-Series arm as for its CB3 namesake, UR7e as UR5 and UR12e as UR10.
  The serial number (UR article "Serial numbers") is YYYY, generation (3 = CB3, 5 =
  e-Series), size digit, production number: UR3 3, UR5 5, UR10 0, UR16e 6, and UR10e 0
  but 2 for the 12.5 kg arm sold as UR12e. The controller's major version is 3 on CB3 and
  5 on e-Series and UR-Series (UR Client Library ``robotSeriesFromTypeAndVersion``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from rigctl.errors import ConfigError

UR_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
ELBOW_PLANNING_LIMIT_DEG = 180.0  # ur_description joint_limits.yaml, elbow_joint
JOINT_NAMES = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
_ALL_360 = ((-360.0, 360.0),) * 6
_LAST_FREE = ((-360.0, 360.0),) * 5 + (None,)


@dataclass(frozen=True)
class URModel:
    """One UR arm model's published facts (metres, radians for alpha, degrees for limits)."""

    name: str  # as ur_description spells it
    dashboard: str  # what `get robot model` answers
    generation: str  # "CB3", "e-Series" or "UR-Series"
    d1: float
    a2: float
    a3: float
    d4: float
    d5: float
    d6: float
    max_speed_dps: tuple[float, ...]
    max_effort_nm: tuple[float, ...]
    reach_m: float
    serial_size: str | None = None  # the serial number's size digit, where published
    position_limits_deg: tuple[tuple[float, float] | None, ...] = _ALL_360

    @property
    def d(self) -> tuple[float, ...]:
        return (self.d1, 0.0, 0.0, self.d4, self.d5, self.d6)

    @property
    def a(self) -> tuple[float, ...]:
        return (0.0, self.a2, self.a3, 0.0, 0.0, 0.0)

    @property
    def alpha(self) -> tuple[float, ...]:
        return UR_ALPHA

    @property
    def controller_major(self) -> int:
        return 3 if self.generation == "CB3" else 5

    @property
    def rtde_max_hz(self) -> float:
        """The fastest RTDE output stream the controller offers: 125 Hz on CB3, 500 Hz on
        e-Series and UR-Series (UR's RTDE guide, "Real-Time Data Exchange (RTDE) Guide";
        ur_rtde takes the same as its default frequency per generation)."""
        return 125.0 if self.generation == "CB3" else 500.0

    def limits_rad(self) -> list[tuple[float, float] | None]:
        """Position limits per joint in radians (None: the joint turns without limit)."""
        return [None if lim is None else (math.radians(lim[0]), math.radians(lim[1]))
                for lim in self.position_limits_deg]

    def max_speed_rad_s(self) -> list[float]:
        return [math.radians(v) for v in self.max_speed_dps]


_SMALL = (180.0, 180.0, 180.0, 360.0, 360.0, 360.0)  # UR3, UR3e
_FIVE = (180.0,) * 6  # UR5, UR5e, UR7e
_TEN = (120.0, 120.0, 180.0, 180.0, 180.0, 180.0)  # UR10, UR10e, UR12e, UR16e
_FIFTEEN = (180.0, 180.0, 240.0, 300.0, 300.0, 300.0)  # UR15, UR18
_TWENTY = (120.0, 120.0, 150.0, 210.0, 210.0, 210.0)  # UR20, UR30

MODELS: dict[str, URModel] = {m.name: m for m in (
    #       name     dashboard gen          d1        a2        a3        d4        d5       d6
    URModel("ur3", "UR3", "CB3", 0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819,
            _SMALL, (56, 56, 28, 12, 12, 12), 0.50, "3", _LAST_FREE),
    URModel("ur5", "UR5", "CB3", 0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823,
            _FIVE, (150, 150, 150, 28, 28, 28), 0.85, "5"),
    URModel("ur10", "UR10", "CB3", 0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922,
            _TEN, (330, 330, 150, 56, 56, 56), 1.30, "0"),
    URModel("ur3e", "UR3", "e-Series", 0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921,
            _SMALL, (54, 54, 28, 9, 9, 9), 0.50, "3", _LAST_FREE),
    URModel("ur5e", "UR5", "e-Series", 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996,
            _FIVE, (150, 150, 150, 28, 28, 28), 0.85, "5"),
    URModel("ur7e", "UR5", "e-Series", 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996,
            _FIVE, (150, 150, 150, 28, 28, 28), 0.85, None),
    URModel("ur10e", "UR10", "e-Series", 0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655,
            _TEN, (330, 330, 150, 54, 54, 54), 1.30, "0"),
    URModel("ur12e", "UR10", "e-Series", 0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655,
            _TEN, (330, 330, 150, 54, 54, 54), 1.30, "2"),
    URModel("ur16e", "UR16", "e-Series", 0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655,
            _TEN, (330, 330, 150, 54, 54, 54), 0.90, "6"),
    URModel("ur15", "UR15", "UR-Series", 0.2186, -0.6475, -0.5164, 0.1824, 0.1361, 0.1434,
            _FIFTEEN, (433, 433, 204, 70, 70, 70), 1.30),
    URModel("ur18", "UR18", "UR-Series", 0.2186, -0.475, -0.3389, 0.1824, 0.1361, 0.1434,
            _FIFTEEN, (433, 433, 204, 70, 70, 70), 0.95),
    URModel("ur20", "UR20", "UR-Series", 0.2363, -0.862, -0.7287, 0.201, 0.1593, 0.1543,
            _TWENTY, (738, 738, 433, 107, 107, 107), 1.75),
    URModel("ur30", "UR30", "UR-Series", 0.2363, -0.637, -0.5037, 0.201, 0.1593, 0.1543,
            _TWENTY, (738, 738, 433, 107, 107, 107), 1.30),
)}
MODEL_NAMES = tuple(MODELS)


def ur_model(name: str, key: str = "devices.arm.model") -> URModel:
    """The row of ``name`` (lower case, as ur_description spells it); ``ConfigError``
    naming ``key`` and the known models when there is none."""
    try:
        return MODELS[name]
    except (KeyError, TypeError):
        raise ConfigError(f"{key}: unknown UR arm model {name!r}; known: "
                          f"{', '.join(MODEL_NAMES)}") from None


@dataclass(frozen=True)
class ControllerIdentity:
    """What a controller says it is: dashboard ``get robot model``, ``get serial number``
    and ``PolyscopeVersion`` (None where it gave no answer)."""

    robot_model: str | None
    serial: str | None
    version: str | None

    @property
    def major(self) -> int | None:
        match = re.search(r"(\d+)\.\d+", self.version or "")
        return int(match.group(1)) if match else None

    def serial_digits(self) -> tuple[str | None, str | None]:
        """(generation, size) digits of an old-format serial (YYYY G S n...), else Nones."""
        serial = (self.serial or "").strip()
        if re.fullmatch(r"20\d{8,9}", serial):
            return serial[4], serial[5]
        return None, None

    def candidates(self) -> list[str]:
        """The models consistent with every answer given (all models for no answer)."""
        names = list(MODEL_NAMES)
        model = (self.robot_model or "").strip().upper()
        if model:
            names = [n for n in names if MODELS[n].dashboard == model]
        if self.major is not None:
            names = [n for n in names if MODELS[n].controller_major == min(self.major, 5)]
        generation, size = self.serial_digits()
        if generation in ("3", "5"):
            names = [n for n in names if (MODELS[n].generation == "CB3") == (generation == "3")]
        if size is not None and any(MODELS[n].serial_size == size for n in names):
            # the size digit decides among the models it is published for; a model without
            # a published digit is never excluded by it
            names = [n for n in names if MODELS[n].serial_size in (size, None)]
        return names

    def describe(self) -> str:
        parts = [f"get robot model {self.robot_model!r}" if self.robot_model else None,
                 f"serial {self.serial}" if self.serial else None,
                 f"software {self.version}" if self.version else None]
        return ", ".join(p for p in parts if p) or "no answer"


def check_model(configured: str, identity: ControllerIdentity, host: str) -> list[str]:
    """The candidate models of ``identity``; ``ConfigError`` naming both the rig file's
    ``devices.arm.model`` and what the controller at ``host`` reports when they disagree."""
    candidates = identity.candidates()
    if configured not in candidates:
        found = " or ".join(candidates) if candidates else "no known model"
        raise ConfigError(f"devices.arm.model is {configured!r} but the controller at {host} "
                          f"reports {identity.describe()}, which is {found}; fix the rig "
                          "file (nothing was moved)")
    return candidates
