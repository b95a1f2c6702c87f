"""One simulated X-series servo: control table, access rules, trapezoidal motion, faults.

Facts from the ROBOTIS e-Manual (XM430-W350, XL430-W250 control tables). Behaviour the
e-Manual leaves open is configurable through ``ServoOptions``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

# Error numbers of the status packet (bits 0-6), and the Alert bit.
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC = 1, 2, 3
ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = 4, 5, 6, 7
ALERT = 0x80

# Hardware Error Status (70) bits.
HW_VOLTAGE, HW_OVERHEAT, HW_ENCODER, HW_SHOCK, HW_OVERLOAD = 0x01, 0x04, 0x08, 0x10, 0x20
HW_ERRORS = {"voltage": HW_VOLTAGE, "overheat": HW_OVERHEAT, "encoder": HW_ENCODER,
             "shock": HW_SHOCK, "overload": HW_OVERLOAD}

PULSES_PER_REV = 4096
VELOCITY_UNIT_RPM = 0.229
ACCEL_UNIT_RPM2 = 214.577
TABLE_END = 228  # addresses past the indirect-data area are undefined here


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


def _table(model: str) -> list[Item]:
    xm = model == "xm430-w350"
    items = [
        Item(0, 2, "model_number", "R", 1020 if xm else 1060, eeprom=True),
        Item(2, 4, "model_information", "R", 0, eeprom=True),
        Item(6, 1, "firmware_version", "R", 52 if xm else 46, eeprom=True),
        Item(7, 1, "id", "RW", 1, 0, 252, eeprom=True),
        Item(8, 1, "baud_rate", "RW", 1, 0, 7, eeprom=True),
        Item(9, 1, "return_delay_time", "RW", 250, 0, 254, eeprom=True),
        Item(10, 1, "drive_mode", "RW", 0, 0, 13, eeprom=True),
        Item(11, 1, "operating_mode", "RW", 3, 0, 16, eeprom=True),
        Item(12, 1, "secondary_id", "RW", 255, 0, 255, eeprom=True),
        Item(13, 1, "protocol_type", "RW", 2, 1, 2, eeprom=True),
        Item(20, 4, "homing_offset", "RW", 0, -1044479, 1044479, eeprom=True, signed=True),
        Item(24, 4, "moving_threshold", "RW", 10, 0, 1023, eeprom=True),
        Item(31, 1, "temperature_limit", "RW", 80 if xm else 72, 0, 100, eeprom=True),
        Item(32, 2, "max_voltage_limit", "RW", 160 if xm else 140, 60, 160, eeprom=True),
        Item(34, 2, "min_voltage_limit", "RW", 95 if xm else 60, 60, 160, eeprom=True),
        Item(36, 2, "pwm_limit", "RW", 885, 0, 885, eeprom=True),
        Item(44, 4, "velocity_limit", "RW", 200 if xm else 265, 0, 1023, eeprom=True),
        Item(48, 4, "max_position_limit", "RW", 4095, 0, 4095, eeprom=True),
        Item(52, 4, "min_position_limit", "RW", 0, 0, 4095, eeprom=True),
        Item(63, 1, "shutdown", "RW", 52, 0, 255, eeprom=True),
        Item(64, 1, "torque_enable", "RW", 0, 0, 1),
        Item(65, 1, "led", "RW", 0, 0, 1),
        Item(68, 1, "status_return_level", "RW", 2, 0, 2),
        Item(69, 1, "registered_instruction", "R", 0),
        Item(70, 1, "hardware_error_status", "R", 0),
        Item(76, 2, "velocity_i_gain", "RW", 1920 if xm else 1000, 0, 16383),
        Item(78, 2, "velocity_p_gain", "RW", 100, 0, 16383),
        Item(80, 2, "position_d_gain", "RW", 0, 0, 16383),
        Item(82, 2, "position_i_gain", "RW", 0, 0, 16383),
        Item(84, 2, "position_p_gain", "RW", 800 if xm else 640, 0, 16383),
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
        Item(126, 2, "present_current", "R", 0, signed=True),
        Item(128, 4, "present_velocity", "R", 0, signed=True),
        Item(132, 4, "present_position", "R", 2048, signed=True),
        Item(136, 4, "velocity_trajectory", "R", 0, signed=True),
        Item(140, 4, "position_trajectory", "R", 2048, signed=True),
        Item(144, 2, "present_input_voltage", "R", 120 if xm else 115),
        Item(146, 1, "present_temperature", "R", 32),
    ]
    if xm:
        items += [Item(38, 2, "current_limit", "RW", 1193, 0, 1193, eeprom=True),
                  Item(102, 2, "goal_current", "RW", 0, -1193, 1193, signed=True)]
    return sorted(items, key=lambda i: i.address)


MODELS = {"xm430-w350": 1020, "xl430-w250": 1060}
GOAL_ITEMS = ("goal_pwm", "goal_current", "goal_velocity", "goal_position")


@dataclass
class ServoOptions:
    """Behaviour the e-Manual leaves open (unverified on real servos): configurable."""

    goal_out_of_limit: str = "reject"  # reject (ERR 6) or clamp
    torque_on_sets_goal_to_present: bool = True


@dataclass
class Profile:
    """A trapezoidal (or triangular) move from ``start`` to ``goal`` beginning at ``t0``."""

    start: float
    goal: float
    t0: float
    t_acc: float = 0.0
    t_total: float = 0.0
    v_peak: float = 0.0
    kind: int = 0  # Moving Status bits 4-5: 3 trapezoid, 2 triangle, 1 rectangle, 0 step

    @classmethod
    def plan(cls, start: float, goal: float, t0: float, v: float, a: float) -> Profile:
        """Velocity ``v`` (pulse/s, inf = unlimited) and acceleration ``a`` (pulse/s^2)."""
        d = abs(goal - start)
        if d == 0 or (math.isinf(v) and math.isinf(a)):
            return cls(start, goal, t0, 0.0, 0.0, 0.0, 0)
        if math.isinf(a):
            return cls(start, goal, t0, 0.0, d / v, v, 1)
        if math.isinf(v) or d < v * v / a:
            t_acc = math.sqrt(d / a)
            return cls(start, goal, t0, t_acc, 2 * t_acc, a * t_acc, 2)
        t_acc = v / a
        return cls(start, goal, t0, t_acc, d / v + t_acc, v, 3)

    def at(self, t: float) -> tuple[float, float]:
        """Position and signed velocity (pulses, pulse/s) at time ``t``."""
        tau = t - self.t0
        sign = 1.0 if self.goal >= self.start else -1.0
        if tau >= self.t_total:
            return self.goal, 0.0
        if tau <= 0:
            return self.start, 0.0
        if self.kind == 1:
            return self.start + sign * self.v_peak * tau, sign * self.v_peak
        a = self.v_peak / self.t_acc
        if tau < self.t_acc:
            return self.start + sign * 0.5 * a * tau * tau, sign * a * tau
        cruise = self.t_total - 2 * self.t_acc
        if tau < self.t_acc + cruise:
            s = 0.5 * a * self.t_acc ** 2 + self.v_peak * (tau - self.t_acc)
            return self.start + sign * s, sign * self.v_peak
        rem = self.t_total - tau
        return self.goal - sign * 0.5 * a * rem * rem, sign * a * rem

    def ongoing(self, t: float) -> bool:
        return t - self.t0 < self.t_total


@dataclass
class Servo:
    """A simulated servo. ``clock`` is injectable for tests."""

    dxl_id: int
    model: str = "xm430-w350"
    options: ServoOptions = field(default_factory=ServoOptions)
    clock: Callable[[], float] = time.monotonic
    position_noise: float = 0.0  # pulses, sigma of the present-position reading

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"unknown servo model {self.model!r}; known: {sorted(MODELS)}")
        self.items = _table(self.model)
        self.by_name = {i.name: i for i in self.items}
        self.by_addr = {i.address: i for i in self.items}
        self.values = {i.name: i.default for i in self.items}
        self.values["id"] = self.dxl_id
        self.actual = 2048.0  # true shaft angle, pulses (0..4095 one turn)
        self.profile = Profile(2048.0, 2048.0, self.clock())
        self.registered: tuple[int, bytes] | None = None
        # a stuck shaft (a test's latched fault): the motion clock stops at ``frozen``,
        # armed to stop once a move has run ``freeze_at`` of its profile's time
        self.freeze_at: float | None = None
        self.frozen: float | None = None
        self.last_comm = self.clock()
        self.boot_time = self.clock()
        import random

        self._rng = random.Random(self.dxl_id)

    # -- state ------------------------------------------------------------------

    @property
    def torque(self) -> bool:
        return self.values["torque_enable"] == 1

    def alert(self) -> int:
        return ALERT if self.values["hardware_error_status"] else 0

    def _motion_now(self, now: float) -> float:
        """The time the motion has reached: ``now`` unless the shaft is frozen (an armed
        freeze latches here, at its fraction of the profile, whenever it is looked at)."""
        if self.frozen is None and self.freeze_at is not None and self.profile.t_total > 0 \
                and now - self.profile.t0 >= self.freeze_at * self.profile.t_total:
            self.frozen = self.profile.t0 + self.freeze_at * self.profile.t_total
            self.freeze_at = None
        return now if self.frozen is None else min(now, self.frozen)

    def freeze(self, at_fraction: float) -> None:
        """Stop the shaft once the current or next move has run ``at_fraction`` of its
        profile's time (0 to 1); it stays there, moving, until ``thaw``."""
        if not 0.0 <= at_fraction < 1.0:
            raise ValueError(f"freeze at_fraction {at_fraction} outside [0, 1)")
        self.freeze_at = at_fraction
        self.update()

    def thaw(self) -> None:
        """Let a frozen move go on from where it stopped."""
        now = self.clock()
        self.update()
        if self.frozen is not None:  # the profile resumes where the shaft stopped
            self.profile.t0 += now - max(self.frozen, self.profile.t0)
        self.frozen = self.freeze_at = None

    def update(self) -> None:
        """Bring the present values up to the clock."""
        now = self.clock()
        self._check_watchdog(now)
        motion_now = self._motion_now(now)
        if self.torque:
            pos, vel = self.profile.at(motion_now)
            self.actual = pos
        else:
            vel = 0.0
        v = self.values
        noise = self._rng.gauss(0.0, self.position_noise) if self.position_noise else 0.0
        v["present_position"] = round(self.actual + noise) + v["homing_offset"]
        v["position_trajectory"] = round(self.profile.at(motion_now)[0]) if self.torque else \
            v["present_position"]
        rpm = vel / PULSES_PER_REV * 60.0
        v["present_velocity"] = round(rpm / VELOCITY_UNIT_RPM)
        v["velocity_trajectory"] = v["present_velocity"]
        v["realtime_tick"] = int((now - self.boot_time) * 1000) % 32768
        ongoing = self.torque and self.profile.ongoing(motion_now)
        in_position = abs(v["goal_position"] - v["present_position"]) <= 1 or not self.torque
        v["moving"] = 1 if ongoing or abs(v["present_velocity"]) > v["moving_threshold"] else 0
        v["moving_status"] = ((1 if in_position else 0) | (2 if ongoing else 0)
                              | (self.profile.kind << 4 if ongoing else 0))
        v["present_current"] = int(20 + abs(vel) * 0.01) if self.torque else 0

    def _check_watchdog(self, now: float) -> None:
        wd = self.values["bus_watchdog"]
        if wd > 0 and self.torque and now - self.last_comm > wd * 0.020:
            self._hold(now)
            self.values["bus_watchdog"] = -1

    def _hold(self, now: float) -> None:
        pos, _ = self.profile.at(self._motion_now(now))
        self.actual = pos
        self.profile = Profile(pos, pos, now)
        self.values["goal_position"] = round(pos) + self.values["homing_offset"]

    def touch(self) -> None:
        """Any instruction packet counts as bus traffic for the watchdog."""
        self._check_watchdog(self.clock())
        self.last_comm = self.clock()

    # -- faults -----------------------------------------------------------------

    def inject_hardware_error(self, bits: int) -> None:
        """Set Hardware Error Status bits; errors selected by Shutdown cut torque."""
        self.update()
        self.values["hardware_error_status"] |= bits
        if bits & self.values["shutdown"]:
            self._hold(self.clock())
            self.values["torque_enable"] = 0

    def reboot(self) -> None:
        """RAM back to defaults (torque off, errors cleared); EEPROM and shaft kept."""
        self.update()
        for item in self.items:
            if not item.eeprom:
                self.values[item.name] = item.default
        self.values["goal_position"] = round(self.actual) + self.values["homing_offset"]
        self.profile = Profile(self.actual, self.actual, self.clock())
        self.boot_time = self.clock()
        self.update()

    def factory_reset(self, option: int) -> int:
        """0xFF all, 0x01 all but ID, 0x02 all but ID and baud."""
        if self.torque:
            return ERR_ACCESS
        if option not in (0xFF, 0x01, 0x02):
            return ERR_DATA_RANGE
        keep = {"model_number", "model_information", "firmware_version"}
        if option in (0x01, 0x02):
            keep.add("id")
        if option == 0x02:
            keep.add("baud_rate")
        for item in self.items:
            if item.name not in keep:
                self.values[item.name] = item.default
        if option == 0xFF:
            self.values["id"] = 1
        self.reboot()
        return 0

    # -- memory -----------------------------------------------------------------

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        if length == 0 or address < 0 or address + length > TABLE_END:
            return ERR_ACCESS, b""
        self.update()
        memory = bytearray(TABLE_END)
        for item in self.items:
            value = self.values[item.name]
            memory[item.address:item.address + item.size] = int(value).to_bytes(
                item.size, "little", signed=item.signed)
        return 0, bytes(memory[address:address + length])

    def check_write(self, address: int, data: bytes) -> int:
        """The error a write would give (0 if it is allowed)."""
        end = address + len(data)
        if not data or address < 0 or end > TABLE_END:
            return ERR_ACCESS
        pos = address
        while pos < end:
            item = self.by_addr.get(pos)
            if item is None or item.access != "RW":
                return ERR_ACCESS
            if pos + item.size > end:
                return ERR_DATA_LENGTH
            if item.eeprom and self.torque:
                return ERR_ACCESS
            if item.name in GOAL_ITEMS and self.values["bus_watchdog"] == -1:
                return ERR_ACCESS
            value = int.from_bytes(data[pos - address:pos - address + item.size], "little",
                                   signed=item.signed)
            if item.lo is not None and not item.lo <= value <= item.hi:
                return ERR_DATA_RANGE
            if item.name == "goal_position" and self.values["operating_mode"] == 3 \
                    and self.options.goal_out_of_limit == "reject":
                lo, hi = self.values["min_position_limit"], self.values["max_position_limit"]
                if not lo <= value - self.values["homing_offset"] <= hi:
                    return ERR_DATA_LIMIT
            if item.name == "torque_enable" and value == 1 \
                    and self.values["hardware_error_status"]:
                return ERR_RESULT_FAIL
            pos += item.size
        return 0

    def write(self, address: int, data: bytes) -> int:
        error = self.check_write(address, data)
        if error:
            return error
        self.update()
        pos = address
        while pos < address + len(data):
            item = self.by_addr[pos]
            value = int.from_bytes(data[pos - address:pos - address + item.size], "little",
                                   signed=item.signed)
            self._set(item.name, value)
            pos += item.size
        return 0

    def _set(self, name: str, value: int) -> None:
        now = self.clock()
        v = self.values
        if name == "torque_enable":
            if value == 1 and not self.torque:
                v["torque_enable"] = 1
                if self.options.torque_on_sets_goal_to_present:
                    v["goal_position"] = round(self.actual) + v["homing_offset"]
                self.profile = Profile(self.actual, self.actual, now)
            elif value == 0:
                self._hold(now)
                v["torque_enable"] = 0
            return
        if name == "goal_position":
            lo, hi = v["min_position_limit"], v["max_position_limit"]
            target = value - v["homing_offset"]
            if v["operating_mode"] == 3:
                target = min(max(target, lo), hi)
            v["goal_position"] = int(target + v["homing_offset"])
            if self.torque:
                self._start_move(float(target), now)
            return
        if name == "bus_watchdog" and value == 0:
            v["bus_watchdog"] = 0
            return
        v[name] = value

    def _start_move(self, target: float, now: float) -> None:
        pos, _ = self.profile.at(self._motion_now(now))
        self.actual = pos
        v, a = self.values["profile_velocity"], self.values["profile_acceleration"]
        if self.values["drive_mode"] & 0x04:  # time-based profile: v = total ms, a = accel ms
            t_total = v / 1000.0
            t_acc = min(a / 1000.0, t_total / 2)
            d = abs(target - pos)
            if t_total <= 0 or d == 0:
                self.profile = Profile(pos, target, now)
                return
            v_peak = d / (t_total - t_acc) if t_total > t_acc else math.inf
            kind = 3 if t_acc > 0 else 1
            self.profile = Profile(pos, target, now, t_acc, t_total, v_peak, kind)
            return
        vel = v * VELOCITY_UNIT_RPM / 60.0 * PULSES_PER_REV if v else math.inf
        acc = a * ACCEL_UNIT_RPM2 / 3600.0 * PULSES_PER_REV if a else math.inf
        self.profile = Profile.plan(pos, target, now, vel, acc)

    def dump(self) -> dict:
        self.update()
        return {"id": self.dxl_id, "model": self.model, "actual_pulses": self.actual,
                "frozen": self.frozen is not None,
                **{k: self.values[k] for k in (
                    "torque_enable", "goal_position", "present_position", "moving",
                    "moving_status", "hardware_error_status", "bus_watchdog",
                    "profile_velocity", "profile_acceleration", "return_delay_time",
                    "present_temperature", "present_input_voltage", "drive_mode",
                    "status_return_level")}}
