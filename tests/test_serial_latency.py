"""``rigctl doctor``'s check of the head port's USB-serial latency timer, against a sysfs
tree laid out as Linux lays it out (``/sys/bus/usb-serial/devices/ttyUSB0/latency_timer``)."""

from __future__ import annotations

from rigctl.doctor import UDEV_RULE, serial_latency


def sysfs_with(tmp_path, value: str):
    dev = tmp_path / "dev"
    dev.mkdir()
    (dev / "ttyUSB0").write_text("")
    by_id = dev / "usb-FTDI_USB__-__Serial_Converter_FT1234-if00-port0"
    by_id.symlink_to(dev / "ttyUSB0")
    node = tmp_path / "sys" / "bus" / "usb-serial" / "devices" / "ttyUSB0"
    node.mkdir(parents=True)
    (node / "latency_timer").write_text(value)
    return str(by_id), tmp_path / "sys", node / "latency_timer"


def test_default_ftdi_timer_gets_the_command_and_the_udev_rule(tmp_path):
    port, sysfs, timer = sysfs_with(tmp_path, "16\n")
    found = serial_latency(port, sysfs)
    assert found["latency_timer_ms"] == 16
    hint = found["hint"]
    assert "ttyUSB0" in hint and "16 ms" in hint
    assert f"echo 1 | sudo tee {timer}" in hint and UDEV_RULE in hint


def test_one_ms_is_fine_and_a_pty_has_nothing_to_set(tmp_path):
    port, sysfs, _ = sysfs_with(tmp_path, "1\n")
    assert serial_latency(port, sysfs) == {"latency_timer_ms": 1, "hint": None}
    missing = serial_latency("/dev/pts/7", sysfs)
    assert missing["latency_timer_ms"] is None and missing["hint"] is None
    assert "no USB-serial latency timer" in missing["latency_timer_note"]


def test_unreadable_timer_is_reported_not_raised(tmp_path):
    port, sysfs, _ = sysfs_with(tmp_path, "garbage")
    found = serial_latency(port, sysfs)
    assert found["latency_timer_ms"] is None and "cannot read it" in found["hint"]
