"""The real dynamixel_sdk against the Protocol 2.0 bus stand-in on a pty."""

from __future__ import annotations

import json
import math
import os
import socket
import time
from pathlib import Path

import dynamixel_sdk as sdk
import pytest
import yaml

from rigctl.config import load_rig, parse_rig
from rigctl.drivers.dynamixel import DynamixelHead, TimedPortHandler
from rigctl.errors import DeviceError, ProtocolError
from rigctl.mocks.sim import STAND_IN_TIMING
from rigctl.records import RunDirectory
from rigctl.runner import Runner
from tests.mockproc import MockProcess, control
from tests.waiting import wait_until

pytestmark = pytest.mark.integration


@pytest.fixture
def bus(tmp_path):
    """A stand-in bus with servos 1, 2, 3; stopped by PID in teardown."""
    link, sock = tmp_path / "dxl", tmp_path / "dxl.sock"
    proc = MockProcess(["-m", "rigctl.mocks.dynamixel_bus", "--link", str(link),
                        "--control", str(sock)])
    yield proc
    assert proc.stop() == 0
    assert not link.exists() and not sock.exists()  # the stand-in cleans up after itself


@pytest.fixture
def port(bus):
    # the SDK's ~34 ms timeout is for servos; a stand-in on a busy host may answer later
    handler = TimedPortHandler(bus.ready["link"], 500.0)
    assert handler.openPort() and handler.setBaudRate(1_000_000)
    yield handler
    handler.closePort()


def head_config(link: str, **extra):
    """A head on the stand-in's bus, with the timing `sim up` writes for stand-in
    processes (a descheduled stand-in answers late; the SDK's ~34 ms suits servos)."""
    text = f"devices:\n  head:\n    port: {link}\n    speed_cap_dps: 120\n" \
           f"    accel_cap_dps2: 600\n    park: {{policy: hold}}\n"
    for key, value in {**STAND_IN_TIMING["head"], **extra}.items():
        text += f"    {key}: {value}\n"
    return parse_rig(text).devices.head


ph = sdk.PacketHandler(2.0)


def test_a_control_client_that_gives_up_does_not_stop_the_bus(port, bus):
    """A control client that hangs up before reading its replies (as the camera stand-in
    does after 1 s on a busy host) is dropped; the bus goes on answering on the serial
    port and on the control socket. Before, writing the replies raised EPIPE and the
    stand-in exited."""
    for _ in range(3):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.connect(bus.ready["control"])
            sock.sendall(b'{"cmd": "dump"}\n' * 500)  # more reply than a socket buffers
    assert control(bus.ready["control"], {"cmd": "dump"})["ok"]
    assert bus.proc.poll() is None
    model, comm, error = ph.ping(port, 2)
    assert (model, comm, error) == (1020, sdk.COMM_SUCCESS, 0)


def test_ping_and_broadcast_ping(port, bus):
    model, comm, error = ph.ping(port, 2)
    assert (model, comm, error) == (1020, sdk.COMM_SUCCESS, 0)
    _, comm, _ = ph.ping(port, 9)
    assert comm == sdk.COMM_RX_TIMEOUT
    found, comm = ph.broadcastPing(port)
    assert comm == sdk.COMM_SUCCESS
    assert sorted(found) == [1, 2, 3] and found[1] == [1020, 52]


