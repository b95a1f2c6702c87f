"""The bus stand-in's own transcription of the ROBOTIS e-Manual control tables.

Typed from the e-Manual pages (https://emanual.robotis.com/docs/en/dxl/...) for the
stand-in alone: it never imports the driver's tables (``rigctl.drivers.dynamixel_models``),
so that a wrong address in one cannot hide in the other.

``Item`` rows: address, size, name, access, default, range. EEPROM items are writable
only with torque off. Per model (``ModelSpec``): the model number, the resolution and
the pulse at the centre, the units of velocity, acceleration and current, the defaults
that differ between models, and the encoder's reading noise (``noise_ticks``, sigma in
pulses: a reading dithers by about a tick).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Item:
    address: int
    size: int
    name: str
    access: str  # "R" or "RW"
    default: int
    lo: int | None = None
    hi: int | None = None
    eeprom: bool = False
    signed: bool = False


@dataclass(frozen=True)
class ModelSpec:
    """One model as the stand-in plays it. ``defaults`` override item defaults."""

    name: str
    number: int
    family: str  # "x", "mx2" or "p"
    firmware: int
    pulses_per_rev: int
    center: int
    velocity_rpm: float  # Profile Velocity / Present Velocity unit
    accel_rpm2: float  # Profile Acceleration unit
    load_item: str  # "present_current" or "present_load"
    noise_ticks: float
    defaults: dict[str, int] = field(default_factory=dict)
    page: str = ""


def _x_items(spec: ModelSpec) -> list[Item]:
    """X series / MX (2.0) table, e.g. https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/
    (addresses 0-146); Current Limit and Goal Current only where the model senses current."""
    d = spec.defaults
    items = [
        Item(0, 2, "model_number", "R", spec.number, eeprom=True),
        Item(2, 4, "model_information", "R", 0, eeprom=True),
        Item(6, 1, "firmware_version", "R", spec.firmware, eeprom=True),
        Item(7, 1, "id", "RW", 1, 0, 252, eeprom=True),
        Item(8, 1, "baud_rate", "RW", 1, 0, 7, eeprom=True),
        Item(9, 1, "return_delay_time", "RW", 250, 0, 254, eeprom=True),
        Item(10, 1, "drive_mode", "RW", 0, 0, 13, eeprom=True),
        Item(11, 1, "operating_mode", "RW", 3, 0, 16, eeprom=True),
        Item(12, 1, "secondary_id", "RW", 255, 0, 255, eeprom=True),
        Item(13, 1, "protocol_type", "RW", 2, 1, 2, eeprom=True),
        Item(20, 4, "homing_offset", "RW", 0, -1044479, 1044479, eeprom=True, signed=True),
        Item(24, 4, "moving_threshold", "RW", 10, 0, 1023, eeprom=True),
        Item(31, 1, "temperature_limit", "RW", d.get("temperature_limit", 80), 0, 100,
             eeprom=True),
        Item(32, 2, "max_voltage_limit", "RW", d.get("max_voltage_limit", 160), 60, 350,
             eeprom=True),
        Item(34, 2, "min_voltage_limit", "RW", d.get("min_voltage_limit", 95), 60, 350,
             eeprom=True),
        Item(36, 2, "pwm_limit", "RW", 885, 0, 885, eeprom=True),
        Item(44, 4, "velocity_limit", "RW", d.get("velocity_limit", 200), 0, 1023, eeprom=True),
        Item(48, 4, "max_position_limit", "RW", 4095, 0, 4095, eeprom=True),
        Item(52, 4, "min_position_limit", "RW", 0, 0, 4095, eeprom=True),
        Item(63, 1, "shutdown", "RW", 52, 0, 255, eeprom=True),
        Item(64, 1, "torque_enable", "RW", 0, 0, 1),
        Item(65, 1, "led", "RW", 0, 0, 1),
        Item(68, 1, "status_return_level", "RW", 2, 0, 2),
        Item(69, 1, "registered_instruction", "R", 0),
        Item(70, 1, "hardware_error_status", "R", 0),
        Item(76, 2, "velocity_i_gain", "RW", 1920, 0, 16383),
        Item(78, 2, "velocity_p_gain", "RW", 100, 0, 16383),
        Item(80, 2, "position_d_gain", "RW", 0, 0, 16383),
        Item(82, 2, "position_i_gain", "RW", 0, 0, 16383),
        Item(84, 2, "position_p_gain", "RW", 800, 0, 16383),
        Item(88, 2, "feedforward_2nd_gain", "RW", 0, 0, 16383),
        Item(90, 2, "feedforward_1st_gain", "RW", 0, 0, 16383),
        Item(98, 1, "bus_watchdog", "RW", 0, -1, 127, signed=True),
        Item(100, 2, "goal_pwm", "RW", 0, -885, 885, signed=True),
        Item(104, 4, "goal_velocity", "RW", 0, -1023, 1023, signed=True),
        Item(108, 4, "profile_acceleration", "RW", 0, 0, 32767),
        Item(112, 4, "profile_velocity", "RW", 0, 0, 32767),
        Item(116, 4, "goal_position", "RW", 2048, -1048575, 1048575, signed=True),
        Item(120, 2, "realtime_tick", "R", 0),
        Item(122, 1, "moving", "R", 0),
        Item(123, 1, "moving_status", "R", 0),
        Item(124, 2, "present_pwm", "R", 0, signed=True),
        Item(126, 2, spec.load_item, "R", 0, signed=True),
        Item(128, 4, "present_velocity", "R", 0, signed=True),
        Item(132, 4, "present_position", "R", 2048, signed=True),
        Item(136, 4, "velocity_trajectory", "R", 0, signed=True),
        Item(140, 4, "position_trajectory", "R", 2048, signed=True),
        Item(144, 2, "present_input_voltage", "R", d.get("present_input_voltage", 120)),
        Item(146, 1, "present_temperature", "R", 32),
    ]
    if spec.load_item == "present_current":
        limit = d.get("current_limit", 1193)
        items += [Item(38, 2, "current_limit", "RW", limit, 0, limit, eeprom=True),
                  Item(102, 2, "goal_current", "RW", 0, -limit, limit, signed=True)]
    return items


def _p_items(spec: ModelSpec) -> list[Item]:
    """DYNAMIXEL-P table, e.g. https://emanual.robotis.com/docs/en/dxl/p/ph54-200-s500-r/
    (EEPROM 0-63, RAM from 512)."""
    half = spec.pulses_per_rev // 2
    limit = spec.defaults.get("max_position_limit", half)
    return [
        Item(0, 2, "model_number", "R", spec.number, eeprom=True),
        Item(2, 4, "model_information", "R", 0, eeprom=True),
        Item(6, 1, "firmware_version", "R", spec.firmware, eeprom=True),
        Item(7, 1, "id", "RW", 1, 0, 252, eeprom=True),
        Item(8, 1, "baud_rate", "RW", 1, 0, 9, eeprom=True),
        Item(9, 1, "return_delay_time", "RW", 250, 0, 254, eeprom=True),
        Item(10, 1, "drive_mode", "RW", 0, 0, 13, eeprom=True),
        Item(11, 1, "operating_mode", "RW", 3, 0, 16, eeprom=True),
        Item(12, 1, "secondary_id", "RW", 255, 0, 255, eeprom=True),
        Item(13, 1, "protocol_type", "RW", 2, 2, 10, eeprom=True),
        Item(20, 4, "homing_offset", "RW", 0, -2**31, 2**31 - 1, eeprom=True, signed=True),
        Item(24, 4, "moving_threshold", "RW", 20, 0, 2900, eeprom=True),
        Item(31, 1, "temperature_limit", "RW", 80, 0, 100, eeprom=True),
        Item(32, 2, "max_voltage_limit", "RW", 350, 150, 350, eeprom=True),
        Item(34, 2, "min_voltage_limit", "RW", 150, 150, 350, eeprom=True),
        Item(36, 2, "pwm_limit", "RW", 2009, 0, 2009, eeprom=True),
        Item(38, 2, "current_limit", "RW", spec.defaults.get("current_limit", 22740), 0,
             spec.defaults.get("current_limit", 22740), eeprom=True),
        Item(40, 4, "acceleration_limit", "RW", spec.defaults.get("acceleration_limit",
                                                                  3_992_644), 0, 2**31 - 1,
             eeprom=True),
        Item(44, 4, "velocity_limit", "RW", spec.defaults.get("velocity_limit", 2900), 0,
             2**31 - 1, eeprom=True),
        Item(48, 4, "max_position_limit", "RW", limit, -half, half, eeprom=True,
             signed=True),
        Item(52, 4, "min_position_limit", "RW", -limit, -half, half, eeprom=True,
             signed=True),
        Item(63, 1, "shutdown", "RW", 52, 0, 63, eeprom=True),
        Item(512, 1, "torque_enable", "RW", 0, 0, 1),
        Item(513, 1, "led_red", "RW", 0, 0, 255),
        Item(514, 1, "led_green", "RW", 0, 0, 255),
        Item(515, 1, "led_blue", "RW", 0, 0, 255),
        Item(516, 1, "status_return_level", "RW", 2, 0, 2),
        Item(517, 1, "registered_instruction", "R", 0),
        Item(518, 1, "hardware_error_status", "R", 0),
        Item(524, 2, "velocity_i_gain", "RW", 2209, 0, 32767),
        Item(526, 2, "velocity_p_gain", "RW", 6153, 0, 32767),
        Item(528, 2, "position_d_gain", "RW", 0, 0, 32767),
        Item(530, 2, "position_i_gain", "RW", 0, 0, 32767),
        Item(532, 2, "position_p_gain", "RW", 314, 0, 32767),
        Item(536, 2, "feedforward_2nd_gain", "RW", 0, 0, 32767),
        Item(538, 2, "feedforward_1st_gain", "RW", 0, 0, 32767),
        Item(546, 1, "bus_watchdog", "RW", 0, -1, 127, signed=True),
        Item(548, 2, "goal_pwm", "RW", 0, -2009, 2009, signed=True),
        Item(550, 2, "goal_current", "RW", 0, -32768, 32767, signed=True),
        Item(552, 4, "goal_velocity", "RW", 0, -2**31, 2**31 - 1, signed=True),
        Item(556, 4, "profile_acceleration", "RW", 0, 0, 2**31 - 1),
        Item(560, 4, "profile_velocity", "RW", 0, 0, 2**31 - 1),
        Item(564, 4, "goal_position", "RW", 0, -2**31, 2**31 - 1, signed=True),
        Item(568, 2, "realtime_tick", "R", 0),
        Item(570, 1, "moving", "R", 0),
        Item(571, 1, "moving_status", "R", 0),
        Item(572, 2, "present_pwm", "R", 0, signed=True),
        Item(574, 2, "present_current", "R", 0, signed=True),
        Item(576, 4, "present_velocity", "R", 0, signed=True),
        Item(580, 4, "present_position", "R", 0, signed=True),
        Item(584, 4, "velocity_trajectory", "R", 0, signed=True),
        Item(588, 4, "position_trajectory", "R", 0, signed=True),
        Item(592, 2, "present_input_voltage", "R", 240),
        Item(594, 1, "present_temperature", "R", 32),
    ]


_X = {"family": "x", "pulses_per_rev": 4096, "center": 2048, "velocity_rpm": 0.229,
      "accel_rpm2": 214.577, "noise_ticks": 0.5}
_P = {"family": "p", "center": 0, "velocity_rpm": 0.01, "accel_rpm2": 1.0,
      "load_item": "present_current", "noise_ticks": 2.0}
_12V = {"max_voltage_limit": 160, "min_voltage_limit": 95}
_24V = {"max_voltage_limit": 300, "min_voltage_limit": 150, "present_input_voltage": 240}

SPECS: tuple[ModelSpec, ...] = (
    # X series (e-Manual x/<model>/): 4096 pulses, 0.229 rev/min, 214.577 rev/min^2
    ModelSpec("xl430-w250", 1060, firmware=46, load_item="present_load", page="x/xl430-w250",
              defaults={"temperature_limit": 72, "max_voltage_limit": 140,
                        "min_voltage_limit": 60, "velocity_limit": 265,
                        "present_input_voltage": 115}, **_X),
    ModelSpec("xc430-w150", 1070, firmware=46, load_item="present_load", page="x/xc430-w150",
              defaults={"max_voltage_limit": 160, "min_voltage_limit": 65,
                        "velocity_limit": 460, "present_input_voltage": 115}, **_X),
    ModelSpec("xc430-w240", 1080, firmware=46, load_item="present_load", page="x/xc430-w240",
              defaults={"max_voltage_limit": 160, "min_voltage_limit": 65,
                        "velocity_limit": 306, "present_input_voltage": 115}, **_X),
    ModelSpec("xm430-w210", 1030, firmware=52, load_item="present_current",
              page="x/xm430-w210", defaults={**_12V, "velocity_limit": 330,
                                             "current_limit": 1193}, **_X),
    ModelSpec("xm430-w350", 1020, firmware=52, load_item="present_current",
              page="x/xm430-w350", defaults={**_12V, "velocity_limit": 200,
                                             "current_limit": 1193}, **_X),
    ModelSpec("xh430-w210", 1010, firmware=52, load_item="present_current",
              page="x/xh430-w210", defaults={**_12V, "current_limit": 648}, **_X),
    ModelSpec("xh430-w350", 1000, firmware=52, load_item="present_current",
              page="x/xh430-w350", defaults={**_12V, "current_limit": 648}, **_X),
    ModelSpec("xh430-v210", 1050, firmware=52, load_item="present_current",
              page="x/xh430-v210", defaults={**_24V, "current_limit": 689}, **_X),
    ModelSpec("xh430-v350", 1040, firmware=52, load_item="present_current",
              page="x/xh430-v350", defaults={**_24V, "current_limit": 689}, **_X),
    ModelSpec("xw430-t200", 1280, firmware=52, load_item="present_current",
              page="x/xw430-t200", defaults={**_12V, "current_limit": 1193}, **_X),
    ModelSpec("xw430-t333", 1270, firmware=52, load_item="present_current",
              page="x/xw430-t333", defaults={**_12V, "current_limit": 1193}, **_X),
    ModelSpec("xm540-w150", 1130, firmware=52, load_item="present_current",
              page="x/xm540-w150", defaults={**_12V, "current_limit": 2047}, **_X),
    ModelSpec("xm540-w270", 1120, firmware=52, load_item="present_current",
              page="x/xm540-w270", defaults={**_12V, "current_limit": 2047}, **_X),
    ModelSpec("xh540-w150", 1110, firmware=52, load_item="present_current",
              page="x/xh540-w150", defaults={**_12V, "current_limit": 2047}, **_X),
    ModelSpec("xh540-w270", 1100, firmware=52, load_item="present_current",
              page="x/xh540-w270", defaults={**_12V, "current_limit": 2047,
                                             "velocity_limit": 167}, **_X),
    ModelSpec("xh540-v150", 1150, firmware=52, load_item="present_current",
              page="x/xh540-v150", defaults={**_24V, "current_limit": 2047}, **_X),
    ModelSpec("xh540-v270", 1140, firmware=52, load_item="present_current",
              page="x/xh540-v270", defaults={**_24V, "current_limit": 2047}, **_X),
    ModelSpec("xw540-t140", 1180, firmware=52, load_item="present_current",
              page="x/xw540-t140", defaults={**_12V, "current_limit": 2047}, **_X),
    ModelSpec("xw540-t260", 1170, firmware=52, load_item="present_current",
              page="x/xw540-t260", defaults={**_12V, "current_limit": 2047}, **_X),
    # MX series, Protocol 2.0 firmware (mx/mx-28-2, mx-64-2, mx-106-2): the X layout;
    # MX-28 (2.0) reports Present Load, MX-64/106 Present Current (3.36 mA)
    ModelSpec("mx-28", 30, firmware=41, load_item="present_load", page="mx/mx-28-2",
              defaults={**_12V, "velocity_limit": 230}, **_X),
    ModelSpec("mx-64", 311, firmware=41, load_item="present_current", page="mx/mx-64-2",
              defaults={**_12V, "velocity_limit": 435, "current_limit": 1941}, **_X),
    ModelSpec("mx-106", 321, firmware=41, load_item="present_current", page="mx/mx-106-2",
              defaults={**_12V, "velocity_limit": 270, "current_limit": 2047}, **_X),
    # DYNAMIXEL-P (p/<model>): 0.01 rev/min, 1 rev/min^2, 1 mA; pulses per turn each page
    ModelSpec("ph42-020-s300-r", 2000, firmware=12, pulses_per_rev=607_500,
              page="p/ph42-020-s300-r", defaults={"current_limit": 4500}, **_P),
    ModelSpec("ph54-100-s500-r", 2010, firmware=12, pulses_per_rev=1_003_846,
              page="p/ph54-100-s500-r", defaults={"current_limit": 15900}, **_P),
    ModelSpec("ph54-200-s500-r", 2020, firmware=12, pulses_per_rev=1_003_846,
              page="p/ph54-200-s500-r",
              defaults={"current_limit": 22740, "max_position_limit": 501_433}, **_P),
    ModelSpec("pm42-010-s260-r", 2100, firmware=12, pulses_per_rev=526_374,
              page="p/pm42-010-s260-r", defaults={"current_limit": 1461}, **_P),
    ModelSpec("pm54-040-s250-r", 2110, firmware=12, pulses_per_rev=502_834,
              page="p/pm54-040-s250-r", defaults={"current_limit": 10300}, **_P),
    ModelSpec("pm54-060-s250-r", 2120, firmware=12, pulses_per_rev=502_834,
              page="p/pm54-060-s250-r", defaults={"current_limit": 10300}, **_P),
)
SPEC_BY_NAME = {s.name: s for s in SPECS}
# PRO+ names of the same servos (same model numbers)
SPEC_BY_NAME.update({"h42p-020-s300-r": SPEC_BY_NAME["ph42-020-s300-r"],
                     "h54p-100-s500-r": SPEC_BY_NAME["ph54-100-s500-r"],
                     "h54p-200-s500-r": SPEC_BY_NAME["ph54-200-s500-r"],
                     "m42p-010-s260-r": SPEC_BY_NAME["pm42-010-s260-r"],
                     "m54p-040-s250-r": SPEC_BY_NAME["pm54-040-s250-r"],
                     "m54p-060-s250-r": SPEC_BY_NAME["pm54-060-s250-r"]})


def items_of(spec: ModelSpec) -> list[Item]:
    """The control table the stand-in plays for ``spec``, sorted by address."""
    items = _p_items(spec) if spec.family == "p" else _x_items(spec)
    return sorted(items, key=lambda i: i.address)


def table_end(spec: ModelSpec) -> int:
    """One past the last address the stand-in defines."""
    return 1024 if spec.family == "p" else 228
