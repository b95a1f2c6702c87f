"""The UR primary interface: the parser against byte vectors laid out by hand from the
documented layout, the kinematics hash against libstdc++, and the stand-in through the
driver over TCP on loopback."""

from __future__ import annotations

import json
import math
import shutil
import struct
import subprocess
import sys

import numpy as np
import pytest

from rigctl.config import load_rig
from rigctl.drivers.ur_primary import (
    KinematicsInfo,
    libstdcxx_hash_bytes,
    parse_kinematics_info,
    parse_version,
    read_primary_info,
    split_packages,
    sub_packages,
)
from rigctl.errors import ProtocolError
from rigctl.procedures.planning import planning_arm

# ur5e factory-style DH (radians, metres), written out for these tests
THETA = [1e-4, -2e-4, 3e-4, -1e-4, 2e-4, -5e-5]
A = [0.0002, -0.4251, -0.3919, 0.0004, -0.0003, 0.0]
D = [0.1627, -0.0011, 0.0009, 0.1335, 0.0995, 0.0997]
ALPHA = [math.pi / 2 + 1e-4, -2e-4, 1e-4, math.pi / 2 - 1e-4, -math.pi / 2, 0.0]


def kinematics_sub(status=7) -> bytes:
    """KINEMATICS_INFO: int32 length, uint8 type 5, uint32 checksum[6], then dh_theta,
    dh_a, dh_d, dh_alpha (6 doubles each), uint32 calibration_status; big-endian."""
    body = b"".join(struct.pack(">I", 1000 + i) for i in range(6))
    for values in (THETA, A, D, ALPHA):
        body += b"".join(struct.pack(">d", v) for v in values)
    body += struct.pack(">I", status)
    return struct.pack(">i", len(body) + 5) + bytes([5]) + body


def unknown_sub(kind: int, size: int) -> bytes:
    return struct.pack(">i", size + 5) + bytes([kind]) + bytes(range(size))


def package(kind: int, body: bytes) -> bytes:
    return struct.pack(">i", len(body) + 5) + bytes([kind]) + body


def version_body(name=b"URControl", major=5, minor=12, bugfix=3, build=1234,
                 date=b"01-02-2023, 10:11:12") -> bytes:
    """ROBOT_MESSAGE body: uint64 timestamp, int8 source (-1), uint8 type (3 = version),
    int8 name length, name, uint8 major, uint8 minor, int32 bugfix, int32 build, date."""
    return (struct.pack(">Q", 123456789) + struct.pack(">b", -1) + bytes([3])
            + struct.pack(">b", len(name)) + name + bytes([major, minor])
            + struct.pack(">i", bugfix) + struct.pack(">i", build) + date)


def test_parses_version_and_kinematics_skipping_unknown_sub_packages():
    stream = (package(20, version_body())
              + package(16, unknown_sub(0, 47) + kinematics_sub() + unknown_sub(9, 13))
              + package(25, b"\x00" * 10))
    # fed in two pieces, split mid-package: the rest waits for more bytes
    first, rest = split_packages(stream[:40])
    assert first == [] and rest == stream[:40]
    packages, rest = split_packages(stream)
    assert rest == b"" and [k for k, _ in packages] == [20, 16, 25]
    version = parse_version(packages[0][1])
    assert (version.project, version.major, version.minor, version.bugfix, version.build) == \
        ("URControl", 5, 12, 3, 1234)
    assert version.build_date == "01-02-2023, 10:11:12" and version.text == "5.12.3.1234"
    subs = sub_packages(packages[1][1])
    assert sorted(subs) == [0, 5, 9] and len(subs[0]) == 47
    info = parse_kinematics_info(subs[5])
    assert info.checksum == (1000, 1001, 1002, 1003, 1004, 1005)
    assert info.theta == tuple(THETA) and info.a == tuple(A)
    assert info.d == tuple(D) and info.alpha == tuple(ALPHA)
    assert info.calibration_status == 7


def test_other_robot_messages_are_not_versions():
    body = struct.pack(">Q", 1) + struct.pack(">b", -1) + bytes([0]) + b"text message"
    assert parse_version(body) is None


@pytest.mark.parametrize("stream, where", [
    (struct.pack(">i", 3) + bytes([16]), "length 3"),
    (package(16, struct.pack(">i", 400) + bytes([5]) + b"\x00" * 20), "claims 400 bytes"),
    (package(16, unknown_sub(1, 4) + b"\x00\x00"), "2 stray bytes"),
])
def test_malformed_packages_name_what_is_wrong(stream, where):
    with pytest.raises(ProtocolError, match=where):
        packages, _ = split_packages(stream)
        for _kind, body in packages:
            sub_packages(body)


def test_short_kinematics_info_is_refused():
    with pytest.raises(ProtocolError, match="KINEMATICS_INFO of 100 bytes"):
        parse_kinematics_info(b"\x00" * 100)


# std::hash<std::string> of these strings, printed by a program built with g++ 12
# (libstdc++, x86-64); the program is the one test_hash_matches_libstdcxx compiles.
LIBSTDCXX_HASHES = {
    "": 6142509188972423790,
    "abc": 3663726644998027833,
    "hello world, 123": 15833308631572624555,
    "0.16250-0.4251.5708": 4567703134364989885,
}


def test_hash_bytes_matches_recorded_libstdcxx_values():
    for text, value in LIBSTDCXX_HASHES.items():
        assert libstdcxx_hash_bytes(text.encode()) == value, text


