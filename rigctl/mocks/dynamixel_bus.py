"""A Dynamixel Protocol 2.0 servo bus on a pty, driven by the real ``dynamixel_sdk``.

Run as its own process (the SDK busy-waits; a thread in the client's interpreter would
add GIL contention)::

    rigctl mock head --link /tmp/dxl [--ids 1 2 3] [--model xh540-w270 [M ...]] \
        [--baud 1000000 [B ...]] [--encoder ideal|hardware] [--wire-timing] \
        [--control /tmp/dxl.sock]

``--model`` and ``--baud``: one for every ID, or one per ID (a mixed bus: e.g.
``--model xh540-w270 xh540-w270 xm430-w350``). Each servo plays its model's control
table from the stand-in's own transcription (``dxl_models``).

It prints one JSON ready line ``{"port", "link", "pid", "control"}`` and runs until
SIGTERM or SIGINT, then removes the link and the control socket.

Control socket (JSON lines, one reply line per request)::

    {"cmd": "corrupt_next"}   {"cmd": "drop_next"}   {"cmd": "delay_next", "seconds": 0.1}
    {"cmd": "hw_error", "id": 2, "error": "overload"}     (overload|overheat|voltage|...)
    {"cmd": "set", "id": 1, "temperature": 70, "voltage": 11.1}   (no "id": every servo)
    {"cmd": "set", "id": 1, "heating_c_per_s": 2.0}   (heat under load; 0 stops heating)
    {"cmd": "dump"}           {"cmd": "stats"}
    {"cmd": "freeze", "id": 1, "at_fraction": 0.5}   {"cmd": "thaw", "id": 1}
        (a held move, latched: once the move under way or the next one has run that
        fraction of its profile's time it stays there, still moving, until thawed or until
        a new goal position ends that move)
"""

from __future__ import annotations

import argparse
import json
import os
import selectors
import signal
import sys
import termios
import time
import tty
from pathlib import Path

from rigctl.mocks.dxl_codec import (
    BROADCAST_ID,
    BadPacket,
    Packet,
    PacketParser,
    crc16,
    status_packet,
)
from rigctl.mocks.dxl_models import SPEC_BY_NAME
from rigctl.mocks.dxl_servo import (
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_INSTRUCTION,
    HW_ERRORS,
    MODELS,
    Servo,
    ServoOptions,
)
from rigctl.mocks.jsonlines import answer, listen

BAUD_CODES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}
_SPEEDS = {getattr(termios, f"B{b}"): b for b in BAUD_CODES.values() if hasattr(termios, f"B{b}")}

PING, READ, WRITE, REG_WRITE, ACTION, FACTORY_RESET, REBOOT, CLEAR = 1, 2, 3, 4, 5, 6, 8, 0x10
SYNC_READ, SYNC_WRITE, FAST_SYNC_READ = 0x82, 0x83, 0x8A
BULK_READ, BULK_WRITE, FAST_BULK_READ = 0x92, 0x93, 0x9A


def _u16(data: bytes, i: int) -> int:
    return data[i] | (data[i + 1] << 8)