def test_read_write_sizes_and_error_bytes(port):
    assert ph.read2ByteTxRx(port, 1, 0) == (1020, sdk.COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, 65, 1) == (sdk.COMM_SUCCESS, 0)  # LED
    assert ph.read1ByteTxRx(port, 1, 65)[0] == 1
    assert ph.write4ByteTxRx(port, 1, 112, 77) == (sdk.COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 1, 112)[0] == 77
    assert ph.write2ByteTxRx(port, 1, 84, 700) == (sdk.COMM_SUCCESS, 0)
    assert ph.read2ByteTxRx(port, 1, 84)[0] == 700
    # read-only item: access error 7; out of range: data range 4; half an item: length 5
    assert ph.write2ByteTxRx(port, 1, 0, 5) == (sdk.COMM_SUCCESS, 7)
    assert ph.write1ByteTxRx(port, 1, 68, 9) == (sdk.COMM_SUCCESS, 4)
    assert ph.write2ByteTxRx(port, 1, 112, 5) == (sdk.COMM_SUCCESS, 5)
    # EEPROM with torque on: access error
    assert ph.write1ByteTxRx(port, 1, 64, 1) == (sdk.COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, 9, 0) == (sdk.COMM_SUCCESS, 7)
    # goal outside the position limits: data limit error 6
    assert ph.write4ByteTxRx(port, 1, 116, 5000) == (sdk.COMM_SUCCESS, 6)


def test_reg_write_then_action(port):
    assert ph.regWriteTxRx(port, 2, 65, 1, [1]) == (sdk.COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 2, 69)[0] == 1  # registered instruction
    assert ph.read1ByteTxRx(port, 2, 65)[0] == 0  # not applied yet
    ph.action(port, sdk.BROADCAST_ID)
    time.sleep(0.01)
    assert ph.read1ByteTxRx(port, 2, 65)[0] == 1
    # A unicast action is answered (instruction error: nothing registered) but the SDK
    # never reads that reply; the next transaction must still get its own answer.
    assert ph.action(port, 2) == sdk.COMM_SUCCESS
    time.sleep(0.01)
    assert ph.read2ByteTxRx(port, 2, 0) == (1020, sdk.COMM_SUCCESS, 0)


def test_sync_and_fast_sync_read_write(port):
    write = sdk.GroupSyncWrite(port, ph, 112, 4)
    for dxl_id, value in ((1, 10), (2, 20), (3, 30)):
        assert write.addParam(dxl_id, value.to_bytes(4, "little"))
    assert write.txPacket() == sdk.COMM_SUCCESS
    for fast in (False, True):
        read = sdk.GroupSyncRead(port, ph, 112, 4)
        for dxl_id in (1, 2, 3):
            read.addParam(dxl_id)
        result = read.fastSyncRead() if fast else read.txRxPacket()
        assert result == sdk.COMM_SUCCESS
        assert [read.getData(i, 112, 4) for i in (1, 2, 3)] == [10, 20, 30]


def test_bulk_read_write_and_fast_bulk_read(port):
    write = sdk.GroupBulkWrite(port, ph)
    assert write.addParam(1, 65, 1, [1])
    assert write.addParam(3, 112, 4, list((99).to_bytes(4, "little")))
    assert write.txPacket() == sdk.COMM_SUCCESS
    read = sdk.GroupBulkRead(port, ph)
    assert read.addParam(1, 65, 1)
    assert read.addParam(3, 112, 4)
    assert read.txRxPacket() == sdk.COMM_SUCCESS
    assert (read.getData(1, 65, 1), read.getData(3, 112, 4)) == (1, 99)
    assert read.fastBulkRead() == sdk.COMM_SUCCESS
    assert (read.getData(1, 65, 1), read.getData(3, 112, 4)) == (1, 99)


def test_reboot_clears_hardware_error_and_factory_reset(port, bus):
    ph.write1ByteTxRx(port, 2, 64, 1)
    control(bus.ready["control"], {"cmd": "hw_error", "id": 2, "error": "overheat"})
    value, comm, error = ph.read1ByteTxRx(port, 2, 70)
    assert (value, comm, error) == (0x04, sdk.COMM_SUCCESS, 0x80)  # Alert bit
    assert ph.read1ByteTxRx(port, 2, 64)[0] == 0  # torque cut
    assert ph.write1ByteTxRx(port, 2, 64, 1) == (sdk.COMM_SUCCESS, 0x81)  # refused until reboot
    assert ph.reboot(port, 2) == (sdk.COMM_SUCCESS, 0x80)
    assert ph.read1ByteTxRx(port, 2, 70) == (0, sdk.COMM_SUCCESS, 0)
    ph.write1ByteTxRx(port, 3, 9, 10)
    assert ph.factoryReset(port, 3, 0x02) == (sdk.COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 3, 9)[0] == 250  # back to the default
    assert ph.clearMultiTurn(port, 3)[0] == sdk.COMM_SUCCESS


