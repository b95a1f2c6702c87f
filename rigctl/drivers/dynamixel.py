"""``Head`` on ``dynamixel_sdk`` (Protocol 2.0): a pan/tilt/roll head of X-series servos.

Facts this driver is built around (see ``shared/reference/dynamixel-protocol.md``):

- the SDK's ``is_using`` flag is not a lock: every transaction here holds ``self._lock``,
  which other processes on the same bus respect too (``bus_lock``);
- the SDK's group reads drop each servo's error byte, so an Alert (hardware error) is
  found by reading Hardware Error Status (70); the driver does so whenever a servo stops
  short of its goal, at the end of every move, and on any unicast reply whose error byte
  has the Alert bit. The driver receives group replies itself (``_sync_rx``,
  ``_fast_sync_rx``) so that it knows which servo's reply failed and counts every
  servo's error bytes (``bus_stats``);
- a vanished port raises ``termios.error``/``OSError`` (EIO) and leaves the port busy: the
  driver closes it, reopens the same path and retries once;
- CRC errors and timeouts are retried ``retries`` times with a doubling pause
  (``retry_backoff_s``), then ``DeviceError`` names the servo, the time spent and the
  host's load;
- the SDK sets each packet's timeout from its length and a 16 ms USB latency timer;
  ``packet_timeout_ms`` in the rig file raises that floor (a stand-in process on a busy
  host, or a slow adapter); the late reply to a timed-out try is flushed by the SDK,
  which clears the port before every transmission.
"""

from __future__ import annotations

import logging
import math
import termios
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import dynamixel_sdk as sdk

from rigctl.drivers.base import (
    DeviceError,
    Head,
    HeadAngles,
    ProtocolError,
    SafetyError,
    Status,
    load_note,
)
from rigctl.drivers.bus_lock import BusLock
from rigctl.drivers.dynamixel_models import (
    BY_NUMBER,
    STANDARD_BAUDS,
    STATUS_OFFSETS,
    STATUS_SIZE,
    ServoModel,
    by_name,
    model_label,
)
from rigctl.errors import ConfigError

log = logging.getLogger(__name__)

AXES = ("pan", "tilt", "roll")

HW_ERROR_NAMES = {0x01: "input voltage", 0x04: "overheating", 0x08: "motor encoder",
                  0x10: "electrical shock", 0x20: "overload"}
RETRYABLE = (sdk.COMM_RX_TIMEOUT, sdk.COMM_RX_CORRUPT, sdk.COMM_RX_FAIL, sdk.COMM_TX_FAIL)
# EEPROM items the driver sets (the same addresses in every table) and the values it wants.
EEPROM_WANTED = {"return_delay_time": 0, "operating_mode": 3, "drive_mode": 0}
STATUS_HEAD = 14  # Moving .. Present Position: what a move's watch polls
ARRIVED_RAD = 2 * 2 * math.pi / 4096  # arrival tolerance: two X-series pulses, any family


def hw_error_text(bits: int) -> str:
    """The names of the Hardware Error Status bits set in ``bits``."""
    names = [name for bit, name in HW_ERROR_NAMES.items() if bits & bit]
    return ", ".join(names) or f"0x{bits:02x}"


class TimedPortHandler(sdk.PortHandler):
    """The SDK's port with a floor under every packet timeout (``floor_ms``, None: the
    SDK's own timeouts). The SDK calls ``setPacketTimeout``/``setPacketTimeoutMillis``
    before each reception; both are raised to the floor here."""

    def __init__(self, port_name: str, floor_ms: float | None) -> None:
        super().__init__(port_name)
        self.floor_ms = floor_ms

    def setPacketTimeout(self, packet_length):
        super().setPacketTimeout(packet_length)
        if self.floor_ms is not None:
            self.packet_timeout = max(self.packet_timeout, self.floor_ms)

    def setPacketTimeoutMillis(self, msec):
        super().setPacketTimeoutMillis(max(msec, self.floor_ms or 0.0))


def _signed32(value: int) -> int:
    return value - (1 << 32) if value & 0x80000000 else value


@dataclass
class _GroupReply:
    """What a sync read brought back: each servo's data and status error byte, and the
    servo whose reply was missing or corrupt (None: none, or not a servo's fault)."""

    comm: int
    data: dict[int, bytes] = field(default_factory=dict)
    errors: dict[int, int] = field(default_factory=dict)
    failed: int | None = None


FAST_BLOCK_START = 8  # a fast sync read reply: header, ID, length, 0x55, then the blocks