class Bus:
    """The servos on one bus and the instruction semantics; no I/O here."""

    def __init__(self, servos: list[Servo], crc_error_reply: bool = True) -> None:
        self.servos = {s.dxl_id: s for s in servos}
        self.crc_error_reply = crc_error_reply
        self.stats = {"packets": 0, "bad_crc": 0, "replies": 0, "dropped_bytes": 0}

    def _targets(self, dxl_id: int) -> list[Servo]:
        if dxl_id == BROADCAST_ID:
            return list(self.servos.values())
        return [self.servos[dxl_id]] if dxl_id in self.servos else []

    def _reply(self, servo: Servo, error: int, params: bytes = b"", level: int = 2) -> bytes:
        if servo.values["status_return_level"] < level:
            return b""
        return status_packet(servo.dxl_id, error | servo.alert(), params)

    def handle(self, packet: Packet | BadPacket) -> list[tuple[Servo, bytes]]:
        """Replies in bus order, each with the servo that sends it (for its delay)."""
        self.stats["packets"] += 1
        if isinstance(packet, BadPacket):
            self.stats["bad_crc"] += 1
            servo = self.servos.get(packet.dxl_id)
            if servo is None or not self.crc_error_reply:
                return []
            return [(servo, self._reply(servo, ERR_CRC))]
        for servo in self._touched(packet):
            servo.touch()
        handler = {PING: self._ping, READ: self._read, WRITE: self._write,
                   REG_WRITE: self._reg_write, ACTION: self._action,
                   FACTORY_RESET: self._factory_reset, REBOOT: self._reboot, CLEAR: self._clear,
                   SYNC_READ: self._sync_read, FAST_SYNC_READ: self._fast_sync_read,
                   SYNC_WRITE: self._sync_write, BULK_READ: self._bulk_read,
                   FAST_BULK_READ: self._fast_bulk_read, BULK_WRITE: self._bulk_write,
                   }.get(packet.instruction)
        if handler is None:
            servo = self.servos.get(packet.dxl_id)
            return [(servo, self._reply(servo, ERR_INSTRUCTION))] if servo else []
        replies = handler(packet)
        return [(s, r) for s, r in replies if r]

    def _touched(self, packet: Packet) -> list[Servo]:
        if packet.dxl_id != BROADCAST_ID:
            return self._targets(packet.dxl_id)
        return list(self.servos.values())

    # -- single-servo instructions ---------------------------------------------------

    def _ping(self, p: Packet):
        out = []
        for servo in self._targets(p.dxl_id):
            model = servo.values["model_number"]
            params = bytes([model & 0xFF, model >> 8, servo.values["firmware_version"]])
            out.append((servo, status_packet(servo.dxl_id, servo.alert(), params)))
        return out

    def _read(self, p: Packet):
        if p.dxl_id == BROADCAST_ID or p.dxl_id not in self.servos:
            return []
        servo = self.servos[p.dxl_id]
        if len(p.params) != 4:
            return [(servo, self._reply(servo, ERR_DATA_LENGTH, level=1))]
        error, data = servo.read(_u16(p.params, 0), _u16(p.params, 2))
        return [(servo, self._reply(servo, error, data, level=1))]

    def _write(self, p: Packet):
        out = []
        for servo in self._targets(p.dxl_id):
            if len(p.params) < 3:
                error = ERR_DATA_LENGTH
            else:
                error = servo.write(_u16(p.params, 0), p.params[2:])
            if p.dxl_id != BROADCAST_ID:
                out.append((servo, self._reply(servo, error)))
        return out

    def _reg_write(self, p: Packet):
        out = []
        for servo in self._targets(p.dxl_id):
            error = ERR_DATA_LENGTH if len(p.params) < 3 else servo.check_write(
                _u16(p.params, 0), p.params[2:])
            if not error:
                servo.registered = (_u16(p.params, 0), bytes(p.params[2:]))
                servo.values["registered_instruction"] = 1
            if p.dxl_id != BROADCAST_ID:
                out.append((servo, self._reply(servo, error)))
        return out

    def _action(self, p: Packet):
        out = []
        for servo in self._targets(p.dxl_id):
            if servo.registered is None:
                error = ERR_INSTRUCTION
            else:
                error = servo.write(*servo.registered)
                servo.registered = None
                servo.values["registered_instruction"] = 0
            if p.dxl_id != BROADCAST_ID:
                out.append((servo, self._reply(servo, error)))
        return out

    def _factory_reset(self, p: Packet):
        out = []
        option = p.params[0] if p.params else 0xFF
        for servo in self._targets(p.dxl_id):
            error = servo.factory_reset(option)
            if p.dxl_id != BROADCAST_ID:
                out.append((servo, self._reply(servo, error)))
        if option == 0xFF:  # IDs reset to 1: re-key the bus
            self.servos = {s.dxl_id: s for s in self.servos.values()}
            for servo in list(self.servos.values()):
                servo.dxl_id = servo.values["id"]
            self.servos = {s.dxl_id: s for s in self.servos.values()}
        return out

    def _reboot(self, p: Packet):
        out = []
        for servo in self._targets(p.dxl_id):
            if p.dxl_id != BROADCAST_ID:
                out.append((servo, self._reply(servo, 0)))  # the reply goes out before reboot
            servo.reboot()
        return out

    def _clear(self, p: Packet):
        return [(s, self._reply(s, 0)) for s in self._targets(p.dxl_id)
                if p.dxl_id != BROADCAST_ID]

    # -- group instructions -----------------------------------------------------------

    def _sync_read(self, p: Packet):
        if p.dxl_id != BROADCAST_ID or len(p.params) < 5:
            return []
        address, length = _u16(p.params, 0), _u16(p.params, 2)
        out = []
        for dxl_id in p.params[4:]:
            servo = self.servos.get(dxl_id)
            if servo is not None:
                error, data = servo.read(address, length)
                out.append((servo, self._reply(servo, error, data, level=1)))
        return out

    def _fast_reply(self, blocks: list[tuple[Servo, int, bytes]]) -> bytes:
        """One packet from 0xFE: per servo ``ERR ID data CRC``, each CRC running over the
        packet so far; the last CRC is the packet's own."""
        size = sum(len(d) + 4 for _, _, d in blocks)
        length = 1 + size  # instruction + blocks (the final CRC is the last block's)
        packet = bytearray(b"\xff\xff\xfd\x00" + bytes([BROADCAST_ID, length & 0xFF,
                                                         length >> 8, 0x55]))
        for servo, error, data in blocks:
            packet += bytes([error | servo.alert(), servo.dxl_id]) + data
            crc = crc16(bytes(packet))
            packet += bytes([crc & 0xFF, crc >> 8])
        return bytes(packet)

    def _fast_sync_read(self, p: Packet):
        if p.dxl_id != BROADCAST_ID or len(p.params) < 5:
            return []
        address, length = _u16(p.params, 0), _u16(p.params, 2)
        blocks = []
        for dxl_id in p.params[4:]:
            servo = self.servos.get(dxl_id)
            if servo is not None:
                error, data = servo.read(address, length)
                blocks.append((servo, error, data.ljust(length, b"\0")))
        if not blocks:
            return []
        return [(blocks[-1][0], self._fast_reply(blocks))]

    def _sync_write(self, p: Packet):
        if len(p.params) < 4:
            return []
        address, length = _u16(p.params, 0), _u16(p.params, 2)
        body = p.params[4:]
        for i in range(0, len(body) - length, length + 1):
            servo = self.servos.get(body[i])
            if servo is not None:
                servo.write(address, body[i + 1:i + 1 + length])
        return []

    def _bulk_entries(self, params: bytes):
        for i in range(0, len(params) - 4, 5):
            yield params[i], _u16(params, i + 1), _u16(params, i + 3)

    def _bulk_read(self, p: Packet):
        out = []
        for dxl_id, address, length in self._bulk_entries(p.params):
            servo = self.servos.get(dxl_id)
            if servo is not None:
                error, data = servo.read(address, length)
                out.append((servo, self._reply(servo, error, data, level=1)))
        return out

    def _fast_bulk_read(self, p: Packet):
        blocks = []
        for dxl_id, address, length in self._bulk_entries(p.params):
            servo = self.servos.get(dxl_id)
            if servo is not None:
                error, data = servo.read(address, length)
                blocks.append((servo, error, data.ljust(length, b"\0")))
        return [(blocks[-1][0], self._fast_reply(blocks))] if blocks else []

    def _bulk_write(self, p: Packet):
        params, i = p.params, 0
        while i + 5 <= len(params):
            dxl_id, address, length = params[i], _u16(params, i + 1), _u16(params, i + 3)
            servo = self.servos.get(dxl_id)
            if servo is not None:
                servo.write(address, params[i + 5:i + 5 + length])
            i += 5 + length
        return []