def test_trapezoid_and_triangle_timing(port, bus):
    """1024 pulses at profile velocity 100, acceleration 20: 0.975 s trapezoid (e-Manual
    units 0.229 rpm and 214.577 rev/min^2); 100 pulses: a triangle. The shaft is frozen
    half-way (a latched fault of the stand-in) so that the profile is seen under way
    however late the reads come; thawed, the move goes on to its goal."""
    sock = bus.ready["control"]
    ph.write4ByteTxRx(port, 1, 108, 20)
    ph.write4ByteTxRx(port, 1, 112, 100)
    ph.write1ByteTxRx(port, 1, 64, 1)
    control(sock, {"cmd": "freeze", "id": 1, "at_fraction": 0.5})
    t0 = time.monotonic()
    ph.write4ByteTxRx(port, 1, 116, 2048 + 1024)
    status = ph.read1ByteTxRx(port, 1, 123)[0]
    assert status & 0x02 and (status >> 4) == 3  # profile ongoing, trapezoidal
    assert ph.read1ByteTxRx(port, 1, 122)[0] == 1  # moving
    # frozen at half the profile's time: half-way, by the trapezoid's symmetry
    wait_until(lambda: servo(sock, 1)["frozen"], what="servo 1 frozen half-way")
    assert ph.read4ByteTxRx(port, 1, 132)[0] == 2048 + 512
    control(sock, {"cmd": "thaw", "id": 1})
    wait_until(lambda: ph.read1ByteTxRx(port, 1, 122)[0] == 0, what="the move to end")
    # never sooner than the profile allows (0.975 s); a busy host only makes it later
    assert time.monotonic() - t0 > 0.9
    assert ph.read4ByteTxRx(port, 1, 132)[0] == 3072
    control(sock, {"cmd": "freeze", "id": 1, "at_fraction": 0.5})
    ph.write4ByteTxRx(port, 1, 116, 3072 - 100)
    assert ph.read1ByteTxRx(port, 1, 123)[0] >> 4 == 2  # triangular
    control(sock, {"cmd": "thaw", "id": 1})


def servo(sock: str, dxl_id: int) -> dict:
    """One servo's state from the stand-in's control socket."""
    return next(s for s in control(sock, {"cmd": "dump"})["servos"] if s["id"] == dxl_id)


def test_bus_watchdog_stops_servo_and_locks_goal(port):
    ph.write1ByteTxRx(port, 1, 64, 1)
    ph.write1ByteTxRx(port, 1, 98, 5)  # 100 ms
    # polled every 0.25 s, longer than the watchdog: each poll finds the bus quiet
    wait_until(lambda: ph.read1ByteTxRx(port, 1, 98)[0] == 0xFF, poll=0.25,
               what="-1: Bus Watchdog Error")
    assert ph.write4ByteTxRx(port, 1, 116, 2100) == (sdk.COMM_SUCCESS, 7)
    assert ph.write1ByteTxRx(port, 1, 98, 0) == (sdk.COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, 116, 2100) == (sdk.COMM_SUCCESS, 0)


def test_driver_moves_and_reads_angles(bus):
    head = DynamixelHead(head_config(bus.ready["link"], zero_offset_deg="{pan: 5}",
                                     direction="{tilt: -1}"))
    with head:
        assert len(head.eeprom_writes) == 3  # return delay time 250 -> 0 on each servo
        head.move_to(math.radians(12), math.radians(-7), math.radians(45)).wait(10)
        angles = head.read_angles()
        quantum = math.radians(360 / 4096)
        assert abs(angles.pan - math.radians(12)) <= quantum
        assert abs(angles.tilt - math.radians(-7)) <= quantum
        assert abs(angles.roll - math.radians(45)) <= quantum
        servos = {s["id"]: s for s in control(bus.ready["control"], {"cmd": "dump"})["servos"]}
        # offset and direction reach the wire: pan 12+5 deg, tilt inverted
        assert servos[1]["goal_position"] == round(2048 + 17 * 4096 / 360)
        assert servos[2]["goal_position"] == round(2048 + 7 * 4096 / 360)
    # a second connection finds the EEPROM right and writes nothing
    head2 = DynamixelHead(head_config(bus.ready["link"]))
    with head2:
        assert head2.eeprom_writes == []


