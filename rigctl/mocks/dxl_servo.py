"""One simulated servo of any family the stand-in knows: control table, access rules,
trapezoidal motion, encoder, temperature and supply, faults.

The tables and units are the stand-in's own transcription of the ROBOTIS e-Manual
(``dxl_models``). Behaviour the e-Manual leaves open is configurable through
``ServoOptions``.

Encoder as on hardware (``encoder="hardware"``): the true shaft angle is continuous (a
move ends within half a pulse of its goal, as a position loop holds it), and a reading
is that angle plus noise (the model's ``noise_ticks`` pulses, sigma), quantized to one
pulse. ``encoder="ideal"`` (the default) ends every move exactly on its goal pulse and
reads it without noise; ``position_noise`` adds noise (pulses, sigma) in either mode.

Heating: with ``heating_c_per_s`` set, the temperature climbs while torque is on, faster
under load, and cools towards ``ambient_c``; at the Temperature Limit the servo raises
its overheating error (shutting torque off when Shutdown selects it, as by default).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from rigctl.mocks.dxl_models import SPEC_BY_NAME, items_of, table_end

# Error numbers of the status packet (bits 0-6), and the Alert bit.
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC = 1, 2, 3
ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = 4, 5, 6, 7
ALERT = 0x80

# Hardware Error Status (70) bits.
HW_VOLTAGE, HW_OVERHEAT, HW_ENCODER, HW_SHOCK, HW_OVERLOAD = 0x01, 0x04, 0x08, 0x10, 0x20
HW_ERRORS = {"voltage": HW_VOLTAGE, "overheat": HW_OVERHEAT, "encoder": HW_ENCODER,
             "shock": HW_SHOCK, "overload": HW_OVERLOAD}

MODELS = {name: spec.number for name, spec in SPEC_BY_NAME.items()}
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
    encoder: str = "ideal"  # or "hardware": continuous true angle, the model's noise
    seed: int | None = None

    def __post_init__(self) -> None:
        if self.model not in SPEC_BY_NAME:
            raise ValueError(f"unknown servo model {self.model!r}; known: {sorted(MODELS)}")
        if self.encoder not in ("ideal", "hardware"):
            raise ValueError(f"encoder {self.encoder!r}: 'ideal' or 'hardware'")
        self.spec = SPEC_BY_NAME[self.model]
        self.table_end = table_end(self.spec)
        self.items = items_of(self.spec)
        self.by_name = {i.name: i for i in self.items}
        self.by_addr = {i.address: i for i in self.items}
        self.values = {i.name: i.default for i in self.items}
        self.values["id"] = self.dxl_id
        center = float(self.spec.center)
        self.actual = center  # true shaft angle, pulses of this model (centre: 0 rad)
        self.profile = Profile(center, center, self.clock())
        self.registered: tuple[int, bytes] | None = None
        # a stuck shaft (a test's latched fault): the motion clock stops at ``frozen``,
        # armed to stop once a move has run ``freeze_at`` of its profile's time
        self.freeze_at: float | None = None
        self.freeze_armed = 0.0  # when it was armed: a move over by then is not held
        self.frozen: float | None = None
        self.last_comm = self.clock()
        self.boot_time = self.clock()
        self.temperature = float(self.values["present_temperature"])
        self.ambient_c = self.temperature
        self.heating_c_per_s = 0.0
        self.cooling_s = 300.0
        self._last_update = self.clock()
        import random

        self._rng = random.Random(self.dxl_id if self.seed is None else self.seed)
        noise = self.spec.noise_ticks if self.encoder == "hardware" else 0.0
        self.noise = math.hypot(noise, self.position_noise)

    # -- state ------------------------------------------------------------------

    @property
    def torque(self) -> bool:
        return self.values["torque_enable"] == 1

    def alert(self) -> int:
        return ALERT if self.values["hardware_error_status"] else 0

    def angle_rad(self) -> float:
        """The true shaft angle, radians from the centre (what a camera on it sees)."""
        return (self.actual - self.spec.center) * 2 * math.pi / self.spec.pulses_per_rev

    def _motion_now(self, now: float) -> float:
        """The time the motion has reached: ``now`` unless the shaft is frozen (an armed
        freeze latches here, at its fraction of the profile, whenever it is looked at; a
        move that had ended when the freeze was armed is not held, and one past the
        fraction then is held where it was, never taken back)."""
        p = self.profile
        if self.frozen is None and self.freeze_at is not None and p.t_total > 0 \
                and p.t0 + p.t_total > self.freeze_armed \
                and now - p.t0 >= self.freeze_at * p.t_total:
            self.frozen = max(p.t0 + self.freeze_at * p.t_total, self.freeze_armed)
            self.freeze_at = None
        return now if self.frozen is None else min(now, self.frozen)

    def freeze(self, at_fraction: float) -> None:
        """Hold the move under way, or the next one, once it has run ``at_fraction`` of
        its profile's time (0 to 1): the shaft stays there, moving, until ``thaw`` or
        until a new goal position ends that move (as a stop or a park writes one)."""
        if not 0.0 <= at_fraction < 1.0:
            raise ValueError(f"freeze at_fraction {at_fraction} outside [0, 1)")
        self.update()
        self.freeze_at, self.freeze_armed = at_fraction, self.clock()
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
        noise = self._rng.gauss(0.0, self.noise) if self.noise else 0.0
        v["present_position"] = round(self.actual + noise) + v["homing_offset"]
        v["position_trajectory"] = round(self.profile.at(motion_now)[0]) if self.torque else \
            v["present_position"]
        rpm = vel / self.spec.pulses_per_rev * 60.0
        v["present_velocity"] = round(rpm / self.spec.velocity_rpm)
        v["velocity_trajectory"] = v["present_velocity"]
        v["realtime_tick"] = int((now - self.boot_time) * 1000) % 32768
        ongoing = self.torque and self.profile.ongoing(motion_now)
        in_position = (abs(v["goal_position"] - v["homing_offset"] - self.actual) <= 1
                       or not self.torque)
        v["moving"] = 1 if ongoing or abs(v["present_velocity"]) > v["moving_threshold"] else 0
        v["moving_status"] = ((1 if in_position else 0) | (2 if ongoing else 0)
                              | (self.profile.kind << 4 if ongoing else 0))
        self._update_load_and_heat(now, vel)

    def _update_load_and_heat(self, now: float, vel: float) -> None:
        """Present current (or load) from the motion; temperature from load and time."""
        v = self.values
        peak = v["velocity_limit"] * self.spec.velocity_rpm / 60.0 * self.spec.pulses_per_rev
        load = (0.05 + 0.3 * min(abs(vel) / peak, 1.0)) if self.torque and peak else 0.0
        if self.spec.load_item == "present_current":
            v["present_current"] = round(load * v.get("current_limit", 1000))
        else:
            v["present_load"] = round(load * 1000)  # 0.1 %
        dt, self._last_update = max(now - self._last_update, 0.0), now
        if self.torque and self.heating_c_per_s:
            self.temperature += self.heating_c_per_s * (0.5 + 5.0 * load) * dt
        self.temperature -= (self.temperature - self.ambient_c) * min(dt / self.cooling_s, 1.0)
        v["present_temperature"] = max(0, min(255, round(self.temperature)))
        if v["present_temperature"] >= v["temperature_limit"] \
                and not v["hardware_error_status"] & HW_OVERHEAT:
            self._raise_error(HW_OVERHEAT, now)

    def set_supply(self, volts: float) -> None:
        """The supply voltage; outside the servo's voltage limits it raises its input
        voltage error (torque stays on unless Shutdown selects that error)."""
        self.values["present_input_voltage"] = round(10 * volts)
        v = self.values["present_input_voltage"]
        if not self.values["min_voltage_limit"] <= v <= self.values["max_voltage_limit"]:
            self.inject_hardware_error(HW_VOLTAGE)

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
        self._raise_error(bits, self.clock())

    def _raise_error(self, bits: int, now: float) -> None:
        self.values["hardware_error_status"] |= bits
        if bits & self.values["shutdown"]:
            self._hold(now)
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
        if length == 0 or address < 0 or address + length > self.table_end:
            return ERR_ACCESS, b""
        self.update()
        memory = bytearray(self.table_end)
        for item in self.items:
            value = self.values[item.name]
            memory[item.address:item.address + item.size] = int(value).to_bytes(
                item.size, "little", signed=item.signed)
        return 0, bytes(memory[address:address + length])

    def check_write(self, address: int, data: bytes) -> int:
        """The error a write would give (0 if it is allowed)."""
        end = address + len(data)
        if not data or address < 0 or end > self.table_end:
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
        self.frozen = None  # a new goal ends a held move: the new one starts where it is
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
        ppr = self.spec.pulses_per_rev
        vel = v * self.spec.velocity_rpm / 60.0 * ppr if v else math.inf
        acc = a * self.spec.accel_rpm2 / 3600.0 * ppr if a else math.inf
        self.profile = Profile.plan(pos, target + self._settle_error(), now, vel, acc)

    def _settle_error(self) -> float:
        """Where the true angle ends against the goal pulse: anywhere within half a pulse
        for a hardware encoder (the reading is quantized, the shaft is not), 0 ideal."""
        return self._rng.uniform(-0.5, 0.5) if self.encoder == "hardware" else 0.0

    def dump(self) -> dict:
        self.update()
        return {"id": self.dxl_id, "model": self.model, "actual_pulses": self.actual,
                "actual_rad": self.angle_rad(), "pulses_per_rev": self.spec.pulses_per_rev,
                "heating_c_per_s": self.heating_c_per_s,
                "frozen": self.frozen is not None,
                **{k: self.values[k] for k in (
                    "torque_enable", "goal_position", "present_position", "moving",
                    "moving_status", "hardware_error_status", "bus_watchdog",
                    "profile_velocity", "profile_acceleration", "return_delay_time",
                    "present_temperature", "present_input_voltage", "drive_mode",
                    "status_return_level")}}