def _spin_until(deadline: float) -> None:
    """Sleep coarsely, then spin: wire times are tens of microseconds."""
    remaining = deadline - time.perf_counter()
    if remaining > 0.002:
        time.sleep(remaining - 0.0015)
    while time.perf_counter() < deadline:
        pass


class BusServer:
    """The pty, the wire-time emulation, fault injection and the control socket."""

    def __init__(self, bus: Bus, link: Path, control: Path | None, wire_timing: bool,
                 latency_timer_s: float = 0.0) -> None:
        self.bus = bus
        self.latency_timer_s = latency_timer_s
        self.link = link
        self.control_path = control
        self.wire_timing = wire_timing
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # raw at once: no echo, no line discipline
        attrs = termios.tcgetattr(self.slave)
        attrs[4] = attrs[5] = termios.B1000000
        termios.tcsetattr(self.slave, termios.TCSANOW, attrs)
        os.set_blocking(self.master, False)
        self.port_name = os.ttyname(self.slave)
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(self.port_name)
        self.parser = PacketParser()
        self.faults = {"corrupt_next": 0, "drop_next": 0, "delay_next": 0.0}
        self.selector = selectors.DefaultSelector()
        self.selector.register(self.master, selectors.EVENT_READ, "bus")
        self.control_sock = None
        if control is not None:
            self.control_sock = listen(control)
            self.control_sock.setblocking(False)
            self.selector.register(self.control_sock, selectors.EVENT_READ, "accept")
        self.running = True

    def client_baud(self) -> int | None:
        try:
            return _SPEEDS.get(termios.tcgetattr(self.slave)[4])
        except termios.error:
            return None

    def serve(self) -> None:
        while self.running:
            for key, _ in self.selector.select(timeout=0.01):
                if key.data == "bus":
                    self._on_bus()
                elif key.data == "accept":
                    conn, _ = self.control_sock.accept()
                    conn.setblocking(False)
                    self.selector.register(conn, selectors.EVENT_READ, ["client", b""])
                else:
                    self._on_control(key)
            for servo in self.bus.servos.values():
                servo.update()  # bus watchdog and alerts progress even on a quiet bus

    def _on_bus(self) -> None:
        t_rx = time.perf_counter()
        try:
            data = os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return
        for packet in self.parser.feed(data):
            self._respond(packet, t_rx)
        self.bus.stats["dropped_bytes"] = self.parser.dropped

    def _respond(self, packet, t_rx: float) -> None:
        baud = self.client_baud()
        replies = self.bus.handle(packet)
        if self.wire_timing and baud is not None:
            # Servos answer only at their own baud: a mismatch is silence, as on a real bus.
            replies = [(s, r) for s, r in replies
                       if BAUD_CODES.get(s.values["baud_rate"]) == baud]
        if not replies:
            return
        byte_time = 10.0 / baud if (self.wire_timing and baud) else 0.0
        held = []  # replies a USB-serial latency timer holds back until it expires
        request_bytes = 10 + (len(packet.params) if isinstance(packet, Packet) else 0)
        t = t_rx + request_bytes * byte_time
        for servo, reply in replies:
            if self.faults["drop_next"]:
                self.faults["drop_next"] -= 1
                continue
            if self.faults["corrupt_next"]:
                self.faults["corrupt_next"] -= 1
                reply = reply[:-1] + bytes([reply[-1] ^ 0x5A])
            if self.faults["delay_next"]:
                t += self.faults["delay_next"]
                self.faults["delay_next"] = 0.0
            if self.wire_timing:
                t += servo.values["return_delay_time"] * 2e-6
            t += len(reply) * byte_time
            if self.latency_timer_s:
                held.append(reply)
                continue
            _spin_until(t)
            os.write(self.master, reply)
            self.bus.stats["replies"] += 1
        if held:
            # An FTDI adapter passes fewer than 62 received bytes to the host only when
            # its latency timer expires: the transaction's replies arrive together, late.
            _spin_until(t + self.latency_timer_s)
            os.write(self.master, b"".join(held))
            self.bus.stats["replies"] += len(held)

    def _on_control(self, key) -> None:
        """Answers a control client's complete lines. A client that gave up (the camera
        stand-in's ``Client`` waits 1 s, then reconnects: a busy host delays the bus
        longer) is dropped, never the bus: an unguarded EPIPE here once ended the head
        stand-in, and `sim up` with it, in the middle of a run under the load check."""
        conn = key.fileobj
        try:
            chunk = conn.recv(65536)
            if not chunk:
                raise ConnectionResetError
            key.data[1] += chunk
            while b"\n" in key.data[1]:
                line, key.data[1] = key.data[1].split(b"\n", 1)
                conn.setblocking(True)
                conn.sendall(answer(line, self.control))
                conn.setblocking(False)
        except BlockingIOError:
            return
        except OSError:  # the peer closed or reset: forget it
            self.selector.unregister(conn)
            conn.close()

    def control(self, request: dict) -> dict:
        cmd = request.get("cmd")
        if cmd in ("corrupt_next", "drop_next"):
            self.faults[cmd] += int(request.get("count", 1))
        elif cmd == "delay_next":
            self.faults["delay_next"] = float(request["seconds"])
        elif cmd == "hw_error":
            bits = HW_ERRORS[request["error"]]
            self.bus.servos[int(request["id"])].inject_hardware_error(bits)
        elif cmd == "set":
            targets = ([self.bus.servos[int(request["id"])]] if "id" in request
                       else list(self.bus.servos.values()))
            for servo in targets:
                _set_servo(servo, request)
        elif cmd == "freeze":
            self.bus.servos[int(request["id"])].freeze(float(request.get("at_fraction", 0.5)))
        elif cmd == "thaw":
            self.bus.servos[int(request["id"])].thaw()
        elif cmd == "dump":
            return {"ok": True, "servos": [s.dump() for s in self.bus.servos.values()],
                    "client_baud": self.client_baud(), "stats": self.bus.stats}
        elif cmd == "stats":
            return {"ok": True, **self.bus.stats}
        else:
            return {"ok": False, "error": f"unknown cmd {cmd!r}"}
        return {"ok": True}

    def close(self) -> None:
        for path in (self.link, self.control_path):
            if path is not None and (path.is_symlink() or path.exists()):
                path.unlink()
        self.selector.close()
        if self.control_sock is not None:
            self.control_sock.close()
        os.close(self.master)
        os.close(self.slave)


