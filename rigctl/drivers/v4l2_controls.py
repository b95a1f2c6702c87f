"""V4L2 controls by name, through the kernel's own ioctls (``VIDIOC_QUERYCTRL`` with
``V4L2_CTRL_FLAG_NEXT_CTRL`` to list them, ``VIDIOC_G_CTRL`` and ``VIDIOC_S_CTRL``).

Names are v4l2-ctl's: the driver's control name in lower case, every run of other
characters an underscore ("Focus, Automatic Continuous" -> ``focus_automatic_continuous``).
Linux 5.16 renamed several controls; a rig file may use either name and the device's own
is used (``RENAMED``). For calibration the automatic focus, exposure and white balance are
turned off (``AUTO_OFF``), and every value set is read back.

The ioctl is a parameter, so the logic is tested against a fake device
(``tests/test_v4l2_controls.py``); only the struct layouts and request numbers below meet
a real kernel.
"""

from __future__ import annotations

import fcntl
import os
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass

from rigctl.errors import DeviceError

# struct v4l2_queryctrl: id, type, name[32], minimum, maximum, step, default_value, flags,
# reserved[2]; struct v4l2_control: id, value
QUERYCTRL = struct.Struct("=II32siiiiI2I")
CONTROL = struct.Struct("=Ii")


def _iowr(nr: int, size: int) -> int:
    return (3 << 30) | (size << 16) | (ord("V") << 8) | nr


VIDIOC_G_CTRL = _iowr(27, CONTROL.size)
VIDIOC_S_CTRL = _iowr(28, CONTROL.size)
VIDIOC_QUERYCTRL = _iowr(36, QUERYCTRL.size)
FLAG_NEXT_CTRL = 0x80000000
FLAG_DISABLED = 0x0001
FLAG_READ_ONLY = 0x0004
FLAG_INACTIVE = 0x0010
TYPE_CTRL_CLASS = 6

# old name (before Linux 5.16) -> new name. Until then uvcvideo named its controls itself;
# since "media: uvcvideo: Use control names from framework" it reports the names of
# v4l2_ctrl_get_name(). The renames below are every UVC control whose v4l2-ctl name
# changed with that ("Focus (absolute)" -> "Focus, Absolute" keeps focus_absolute).
RENAMED = {
    "focus_auto": "focus_automatic_continuous",
    "exposure_absolute": "exposure_time_absolute",
    "exposure_auto": "auto_exposure",
    "exposure_auto_priority": "exposure_dynamic_framerate",
    "white_balance_temperature_auto": "white_balance_automatic",
    "white_balance_component_auto": "white_balance_automatic",
    "white_balance_red_component": "red_balance",
    "white_balance_blue_component": "blue_balance",
    "hue_auto": "hue_automatic",
}
# automatic control -> its "off" value (auto_exposure: 1 = manual mode)
AUTO_OFF = {"focus_automatic_continuous": 0, "auto_exposure": 1,
            "white_balance_automatic": 0}


def v4l2_name(text: str) -> str:
    """v4l2-ctl's name for a control."""
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")


def canonical(name: str) -> str:
    """A control's name since Linux 5.16, from either its old or its new name: the one
    name to compare settings by, whichever kernel reported them."""
    return RENAMED.get(name, name)


def device_path(device: str | int) -> str | None:
    """The V4L2 device node a rig file's ``devices.camera.device`` opens (an index N is
    ``/dev/videoN``), or None when it is no device node (a stream URL): only a device
    node has V4L2 controls."""
    if isinstance(device, int) or str(device).isdigit():
        return f"/dev/video{device}"
    return str(device) if str(device).startswith("/dev/") else None


@dataclass(frozen=True)
class Control:
    id: int
    name: str
    type: int
    minimum: int
    maximum: int
    default: int
    flags: int


Ioctl = Callable[[int, int, bytearray], object]


