"""The UR primary interface (port 30001): the controller's version and its own kinematics.

Read on connect, once per run, for provenance and as the arm model the controller itself
uses. Layout (UR "Client Interfaces" manual; ``shared/reference/ur-primary-interface.md``),
big-endian throughout:

- package: ``int32 length`` (including the 5-byte header), ``uint8 type``;
  16 ROBOT_STATE, 20 ROBOT_MESSAGE, others skipped by length;
- ROBOT_MESSAGE: ``uint64 timestamp``, ``int8 source``, ``uint8 message type``; type 3 is
  VERSION: ``int8 name length``, name, ``uint8 major``, ``uint8 minor``, ``int32 bugfix``,
  ``int32 build``, build date (the rest);
- ROBOT_STATE: sub-packages, each ``int32 length`` (including its 5-byte header),
  ``uint8 type``; sub-package 5 is KINEMATICS_INFO: ``uint32 checksum[6]``,
  ``double dh_theta[6]``, ``double dh_a[6]``, ``double dh_d[6]``, ``double dh_alpha[6]``,
  ``uint32 calibration_status``.

The kinematics hash is the one the UR ROS 2 driver compares with its
``kinematics_params_file``: ``"calib_" + std::hash<std::string>`` of the DH values
streamed per joint as theta, d, a, alpha with C++'s default formatting. libstdc++'s
``std::hash<std::string>`` is ``_Hash_bytes`` (a 64-bit MurmurHash2 variant, seed
0xc70f6907); ``tests/test_ur_primary.py`` checks this implementation against libstdc++
itself when a C++ compiler is present.
"""

from __future__ import annotations

import socket
import struct
import time
from dataclasses import asdict, dataclass

from rigctl.errors import DeviceError, ProtocolError

PRIMARY_PORT = 30001
ROBOT_STATE = 16
ROBOT_MESSAGE = 20
MESSAGE_VERSION = 3
SUB_KINEMATICS_INFO = 5
HEADER = struct.Struct(">iB")
KINEMATICS_INFO = struct.Struct(">6I6d6d6d6dI")
MAX_PACKAGE = 1 << 20

_MASK64 = (1 << 64) - 1
_MUL = 0xC6A4A7935BD1E995
STD_HASH_SEED = 0xC70F6907


def libstdcxx_hash_bytes(data: bytes, seed: int = STD_HASH_SEED) -> int:
    """libstdc++'s 64-bit ``_Hash_bytes`` (MurmurHash2 variant), what
    ``std::hash<std::string>`` returns on 64-bit Linux."""

    def shift_mix(v: int) -> int:
        return v ^ (v >> 47)

    n = len(data)
    h = (seed ^ (n * _MUL)) & _MASK64
    aligned = n & ~7
    for i in range(0, aligned, 8):
        word = int.from_bytes(data[i:i + 8], "little")
        h ^= (shift_mix((word * _MUL) & _MASK64) * _MUL) & _MASK64
        h = (h * _MUL) & _MASK64
    if n & 7:
        h ^= int.from_bytes(data[aligned:], "little")
        h = (h * _MUL) & _MASK64
    h = (shift_mix(h) * _MUL) & _MASK64
    return shift_mix(h)


def cpp_stream_double(value: float) -> str:
    """A double as ``std::ostream << value`` writes it by default (``%g``, 6 digits)."""
    return f"{value:g}"


@dataclass(frozen=True)
class ControllerVersion:
    project: str
    major: int
    minor: int
    bugfix: int
    build: int
    build_date: str

    @property
    def text(self) -> str:
        return f"{self.major}.{self.minor}.{self.bugfix}.{self.build}"


@dataclass(frozen=True)
class KinematicsInfo:
    """The controller's own (factory-calibrated) DH table: radians and metres."""

    checksum: tuple[int, ...]
    theta: tuple[float, ...]
    a: tuple[float, ...]
    d: tuple[float, ...]
    alpha: tuple[float, ...]
    calibration_status: int

    def ur_hash(self) -> str:
        """The hash the UR ROS 2 driver computes (``KinematicsInfo::toHash``)."""
        text = "".join(cpp_stream_double(v) for i in range(6)
                       for v in (self.theta[i], self.d[i], self.a[i], self.alpha[i]))
        return f"calib_{libstdcxx_hash_bytes(text.encode())}"

    def as_dict(self) -> dict:
        return {**{k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()},
                "hash": self.ur_hash()}


@dataclass(frozen=True)
class PrimaryInfo:
    version: ControllerVersion | None
    kinematics: KinematicsInfo | None

    def as_dict(self) -> dict:
        return {"controller_version": self.version.text if self.version else None,
                "project": self.version.project if self.version else None,
                "kinematics": self.kinematics.as_dict() if self.kinematics else None}