def _set_servo(servo: Servo, request: dict) -> None:
    """A control ``set``: temperature (C), supply voltage (V), heating rate (C/s)."""
    if "heating_c_per_s" in request:
        servo.heating_c_per_s = float(request["heating_c_per_s"])
    if "temperature" in request:
        servo.temperature = float(request["temperature"])
        servo.update()  # the Temperature Limit check raises overheating
    if "voltage" in request:
        servo.set_supply(float(request["voltage"]))


def _per_id(values: list, ids: list[int], flag: str) -> list:
    if len(values) == 1:
        return values * len(ids)
    if len(values) != len(ids):
        raise SystemExit(f"rigctl mock head: {flag}: give one value, or one per ID "
                         f"({len(ids)} IDs), got {len(values)}")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rigctl mock head",
                                     description="Dynamixel Protocol 2.0 bus stand-in on a pty.")
    parser.add_argument("--link", required=True, type=Path, help="symlink to create")
    parser.add_argument("--ids", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--model", nargs="+", default=["xm430-w350"], choices=sorted(MODELS),
                        metavar="MODEL", help="one model for every ID or one per ID, e.g. "
                        "xh540-w270, xm430-w350, ph54-200-s500-r, mx-64")
    parser.add_argument("--baud", type=int, nargs="+", default=[1_000_000],
                        choices=sorted(BAUD_CODES.values()), metavar="BAUD",
                        help="the servos' configured Baud Rate (address 8): one, or one per ID")
    parser.add_argument("--encoder", choices=("ideal", "hardware"), default="ideal",
                        help="hardware: continuous true angle, readings quantized with the "
                             "model's noise (about a pulse)")
    parser.add_argument("--wire-timing", action="store_true",
                        help="emulate wire time from the client's baud and Return Delay Time")
    parser.add_argument("--control", type=Path, default=None, help="JSON-lines control socket")
    parser.add_argument("--goal-out-of-limit", choices=("reject", "clamp"), default="reject")
    parser.add_argument("--no-crc-reply", action="store_true",
                        help="stay silent on a bad CRC instead of answering ERR=3")
    parser.add_argument("--position-noise", type=float, default=0.0,
                        help="sigma of present-position readings, pulses")
    parser.add_argument("--position-noise-deg", type=float, default=0.0,
                        help="sigma of present-position readings, degrees (each servo in "
                             "its own pulses)")
    parser.add_argument("--latency-timer-ms", type=float, default=0.0,
                        help="emulate a USB-serial adapter's latency timer (FTDI default: "
                             "16 ms): replies reach the host that long after the last byte")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    codes = {v: k for k, v in BAUD_CODES.items()}
    options = ServoOptions(goal_out_of_limit=args.goal_out_of_limit)
    servos = []
    models = _per_id(args.model, args.ids, "--model")
    bauds = _per_id(args.baud, args.ids, "--baud")
    for dxl_id, model, baud in zip(args.ids, models, bauds, strict=True):
        pulses = args.position_noise_deg * SPEC_BY_NAME[model].pulses_per_rev / 360.0
        servo = Servo(dxl_id, model, options, position_noise=args.position_noise + pulses,
                      encoder=args.encoder)
        servo.values["baud_rate"] = codes[baud]
        servos.append(servo)
    server = BusServer(Bus(servos, crc_error_reply=not args.no_crc_reply), args.link,
                       args.control, args.wire_timing, args.latency_timer_ms / 1000.0)

    def stop(*_):
        server.running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print(json.dumps({"port": server.port_name, "link": str(args.link), "pid": os.getpid(),
                      "control": str(args.control) if args.control else None,
                      "models": dict(zip(map(str, args.ids), models, strict=True))}),
          flush=True)
    try:
        server.serve()
    finally:
        server.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
