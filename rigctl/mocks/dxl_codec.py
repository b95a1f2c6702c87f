"""Dynamixel Protocol 2.0 packet codec for the bus stand-in.

Written from the e-Manual's packet description (header ``FF FF FD 00``, ID, LEN,
instruction, parameters, CRC-16 over the stuffed packet), independently of the
client library the tests drive against it.
"""

from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
STATUS = 0x55
MAX_LEN = 1024  # longest packet the stand-in accepts (SDK: TXPACKET_MAX_LEN 1024)


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC-16: polynomial 0x8005, initial 0, not reflected, no final XOR."""
    for byte in data:
        crc = ((crc << 8) ^ _TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after each ``FF FF FD`` in instruction + parameters."""
    out = bytearray()
    for byte in body:
        out.append(byte)
        if len(out) >= 3 and out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Remove the ``FD`` inserted after each ``FF FF FD``."""
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if len(out) >= 3 and out[-3:] == b"\xff\xff\xfd" and i + 1 < len(body) \
                and body[i + 1] == 0xFD:
            i += 1
        i += 1
    return bytes(out)


def encode(dxl_id: int, body: bytes, stuffing: bool = True) -> bytes:
    """A whole packet: header, ID, LEN, (stuffed) body, CRC."""
    payload = stuff(body) if stuffing else body
    length = len(payload) + 2
    head = HEADER + bytes([dxl_id, length & 0xFF, length >> 8])
    crc = crc16(head + payload)
    return head + payload + bytes([crc & 0xFF, crc >> 8])


def status_packet(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    return encode(dxl_id, bytes([STATUS, error]) + params)


@dataclass(frozen=True)
class Packet:
    dxl_id: int
    instruction: int
    params: bytes


@dataclass(frozen=True)
class BadPacket:
    """A complete frame whose CRC did not match (the servo may answer ERR=3)."""

    dxl_id: int
    instruction: int


class PacketParser:
    """Incremental parser: feed bytes, take complete packets; garbage is skipped.

    It never raises on input: a bad header, impossible length or CRC mismatch
    drops one byte and searches for the next ``FF FF FD 00`` header.
    """

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.dropped = 0

    def feed(self, data: bytes) -> list[Packet | BadPacket]:
        self.buffer.extend(data)
        out: list[Packet | BadPacket] = []
        while True:
            start = self.buffer.find(HEADER)
            if start < 0:
                keep = 3  # a header may be split across reads
                self.dropped += max(len(self.buffer) - keep, 0)
                del self.buffer[:-keep or None]
                if len(self.buffer) > keep:
                    del self.buffer[:-keep]
                return out
            if start:
                self.dropped += start
                del self.buffer[:start]
            if len(self.buffer) < 7:
                return out
            length = self.buffer[5] | (self.buffer[6] << 8)
            if length < 3 or length + 7 > MAX_LEN:
                self._skip()
                continue
            total = 7 + length
            if len(self.buffer) < total:
                return out
            frame = bytes(self.buffer[:total])
            crc = frame[-2] | (frame[-1] << 8)
            if crc16(frame[:-2]) != crc:
                out.append(BadPacket(frame[4], frame[7]))
                self._skip()
                continue
            del self.buffer[:total]
            body = unstuff(frame[7:-2])
            out.append(Packet(frame[4], body[0], body[1:]))

    def _skip(self) -> None:
        del self.buffer[:1]
        self.dropped += 1