def test_corrupted_and_dropped_replies_are_retried(bus):
    # a second's wait for each reply: a stand-in descheduled past the sim's 100 ms would
    # time out a try of its own and leave the injected faults to other tries (seen once)
    head = DynamixelHead(head_config(bus.ready["link"], packet_timeout_ms=1000, retries=3))
    with head:
        control(bus.ready["control"], {"cmd": "corrupt_next"})
        control(bus.ready["control"], {"cmd": "drop_next"})
        head.move_to(math.radians(5), 0.0, 0.0).wait(10)
        assert abs(head.read_angles().pan - math.radians(5)) < 0.002
        assert head.retries_used >= 2
        stats = head.describe()["bus_stats"]
        servos = {k: v for k, v in stats.items() if k.isdigit()}
        assert sorted(servos) == ["1", "2", "3"]
        # both faults hit the move's first fast sync read: the corrupt packet fails its
        # last block (servo 3), the dropped one has no block at all (servo 1 opens it)
        assert servos["3"]["retries"] >= 1 and servos["1"]["retries"] >= 1
        # every retry is counted in the head's total; a retry with no servo to blame (a
        # late reply on a busy host, a sync write) counts for the group alone, so the
        # servos' counts make up at most the total (equal on an idle host)
        assert sum(v["retries"] for v in servos.values()) <= head.retries_used
        assert 2 <= stats["group"]["retries"] <= head.retries_used
        assert all(v["errors"] == 0 for v in servos.values()) and stats["group"]["errors"] == 0


def test_persistent_silence_is_counted_against_the_servo(bus):
    head = DynamixelHead(head_config(bus.ready["link"], retries=2))
    with head:
        before = dict(head.describe()["bus_stats"]["1"])
        control(bus.ready["control"], {"cmd": "drop_next", "count": 10})
        with pytest.raises(DeviceError):
            head._read1(1, 65, "read LED")
        after = head.describe()["bus_stats"]["1"]
        assert after["transactions"] == before["transactions"] + 1
        assert after["retries"] == before["retries"] + 2
        assert after["errors"] == before["errors"] + 1


def test_latency_timer_emulation_holds_every_reply(tmp_path):
    """--latency-timer-ms 16: no reply reaches the host sooner than 16 ms after its
    request (a lower bound: a busy host only makes it later)."""
    link = tmp_path / "dxl-lt"
    proc = MockProcess(["-m", "rigctl.mocks.dynamixel_bus", "--link", str(link),
                        "--latency-timer-ms", "16"])
    try:
        handler = TimedPortHandler(proc.ready["link"], 500.0)
        assert handler.openPort() and handler.setBaudRate(1_000_000)
        try:
            for _ in range(5):
                t0 = time.perf_counter()
                _, comm, _ = ph.read4ByteTxRx(handler, 1, 132)
                assert comm == sdk.COMM_SUCCESS
                assert time.perf_counter() - t0 >= 0.016
        finally:
            handler.closePort()
    finally:
        assert proc.stop() == 0


def test_persistent_silence_raises_device_error_naming_servo(bus):
    head = DynamixelHead(head_config(bus.ready["link"], retries=2))
    with head:
        control(bus.ready["control"], {"cmd": "drop_next", "count": 10})
        with pytest.raises(DeviceError, match=r"head servo 1 \(pan\).*failed after 3 tries"):
            head._read1(1, 65, "read LED")