def test_kinematics_hash_streams_values_as_cpp_does():
    info = KinematicsInfo((0,) * 6, (0.0,) * 6, (0.0, -0.425, -0.3922, 0, 0, 0),
                          (0.1625, 0, 0, 0.1333, 0.0997, 0.0996),
                          (math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0), 0)
    # per joint theta, d, a, alpha with 6 significant digits and no separator
    text = ("00.162501.5708" "00-0.4250" "00-0.39220" "00.133301.5708" "00.09970-1.5708"
            "00.099600")
    assert info.ur_hash() == f"calib_{libstdcxx_hash_bytes(text.encode())}"


CPP = r"""
#include <iostream>
#include <sstream>
#include <string>
int main() {
  std::string line;
  while (std::getline(std::cin, line)) std::cout << std::hash<std::string>{}(line) << "\n";
  double v[] = {0.0, 0.1625, -0.425, 1.5707963267948966, 1e-07, -0.0, 123456789.0, 2.5e-05};
  std::stringstream ss;
  for (double x : v) ss << x;
  std::cout << ss.str() << "\n";
}
"""


@pytest.mark.skipif(shutil.which("g++") is None, reason="no C++ compiler to ask libstdc++")
def test_hash_matches_libstdcxx(tmp_path):
    from rigctl.drivers.ur_primary import cpp_stream_double

    source = tmp_path / "h.cpp"
    source.write_text(CPP)
    subprocess.run(["g++", "-O1", "-o", str(tmp_path / "h"), str(source)], check=True,
                   timeout=120)
    texts = ["", "abc", "calib", "x" * 8, "y" * 15, "0.16250-0.4251.5708" * 7]
    out = subprocess.run([str(tmp_path / "h")], input="\n".join(texts) + "\n",
                         capture_output=True, text=True, timeout=30, check=True).stdout
    *hashes, streamed = out.splitlines()
    assert [int(h) for h in hashes] == [libstdcxx_hash_bytes(t.encode()) for t in texts]
    values = [0.0, 0.1625, -0.425, 1.5707963267948966, 1e-07, -0.0, 123456789.0, 2.5e-05]
    assert streamed == "".join(cpp_stream_double(v) for v in values)


def dh_fk(q, info: KinematicsInfo) -> np.ndarray:
    """Plain DH forward kinematics from a KINEMATICS_INFO table, written out here."""
    T = np.eye(4)
    for i in range(6):
        th = q[i] + info.theta[i]
        ct, st = math.cos(th), math.sin(th)
        ca, sa = math.cos(info.alpha[i]), math.sin(info.alpha[i])
        T = T @ np.array([[ct, -st * ca, st * sa, info.a[i] * ct],
                          [st, ct * ca, -ct * sa, info.a[i] * st],
                          [0, sa, ca, info.d[i]], [0, 0, 0, 1]])
    return T


@pytest.mark.integration
def test_stand_in_reports_its_factory_kinematics_and_moves_by_them(tmp_path):
    """The stand-in's KINEMATICS_INFO is the world's factory model (not nominal, not the
    truth), and the TCP pose ur_rtde reads is that model's forward kinematics."""
    import rtde_receive

    from rigctl.loopback import free_host
    from rigctl.mocks.ur_kinematics import ArmModel
    from tests.mockproc import MockProcess

    world = tmp_path / "world.yaml"
    world.write_text("arm:\n  model: ur10e\n  errors:\n    d_mm: [2, 0, 0, 0, 0, 0]\n"
                     "  factory_errors:\n    d_mm: [1.5, 0, 0, 0.4, 0, 0]\n"
                     "    theta_deg: [0, 0.1, 0, 0, 0, 0]\n")
    proc = MockProcess(["-m", "rigctl.mocks.ur_controller", "--host", free_host(), "--world",
                        str(world)])
    try:
        host = proc.ready["host"]
        assert proc.ready["primary_port"] == 30001
        info = read_primary_info(host, timeout_s=30)
        assert info.version.project == "URControl" and info.version.major == 5
        k = info.kinematics
        nominal = ArmModel.nominal("ur10e")
        assert np.allclose(k.d, nominal.d + np.array([1.5, 0, 0, 0.4, 0, 0]) * 1e-3, atol=1e-12)
        assert np.allclose(k.theta, np.radians([0, 0.1, 0, 0, 0, 0]), atol=1e-12)
        assert np.allclose(k.a, nominal.a) and np.allclose(k.alpha, nominal.alpha)
        assert len(set(k.checksum)) == 6 and k.ur_hash().startswith("calib_")
        receive = rtde_receive.RTDEReceiveInterface(host)
        try:
            q = receive.getActualQ()
            pose = receive.getActualTCPPose()
        finally:
            receive.disconnect()
        assert np.allclose(pose[:3], dh_fk(q, k)[:3, 3], atol=1e-9)
        # doctor reports the controller's version and its kinematics hash
        rig = tmp_path / "rig.yaml"
        rig.write_text(f"name: primary\ndevices:\n  arm: {{host: {host}, model: ur10e}}\n")
        done = subprocess.run([sys.executable, "-m", "rigctl.cli", "doctor", "--rig", str(rig),
                               "--json"], capture_output=True, text=True, timeout=120)
        arm = {r["device"]: r for r in json.loads(done.stdout)}["arm"]
        assert arm["state"] == "ok", arm
        assert arm["describe"]["controller"] == "5.11.1.108318"
        assert arm["describe"]["kinematics_hash"] == k.ur_hash()
        assert arm["describe"]["controller_kinematics"]["d"] == list(k.d)
        assert f"kinematics_hash={k.ur_hash()}" in arm["message"]
        # the planner reads the same table when a run is planned, and plans with it
        planned = planning_arm(load_rig(rig))
        assert planned.source == "controller" and planned.robot_hash == k.ur_hash()
        assert planned.controller_version == "5.11.1.108318"
        assert np.array_equal(planned.model.d, k.d)
        assert np.array_equal(planned.model.theta_offset, k.theta)
    finally:
        proc.stop()
