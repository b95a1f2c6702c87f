"""V4L2 controls by name against a fake ioctl layer that answers VIDIOC_QUERYCTRL,
VIDIOC_G_CTRL and VIDIOC_S_CTRL as a UVC camera's driver does (names from before or
after Linux 5.16). What a real /dev/video device does is not tested here."""

from __future__ import annotations

import errno

import pytest

from rigctl.drivers.v4l2_controls import (
    CONTROL,
    FLAG_INACTIVE,
    FLAG_NEXT_CTRL,
    QUERYCTRL,
    RENAMED,
    VIDIOC_G_CTRL,
    VIDIOC_QUERYCTRL,
    VIDIOC_S_CTRL,
    V4L2Controls,
    canonical,
    device_path,
    v4l2_name,
)
from rigctl.errors import DeviceError

# (id, kernel name, type, min, max, default); ids as in linux/v4l2-controls.h
NEW_NAMES = [
    (0x00980001, b"Camera Controls", 6, 0, 0, 0),  # a control class: skipped
    (0x00980900, b"Brightness", 1, -64, 64, 0),
    (0x0098090C, b"White Balance, Automatic", 2, 0, 1, 1),
    (0x00980919, b"Hue, Automatic", 2, 0, 1, 0),
    (0x009A0901, b"Auto Exposure", 3, 0, 3, 3),
    (0x009A0902, b"Exposure Time, Absolute", 1, 1, 5000, 156),
    (0x009A0903, b"Exposure, Dynamic Framerate", 2, 0, 1, 1),
    (0x009A090A, b"Focus, Absolute", 1, 0, 1023, 68),
    (0x009A090C, b"Focus, Automatic Continuous", 2, 0, 1, 1),
]
# uvcvideo's own names before it took the framework's (Linux 5.16)
UVC_OLD = {b"White Balance, Automatic": b"White Balance Temperature, Auto",
           b"Hue, Automatic": b"Hue, Auto",
           b"Auto Exposure": b"Exposure, Auto",
           b"Exposure Time, Absolute": b"Exposure (Absolute)",
           b"Exposure, Dynamic Framerate": b"Exposure, Auto Priority",
           b"Focus, Absolute": b"Focus (absolute)",
           b"Focus, Automatic Continuous": b"Focus, Auto"}
OLD_NAMES = [(cid, UVC_OLD.get(name, name), *rest) for cid, name, *rest in NEW_NAMES]


class FakeCamera:
    """Answers the three ioctls on a table of controls; an automatic that is on makes its
    manual control inactive (writes fail with EACCES), as UVC drivers do."""

    def __init__(self, table, stubborn=None):
        self.table = {c[0]: list(c) for c in table}
        self.values = {c[0]: c[5] for c in table}
        self.stubborn = stubborn or {}  # id -> value it keeps whatever is written
        self.writes: list[tuple[int, int]] = []

    def _inactive(self, cid):
        return (cid == 0x009A0902 and self.values.get(0x009A0901) != 1) or \
            (cid == 0x009A090A and self.values.get(0x009A090C) == 1)

    def ioctl(self, fd, request, buf):
        assert fd == 99
        if request == VIDIOC_QUERYCTRL:
            cid = QUERYCTRL.unpack(buf)[0]
            assert cid & FLAG_NEXT_CTRL
            later = sorted(i for i in self.table if i > cid & ~FLAG_NEXT_CTRL)
            if not later:
                raise OSError(errno.EINVAL, "Invalid argument")
            i, name, ctype, lo, hi, default = self.table[later[0]]
            flags = FLAG_INACTIVE if self._inactive(i) else 0
            buf[:] = QUERYCTRL.pack(i, ctype, name, lo, hi, 1, default, flags, 0, 0)
        elif request == VIDIOC_G_CTRL:
            cid = CONTROL.unpack(buf)[0]
            buf[:] = CONTROL.pack(cid, self.stubborn.get(cid, self.values[cid]))
        elif request == VIDIOC_S_CTRL:
            cid, value = CONTROL.unpack(buf)
            if self._inactive(cid):
                raise OSError(errno.EACCES, "Permission denied")
            self.values[cid] = value
            self.writes.append((cid, value))
        else:
            raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")


def controls(table, **kw):
    fake = FakeCamera(table, **kw)
    return V4L2Controls(99, "/dev/video7", fake.ioctl), fake


