"""The controller stand-in's own table of UR arm models: what each controller reports and
enforces. Typed apart from the driver's ``rigctl.hardware.ur_models`` on purpose (never
imported from there): a wrong number in one shows up as a failing integration test.

Sources, read again for this table:

- DH (d, a; m): UR support article "DH parameters for calculations of kinematics and
  dynamics" (e-Series, UR20, UR30) and ur_description ``config/<model>/
  default_kinematics.yaml`` (CB3 UR3/UR5/UR10; UR15, UR18 in ros-industrial/
  universal_robot; UR7e as UR5e and UR12e as UR10e, whose files are links or copies).
  Twists alpha: pi/2, 0, 0, pi/2, -pi/2, 0 on every model.
- Joint speed limits (deg/s, base to wrist 3) and position limits: ``joint_limits.yaml``
  of the same packages (from the user manuals); a controller allows +-360 deg on every
  joint, the UR3's and UR3e's wrist 3 without limit.
- What the controller says: dashboard ``get robot model`` ("UR" + size, the e-Series arm
  like its CB3 namesake, UR7e as UR5, UR12e as UR10) and ``get serial number``, both from
  CB3 3.12 and e-Series 5.6 (UR Client Library, dashboard command table); serial numbers
  YYYY + generation (3 CB3, 5 e-Series) + size digit + production number (UR article
  "Serial numbers": UR3 3, UR5 5, UR10 0, UR16e 6, UR10e 12.5 kg 2). Where no size digit
  was published (UR7e, UR15, UR18, UR20, UR30) the stand-in's serial uses one of its own.
- Software versions: a CB3 reports 3.15 (RTDE at 125 Hz in ur_rtde, no serial-number
  query, ``$5.x`` lines stripped from the control script); the e-Series 5.11 as before;
  the newer arms a PolyScope 5 release of their time (the build numbers are the
  stand-in's).
"""

from __future__ import annotations

import math

FREE = None  # a joint without position limit

# name: (dashboard model, (d1, d4, d5, d6), (a2, a3), max speed deg/s per joint,
#        free last joint, version (major, minor, bugfix, build), serial)
_TABLE = {
    "ur3": ("UR3", (0.1519, 0.11235, 0.08535, 0.0819), (-0.24365, -0.21325),
            (180, 180, 180, 360, 360, 360), True, (3, 15, 7, 106331), "2018330412"),
    "ur5": ("UR5", (0.089159, 0.10915, 0.09465, 0.0823), (-0.425, -0.39225),
            (180, 180, 180, 180, 180, 180), False, (3, 15, 7, 106331), "2017350881"),
    "ur10": ("UR10", (0.1273, 0.163941, 0.1157, 0.0922), (-0.612, -0.5723),
             (120, 120, 180, 180, 180, 180), False, (3, 15, 7, 106331), "2016301779"),
    "ur3e": ("UR3", (0.15185, 0.13105, 0.08535, 0.0921), (-0.24355, -0.2132),
             (180, 180, 180, 360, 360, 360), True, (5, 11, 1, 108318), "20215300001"),
    "ur5e": ("UR5", (0.1625, 0.1333, 0.0997, 0.0996), (-0.425, -0.3922),
             (180, 180, 180, 180, 180, 180), False, (5, 11, 1, 108318), "20215500001"),
    "ur7e": ("UR5", (0.1625, 0.1333, 0.0997, 0.0996), (-0.425, -0.3922),
             (180, 180, 180, 180, 180, 180), False, (5, 19, 0, 117337), "20245700021"),
    "ur10e": ("UR10", (0.1807, 0.17415, 0.11985, 0.11655), (-0.6127, -0.57155),
              (120, 120, 180, 180, 180, 180), False, (5, 11, 1, 108318), "20215000001"),
    "ur12e": ("UR10", (0.1807, 0.17415, 0.11985, 0.11655), (-0.6127, -0.57155),
              (120, 120, 180, 180, 180, 180), False, (5, 19, 0, 117337), "20245200031"),
    "ur16e": ("UR16", (0.1807, 0.17415, 0.11985, 0.11655), (-0.4784, -0.36),
              (120, 120, 180, 180, 180, 180), False, (5, 11, 1, 108318), "20215600001"),
    "ur15": ("UR15", (0.2186, 0.1824, 0.1361, 0.1434), (-0.6475, -0.5164),
             (180, 180, 240, 300, 300, 300), False, (5, 21, 0, 119000), "20255150041"),
    "ur18": ("UR18", (0.2186, 0.1824, 0.1361, 0.1434), (-0.475, -0.3389),
             (180, 180, 240, 300, 300, 300), False, (5, 21, 0, 119000), "20255180051"),
    "ur20": ("UR20", (0.2363, 0.201, 0.1593, 0.1543), (-0.862, -0.7287),
             (120, 120, 150, 210, 210, 210), False, (5, 14, 2, 112011), "20235200061"),
    "ur30": ("UR30", (0.2363, 0.201, 0.1593, 0.1543), (-0.637, -0.5037),
             (120, 120, 150, 210, 210, 210), False, (5, 15, 1, 113206), "20235300071"),
}
MODEL_NAMES = tuple(_TABLE)
ALPHA = [math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0]


def known(model: str) -> bool:
    return model in _TABLE


def _row(model: str):
    if model not in _TABLE:
        raise ValueError(f"unknown UR model {model!r}; known: {', '.join(MODEL_NAMES)}")
    return _TABLE[model]


def dh(model: str) -> tuple[list[float], list[float]]:
    """Nominal (d, a) per joint, metres."""
    _, (d1, d4, d5, d6), (a2, a3), *_ = _row(model)
    return [d1, 0.0, 0.0, d4, d5, d6], [0.0, a2, a3, 0.0, 0.0, 0.0]


def joint_limits_rad(model: str) -> list[float]:
    """Each joint's position limit (symmetric, radians); ``inf`` for a free joint."""
    free_last = _row(model)[4]
    return [math.radians(360.0)] * 5 + [math.inf if free_last else math.radians(360.0)]


def joint_speed_max(model: str) -> list[float]:
    """Each joint's maximum speed, rad/s."""
    return [math.radians(v) for v in _row(model)[3]]


def version(model: str) -> tuple[int, int, int, int]:
    return _row(model)[5]


def dashboard_model(model: str) -> str:
    return _row(model)[0]


def serial_number(model: str) -> str:
    return _row(model)[6]


def polyscope_line(model: str) -> str:
    """The dashboard's ``PolyscopeVersion`` answer."""
    major, minor, bugfix, build = version(model)
    return f"URSoftware {major}.{minor}.{bugfix}.{build} (Jan 01 2024)"


# published working radius, m (UR product pages and manuals; UR18: |a2| + |a3| + d5, the
# sum that gives the published figure of UR10e, UR15, UR20 and UR30)
REACH_M = {"ur3": 0.50, "ur5": 0.85, "ur10": 1.30, "ur3e": 0.50, "ur5e": 0.85, "ur7e": 0.85,
           "ur10e": 1.30, "ur12e": 1.30, "ur16e": 0.90, "ur15": 1.30, "ur18": 0.95,
           "ur20": 1.75, "ur30": 1.30}


def is_cb3(model: str) -> bool:
    return version(model)[0] < 5
