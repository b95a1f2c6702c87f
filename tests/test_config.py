"""Rig file validation: good files load, bad files give the exact error."""

from __future__ import annotations

import math

import pytest

from rigctl.config import load_rig, parse_rig
from rigctl.errors import ConfigError
from tests.conftest import ROOT


def test_example_rig_file_loads_with_units_converted():
    config = load_rig(ROOT / "examples" / "rig.example.yaml")
    assert config.name == "lab-rig-1"
    lo, hi = config.devices.head.limits_rad()["tilt"]
    assert lo == pytest.approx(-math.pi / 4) and hi == pytest.approx(math.pi / 4)
    assert config.devices.arm.joint_limits_rad()[1] == pytest.approx((-math.pi, 0.0))
    assert config.devices.camera.fourcc == "MJPG"
    assert config.database_url().endswith("examples/records/index.sqlite")
    assert len(config.config_hash()) == 16


def test_arm_home_and_park_in_radians():
    arm = parse_rig("devices:\n  arm: {home_deg: [0, -90, 90, -90, -90, 180]}\n").devices.arm
    assert arm.home_rad() == pytest.approx((0, -math.pi / 2, math.pi / 2, -math.pi / 2,
                                            -math.pi / 2, math.pi))
    assert arm.park_rad() == arm.home_rad()  # no park joints: home
    parked = parse_rig("devices:\n  arm: {park: {policy: home, joints_deg: [10, -80, 80, "
                       "-90, -90, 0]}}\n").devices.arm
    assert parked.park_rad()[0] == pytest.approx(math.radians(10))


def test_servo_range_error_names_file_key_and_reason():
    text = "devices:\n  head:\n    port: /dev/ttyUSB0\n    limits:\n      pan: [-90, 200]\n"
    with pytest.raises(ConfigError) as info:
        parse_rig(text, "rig.yaml")
    assert str(info.value) == (
        "rig.yaml: devices.head.limits.pan: max 200 deg exceeds the servo range of 180 deg")


@pytest.mark.parametrize("text, expected", [
    ("devices:\n  head:\n    prot: /dev/x\n    port: /dev/y\n",
     "rig.yaml: devices.head.prot: unknown key"),
    ("devices:\n  head: {}\n", "rig.yaml: devices.head.port: Field required"),
    ("devices:\n  head: {port: a, baud: 12345}\n",
     "rig.yaml: devices.head.baud: 12345 is not a Dynamixel baud rate"),
    ("devices:\n  head: {port: a, ids: {pan: 1, tilt: 1, roll: 3}}\n",
     "rig.yaml: devices.head: ids: pan, tilt and roll need distinct servo IDs, got [1, 1, 3]"),
    ("devices:\n  arm: {joint_limits_deg: [[0, 1]]}\n",
     "rig.yaml: devices.arm.joint_limits_deg: expected 6 [min, max] pairs, got 1"),
    ("devices:\n  camera: {device: 0, fourcc: MJPEG}\n",
     "rig.yaml: devices.camera.fourcc: FOURCC must have 4 characters, got 'MJPEG'"),
    ("devices:\n  camera: {device: 0, controls: {exposur: 3}}\n",
     "rig.yaml: devices.camera.controls: unknown camera control(s) ['exposur']"),
    ("service:\n  schedules: [{procedure: x}]\n",
     "rig.yaml: service.schedules.0: give exactly one of cron or interval_s"),
    ("devices:\n  arm: {model: ur10, rtde_frequency_hz: 500}\n",
     "rig.yaml: devices.arm: rtde_frequency_hz: 500 Hz exceeds the ur10's RTDE stream, at "
     "most 125 Hz"),
    ("devices: [1, 2\n", "rig.yaml:2:1: not valid YAML"),
    ("- 1\n", "rig.yaml: top level must be a mapping, got list"),
])
def test_bad_rig_files_give_precise_errors(text, expected):
    with pytest.raises(ConfigError) as info:
        parse_rig(text, "rig.yaml")
    assert str(info.value).startswith(expected)


def test_missing_rig_file(tmp_path):
    with pytest.raises(ConfigError, match=r"nope.yaml: rig file not found"):
        load_rig(tmp_path / "nope.yaml")


def test_several_errors_are_all_reported():
    text = "devices:\n  head: {port: a, speed_cap_dps: -1, limits: {tilt: [10, 5]}}\n"
    with pytest.raises(ConfigError) as info:
        parse_rig(text, "r.yaml")
    lines = str(info.value).splitlines()
    assert "r.yaml: devices.head.limits.tilt: min 10 deg must be below max 5 deg" in lines
    assert any(line.startswith("r.yaml: devices.head.speed_cap_dps:") for line in lines)
