"""Every Dynamixel family through the real dynamixel_sdk and the bus stand-in.

The expected addresses, model numbers and resolutions below are typed from the ROBOTIS
e-Manual pages in this test (not imported from the driver's or the stand-in's tables):
X series (xh540-w270: Model Number 1100, Goal Position 116, Present Position 132,
Profile Velocity 112 in 0.229 rev/min, 4096 pulses per turn centred at 2048), MX-64 on
Protocol 2.0 (Model Number 311, the X addresses), DYNAMIXEL-P (ph54-200-s500-r: Model
Number 2020, Torque Enable 512, Profile Velocity 560 in 0.01 rev/min, Goal Position 564,
Present Position 580, 1,003,846 pulses per turn centred at 0).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import dynamixel_sdk as sdk
import pytest
import yaml

from rigctl.config import load_rig, parse_rig
from rigctl.doctor import servo_warnings
from rigctl.drivers.dynamixel import DynamixelHead, TimedPortHandler
from rigctl.errors import ConfigError
from rigctl.mocks.dxl_models import SPEC_BY_NAME
from rigctl.mocks.random_world import random_world
from rigctl.mocks.sim import STAND_IN_TIMING
from rigctl.mocks.world import WorldFile, load_world, world_file
from rigctl.records import RunDirectory
from rigctl.runner import Runner
from tests.mockproc import ROOT, MockProcess, control

pytestmark = pytest.mark.integration

EMANUAL = {  # model: (model number, goal, present position, profile velocity, rpm unit,
    #           pulses per turn, centre pulse)
    "xh540-w270": (1100, 116, 132, 112, 0.229, 4096, 2048),
    "mx-64": (311, 116, 132, 112, 0.229, 4096, 2048),
    "ph54-200-s500-r": (2020, 564, 580, 560, 0.01, 1_003_846, 0),
}
MIXED = ["xh540-w270", "mx-64", "ph54-200-s500-r"]  # pan, tilt, roll: X, MX and P


@pytest.fixture
def start_bus(tmp_path):
    """Start stand-in buses (extra arguments per call); each stopped by PID at the end."""
    procs = []

    def start(*args: str) -> MockProcess:
        n = len(procs)
        proc = MockProcess(["-m", "rigctl.mocks.dynamixel_bus", "--link",
                            str(tmp_path / f"dxl{n}"), "--control",
                            str(tmp_path / f"dxl{n}.sock"), *args])
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        assert proc.stop() == 0


def head_cfg(link: str, **extra):
    head = {"port": link, "speed_cap_dps": 120, "accel_cap_dps2": 600,
            "park": {"policy": "hold"}, **STAND_IN_TIMING["head"], **extra}
    return parse_rig(yaml.safe_dump({"devices": {"head": head}})).devices.head


def dump(bus) -> dict[int, dict]:
    return {s["id"]: s for s in control(bus.ready["control"], {"cmd": "dump"})["servos"]}


def cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "rigctl.cli", *args], capture_output=True,
                          text=True, timeout=120, env=env, cwd=cwd)


def test_each_family_plays_its_emanual_table_to_the_real_sdk(start_bus):
    bus = start_bus("--model", *MIXED)
    # the SDK's ~34 ms timeout is for servos; a stand-in on a busy host may answer later
    # (a ping timed out under the load check's companion load)
    port = TimedPortHandler(bus.ready["link"], 500.0)
    assert port.openPort() and port.setBaudRate(1_000_000)
    ph = sdk.PacketHandler(2.0)
    try:
        for dxl_id, model in enumerate(MIXED, start=1):
            number, goal, present, _, _, _, centre = EMANUAL[model]
            assert ph.ping(port, dxl_id)[:2] == (number, sdk.COMM_SUCCESS)
            value, comm, _ = ph.read4ByteTxRx(port, dxl_id, present)
            assert comm == sdk.COMM_SUCCESS and value == centre & 0xFFFFFFFF
            value, comm, _ = ph.read4ByteTxRx(port, dxl_id, goal)
            assert comm == sdk.COMM_SUCCESS and value == centre & 0xFFFFFFFF
        # the P servo has nothing at the X addresses past its EEPROM: torque is at 512
        assert ph.read1ByteTxRx(port, 3, 512)[1:] == (sdk.COMM_SUCCESS, 0)
    finally:
        port.closePort()


def test_driver_drives_a_bus_mixing_x_mx_and_p(start_bus):
    bus = start_bus("--model", *MIXED)
    head = DynamixelHead(head_cfg(bus.ready["link"]))
    with head:
        assert [head.info[i]["model_name"] for i in (1, 2, 3)] == MIXED
        assert [head.info[i]["model"] for i in (1, 2, 3)] == [1100, 311, 2020]
        head.move_to(math.radians(10), math.radians(-5), math.radians(30)).wait(15)
        servos = dump(bus)
        for dxl_id, (model, deg) in enumerate(zip(MIXED, (10, -5, 30), strict=True), start=1):
            _, _, _, _, rpm_unit, ppr, centre = EMANUAL[model]
            assert servos[dxl_id]["goal_position"] == centre + round(deg / 360 * ppr)
            # 120 deg/s = 20 rev/min in the model's own unit
            assert servos[dxl_id]["profile_velocity"] == int(20 / rpm_unit)
        angles = head.read_angles()
        for got, deg, model in zip((angles.pan, angles.tilt, angles.roll), (10, -5, 30), MIXED,
                                   strict=True):
            assert abs(math.degrees(got) - deg) <= 360 / EMANUAL[model][5] + 1e-9
        health = head.health()
        assert health["roll"]["voltage_v"] == 24.0 and health["pan"]["voltage_v"] == 12.0
        assert health["pan"]["temperature_c"] == 32 and health["roll"]["hardware_error"] == 0


def test_hardware_encoders_read_a_continuous_angle_to_about_a_pulse(start_bus):
    bus = start_bus("--model", "xh540-w270", "xh540-w270", "ph54-200-s500-r",
                    "--encoder", "hardware")
    errors = {1: [], 3: []}
    with DynamixelHead(head_cfg(bus.ready["link"])) as head:
        for k in range(6):
            head.move_to(math.radians(3 * k + 0.03), 0.0, math.radians(7 * k + 0.01)).wait(15)
            angles = head.read_angles()
            servos = dump(bus)
            errors[1].append(math.degrees(angles.pan - servos[1]["actual_rad"]))
            errors[3].append(math.degrees(angles.roll - servos[3]["actual_rad"]))
    x_pulse, p_pulse = 360 / 4096, 360 / 1_003_846
    # the reading is not the truth, but within a few pulses of it
    assert any(abs(e) > 1e-6 for e in errors[1])
    assert max(map(abs, errors[1])) < 4 * x_pulse
    assert max(map(abs, errors[3])) < 10 * p_pulse


def test_a_servo_of_another_model_is_refused_before_anything_moves(start_bus, tmp_path):
    bus = start_bus("--model", "xh540-w270", "xh540-w270", "xm430-w350")
    head = DynamixelHead(head_cfg(bus.ready["link"], model={"roll": "xm430-w350",
                                                             "pan": "xm540-w270"}))
    with pytest.raises(ConfigError) as info:
        head.open()
    head.disconnect()
    message = str(info.value)
    assert "devices.head.model.pan" in message and "servo 1 (pan)" in message
    assert "xm540-w270" in message and "xh540-w270" in message
    assert bus.ready["link"] in message
    servos = dump(bus)
    assert all(s["torque_enable"] == 0 and s["return_delay_time"] == 250
               for s in servos.values())  # no EEPROM write, no torque
    # through the CLI: exit 2, the same message, nothing moves
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({
        "name": "dxl", "records": {"directory": str(tmp_path / "rec")},
        "devices": {"head": {"port": bus.ready["link"], "model": "xm430-w350",
                             **STAND_IN_TIMING["head"]}}}))
    done = cli("run", "head-sweep", "--rig", str(rig))
    assert done.returncode == 2, done.stderr
    assert "devices.head.model" in done.stderr and "xh540-w270" in done.stderr
    assert all(s["torque_enable"] == 0 for s in dump(bus).values())


def test_a_servo_at_another_baud_is_refused_naming_the_baud_it_answers_at(start_bus):
    bus = start_bus("--baud", "57600", "--wire-timing")
    head = DynamixelHead(head_cfg(bus.ready["link"], retries=0))
    with pytest.raises(ConfigError) as info:
        head.open()
    head.disconnect()
    message = str(info.value)
    assert message.startswith("devices.head.baud: 1000000")
    assert "servo 1 (pan)" in message and "answers at 57600 baud" in message
    assert bus.ready["link"] in message
    assert all(s["torque_enable"] == 0 for s in dump(bus).values())


def test_head_scan_finds_ids_models_and_bauds(start_bus):
    bus = start_bus("--ids", "1", "2", "7", "--model", "xh540-w270", "mx-64",
                    "ph54-200-s500-r", "--baud", "1000000", "1000000", "57600",
                    "--wire-timing")
    done = cli("head", "scan", "--port", bus.ready["link"], "--json")
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    assert [(s["id"], s["model"], s["baud"]) for s in found] == [
        (7, "ph54-200-s500-r", 57600), (1, "xh540-w270", 1_000_000),
        (2, "mx-64", 1_000_000)]
    assert {s["id"]: s["model_number"] for s in found} == {1: 1100, 2: 311, 7: 2020}
    assert all(isinstance(s["firmware"], int) for s in found)


def test_head_reboot_clears_an_alert_and_reports_it(start_bus, tmp_path):
    bus = start_bus("--model", "xm430-w350", "xm430-w350", "ph54-100-s500-r")
    control(bus.ready["control"], {"cmd": "hw_error", "id": 3, "error": "overload"})
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({"name": "dxl", "devices": {"head": {
        "port": bus.ready["link"], **STAND_IN_TIMING["head"]}}}))
    done = cli("head", "reboot", "--rig", str(rig), "--json")
    assert done.returncode == 0, done.stderr
    (row,) = json.loads(done.stdout)
    assert (row["axis"], row["id"], row["model"]) == ("roll", 3, "ph54-100-s500-r")
    assert (row["before"], row["after"]) == ("overload", "none")
    assert dump(bus)[3]["hardware_error_status"] == 0


def test_heating_under_load_and_low_supply_are_seen_by_health_and_doctor(start_bus):
    bus = start_bus("--model", "xh540-w270", "xh540-w270", "xm430-w350")
    with DynamixelHead(head_cfg(bus.ready["link"])) as head:
        control(bus.ready["control"], {"cmd": "set", "id": 2, "heating_c_per_s": 40.0})
        deadline = time.monotonic() + 30
        while head.health()["tilt"]["temperature_c"] < 72 and time.monotonic() < deadline:
            time.sleep(0.05)
        control(bus.ready["control"], {"cmd": "set", "id": 2, "heating_c_per_s": 0.0})
        health = head.health()
        assert 72 <= health["tilt"]["temperature_c"] < 80
        assert health["pan"]["temperature_c"] == 32
        control(bus.ready["control"], {"cmd": "set", "voltage": 9.0})  # every servo
        warnings = servo_warnings(head)
        assert any("servo 2 (tilt, xh540-w270): temperature" in w for w in warnings)
        assert any("servo 3 (roll, xm430-w350): input voltage 9.0 V" in w for w in warnings)
        assert any("alert: input voltage" in w for w in warnings)


def test_over_temperature_stops_a_run_with_the_reason(start_bus, tmp_path):
    bus = start_bus("--model", "ph54-200-s500-r", "ph54-200-s500-r", "xm430-w350")
    rig = tmp_path / "rig.yaml"
    # pausing off (``max_pause_s: 0``): the alert ends the run (tests/test_cli_runs.py
    # checks that an alert pauses a run until `rigctl head reboot`)
    rig.write_text(yaml.safe_dump({"name": "dxl", "records": {"directory": "rec"},
                                   "max_pause_s": 0,
                                   "devices": {"head": {"port": bus.ready["link"],
                                                        **STAND_IN_TIMING["head"]}}}))

    def on_event(event):
        if event["type"] == "step" and event["step"].startswith("capture"):
            control(bus.ready["control"], {"cmd": "set", "id": 1, "temperature": 80})

    outcome = Runner(load_rig(rig), show_progress=False, on_event=on_event).run(
        "head-sweep", {"pan_deg": [-6, 6], "tilt_deg": [0], "settle_s": 0.0})
    assert outcome.status == "failed"
    assert "servo 1 (pan)" in outcome.reason and "80 C" in outcome.reason
    meta = json.loads((RunDirectory(Path(outcome.run_dir)).captures_dir / "000.json")
                      .read_text())
    assert meta["head_health"]["pan"]["temperature_c"] == 80
    assert meta["head_health"]["roll"]["voltage_v"] == 12.0
    assert "current_a" in meta["head_health"]["tilt"]


def test_worlds_per_family_and_random_worlds_draw_servo_models():
    families = {"head-xh540": "xh540-w270", "head-mx64": "mx-64",
                "head-ph54": "ph54-200-s500-r", "head-mixed": "ph54-100-s500-r"}
    for name, pan in families.items():
        head = load_world(world_file(name)).spec.head
        assert head.models[0] == pan and head.encoder == "hardware"
    assert load_world(world_file("head-mixed")).spec.head.models[2] == "xm430-w350"
    drawn = [random_world(seed)["head"] for seed in range(300, 340)]
    assert all(h["encoder"] == "hardware" for h in drawn)
    assert {SPEC_BY_NAME[h["models"][0]].family for h in drawn} == {"x", "p"}
    assert any(h["models"][0].startswith("mx-") for h in drawn)
    assert any(SPEC_BY_NAME[h["models"][0]].family != SPEC_BY_NAME[h["models"][2]].family
               for h in drawn)
    for h in drawn:  # noise up to half of the pan servo's pulse
        assert 0 <= h["encoder_noise_deg"] <= 0.5 * 360 / SPEC_BY_NAME[
            h["models"][0]].pulses_per_rev
    WorldFile.model_validate(random_world(300))