class DynamixelHead(Head):
    """Pan (id ``ids.pan``), tilt and roll servos on one Protocol 2.0 bus.

    Each servo's model number, read when it is pinged, selects its control table,
    resolution and units (``dynamixel_models``); servos whose items sit at one address
    share a sync read or write, a bus that mixes tables uses bulk read (different
    addresses, one packet) and one sync write per address."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self.ids = {axis: getattr(cfg.ids, axis) for axis in AXES}
        self.axis_of = {v: k for k, v in self.ids.items()}
        # every transaction holds it, against this process's other threads and any
        # other process on the same bus (``bus_lock``)
        self._lock = BusLock(self._port_fileno)
        self.port: sdk.PortHandler | None = None
        self.packet = sdk.PacketHandler(2.0)
        self.info: dict[int, dict[str, Any]] = {}
        self.models: dict[int, ServoModel] = {}
        self.eeprom_writes: list[str] = []
        self.retries_used = 0
        # The bus record (versions.json, doctor). Per servo id: transactions addressed to
        # it (unicast, and every sync read or write it is part of), retries and errors
        # its reply caused (a sync read whose reply from servo 2 is missing counts against
        # servo 2), status packets it sent with an error byte and, among those, with the
        # Alert bit (hardware error). "group": the sync packets on the wire, each retry and
        # failure of one whatever its cause. "port": the port lost (EIO) and reopened.
        self.bus_stats: dict[str, dict[str, int]] = {}
        self._stop_event = threading.Event()
        self._motion: threading.Thread | None = None

    # -- conversions --------------------------------------------------------------

    def _model(self, axis: str) -> ServoModel:
        return self.models[self.ids[axis]]

    def _to_pulses(self, axis: str, angle: float) -> int:
        servo_deg = (getattr(self.cfg.direction, axis) * math.degrees(angle)
                     + getattr(self.cfg.zero_offset_deg, axis))
        return self._model(axis).to_pulses(math.radians(servo_deg))

    def _to_angle(self, axis: str, pulses: int) -> float:
        servo_deg = math.degrees(self._model(axis).to_rad(pulses))
        return math.radians((servo_deg - getattr(self.cfg.zero_offset_deg, axis))
                            * getattr(self.cfg.direction, axis))

    def _addr(self, dxl_id: int, item: str) -> int:
        return self.models[dxl_id].table[item][0]

    def _tolerance(self, dxl_id: int) -> int:
        """Arrival tolerance in this servo's pulses (the same angle for every family)."""
        return max(2, math.ceil(ARRIVED_RAD * self.models[dxl_id].pulses_per_rev
                                / (2 * math.pi)))

    def _name(self, dxl_id: int) -> str:
        return f"head servo {dxl_id} ({self.axis_of.get(dxl_id, '?')}) on {self.cfg.port}"

    # -- transport ----------------------------------------------------------------

    def _open_port(self) -> None:
        port = TimedPortHandler(self.cfg.port, self.cfg.packet_timeout_ms)
        try:
            opened = port.openPort()
        except Exception as exc:  # pyserial raises SerialException with the OS reason
            raise DeviceError(f"head: cannot open {self.cfg.port}: {exc}") from None
        if not opened or not port.setBaudRate(self.cfg.baud):
            raise DeviceError(f"head: cannot open {self.cfg.port} at {self.cfg.baud} baud")
        self.port = port
        self._lock.port_opened()  # opened inside a held lock: lock the new file too

    def _port_fileno(self) -> int | None:
        serial_port = getattr(self.port, "ser", None) if self.port is not None else None
        return serial_port.fileno() if serial_port is not None else None

    def _reopen(self) -> None:
        log.warning("head: port %s vanished (EIO); reopening", self.cfg.port)
        try:
            if self.port is not None:
                self.port.closePort()
        except Exception:
            pass
        self.port = None
        self._open_port()

    def _stats(self, key: int | str) -> dict[str, int]:
        if key == "port":
            return self.bus_stats.setdefault("port", {"lost": 0, "reopened": 0})
        if key == "group":
            return self.bus_stats.setdefault(
                "group", {"transactions": 0, "retries": 0, "errors": 0})
        return self.bus_stats.setdefault(str(key), {
            "transactions": 0, "retries": 0, "errors": 0, "error_bytes": 0, "alerts": 0})

    def _count_status(self, dxl_id: int, error: int) -> None:
        """A status packet from ``dxl_id`` arrived with error byte ``error``."""
        if error:
            stats = self._stats(dxl_id)
            stats["error_bytes"] += 1
            if error & 0x80:
                stats["alerts"] += 1

    def _count_try(self, target: int | tuple[int, ...], result) -> int | None:
        """Count the status packets of one try; the servo a failed try is held against."""
        if isinstance(target, tuple):
            reply = result[0]  # _GroupReply of a sync read, None for a sync write
            if reply is None:
                return None
            for dxl_id, error in reply.errors.items():
                self._count_status(dxl_id, error)
            return reply.failed
        if result[1] == sdk.COMM_SUCCESS:
            self._count_status(target, result[2])
        return target

    def _count_failed(self, key: str, group: bool, culprit: int | None) -> None:
        """A try repeated (``key`` "retries") or a transaction failed ("errors")."""
        if group:
            self._stats("group")[key] += 1
        if culprit is not None:
            self._stats(culprit)[key] += 1

    def _call(self, what: str, target: int | tuple[int, ...], fn, *args):
        """Run one SDK transaction ``fn(port, *args) -> (value, comm, error)`` under the lock,
        retrying timeouts and corrupt replies; reopen the port once on EIO.

        ``target``: the servo addressed, or a tuple of the servos a group instruction
        addresses, whose ``fn`` returns a ``_GroupReply`` (sync read) or None (sync
        write) as its value. Every servo addressed counts the transaction; a failed try
        counts against the servo whose reply failed (for a sync write, none: it has no
        reply; for a lost port, none: "port" counts it)."""
        group = isinstance(target, tuple)
        attempts = self.cfg.retries + 1
        last = ""
        reopened = False
        culprit: int | None = None
        t0 = time.monotonic()
        with self._lock:
            for dxl_id in (target if group else (target,)):
                self._stats(dxl_id)["transactions"] += 1
            if group:
                self._stats("group")["transactions"] += 1
            for attempt in range(attempts):
                if attempt:
                    self._count_failed("retries", group, culprit)
                if attempt and self.cfg.retry_backoff_s:
                    time.sleep(self.cfg.retry_backoff_s * 2 ** (attempt - 1))
                if self.port is None:
                    self._open_port()
                try:
                    result = fn(self.port, *args)
                except (termios.error, OSError) as exc:
                    self._stats("port")["lost"] += 1
                    if reopened:
                        self._count_failed("errors", group, None)
                        raise DeviceError(f"head: {self.cfg.port} lost: {exc}") from None
                    reopened = True
                    self._reopen()
                    self._stats("port")["reopened"] += 1
                    culprit = None
                    continue
                culprit = self._count_try(target, result)
                comm = result[1]
                if comm == sdk.COMM_SUCCESS:
                    if attempt:
                        self.retries_used += attempt
                    return result
                last = self.packet.getTxRxResult(comm)
                if comm not in RETRYABLE:
                    break
                log.info("head: %s: %s (try %d/%d)", what, last, attempt + 1, attempts)
            self._count_failed("errors", group, culprit)
        named = target if not group else culprit
        where = self._name(named) if named is not None else f"head bus {self.cfg.port}"
        spent = time.monotonic() - t0
        note = load_note("devices.head.packet_timeout_ms, retries and retry_backoff_s")
        raise DeviceError(f"{where}: {what} failed after {attempts} tries in {spent:.2f} s: "
                          f"{last} ({note})")

    def _check_error(self, dxl_id: int, error: int, what: str) -> None:
        if error & 0x80:
            bits = self._read1(dxl_id, self._addr(dxl_id, "hardware_error_status"),
                               "read hardware error status", check=False)
            raise self._hardware_error(dxl_id, bits)
        if error:
            raise ProtocolError(f"{self._name(dxl_id)}: {what}: "
                                f"{self.packet.getRxPacketError(error)} (error {error})")

    def _read1(self, dxl_id: int, address: int, what: str, check: bool = True) -> int:
        value, _, error = self._call(what, dxl_id, self.packet.read1ByteTxRx, dxl_id, address)
        if check:
            self._check_error(dxl_id, error, what)
        return value

    def _read2(self, dxl_id: int, address: int, what: str) -> int:
        value, _, error = self._call(what, dxl_id, self.packet.read2ByteTxRx, dxl_id, address)
        self._check_error(dxl_id, error, what)
        return value

    def _read4(self, dxl_id: int, address: int, what: str) -> int:
        value, _, error = self._call(what, dxl_id, self.packet.read4ByteTxRx, dxl_id, address)
        self._check_error(dxl_id, error, what)
        return value

    def _write(self, dxl_id: int, address: int, size: int, value: int, what: str) -> None:
        fn = {1: self.packet.write1ByteTxRx, 2: self.packet.write2ByteTxRx,
              4: self.packet.write4ByteTxRx}[size]
        _, _, error = self._call(what, dxl_id, lambda *a: _wrap_write(fn, *a),
                                 dxl_id, address, value)
        self._check_error(dxl_id, error, what)

    def _by_address(self, item: str, ids) -> dict[int, list[int]]:
        """The servos ``ids`` grouped by where ``item`` sits in their control tables."""
        groups: dict[int, list[int]] = {}
        for dxl_id in ids:
            groups.setdefault(self._addr(dxl_id, item), []).append(dxl_id)
        return groups

    def _sync_write(self, item: str, size: int, values: dict[int, int], what: str) -> None:
        """One sync write per address ``item`` sits at (one packet on a single-family bus)."""
        for address, ids in self._by_address(item, values).items():
            def send(port, address=address, ids=ids):
                group = sdk.GroupSyncWrite(port, self.packet, address, size)
                for dxl_id in ids:
                    group.addParam(dxl_id, (values[dxl_id] & 0xFFFFFFFF).to_bytes(size, "little"))
                return None, group.txPacket(), 0

            self._call(what, tuple(ids), send)

    def _group_read(self, item: str, size: int, what: str, fast: bool = True
                    ) -> dict[int, bytes]:
        """``size`` bytes from ``item`` on every servo in one transaction: a (fast) sync
        read where the item sits at one address on every servo, else a (fast) bulk read
        (each servo its own address; the same reply format)."""
        ids = tuple(self.ids.values())
        groups = self._by_address(item, ids)

        def exchange(port):
            if len(groups) == 1:
                group = sdk.GroupSyncRead(port, self.packet, next(iter(groups)), size)
                for dxl_id in ids:
                    group.addParam(dxl_id)
                comm = group.fastSyncReadTxPacket() if fast else group.txPacket()
            else:
                group = sdk.GroupBulkRead(port, self.packet)
                for dxl_id in ids:
                    group.addParam(dxl_id, self._addr(dxl_id, item), size)
                comm = group.fastBulkReadTxPacket() if fast else group.txPacket()
            if comm != sdk.COMM_SUCCESS:
                return _GroupReply(comm), comm, 0  # not sent: no servo's doing
            reply = (self._fast_sync_rx(port, ids, size) if fast
                     else self._sync_rx(port, ids, size))
            return reply, reply.comm, 0

        with self._lock:
            reply, _, _ = self._call(what, ids, exchange)
            for dxl_id in ids:
                if len(reply.data.get(dxl_id, b"")) < size:
                    raise ProtocolError(f"{self._name(dxl_id)}: {what}: no data in the reply")
            return reply.data

    def _sync_rx(self, port, ids: tuple[int, ...], size: int) -> _GroupReply:
        """The replies to a sync read: one status packet per servo, in the order asked
        (``GroupSyncRead.rxPacket``, keeping each error byte and the servo that failed)."""
        reply = _GroupReply(sdk.COMM_SUCCESS)
        for dxl_id in ids:
            data, comm, error = self.packet.readRx(port, dxl_id, size)
            if comm != sdk.COMM_SUCCESS:
                reply.comm, reply.failed = comm, dxl_id
                return reply
            reply.data[dxl_id], reply.errors[dxl_id] = bytes(data), error
        return reply

    def _fast_sync_rx(self, port, ids: tuple[int, ...], size: int) -> _GroupReply:
        """The reply to a fast sync read: one packet of per-servo blocks (error byte, ID,
        data, CRC) in the order asked (``GroupSyncRead.fastSyncReadRxPacket``, keeping
        each error byte). When the packet is missing or corrupt, the servos whose blocks
        arrived whole (each block's CRC is the running CRC of the packet so far, see the
        protocol reference) are cleared and the first one without such a block is the one
        that failed; with nothing received, the first servo asked (its block opens the
        packet)."""
        raw, comm = self.packet.rxPacket(port, True)
        raw = list(raw or [])
        reply = _GroupReply(comm)
        width = size + 4
        complete = comm == sdk.COMM_SUCCESS
        if len(raw) > FAST_BLOCK_START and raw[:3] == [0xFF, 0xFF, 0xFD] \
                and raw[4] == sdk.BROADCAST_ID:
            for k in range(len(ids)):
                start = FAST_BLOCK_START + k * width
                end = start + 2 + size  # the block's CRC follows
                if len(raw) < end + 2:
                    break
                if not complete and (self.packet.updateCRC(0, raw, end)
                                     != raw[end] | raw[end + 1] << 8):
                    break
                dxl_id = raw[start + 1]
                if dxl_id not in ids or dxl_id in reply.data:
                    break
                reply.data[dxl_id], reply.errors[dxl_id] = bytes(raw[start + 2:end]), raw[start]
        missing = [dxl_id for dxl_id in ids if dxl_id not in reply.data]
        if missing:
            reply.failed = missing[0]
            if complete:  # the packet's CRC checked but its blocks are not the servos'
                reply.comm = sdk.COMM_RX_CORRUPT
        return reply

    # -- life cycle -----------------------------------------------------------------

    def open(self) -> None:
        """Ping every servo and check its model against the rig file before anything is
        written; then fix EEPROM where it differs and enable torque without a jump."""
        with self._lock:
            errors = self.connect()
            for axis, dxl_id in self.ids.items():
                self._prepare(axis, dxl_id, errors[dxl_id])
            self._set_profile()
            self.set_torque(True)

    def connect(self) -> dict[int, int]:
        """Open the port, ping every servo and check its model; nothing is written (the
        bus tools' way in). Returns each servo's status error byte."""
        with self._lock:
            self._open_port()
            pinged = {axis: self._ping_axis(axis, dxl_id) for axis, dxl_id in self.ids.items()}
            for axis, dxl_id in self.ids.items():
                self._check_model(axis, dxl_id, pinged[axis][0])
            return {self.ids[axis]: error for axis, (_, error) in pinged.items()}

    def disconnect(self) -> None:
        """Close the port without parking (after ``connect``)."""
        with self._lock:
            if self.port is not None:
                self.port.closePort()
            self.port = None

    def _ping_axis(self, axis: str, dxl_id: int) -> tuple[int, int]:
        """Model number and status error byte of one servo; a servo silent at the rig
        file's baud but answering at another is a rig-file error (exit 2)."""
        try:
            model, _, error = self._call("ping", dxl_id, self.packet.ping, dxl_id)
        except DeviceError as exc:
            found = self._baud_of(dxl_id)
            if found is None or self._answers(dxl_id):
                # silent at the rig file's baud, then answering at it after all: the
                # silence was the bus's or the host's (a stall), not the baud's
                raise exc from None
            raise ConfigError(
                f"devices.head.baud: {self.cfg.baud}, but servo {dxl_id} ({axis}) on "
                f"{self.cfg.port} does not answer at that baud; it answers at {found} baud "
                "(set devices.head.baud, or change the servo's Baud Rate)") from None
        return model, error

    def _answers(self, dxl_id: int) -> bool:
        """Does ``dxl_id`` answer one ping at the rig file's baud now?"""
        return self.packet.ping(self.port, dxl_id)[1] == sdk.COMM_SUCCESS

    def _baud_of(self, dxl_id: int) -> int | None:
        """The standard baud rate ``dxl_id`` answers a ping at (None: none); the port is
        left at the rig file's baud."""
        port = self.port
        try:
            for baud in STANDARD_BAUDS:
                if baud == self.cfg.baud or not port.setBaudRate(baud):
                    continue
                if self.packet.ping(port, dxl_id)[1] == sdk.COMM_SUCCESS:
                    return baud
            return None
        finally:
            port.setBaudRate(self.cfg.baud)

    def _check_model(self, axis: str, dxl_id: int, number: int) -> None:
        model = BY_NUMBER.get(number)
        named = self.cfg.model_of(axis)
        if named is not None and by_name(named).number != number:
            key = "devices.head.model" + (f".{axis}" if not isinstance(self.cfg.model, str)
                                          else "")
            raise ConfigError(
                f"{key}: {named} (model number {by_name(named).number}), but servo {dxl_id} "
                f"({axis}) on {self.cfg.port} reports {model_label(number)} (model number "
                f"{number})")
        if model is None:
            raise DeviceError(f"{self._name(dxl_id)}: model number {number} is not a servo "
                              f"this driver knows (see rigctl.drivers.dynamixel_models)")
        self.models[dxl_id] = model

    def _prepare(self, axis: str, dxl_id: int, error: int) -> None:
        """Firmware, reboot on an alert, EEPROM, and the limits the servo holds."""
        model = self.models[dxl_id]
        table = model.table
        firmware = self._read1(dxl_id, table["firmware_version"][0], "read firmware",
                               check=False)
        self.info[dxl_id] = {"axis": axis, "model": model.number, "model_name": model.name,
                             "firmware": firmware}
        if error & 0x80:
            bits = self._read1(dxl_id, table["hardware_error_status"][0],
                               "read hardware error", check=False)
            log.warning("%s: alert on connect (%s); rebooting", self._name(dxl_id),
                        hw_error_text(bits))
            self._reboot_servo(dxl_id)
        self._configure_eeprom(dxl_id)
        self.info[dxl_id]["position_limits"] = (
            _signed32(self._read4(dxl_id, table["min_position_limit"][0],
                                  "read min position limit")),
            _signed32(self._read4(dxl_id, table["max_position_limit"][0],
                                  "read max position limit")))
        self.info[dxl_id]["temperature_limit_c"] = self._read1(
            dxl_id, table["temperature_limit"][0], "read temperature limit")
        self.info[dxl_id]["voltage_limits_v"] = (
            self._read2(dxl_id, table["min_voltage_limit"][0], "read min voltage limit") / 10,
            self._read2(dxl_id, table["max_voltage_limit"][0], "read max voltage limit") / 10)

    def _reboot_servo(self, dxl_id: int) -> None:
        self._call("reboot", dxl_id, lambda *a: _wrap_write(self.packet.reboot, *a), dxl_id)
        time.sleep(0.05)

    def _configure_eeprom(self, dxl_id: int) -> None:
        table = self.models[dxl_id].table
        for item, wanted in EEPROM_WANTED.items():
            address, size = table[item]
            current = self._read1(dxl_id, address, f"read EEPROM {address}")
            if current != wanted:
                torque = table["torque_enable"][0]
                if self._read1(dxl_id, torque, "read torque"):
                    self._write(dxl_id, torque, 1, 0, "torque off for EEPROM write")
                self._write(dxl_id, address, size, wanted, f"write EEPROM {address}")
                self.eeprom_writes.append(f"id {dxl_id} addr {address}: {current} -> {wanted}")

    def _set_profile(self) -> None:
        ids = self.ids.values()
        velocity = {i: self.models[i].velocity_value(self.cfg.speed_cap_dps) for i in ids}
        acceleration = {i: self.models[i].accel_value(self.cfg.accel_cap_dps2) for i in ids}
        self._sync_write("profile_acceleration", 4, acceleration, "write profile acceleration")
        self._sync_write("profile_velocity", 4, velocity, "write profile velocity")
        self.profile = {"velocity": velocity, "acceleration": acceleration}

    def set_torque(self, enabled: bool) -> None:
        """Torque on: goal := present position first, so the head never jumps."""
        with self._lock:
            for dxl_id in self.ids.values():
                torque = self._addr(dxl_id, "torque_enable")
                if enabled:
                    present = _signed32(self._read4(dxl_id, self._addr(dxl_id, "present_position"),
                                                    "read present position"))
                    if self._read1(dxl_id, torque, "read torque") == 0:
                        # The goal item is writable with torque off; align it to present.
                        self._write(dxl_id, self._addr(dxl_id, "goal_position"), 4,
                                    present & 0xFFFFFFFF, "align goal")
                self._write(dxl_id, torque, 1, int(enabled), "write torque enable")

    def close(self) -> None:
        if self.port is None:
            return
        policy = self.cfg.park.policy
        try:
            if policy in ("home", "home_then_torque_off"):
                pan, tilt, roll = (math.radians(a) for a in self.cfg.park.angles_deg)
                self.move_to(pan, tilt, roll).wait(self.cfg.move_timeout_s)
            if policy in ("torque_off", "home_then_torque_off"):
                self.set_torque(False)
        finally:
            with self._lock:
                if self.port is not None:
                    self.port.closePort()
                self.port = None

    def describe(self) -> dict[str, Any]:
        models = sorted({v["model_name"] for v in self.info.values()})
        return {"model": models[0] if len(models) == 1 else models, "port": self.cfg.port,
                "baud": self.cfg.baud,
                "servos": {str(k): v for k, v in self.info.items()},
                "firmware": sorted({v["firmware"] for v in self.info.values()}),
                "profile": getattr(self, "profile", None), "eeprom_writes": self.eeprom_writes,
                "bus_stats": {k: dict(v) for k, v in self.bus_stats.items()},
                "sdk": getattr(sdk, "__version__", "dynamixel-sdk")}

    def limits(self) -> dict[str, tuple[float, float]]:
        return self.cfg.limits_rad()

    # -- servo health ---------------------------------------------------------------

    def health(self) -> dict[str, dict[str, Any]]:
        """Per axis: present temperature, input voltage and load (one group read), the
        hardware error status, and the servo's own limits."""
        data = self._group_read("moving", STATUS_SIZE, "fast sync read servo health")
        errors = self.hardware_errors()
        out = {}
        for axis, dxl_id in self.ids.items():
            raw, model, info = data[dxl_id], self.models[dxl_id], self.info.get(dxl_id, {})
            load = int.from_bytes(raw[4:6], "little", signed=True) * model.load_unit
            out[axis] = {
                "id": dxl_id, "model": model.name,
                "temperature_c": raw[STATUS_OFFSETS["temperature"]],
                "voltage_v": int.from_bytes(raw[22:24], "little") / 10.0,
                **({"current_a": load / 1000.0} if model.load == "current"
                   else {"load_pct": load}),
                "hardware_error": errors.get(dxl_id, 0),
                "temperature_limit_c": info.get("temperature_limit_c"),
                "voltage_limits_v": info.get("voltage_limits_v")}
        return out

    def check_health(self, health: dict[str, dict[str, Any]]) -> None:
        """Raise ``DeviceError`` naming the servo when one reached its temperature limit
        or reports a hardware error (an alert)."""
        for h in health.values():
            name = self._name(h["id"])
            if h["hardware_error"]:
                bits = hw_error_text(h["hardware_error"])
                raise DeviceError(f"{name}: alert: hardware error ({bits}); temperature "
                                  f"{h['temperature_c']} C, input voltage {h['voltage_v']:.1f} V")
            limit = h.get("temperature_limit_c")
            if limit is not None and h["temperature_c"] >= limit:
                raise DeviceError(f"{name}: temperature {h['temperature_c']} C reached its "
                                  f"limit of {limit} C (Temperature Limit, address 31); "
                                  f"let it cool")

    def reboot(self, axis: str) -> dict[str, Any]:
        """Reboot one servo (clears an alert), then read its hardware error status."""
        dxl_id = self.ids[axis]
        with self._lock:
            before = self._read1(dxl_id, self._addr(dxl_id, "hardware_error_status"),
                                 "read hardware error status", check=False)
            self._reboot_servo(dxl_id)
            after = self._read1(dxl_id, self._addr(dxl_id, "hardware_error_status"),
                                "read hardware error status", check=False)
        return {"axis": axis, "id": dxl_id, "model": self.models[dxl_id].name,
                "hardware_error_before": before, "before": hw_error_text(before) if before
                else "none", "hardware_error_after": after,
                "after": hw_error_text(after) if after else "none"}

    # -- motion -------------------------------------------------------------------

    def read_angles(self) -> HeadAngles:
        t0 = time.time()
        data = self._group_read("present_position", 4, "fast sync read present position")
        t1 = time.time()
        angles = {axis: self._to_angle(axis, _signed32(int.from_bytes(data[i], "little")))
                  for axis, i in self.ids.items()}
        return HeadAngles(angles["pan"], angles["tilt"], angles["roll"], (t0 + t1) / 2)

    def read_status(self) -> dict[int, dict[str, int]]:
        """Moving, moving status and present position of every servo (one fast read)."""
        data = self._group_read("moving", STATUS_HEAD, "fast sync read status")
        return {dxl_id: {"moving": raw[0], "moving_status": raw[1],
                         "position": _signed32(int.from_bytes(raw[10:14], "little"))}
                for dxl_id, raw in data.items()}

    def hardware_errors(self) -> dict[int, int]:
        data = self._group_read("hardware_error_status", 1, "sync read hardware error status",
                                fast=False)
        return {dxl_id: raw[0] for dxl_id, raw in data.items() if raw[0]}

    def _raise_hardware_errors(self) -> None:
        errors = self.hardware_errors()
        if errors:
            dxl_id, bits = next(iter(errors.items()))
            raise self._hardware_error(dxl_id, bits)

    def _hardware_error(self, dxl_id: int, bits: int) -> DeviceError:
        """The error to raise for Hardware Error Status ``bits``; says whether the servo
        shut its torque off (only errors in its Shutdown mask, address 63, do)."""
        try:
            torque = self._read1(dxl_id, self._addr(dxl_id, "torque_enable"),
                                 "read torque enable", check=False)
            after = ("torque is off until a reboot" if not torque else
                     "torque stays on (not a shutdown condition); fix the cause")
        except DeviceError:
            after = "the servo no longer answers"
        return DeviceError(f"{self._name(dxl_id)}: hardware error ({hw_error_text(bits)}); "
                           f"{after}")

    def move_to(self, pan: float, tilt: float, roll: float) -> Status:
        """Sync-write the goals, then watch arrival with fast sync reads in a thread."""
        self.check_limits(pan, tilt, roll)
        targets = {self.ids[a]: self._to_pulses(a, v)
                   for a, v in zip(AXES, (pan, tilt, roll), strict=True)}
        for dxl_id, goal in targets.items():
            lo, hi = self.info.get(dxl_id, {}).get("position_limits",
                                                   self.models[dxl_id].position_range)
            if not lo <= goal <= hi:
                raise SafetyError(f"{self._name(dxl_id)}: goal {goal} pulses outside the servo's "
                                  f"position limits [{lo}, {hi}] (check zero_offset_deg)")
        if self._motion is not None and self._motion.is_alive():
            self._stop_event.set()
            self._motion.join(timeout=2)
        self._stop_event.clear()
        status = Status(f"head move to pan {math.degrees(pan):.2f}, tilt "
                        f"{math.degrees(tilt):.2f}, roll {math.degrees(roll):.2f} deg")
        start = {k: v["position"] for k, v in self.read_status().items()}
        self._sync_write("goal_position", 4, targets, "sync write goal position")
        # Sync write has no reply: read the goals back so a refused goal is not a silent hang.
        written = self._group_read("goal_position", 4, "fast sync read goal position")
        for dxl_id, goal in targets.items():
            got = _signed32(int.from_bytes(written[dxl_id], "little"))
            if got != goal:
                raise DeviceError(f"{self._name(dxl_id)}: goal {goal} not accepted (servo "
                                  f"holds {got}); torque off or goal out of range?")
        self._motion = threading.Thread(target=self._watch, args=(status, start, targets),
                                        name="head-move", daemon=True)
        self._motion.start()
        return status

    def _remaining(self, targets: dict[int, int], state: dict) -> tuple[float, bool, bool]:
        """The largest distance to go (radians), whether every servo arrived, and whether
        one stopped short of its goal."""
        remaining, arrived, stalled = 0.0, True, False
        for i, s in state.items():
            off = abs(targets[i] - s["position"])
            remaining = max(remaining, off * 2 * math.pi / self.models[i].pulses_per_rev)
            near = off <= self._tolerance(i)
            arrived &= s["moving"] == 0 and bool(s["moving_status"] & 0x01) and near
            stalled |= s["moving"] == 0 and not s["moving_status"] & 0x02 and not near
        return remaining, arrived, stalled

    def _watch(self, status: Status, start: dict[int, int], targets: dict[int, int]) -> None:
        deadline = time.monotonic() + self.cfg.move_timeout_s
        span = max(max(abs(targets[i] - start[i]) * 2 * math.pi / self.models[i].pulses_per_rev
                       for i in targets), ARRIVED_RAD)
        polls = 0
        try:
            while True:
                if self._stop_event.is_set():
                    raise SafetyError("head move stopped")
                state = self.read_status()
                polls += 1
                remaining, arrived, stalled = self._remaining(targets, state)
                status.set_progress(1.0 - remaining / span)
                if arrived:
                    self._raise_hardware_errors()
                    status.set_finished()
                    return
                if stalled or polls % 25 == 0:
                    self._raise_hardware_errors()  # an Alert is possible: look for it
                if time.monotonic() > deadline:
                    raise DeviceError(f"head: move not finished after {self.cfg.move_timeout_s}"
                                      f" s (remaining {math.degrees(remaining):.2f} deg)")
                time.sleep(0.01)
        except Exception as exc:
            status.set_exception(exc)

    def stop(self) -> None:
        """Hold where the head is now: goal := present position on every servo."""
        self._stop_event.set()
        if self.port is None:
            return
        try:
            present = {k: v["position"] for k, v in self.read_status().items()}
            self._sync_write("goal_position", 4, present, "sync write goal (stop)")
        except DeviceError as exc:
            log.error("head stop: %s", exc)
            raise


def scan_bus(port_name: str, bauds: tuple[int, ...] = STANDARD_BAUDS) -> list[dict[str, Any]]:
    """Broadcast ping at each baud rate in ``bauds``: every servo that answers, with its
    ID, model (lower case), model number, firmware and baud."""
    port = sdk.PortHandler(port_name)
    try:
        opened = port.openPort()
    except Exception as exc:
        raise DeviceError(f"head scan: cannot open {port_name}: {exc}") from None
    if not opened:
        raise DeviceError(f"head scan: cannot open {port_name}")
    packet = sdk.PacketHandler(2.0)
    found = []
    try:
        for baud in bauds:
            if not port.setBaudRate(baud):
                continue
            servos, _ = packet.broadcastPing(port)
            for dxl_id, (number, firmware) in sorted(servos.items()):
                found.append({"id": dxl_id, "model": model_label(number),
                              "model_number": number, "firmware": firmware, "baud": baud})
    finally:
        port.closePort()
    return found


def _wrap_write(fn, *args):
    """Normalise SDK write/reboot results ``(comm, error)`` to ``(None, comm, error)``."""
    comm, error = fn(*args)
    return None, comm, error