def split_packages(buffer: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    """Whole packages at the front of ``buffer`` as (type, body), and the rest."""
    packages, pos = [], 0
    while len(buffer) - pos >= HEADER.size:
        length, kind = HEADER.unpack_from(buffer, pos)
        if length < HEADER.size or length > MAX_PACKAGE:
            raise ProtocolError(f"primary interface: package at byte {pos} has length "
                                f"{length} (type {kind}); the stream is out of step")
        if len(buffer) - pos < length:
            break
        packages.append((kind, bytes(buffer[pos + HEADER.size:pos + length])))
        pos += length
    return packages, bytes(buffer[pos:])


def parse_version(body: bytes) -> ControllerVersion | None:
    """The VERSION robot message in a ROBOT_MESSAGE body, or None for other messages."""
    head = struct.Struct(">QbB")
    if len(body) < head.size + 1:
        raise ProtocolError(f"primary interface: robot message of {len(body)} bytes is "
                            "shorter than its header")
    _, _source, kind = head.unpack_from(body, 0)
    if kind != MESSAGE_VERSION:
        return None
    pos = head.size
    (name_len,) = struct.unpack_from(">b", body, pos)
    pos += 1
    tail = struct.Struct(">BBii")
    if name_len < 0 or len(body) < pos + name_len + tail.size:
        raise ProtocolError(f"primary interface: version message of {len(body)} bytes "
                            f"cannot hold a project name of {name_len} bytes and its numbers")
    project = body[pos:pos + name_len].decode(errors="replace")
    pos += name_len
    major, minor, bugfix, build = tail.unpack_from(body, pos)
    date = body[pos + tail.size:].decode(errors="replace")
    return ControllerVersion(project, major, minor, bugfix, build, date)


def sub_packages(body: bytes) -> dict[int, bytes]:
    """ROBOT_STATE sub-packages by type (payload after the 5-byte sub-header)."""
    out, pos = {}, 0
    while pos < len(body):
        if len(body) - pos < HEADER.size:
            raise ProtocolError(f"primary interface: robot state has {len(body) - pos} "
                                f"stray bytes at byte {pos}")
        length, kind = HEADER.unpack_from(body, pos)
        if length < HEADER.size or pos + length > len(body):
            raise ProtocolError(f"primary interface: robot-state sub-package type {kind} at "
                                f"byte {pos} claims {length} bytes; {len(body) - pos} remain")
        out[kind] = body[pos + HEADER.size:pos + length]
        pos += length
    return out


def parse_kinematics_info(payload: bytes) -> KinematicsInfo:
    """A KINEMATICS_INFO sub-package payload."""
    if len(payload) < KINEMATICS_INFO.size:
        raise ProtocolError(f"primary interface: KINEMATICS_INFO of {len(payload)} bytes; "
                            f"its layout needs {KINEMATICS_INFO.size}")
    v = KINEMATICS_INFO.unpack_from(payload, 0)
    return KinematicsInfo(tuple(v[0:6]), tuple(v[6:12]), tuple(v[12:18]), tuple(v[18:24]),
                          tuple(v[24:30]), v[30])


def read_primary_info(host: str, port: int = PRIMARY_PORT, timeout_s: float = 5.0
                      ) -> PrimaryInfo:
    """Connect to the primary interface and read until the version message and one
    KINEMATICS_INFO have arrived (the controller sends state at 10 Hz), within
    ``timeout_s``. A controller that sends no KINEMATICS_INFO gives ``kinematics=None``
    once a robot state without it has been seen."""
    version = kinematics = None
    states = 0
    deadline = time.monotonic() + timeout_s
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            buffer = b""
            while time.monotonic() < deadline:
                sock.settimeout(max(0.05, deadline - time.monotonic()))
                chunk = sock.recv(65536)
                if not chunk:
                    break
                packages, buffer = split_packages(buffer + chunk)
                for kind, body in packages:
                    if kind == ROBOT_MESSAGE:
                        version = parse_version(body) or version
                    elif kind == ROBOT_STATE:
                        states += 1
                        subs = sub_packages(body)
                        if SUB_KINEMATICS_INFO in subs:
                            kinematics = parse_kinematics_info(subs[SUB_KINEMATICS_INFO])
                if version is not None and (kinematics is not None or states >= 2):
                    return PrimaryInfo(version, kinematics)
    except OSError as exc:
        raise DeviceError(f"arm {host}:{port}: primary interface: {exc}") from exc
    if version is None and kinematics is None:
        raise DeviceError(f"arm {host}:{port}: primary interface sent no version message "
                          f"and no robot state within {timeout_s:.1f} s")
    return PrimaryInfo(version, kinematics)
