"""Dynamixel servo models the head driver knows: control tables, resolution, units, limits.

Hardware facts as data, each table with the ROBOTIS e-Manual page it was typed from
(https://emanual.robotis.com/docs/en/dxl/...). Model numbers were checked against
ROBOTIS' ``dynamixel_hardware_interface`` model list and DynamixelWorkbench's
``dynamixel_item.h``. The bus stand-in keeps its own transcription
(``rigctl.mocks.dxl_models``) and never imports this module.

Three control tables cover the families:

- ``X``: X series (XL430, XC430, XM430, XH430, XW430, XM540, XH540, XW540) and the MX
  series on Protocol 2.0 (MX-28/64/106 (2.0)), which share the X series' addresses;
- ``P``: DYNAMIXEL-P (PH42, PH54, PM42, PM54), formerly sold as PRO+ (H42P, H54P, M42P,
  M54P) under the same model numbers: RAM items from address 512 on.

The block from Moving to Present Temperature has the same layout in both tables
(Moving +0, Moving Status +1, Present Current/Load +4, Present Velocity +6, Present
Position +10, Present Input Voltage +22, Present Temperature +24), so one read of
``STATUS_SIZE`` bytes at ``table["moving"]`` brings a servo's whole state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# name: (address, size). X series control table, e.g.
# https://emanual.robotis.com/docs/en/dxl/x/xh540-w270/#control-table (and every X page);
# MX (2.0): https://emanual.robotis.com/docs/en/dxl/mx/mx-64-2/#control-table
X_TABLE: dict[str, tuple[int, int]] = {
    "model_number": (0, 2), "firmware_version": (6, 1), "id": (7, 1), "baud_rate": (8, 1),
    "return_delay_time": (9, 1), "drive_mode": (10, 1), "operating_mode": (11, 1),
    "temperature_limit": (31, 1), "max_voltage_limit": (32, 2), "min_voltage_limit": (34, 2),
    "max_position_limit": (48, 4), "min_position_limit": (52, 4), "shutdown": (63, 1),
    "torque_enable": (64, 1), "hardware_error_status": (70, 1),
    "profile_acceleration": (108, 4), "profile_velocity": (112, 4), "goal_position": (116, 4),
    "moving": (122, 1), "moving_status": (123, 1), "present_load": (126, 2),
    "present_velocity": (128, 4), "present_position": (132, 4),
    "present_input_voltage": (144, 2), "present_temperature": (146, 1),
}
# DYNAMIXEL-P control table:
# https://emanual.robotis.com/docs/en/dxl/p/ph54-200-s500-r/#control-table (same on every
# P page: PH42-020-S300-R, PH54-100-S500-R, PM42-010-S260-R, PM54-040/060-S250-R)
P_TABLE: dict[str, tuple[int, int]] = {
    "model_number": (0, 2), "firmware_version": (6, 1), "id": (7, 1), "baud_rate": (8, 1),
    "return_delay_time": (9, 1), "drive_mode": (10, 1), "operating_mode": (11, 1),
    "temperature_limit": (31, 1), "max_voltage_limit": (32, 2), "min_voltage_limit": (34, 2),
    "max_position_limit": (48, 4), "min_position_limit": (52, 4), "shutdown": (63, 1),
    "torque_enable": (512, 1), "hardware_error_status": (518, 1),
    "profile_acceleration": (556, 4), "profile_velocity": (560, 4), "goal_position": (564, 4),
    "moving": (570, 1), "moving_status": (571, 1), "present_load": (574, 2),
    "present_velocity": (576, 4), "present_position": (580, 4),
    "present_input_voltage": (592, 2), "present_temperature": (594, 1),
}
STATUS_SIZE = 25  # Moving .. Present Temperature
STATUS_OFFSETS = {"moving": 0, "moving_status": 1, "load": 4, "velocity": 6, "position": 10,
                  "voltage": 22, "temperature": 24}

# Baud Rate (8) codes, the same in both tables for the rates the head uses
# (https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/#baud-rate8).
BAUD_CODES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}
STANDARD_BAUDS = tuple(BAUD_CODES.values())


@dataclass(frozen=True)
class ServoModel:
    """One servo model: which control table, how pulses map to angles, units, limits.

    ``pulses_per_rev``/``center``: a position reading ``p`` is the angle
    ``(p - center) * 2 pi / pulses_per_rev``; ``position_range``: what Goal Position takes
    in position mode. ``load``: what the 2-byte item at Present Current/Load holds,
    "current" (``load_unit`` mA) or "load" (``load_unit`` % of the maximum).
    ``voltage_v``/``max_temperature_c``: the operating range of the specification page.
    """

    name: str
    number: int
    family: str  # "X", "MX" or "P"
    table: dict[str, tuple[int, int]]
    pulses_per_rev: int
    center: int
    position_range: tuple[int, int]
    velocity_unit_rpm: float
    accel_unit_rpm2: float
    load: str
    load_unit: float
    voltage_v: tuple[float, float]
    max_temperature_c: float
    source: str

    @property
    def resolution_deg(self) -> float:
        """One pulse, degrees."""
        return 360.0 / self.pulses_per_rev

    def to_pulses(self, servo_rad: float) -> int:
        """The nearest pulse to a servo angle (radians from the centre)."""
        return round(self.center + servo_rad * self.pulses_per_rev / (2 * math.pi))

    def to_rad(self, pulses: int) -> float:
        """A servo angle (radians from the centre) from a position reading."""
        return (pulses - self.center) * 2 * math.pi / self.pulses_per_rev

    def velocity_value(self, dps: float) -> int:
        """Profile Velocity for ``dps`` degrees per second (at least 1: 0 is unlimited)."""
        return max(1, int(dps / 6.0 / self.velocity_unit_rpm))

    def accel_value(self, dps2: float) -> int:
        """Profile Acceleration for ``dps2`` degrees per second squared (at least 1)."""
        return max(1, int(dps2 / 360.0 * 3600.0 / self.accel_unit_rpm2))


_EM = "https://emanual.robotis.com/docs/en/dxl/"
_X_UNITS = {"table": X_TABLE, "pulses_per_rev": 4096, "center": 2048,
            "position_range": (0, 4095), "velocity_unit_rpm": 0.229,
            "accel_unit_rpm2": 214.577}


def _x(name: str, number: int, load: str, load_unit: float, volts: tuple[float, float],
       max_c: float, page: str, family: str = "X") -> ServoModel:
    return ServoModel(name=name, number=number, family=family, load=load, load_unit=load_unit,
                      voltage_v=volts, max_temperature_c=max_c, source=_EM + page,
                      **_X_UNITS)  # type: ignore[arg-type]


def _p(name: str, number: int, pulses_per_rev: int, page: str) -> ServoModel:
    half = pulses_per_rev // 2
    return ServoModel(name=name, number=number, family="P", table=P_TABLE,
                      pulses_per_rev=pulses_per_rev, center=0, position_range=(-half, half),
                      velocity_unit_rpm=0.01, accel_unit_rpm2=1.0, load="current",
                      load_unit=1.0, voltage_v=(24.0, 24.0), max_temperature_c=55.0,
                      source=_EM + page)


# Model Number (address 0), specification (resolution, input voltage, operating
# temperature) and Present Current/Load unit from each model's e-Manual page.
MODELS: tuple[ServoModel, ...] = (
    # X series, 4096 pulses per turn, 0.229 rev/min, 214.577 rev/min^2
    _x("xl430-w250", 1060, "load", 0.1, (6.5, 12.0), 72.0, "x/xl430-w250/"),
    _x("xc430-w150", 1070, "load", 0.1, (6.5, 14.8), 80.0, "x/xc430-w150/"),
    _x("xc430-w240", 1080, "load", 0.1, (6.5, 14.8), 80.0, "x/xc430-w240/"),
    _x("xm430-w210", 1030, "current", 2.69, (10.0, 14.8), 80.0, "x/xm430-w210/"),
    _x("xm430-w350", 1020, "current", 2.69, (10.0, 14.8), 80.0, "x/xm430-w350/"),
    _x("xh430-w210", 1010, "current", 1.34, (10.0, 14.8), 80.0, "x/xh430-w210/"),
    _x("xh430-w350", 1000, "current", 1.34, (10.0, 14.8), 80.0, "x/xh430-w350/"),
    _x("xh430-v210", 1050, "current", 1.34, (24.0, 24.0), 80.0, "x/xh430-v210/"),
    _x("xh430-v350", 1040, "current", 1.34, (24.0, 24.0), 80.0, "x/xh430-v350/"),
    _x("xw430-t200", 1280, "current", 2.69, (10.0, 14.8), 80.0, "x/xw430-t200/"),
    _x("xw430-t333", 1270, "current", 2.69, (10.0, 14.8), 80.0, "x/xw430-t333/"),
    _x("xm540-w150", 1130, "current", 2.69, (10.0, 14.8), 80.0, "x/xm540-w150/"),
    _x("xm540-w270", 1120, "current", 2.69, (10.0, 14.8), 80.0, "x/xm540-w270/"),
    _x("xh540-w150", 1110, "current", 2.69, (10.0, 14.8), 80.0, "x/xh540-w150/"),
    _x("xh540-w270", 1100, "current", 2.69, (10.0, 14.8), 80.0, "x/xh540-w270/"),
    _x("xh540-v150", 1150, "current", 2.69, (24.0, 24.0), 80.0, "x/xh540-v150/"),
    _x("xh540-v270", 1140, "current", 2.69, (24.0, 24.0), 80.0, "x/xh540-v270/"),
    _x("xw540-t140", 1180, "current", 2.69, (10.0, 14.8), 80.0, "x/xw540-t140/"),
    _x("xw540-t260", 1170, "current", 2.69, (10.0, 14.8), 80.0, "x/xw540-t260/"),
    # MX series on Protocol 2.0: the X table; MX-28 (2.0) reports load, not current
    _x("mx-28", 30, "load", 0.1, (10.0, 14.8), 80.0, "mx/mx-28-2/", "MX"),
    _x("mx-64", 311, "current", 3.36, (10.0, 14.8), 80.0, "mx/mx-64-2/", "MX"),
    _x("mx-106", 321, "current", 3.36, (10.0, 14.8), 80.0, "mx/mx-106-2/", "MX"),
    # DYNAMIXEL-P: 0.01 rev/min, 1 rev/min^2, 1 mA, 24 V, -5 to +55 C; resolution per model
    _p("ph42-020-s300-r", 2000, 607_500, "p/ph42-020-s300-r/"),
    _p("ph54-100-s500-r", 2010, 1_003_846, "p/ph54-100-s500-r/"),
    _p("ph54-200-s500-r", 2020, 1_003_846, "p/ph54-200-s500-r/"),
    _p("pm42-010-s260-r", 2100, 526_374, "p/pm42-010-s260-r/"),
    _p("pm54-040-s250-r", 2110, 502_834, "p/pm54-040-s250-r/"),
    _p("pm54-060-s250-r", 2120, 502_834, "p/pm54-060-s250-r/"),
)
# The same servos' PRO+ names: the same model numbers (DynamixelWorkbench's
# dynamixel_item.h: PRO_PLUS_H42P_020_S300_R 2000 ... PRO_PLUS_M54P_060_S250_R 2120).
ALIASES = {"h42p-020-s300-r": "ph42-020-s300-r", "h54p-100-s500-r": "ph54-100-s500-r",
           "h54p-200-s500-r": "ph54-200-s500-r", "m42p-010-s260-r": "pm42-010-s260-r",
           "m54p-040-s250-r": "pm54-040-s250-r", "m54p-060-s250-r": "pm54-060-s250-r"}

BY_NAME = {m.name: m for m in MODELS}
BY_NUMBER = {m.number: m for m in MODELS}
MODEL_NAMES = tuple(BY_NAME) + tuple(ALIASES)


def by_name(name: str) -> ServoModel:
    """The model a rig file names (lower case, PRO+ aliases accepted)."""
    return BY_NAME[ALIASES.get(name.lower(), name.lower())]


def model_label(number: int) -> str:
    """The lower-case name of a model number, or ``model <number>`` when unknown."""
    model = BY_NUMBER.get(number)
    return model.name if model else f"model {number}"