def test_overload_mid_move_ends_in_device_error_with_torque_off(bus):
    head = DynamixelHead(head_config(bus.ready["link"], speed_cap_dps=20))
    with head:
        # the pan shaft sticks a fifth of the way (latched): the move is under way
        # whenever the overload comes
        control(bus.ready["control"], {"cmd": "freeze", "id": 1, "at_fraction": 0.2})
        status = head.move_to(math.radians(40), 0.0, 0.0)
        wait_until(lambda: servo(bus.ready["control"], 1)["frozen"], what="pan stuck")
        assert not status.done
        control(bus.ready["control"], {"cmd": "hw_error", "id": 1, "error": "overload"})
        with pytest.raises(DeviceError, match=r"servo 1 \(pan\).*overload.*torque is off"):
            status.wait(10)
        assert head._read1(1, 64, "read torque", check=False) == 0


def test_eeprom_write_with_torque_on_surfaces_access_error(bus):
    head = DynamixelHead(head_config(bus.ready["link"]))
    with head:
        with pytest.raises(ProtocolError, match=r"servo 3 \(roll\).*error 7"):
            head._write(3, 9, 1, 5, "write return delay time")
        # the status packet's error byte is counted against the servo that sent it
        stats = head.describe()["bus_stats"]
        assert (stats["3"]["error_bytes"], stats["3"]["alerts"]) == (1, 0)
        assert stats["1"]["error_bytes"] == stats["2"]["error_bytes"] == 0


def test_a_failed_sync_read_counts_against_the_servo_that_did_not_answer(bus):
    """A sync read's replies come one per servo in the order asked; servo 2, asked first
    here (pan), stays silent on every try (the stand-in drops all nine replies of three
    tries): its retries and its failure, not the others'."""
    head = DynamixelHead(head_config(bus.ready["link"], retries=2,
                                     ids="{pan: 2, tilt: 1, roll: 3}"))
    with head:
        before = head.describe()["bus_stats"]
        control(bus.ready["control"], {"cmd": "drop_next", "count": 9})
        with pytest.raises(DeviceError, match=r"head servo 2 \(pan\).*sync read hardware "
                                              r"error status failed after 3 tries"):
            head.hardware_errors()
        after = head.describe()["bus_stats"]
        change = {k: {n: after[k][n] - before[k][n] for n in ("transactions", "retries",
                                                              "errors")}
                  for k in ("1", "2", "3", "group")}
        one = {"transactions": 1, "retries": 0, "errors": 0}
        assert change == {"1": one, "3": one, "2": {"transactions": 1, "retries": 2,
                                                    "errors": 1},
                          "group": {"transactions": 1, "retries": 2, "errors": 1}}
        assert head.hardware_errors() == {}  # the bus is quiet again


def test_driver_reconnects_after_port_vanishes(bus, tmp_path):
    link = bus.ready["link"]
    head = DynamixelHead(head_config(link, packet_timeout_ms=500))  # no timeouts of load
    head.open()
    try:
        bus.stop()
        replacement = MockProcess(["-m", "rigctl.mocks.dynamixel_bus", "--link", link])
        try:
            angles = head.read_angles()  # EIO on the old pty, reopened on the new one
            assert angles.pan == pytest.approx(0.0, abs=1e-9)
            stats = head.describe()["bus_stats"]
            assert stats["port"] == {"lost": 1, "reopened": 1}
            # the retry was the port's doing, not a servo's
            assert stats["group"]["retries"] == 1
            assert all(stats[k]["retries"] == stats[k]["errors"] == 0 for k in "123")
        finally:
            head.port.closePort()
            head.port = None
            replacement.stop()
    finally:
        head.port = None


