"""Packages of the UR primary and secondary interfaces (ports 30001/30002), as the
controller stand-in sends them.

Written apart from ``rigctl.drivers.ur_primary`` (the parser) on purpose. Layout, big-endian
(UR "Client Interfaces" manual; ``shared/reference/ur-primary-interface.md``):
package = ``int32 length`` (header included), ``uint8 type``; the VERSION robot message
(type 20, source -1, message type 3) is sent once on connect, then ROBOT_STATE (type 16)
at 10 Hz with the sub-packages the stand-in models: joint data (1), cartesian info (4) and
KINEMATICS_INFO (5, the controller's own DH table).
"""

from __future__ import annotations

import struct
import zlib

PROJECT = "URControl"
VERSION = (5, 11, 1, 108318)
BUILD_DATE = "21-07-2021, 09:25:11"


def _package(kind: int, body: bytes) -> bytes:
    return struct.pack(">iB", len(body) + 5, kind) + body


def version_message(timestamp_us: int, version=VERSION, project: str = PROJECT,
                    build_date: str = BUILD_DATE) -> bytes:
    major, minor, bugfix, build = version
    name = project.encode()
    body = (struct.pack(">QbB", timestamp_us, -1, 3) + struct.pack(">b", len(name)) + name
            + struct.pack(">BBii", major, minor, bugfix, build) + build_date.encode())
    return _package(20, body)


def joint_data(q, qd) -> bytes:
    """Sub-package 1: per joint q_actual, q_target, qd_actual (double), current, voltage,
    motor and micro temperature (float), joint mode (uint8; 253 = running)."""
    body = b"".join(struct.pack(">dddffffB", q[i], q[i], qd[i], 0.3, 47.9, 31.5, 35.0, 253)
                    for i in range(6))
    return struct.pack(">iB", len(body) + 5, 1) + body


def cartesian_info(tcp_pose, tcp_offset) -> bytes:
    """Sub-package 4: the TCP pose (x, y, z, rx, ry, rz) and the TCP offset."""
    body = struct.pack(">12d", *tcp_pose, *tcp_offset)
    return struct.pack(">iB", len(body) + 5, 4) + body


def dh_checksums(theta, a, d, alpha) -> list[int]:
    """The stand-in's per-joint checksum of its calibration: CRC-32 of the joint's four
    DH values. (A real controller's checksum is its own; clients only compare them.)"""
    return [zlib.crc32(struct.pack(">4d", theta[i], a[i], d[i], alpha[i])) for i in range(6)]


def kinematics_info(theta, a, d, alpha, calibration_status: int) -> bytes:
    """Sub-package 5: checksums, dh_theta, dh_a, dh_d, dh_alpha, calibration status."""
    body = struct.pack(">6I6d6d6d6dI", *dh_checksums(theta, a, d, alpha), *theta, *a, *d,
                       *alpha, calibration_status)
    return struct.pack(">iB", len(body) + 5, 5) + body


def robot_state(q, qd, tcp_pose, tcp_offset, dh: dict, calibration_status: int) -> bytes:
    """One ROBOT_STATE package."""
    body = (joint_data(q, qd) + cartesian_info(tcp_pose, tcp_offset)
            + kinematics_info(dh["theta"], dh["a"], dh["d"], dh["alpha"], calibration_status))
    return _package(16, body)


def dh_table(model) -> dict[str, list[float]]:
    """The DH table a controller reports for an ``ArmModel`` (no beta: the controller's
    kinematics are plain DH)."""
    return {"theta": [float(v) for v in model.theta_offset], "a": [float(v) for v in model.a],
            "d": [float(v) for v in model.d], "alpha": [float(v) for v in model.alpha]}