def test_names_are_v4l2_ctls():
    assert v4l2_name("Focus, Automatic Continuous") == "focus_automatic_continuous"
    assert v4l2_name("Exposure (Absolute)") == "exposure_absolute"
    assert v4l2_name("White Balance Temperature, Auto") == "white_balance_temperature_auto"
    assert v4l2_name("Exposure, Auto Priority") == "exposure_auto_priority"
    assert v4l2_name("Exposure, Dynamic Framerate") == "exposure_dynamic_framerate"


def test_every_uvc_rename_in_the_fake_tables_is_known():
    """Each control the fake device names differently before and after 5.16 has its old
    name mapped to its new one; a name that did not change is its own canonical name."""
    for (_, new, *_r), (_, old, *_s) in zip(NEW_NAMES, OLD_NAMES, strict=True):
        new_name, old_name = v4l2_name(new.decode()), v4l2_name(old.decode())
        assert canonical(old_name) == new_name and canonical(new_name) == new_name
    assert RENAMED["exposure_auto_priority"] == "exposure_dynamic_framerate"


@pytest.mark.parametrize("table", [NEW_NAMES, OLD_NAMES], ids=["linux>=5.16", "linux<5.16"])
@pytest.mark.parametrize("name", ["exposure_auto_priority", "exposure_dynamic_framerate"])
def test_exposure_dynamic_framerate_by_either_name(table, name):
    """V4L2_CID_EXPOSURE_AUTO_PRIORITY: uvcvideo's "Exposure, Auto Priority" before 5.16,
    the framework's "Exposure, Dynamic Framerate" since."""
    cam, fake = controls(table)
    assert cam.resolve(name).id == 0x009A0903
    got = cam.apply({name: 0}, auto_off=False)
    assert fake.values[0x009A0903] == 0 and fake.writes == [(0x009A0903, 0)]
    device_name = "exposure_dynamic_framerate" if table is NEW_NAMES \
        else "exposure_auto_priority"
    assert got == {device_name: 0}


def test_device_path_of_the_rig_files_camera():
    assert device_path(0) == "/dev/video0" and device_path("2") == "/dev/video2"
    assert device_path("/dev/v4l/by-id/usb-cam-video-index0") == \
        "/dev/v4l/by-id/usb-cam-video-index0"
    assert device_path("http://127.0.0.1:8080/stream.mjpg") is None


@pytest.mark.parametrize("table", [NEW_NAMES, OLD_NAMES], ids=["linux>=5.16", "linux<5.16"])
@pytest.mark.parametrize("focus, exposure", [("focus_absolute", "exposure_time_absolute"),
                                             ("focus_absolute", "exposure_absolute")])
def test_automatics_off_then_values_set_by_either_name_and_read_back(table, focus, exposure):
    cam, fake = controls(table)
    assert "camera_controls" not in cam.controls  # control classes are not controls
    got = cam.apply({focus: 300, exposure: 250, "brightness": -10}, auto_off=True)
    assert fake.values[0x009A090C] == 0 and fake.values[0x009A0901] == 1
    assert fake.values[0x0098090C] == 0
    assert fake.values[0x009A090A] == 300 and fake.values[0x009A0902] == 250
    assert fake.values[0x00980900] == -10
    # automatics first: the manual controls are inactive until they are off
    order = [cid for cid, _ in fake.writes]
    assert order.index(0x009A090C) < order.index(0x009A090A)
    assert order.index(0x009A0901) < order.index(0x009A0902)
    # reported under the device's own names, each value as read back
    names = {c.id: c.name for c in cam.controls.values()}
    assert got == {names[cid]: fake.values[cid] for cid, _ in fake.writes}


def test_a_value_that_does_not_take_is_named():
    cam, _ = controls(NEW_NAMES, stubborn={0x009A090A: 68})
    with pytest.raises(DeviceError, match=r"focus_absolute 300 \(read back 68\)"):
        cam.apply({"focus_absolute": 300}, auto_off=True)


def test_unknown_out_of_range_and_inactive_controls_are_refused_clearly():
    cam, _ = controls(NEW_NAMES)
    with pytest.raises(DeviceError, match=r"no control .zoom_absolute.; it has .*focus_absolute"):
        cam.apply({"zoom_absolute": 3}, auto_off=False)
    with pytest.raises(DeviceError, match=r"focus_absolute = 5000 is outside \[0, 1023\]"):
        cam.set("focus_absolute", 5000)
    # with autofocus left on, the manual focus cannot be written: the kernel's error
    with pytest.raises(DeviceError, match=r"setting focus_absolute = 300: .*Permission denied"):
        cam.apply({"focus_absolute": 300}, auto_off=False)
