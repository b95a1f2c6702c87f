"""Protocol 2.0 codec of the bus stand-in, against the e-Manual's example packets."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rigctl.mocks.dxl_codec import BadPacket, Packet, PacketParser, crc16, encode, stuff, unstuff

# Example packets from the ROBOTIS e-Manual, Protocol 2.0 page (ID 1).
EMANUAL_VECTORS = [
    "FF FF FD 00 01 03 00 01 19 4E",                                  # ping
    "FF FF FD 00 01 07 00 55 00 06 04 26 65 5D",                      # ping status
    "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15",                      # read 132, 4 bytes
    "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0",                   # read status
    "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89",                # write goal 512
    "FF FF FD 00 01 04 00 55 00 A1 0C",                               # write status
    "FF FF FD 00 01 03 00 08 2F 4E",                                  # reboot
    "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA",                # sync read ids 1,2
]


@pytest.mark.parametrize("vector", EMANUAL_VECTORS)
def test_crc_matches_emanual_examples(vector):
    frame = bytes.fromhex(vector)
    assert crc16(frame[:-2]) == frame[-2] | (frame[-1] << 8)


@pytest.mark.parametrize("vector", EMANUAL_VECTORS)
def test_encode_reproduces_emanual_examples(vector):
    frame = bytes.fromhex(vector)
    assert encode(frame[4], frame[7:-2]) == frame
    [packet] = PacketParser().feed(frame)
    assert packet == Packet(frame[4], frame[7], frame[8:-2])


def test_byte_stuffing_round_trip_and_length():
    body = bytes([0x03, 0xFF, 0xFF, 0xFD, 0x01])
    assert stuff(body) == bytes([0x03, 0xFF, 0xFF, 0xFD, 0xFD, 0x01])
    assert unstuff(stuff(body)) == body
    frame = encode(1, body)
    assert frame[5] == len(stuff(body)) + 2  # LEN counts the stuffed bytes
    assert PacketParser().feed(frame) == [Packet(1, 0x03, body[1:])]


def test_crc_error_reported_and_parser_resyncs():
    good = encode(1, bytes([0x01]))
    bad = bytearray(encode(2, bytes([0x02, 0x84, 0x00, 0x04, 0x00])))
    bad[-1] ^= 0xFF
    packets = PacketParser().feed(b"\x00\x13" + bytes(bad) + good)
    assert packets[0] == BadPacket(2, 0x02)
    assert packets[-1] == Packet(1, 0x01, b"")


@settings(max_examples=300, deadline=None)
@given(noise=st.binary(max_size=300), chunks=st.lists(st.integers(1, 40), max_size=30),
       dxl_id=st.integers(0, 252), params=st.binary(max_size=40))
def test_parser_survives_garbage_and_finds_next_valid_packet(noise, chunks, dxl_id, params):
    """Random and corrupted streams never crash the parser; it resyncs on the next valid
    packet (noise is followed by a few idle bytes so a half-header cannot swallow it)."""
    packet = encode(dxl_id, bytes([0x03]) + params)
    stream = noise + b"\x00" * 8 + packet
    parser = PacketParser()
    found = []
    pos = 0
    for size in [*chunks, len(stream)]:
        found += parser.feed(stream[pos:pos + size])
        pos += size
        if pos >= len(stream):
            break
    valid = [p for p in found if isinstance(p, Packet)]
    assert valid and valid[-1] == Packet(dxl_id, 0x03, params)


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=1, max_size=200))
def test_parser_never_crashes_on_random_bytes(data):
    parser = PacketParser()
    for i in range(0, len(data), 7):
        parser.feed(data[i:i + 7])
    assert len(parser.buffer) <= len(data)