def test_head_sweep_procedure_runs_through_runner(bus, tmp_path):
    rig = tmp_path / "rig.yaml"
    head = {"port": bus.ready["link"], "speed_cap_dps": 180, "accel_cap_dps2": 1000,
            **STAND_IN_TIMING["head"]}
    rig.write_text(yaml.safe_dump({"name": "dxl-rig", "records": {"directory": "rec"},
                                   "devices": {"head": head}}))
    config = load_rig(rig)
    outcome = Runner(config, show_progress=False).run(
        "head-sweep", {"pan_deg": [-6, 6], "tilt_deg": [-3, 3], "settle_s": 0.0})
    assert outcome.status == "succeeded", outcome.reason
    assert outcome.result["poses"] == 4
    # encoder quantisation is 0.088 deg: the head reaches every goal within one pulse
    assert outcome.result["summary"]["max_abs_error_deg"] <= 360 / 4096
    run = RunDirectory(outcome.run_dir)
    assert len(run.captures()) == 4
    versions = (run.path / "versions.json").read_text()
    assert '"model": "xm430-w350"' in versions
    servos = control(bus.ready["control"], {"cmd": "dump"})["servos"]
    assert all(s["goal_position"] == 2048 for s in servos)  # parked home
    assert os.path.exists(bus.ready["link"])


def test_head_sweep_records_bus_stats_per_servo(bus, tmp_path):
    """Faults placed on given transactions of a head-sweep through the runner land on
    the servo that caused them in the run's versions.json. Servo 2 is addressed last
    (ids pan 1, tilt 3, roll 2) and has an overload when the run starts: the driver reads
    the Alert and reboots it on open. Before the first capture's fast sync read the
    stand-in corrupts the next reply (the CRC of its last block, servo 2's); before the
    second it drops the next reply (the whole packet: servo 1, whose block opens it)."""
    rig = tmp_path / "rig.yaml"
    head = {"port": bus.ready["link"], "speed_cap_dps": 180, "accel_cap_dps2": 1000,
            "ids": {"pan": 1, "tilt": 3, "roll": 2},
            **STAND_IN_TIMING["head"], "packet_timeout_ms": 500}  # no timeouts of load
    rig.write_text(yaml.safe_dump({"name": "dxl-rig", "records": {"directory": "rec"},
                                   "devices": {"head": head}}))
    sock = bus.ready["control"]
    control(sock, {"cmd": "hw_error", "id": 2, "error": "overload"})
    faults = ["corrupt_next", "drop_next"]
    placed = []

    def on_event(event):
        # a capture step's first transaction is read_angles' fast sync read; the move
        # before it has finished, so nothing else is on the bus
        if event["type"] == "step" and event["step"].startswith("capture") and faults:
            placed.append(faults.pop(0))
            control(sock, {"cmd": placed[-1]})

    outcome = Runner(load_rig(rig), show_progress=False, on_event=on_event).run(
        "head-sweep", {"pan_deg": [-6, 6], "tilt_deg": [0], "settle_s": 0.0})
    assert outcome.status == "succeeded", outcome.reason
    assert placed == ["corrupt_next", "drop_next"]
    stats = json.loads((Path(outcome.run_dir) / "versions.json").read_text()
                       )["devices"]["head"]["bus_stats"]
    assert sorted(stats) == ["1", "2", "3", "group"]  # no "port": it was never lost
    s1, s2, s3, group = stats["1"], stats["2"], stats["3"], stats["group"]
    # retries against the servo whose reply failed, none of them a failure
    assert (s1["retries"], s2["retries"], s3["retries"], group["retries"]) == (1, 1, 0, 2)
    assert s1["errors"] == s2["errors"] == s3["errors"] == group["errors"] == 0
    # servo 2's Alert on ping, firmware read, hardware error read and reboot; then none
    assert (s2["error_bytes"], s2["alerts"]) == (4, 4)
    assert (s1["error_bytes"], s1["alerts"], s3["error_bytes"], s3["alerts"]) == (0, 0, 0, 0)
    # every sync packet counts for each servo it addressed; the unicast ones are the same
    # for all three, but for servo 2's two (hardware error read, reboot)
    assert group["transactions"] >= 10
    assert s1["transactions"] - group["transactions"] == s3["transactions"] - group[
        "transactions"] > 0
    assert s2["transactions"] == s1["transactions"] + 2
    servos = {s["id"]: s for s in control(sock, {"cmd": "dump"})["servos"]}
    assert servos[2]["hardware_error_status"] == 0  # rebooted