class V4L2Controls:
    """The controls of one open V4L2 device (``fd``)."""

    def __init__(self, fd: int, device: str, ioctl: Ioctl = fcntl.ioctl) -> None:
        self.fd, self.device, self._ioctl = fd, device, ioctl
        self.controls = self._list()

    @classmethod
    def open(cls, device: str) -> V4L2Controls:
        try:
            fd = os.open(device, os.O_RDWR | os.O_NONBLOCK)
        except OSError as exc:
            raise DeviceError(f"camera {device}: cannot open for its controls: {exc}") from None
        return cls(fd, device)

    def close(self) -> None:
        os.close(self.fd)

    def _list(self) -> dict[str, Control]:
        found: dict[str, Control] = {}
        next_id = FLAG_NEXT_CTRL
        while True:
            buf = bytearray(QUERYCTRL.pack(next_id, 0, b"", 0, 0, 0, 0, 0, 0, 0))
            try:
                self._ioctl(self.fd, VIDIOC_QUERYCTRL, buf)
            except OSError:  # EINVAL: no more controls
                break
            cid, ctype, raw, lo, hi, _step, default, flags, _r0, _r1 = QUERYCTRL.unpack(buf)
            next_id = cid | FLAG_NEXT_CTRL
            if ctype == TYPE_CTRL_CLASS or flags & FLAG_DISABLED:
                continue
            name = v4l2_name(raw.split(b"\0", 1)[0].decode(errors="replace"))
            found[name] = Control(cid, name, ctype, lo, hi, default, flags)
        return found

    def resolve(self, name: str) -> Control:
        """The device's control for ``name``, under its old or its new (5.16) name."""
        new = canonical(name)
        aliases = [name, new, *(old for old, renamed in RENAMED.items() if renamed == new)]
        for alias in aliases:
            if alias in self.controls:
                return self.controls[alias]
        raise DeviceError(f"camera {self.device}: no control {name!r}; it has "
                          f"{', '.join(sorted(self.controls)) or 'none'}")

    def get(self, name: str) -> int:
        control = self.resolve(name)
        buf = bytearray(CONTROL.pack(control.id, 0))
        try:
            self._ioctl(self.fd, VIDIOC_G_CTRL, buf)
        except OSError as exc:
            raise DeviceError(f"camera {self.device}: reading {control.name}: {exc}") from None
        return CONTROL.unpack(buf)[1]

    def set(self, name: str, value: int) -> None:
        control = self.resolve(name)
        if control.flags & FLAG_READ_ONLY:
            raise DeviceError(f"camera {self.device}: control {control.name} is read-only")
        if not control.minimum <= value <= control.maximum:
            raise DeviceError(f"camera {self.device}: {control.name} = {value} is outside "
                              f"[{control.minimum}, {control.maximum}]")
        try:
            self._ioctl(self.fd, VIDIOC_S_CTRL, bytearray(CONTROL.pack(control.id, int(value))))
        except OSError as exc:
            raise DeviceError(f"camera {self.device}: setting {control.name} = {value}: "
                              f"{exc}") from None

    def apply(self, wanted: dict[str, int], auto_off: bool) -> dict[str, int]:
        """Turn the automatics off (those the device has), then set ``wanted`` in the
        order given, and read every one back. Returns the device's names and values;
        ``DeviceError`` names every control that did not take."""
        plan: dict[str, int] = {}
        if auto_off:
            for name, off in AUTO_OFF.items():
                try:
                    plan[self.resolve(name).name] = off
                except DeviceError:
                    continue  # the camera has no such automatic
        for name, value in wanted.items():
            plan[self.resolve(name).name] = int(value)
        for name, value in plan.items():
            self.set(name, value)
        got = {name: self.get(name) for name in plan}
        failed = [f"{n} {plan[n]} (read back {got[n]})" for n in plan if got[n] != plan[n]]
        if failed:
            raise DeviceError(f"camera {self.device}: controls did not take: "
                              + "; ".join(failed))
        return got
